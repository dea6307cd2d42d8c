"""One ping from echoes to labelled landmarks: the steps the nodes and ``sonar-ring process`` share.

* :func:`localise_ping` -- every echo row to a landmark hypothesis per enabled
  model (plane, corner, edge; on a triad one model-free landmark from phase
  bearing and TOF range), with covariance;
* :func:`classify_ping` -- the evidence of the layout picks one hypothesis per
  echo: Barshan & Kuc's amplitude rules where two transmitters fire, geometric
  consistency over overlapping groups on a single-emitter ring; without
  evidence the echo stays UNKNOWN and is placed with the corner model
  (Browne s7).  A triad's ping has none (one emitter, receivers within 15 mm):
  its landmarks are always UNKNOWN, and the map classifies what motion decides.

Both return :class:`~sonar_ring.landmarks.Landmarks` in the sensor frame; the
``echo`` field ties a landmark to its echo row, so the two steps can run in
different processes.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, fields, replace

import numpy as np

from sonar_ring import amplitude_rules, confidence, doa, localise, ring_consistency, solvers, uncertainty
from sonar_ring.compiled import kernel
from sonar_ring.echoes import EchoArrays
from sonar_ring.geometry import Layout
from sonar_ring.landmarks import CORNER, EDGE, PLANE, UNKNOWN, Landmarks, make_landmarks

MODEL_CLASS = {"plane": PLANE, "corner": CORNER, "edge": EDGE}
"""Class code of the landmark each localisation model produces."""

ROBOT_SIGMA_SPEED = 1.2
"""Speed-of-sound uncertainty a robot's nodes assume, m/s: the air's temperature known to about 2 K (the
localiser's ``sigma_speed`` default)."""


@dataclass(frozen=True)
class Settings:
    """What the localiser node does to a ping, localisation and labelling; its parameters map onto it.

    Attributes
    ----------
    models : tuple of str
        Localisation models to run, a subset of ``plane``, ``corner``, ``edge``.
    vertical_correction : bool
        Replace each path by its exact horizontal part ``sqrt(d^2 - dz^2)``.
    sigma_tof : float
        Time-of-flight noise, s (covariances, consistency test).
    sigma_speed : float
        Speed-of-sound uncertainty, m/s.
    sigma_amplitude : float
        Amplitude noise relative to A_max (Barshan & Kuc rules).
    consistency_z : float
        Significance of the geometric-consistency test, standard deviations.
    triad_eps : float
        Kreczmer's eq 6 tolerance for the (n1, n2) search; 0 derives it from
        the layout with his robustness procedure (:func:`triad_eps_for`).
    triad_max_angle : float
        Largest azimuth a triad accepts, rad.
    """

    models: tuple[str, ...] = ("plane", "corner", "edge")
    vertical_correction: bool = True
    sigma_tof: float = 1e-6
    sigma_speed: float = 0.0
    sigma_amplitude: float = 0.02
    consistency_z: float = ring_consistency.CONSISTENCY_Z
    triad_eps: float = 0.0
    triad_max_angle: float = np.radians(50.0)

    def __post_init__(self):
        unknown = set(self.models) - set(MODEL_CLASS)
        if unknown or not self.models or len(set(self.models)) != len(self.models):
            raise ValueError(f"models must be a non-empty subset of {sorted(MODEL_CLASS)}, each once, "
                             f"got {list(self.models)}")


def localise_ping(layout: Layout, echoes: EchoArrays, settings: Settings = Settings()) -> Landmarks:
    """Landmark hypotheses for every echo row and enabled model, sensor frame.

    Pairs (ring, Barshan & Kuc) give one hypothesis per model and row, with
    ``landmark_class`` the model's class; triads give one UNKNOWN landmark per
    row (bearing from phase, range from TOF, :func:`sonar_ring.doa.triad_landmark`).
    Invalid hypotheses are kept with ``valid`` False and their reason code, so
    the caller can count them.
    """
    if layout.kind == "triad":
        return _localise_triads(layout, echoes, settings)
    uncertainty.check_path_noise(settings.sigma_tof, echoes.speed_of_sound, settings.sigma_speed, "localise_ping")
    count = echoes.n_echoes
    if echoes.group.shape != (count,) or echoes.transmitter.shape != (count,) or echoes.tof.shape != (count, 2):
        raise ValueError(f"localise_ping: need one group, one transmitter and two TOFs per echo row: group "
                         f"{echoes.group.shape}, transmitter {echoes.transmitter.shape}, tof {echoes.tof.shape}")
    models, model_class = _model_codes(tuple(settings.models))
    # The types the kernel is compiled for (astype copies): a message's uint16 groups and uint8 transmitters
    # become int64, and TOFs C-contiguous float64 whatever order or flags the caller's array has.
    *fields, first_order, covariance_paths = solvers.localise_ping_rows(
        layout.transmitters, layout.receivers, layout.groups, echoes.transmitter.astype(np.int64),
        echoes.group.astype(np.int64), echoes.tof.astype(float, order="C"), float(echoes.speed_of_sound),
        settings.vertical_correction, float(settings.sigma_tof), float(settings.sigma_speed), models, model_class)
    hypotheses = Landmarks(*fields)
    if first_order.size:
        # Near the border of the solvable region (|d2 - d1| close to the baseline) a sigma point can
        # fall outside it while the estimate is valid: first-order covariance there.
        group_receivers = layout.group_receivers()
        for index in np.unique(first_order // count):
            entries = first_order[first_order // count == index]
            rows = entries - index * count
            receivers = group_receivers[echoes.group[rows], :, :2]
            estimate = localise.PointEstimate(hypotheses.position[entries], np.ones(rows.size, dtype=bool),
                                              hypotheses.reason[entries], settings.models[index])
            hypotheses.covariance[entries] = uncertainty.position_covariance(
                estimate, layout.transmitters[echoes.transmitter[rows], :2], receivers[:, 0], receivers[:, 1],
                covariance_paths[rows])
    return hypotheses


@functools.lru_cache(maxsize=8)
def _model_codes(models: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The solver index (:data:`sonar_ring.solvers.SOLVERS`) and landmark class of each model, shapes (M,).

    Cached for every ping: not to be written to.
    """
    return (np.array([solvers.SOLVERS.index(model) for model in models], dtype=np.int64),
            np.array([MODEL_CLASS[model] for model in models], dtype=np.uint8))


@functools.lru_cache(maxsize=32)
def triad_eps_for(b1: float, b2: float, max_angle: float, wavelength: float, speed_of_sound: float) -> float:
    """Kreczmer's eq 6 tolerance for a triad: the eps of :func:`sonar_ring.doa.robustness`.

    Cached: the procedure steps the timing error over every azimuth it accepts, too slow
    for every ping, and its arguments change only with the layout (the speed of
    sound is rounded to 1 m/s by the caller).
    """
    return doa.robustness(b1, b2, max_angle, wavelength, speed_of_sound).eps


def _localise_triads(layout: Layout, echoes: EchoArrays, settings: Settings) -> Landmarks:
    # An empty ping decoded from a message carries no phase-delay columns at all: it has no landmarks.
    if echoes.n_echoes and echoes.phase_delay.shape[1] != 2:
        raise ValueError("triad echoes need two phase delays per row")
    speed = float(round(echoes.speed_of_sound))
    wavelength = layout.wavelength(speed)
    parts = []
    for group in np.unique(echoes.group):
        rows = np.flatnonzero(echoes.group == group)
        members = layout.groups[group]
        emitter = layout.transmitters[layout.group_transmitters[group, 0]]
        receivers = layout.receivers[members, :2]
        baselines = np.linalg.norm(np.diff(receivers, axis=0), axis=1)
        eps = settings.triad_eps or triad_eps_for(float(baselines[0]), float(baselines[1]),
                                                  settings.triad_max_angle, wavelength, speed)
        result = doa.triad_landmark(
            receivers, emitter[:2], echoes.tof[rows], echoes.phase_delay[rows, 0],
            echoes.phase_delay[rows, 1], wavelength, echoes.speed_of_sound, eps,
            settings.triad_max_angle, delay_std=doa.delay_std(settings.sigma_tof, 0.0), tof_std=settings.sigma_tof,
            height_offset=float(emitter[2] - layout.receivers[members[0], 2]),
            speed_of_sound_std=settings.sigma_speed)
        parts.append(make_landmarks(UNKNOWN, np.nan_to_num(result.position),
                                    covariance=np.nan_to_num(result.covariance, nan=0.0), group=group, echo=rows,
                                    valid=result.valid, reason=result.reason))
    return Landmarks.concatenate(parts)


def classify_ping(layout: Layout, echoes: EchoArrays, hypotheses: Landmarks,
                  settings: Settings = Settings(), ping=None, fits=None) -> Landmarks:
    """One labelled landmark per echo row that has a valid hypothesis.

    The class comes from the evidence the layout gives: amplitude rules for
    groups with two transmitters (both rows of an echo, matched by arrival order),
    geometric consistency for single-emitter groups; evidence joins rows of one
    ping only (``ping``, shape (N,) int, when several pings are stacked; default
    all rows one ping).  The position is the
    hypothesis of the decided class, or the corner model's (Browne s7) while
    the class is UNKNOWN or its model is not enabled; the confidence is the
    deciding test's.  ``fits``: on a ring, :func:`ring_fits` of the same rows, if
    the caller has it (computed here otherwise).
    """
    ping = np.zeros(echoes.n_echoes, dtype=np.int64) if ping is None else np.asarray(ping, dtype=np.int64)
    decided, confidence = _evidence(layout, echoes, settings, ping, fits)
    # Copies (astype) in the types load_kernels compiled, whatever arrays the caller's hypotheses hold:
    # Landmarks' uint32 echo rows become int64, a read-only or strided array (another type to numba) a new one.
    pick, label, decided_confidence, edge_row = _picks(hypotheses.landmark_class.astype(np.uint8),
                                                       hypotheses.echo.astype(np.int64), hypotheses.valid.astype(bool),
                                                       decided, confidence)
    picked = hypotheses.select(pick)  # new arrays: the covariance may be added to in place
    _add_edge_discrepancy(picked.covariance, picked.position, hypotheses.position.astype(float, order="C"), edge_row)
    return picked.with_class(label, decided_confidence)


def ring_fits(layout: Layout, echoes: EchoArrays, settings: Settings = Settings(), ping=None):
    """The ring's consistency test of a ping with its fits' covariances (:func:`sonar_ring.ring_consistency`).

    What :func:`classify_ping` decides by and :func:`joint_landmarks` places by; a
    caller that runs both computes it once and gives it to each.  ``ping`` as for
    :func:`classify_ping`.
    """
    speed = float(echoes.speed_of_sound)
    return ring_consistency.ring_consistency(layout, echoes.group, echoes.path_lengths(), speed * settings.sigma_tof,
                                             ping=ping, z=settings.consistency_z, covariances=True,
                                             relative_sigma_speed=settings.sigma_speed / speed)


def joint_landmarks(layout: Layout, echoes: EchoArrays, labelled: Landmarks, settings: Settings = Settings(),
                    ping=None, fits=None) -> Landmarks:
    """A ping's landmarks with every echo several pairs heard as one landmark: the fit over all their receivers.

    :func:`sonar_ring.ring_consistency.ring_consistency` joins each echo row with the
    overlapping groups' rows of the same echo and fits both models over all their
    receivers, at the joint Cramer-Rao bound (``bench/results/joint.md``).  Rows are taken
    by the number of rows joined to them, most first (ties: the first row); a row that
    joined two or more, whose rows no landmark taken before used and whose fit of its
    labelled class's model fits, becomes its echo's landmark at that fit -- an EDGE's edge
    fit, any other's virtual image ``T'`` at ``G = (T + T') / 2`` (an UNKNOWN one's
    covariance widened by ``g g^T``, ``g`` the gap to the edge fit, as :func:`classify_ping`
    widens a pair's) -- and the rows it joined are left out: their paths are in its fit.
    Every other row keeps its labelled landmark, the pair's closed form.  So no row's paths
    go into two landmarks, and the landmarks stay independent sightings.  Other layouts
    than a ring: ``labelled`` as it is.

    Parameters
    ----------
    layout : Layout
    echoes : EchoArrays
        The screened ping (N rows), as :func:`classify_ping` took it.
    labelled : Landmarks
        :func:`classify_ping`'s landmarks of ``echoes`` (L), sensor frame.
    settings : Settings
        TOF and speed-of-sound noise and the test's significance, as for :func:`classify_ping`.
    ping : array_like of int, shape (N,), optional
        Ping of each row when several are stacked (rows join only within a ping).
    fits : ConsistencyResult, optional
        :func:`ring_fits` of the same rows, if the caller has it (computed here otherwise).

    Returns
    -------
    Landmarks
        At most L landmarks, sensor frame, ``echo`` each one's row.
    """
    if layout.kind != "ring" or not len(labelled):
        return labelled
    row = labelled.echo.astype(np.int64)
    if row.min() < 0 or row.max() >= echoes.n_echoes:
        raise ValueError(f"joint_landmarks: the landmarks name echo rows {row.min()}-{row.max()}, the ping has "
                         f"{echoes.n_echoes}")
    result = fits if fits is not None else ring_fits(layout, echoes, settings, ping)
    is_edge = labelled.landmark_class == EDGE
    transmitter = layout.plan.transmitters[echoes.group[row].astype(np.int64), 0]
    position = np.where(is_edge[:, None], result.edge_position[row], 0.5 * (transmitter + result.virtual_image[row]))
    covariance = np.where(is_edge[:, None, None], result.edge_covariance[row], 0.25 * result.image_covariance[row])
    fitting = np.zeros(echoes.n_echoes, dtype=bool)
    fitting[row] = np.all(np.isfinite(covariance), axis=(1, 2)) & np.all(np.isfinite(position), axis=1)
    joint, used = _joint_rows(result.joined, fitting)
    chosen = joint[row]
    kept = np.flatnonzero(chosen | ~used[row])
    undecided = chosen & (labelled.landmark_class == UNKNOWN)
    gap = np.where(np.isfinite(result.edge_position[row]), result.edge_position[row] - position, 0.0)
    covariance[undecided] += gap[undecided, :, None] * gap[undecided, None, :]
    out = labelled.select(kept)  # new arrays
    out.position[chosen[kept]] = position[kept[chosen[kept]]]
    out.covariance[chosen[kept]] = covariance[kept[chosen[kept]]]
    return out


@kernel
def _joint_rows(joined, fitting):
    """Which echo rows become joint landmarks, and which rows' paths those took, for :func:`joint_landmarks`.

    ``joined`` (N, J): each row's own row and the rows its fits joined, -1 padded;
    ``fitting`` (N,): the row's fit of its landmark's model fits.  Rows by the number they
    joined, most first (a stable order: ties by row); a row that joined two or more,
    fits, and whose rows no joint landmark took yet becomes one and takes them.  Returns
    ``joint`` and ``used``, (N,) bool each.
    """
    count = joined.shape[0]
    size = np.zeros(count, dtype=np.int64)
    for n in range(count):
        for j in range(joined.shape[1]):
            if joined[n, j] >= 0:
                size[n] += 1
    joint = np.zeros(count, dtype=np.bool_)
    used = np.zeros(count, dtype=np.bool_)
    for n in np.argsort(-size, kind="mergesort"):
        if size[n] < 2 or not fitting[n]:
            continue
        free = True
        for j in range(joined.shape[1]):
            if joined[n, j] >= 0 and used[joined[n, j]]:
                free = False
        if not free:
            continue
        joint[n] = True
        for j in range(joined.shape[1]):
            if joined[n, j] >= 0:
                used[joined[n, j]] = True
    return joint, used


def load_kernels() -> None:
    """Load the compiled parts of :func:`classify_ping` and :func:`joint_landmarks` now instead of at the first ping.

    :meth:`sonar_ring.ping_stage.PingStage.load_kernels` calls it (the localiser node and the
    workers of ``sonar-ring process``, at start), with
    :func:`sonar_ring.ring_consistency.load_kernels` on a ring.
    """
    _picks(np.zeros(1, dtype=np.uint8), np.zeros(1, dtype=np.int64), np.ones(1, dtype=bool),
           np.zeros(1, dtype=np.uint8), np.zeros(1))
    _add_edge_discrepancy(np.zeros((1, 2, 2)), np.zeros((1, 2)), np.zeros((1, 2)), np.zeros(1, dtype=np.int64))
    _joint_rows(np.zeros((1, 2), dtype=np.int64), np.zeros(1, dtype=bool))
    confidence.load_kernels()


@kernel
def _picks(landmark_class, echo, valid, decided, confidence):
    """Which hypothesis labels each echo row, for :func:`classify_ping`.

    Hypotheses: ``landmark_class``, ``echo`` (their echo rows) and ``valid``
    (H,); per echo row: the evidence's ``decided`` class and ``confidence`` (N,).
    Hypotheses of an unknown class or of an echo row outside ``[0, N)`` are
    ignored.  An echo takes the hypothesis of its decided class when that one is valid,
    else the corner model's, else the UNKNOWN one (a triad's), else none.
    Returns, per labelled echo in row order: the hypothesis row (L,), its class
    (the decided one, or UNKNOWN) and confidence (L,), and the row of its valid
    edge hypothesis where the class is not decided, else -1 (L,).
    """
    count = decided.size
    index = np.full((4, count), -1, dtype=np.int64)  # by class code: UNKNOWN, PLANE, CORNER, EDGE
    for row in range(landmark_class.size):
        if landmark_class[row] <= EDGE and 0 <= echo[row] < count:  # no other hypothesis names an echo
            index[landmark_class[row], echo[row]] = row
    pick = np.empty(count, dtype=np.int64)
    label = np.empty(count, dtype=np.uint8)
    label_confidence = np.empty(count)
    edge_row = np.empty(count, dtype=np.int64)
    kept = 0
    for n in range(count):
        chosen = index[decided[n], n] if decided[n] != UNKNOWN else -1
        if chosen >= 0 and valid[chosen]:
            label[kept], label_confidence[kept], edge_row[kept] = decided[n], confidence[n], -1
        else:
            chosen = index[CORNER, n]
            if not (chosen >= 0 and valid[chosen]):
                chosen = index[UNKNOWN, n]
            if not (chosen >= 0 and valid[chosen]):
                continue
            edge = index[EDGE, n]
            label[kept], label_confidence[kept] = UNKNOWN, 0.0
            edge_row[kept] = edge if edge >= 0 and valid[edge] else -1
        pick[kept] = chosen
        kept += 1
    return pick[:kept], label[:kept], label_confidence[:kept], edge_row[:kept]


@kernel
def _add_edge_discrepancy(covariance, position, hypothesis_position, edge_row):
    """Add the edge model's discrepancy to the covariance of each undecided echo, in place.

    An undecided echo may be an edge placed with the corner model (Browne s7): its
    covariance (L, 2, 2) m^2, at ``position`` (L, 2) m, gets ``g g^T`` with ``g`` the
    gap to its valid edge hypothesis (row ``edge_row`` (L,) of ``hypothesis_position``
    (H, 2) m; -1: none), so it stays consistent either way.
    """
    for n in range(edge_row.size):
        if edge_row[n] < 0:
            continue
        gap_x = hypothesis_position[edge_row[n], 0] - position[n, 0]
        gap_y = hypothesis_position[edge_row[n], 1] - position[n, 1]
        covariance[n, 0, 0] += gap_x * gap_x
        covariance[n, 0, 1] += gap_x * gap_y
        covariance[n, 1, 0] += gap_y * gap_x
        covariance[n, 1, 1] += gap_y * gap_y


def _evidence(layout: Layout, echoes: EchoArrays, settings: Settings, ping: np.ndarray, fits):
    """Class decision and confidence per echo row, shapes (N,); ``ping`` (N,) keeps pings apart."""
    if echoes.n_echoes and layout.kind == "ring":
        result = fits if fits is not None else ring_consistency.ring_consistency(
            layout, echoes.group, echoes.path_lengths(), echoes.speed_of_sound * settings.sigma_tof, ping=ping,
            z=settings.consistency_z)
        return result.cls, np.where(result.cls == EDGE, result.confidence, 0.0)
    decided = np.full(echoes.n_echoes, UNKNOWN, dtype=np.uint8)
    confidence = np.zeros(echoes.n_echoes)
    if echoes.n_echoes and layout.group_transmitters.shape[1] == 2 and echoes.amplitude.shape[1] == 2:
        first, second = _matched_rows(layout, echoes, ping)
        # [[A_aa', A_ab'], [A_ba', A_bb']]: rows by transmitter, columns by receiver.
        amplitudes = np.stack([echoes.amplitude[first], echoes.amplitude[second]], axis=1)
        result = amplitude_rules.classify_amplitudes(amplitudes, settings.sigma_amplitude)
        for rows in (first, second):
            decided[rows] = result.cls
            confidence[rows] = result.confidence
    return decided, confidence


def _matched_rows(layout: Layout, echoes: EchoArrays, ping: np.ndarray):
    """Rows of the same echo after each of a group's two transmitters fired, by arrival order, within a ping."""
    firsts, seconds = [], []
    slot = ping * layout.n_groups + echoes.group
    for key in np.unique(slot):
        group = key % layout.n_groups
        a, b = layout.group_transmitters[group]
        rows_a = np.flatnonzero((slot == key) & (echoes.transmitter == a))
        rows_b = np.flatnonzero((slot == key) & (echoes.transmitter == b))
        count = min(len(rows_a), len(rows_b))
        firsts.append(rows_a[:count])
        seconds.append(rows_b[:count])
    return np.concatenate(firsts).astype(np.int64), np.concatenate(seconds).astype(np.int64)


def label_and_publish(layout: Layout, echoes: EchoArrays, settings: Settings = Settings(), ping=None
                      ) -> tuple[Landmarks, Landmarks, Landmarks]:
    """:func:`localise_ping`, :func:`classify_ping` and :func:`joint_landmarks` of a ping, the ring's fits once.

    The hypotheses (valid and not), the labelled landmarks and those to publish;
    ``ping`` as for :func:`classify_ping` (stacked pings, :func:`label_pings`).
    """
    hypotheses = localise_ping(layout, echoes, settings)
    fits = ring_fits(layout, echoes, settings, ping) if layout.kind == "ring" else None
    labelled = classify_ping(layout, echoes, hypotheses, settings, ping=ping, fits=fits)
    return hypotheses, labelled, joint_landmarks(layout, echoes, labelled, settings, ping=ping, fits=fits)


def label_pings(layout: Layout, pings: list[EchoArrays], settings: Settings = Settings()
                ) -> list[tuple[Landmarks, Landmarks, Landmarks]]:
    """:func:`localise_ping`, :func:`classify_ping` and :func:`joint_landmarks` for many pings at once.

    For each ping of ``pings`` (screened echoes of ``layout``): its valid
    hypotheses, its labelled landmarks and the landmarks to publish, ``echo``
    counting the ping's own rows -- exactly what :func:`label_and_publish` gives
    that ping alone, since a row's results depend only on its own ping.
    Consecutive pings with the same speed of sound (and the same amplitude and
    phase-delay columns) are stacked and go through each step in one call, so
    numpy's cost per call is paid once per batch instead of once per ping, and
    a ring's consistency test (:func:`ring_fits`) runs once for both the labels
    and the joint landmarks (``sonar-ring process``).
    """
    results = []
    start = 0
    while start < len(pings):
        stop = start + 1
        while stop < len(pings) and _stackable(pings[start], pings[stop]):
            stop += 1
        batch = pings[start:stop]
        sizes = np.array([p.n_echoes for p in batch])
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        stacked = EchoArrays(batch[0].layout, batch[0].speed_of_sound,
                             *(np.concatenate([getattr(p, name) for p in batch])
                               for name in ("group", "transmitter", "tof", "amplitude", "phase_delay")))
        hypotheses, labelled, published = label_and_publish(layout, stacked, settings,
                                                            ping=np.repeat(np.arange(len(batch)), sizes))
        results += zip(_split(hypotheses.select(hypotheses.valid), offsets), _split(labelled, offsets),
                       _split(published, offsets), strict=True)
        start = stop
    return results


def _stackable(first: EchoArrays, other: EchoArrays) -> bool:
    """Whether ``other`` stacks with ``first``: one speed of sound, the same amplitude and phase-delay columns.

    An empty ping decoded from a message has no columns at all.
    """
    return (other.speed_of_sound == first.speed_of_sound and other.amplitude.shape[1] == first.amplitude.shape[1]
            and other.phase_delay.shape[1] == first.phase_delay.shape[1])


def _split(landmarks: Landmarks, offsets: np.ndarray) -> list[Landmarks]:
    """Landmarks of stacked pings back per ping (rows ``offsets[i]:offsets[i + 1]``), ``echo`` per ping, in order.

    One gather puts the rows in ping order; each ping's landmarks are then slices
    of it (views of the batch's arrays).
    """
    ping = np.searchsorted(offsets, landmarks.echo, side="right") - 1
    order = np.argsort(ping, kind="stable")
    ordered = landmarks.select(order)
    ordered = replace(ordered, echo=(ordered.echo - offsets[ping[order]]).astype(ordered.echo.dtype))
    bounds = np.searchsorted(ping[order], np.arange(len(offsets)))
    columns = [getattr(ordered, field.name) for field in fields(Landmarks)]
    return [Landmarks(*(column[bounds[index]:bounds[index + 1]] for column in columns))
            for index in range(len(offsets) - 1)]
