"""Geometric consistency for a single emitter: an edge told from a plane or corner by the shape of its echo.

On Browne's ring (and Kreczmer's triad) one emitter fires for every group, so
amplitudes cannot separate the classes.  Planes and corners put one virtual
image of the emitter behind all receivers, an edge does not: when three or
more receivers hear one echo -- a group's own and those of the groups whose
fields of view overlap it -- the residuals of the two models are compared
with a chi-square test at the TOF noise level, and EDGE versus "specular"
(PLANE or CORNER) is decided only when the difference is significant, with a
margin and a confidence (:mod:`sonar_ring.confidence`).

Nothing here tells a plane from a corner on a single-emitter ring; that needs
motion (the mapper) or two transmitters (:mod:`sonar_ring.amplitude_rules`).
Without evidence a landmark stays UNKNOWN, and is localised with the corner
model (Browne section 7).

Frames and units (REP 103): metres, the sensor frame with x forward, y left.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from sonar_ring import solvers
from sonar_ring.checks import non_negative_number, positive_finite, positive_number
from sonar_ring.compiled import kernel
from sonar_ring.confidence import confidence_from_margin
from sonar_ring.landmarks import EDGE, UNKNOWN
from sonar_ring.localise import horizontal_path


@dataclass(frozen=True)
class ConsistencyResult:
    """Outcome of :func:`geometric_consistency` for a batch of echoes.

    Attributes
    ----------
    cls : ndarray of uint8, shape (N,)
        :data:`EDGE` where the edge model is significantly better, else :data:`UNKNOWN`
        (a significant specular echo is a PLANE or a CORNER, which one geometry
        alone cannot tell; see ``specular``).
    specular : ndarray of bool, shape (N,)
        True where the single-virtual-image model (plane or corner) is significantly better.
    margin : ndarray of float, shape (N,)
        ``(|D| - z^2) / (2 sqrt(|D|))`` with ``D = chi2_specular - chi2_edge`` where a
        decision was made, else 0: the excess of the statistic over its threshold in
        its linearised standard deviation ``2 sqrt(|D|)``.
    confidence : ndarray of float, shape (N,)
        ``2 Phi(margin) - 1``, in [0, 1]; 0 where nothing was decided.
    chi2_specular, chi2_edge : ndarray of float, shape (N,)
        Weighted residual sums of squares of the two fitted models (NaN where untested).
    dof : ndarray of int, shape (N,)
        Degrees of freedom of each fit, valid receivers minus 2 (< 1 means untested).
    virtual_image : ndarray of float, shape (N, 2)
        Fitted virtual image ``T'`` of the transmitter, m, sensor frame.
    edge_position : ndarray of float, shape (N, 2)
        Fitted edge position ``P``, m, sensor frame.
    image_covariance, edge_covariance : ndarray of float, shape (N, 2, 2)
        Covariance of ``virtual_image`` and of ``edge_position``, m^2 (:func:`_fit_covariance`, with the sag
        :func:`_result` adds): the joint estimate over every receiver that heard the echo; NaN where not asked
        for (``covariances``), untested, or where that model does not fit (its chi-square above the fit limit
        of :func:`geometric_consistency`).
    joined : ndarray of int, shape (N, J)
        The echo's own row, then the rows whose receivers its fits used with its own, -1 padded (one column
        outside a ring).  Rows whose fits share a row are estimates of one echo, not independent.
    """

    cls: np.ndarray
    specular: np.ndarray
    margin: np.ndarray
    confidence: np.ndarray
    chi2_specular: np.ndarray
    chi2_edge: np.ndarray
    dof: np.ndarray
    virtual_image: np.ndarray
    edge_position: np.ndarray
    image_covariance: np.ndarray
    edge_covariance: np.ndarray
    joined: np.ndarray


CONSISTENCY_Z = 3.5
"""Default significance of the consistency test, standard normal deviates.

Only about one ring echo in ten carries enough curvature to be decided, so the
per-test error bound ``P(N(0,1) > z)`` is multiplied by ~10 when counted per
decision: z = 3 (0.13 %) would allow ~1 % false decisions, z = 3.5 (0.023 %) ~0.2 %.
"""

_GAUSS_NEWTON_STEPS = 5
"""Most iterations of each fit.  The model that fits converges fast (exact echoes quadratically;
with noise each step is ~100x shorter than the last, so :data:`_CONVERGED` ends it after 2-3), the
one that does not only slowly, so its chi-square may stay above its minimum.  That only ever
favours the model that fits (whose chi-square is within about :data:`_CONVERGED` of its
minimum, either side): a false decision needs the wrong model's chi-square to be the smaller,
so the error bound of :func:`geometric_consistency` still holds.  (On 620 simulated room
pings, 5 and 8 steps gave identical decisions.)"""


CHI2_3_SIGMA = -2.0 * math.log(math.erfc(3.0 / math.sqrt(2.0)))
"""11.83: the 2-D chi-square's 99.73 % point (``1 - exp(-x / 2)`` equal to a Gaussian's 3-sigma share), the
normalised error a 2-D covariance's 3-sigma ellipse holds."""

SAG_BAND = 4.5 ** 2 / (CHI2_3_SIGMA - 9.0)
"""A joint fit's sag in :func:`sonar_ring.solvers.arc_spread`'s units (7.16): a band its 3-sigma ellipse holds.

An error ``a`` across the line of sight (variance ``s^2``) moves a point on an arc of radius ``r`` by
``a^2 / (2 r)`` along it, always the same way: a squared Gaussian, whose 99.73 % point is ``4.5 s^2 / r``, at
``a = 3 s``.  That error is 9 of the ellipse's :data:`CHI2_3_SIGMA` across the line of sight; variance
``4.5^2 / (CHI2_3_SIGMA - 9) s^4 / r^2`` along it puts its sag on the ellipse too.  (A band whose own 3 sigma
held the sag alone, ``(1.5 s^2 / r)^2``, left the across error out: the ellipse held 98.75-99.62 % of a
joint fit's errors in the standard scenes, the corners' the fewest; 99.59-99.81 % with this one.  A pair's
sightings carry the sag's variance and squared mean instead, :data:`sonar_ring.solvers.ARC_SPREAD`: their
along-sight error is the sag's, where a joint fit's is mostly the paths' noise with the sag's tail.)"""


MAX_ECHOES_PER_GROUP = 32
"""Echoes of one group in one ping beyond which :func:`ring_consistency` leaves that group out."""

_CONVERGED = 1e-6
"""A Gauss-Newton step predicted to lower the chi-square by at most this is an echo's last.

The chi-square decides, so the stop is set on it, not on the position: a fit converging
at rate r then ends about 1e-6 r^2 / (1 - r^2) above its minimum (r ~ 0.01 on the ring's
noisy echoes), against test thresholds of z^2 (z >= 1 by the parameters' range), and
its point within sqrt(1e-6 / lambda_min) of the minimum's (lambda_min the smallest
eigenvalue of J^T W J): nanometres to micrometres at sigma_path = 0.34 mm.  A stop on
the step's length (1e-13 m before) took every step on noisy echoes, where the fit
converges only linearly: twice the work for no change in any decision."""


def geometric_consistency(transmitter, receivers, paths, sigma_path, z=CONSISTENCY_Z,
                          facing=None, covariances=False, relative_sigma_speed=0.0) -> ConsistencyResult:
    """EDGE versus specular (PLANE/CORNER) from one echo seen by three or more receivers.

    Two models are fitted by weighted least squares (Gauss-Newton, per echo) to the
    horizontal path lengths ``d_n`` of every echo:

    * specular (plane or corner): one virtual image ``T'`` for all receivers,
      residuals ``|T' - R_n| - d_n``;
    * edge: one reflecting point ``P``, residuals ``|P - T| + |P - R_n| - d_n``.

    Both have two parameters, so with ``n`` receivers each chi-square has ``n - 2``
    degrees of freedom and their difference ``D = chi2_specular - chi2_edge`` is a
    log-likelihood ratio.  Linearised, when the specular model is true ``D`` is normal
    with mean ``-s^2`` and standard deviation ``2 s`` (``s`` = separation of the two
    models' predictions in noise units), so deciding EDGE only when ``D > z^2`` is
    wrong with probability at most ``P(N(0,1) > z)`` whatever ``s`` is (0.023 % for the
    default ``z = 3.5``), and symmetrically for a specular decision.  The chosen model must also
    fit: its chi-square must lie below the upper ``z`` quantile of chi-square with
    ``n - 2`` degrees of freedom (Wilson-Hilferty approximation), so echoes that fit
    neither model (wrong association, multipath) stay UNKNOWN.

    Parameters
    ----------
    transmitter : array_like, shape (2,) or (N, 2)
        Horizontal position of the emitter ``T``, m, sensor frame.
    receivers : array_like, shape (N, K, 2)
        Horizontal positions of the receivers that saw each echo, m, sensor frame.
    paths : array_like, shape (N, K)
        Horizontal path lengths ``T -> reflector -> R_n``, m, already corrected for
        the transmitter/receiver height difference (``sqrt(d^2 - dz^2)``); NaN where a
        receiver did not see the echo.
    sigma_path : array_like
        Standard deviation of each path length, m (``c * sigma_tof``, times
        ``d / sqrt(d^2 - dz^2)`` after the height correction), > 0; broadcastable to (N, K).
    z : float
        Significance of both tests in standard normal deviates, > 0.
    facing : array_like, shape (2,) or (N, 2), optional
        Direction the receivers face (echoes arrive from that side), sensor frame;
        default the direction from the transmitter to the receivers' centroid, right
        for a ring but not for an emitter beside its receivers (a triad).
    covariances : bool
        Also the fitted positions' covariances (else NaN): what an echo's joint estimate needs, not the test.
    relative_sigma_speed : float
        Relative standard deviation of the speed of sound, >= 0: a scale common to every path, which the
        covariances include.

    Returns
    -------
    ConsistencyResult
        Decisions, confidences, chi-squares and both fitted positions (with their
        covariances where asked for).  Echoes with fewer than three usable receivers are UNKNOWN with
        zero confidence.
    """
    z = positive_number("z", z)
    receivers = np.asarray(receivers, dtype=float)
    if receivers.ndim != 3 or receivers.shape[-1] != 2:
        raise ValueError(f"receivers must have shape (N, K, 2), got {receivers.shape}")
    n_echoes, n_receivers = receivers.shape[:2]
    paths = np.asarray(paths, dtype=float)
    if paths.shape != (n_echoes, n_receivers):
        raise ValueError(f"paths must have shape {(n_echoes, n_receivers)}, got {paths.shape}")
    transmitter = np.asarray(transmitter, dtype=float)
    if transmitter.shape not in ((2,), (n_echoes, 2)):
        raise ValueError(f"transmitter must have shape (2,) or {(n_echoes, 2)}, got {transmitter.shape}")
    transmitter = np.broadcast_to(transmitter, (n_echoes, 2))
    sigma = np.broadcast_to(positive_finite("sigma_path", sigma_path), (n_echoes, n_receivers))

    outward = np.zeros((n_echoes, 2)) if facing is None else np.broadcast_to(np.asarray(facing, dtype=float),
                                                                            (n_echoes, 2))
    relative_sigma_speed = non_negative_number("relative_sigma_speed", relative_sigma_speed)
    (image, chi2_specular, edge, chi2_edge, dof, image_covariance, edge_covariance, image_centre,
     edge_centre) = _fit_models(np.ascontiguousarray(transmitter), np.ascontiguousarray(receivers),
                                np.ascontiguousarray(paths), np.ascontiguousarray(sigma),
                                np.ascontiguousarray(outward), facing is not None, bool(covariances),
                                relative_sigma_speed)
    decided = _decide(image, chi2_specular, edge, chi2_edge, dof, image_covariance, edge_covariance, z)
    return _result(decided, image_centre, edge_centre, np.arange(n_echoes)[:, None], covariances)


def _result(decided, image_centre, edge_centre, joined, covariances) -> ConsistencyResult:
    """The :class:`ConsistencyResult` of :func:`_decide`'s outputs, the fits' arc centres and the joined rows.

    Adds the confidences and, where ``covariances``, each fit's sag along the line of sight about its arc's
    centre (N, 2) as a band (:data:`SAG_BAND`, :func:`sonar_ring.solvers.arc_spread`): here, not in the
    kernels, which call kernels of their own module only.
    """
    cls, specular, margin, chi2_specular, chi2_edge, dof, image, edge, image_covariance, edge_covariance = decided
    if covariances:
        solvers.arc_spread_rows(image, image_centre, image_covariance, SAG_BAND)
        solvers.arc_spread_rows(edge, edge_centre, edge_covariance, SAG_BAND)
    return ConsistencyResult(cls, specular, margin, confidence_from_margin(margin), chi2_specular, chi2_edge, dof,
                             image, edge, image_covariance, edge_covariance, joined)


@kernel
def _decide(image, chi2_specular, edge, chi2_edge, dof, image_covariance, edge_covariance, z):
    """Per echo, the two tests of :func:`geometric_consistency` on both models' fits (:func:`_fit_models`' outputs).

    ``image`` and ``edge`` (N, 2) m, ``chi2_specular`` and ``chi2_edge`` (N,), ``dof``
    (N,) int, the fits' covariances (N, 2, 2) m^2; ``z`` the significance.  An echo is tested when
    ``dof >= 1``: EDGE when ``chi2_specular - chi2_edge > z^2`` and the edge fits (``chi2_edge`` within
    :func:`_chi2_upper_quantile`), specular in the mirror case.  Returns the fields
    of :class:`ConsistencyResult` in order but the confidence (:func:`_result`
    adds it) and the joined rows: the class (N,) uint8, specular (N,) bool, the margin (N,) (0 where
    nothing was decided), the chi-squares, ``dof``, and the fitted points, NaN
    where untested, and their covariances, set to NaN in place there and where that model does not fit.
    """
    n_echoes = dof.size
    cls = np.full(n_echoes, UNKNOWN, dtype=np.uint8)
    specular = np.zeros(n_echoes, dtype=np.bool_)
    margin = np.zeros(n_echoes)
    tested_specular, tested_edge = np.full(n_echoes, np.nan), np.full(n_echoes, np.nan)
    tested_image, tested_point = np.full((n_echoes, 2), np.nan), np.full((n_echoes, 2), np.nan)
    threshold = z * z
    for n in range(n_echoes):
        if dof[n] < 1:
            image_covariance[n] = edge_covariance[n] = np.nan
            continue
        tested_specular[n], tested_edge[n] = chi2_specular[n], chi2_edge[n]
        tested_image[n], tested_point[n] = image[n], edge[n]
        difference = chi2_specular[n] - chi2_edge[n]
        fit_limit = _chi2_upper_quantile(dof[n], z)
        if not chi2_specular[n] <= fit_limit:
            image_covariance[n] = np.nan
        if not chi2_edge[n] <= fit_limit:
            edge_covariance[n] = np.nan
        is_edge = difference > threshold and chi2_edge[n] <= fit_limit
        is_specular = -difference > threshold and chi2_specular[n] <= fit_limit
        if is_edge or is_specular:
            statistic = abs(difference)
            margin[n] = (statistic - threshold) / (2.0 * np.sqrt(statistic))
            specular[n] = is_specular
            if is_edge:
                cls[n] = EDGE
    return (cls, specular, margin, tested_specular, tested_edge, dof, tested_image, tested_point, image_covariance,
            edge_covariance)


@kernel
def _far_field_image(centroid, outward, receivers, paths, usable):
    """Starting virtual image from a plane-wave fit: T' ~= centroid + mean(d) * arrival direction.

    Starting on the far side of the receivers (``outward``, unit (N, 2)) matters: nearly
    collinear receivers make the mirror image of ``T'`` across their line an almost
    equally good local minimum.  ``receivers`` (N, K, 2), ``paths`` (N, K), m, and
    ``usable`` (N, K); returns (N, 2), m.
    """
    n_echoes, n_receivers = paths.shape
    image = np.empty((n_echoes, 2))
    offset = np.empty(n_receivers)
    for n in range(n_echoes):
        lateral_x, lateral_y = -outward[n, 1], outward[n, 0]
        count = max(np.sum(usable[n]), 1)
        mean_path = mean_offset = 0.0
        for k in range(n_receivers):
            offset[k] = ((receivers[n, k, 0] - centroid[n, 0]) * lateral_x
                         + (receivers[n, k, 1] - centroid[n, 1]) * lateral_y)
            if usable[n, k]:
                mean_path += paths[n, k]
                mean_offset += offset[k]
        mean_path /= count
        mean_offset /= count
        spread = moment = 0.0
        for k in range(n_receivers):
            if usable[n, k]:
                spread += (offset[k] - mean_offset) ** 2
                moment += (offset[k] - mean_offset) * (paths[n, k] - mean_path)
        # A receiver further towards the source (larger lateral offset) has a shorter path.
        sine = min(max(-moment / (spread if spread > 0 else 1.0), -1.0), 1.0)
        cosine = np.sqrt(1.0 - sine ** 2)
        image[n, 0] = centroid[n, 0] + mean_path * (cosine * outward[n, 0] + sine * lateral_x)
        image[n, 1] = centroid[n, 1] + mean_path * (cosine * outward[n, 1] + sine * lateral_y)
    return image


def load_kernels() -> None:
    """Load the compiled consistency kernels now instead of at the first classification.

    Loading starts numba and reads the cached machine code; a process that
    classifies on a deadline pays that at start: the localiser node, so its first
    ping is not late, and the workers of ``sonar-ring process``, while the main
    process opens the bag.  Runs each kernel with the argument types of production
    (``test_compiled`` checks that a ping compiles nothing more): the fits through
    :func:`geometric_consistency`, the ring's kernel with read-only per-group
    arrays as :attr:`sonar_ring.geometry.Layout.plan` holds them.
    """
    receivers = np.array([[[0.02, 0.04], [0.02, 0.0], [0.02, -0.04]]])
    paths = np.full((1, 3), 2.0)
    geometric_consistency(np.zeros(2), receivers, paths, 1e-3, facing=np.array([1.0, 0.0]))
    # ring_consistency's arguments: per-group arrays as Layout.plan and _ring_slots give them, read-only.
    pair, transmitters = np.ascontiguousarray(receivers[:, :2]), np.zeros((1, 1, 2))
    facing, slots, spacing = np.array([[1.0, 0.0]]), np.zeros((1, 1), dtype=np.int64), np.zeros((1, 1, 2, 2))
    for array in (pair, transmitters, facing, slots, spacing):
        array.flags.writeable = False
    one = np.zeros(1, dtype=np.int64)
    two_paths = np.full((1, 2), 2.0)
    _ring_tests(one, one, two_paths, horizontal_path(two_paths, 0.0).value, pair, transmitters, facing, slots,
                spacing, 1e-3, CONSISTENCY_Z, MAX_ECHOES_PER_GROUP, False, 0.0)
    height_offset = np.zeros((1, 1, 2))
    height_offset.flags.writeable = False
    _row_height_offsets(height_offset, one)


@kernel
def _fit_models(transmitter, receivers, paths, sigma, facing, has_facing, covariances, relative_sigma_speed):
    """Both models' fits for :func:`geometric_consistency`, each echo on its own.

    ``transmitter`` (N, 2), ``receivers`` (N, K, 2), ``paths`` and ``sigma`` (N, K), m;
    ``facing`` (N, 2) the outward direction where ``has_facing``, else the direction
    from the transmitter to the receivers' centroid is used.  A receiver is used
    where its path is finite and positive and the geometry finite.  Returns the
    fitted virtual image (N, 2) and its chi-square (N,), the fitted edge point and
    its chi-square, the degrees of freedom (usable receivers - 2) (N,), and the two
    fits' covariances (N, 2, 2) without their sag and their arcs' centres (N, 2) (:func:`_fit_covariance`,
    with ``relative_sigma_speed``) where ``covariances``, else NaN.
    """
    n_echoes, n_receivers = paths.shape
    usable = np.zeros((n_echoes, n_receivers), dtype=np.bool_)
    weight = np.zeros((n_echoes, n_receivers))
    # Unused entries get harmless finite values; their weight keeps them out of every sum.
    safe_receivers = np.zeros((n_echoes, n_receivers, 2))
    safe_paths = np.zeros((n_echoes, n_receivers))
    safe_transmitter = np.zeros((n_echoes, 2))
    centroid = np.zeros((n_echoes, 2))
    outward = np.empty((n_echoes, 2))
    dof = np.empty(n_echoes, dtype=np.int64)
    for n in range(n_echoes):
        transmitter_finite = np.isfinite(transmitter[n, 0]) and np.isfinite(transmitter[n, 1])
        for axis in range(2):
            if np.isfinite(transmitter[n, axis]):
                safe_transmitter[n, axis] = transmitter[n, axis]
        for k in range(n_receivers):
            if (np.isfinite(paths[n, k]) and paths[n, k] > 0 and np.isfinite(receivers[n, k, 0])
                    and np.isfinite(receivers[n, k, 1]) and transmitter_finite):
                usable[n, k] = True
                weight[n, k] = 1.0 / sigma[n, k] ** 2
                safe_receivers[n, k] = receivers[n, k]
                safe_paths[n, k] = paths[n, k]
                centroid[n] += receivers[n, k]
        count = np.sum(usable[n])
        dof[n] = count - 2
        centroid[n] /= max(count, 1)
        direction = facing[n] if has_facing else centroid[n] - safe_transmitter[n]
        outward[n] = direction / np.sqrt(direction[0] ** 2 + direction[1] ** 2)
    image, chi2_specular = _fit(_far_field_image(centroid, outward, safe_receivers, safe_paths, usable),
                                safe_receivers, safe_paths, weight, safe_transmitter, False, _GAUSS_NEWTON_STEPS,
                                _CONVERGED)
    # The corner point (T + T') / 2 is within millimetres of an edge (Browne section 7).
    edge, chi2_edge = _fit(0.5 * (safe_transmitter + image), safe_receivers, safe_paths, weight, safe_transmitter,
                           True, _GAUSS_NEWTON_STEPS, _CONVERGED)
    if not covariances:
        return (image, chi2_specular, edge, chi2_edge, dof, np.full((n_echoes, 2, 2), np.nan),
                np.full((n_echoes, 2, 2), np.nan), np.full((n_echoes, 2), np.nan), np.full((n_echoes, 2), np.nan))
    image_covariance, image_centre = _fit_covariance(image, safe_receivers, safe_paths, weight, safe_transmitter,
                                                     False, relative_sigma_speed)
    edge_covariance, edge_centre = _fit_covariance(edge, safe_receivers, safe_paths, weight, safe_transmitter, True,
                                                   relative_sigma_speed)
    return (image, chi2_specular, edge, chi2_edge, dof, image_covariance, edge_covariance, image_centre,
            edge_centre)


@kernel
def _fit(start, receivers, paths, weight, emitter, edge, steps, converged):
    """Each echo's weighted least squares for a virtual image (not ``edge``) or an edge point.

    ``start`` (N, 2) m; ``receivers`` (N, K, 2) m; ``paths`` (N, K) m; ``weight``
    (N, K), 0 for receivers left out; ``emitter`` (N, 2) m, used for an edge.
    Returns the fitted points (N, 2) and their weighted residual sums of squares (N,).
    Each echo iterates on its own, up to ``steps`` Gauss-Newton steps, until a
    step predicted to lower the sum by at most ``converged`` (then the sum is the
    one the step's linear model predicts, ``S - g^T step``, and no pass is spent
    on it), or until a step would not descend (H indefinite by rounding; it is
    not taken), so its fit is the same in any batch.

    The echoes step in lockstep, each pass summing over the receivers for all
    of them at once: the loop over echoes is then free of dependences and runs
    in vector registers, where one echo's sums would be a chain of dependent
    square roots and divisions.  Every echo still adds its receivers in order,
    so its result is the one it would get alone.
    """
    n_echoes, n_receivers = paths.shape
    # Receiver-major copies: the echo loop reads each with unit stride.
    receiver_x = np.ascontiguousarray(receivers[:, :, 0].T)
    receiver_y = np.ascontiguousarray(receivers[:, :, 1].T)
    path = np.ascontiguousarray(paths.T)
    weights = np.ascontiguousarray(weight.T)
    x, y = start[:, 0].copy(), start[:, 1].copy()
    emitter_distance, emitter_unit_x, emitter_unit_y = np.zeros(n_echoes), np.zeros(n_echoes), np.zeros(n_echoes)
    xx, xy, yy = np.empty(n_echoes), np.empty(n_echoes), np.empty(n_echoes)
    gradient_x, gradient_y, squares = np.empty(n_echoes), np.empty(n_echoes), np.empty(n_echoes)
    chi2 = np.empty(n_echoes)
    step = np.zeros(n_echoes, dtype=np.int64)
    active = np.ones(n_echoes, dtype=np.bool_)
    for _ in range(steps + 1):  # an echo sums at most steps + 1 times: once per step, and at its last point
        xx[:] = xy[:] = yy[:] = gradient_x[:] = gradient_y[:] = squares[:] = 0.0
        if edge:
            for n in range(n_echoes):  # the emitter's part of the edge's path and Jacobian: once per pass
                away_x, away_y = x[n] - emitter[n, 0], y[n] - emitter[n, 1]
                emitter_distance[n] = np.sqrt(away_x * away_x + away_y * away_y)
                emitter_unit_x[n], emitter_unit_y[n] = away_x / emitter_distance[n], away_y / emitter_distance[n]
        for k in range(n_receivers):
            for n in range(n_echoes):
                w = weights[k, n]
                to_x, to_y = x[n] - receiver_x[k, n], y[n] - receiver_y[k, n]
                distance = np.sqrt(to_x * to_x + to_y * to_y)
                jacobian_x, jacobian_y = to_x / distance, to_y / distance
                if edge:
                    distance += emitter_distance[n]
                    jacobian_x += emitter_unit_x[n]
                    jacobian_y += emitter_unit_y[n]
                residual = distance - path[k, n]
                used = w != 0.0  # a receiver left out adds nothing, not 0 * NaN
                xx[n] += w * jacobian_x * jacobian_x if used else 0.0
                xy[n] += w * jacobian_x * jacobian_y if used else 0.0
                yy[n] += w * jacobian_y * jacobian_y if used else 0.0
                gradient_x[n] += w * jacobian_x * residual if used else 0.0
                gradient_y[n] += w * jacobian_y * residual if used else 0.0
                squares[n] += w * residual * residual if used else 0.0
        moving = False
        for n in range(n_echoes):
            if not active[n]:
                continue
            chi2[n] = squares[n]
            active[n] = False
            if step[n] == steps:
                continue
            det = xx[n] * yy[n] - xy[n] * xy[n]
            if not (np.isfinite(det) and det != 0.0):
                continue
            step_x = (yy[n] * gradient_x[n] - xy[n] * gradient_y[n]) / det
            step_y = (xx[n] * gradient_y[n] - xy[n] * gradient_x[n]) / det
            if not (np.isfinite(step_x) and np.isfinite(step_y)):
                continue
            decrease = step_x * gradient_x[n] + step_y * gradient_y[n]  # g^T H^-1 g, the linear model's
            if not decrease >= 0.0:  # no descent (H indefinite by rounding): the fit stays where it is
                continue
            x[n], y[n] = x[n] - step_x, y[n] - step_y
            step[n] += 1
            if decrease <= converged:
                chi2[n] = max(squares[n] - decrease, 0.0)
                continue
            active[n] = moving = True
        if not moving:
            break
    fitted = np.empty((n_echoes, 2))
    fitted[:, 0], fitted[:, 1] = x, y
    return fitted, chi2


@kernel
def _fit_covariance(fitted, receivers, paths, weight, emitter, edge, relative_sigma_speed):
    """Covariance (N, 2, 2) of each echo's fitted point, m^2, without its sag, and its arc's centre (N, 2), m.

    ``fitted`` the fitted points (N, 2), the other arguments :func:`_fit`'s.

    The fit's, ``H^-1`` with ``H = J^T W J`` at the fitted point (``J`` the paths' derivatives by the point,
    ``W`` the weights, the paths' inverse variances): the joint Cramer-Rao bound of the receivers that heard
    the echo, evaluated at the estimate.  Plus the speed of sound's share: every path scaled by ``1 + e``,
    ``e`` of standard deviation ``relative_sigma_speed``, moves the fit by ``e v`` with ``v = H^-1 J^T W d``
    (``d`` the paths; the vertical offset's share of the scale, ``(dz / d)^2``, is left out).  NaN where ``H``
    is singular or the point not finite.  The point lies on an arc about the centre (N, 2) returned, m, where
    its error across the line of sight (centimetres where its aperture is a few pairs') moves it along the
    line of sight by about the path noise, always outwards: :func:`_result` adds that sag.
    """
    n_echoes, n_receivers = paths.shape
    covariance = np.full((n_echoes, 2, 2), np.nan)
    centre = np.full((n_echoes, 2), np.nan)
    for n in range(n_echoes):
        x, y = fitted[n, 0], fitted[n, 1]
        emitter_unit_x = emitter_unit_y = 0.0  # the edge's path has a leg from the emitter, the image's not
        if edge:
            away_x, away_y = x - emitter[n, 0], y - emitter[n, 1]
            away = np.sqrt(away_x * away_x + away_y * away_y)
            emitter_unit_x, emitter_unit_y = away_x / away, away_y / away
        xx = xy = yy = scale_x = scale_y = centre_x = centre_y = 0.0
        used = 0
        for k in range(n_receivers):
            w = weight[n, k]
            if w == 0.0:
                continue
            centre_x += receivers[n, k, 0]
            centre_y += receivers[n, k, 1]
            used += 1
            to_x, to_y = x - receivers[n, k, 0], y - receivers[n, k, 1]
            distance = np.sqrt(to_x * to_x + to_y * to_y)
            jacobian_x, jacobian_y = to_x / distance + emitter_unit_x, to_y / distance + emitter_unit_y
            xx += w * jacobian_x * jacobian_x
            xy += w * jacobian_x * jacobian_y
            yy += w * jacobian_y * jacobian_y
            scale_x += w * jacobian_x * paths[n, k]
            scale_y += w * jacobian_y * paths[n, k]
        det = xx * yy - xy * xy
        if not (np.isfinite(det) and det > 0.0):
            continue
        inverse_xx, inverse_xy, inverse_yy = yy / det, -xy / det, xx / det
        shift_x = inverse_xx * scale_x + inverse_xy * scale_y
        shift_y = inverse_xy * scale_x + inverse_yy * scale_y
        speed = relative_sigma_speed * relative_sigma_speed
        covariance[n, 0, 0] = inverse_xx + speed * shift_x * shift_x
        covariance[n, 0, 1] = covariance[n, 1, 0] = inverse_xy + speed * shift_x * shift_y
        covariance[n, 1, 1] = inverse_yy + speed * shift_y * shift_y
        # The arc: a virtual image's equal-path circle is about the receivers, an edge's about them and the emitter.
        centre[n, 0], centre[n, 1] = centre_x / used, centre_y / used
        if edge:
            centre[n, 0], centre[n, 1] = 0.5 * (centre[n, 0] + emitter[n, 0]), 0.5 * (centre[n, 1] + emitter[n, 1])
    return covariance, centre


@kernel
def _chi2_upper_quantile(dof, z):
    """Upper quantile of chi-square with ``dof`` (>= 1) degrees of freedom at ``z`` (Wilson-Hilferty).

    ``z`` is a standard normal deviate.  For z = 3 to 3.5 it is at most 6 % above the exact
    quantile (slightly lenient, worst for one degree of freedom).
    """
    scale = 2.0 / (9.0 * dof)
    return dof * (1.0 - scale + z * np.sqrt(scale)) ** 3


# --------------------------------------------------------------------------- the single-emitter ring

def overlapping_groups(layout):
    """Groups whose fields of view overlap each group's, shape (G, J), -1 padded.

    Two groups overlap when their facings differ by less than twice the receivers'
    acceptance half-angle, so one reflector can be heard by both.  On Browne's ring
    (pairs every 7.5 deg, +-10 deg acceptance) these are the two neighbours on
    either side.

    Parameters
    ----------
    layout : sonar_ring.geometry.Layout
        The sensor.

    Returns
    -------
    ndarray of int, shape (G, J)
        Overlapping groups of each group, nearest facing first; J is the largest count.
    """
    return _overlapping_groups(layout.group_yaw().tobytes(), float(layout.beam_half_angle)).copy()


@functools.lru_cache(maxsize=16)
def _overlapping_groups(yaw_bytes: bytes, beam_half_angle: float) -> np.ndarray:
    """:func:`overlapping_groups` from the group facings (float64 bytes), computed once per layout."""
    yaw = np.frombuffer(yaw_bytes)
    gap = np.abs(np.angle(np.exp(1j * (yaw[:, None] - yaw[None, :]))))
    overlap = (gap < 2.0 * beam_half_angle) & ~np.eye(yaw.size, dtype=bool)
    order = np.argsort(np.where(overlap, gap, np.inf), axis=1, kind="stable")
    width = int(overlap.sum(axis=1).max(initial=0))
    chosen = order[:, :width]
    return np.where(np.take_along_axis(overlap, chosen, axis=1), chosen, -1)


def ring_consistency(layout, group, paths, sigma_path, ping=None, z=CONSISTENCY_Z, covariances=False,
                     relative_sigma_speed=0.0) -> ConsistencyResult:
    """Geometric consistency of every echo of a single-emitter sensor, with its overlapping groups.

    Each echo row (one group, its K receivers) is joined by the echo of each
    overlapping group (:func:`overlapping_groups`) of the same ping that passes the
    triangle-inequality gate ``|h_i - h_k| <= |R_i - R_k| + z sqrt(sigma_i^2 + sigma_k^2)``
    for every receiver pair -- which any single reflector satisfies -- provided it is
    the only one there that does; where two pass, which one belongs is unknown and
    that group is left out.  An echo whose own group holds another echo passing the
    gate (two reflectors at indistinguishable ranges, e.g. a wall and the edge at its
    end) is not tested at all.  A wrong join that still slips through fits neither
    model and stays UNKNOWN by the goodness-of-fit check of :func:`geometric_consistency`.

    Path lengths are first made horizontal, ``sqrt(d^2 - dz^2)``, exact for vertically
    extruded reflectors, with their standard deviation scaled by ``d / sqrt(d^2 - dz^2)``.

    A group reporting more than :data:`MAX_ECHOES_PER_GROUP` echoes in one ping is
    not tested and joins no other echo: the gate compares every pair of candidate
    echoes, so its time would grow with the square of that count, and no
    reflector geometry produces so many separate echoes in one pair.

    Parameters
    ----------
    layout : sonar_ring.geometry.Layout
        A layout whose groups each have one transmitter (Browne ring, Kreczmer triad).
    group : array_like of int, shape (N,)
        Receiver group of each echo.
    paths : array_like, shape (N, K)
        Measured path lengths ``c * tof``, m; NaN where a receiver missed the echo.
    sigma_path : float
        Standard deviation of one measured path length, m (``c * sigma_tof``), > 0.
    ping : array_like of int, shape (N,), optional
        Ping of each echo when several pings are stacked; echoes join only within a ping.
    z : float
        Significance in standard normal deviates, > 0 (see :func:`geometric_consistency`).
    covariances : bool
        Also the fits' covariances (:func:`geometric_consistency`).
    relative_sigma_speed : float
        Relative standard deviation of the speed of sound, >= 0 (the fits' covariances).

    Returns
    -------
    ConsistencyResult
        One entry per echo row; positions in the sensor frame, the fits over the echo's row and the rows
        joined with it (``joined``).
    """
    if layout.group_transmitters.shape[1] != 1:
        raise ValueError(f"ring_consistency: layout {layout.name!r} has "
                         f"{layout.group_transmitters.shape[1]} transmitters per group; geometric "
                         "consistency needs one emitter (use the amplitude rule for transducer pairs)")
    sigma_path = positive_number("sigma_path", sigma_path)
    z = positive_number("z", z)
    relative_sigma_speed = non_negative_number("relative_sigma_speed", relative_sigma_speed)
    group = np.array(group, dtype=np.int64).reshape(-1)  # a copy: writable, one type to numba
    n_echoes, k = group.size, layout.receivers_per_group
    paths = np.array(paths, dtype=float, order="C")  # a copy: writable and contiguous, one type to numba
    if paths.shape != (n_echoes, k):
        raise ValueError(f"paths must have shape {(n_echoes, k)}, got {paths.shape}")
    ping = np.zeros(n_echoes, dtype=int) if ping is None else np.asarray(ping, dtype=int).reshape(-1)
    if ping.shape != (n_echoes,):
        raise ValueError(f"ping must have shape {(n_echoes,)}, got {ping.shape}")

    plan = layout.plan
    # Through the module: a kernel imported by name stays the wrapper that compiles at first use.
    height_offsets, outside = _row_height_offsets(plan.height_offset, group)
    if outside >= 0:
        raise ValueError(f"group indices must be in [0, {layout.n_groups}), got {group[outside]} in row {outside}")
    horizontal = solvers.horizontal_rows(paths.ravel(), height_offsets)[0].reshape(paths.shape)
    slots, spacing = _ring_slots(plan.yaw.tobytes(), float(layout.beam_half_angle), plan.receivers.tobytes())
    *decided, joined, image_centre, edge_centre = _ring_tests(
        ping.astype(np.int64), group, paths, horizontal, plan.receivers, plan.transmitters, plan.facing, slots,
        spacing, sigma_path, z, MAX_ECHOES_PER_GROUP, bool(covariances), relative_sigma_speed)
    return _result(decided, image_centre, edge_centre, joined, covariances)


@kernel
def _row_height_offsets(height_offset, group):
    """Each echo's transmitter-minus-receiver heights, ``height_offset[group, 0]`` flattened (N K,), m.

    ``height_offset`` (G, M, K) as :attr:`sonar_ring.geometry.Layout.plan` holds
    it, ``group`` (N,).  Also returns the first row whose group is outside
    ``[0, G)`` (checked here: compiled indexing does not check bounds), or -1.
    """
    n_groups, n_receivers = height_offset.shape[0], height_offset.shape[2]
    offsets = np.empty(group.size * n_receivers)
    for n in range(group.size):
        if not 0 <= group[n] < n_groups:
            return offsets, n
        for k in range(n_receivers):
            offsets[n * n_receivers + k] = height_offset[group[n], 0, k]
    return offsets, -1


@functools.lru_cache(maxsize=16)
def _ring_slots(yaw_bytes: bytes, beam_half_angle: float, receiver_bytes: bytes) -> tuple[np.ndarray, np.ndarray]:
    """What :func:`_ring_tests` joins, computed once per layout from its facings and receivers (float64 bytes).

    Returns each group followed by its overlapping groups (:func:`overlapping_groups`),
    shape (G, 1 + J), -1 padded, and the distances ``|R_i - R_k|`` between each
    group's receivers and each of those groups' (G, 1 + J, K, K), m (0 where padded);
    both read-only.
    """
    overlapping = _overlapping_groups(yaw_bytes, beam_half_angle)
    slots = np.concatenate([np.arange(len(overlapping))[:, None], overlapping], axis=1).astype(np.int64)
    receivers = np.frombuffer(receiver_bytes).reshape(len(slots), -1, 2)
    spacing = np.linalg.norm(receivers[:, None, :, None, :] - receivers[slots][:, :, None, :, :], axis=-1)
    spacing[slots < 0] = 0.0
    for array in (slots, spacing):
        array.flags.writeable = False
    return slots, spacing


@kernel
def _ring_tests(ping, group, paths, horizontal, receivers, transmitters, facing, slots, spacing, sigma_path, z,
                max_per_group, covariances, relative_sigma_speed):
    """Both models' fits and tests (:func:`_decide`) of every echo of :func:`ring_consistency`.

    Each echo is joined with its overlapping groups' echoes first.

    ``ping`` and ``group`` (N,) int; ``paths`` (N, K) measured path lengths and
    ``horizontal`` their horizontal parts (NaN where unusable), m;
    per group (:attr:`sonar_ring.geometry.Layout.plan`): ``receivers`` (G, K, 2),
    ``transmitters`` (G, M, 2), m, and the unit
    ``facing`` (G, 2); ``slots`` (G, 1 + J) each group and its overlapping ones and
    ``spacing`` (G, 1 + J, K, K) the distances between their receivers, m
    (:func:`_ring_slots`); ``sigma_path`` m; ``z`` the gate's significance; a group
    with more than ``max_per_group`` echoes in a ping is left out.  Returns what
    :func:`_decide` returns, one row per echo (the fits' covariances where ``covariances``, with
    ``relative_sigma_speed``), and
    the rows joined with each (N, 1 + J), its own first, -1 padded, and the fits' arc centres (N, 2)
    (:func:`_fit_models`); an echo left out (crowded, too many echoes) has no usable receiver, so is
    untested, and is joined with no other.
    """
    n_echoes, n_receivers = paths.shape
    n_groups, n_slots = slots.shape
    # A horizontal path's sigma: the measured one's, scaled by d / sqrt(d^2 - dz^2).
    sigma = np.full((n_echoes, n_receivers), sigma_path)
    for n in range(n_echoes):
        for k in range(n_receivers):
            scaled = sigma_path * paths[n, k] / horizontal[n, k]
            if np.isfinite(scaled) and scaled > 0:
                sigma[n, k] = scaled
    # Rows of each (ping, group) slot, in row order: a stable sort by key and a binary search.
    key = ping * n_groups + group
    order = np.argsort(key, kind="mergesort")
    sorted_key = key[order]
    overfull = np.empty(n_echoes, dtype=np.bool_)
    for n in range(n_echoes):
        overfull[n] = (np.searchsorted(sorted_key, key[n], side="right")
                       - np.searchsorted(sorted_key, key[n], side="left")) > max_per_group
    width = n_slots * n_receivers
    all_paths = np.full((n_echoes, width), np.nan)
    all_sigma = np.full((n_echoes, width), sigma_path)
    all_receivers = np.zeros((n_echoes, width, 2))
    echo_transmitter = np.empty((n_echoes, 2))
    echo_facing = np.empty((n_echoes, 2))
    joined = np.empty(n_slots, dtype=np.int64)
    joined_rows = np.full((n_echoes, n_slots), -1, dtype=np.int64)
    for n in range(n_echoes):
        joined_rows[n, 0] = n
        echo_transmitter[n] = transmitters[group[n], 0]
        echo_facing[n] = facing[group[n]]
        if overfull[n]:
            continue
        # Each slot's echo joins when it alone passes the gate; a second echo passing in the
        # echo's own group (slot 0) makes the echo crowded: it is not tested at all.
        crowded = False
        for slot in range(n_slots):
            joined[slot] = -1
            target = slots[group[n], slot]
            if target < 0:
                continue
            wanted = ping[n] * n_groups + target
            passing = 0
            for index in range(np.searchsorted(sorted_key, wanted, side="left"),
                               np.searchsorted(sorted_key, wanted, side="right")):
                other = order[index]
                if (other != n and not overfull[other]
                        and _passes_gate(n, other, horizontal, sigma, spacing[group[n], slot], z)):
                    passing += 1
                    joined[slot] = other
            if slot == 0 and passing > 0:
                crowded = True
            if passing != 1:
                joined[slot] = -1
        if crowded:
            continue
        joined[0] = n
        joined_rows[n] = joined
        for slot in range(n_slots):
            row = joined[slot]
            if row < 0:
                continue
            for k in range(n_receivers):
                column = slot * n_receivers + k
                all_paths[n, column] = horizontal[row, k]
                all_sigma[n, column] = sigma[row, k]
                all_receivers[n, column] = receivers[group[row], k]
    (image, chi2_specular, edge, chi2_edge, dof, image_covariance, edge_covariance, image_centre,
     edge_centre) = _fit_models(echo_transmitter, all_receivers, all_paths, all_sigma, echo_facing, True, covariances,
                                relative_sigma_speed)
    (cls, specular, margin, chi2_specular, chi2_edge, dof, image, edge, image_covariance,
     edge_covariance) = _decide(image, chi2_specular, edge, chi2_edge, dof, image_covariance, edge_covariance, z)
    return (cls, specular, margin, chi2_specular, chi2_edge, dof, image, edge, image_covariance, edge_covariance,
            joined_rows, image_centre, edge_centre)


@kernel
def _passes_gate(n, other, horizontal, sigma, spacing, z):
    """Whether echoes ``n`` and ``other`` were both heard and fit one reflector.

    Every pair of receivers that heard them must satisfy the triangle inequality
    ``|h_i - h_k| <= |R_i - R_k| + z sqrt(sigma_i^2 + sigma_k^2)``; ``spacing``
    (K, K) holds ``|R_i - R_k|``, m, between their groups' receivers.
    """
    n_receivers = horizontal.shape[1]
    heard = False
    for i in range(n_receivers):
        own = horizontal[n, i]
        if not np.isfinite(own):
            continue
        for j in range(n_receivers):
            theirs = horizontal[other, j]
            if not np.isfinite(theirs):
                continue
            heard = True
            # Squared, where the gap exceeds the spacing: no square root (several thousand a ping).
            excess = abs(own - theirs) - spacing[i, j]
            if excess > 0.0 and excess * excess > z * z * (sigma[n, i] ** 2 + sigma[other, j] ** 2):
                return False
    return heard
