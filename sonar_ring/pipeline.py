"""One ping from echoes to labelled landmarks: the steps the nodes and ``sonar-ring process`` share.

* :func:`localise_ping` -- every echo row to a landmark hypothesis per enabled
  model (plane, corner, edge; on a triad one model-free landmark from phase
  bearing and TOF range), with covariance;
* :func:`classify_ping` -- the evidence of the layout picks one hypothesis per
  echo: Barshan & Kuc's amplitude rules where two transmitters fire, geometric
  consistency over overlapping groups on a single-emitter ring; without
  evidence the echo stays UNKNOWN and is placed with the corner model
  (Browne s7).

Both return :class:`~sonar_ring.landmarks.Landmarks` in the sensor frame; the
``echo`` field ties a landmark to its echo row, so the two steps can run in
different processes.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, fields, replace

import numpy as np

from sonar_ring import classify, doa, localise
from sonar_ring.echoes import EchoArrays
from sonar_ring.geometry import Layout
from sonar_ring.landmarks import CORNER, EDGE, PLANE, UNKNOWN, Landmarks, make_landmarks

ARC_MSE = 30.0
"""Mean-squared error along an estimate's arc bias, in squared biases (see :func:`unscented_covariance`)."""

MODEL_CLASS = {"plane": PLANE, "corner": CORNER, "edge": EDGE}
"""Class code of the landmark each localisation model produces."""


@dataclass(frozen=True)
class Settings:
    """What the localiser and classifier do; the nodes' parameters map onto it.

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
    consistency_z: float = classify.CONSISTENCY_Z
    triad_eps: float = 0.0
    triad_max_angle: float = np.radians(50.0)

    def __post_init__(self):
        unknown = set(self.models) - set(MODEL_CLASS)
        if unknown or not self.models:
            raise ValueError(f"models must be a non-empty subset of {sorted(MODEL_CLASS)}, got {self.models}")


def _row_geometry(layout: Layout, echoes: EchoArrays):
    """Transmitter and receivers of every echo row, horizontal, and their height differences.

    Returns ``tx`` (N, 2), ``receivers`` (N, K, 2) in m, and ``dz`` (N, K), the
    transmitter minus each receiver's height, m.
    """
    tx = layout.transmitters[echoes.transmitter.astype(np.int64)]
    receivers = layout.receivers[layout.groups[echoes.group.astype(np.int64)]]
    return tx[:, :2], receivers[..., :2], tx[:, None, 2] - receivers[..., 2]


def horizontal_paths(echoes: EchoArrays, dz: np.ndarray, settings: Settings):
    """Path lengths of every row and receiver, shape (N, K), m, and their scale d/h.

    With ``settings.vertical_correction`` the exact horizontal part
    ``sqrt(d^2 - dz^2)`` (``dz`` (N, K), m); NaN where a receiver missed the
    echo or ``d < |dz|``.  The scale ``d / h`` turns a path's standard deviation
    into the horizontal one.
    """
    paths = echoes.path_lengths()
    if not settings.vertical_correction:
        return paths, np.ones_like(paths)
    horizontal = localise.horizontal_path(paths, dz).value
    with np.errstate(invalid="ignore", divide="ignore"):
        return horizontal, paths / horizontal


def sigma_point_paths(d1, d2, paths_covariance):
    """Path lengths at the five sigma points of the unscented transform (``n + kappa = 3``).

    Returns two arrays of shape (5, N): point 0 is the measurement itself, so
    one batched model call gives the estimate and its spread together.
    """
    scale = np.linalg.cholesky(3.0 * np.nan_to_num(paths_covariance) + 1e-30 * np.eye(2))  # (N, 2, 2)
    offsets = np.stack([np.zeros((len(d1), 2))]
                       + [sign * scale[:, :, column] for column in range(2) for sign in (1.0, -1.0)])
    return d1[None, :] + offsets[:, :, 0], d2[None, :] + offsets[:, :, 1]


def unscented_covariance(points) -> np.ndarray:
    """Covariance of an estimate that stays consistent where its error bends along an arc.

    A pair measures range far better than bearing, so the error region is a thin
    arc (a banana): a tangential error ``t`` moves the estimate inwards by about
    ``t^2 / (2 rho)``, which at a few metres exceeds the first-order radial
    standard deviation.  A first-order (Jacobian) covariance then covers only
    ~85 % of errors at 3 sigma, which breaks the mapper's Mahalanobis gating.

    The five sigma points (:func:`sigma_point_paths`) give the covariance
    including the arc's second-order spread, and the bias ``b`` of their mean
    (``|b| = m = sigma_t^2 / (2 rho)``, pointing inwards).  Along ``b`` the
    total mean-squared error is set to :data:`ARC_MSE` ``m^2``: the arc at
    ``t = 3 sigma_t`` lies ``9 m`` inwards, and ``(9 m)^2 / (30 m^2) = 2.7``
    keeps it inside the 3-sigma ellipse (Mahalanobis ``9 + 2.7 < 11.83``).
    Across the arc nothing changes.

    Parameters
    ----------
    points : ndarray, shape (5, N, 2)
        The estimator evaluated at the five sigma points, point 0 the estimate, m.

    Returns
    -------
    ndarray, shape (N, 2, 2)
        m^2; NaN where a sigma point has no solution (the estimate's own
        validity still decides whether it is used).
    """
    weights = np.array([1 / 3] + [1 / 6] * 4)
    mean = np.einsum("s,sni->ni", weights, points)
    deviation = points - mean
    covariance = np.einsum("s,sni,snj->nij", weights, deviation, deviation)
    bias = mean - points[0]
    # The transform already holds 2 m^2 of arc spread along the bias; add the rest of ARC_MSE.
    return covariance + (ARC_MSE - 2.0) * bias[:, :, None] * bias[:, None, :]


def _covariance(batch, estimate, tx, rx1, rx2, paths_covariance) -> np.ndarray:
    """Unscented covariance (N, 2, 2) of a model's estimates, first order where a sigma point has no solution.

    Near the border of the solvable region (``|d2 - d1|`` close to the baseline)
    one sigma point can fall outside it while the estimate itself is valid.
    """
    covariance = unscented_covariance(batch.position)
    lost = estimate.valid & ~np.isfinite(covariance).all(axis=(1, 2))
    if lost.any():
        first_order = localise.position_covariance(estimate, tx, rx1, rx2, paths_covariance)
        covariance[lost] = first_order[lost]
    return covariance


def _first(batch):
    """The estimate at sigma point 0 (the measurement) of a batched model call."""
    return replace(batch, **{f.name: getattr(batch, f.name)[0] for f in fields(batch)
                             if isinstance(getattr(batch, f.name), np.ndarray)})


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
    tx, receivers, dz = _row_geometry(layout, echoes)
    paths, scale = horizontal_paths(echoes, dz, settings)
    rx1, rx2 = receivers[:, 0], receivers[:, 1]
    d1, d2 = paths[:, 0], paths[:, 1]
    # Rows with absurd paths overflow here; localise flags them NOT_FINITE, so the warnings are noise.
    with np.errstate(over="ignore", invalid="ignore"):
        covariance_paths = localise.path_covariance(d1, d2, settings.sigma_tof, echoes.speed_of_sound,
                                                    settings.sigma_speed)
        covariance_paths = covariance_paths * scale[:, :, None] * scale[:, None, :]
        sigma_d1, sigma_d2 = sigma_point_paths(d1, d2, covariance_paths)
    rows = np.arange(echoes.n_echoes)
    batches = localise.hypotheses(tx, rx1, rx2, sigma_d1, sigma_d2, settings.models)
    estimates = {model: _first(batch) for model, batch in batches.items()}
    covariances = [_covariance(batches[model], estimates[model], tx, rx1, rx2, covariance_paths)
                   for model in estimates]
    valid = np.concatenate([estimate.valid for estimate in estimates.values()])
    position = np.concatenate([estimate.position for estimate in estimates.values()])
    normal = np.zeros_like(position)
    segment = np.repeat(position[:, None, :], 2, axis=1)
    if "plane" in estimates:
        start = list(estimates).index("plane") * echoes.n_echoes
        block = slice(start, start + echoes.n_echoes)
        normal[block] = -estimates["plane"].normal
        segment[block] = estimates["plane"].reflection_points
    keep = valid[:, None]
    covariance = np.concatenate(covariances)
    return make_landmarks(
        np.repeat([MODEL_CLASS[model] for model in estimates], echoes.n_echoes),
        np.where(keep, position, 0.0), normal=np.where(keep, normal, 0.0),
        covariance=np.where(keep[:, :, None], covariance, 0.0),
        segment=np.where(keep[:, :, None], segment, 0.0), group=np.tile(echoes.group, len(estimates)),
        echo=np.tile(rows, len(estimates)), valid=valid,
        reason=np.concatenate([estimate.reason for estimate in estimates.values()]))


@functools.lru_cache(maxsize=32)
def triad_eps_for(b1: float, b2: float, max_angle: float, wavelength: float, speed_of_sound: float) -> float:
    """Kreczmer's eq 6 tolerance for a triad: the eps of :func:`sonar_ring.doa.robustness`.

    Cached: the procedure takes about 0.1 s and the arguments change only with
    the layout (the speed of sound is rounded to 1 m/s by the caller).
    """
    return doa.robustness(b1, b2, max_angle, wavelength, speed_of_sound).eps


def _localise_triads(layout: Layout, echoes: EchoArrays, settings: Settings) -> Landmarks:
    if echoes.phase_delay.shape[1] != 2:
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
                  settings: Settings = Settings(), ping=None) -> Landmarks:
    """One labelled landmark per echo row that has a valid hypothesis.

    The class comes from the evidence the layout gives: amplitude rules for
    groups with two transmitters (both rows of an echo, matched by arrival order),
    geometric consistency for single-emitter groups; evidence joins rows of one
    ping only (``ping``, shape (N,) int, when several pings are stacked; default
    all rows one ping).  The position is the
    hypothesis of the decided class, or the corner model's (Browne s7) while
    the class is UNKNOWN or its model is not enabled; the confidence is the
    deciding test's.
    """
    ping = np.zeros(echoes.n_echoes, dtype=np.int64) if ping is None else np.asarray(ping, dtype=np.int64)
    decided, confidence = _evidence(layout, echoes, settings, ping)
    count = echoes.n_echoes
    index = {}
    for code in (UNKNOWN, PLANE, CORNER, EDGE):
        mine = hypotheses.landmark_class == code
        index[code] = np.full(count, -1, dtype=np.int64)
        index[code][hypotheses.echo[mine].astype(np.int64)] = np.flatnonzero(mine)

    def usable(picked):
        ok = picked >= 0
        ok[ok] = hypotheses.valid[picked[ok]]
        return ok

    of_decided = np.full(count, -1, dtype=np.int64)
    for code in (PLANE, CORNER, EDGE):
        of_decided[decided == code] = index[code][decided == code]
    use_decided = usable(of_decided)
    fallback = np.where(usable(index[CORNER]), index[CORNER], index[UNKNOWN])
    pick = np.where(use_decided, of_decided, fallback)
    keep = usable(pick)
    labelled = hypotheses.select(pick[keep]).with_class(np.where(use_decided, decided, UNKNOWN)[keep],
                                                        np.where(use_decided, confidence, 0.0)[keep])
    # An undecided echo may be an edge placed with the corner model (Browne s7): its
    # covariance carries that model discrepancy, so it stays consistent either way.
    undecided = np.flatnonzero(~use_decided[keep] & usable(index[EDGE])[keep])
    edge_rows = index[EDGE][keep][undecided]
    gap = hypotheses.position[edge_rows] - labelled.position[undecided]
    covariance = labelled.covariance.copy()
    covariance[undecided] += gap[:, :, None] * gap[:, None, :]
    return replace(labelled, covariance=covariance)


def _evidence(layout: Layout, echoes: EchoArrays, settings: Settings, ping: np.ndarray):
    """Class decision and confidence per echo row, shapes (N,); ``ping`` (N,) keeps pings apart."""
    decided = np.full(echoes.n_echoes, UNKNOWN, dtype=np.uint8)
    confidence = np.zeros(echoes.n_echoes)
    if echoes.n_echoes == 0:
        return decided, confidence
    if layout.group_transmitters.shape[1] == 2 and echoes.amplitude.shape[1] == 2:
        first, second = _matched_rows(layout, echoes, ping)
        # [[A_aa', A_ab'], [A_ba', A_bb']]: rows by transmitter, columns by receiver.
        amplitudes = np.stack([echoes.amplitude[first], echoes.amplitude[second]], axis=1)
        result = classify.classify_amplitudes(amplitudes, settings.sigma_amplitude)
        for rows in (first, second):
            decided[rows] = result.cls
            confidence[rows] = result.confidence
    elif layout.kind == "ring":
        result = classify.ring_consistency(layout, echoes.group, echoes.path_lengths(),
                                           echoes.speed_of_sound * settings.sigma_tof, ping=ping,
                                           z=settings.consistency_z)
        decided[:] = result.cls
        confidence[:] = np.where(result.cls == EDGE, result.confidence, 0.0)
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


def label_pings(layout: Layout, pings: list[EchoArrays], localiser: Settings = Settings(),
                classifier: Settings = Settings()) -> list[tuple[Landmarks, Landmarks]]:
    """:func:`localise_ping` then :func:`classify_ping` for many pings at once; per ping the same result.

    For each ping of ``pings`` (screened echoes of ``layout``): its valid
    hypotheses (with ``localiser`` settings) and its labelled landmarks (with
    ``classifier`` settings), ``echo`` counting the ping's own rows -- exactly
    what the two functions give for that ping alone, since a row's results
    depend only on its own ping.  Consecutive pings with the same speed of sound
    (and the same amplitude and phase-delay columns) are stacked and go through
    each step in one call, so numpy's cost per call
    is paid once per batch instead of once per ping (``sonar-ring process``).
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
        hypotheses = localise_ping(layout, stacked, localiser)
        hypotheses = hypotheses.select(hypotheses.valid)
        labelled = classify_ping(layout, stacked, hypotheses, classifier,
                                 ping=np.repeat(np.arange(len(batch)), sizes))
        results += zip(_split(hypotheses, offsets), _split(labelled, offsets), strict=True)
        start = stop
    return results


def _stackable(first: EchoArrays, other: EchoArrays) -> bool:
    """Whether ``other`` stacks with ``first``: one speed of sound, the same amplitude and phase-delay columns.

    An empty ping decoded from a message has no columns at all.
    """
    return (other.speed_of_sound == first.speed_of_sound and other.amplitude.shape[1] == first.amplitude.shape[1]
            and other.phase_delay.shape[1] == first.phase_delay.shape[1])


def _split(landmarks: Landmarks, offsets: np.ndarray) -> list[Landmarks]:
    """Landmarks of stacked pings back per ping (rows ``offsets[i]:offsets[i + 1]``), ``echo`` per ping, in order."""
    ping = np.searchsorted(offsets, landmarks.echo, side="right") - 1
    order = np.argsort(ping, kind="stable")
    bounds = np.searchsorted(ping[order], np.arange(len(offsets)))
    parts = []
    for index in range(len(offsets) - 1):
        part = landmarks.select(order[bounds[index]:bounds[index + 1]])
        parts.append(replace(part, echo=(part.echo - offsets[index]).astype(part.echo.dtype)))
    return parts
