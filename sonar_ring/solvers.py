"""The compiled localisation: each reflector model's closed form for one entry, and the loops over rows built on them.

:mod:`sonar_ring.localise` is the public face (checked arguments, any
broadcast shape, results as dataclasses); this module is what it and
:func:`sonar_ring.pipeline.localise_ping` run, one loop over flat rows with
no numpy call per entry.  Its kernels call each other (numba's cache of a
caller holds its callees, so they share one module: see
:mod:`sonar_ring.compiled`):

* one small kernel per model -- :func:`_virtual_image`, :func:`_plane`,
  :func:`_corner`, :func:`_edge`, :func:`_on_axis` -- after the checks every
  model shares (:func:`_pair_frame`, :func:`_checked`);
* :func:`solve_rows`: the models asked for, for N entries;
* :func:`unscented_models`, :func:`localise_rows` and
  :func:`localise_ping_rows`: a ping's rows with their covariances, as the
  nodes localise them;
* :func:`horizontal_rows` and :func:`path_covariance_rows`: the vertical
  correction and the paths' covariance, per entry;
* :func:`reflector_path_rows` (the paths a landmark implies, for
  :func:`sonar_ring.localise.reflector_paths`; :func:`grouped_path_rows` the
  same in 3-D to each landmark's group, for :func:`sonar_ring.explain.landmark_paths`
  and the mapper's echo tests), :func:`jacobian_rows` (each model's derivative by the paths, for
  :func:`sonar_ring.uncertainty.position_jacobian`) and :func:`point_model_rows`
  (both point models of a sighting, for :func:`sonar_ring.curvature.point_models`,
  which the mapper calls every ping).

The reason codes are defined here, with the checks that set them; the
geometry, frames and numerics are described in :mod:`sonar_ring.localise`.
"""

from __future__ import annotations

import numpy as np

from sonar_ring.compiled import kernel

OK = 0
NOT_FINITE = 1
DEGENERATE = 2
NEGATIVE = 3
NO_INTERSECTION = 4
TOO_SHORT = 5
BELOW_HEIGHT = 6
BEHIND = 7
AMBIGUOUS = 8

MAX_LENGTH = 1e6
"""Largest |coordinate| or path length taken, m.  Beyond it an input is corrupt, not a measurement
(squares of lengths near 1e154 m overflow), and is flagged NOT_FINITE like NaN or infinity."""

REASONS = {
    OK: "ok",
    NOT_FINITE: "NaN, infinite or absurd input (beyond MAX_LENGTH)",
    DEGENERATE: "degenerate geometry (coincident receivers or singular configuration)",
    NEGATIVE: "path length not positive",
    NO_INTERSECTION: "no real solution (|d2 - d1| > D or d1 + d2 < D)",
    TOO_SHORT: "path shorter than the direct transmitter-to-receiver distance",
    BELOW_HEIGHT: "path shorter than the height difference",
    BEHIND: "landmark not in front of the receivers",
    AMBIGUOUS: "two edge solutions in front of the receivers",
}
"""Human-readable meaning of each reason code."""

SOLVERS = ("virtual_image", "plane", "corner", "edge", "on_axis")
"""The models :func:`solve_rows` computes, in the order of its ``wanted`` flags and outputs."""
VIRTUAL_IMAGE_SOLVER, PLANE_SOLVER, CORNER_SOLVER, EDGE_SOLVER, ON_AXIS_SOLVER = range(len(SOLVERS))
"""Each model's index in :data:`SOLVERS` (not the landmark classes of :mod:`sonar_ring.landmarks`)."""
NEAR_TRANSMITTER = 0.1
"""An edge nearer the transmitter than this share of its shorter path gets its position polished (:func:`_edge`)."""
ARC_MSE = 30.0
"""Mean-squared error along an estimate's arc bias, in squared biases (see :func:`unscented_models`)."""


# --------------------------------------------------------------------------- one entry

@kernel
def _pair_frame(r1_x, r1_y, r2_x, r2_y):
    """The receivers' frame: separation D (m), unit baseline ``u`` (R1 to R2), front ``n``, mid-point ``c`` (m).

    ``n`` is ``u`` turned counter-clockwise, which is R1 - R2 turned clockwise.
    Returns ``separation, u_x, u_y, n_x, n_y, c_x, c_y``.
    """
    base_x, base_y = r2_x - r1_x, r2_y - r1_y
    separation = np.sqrt(base_x * base_x + base_y * base_y)
    u_x, u_y = base_x / separation, base_y / separation
    return separation, u_x, u_y, -u_y, u_x, 0.5 * (r1_x + r2_x), 0.5 * (r1_y + r2_y)


@kernel
def _checked(tx_x, tx_y, r1_x, r1_y, r2_x, r2_y, a, b, separation):
    """The checks every model shares, for transmitter, receivers (m) and paths ``a``, ``b`` (m).

    Returns the first failing code of NOT_FINITE, DEGENERATE (coincident
    receivers) and NEGATIVE, or OK; whether the receivers' circles are too far
    apart to meet (``|d2 - d1| > D``); and whether a path is shorter than the
    direct one, which no reflector can produce (triangle inequality).
    """
    common = OK
    if not (abs(tx_x) <= MAX_LENGTH and abs(tx_y) <= MAX_LENGTH and abs(r1_x) <= MAX_LENGTH
            and abs(r1_y) <= MAX_LENGTH and abs(r2_x) <= MAX_LENGTH and abs(r2_y) <= MAX_LENGTH
            and abs(a) <= MAX_LENGTH and abs(b) <= MAX_LENGTH):
        common = NOT_FINITE
    elif not separation > 0:
        common = DEGENERATE
    elif not (a > 0 and b > 0):
        common = NEGATIVE
    difference = b - a  # exact for nearby values (Sterbenz), so no cancellation downstream
    apart = separation + difference < 0 or separation - difference < 0
    to_r1_x, to_r1_y, to_r2_x, to_r2_y = r1_x - tx_x, r1_y - tx_y, r2_x - tx_x, r2_y - tx_y
    too_short = (a < np.sqrt(to_r1_x * to_r1_x + to_r1_y * to_r1_y)
                 or b < np.sqrt(to_r2_x * to_r2_x + to_r2_y * to_r2_y))
    return common, apart, too_short


@kernel
def _virtual_image(a, b, separation, u_x, u_y, n_x, n_y, c_x, c_y, common, apart, too_short):
    """The virtual image ``T'``: at ``a`` from R1 and ``b`` from R2, in front; ``reason, x, y`` (m, NaN unless OK).

    The frame is :func:`_pair_frame`'s, ``common``, ``apart`` and ``too_short`` :func:`_checked`'s.
    """
    reason = common
    difference, total = b - a, a + b
    if reason == OK and (apart or total < separation):
        reason = NO_INTERSECTION
    if reason == OK and too_short:
        reason = TOO_SHORT
    if reason != OK:
        return reason, np.nan, np.nan
    along = -difference * total / (2.0 * separation)
    # Heron: the height over the baseline is 2 * area / D, every factor formed from inputs directly.
    heron = (separation + difference) * (separation - difference) * (total - separation) * (total + separation)
    height = np.sqrt(heron) / (2.0 * separation)
    return reason, c_x + along * u_x + height * n_x, c_y + along * u_y + height * n_y


@kernel
def _plane(tx_x, tx_y, r1_x, r1_y, r2_x, r2_y, image_reason, image_x, image_y):
    """The plane of a virtual image (:func:`_virtual_image`'s outputs): the perpendicular bisector of ``T T'``.

    Returns ``reason`` (DEGENERATE where ``T' = T``), the foot point ``G = (T + T') / 2``,
    the unit normal along ``T' - T`` and the reflection points seen by R1 and R2
    (where ``R_n T'`` crosses the plane), m; NaN unless OK.
    """
    axis_x, axis_y = image_x - tx_x, image_y - tx_y
    length = np.sqrt(axis_x * axis_x + axis_y * axis_y)
    reason = image_reason
    if reason == OK and not length > 0:
        reason = DEGENERATE
    if reason != OK:
        return reason, np.nan, np.nan, np.nan, np.nan, np.nan, np.nan, np.nan, np.nan
    normal_x, normal_y = axis_x / length, axis_y / length
    # Distance of the receiver from the plane over that of T' from it: where R_n T' crosses.
    depth = 0.5 * length - ((r1_x - tx_x) * normal_x + (r1_y - tx_y) * normal_y)
    fraction_1 = depth / (depth + 0.5 * length)
    depth = 0.5 * length - ((r2_x - tx_x) * normal_x + (r2_y - tx_y) * normal_y)
    fraction_2 = depth / (depth + 0.5 * length)
    return (reason, tx_x + 0.5 * axis_x, tx_y + 0.5 * axis_y, normal_x, normal_y,
            r1_x + fraction_1 * (image_x - r1_x), r1_y + fraction_1 * (image_y - r1_y),
            r2_x + fraction_2 * (image_x - r2_x), r2_y + fraction_2 * (image_y - r2_y))


@kernel
def _corner(tx_x, tx_y, n_x, n_y, c_x, c_y, image_reason, image_x, image_y):
    """The corner of a virtual image, ``G = (T + T') / 2``: ``reason`` (BEHIND unless in front), x, y."""
    corner_x, corner_y = 0.5 * (tx_x + image_x), 0.5 * (tx_y + image_y)
    reason = image_reason
    if reason == OK and not (corner_x - c_x) * n_x + (corner_y - c_y) * n_y > 0:
        reason = BEHIND
    if reason != OK:
        return reason, np.nan, np.nan
    return reason, corner_x, corner_y


@kernel(inline=True)
def _edge(tx_x, tx_y, r1_x, r1_y, r2_x, r2_y, a, b, separation, u_x, u_y, n_x, n_y, c_x, c_y, common, apart,
          too_short):
    """The edge ``P`` with ``|P - T| + |P - R_n| = d_n`` (method: :func:`sonar_ring.localise.edge`); ``reason, x, y``.

    The frame is :func:`_pair_frame`'s, ``common``, ``apart`` and ``too_short``
    :func:`_checked`'s; NaN unless OK.
    """
    reason = common
    if reason == OK and apart:
        reason = NO_INTERSECTION
    if reason == OK and too_short:
        reason = TOO_SHORT
    difference, total = b - a, a + b
    offset_x, offset_y = tx_x - c_x, tx_y - c_y
    t_u = offset_x * u_x + offset_y * u_y
    t_n = offset_x * n_x + offset_y * n_y
    # Difference of the receivers' circles: p_u = (d1 - d2)(d1 + d2 - 2k) / (2D) = beta0 + beta1 k.
    beta1 = difference / separation
    beta0 = -difference * total / (2.0 * separation)
    # Their mean minus the transmitter's circle: 2 t_n p_n = mu0 - mu1 k.
    mu0 = 0.5 * (a * a + b * b) - 0.25 * separation * separation + t_u * t_u + t_n * t_n - 2.0 * beta0 * t_u
    mu1 = total + 2.0 * beta1 * t_u
    # Hence k = nu0 + nu1 p_n and p_u = pi0 + pi1 p_n.
    nu0 = mu0 / mu1
    nu1 = -2.0 * t_n / mu1
    pi1 = beta1 * nu1
    # R1's circle (p_u + D/2)^2 + p_n^2 = (d1 - k)^2 as qa p_n^2 + qb p_n + qc = 0, from its values at p_n = 0.
    from_r1 = difference * (2.0 * nu0 - total) / (2.0 * separation) + 0.5 * separation
    radius = a - nu0
    qa = (1.0 - nu1) * (1.0 + nu1) + pi1 * pi1
    qb = 2.0 * (from_r1 * pi1 + radius * nu1)
    qc = (from_r1 - radius) * (from_r1 + radius)
    discriminant = qb * qb - 4.0 * qa * qc
    half = -0.5 * (qb + np.copysign(np.sqrt(discriminant), qb))
    shortest = np.minimum(a, b)
    # The two roots, candidate normal offsets p_n; the squared circles admit k < 0 or d_n - k < 0,
    # only k in [0, min d_n] is an edge, and it must be ahead.
    first, second = half / qa, qc / half
    k_first, k_second = nu0 + nu1 * first, nu0 + nu1 * second
    first_ahead = np.isfinite(first) and k_first >= 0 and k_first <= shortest and first > 0
    second_ahead = np.isfinite(second) and k_second >= 0 and k_second <= shortest and second > 0
    if reason == OK and not mu1 > 0:
        reason = DEGENERATE
    if reason == OK and not discriminant >= 0:
        reason = NO_INTERSECTION
    if reason == OK and not (first_ahead or second_ahead):
        reason = BEHIND
    if reason == OK and first_ahead and second_ahead:
        reason = AMBIGUOUS
    if reason != OK:
        return reason, np.nan, np.nan
    normal_offset, path_k = (first, k_first) if first_ahead else (second, k_second)
    along = difference * (2.0 * path_k - total) / (2.0 * separation)
    p_x = c_x + along * u_x + normal_offset * n_x
    p_y = c_y + along * u_y + normal_offset * n_y
    # k comes from mu0, a difference of squared lengths that cancels as the edge nears the
    # transmitter (k << d_n, by about d_n / k): there one Newton step on the path equations.
    if path_k < NEAR_TRANSMITTER * shortest:
        p_x, p_y = _newton_step(p_x, p_y, tx_x, tx_y, r1_x, r1_y, r2_x, r2_y, a, b)
    return reason, p_x, p_y


@kernel
def _newton_step(p_x, p_y, tx_x, tx_y, r1_x, r1_y, r2_x, r2_y, a, b):
    """One Newton step of the edge ``P`` on ``|P - T| + |P - R_n| = d_n``, kept only where it brings the paths closer.

    Near a tangency or at ``T`` the step is no better, and ``P`` is returned as it is.
    """
    to_t_x, to_t_y = p_x - tx_x, p_y - tx_y
    to_1_x, to_1_y = p_x - r1_x, p_y - r1_y
    to_2_x, to_2_y = p_x - r2_x, p_y - r2_y
    k_t = np.sqrt(to_t_x * to_t_x + to_t_y * to_t_y)
    k_1 = np.sqrt(to_1_x * to_1_x + to_1_y * to_1_y)
    k_2 = np.sqrt(to_2_x * to_2_x + to_2_y * to_2_y)
    j11, j12 = to_t_x / k_t + to_1_x / k_1, to_t_y / k_t + to_1_y / k_1
    j21, j22 = to_t_x / k_t + to_2_x / k_2, to_t_y / k_t + to_2_y / k_2
    residual_1, residual_2 = k_t + k_1 - a, k_t + k_2 - b
    det = j11 * j22 - j12 * j21
    step_x = (j22 * residual_1 - j12 * residual_2) / det
    step_y = (j11 * residual_2 - j21 * residual_1) / det
    new_x, new_y = p_x - step_x, p_y - step_y
    new_t = np.sqrt((new_x - tx_x) ** 2 + (new_y - tx_y) ** 2)
    new_1 = new_t + np.sqrt((new_x - r1_x) ** 2 + (new_y - r1_y) ** 2) - a
    new_2 = new_t + np.sqrt((new_x - r2_x) ** 2 + (new_y - r2_y) ** 2) - b
    if max(abs(new_1), abs(new_2)) < max(abs(residual_1), abs(residual_2)):
        return new_x, new_y
    return p_x, p_y


@kernel
def _on_axis(tx_x, tx_y, a, b, n_x, n_y, c_x, c_y, common):
    """The echo on the receivers' axis: ``P = c + r n`` with ``|P - T| + r`` the mean path; ``reason, x, y``."""
    reason = common
    mean = 0.5 * (a + b)
    offset_x, offset_y = c_x - tx_x, c_y - tx_y
    direct = np.sqrt(offset_x * offset_x + offset_y * offset_y)
    if reason == OK and mean < direct:
        reason = TOO_SHORT
    # |offset + r n|^2 = (mean - r)^2 is linear in r.
    denominator = 2.0 * (mean + (offset_x * n_x + offset_y * n_y))
    if reason == OK and not denominator > 0:
        reason = DEGENERATE
    if reason != OK:
        return reason, np.nan, np.nan
    distance = (mean - direct) * (mean + direct) / denominator
    return reason, c_x + distance * n_x, c_y + distance * n_y


# --------------------------------------------------------------------------- N entries

@kernel
def _mask(rows):
    """-1 (all bits) for an input of several rows, 0 for one: entry k reads its row ``k & mask``."""
    return -1 if len(rows) > 1 else 0


@kernel
def solve_rows(count, tx, rx1, rx2, d1, d2, wanted):
    """The models of :data:`SOLVERS` flagged in ``wanted`` (5,) for ``count`` entries, each entry alone.

    ``tx``, ``rx1``, ``rx2`` (count, 2) or (1, 2), m, and ``d1``, ``d2``
    (count,) or (1,), m: one row per entry, or one row for all of them (a
    shared geometry is then not copied out to every entry).  Returns ``reason``
    (5, count) int8, ``position`` (5, count, 2) m, and the plane's ``normal``
    (count, 2) and ``reflection_points`` (count, 2, 2) m; NaN wherever the
    entry is not valid, and unspecified for models not wanted.  An entry
    carries the code of the first check it fails, in the order of
    :mod:`sonar_ring.localise`'s docstring.
    """
    reason = np.zeros((5, count), dtype=np.int8)
    position = np.empty((5, count, 2))
    normal = np.empty((count, 2))
    reflection = np.empty((count, 2, 2))
    # Entry k reads row k & mask of each input: row k (mask -1, all bits), or its only row (mask 0).
    mask_tx, mask_rx1, mask_rx2 = _mask(tx), _mask(rx1), _mask(rx2)
    mask_d1, mask_d2 = _mask(d1), _mask(d2)
    want_image = wanted[VIRTUAL_IMAGE_SOLVER] or wanted[PLANE_SOLVER] or wanted[CORNER_SOLVER]
    for k in range(count):
        tx_x, tx_y = tx[k & mask_tx, 0], tx[k & mask_tx, 1]
        r1_x, r1_y = rx1[k & mask_rx1, 0], rx1[k & mask_rx1, 1]
        r2_x, r2_y = rx2[k & mask_rx2, 0], rx2[k & mask_rx2, 1]
        a, b = d1[k & mask_d1], d2[k & mask_d2]
        separation, u_x, u_y, n_x, n_y, c_x, c_y = _pair_frame(r1_x, r1_y, r2_x, r2_y)
        common, apart, too_short = _checked(tx_x, tx_y, r1_x, r1_y, r2_x, r2_y, a, b, separation)
        if want_image:
            image_reason, image_x, image_y = _virtual_image(a, b, separation, u_x, u_y, n_x, n_y, c_x, c_y, common,
                                                            apart, too_short)
            if wanted[VIRTUAL_IMAGE_SOLVER]:
                reason[VIRTUAL_IMAGE_SOLVER, k] = image_reason
                position[VIRTUAL_IMAGE_SOLVER, k, 0], position[VIRTUAL_IMAGE_SOLVER, k, 1] = image_x, image_y
            if wanted[PLANE_SOLVER]:
                (reason[PLANE_SOLVER, k], position[PLANE_SOLVER, k, 0], position[PLANE_SOLVER, k, 1],
                 normal[k, 0], normal[k, 1], reflection[k, 0, 0], reflection[k, 0, 1], reflection[k, 1, 0],
                 reflection[k, 1, 1]) = _plane(tx_x, tx_y, r1_x, r1_y, r2_x, r2_y, image_reason, image_x, image_y)
            if wanted[CORNER_SOLVER]:
                reason[CORNER_SOLVER, k], position[CORNER_SOLVER, k, 0], position[CORNER_SOLVER, k, 1] = _corner(
                    tx_x, tx_y, n_x, n_y, c_x, c_y, image_reason, image_x, image_y)
        if wanted[EDGE_SOLVER]:
            reason[EDGE_SOLVER, k], position[EDGE_SOLVER, k, 0], position[EDGE_SOLVER, k, 1] = _edge(
                tx_x, tx_y, r1_x, r1_y, r2_x, r2_y, a, b, separation, u_x, u_y, n_x, n_y, c_x, c_y, common, apart,
                too_short)
        if wanted[ON_AXIS_SOLVER]:
            reason[ON_AXIS_SOLVER, k], position[ON_AXIS_SOLVER, k, 0], position[ON_AXIS_SOLVER, k, 1] = _on_axis(
                tx_x, tx_y, a, b, n_x, n_y, c_x, c_y, common)
    return reason, position, normal, reflection


# --------------------------------------------------------------------------- a ping's rows

@kernel
def unscented_models(tx, rx1, rx2, d1, d2, paths_covariance, wanted):
    """The models of :data:`SOLVERS` flagged in ``wanted`` for N rows, with unscented covariances.

    Each row's paths ``(d1, d2)`` (N,) with covariance ``S`` (N, 2, 2) give five
    sigma points (``n + kappa = 3``): the measurement, and it plus and minus each
    column of the Cholesky factor of ``3 S``; one solve of all five times N
    entries (:func:`solve_rows`) gives the estimate (point 0) and its spread.
    Returns ``reason`` (5, N), ``position`` (5, N, 2), the plane's ``normal``
    (N, 2) and ``reflection_points`` (N, 2, 2) of the estimates, and their
    covariances (5, N, 2, 2): the sigma points' covariance with the arc's bias
    raised to :data:`ARC_MSE` (see :func:`sonar_ring.pipeline.localise_ping`); NaN where a sigma
    point has no solution.
    """
    count = d1.size
    sigma_d1, sigma_d2 = np.empty(5 * count), np.empty(5 * count)
    sigma_tx, sigma_rx1, sigma_rx2 = np.empty((5 * count, 2)), np.empty((5 * count, 2)), np.empty((5 * count, 2))
    largest = np.finfo(np.float64).max
    for row in range(count):
        scaled = np.empty(3)
        for entry, (i, j) in enumerate(((0, 0), (1, 0), (1, 1))):
            value = paths_covariance[row, i, j]
            finite = value if np.isfinite(value) else (0.0 if np.isnan(value) else np.sign(value) * largest)
            scaled[entry] = 3.0 * finite + (1e-30 if i == j else 0.0)
        # Cholesky factor [[l00, 0], [l10, l11]] of 3 S; the sigma points add and subtract its columns.
        l00 = np.sqrt(scaled[0])
        l10 = scaled[1] / l00
        l11 = np.sqrt(scaled[2] - l10 * l10)
        offsets = ((0.0, 0.0), (l00, l10), (-l00, -l10), (0.0, l11), (-0.0, -l11))
        for point in range(5):
            entry = point * count + row
            sigma_d1[entry] = d1[row] + offsets[point][0]
            sigma_d2[entry] = d2[row] + offsets[point][1]
            sigma_tx[entry], sigma_rx1[entry], sigma_rx2[entry] = tx[row], rx1[row], rx2[row]
    reason, position, normal, reflection = solve_rows(5 * count, sigma_tx, sigma_rx1, sigma_rx2, sigma_d1, sigma_d2,
                                                      wanted)
    weights = (1.0 / 3.0, 1.0 / 6.0, 1.0 / 6.0, 1.0 / 6.0, 1.0 / 6.0)
    covariance = np.full((5, count, 2, 2), np.nan)
    for model in range(5):
        if not wanted[model]:
            continue
        for row in range(count):
            mean_x = mean_y = 0.0
            for point in range(5):
                mean_x += weights[point] * position[model, point * count + row, 0]
                mean_y += weights[point] * position[model, point * count + row, 1]
            xx = xy = yy = 0.0
            for point in range(5):
                dx = position[model, point * count + row, 0] - mean_x
                dy = position[model, point * count + row, 1] - mean_y
                xx += weights[point] * dx * dx
                xy += weights[point] * dx * dy
                yy += weights[point] * dy * dy
            # The transform already holds 2 m^2 of arc spread along the bias b; add the rest of ARC_MSE.
            bias_x, bias_y = mean_x - position[model, row, 0], mean_y - position[model, row, 1]
            covariance[model, row, 0, 0] = xx + (ARC_MSE - 2.0) * bias_x * bias_x
            covariance[model, row, 0, 1] = covariance[model, row, 1, 0] = xy + (ARC_MSE - 2.0) * bias_x * bias_y
            covariance[model, row, 1, 1] = yy + (ARC_MSE - 2.0) * bias_y * bias_y
    return (reason[:, :count], position[:, :count], normal[:count], reflection[:count], covariance)


@kernel
def localise_rows(tx, rx1, rx2, paths, dz, vertical, sigma_tof, speed, sigma_speed, models):
    """A ping's rows localised with ``models`` (indices into :data:`SOLVERS`, output order), as hypotheses.

    ``tx``, ``rx1``, ``rx2`` (N, 2) m; ``paths`` (N, 2) the measured path lengths
    to each receiver, m, and ``dz`` (N, 2) the transmitter's height over each
    receiver, m; with ``vertical`` each path is first made horizontal
    (:func:`sonar_ring.localise.horizontal_path`) and its noise scaled by ``d / sqrt(d^2 - dz^2)``;
    ``sigma_tof`` s, ``speed`` and ``sigma_speed`` m/s give the paths'
    covariance (:func:`sonar_ring.uncertainty.path_covariance`), which :func:`unscented_models` carries
    to each model's position.

    Returns, for M models by N rows (entry ``m N + n``): ``reason`` (M N,),
    ``position``, ``normal`` (the plane's, towards the sensor) (M N, 2),
    ``covariance`` (M N, 2, 2) and ``segment`` (M N, 2, 2) (the plane's reflection
    points, else the position twice), all 0 where the reason is not OK; the
    rows' path covariance (N, 2, 2); and ``first_order`` (M N,), valid entries whose
    sigma points left the solvable region: their covariance is still to compute, to first order.
    """
    count = paths.shape[0]
    d1, d2 = np.empty(count), np.empty(count)
    covariance_paths = np.empty((count, 2, 2))
    scale = np.ones(2)
    horizontal = np.empty(2)
    for row in range(count):
        for k in range(2):
            horizontal[k] = paths[row, k]
            if vertical:
                horizontal[k] = _horizontal(paths[row, k], dz[row, k])[0]
                scale[k] = paths[row, k] / horizontal[k]
        d1[row], d2[row] = horizontal[0], horizontal[1]
        _path_covariance(d1[row], d2[row], sigma_tof, speed, sigma_speed, covariance_paths[row])
        for i in range(2):
            for j in range(2):
                covariance_paths[row, i, j] = covariance_paths[row, i, j] * scale[i] * scale[j]
    wanted = np.zeros(len(SOLVERS), dtype=np.bool_)
    for model in models:
        wanted[model] = True
    solved_reason, solved_position, plane_normal, reflection, solved_covariance = unscented_models(
        tx, rx1, rx2, d1, d2, covariance_paths, wanted)
    size = len(models) * count
    reason = np.empty(size, dtype=np.uint8)
    position, normal = np.zeros((size, 2)), np.zeros((size, 2))
    covariance, segment = np.zeros((size, 2, 2)), np.zeros((size, 2, 2))
    first_order = np.zeros(size, dtype=np.bool_)
    for index in range(len(models)):
        model = models[index]
        for row in range(count):
            entry = index * count + row
            reason[entry] = solved_reason[model, row]
            if reason[entry] != OK:
                continue
            position[entry] = solved_position[model, row]
            covariance[entry] = solved_covariance[model, row]
            first_order[entry] = not np.all(np.isfinite(covariance[entry]))
            if model == PLANE_SOLVER:
                normal[entry, 0], normal[entry, 1] = -plane_normal[row, 0], -plane_normal[row, 1]
                segment[entry] = reflection[row]
            else:
                segment[entry, 0] = segment[entry, 1] = position[entry]
    return reason, position, normal, covariance, segment, covariance_paths, first_order


@kernel
def localise_ping_rows(transmitters, receivers, groups, transmitter, group, tof, speed, vertical, sigma_tof,
                       sigma_speed, models, model_class):
    """:func:`localise_rows` of a ping's rows, from the layout's transducers, as the fields of its hypotheses.

    Layout (:class:`sonar_ring.geometry.Layout`): ``transmitters`` (T, 3) and
    ``receivers`` (R, 3), m, sensor frame; ``groups`` (G, 2) each group's
    receivers.  Per echo row: its ``transmitter`` and ``group`` indices (N,)
    and ``tof`` (N, 2), s; ``speed`` m/s makes the paths ``speed * tof``.
    ``models`` as for :func:`localise_rows`, ``model_class`` (M,) their landmark classes.

    Returns, per entry (M N,), the fields of :class:`sonar_ring.landmarks.Landmarks`
    in its order -- ``landmark_class``, ``position``, ``normal``, ``covariance``,
    ``confidence`` (0), ``segment``, ``observations`` (1), ``group``, ``echo`` (the
    row), ``valid`` and ``reason`` -- then the entries whose covariance is still to
    compute (``first_order`` of :func:`localise_rows`, ascending) and the rows' path
    covariance (N, 2, 2).  The arrays' shapes are the caller's to check; an index
    outside the layout raises ``ValueError``.
    """
    count = group.size
    tx, rx1, rx2 = np.empty((count, 2)), np.empty((count, 2)), np.empty((count, 2))
    paths, dz = np.empty((count, 2)), np.empty((count, 2))
    for row in range(count):
        # Checked here: compiled indexing does not check bounds.
        if not (0 <= group[row] < groups.shape[0] and 0 <= transmitter[row] < transmitters.shape[0]):
            raise ValueError("localise_ping: an echo row names a group or transmitter the layout does not have")
        source = transmitters[transmitter[row]]
        first, second = receivers[groups[group[row], 0]], receivers[groups[group[row], 1]]
        for axis in range(2):
            tx[row, axis], rx1[row, axis], rx2[row, axis] = source[axis], first[axis], second[axis]
        paths[row, 0], paths[row, 1] = speed * tof[row, 0], speed * tof[row, 1]
        dz[row, 0], dz[row, 1] = source[2] - first[2], source[2] - second[2]
    reason, position, normal, covariance, segment, covariance_paths, first_order = localise_rows(
        tx, rx1, rx2, paths, dz, vertical, sigma_tof, speed, sigma_speed, models)
    size = len(models) * count
    landmark_class = np.empty(size, dtype=np.uint8)
    entry_group = np.empty(size, dtype=np.uint16)
    echo = np.empty(size, dtype=np.uint32)
    for index in range(len(models)):
        for row in range(count):
            landmark_class[index * count + row] = model_class[index]
            entry_group[index * count + row] = group[row]
            echo[index * count + row] = row
    return (landmark_class, position, normal, covariance, np.zeros(size, dtype=np.float32), segment,
            np.ones(size, dtype=np.uint32), entry_group, echo, reason == OK, reason, np.flatnonzero(first_order),
            covariance_paths)


# --------------------------------------------------------------------------- vertical correction and paths' covariance

@kernel
def horizontal_rows(d, dz):
    """:func:`sonar_ring.localise.horizontal_path` of each entry of flat arrays ``d``, ``dz`` (N,), m: values, reasons.

    Unchecked, for callers that have validated their paths: writable float64
    arrays of one size (a read-only one is another type to numba).  The value
    is NaN where the reason is not OK.
    """
    value = np.empty(d.size)
    reason = np.empty(d.size, dtype=np.int8)
    for entry in range(d.size):
        value[entry], reason[entry] = _horizontal(d[entry], dz[entry])
    return value, reason


@kernel
def _horizontal(d, dz):
    """``sqrt(d^2 - dz^2)`` as ``sqrt((d - |dz|)(d + |dz|))`` and its reason code; NaN unless OK."""
    height = abs(dz)
    if not (abs(d) <= MAX_LENGTH and height <= MAX_LENGTH):
        return np.nan, NOT_FINITE
    if not d > 0:
        return np.nan, NEGATIVE
    if d < height:
        return np.nan, BELOW_HEIGHT
    return np.sqrt((d - height) * (d + height)), OK


@kernel
def path_covariance_rows(d1, d2, sigma_tof, speed, sigma_speed):
    """:func:`_path_covariance` of each entry of flat float64 arrays (N,): sigma_tof s, speed and sigma_speed m/s.

    Returns (N, 2, 2), m^2 (:func:`sonar_ring.uncertainty.path_covariance` checks the arguments).
    """
    covariance = np.empty((d1.size, 2, 2))
    for entry in range(d1.size):
        _path_covariance(d1[entry], d2[entry], sigma_tof[entry], speed[entry], sigma_speed[entry], covariance[entry])
    return covariance


@kernel
def _path_covariance(d1, d2, sigma_tof, speed, sigma_speed, out):
    """Write the paths' covariance ``(c sigma_t)^2 I + (sigma_c / c)^2 d d^T`` into ``out`` (2, 2), m^2."""
    independent = (speed * sigma_tof) ** 2
    relative = (sigma_speed / speed) ** 2
    out[0, 0] = independent + relative * d1 * d1
    out[0, 1] = out[1, 0] = relative * d1 * d2
    out[1, 1] = independent + relative * d2 * d2


# --------------------------------------------------------------------------- implied paths, uncertainty, point models

@kernel
def _reflector_path(tx_x, tx_y, r_x, r_y, p_x, p_y, is_edge):
    """The horizontal path ``T -> reflector -> R`` of a landmark at ``p``, m.

    :func:`sonar_ring.localise.reflector_paths` gives the model: an edge's own
    path, else the virtual image's ``|2p - T - R|``.
    """
    if is_edge:
        return (np.sqrt((p_x - tx_x) * (p_x - tx_x) + (p_y - tx_y) * (p_y - tx_y))
                + np.sqrt((p_x - r_x) * (p_x - r_x) + (p_y - r_y) * (p_y - r_y)))
    image_x, image_y = 2.0 * p_x - tx_x, 2.0 * p_y - tx_y
    return np.sqrt((image_x - r_x) * (image_x - r_x) + (image_y - r_y) * (image_y - r_y))


@kernel
def reflector_path_rows(tx, rx, position, is_edge):
    """:func:`_reflector_path` of L landmarks to K receivers: tx (L, 2), rx (L, K, 2), position (L, 2), m; (L, K)."""
    paths = np.empty((rx.shape[0], rx.shape[1]))
    for n in range(rx.shape[0]):
        for k in range(rx.shape[1]):
            paths[n, k] = _reflector_path(tx[n, 0], tx[n, 1], rx[n, k, 0], rx[n, k, 1], position[n, 0],
                                          position[n, 1], is_edge[n])
    return paths


@kernel
def grouped_path_rows(tx, rx, height_offset, group, position, is_edge):
    """The 3-D paths each of L landmarks implies for every receiver of its group, (L, K), m.

    :func:`_reflector_path` from the group's first transmitter ``tx[group, 0]`` (G, M, 2) to its receivers
    ``rx[group]`` (G, K, 2), with the height offsets ``height_offset[group, 0]`` (G, M, K), m: positions (L, 2), m.
    """
    paths = np.empty((position.shape[0], rx.shape[1]))
    for n in range(position.shape[0]):
        g = group[n]
        for k in range(rx.shape[1]):
            horizontal = _reflector_path(tx[g, 0, 0], tx[g, 0, 1], rx[g, k, 0], rx[g, k, 1], position[n, 0],
                                         position[n, 1], is_edge[n])
            paths[n, k] = np.sqrt(horizontal ** 2 + height_offset[g, 0, k] ** 2)
    return paths


@kernel
def _unit(x, y):
    """``(x, y)`` over its length ``sqrt(x^2 + y^2)`` (no overflow at sensor scales)."""
    length = np.sqrt(x * x + y * y)
    return x / length, y / length


@kernel
def _jacobian(model, tx_x, tx_y, r1_x, r1_y, r2_x, r2_y, p_x, p_y):
    """``d position / d (d1, d2)`` of an estimate of ``model`` (index into :data:`SOLVERS`) at ``p``: j00 j01 j10 j11.

    The equations are :func:`sonar_ring.uncertainty.position_jacobian`'s; +inf
    where the 2 x 2 system is singular (an echo on the receivers' line).
    """
    if model == ON_AXIS_SOLVER:
        u_x, u_y = _unit(r2_x - r1_x, r2_y - r1_y)
        towards_x, towards_y = _unit(p_x - tx_x, p_y - tx_y)
        rate = 0.5 / (1.0 + (towards_x * -u_y + towards_y * u_x))
        return rate * -u_y, rate * -u_y, rate * u_x, rate * u_x
    if model == EDGE_SOLVER:
        towards_x, towards_y = _unit(p_x - tx_x, p_y - tx_y)
        a, b = _unit(p_x - r1_x, p_y - r1_y)
        c, d = _unit(p_x - r2_x, p_y - r2_y)
        a, b, c, d = towards_x + a, towards_y + b, towards_x + c, towards_y + d
        scale = 1.0
    else:
        image_x, image_y = (p_x, p_y) if model == VIRTUAL_IMAGE_SOLVER else (2.0 * p_x - tx_x, 2.0 * p_y - tx_y)
        a, b = _unit(image_x - r1_x, image_y - r1_y)
        c, d = _unit(image_x - r2_x, image_y - r2_y)
        scale = 1.0 if model == VIRTUAL_IMAGE_SOLVER else 0.5
    # The rows [[a, b], [c, d]] are the derivatives of the paths by the position: J is their inverse.
    determinant = a * d - b * c
    if determinant == 0:
        return np.inf, np.inf, np.inf, np.inf
    return d / determinant * scale, -b / determinant * scale, -c / determinant * scale, a / determinant * scale


@kernel
def jacobian_rows(model, tx, rx1, rx2, position):
    """:func:`_jacobian` of N entries of flat float64 arrays (N, 2), m: (N, 2, 2), ``J[n, i, k] = d p_i / d d_k``."""
    jacobian = np.empty((position.shape[0], 2, 2))
    for n in range(position.shape[0]):
        (jacobian[n, 0, 0], jacobian[n, 0, 1], jacobian[n, 1, 0], jacobian[n, 1, 1]) = _jacobian(
            model, tx[n, 0], tx[n, 1], rx1[n, 0], rx1[n, 1], rx2[n, 0], rx2[n, 1], position[n, 0], position[n, 1])
    return jacobian


@kernel
def _carry(j, s, out):
    """``J S J^T`` of 2 x 2 arrays into ``out``."""
    for i in range(2):
        for k in range(2):
            out[i, k] = (j[i, 0] * (s[0, 0] * j[k, 0] + s[0, 1] * j[k, 1])
                         + j[i, 1] * (s[1, 0] * j[k, 0] + s[1, 1] * j[k, 1]))


ARC_SPREAD = 0.75
"""The sag's variance ``s^4 / (2 r^2)`` and squared mean ``s^4 / (4 r^2)`` in :func:`arc_spread`'s units: what a
pair's sighting carries (its along-sight error is the sag's)."""


@kernel
def arc_spread(p_x, p_y, centre_x, centre_y, covariance, factor):
    """Add to ``covariance`` (2, 2) ``factor s^4 / r^2`` along the line of sight: a point's sag on an arc.

    A point sighting lies on an arc of radius ``r`` about ``centre`` (a
    pair's two paths: the middle of the emitter and the pair's receivers):
    an error ``a`` across the line of sight (variance ``s^2``, from
    ``covariance``; a large fraction of a degree) also moves the point
    ``a^2 / (2 r)`` *along* it, which the first-order covariance (a tenth of a
    millimetre along the line of sight) does not hold.  A pair's sighting takes
    :data:`ARC_SPREAD`: without it the model that is true fails its own
    chi-square over a pass of a few metres.
    """
    sight_x, sight_y = p_x - centre_x, p_y - centre_y
    radius = np.sqrt(sight_x * sight_x + sight_y * sight_y)
    if not radius > 0:
        return
    along_x, along_y = sight_x / radius, sight_y / radius
    across_x, across_y = -along_y, along_x
    across_variance = (across_x * (covariance[0, 0] * across_x + covariance[0, 1] * across_y)
                       + across_y * (covariance[1, 0] * across_x + covariance[1, 1] * across_y))
    spread = factor * across_variance ** 2 / radius ** 2
    covariance[0, 0] += spread * along_x * along_x
    covariance[0, 1] += spread * along_x * along_y
    covariance[1, 0] += spread * along_y * along_x
    covariance[1, 1] += spread * along_y * along_y


@kernel
def arc_spread_rows(points, centres, covariance, factor):
    """:func:`arc_spread` of each of N points (N, 2) about its centre (N, 2), into ``covariance`` (N, 2, 2)."""
    for n in range(points.shape[0]):
        arc_spread(points[n, 0], points[n, 1], centres[n, 0], centres[n, 1], covariance[n], factor)


@kernel
def _inverse(m, out):
    """The inverse of a 2 x 2 array into ``out``; False (``out`` untouched) where it is singular."""
    determinant = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    if not abs(determinant) > 0:
        return False
    out[0, 0], out[0, 1] = m[1, 1] / determinant, -m[0, 1] / determinant
    out[1, 0], out[1, 1] = -m[1, 0] / determinant, m[0, 0] / determinant
    return True


@kernel
def point_model_rows(chosen, group, transmitters, receivers, position, is_edge, undecided, covariance):
    """Both point models of L sightings of a single-emitter ring: :func:`sonar_ring.curvature.point_models`.

    Parameters
    ----------
    chosen : ndarray of bool, shape (L,)
        The sightings to solve (the others get none).
    group : ndarray of int, shape (L,)
        Each sighting's receiver group.
    transmitters, receivers : ndarray, shape (G, M, 2) and (G, 2, 2)
        The ring's emitters (the first of each group's) and receiver pairs, m (:class:`~sonar_ring.geometry.Plan`).
    position : ndarray, shape (L, 2)
        Its landmark's position, placed by the edge model where ``is_edge``
        (L,), else by the virtual image's (a corner or an ``undecided`` (L,)
        point), m.
    covariance : ndarray, shape (L, 2, 2)
        The landmark's covariance, m^2 (an undecided one's holds the models'
        discrepancy ``g g^T``, removed here where what remains is a covariance).

    Returns
    -------
    corner, edge : ndarray, shape (L, 2)
        Both models solved from the paths the landmark implies, m; NaN where not ``valid``.
    corner_covariance, edge_covariance : ndarray, shape (L, 2, 2)
        The paths' covariance (the landmark's through the inverse of its
        model's Jacobian) carried through each model's, plus the arc's spread
        (:func:`arc_spread`), m^2; NaN where not valid.
    separation_noise : ndarray, shape (L,)
        ``tr(W D)`` (:class:`sonar_ring.curvature.PointModels`); 0 where not valid.
    valid : ndarray of bool, shape (L,)
        Both models solved, both Jacobians finite, the landmark's own and the corner model's covariance invertible.
    """
    count = position.shape[0]
    corner = np.full((count, 2), np.nan)
    edge = np.full((count, 2), np.nan)
    corner_covariance = np.full((count, 2, 2), np.nan)
    edge_covariance = np.full((count, 2, 2), np.nan)
    separation_noise = np.zeros(count)
    valid = np.zeros(count, dtype=np.bool_)
    corner_jacobian, edge_jacobian, own_inverse = np.empty((2, 2)), np.empty((2, 2)), np.empty((2, 2))
    gap_jacobian, paths, measured, gap, weight = (np.empty((2, 2)), np.empty((2, 2)), np.empty((2, 2)),
                                                  np.empty((2, 2)), np.empty((2, 2)))
    for n in range(count):
        if not chosen[n]:
            continue
        tx_x, tx_y = transmitters[group[n], 0, 0], transmitters[group[n], 0, 1]
        p_x, p_y = position[n, 0], position[n, 1]
        r1_x, r1_y = receivers[group[n], 0, 0], receivers[group[n], 0, 1]
        r2_x, r2_y = receivers[group[n], 1, 0], receivers[group[n], 1, 1]
        # The paths the landmark implies, solved by both models.
        d1 = _reflector_path(tx_x, tx_y, r1_x, r1_y, p_x, p_y, is_edge[n])
        d2 = _reflector_path(tx_x, tx_y, r2_x, r2_y, p_x, p_y, is_edge[n])
        separation, u_x, u_y, n_x, n_y, c_x, c_y = _pair_frame(r1_x, r1_y, r2_x, r2_y)
        common, apart, too_short = _checked(tx_x, tx_y, r1_x, r1_y, r2_x, r2_y, d1, d2, separation)
        image_reason, image_x, image_y = _virtual_image(d1, d2, separation, u_x, u_y, n_x, n_y, c_x, c_y, common,
                                                        apart, too_short)
        corner_reason, corner_x, corner_y = _corner(tx_x, tx_y, n_x, n_y, c_x, c_y, image_reason, image_x, image_y)
        edge_reason, edge_x, edge_y = _edge(tx_x, tx_y, r1_x, r1_y, r2_x, r2_y, d1, d2, separation, u_x, u_y, n_x,
                                            n_y, c_x, c_y, common, apart, too_short)
        if corner_reason != OK or edge_reason != OK:
            continue
        (corner_jacobian[0, 0], corner_jacobian[0, 1], corner_jacobian[1, 0], corner_jacobian[1, 1]) = _jacobian(
            CORNER_SOLVER, tx_x, tx_y, r1_x, r1_y, r2_x, r2_y, corner_x, corner_y)
        (edge_jacobian[0, 0], edge_jacobian[0, 1], edge_jacobian[1, 0], edge_jacobian[1, 1]) = _jacobian(
            EDGE_SOLVER, tx_x, tx_y, r1_x, r1_y, r2_x, r2_y, edge_x, edge_y)
        if not (np.isfinite(corner_jacobian).all() and np.isfinite(edge_jacobian).all()):
            continue
        if not _inverse(edge_jacobian if is_edge[n] else corner_jacobian, own_inverse):
            continue
        # An undecided landmark's covariance less the models' discrepancy, where what remains is a covariance.
        gap_x, gap_y = edge_x - corner_x, edge_y - corner_y
        measured[0, 0], measured[0, 1] = covariance[n, 0, 0] - gap_x * gap_x, covariance[n, 0, 1] - gap_x * gap_y
        measured[1, 0], measured[1, 1] = covariance[n, 1, 0] - gap_y * gap_x, covariance[n, 1, 1] - gap_y * gap_y
        if not (undecided[n] and measured[0, 0] > 0
                and measured[0, 0] * measured[1, 1] - measured[0, 1] ** 2 > 0):
            measured[:, :] = covariance[n]
        _carry(own_inverse, measured, paths)
        centre_x, centre_y = 0.5 * (tx_x + 0.5 * (r1_x + r2_x)), 0.5 * (tx_y + 0.5 * (r1_y + r2_y))
        _carry(corner_jacobian, paths, corner_covariance[n])
        arc_spread(corner_x, corner_y, centre_x, centre_y, corner_covariance[n], ARC_SPREAD)
        _carry(edge_jacobian, paths, edge_covariance[n])
        arc_spread(edge_x, edge_y, centre_x, centre_y, edge_covariance[n], ARC_SPREAD)
        if not _inverse(corner_covariance[n], weight):
            corner_covariance[n], edge_covariance[n] = np.nan, np.nan
            continue
        gap_jacobian[:, :] = edge_jacobian - corner_jacobian
        _carry(gap_jacobian, paths, gap)
        separation_noise[n] = (weight[0, 0] * gap[0, 0] + weight[0, 1] * gap[1, 0] + weight[1, 0] * gap[0, 1]
                               + weight[1, 1] * gap[1, 1])
        corner[n, 0], corner[n, 1], edge[n, 0], edge[n, 1] = corner_x, corner_y, edge_x, edge_y
        valid[n] = True
    return corner, edge, corner_covariance, edge_covariance, separation_noise, valid
