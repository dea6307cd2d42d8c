"""Localisation core: from measured path lengths to landmarks.

Every sensor of the package (Browne's single-emitter ring, Barshan & Kuc's
transmit/receive pairs, Kreczmer's triad) reduces to one 2-D problem: a
transmitter ``T`` and two receivers ``R1``, ``R2`` at known positions, and two
measured path lengths ``d_n = c * tof_n`` from ``T`` via the reflector to
``R_n``.  This module solves it for the three reflector models of the papers:

* **plane** and **corner** -- through the *virtual image* ``T'`` of the
  transmitter, the point at distance ``d1`` from ``R1`` and ``d2`` from ``R2``.
  A plane is the perpendicular bisector of ``T T'`` (foot point
  ``G = (T + T') / 2``, normal along ``T' - T``); a corner is the point ``G``.
* **edge** -- a point ``P`` with ``|P - T| + |P - R_n| = d_n`` (two ellipses
  with the common focus ``T``), which has no virtual image.

Conventions
-----------
* Positions are ``(..., 2)`` arrays in metres, all in one frame (usually the
  sensor frame of REP 103: x forward, y left); path lengths are ``(...)``
  arrays in metres.  Every function broadcasts its arguments over any leading
  shape and computes in float64 (float32 inputs are promoted).
* Receiver order matters: ``rx1`` is the counter-clockwise (left) receiver of
  the group (layout column 0, Browne's R1).  The *front* of the receivers is the
  direction ``n`` obtained by turning ``rx1 - rx2`` 90 degrees clockwise; echoes
  are taken to arrive from that half-plane, so the virtual image and edges are
  placed in front of the line through the receivers.
* The transmitter may be anywhere: behind the receivers (Browne's ring centre),
  on their line (Barshan & Kuc, where ``tx`` is ``rx1`` itself; Kreczmer), or
  elsewhere.
* Bad *data* never raises: each result carries ``valid`` (bool, ``(...)``) and
  ``reason`` (int8, ``(...)``, one of the codes below), and invalid entries hold
  NaN.  Valid entries are never NaN.  Only wrong shapes or non-numeric types
  raise :class:`ValueError`.

Reason codes
------------
``OK`` 0, ``NOT_FINITE`` 1 (NaN, infinite, or beyond :data:`MAX_LENGTH` = 1e6 m), ``DEGENERATE`` 2 (coincident
receivers, or a singular configuration), ``NEGATIVE`` 3 (a path length <= 0),
``NO_INTERSECTION`` 4 (``|d2 - d1| > D`` or ``d1 + d2 < D``: the circles or
ellipses do not meet), ``TOO_SHORT`` 5 (``d_n < |T - R_n|``: shorter than the
direct path, which no reflector can produce), ``BELOW_HEIGHT`` 6 (``d < |dz|``
in the vertical correction), ``BEHIND`` 7 (the landmark is not in front of the
receivers), ``AMBIGUOUS`` 8 (two edge solutions in front of the receivers),
``NONE_VALID`` 9 (fusion without a single usable input).  An entry carries the
code of the first check it fails: the input checks in the order NOT_FINITE,
DEGENERATE (coincident receivers), NEGATIVE, NO_INTERSECTION, TOO_SHORT, then
the model's own (DEGENERATE, NO_INTERSECTION, BEHIND, AMBIGUOUS).

Numerics
--------
The formulas are arranged so that no step subtracts nearly equal rounded
quantities: the virtual image uses the along-baseline offset
``(d1 - d2)(d1 + d2) / (2D)`` and Heron's product
``(D + d2 - d1)(D - d2 + d1)(d1 + d2 - D)(d1 + d2 + D)`` for its height, so
``d1 ~ d2`` at long range and bearings near +-90 degrees stay accurate to a few
ulps of the inputs; the edge quadratic is solved in the cancellation-free
(citardauq) form.  See ``test/test_localise_hard_cases.py`` for the evidence.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

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
NONE_VALID = 9

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
    NONE_VALID: "no valid input to fuse",
}
"""Human-readable meaning of each reason code."""


# --------------------------------------------------------------------------- results

@dataclass(frozen=True, eq=False)
class ScalarEstimate:
    """A scalar per entry (a bearing, a corrected path length).

    Attributes
    ----------
    value : ndarray of float64, shape (...)
        The estimate (rad for bearings, m for lengths); NaN where not valid.
    valid : ndarray of bool, shape (...)
    reason : ndarray of int8, shape (...)
        One of the reason codes of this module (``OK`` where valid).
    """

    value: np.ndarray
    valid: np.ndarray
    reason: np.ndarray


@dataclass(frozen=True, eq=False)
class PointEstimate:
    """A point landmark per entry (virtual image, corner, edge, on-axis echo).

    Attributes
    ----------
    position : ndarray of float64, shape (..., 2)
        Position in the frame of the inputs, m; NaN where not valid.
    valid : ndarray of bool, shape (...)
    reason : ndarray of int8, shape (...)
        One of the reason codes of this module (``OK`` where valid).
    model : str
        ``"virtual_image"``, ``"corner"``, ``"edge"``, ``"plane"`` or ``"on_axis"``;
        :func:`position_jacobian` uses it.
    """

    position: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    model: str


@dataclass(frozen=True, eq=False)
class PlaneEstimate(PointEstimate):
    """A plane per entry: its foot point, normal and the two reflection points.

    Attributes
    ----------
    position : ndarray of float64, shape (..., 2)
        Foot point ``G = (T + T') / 2`` of the perpendicular from the transmitter
        onto the plane, m.
    normal : ndarray of float64, shape (..., 2)
        Unit normal along ``T' - T``: from the transmitter's side into the
        reflector (away from the sensor).
    reflection_points : ndarray of float64, shape (..., 2, 2)
        ``[..., n, :]`` is the specular point seen by receiver n+1 (Browne's X
        for n = 0): where the segment ``R_n T'`` crosses the plane, m.
    """

    normal: np.ndarray
    reflection_points: np.ndarray


@dataclass(frozen=True, eq=False)
class FusedScalar:
    """Inverse-variance fusion of scalars (Barshan & Kuc eq 41).

    Attributes
    ----------
    value, variance : ndarray of float64, shape (...)
    weights : ndarray of float64, shape (..., G)
        Eq 41 weights, zero for invalid inputs.
    valid : ndarray of bool, shape (...)
    reason : ndarray of int8, shape (...)
    """

    value: np.ndarray
    variance: np.ndarray
    weights: np.ndarray
    valid: np.ndarray
    reason: np.ndarray


@dataclass(frozen=True, eq=False)
class FusedPoint:
    """Information-weighted fusion of 2-D positions (eq 41 for covariance matrices).

    Attributes
    ----------
    position : ndarray of float64, shape (..., 2)
    covariance : ndarray of float64, shape (..., 2, 2)
    valid : ndarray of bool, shape (...)
    reason : ndarray of int8, shape (...)
    """

    position: np.ndarray
    covariance: np.ndarray
    valid: np.ndarray
    reason: np.ndarray


# --------------------------------------------------------------------------- input handling

def _quiet(function):
    """Run ``function`` without floating-point warnings.

    Entries that divide by zero or go invalid are reported through the reason
    codes (and hold NaN), so numpy's warnings about them would only be noise.
    """

    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        with np.errstate(all="ignore"):
            return function(*args, **kwargs)

    return wrapper


def _real_array(name: str, value, caller: str) -> np.ndarray:
    array = np.asarray(value)
    if array.dtype.kind not in "iuf":
        raise ValueError(f"{caller}: '{name}' must be real numbers, got dtype {array.dtype}")
    return array.astype(np.float64, copy=False)


def _points(name: str, value, caller: str) -> np.ndarray:
    array = _real_array(name, value, caller)
    if array.ndim == 0 or array.shape[-1] != 2:
        raise ValueError(f"{caller}: '{name}' must be (..., 2) positions (x, y) in m, got shape {array.shape}")
    return array


def _shape(caller: str, **arrays) -> tuple:
    """Broadcast shape of the entries; points contribute their leading shape."""
    shapes = {name: a.shape[:-1] if name in ("tx", "rx1", "rx2") else a.shape
              for name, a in arrays.items()}
    try:
        return np.broadcast_shapes(*shapes.values())
    except ValueError:
        listing = ", ".join(f"{name} {shape}" for name, shape in shapes.items())
        raise ValueError(f"{caller}: leading shapes do not broadcast: {listing}") from None


def _bounded(values: np.ndarray) -> np.ndarray:
    """Finite and at most :data:`MAX_LENGTH` in magnitude (False for NaN)."""
    return np.abs(values) <= MAX_LENGTH


def _flat_copies(shape: tuple, *arrays) -> list[np.ndarray]:
    """Each array broadcast to ``shape``, flattened, as a new (writable) float64 array.

    Writable always: numba compiles a read-only array as another type, so a
    view of a message's buffer would make the kernel compile again at its first ping.
    """
    return [np.array(np.broadcast_to(array, shape), dtype=np.float64).ravel() for array in arrays]


def _flag(reason: np.ndarray, mask, code: int) -> None:
    """Set ``code`` where ``mask`` (broadcastable to ``reason``) holds and no earlier check has failed."""
    reason[(reason == OK) & mask] = code


def _finish(reason: np.ndarray, *outputs):
    """Validity from the reason codes, and full-shape copies of the outputs with NaN where not valid.

    ``outputs`` are ``(array, core)`` pairs, ``core`` the number of trailing
    dimensions of one entry (0 for scalars, 1 for points, 2 for matrices).
    """
    valid = reason == OK
    results = [np.where(valid.reshape(valid.shape + (1,) * core), value, np.nan) for value, core in outputs]
    return valid, results


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]


def _norm(a: np.ndarray) -> np.ndarray:
    # sqrt of the sum of squares: as accurate as hypot here (no overflow at sensor scales) and 3x faster
    return np.sqrt(a[..., 0] * a[..., 0] + a[..., 1] * a[..., 1])


@dataclass(frozen=True)
class _Receivers:
    """The receivers' frame: mid-point, baseline direction u (R1 to R2), front n."""

    centre: np.ndarray
    u: np.ndarray
    n: np.ndarray
    separation: np.ndarray


def _receivers(rx1: np.ndarray, rx2: np.ndarray) -> _Receivers:
    baseline = rx2 - rx1
    separation = _norm(baseline)
    u = baseline / separation[..., None]
    # Turning u (R1 -> R2) counter-clockwise by 90 deg is turning R1 - R2 clockwise: the front.
    n = np.stack([-u[..., 1], u[..., 0]], axis=-1)
    return _Receivers(0.5 * (rx1 + rx2), u, n, separation)


def _flat_inputs(caller, tx, rx1, rx2, d1, d2):
    """Validate types and shapes; the inputs broadcast to their common shape, flattened, and that shape.

    Returns ``shape`` and ``tx``, ``rx1``, ``rx2`` (N, 2), ``d1``, ``d2`` (N,), C-contiguous float64.
    """
    tx = _points("tx", tx, caller)
    rx1 = _points("rx1", rx1, caller)
    rx2 = _points("rx2", rx2, caller)
    d1 = _real_array("d1", d1, caller)
    d2 = _real_array("d2", d2, caller)
    shape = _shape(caller, tx=tx, rx1=rx1, rx2=rx2, d1=d1, d2=d2)
    count = math.prod(shape)

    def flat(array, core):
        return np.ascontiguousarray(np.broadcast_to(array, shape + core).reshape((count,) + core))

    return shape, flat(tx, (2,)), flat(rx1, (2,)), flat(rx2, (2,)), flat(d1, ()), flat(d2, ())


SOLVERS = ("virtual_image", "plane", "corner", "edge", "on_axis")
"""The models :func:`solve_rows` computes, in the order of its ``wanted`` flags and outputs."""
PLANE_SOLVER = SOLVERS.index("plane")
NEAR_TRANSMITTER = 0.1
"""An edge nearer the transmitter than this share of its shorter path gets its position polished (:func:`edge`)."""


@kernel
def solve_rows(tx, rx1, rx2, d1, d2, wanted):
    """The models of :data:`SOLVERS` flagged in ``wanted`` (5,) for N entries: one loop, each entry alone.

    Inputs as :func:`_flat_inputs` gives them.  Returns ``reason`` (5, N) int8,
    ``position`` (5, N, 2), and the plane's ``normal`` (N, 2) and
    ``reflection_points`` (N, 2, 2); NaN wherever the entry is not valid, and
    unspecified for models not wanted.  An entry carries the code of the first check it fails,
    in the order of the module docstring.
    """
    count = d1.size
    reason = np.zeros((5, count), dtype=np.int8)
    # Only what is wanted is filled (NaN until an entry turns out valid); the rest is never read.
    position = np.empty((5, count, 2))
    for model in range(5):
        if wanted[model]:
            position[model] = np.nan
    normal = np.full((count, 2), np.nan) if wanted[1] else np.empty((count, 2))
    reflection = np.full((count, 2, 2), np.nan) if wanted[1] else np.empty((count, 2, 2))
    for k in range(count):
        tx_x, tx_y, r1_x, r1_y, r2_x, r2_y = tx[k, 0], tx[k, 1], rx1[k, 0], rx1[k, 1], rx2[k, 0], rx2[k, 1]
        a, b = d1[k], d2[k]
        # The receivers' frame: mid-point c, baseline direction u (R1 to R2), front n (u turned
        # counter-clockwise, which is R1 - R2 turned clockwise).
        base_x, base_y = r2_x - r1_x, r2_y - r1_y
        separation = np.sqrt(base_x * base_x + base_y * base_y)
        u_x, u_y = base_x / separation, base_y / separation
        n_x, n_y = -u_y, u_x
        c_x, c_y = 0.5 * (r1_x + r2_x), 0.5 * (r1_y + r2_y)
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
        total = a + b
        apart = separation + difference < 0 or separation - difference < 0
        # A reflected path is never shorter than the direct one (triangle inequality).
        to_r1_x, to_r1_y, to_r2_x, to_r2_y = r1_x - tx_x, r1_y - tx_y, r2_x - tx_x, r2_y - tx_y
        too_short = (a < np.sqrt(to_r1_x * to_r1_x + to_r1_y * to_r1_y)
                     or b < np.sqrt(to_r2_x * to_r2_x + to_r2_y * to_r2_y))

        if wanted[0] or wanted[1] or wanted[2]:
            image_reason = common
            if image_reason == OK and (apart or total < separation):
                image_reason = NO_INTERSECTION
            if image_reason == OK and too_short:
                image_reason = TOO_SHORT
            along = -difference * total / (2.0 * separation)
            # Heron: the height over the baseline is 2 * area / D, every factor formed from inputs directly.
            heron = (separation + difference) * (separation - difference) * (total - separation) * (
                total + separation)
            height = np.sqrt(heron) / (2.0 * separation)
            image_x = c_x + along * u_x + height * n_x
            image_y = c_y + along * u_y + height * n_y
            reason[0, k] = image_reason
            if image_reason == OK:
                position[0, k, 0], position[0, k, 1] = image_x, image_y
            # Plane: the perpendicular bisector of T T'.
            axis_x, axis_y = image_x - tx_x, image_y - tx_y
            length = np.sqrt(axis_x * axis_x + axis_y * axis_y)
            plane_reason = image_reason
            if plane_reason == OK and not length > 0:
                plane_reason = DEGENERATE
            reason[1, k] = plane_reason
            if wanted[1] and plane_reason == OK:
                normal_x, normal_y = axis_x / length, axis_y / length
                normal[k, 0], normal[k, 1] = normal_x, normal_y
                position[1, k, 0], position[1, k, 1] = tx_x + 0.5 * axis_x, tx_y + 0.5 * axis_y
                for receiver in range(2):
                    r_x, r_y = (r1_x, r1_y) if receiver == 0 else (r2_x, r2_y)
                    # Distance of the receiver from the plane over that of T' from it: where R_n T' crosses.
                    depth = 0.5 * length - ((r_x - tx_x) * normal_x + (r_y - tx_y) * normal_y)
                    fraction = depth / (depth + 0.5 * length)
                    reflection[k, receiver, 0] = r_x + fraction * (image_x - r_x)
                    reflection[k, receiver, 1] = r_y + fraction * (image_y - r_y)
            # Corner: G = (T + T') / 2, in front of the receivers.
            corner_x, corner_y = 0.5 * (tx_x + image_x), 0.5 * (tx_y + image_y)
            corner_reason = image_reason
            if corner_reason == OK and not (corner_x - c_x) * n_x + (corner_y - c_y) * n_y > 0:
                corner_reason = BEHIND
            reason[2, k] = corner_reason
            if wanted[2] and corner_reason == OK:
                position[2, k, 0], position[2, k, 1] = corner_x, corner_y

        if wanted[3]:
            edge_reason = common
            if edge_reason == OK and apart:
                edge_reason = NO_INTERSECTION
            if edge_reason == OK and too_short:
                edge_reason = TOO_SHORT
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
            if edge_reason == OK and not mu1 > 0:
                edge_reason = DEGENERATE
            if edge_reason == OK and not discriminant >= 0:
                edge_reason = NO_INTERSECTION
            if edge_reason == OK and not (first_ahead or second_ahead):
                edge_reason = BEHIND
            if edge_reason == OK and first_ahead and second_ahead:
                edge_reason = AMBIGUOUS
            reason[3, k] = edge_reason
            if edge_reason == OK:
                normal_offset, path_k = (first, k_first) if first_ahead else (second, k_second)
                along = difference * (2.0 * path_k - total) / (2.0 * separation)
                p_x = c_x + along * u_x + normal_offset * n_x
                p_y = c_y + along * u_y + normal_offset * n_y
                # k comes from mu0, a difference of squared lengths that cancels as the edge nears the
                # transmitter (k << d_n, by about d_n / k): there one Newton step on the path equations.
                if path_k < NEAR_TRANSMITTER * shortest:
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
                    # Kept only where it brings the paths closer: near a tangency or at T the step is no better.
                    new_x, new_y = p_x - step_x, p_y - step_y
                    new_t = np.sqrt((new_x - tx_x) ** 2 + (new_y - tx_y) ** 2)
                    new_1 = new_t + np.sqrt((new_x - r1_x) ** 2 + (new_y - r1_y) ** 2) - a
                    new_2 = new_t + np.sqrt((new_x - r2_x) ** 2 + (new_y - r2_y) ** 2) - b
                    if max(abs(new_1), abs(new_2)) < max(abs(residual_1), abs(residual_2)):
                        p_x, p_y = new_x, new_y
                position[3, k, 0], position[3, k, 1] = p_x, p_y

        if wanted[4]:
            on_axis_reason = common
            mean = 0.5 * total
            offset_x, offset_y = c_x - tx_x, c_y - tx_y
            direct = np.sqrt(offset_x * offset_x + offset_y * offset_y)
            if on_axis_reason == OK and mean < direct:
                on_axis_reason = TOO_SHORT
            # |offset + r n|^2 = (mean - r)^2 is linear in r.
            denominator = 2.0 * (mean + (offset_x * n_x + offset_y * n_y))
            distance = (mean - direct) * (mean + direct) / denominator
            if on_axis_reason == OK and not denominator > 0:
                on_axis_reason = DEGENERATE
            reason[4, k] = on_axis_reason
            if on_axis_reason == OK:
                position[4, k, 0], position[4, k, 1] = c_x + distance * n_x, c_y + distance * n_y
    return reason, position, normal, reflection


ARC_MSE = 30.0
"""Mean-squared error along an estimate's arc bias, in squared biases (see :func:`unscented_models`)."""


@kernel
def unscented_models(tx, rx1, rx2, d1, d2, paths_covariance, wanted):
    """The models of ``localise.SOLVERS`` flagged in ``wanted`` for N rows, with unscented covariances.

    Each row's paths ``(d1, d2)`` (N,) with covariance ``S`` (N, 2, 2) give five
    sigma points (``n + kappa = 3``): the measurement, and it plus and minus each
    column of the Cholesky factor of ``3 S``; one solve of all five times N
    entries (``localise.solve_rows``) gives the estimate (point 0) and its spread.
    Returns ``reason`` (5, N), ``position`` (5, N, 2), the plane's ``normal``
    (N, 2) and ``reflection_points`` (N, 2, 2) of the estimates, and their
    covariances (5, N, 2, 2): the sigma points' covariance with the arc's bias
    raised to :data:`ARC_MSE` (see :func:`localise_ping`); NaN where a sigma
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
    reason, position, normal, reflection = solve_rows(sigma_tx, sigma_rx1, sigma_rx2, sigma_d1, sigma_d2, wanted)
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
    (:func:`horizontal_path`) and its noise scaled by ``d / sqrt(d^2 - dz^2)``;
    ``sigma_tof`` s, ``speed`` and ``sigma_speed`` m/s give the paths'
    covariance (:func:`path_covariance`), which :func:`unscented_models` carries
    to each model's position.

    Returns, for M models by N rows (entry ``m N + n``): ``reason`` (M N,),
    ``position``, ``normal`` (the plane's, towards the sensor) (M N, 2),
    ``covariance`` (M N, 2, 2) and ``segment`` (M N, 2, 2) (the plane's reflection
    points, else the position twice), all 0 where the reason is not OK; the
    rows' path covariance (N, 2, 2); and ``lost`` (M N,), valid entries whose
    sigma points left the solvable region, with a covariance still to compute.
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
    lost = np.zeros(size, dtype=np.bool_)
    for index in range(len(models)):
        model = models[index]
        for row in range(count):
            entry = index * count + row
            reason[entry] = solved_reason[model, row]
            if reason[entry] != OK:
                continue
            position[entry] = solved_position[model, row]
            covariance[entry] = solved_covariance[model, row]
            lost[entry] = not np.all(np.isfinite(covariance[entry]))
            if model == PLANE_SOLVER:
                normal[entry, 0], normal[entry, 1] = -plane_normal[row, 0], -plane_normal[row, 1]
                segment[entry] = reflection[row]
            else:
                segment[entry, 0] = segment[entry, 1] = position[entry]
    return reason, position, normal, covariance, segment, covariance_paths, lost


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
    compute (``lost`` of :func:`localise_rows`, ascending) and the rows' path
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
    reason, position, normal, covariance, segment, covariance_paths, lost = localise_rows(
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
            np.ones(size, dtype=np.uint32), entry_group, echo, reason == OK, reason, np.flatnonzero(lost),
            covariance_paths)


def _solved(caller, models, tx, rx1, rx2, d1, d2) -> dict:
    """The estimates of ``models`` (names of :data:`SOLVERS`) for inputs of any broadcast shape, by name, in order."""
    shape, *inputs = _flat_inputs(caller, tx, rx1, rx2, d1, d2)
    reason, position, normal, reflection = solve_rows(*inputs, np.array([name in models for name in SOLVERS]))
    estimates = {}
    for name in models:
        index = SOLVERS.index(name)
        codes = reason[index].reshape(shape)
        point = position[index].reshape(shape + (2,))
        if name == "plane":
            estimates[name] = PlaneEstimate(point, codes == OK, codes, name, normal.reshape(shape + (2,)),
                                            reflection.reshape(shape + (2, 2)))
        else:
            estimates[name] = PointEstimate(point, codes == OK, codes, name)
    return estimates


@_quiet
def virtual_image(tx, rx1, rx2, d1, d2) -> PointEstimate:
    """Virtual image ``T'`` of the transmitter in a plane or corner reflector.

    ``T'`` is the point at distance ``d1`` from ``rx1`` and ``d2`` from ``rx2`` in
    front of the receivers; planes and corners share it (Browne section 2,
    Barshan & Kuc's virtual receiver).

    Parameters
    ----------
    tx, rx1, rx2 : array_like, shape (..., 2)
        Transmitter and receiver positions, m, one frame.  ``rx1`` is the
        counter-clockwise (left) receiver.
    d1, d2 : array_like, shape (...)
        Path lengths transmitter -> reflector -> ``rx1`` / ``rx2``, m.

    Returns
    -------
    PointEstimate
        ``position`` (..., 2) of ``T'``; reasons NOT_FINITE, DEGENERATE,
        NEGATIVE, NO_INTERSECTION, TOO_SHORT.
    """
    return _solved("virtual_image", ("virtual_image",), tx, rx1, rx2, d1, d2)["virtual_image"]


@_quiet
def plane(tx, rx1, rx2, d1, d2) -> PlaneEstimate:
    """Plane reflector: foot point, unit normal and the two reflection points.

    The plane is the perpendicular bisector of ``T T'`` (Browne eqs 9-18 compute
    the reflection point X by trigonometry; this is the same geometry).

    Parameters
    ----------
    tx, rx1, rx2 : array_like, shape (..., 2)
        Transmitter and receiver positions, m.
    d1, d2 : array_like, shape (...)
        Path lengths to ``rx1`` / ``rx2``, m.

    Returns
    -------
    PlaneEstimate
        ``position`` = foot point ``G`` (..., 2), ``normal`` (..., 2) pointing
        away from the sensor, ``reflection_points`` (..., 2, 2).  Reasons as
        :func:`virtual_image`, plus DEGENERATE where ``T' = T``.
    """
    return _solved("plane", ("plane",), tx, rx1, rx2, d1, d2)["plane"]


@_quiet
def corner(tx, rx1, rx2, d1, d2) -> PointEstimate:
    """Corner reflector (concave junction of two planes): the point ``G = (T + T') / 2``.

    Browne eq 19; Barshan & Kuc's corner dot.  Also the model for a landmark of
    unknown class (Browne section 7).

    Parameters
    ----------
    tx, rx1, rx2 : array_like, shape (..., 2)
        Transmitter and receiver positions, m.
    d1, d2 : array_like, shape (...)
        Path lengths to ``rx1`` / ``rx2``, m.

    Returns
    -------
    PointEstimate
        ``position`` (..., 2); reasons as :func:`virtual_image`, plus BEHIND
        where ``G`` is not in front of the receivers.
    """
    return _solved("corner", ("corner",), tx, rx1, rx2, d1, d2)["corner"]


# --------------------------------------------------------------------------- edge

@_quiet
def edge(tx, rx1, rx2, d1, d2) -> PointEstimate:
    """Edge reflector (convex junction, pole): the point ``P`` with ``|P-T| + |P-R_n| = d_n``.

    Method (Browne section 5 solves the same equations; his Appendix A closed
    form is kept in :mod:`sonar_ring.reference.browne` for comparison).  With
    ``k = |P - T|`` the two receivers' circles ``|P - R_n|^2 = (d_n - k)^2`` and
    the transmitter's ``|P - T|^2 = k^2`` give, by subtraction, two equations
    linear in ``P`` and ``k`` (the ``k^2`` terms cancel).  In the receivers'
    frame (origin at their mid-point M, ``u`` along R1 -> R2, ``n`` to the
    front) they make ``k`` and the along-baseline coordinate affine functions of
    the normal coordinate ``p_n = (P - M) . n`` -- for *every* transmitter
    position, including on the receivers' line (Barshan & Kuc, Kreczmer), where
    a parametrisation by ``k`` is singular.  R1's circle is then a quadratic in
    ``p_n``.  Measuring ``p_n`` from the receivers' line (not from ``T``) keeps
    the two roots apart when the edge is close to the pair, and the quadratic is
    solved in the cancellation-free form ``p_n = c / q, q / a`` with
    ``q = -(b + sign(b) sqrt(b^2 - 4ac)) / 2``, which stays finite when the
    leading coefficient ``a`` vanishes (one root escapes to infinity and is
    discarded; ``a`` vanishes only as ``d_n -> |T - R_n|``).  A root is kept
    when ``0 <= k <= min(d1, d2)`` and ``P`` is in front of the receivers
    (``p_n > 0``).  For an edge nearer the transmitter than
    :data:`NEAR_TRANSMITTER` of the shorter path, ``k`` loses digits to
    cancellation (about ``d_n / k``); one Newton step on the path equations,
    kept where it brings the paths closer, restores them.

    Parameters
    ----------
    tx, rx1, rx2 : array_like, shape (..., 2)
        Transmitter and receiver positions, m.
    d1, d2 : array_like, shape (...)
        Path lengths to ``rx1`` / ``rx2``, m.

    Returns
    -------
    PointEstimate
        ``position`` (..., 2); reasons NOT_FINITE, DEGENERATE, NEGATIVE,
        NO_INTERSECTION, TOO_SHORT, BEHIND (no solution in front), AMBIGUOUS
        (two solutions in front -- only for transmitters in front of the
        receivers).
    """
    return _solved("edge", ("edge",), tx, rx1, rx2, d1, d2)["edge"]


# --------------------------------------------------------------------------- baselines and helpers

@_quiet
def on_axis(tx, rx1, rx2, d1, d2) -> PointEstimate:
    """Conventional ranger baseline: the echo placed on the receivers' axis.

    The point ``P = M + r n`` on the perpendicular bisector of the receivers
    (``M`` their mid-point, ``n`` the front) whose path ``|P - T| + |P - M|``
    equals the mean measured path ``(d1 + d2) / 2``; for a transducer at ``M``
    that transmits and receives this is ``r = d / 2``.  Bearing information is
    ignored, as by a single-transducer time-of-flight ranger.

    Parameters
    ----------
    tx, rx1, rx2 : array_like, shape (..., 2)
        Transmitter and receiver positions, m.
    d1, d2 : array_like, shape (...)
        Path lengths to ``rx1`` / ``rx2``, m.

    Returns
    -------
    PointEstimate
        ``position`` (..., 2); reasons NOT_FINITE, DEGENERATE, NEGATIVE,
        TOO_SHORT (mean path shorter than ``|T - M|``).
    """
    return _solved("on_axis", ("on_axis",), tx, rx1, rx2, d1, d2)["on_axis"]


MODELS = {"plane": plane, "corner": corner, "edge": edge}
"""Reflector model name -> localisation function (all share one signature)."""


@_quiet
def hypotheses(tx, rx1, rx2, d1, d2, models=tuple(MODELS)) -> dict:
    """Several reflector models of the same echoes, validated once and sharing one virtual image.

    The same results as calling each function of :data:`MODELS`, in about half
    the time for all three (what the localiser node does every ping).

    Parameters
    ----------
    tx, rx1, rx2 : array_like, shape (..., 2)
        Transmitter and receiver positions, m.
    d1, d2 : array_like, shape (...)
        Path lengths to ``rx1`` / ``rx2``, m.
    models : sequence of str
        Names from :data:`MODELS`.

    Returns
    -------
    dict of str to PointEstimate
        One estimate per requested model (a :class:`PlaneEstimate` for ``plane``).
    """
    unknown = set(models) - set(MODELS)
    if unknown:
        raise ValueError(f"hypotheses: unknown models {sorted(unknown)}, choose from {sorted(MODELS)}")
    return _solved("hypotheses", tuple(models), tx, rx1, rx2, d1, d2)


def load_kernels() -> None:
    """Load the compiled solvers now instead of at the first solve.

    Loading takes about 0.5 s (numba's start and the cached machine code); a
    process that localises on a deadline pays it at start.  Runs the models
    alone (:func:`hypotheses`) and for a ping (:func:`localise_ping_rows`, what
    ``pipeline.localise_ping`` uses), with the production argument types.
    """
    hypotheses([0.0, 0.0], [0.0, 0.02], [0.0, -0.02], 1.0, 1.0)
    localise_ping_rows(np.zeros((1, 3)), np.array([[0.0, 0.02, 0.0], [0.0, -0.02, 0.0]]), np.array([[0, 1]]),
                       np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64), np.full((1, 2), 0.006), 343.0, True,
                       1e-6, 0.0, np.arange(len(SOLVERS)), np.ones(len(SOLVERS), dtype=np.uint8))


def horizontal_path(d, dz) -> ScalarEstimate:
    """Exact horizontal path length ``sqrt(d^2 - dz^2)`` for vertically extruded reflectors.

    For walls, vertical corners and poles the path from a transmitter to a
    receiver ``dz`` lower or higher unfolds into a right triangle (image
    argument), so the horizontal path is exactly ``sqrt(d^2 - dz^2)``.  Browne's
    eq 26 forms the same root but turns it into a range assuming a plane facing
    the pair head-on.  Computed as ``sqrt((d - dz)(d + dz))``, free of
    cancellation when ``d ~ |dz|``.

    Parameters
    ----------
    d : array_like, shape (...)
        Measured 3-D path length, m.
    dz : array_like, shape (...)
        Transmitter minus receiver height, m (either sign;
        :meth:`sonar_ring.geometry.Layout.height_offset`).

    Returns
    -------
    ScalarEstimate
        ``value`` = horizontal path, m; reasons NOT_FINITE, NEGATIVE (d <= 0),
        BELOW_HEIGHT (d < |dz|).
    """
    d = _real_array("d", d, "horizontal_path")
    dz = _real_array("dz", dz, "horizontal_path")
    shape = _shape("horizontal_path", d=d, dz=dz)
    value, reason = horizontal_rows(*_flat_copies(shape, d, dz))
    return ScalarEstimate(value.reshape(shape), reason.reshape(shape) == OK, reason.reshape(shape))


@kernel
def horizontal_rows(d, dz):
    """:func:`horizontal_path` of each entry of the flat arrays ``d`` and ``dz`` (N,), m: values and reasons (int8).

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


@_quiet
def bearing(d1, d2, separation, exact=True) -> ScalarEstimate:
    """Bearing of the virtual image from the pair (Browne eq 4, or eq 8).

    ``exact=True``: the angle ``phi_1`` at receiver R1 between its normal and
    the virtual image, Browne eq 4 ``asin((d2^2 - d1^2 - D^2) / (2 d1 D))``,
    evaluated as ``atan2(-a, h)`` from the along-baseline offset ``a`` and the
    Heron height ``h`` so that it stays accurate for ``d1 ~ d2`` and near
    +-90 degrees.  ``exact=False``: the far-field approximation, eq 8,
    ``asin((d2 - d1) / D)`` -- the bearing from the pair's mid-point as the
    range goes to infinity.  Counter-clockwise positive when R1 is the
    counter-clockwise receiver: eq 3 gives ``sin(phi_1)`` the sign of
    ``d2^2 - d1^2 - D^2`` (far away: positive when the echo is nearer R1).

    Parameters
    ----------
    d1, d2 : array_like, shape (...)
        Path lengths to R1 / R2, m.
    separation : array_like, shape (...)
        Receiver separation D, m.
    exact : bool
        Eq 4 (True) or eq 8 (False).

    Returns
    -------
    ScalarEstimate
        ``value`` in rad, in [-pi/2, pi/2]; reasons NOT_FINITE, DEGENERATE
        (D <= 0), NEGATIVE, NO_INTERSECTION.
    """
    d1 = _real_array("d1", d1, "bearing")
    d2 = _real_array("d2", d2, "bearing")
    separation = _real_array("separation", separation, "bearing")
    reason = np.zeros(_shape("bearing", d1=d1, d2=d2, separation=separation), dtype=np.int8)
    _flag(reason, ~(_bounded(d1) & _bounded(d2) & _bounded(separation)), NOT_FINITE)
    _flag(reason, ~(separation > 0), DEGENERATE)
    _flag(reason, ~((d1 > 0) & (d2 > 0)), NEGATIVE)
    difference = d2 - d1
    total = d1 + d2
    _flag(reason, (separation + difference < 0) | (separation - difference < 0), NO_INTERSECTION)
    if exact:
        _flag(reason, total < separation, NO_INTERSECTION)
        # Along-baseline offset of T' from R1 towards R2, and its height over the baseline.
        from_r1 = ((d1 - d2) * total + separation * separation) / (2.0 * separation)
        heron = (separation + difference) * (separation - difference) * (total - separation) * (
            total + separation)
        value = np.arctan2(-from_r1, np.sqrt(heron) / (2.0 * separation))
    else:
        value = np.arcsin(difference / separation)
    valid, (value,) = _finish(reason, (value, 0))
    return ScalarEstimate(value, valid, reason)


# --------------------------------------------------------------------------- uncertainty

def cramer_rao_bound(separation, sigma_tof, speed_of_sound, phi=0.0):
    """Cramer-Rao bounds on bearing and range for one pair (DESIGN.md section 5).

    ``sigma_phi >= sqrt(2) c sigma_t / (D cos phi)`` and
    ``sigma_r >= c sigma_t / (2 sqrt(2))``, for independent TOF noise of standard
    deviation ``sigma_t`` on both receivers and a transmitter at the pair's
    mid-point (range = half the mean path).  Far-field bounds: the exact ones
    differ by O(D / range).

    Parameters
    ----------
    separation : array_like
        Receiver separation D, m.
    sigma_tof : array_like
        Standard deviation of each time of flight, s.
    speed_of_sound : array_like
        c, m/s.
    phi : array_like
        Bearing, rad.

    Returns
    -------
    sigma_bearing, sigma_range : ndarray
        Lower bounds on the standard deviations, rad and m.
    """
    sigma_path = np.asarray(speed_of_sound, dtype=float) * np.asarray(sigma_tof, dtype=float)
    sigma_bearing = np.sqrt(2.0) * sigma_path / (np.asarray(separation, dtype=float) * np.cos(phi))
    return sigma_bearing, sigma_path / (2.0 * np.sqrt(2.0))


def path_covariance(d1, d2, sigma_tof, speed_of_sound, sigma_speed=0.0) -> np.ndarray:
    """Covariance of the path lengths ``(d1, d2)`` from TOF and speed-of-sound noise.

    ``d_n = c tof_n``: independent TOF errors of standard deviation ``sigma_tof``
    give ``(c sigma_tof)^2`` on the diagonal; an error ``dc`` of the speed of
    sound, common to both receivers, moves both paths by ``d_n dc / c``.

    Parameters
    ----------
    d1, d2 : array_like, shape (...)
        Path lengths, m.
    sigma_tof : array_like, shape (...)
        Standard deviation of each TOF, s (>= 0).
    speed_of_sound : array_like, shape (...)
        c, m/s (> 0).
    sigma_speed : array_like, shape (...)
        Standard deviation of c, m/s (>= 0).

    Returns
    -------
    ndarray, shape (..., 2, 2)
        Covariance, m^2.

    Raises
    ------
    ValueError
        If a noise parameter is negative or not finite, or c <= 0 (these are
        configuration, not data).
    """
    d1 = _real_array("d1", d1, "path_covariance")
    d2 = _real_array("d2", d2, "path_covariance")
    sigma_tof = _real_array("sigma_tof", sigma_tof, "path_covariance")
    speed = _real_array("speed_of_sound", speed_of_sound, "path_covariance")
    sigma_speed = _real_array("sigma_speed", sigma_speed, "path_covariance")
    check_path_noise(sigma_tof, speed, sigma_speed, "path_covariance")
    shape = _shape("path_covariance", d1=d1, d2=d2, sigma_tof=sigma_tof, speed=speed, sigma_speed=sigma_speed)
    return _path_covariance_rows(*_flat_copies(shape, d1, d2, sigma_tof, speed, sigma_speed)).reshape(shape + (2, 2))


def check_path_noise(sigma_tof, speed_of_sound, sigma_speed, caller: str) -> None:
    """Refuse the noise parameters of a paths' covariance that make no sense, with ``ValueError``.

    All must be finite, ``sigma_tof`` (s) and ``sigma_speed`` (m/s) >= 0 and
    ``speed_of_sound`` (m/s) > 0; arrays or scalars.
    """
    lowest = [_lowest_finite(value) for value in (sigma_tof, speed_of_sound, sigma_speed)]
    if not (lowest[0] >= 0 and lowest[1] > 0 and lowest[2] >= 0):
        raise ValueError(f"{caller}: need sigma_tof >= 0, sigma_speed >= 0 and speed_of_sound > 0, all finite")


def _lowest_finite(value) -> float:
    """The smallest of a number or array (inf when empty: nothing to refuse), NaN when any is not finite."""
    if isinstance(value, float | int):
        # A ping's settings are numbers: numpy's reductions would cost tens of microseconds cold.
        return value if math.isfinite(value) else math.nan
    array = np.asarray(value, dtype=float)
    if not array.size:
        return math.inf
    return float(array.min()) if np.isfinite(array).all() else math.nan


@kernel
def _path_covariance_rows(d1, d2, sigma_tof, speed, sigma_speed):
    """:func:`_path_covariance` of each entry of flat arrays (N,); returns (N, 2, 2), m^2."""
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


def _inverse_2x2(rows: np.ndarray) -> np.ndarray:
    """Inverse of (..., 2, 2) matrices; +inf where singular."""
    a, b = rows[..., 0, 0], rows[..., 0, 1]
    c, d = rows[..., 1, 0], rows[..., 1, 1]
    det = a * d - b * c
    adjugate = np.stack([np.stack([d, -b], -1), np.stack([-c, a], -1)], -2)
    inverse = adjugate / det[..., None, None]
    return np.where((det == 0)[..., None, None], np.inf, inverse)


def _unit(vector: np.ndarray) -> np.ndarray:
    return vector / _norm(vector)[..., None]


@_quiet
def position_jacobian(estimate: PointEstimate, tx, rx1, rx2) -> np.ndarray:
    """Derivative of an estimate's position with respect to the paths ``(d1, d2)``.

    From the implicit equations of each model: the virtual image satisfies
    ``|T' - R_n| = d_n``, so ``dT'/dd = U^-1`` with rows ``(T' - R_n) / d_n``, and
    the plane foot point and the corner ``G = (T + T') / 2`` take half of it; an
    edge satisfies ``|P - T| + |P - R_n| = d_n``.

    Parameters
    ----------
    estimate : PointEstimate
        Result of :func:`virtual_image`, :func:`plane` (foot point),
        :func:`corner`, :func:`edge` or :func:`on_axis`.
    tx, rx1, rx2 : array_like, shape (..., 2)
        The positions the estimate was computed with, m.

    Returns
    -------
    ndarray, shape (..., 2, 2)
        ``J[..., i, n] = d position_i / d d_n`` (dimensionless); +inf where the
        geometry is singular (an echo on the receivers' line), NaN where the
        estimate is not valid.
    """
    tx = _points("tx", tx, "position_jacobian")
    rx1 = _points("rx1", rx1, "position_jacobian")
    rx2 = _points("rx2", rx2, "position_jacobian")
    position = estimate.position
    if estimate.model in ("virtual_image", "plane", "corner"):
        image = position if estimate.model == "virtual_image" else 2.0 * position - tx
        rows = np.stack([_unit(image - rx1), _unit(image - rx2)], axis=-2)
        jacobian = _inverse_2x2(rows) * (1.0 if estimate.model == "virtual_image" else 0.5)
    elif estimate.model == "edge":
        towards_tx = _unit(position - tx)
        rows = np.stack([towards_tx + _unit(position - rx1), towards_tx + _unit(position - rx2)], axis=-2)
        jacobian = _inverse_2x2(rows)
    elif estimate.model == "on_axis":
        frame = _receivers(rx1, rx2)
        # P = M + r n with |P - T| + r = (d1 + d2) / 2, so dr/dd_n = 1 / (2 (1 + cos(P - T, n))).
        rate = 0.5 / (1.0 + _dot(_unit(position - tx), frame.n))
        jacobian = (rate[..., None] * frame.n)[..., :, None] * np.ones(2)
    else:
        raise ValueError(f"position_jacobian: unknown model {estimate.model!r}")
    return np.where(estimate.valid[..., None, None], jacobian, np.nan)


@_quiet
def position_covariance(estimate: PointEstimate, tx, rx1, rx2, paths_covariance) -> np.ndarray:
    """First-order 2x2 covariance of an estimate's position: ``J S J^T``.

    Parameters
    ----------
    estimate : PointEstimate
        As for :func:`position_jacobian` (for a plane, the foot point).
    tx, rx1, rx2 : array_like, shape (..., 2)
        The positions the estimate was computed with, m.
    paths_covariance : array_like, shape (..., 2, 2)
        Covariance ``S`` of ``(d1, d2)``, m^2, e.g. from :func:`path_covariance`.

    Returns
    -------
    ndarray, shape (..., 2, 2)
        Covariance of the position, m^2; +inf where the geometry is singular,
        NaN where the estimate is not valid.
    """
    jacobian = position_jacobian(estimate, tx, rx1, rx2)
    paths_covariance = _real_array("paths_covariance", paths_covariance, "position_covariance")
    if paths_covariance.shape[-2:] != (2, 2):
        raise ValueError(f"position_covariance: 'paths_covariance' must be (..., 2, 2), got {paths_covariance.shape}")
    covariance = jacobian @ paths_covariance @ np.swapaxes(jacobian, -1, -2)
    singular = np.isinf(jacobian).any(axis=(-1, -2))
    return np.where(singular[..., None, None] & estimate.valid[..., None, None], np.inf, covariance)


# --------------------------------------------------------------------------- fusion

@_quiet
def inverse_variance_weights(variances, valid=None) -> np.ndarray:
    """Barshan & Kuc eq 41: ``w_i = (1 / s_i^2) / sum_k (1 / s_k^2)`` over the last axis.

    Inputs that are not valid, or whose variance is not finite and positive,
    get weight 0; a row without any usable input gets NaN weights.

    Parameters
    ----------
    variances : array_like, shape (..., G)
        Variance of each group's estimate.
    valid : array_like of bool, shape (..., G), optional
        Which inputs to use (default: all).

    Returns
    -------
    ndarray, shape (..., G)
    """
    variances = _real_array("variances", variances, "inverse_variance_weights")
    usable = np.isfinite(variances) & (variances > 0)
    if valid is not None:
        usable &= np.asarray(valid, dtype=bool)
    information = np.where(usable, 1.0 / variances, 0.0)
    return information / information.sum(axis=-1, keepdims=True)


@_quiet
def fuse_scalars(values, variances, valid=None) -> FusedScalar:
    """Fuse several groups' estimates of one scalar (e.g. an inclination), eq 41.

    Parameters
    ----------
    values, variances : array_like, shape (..., G)
        Each group's estimate and its variance; groups along the last axis.
    valid : array_like of bool, shape (..., G), optional

    Returns
    -------
    FusedScalar
        ``value`` and ``variance = 1 / sum(1 / s_i^2)`` (the minimum of eq 36),
        shape (...); reason NONE_VALID where no input is usable.
    """
    values = _real_array("values", values, "fuse_scalars")
    variances = _real_array("variances", variances, "fuse_scalars")
    weights = inverse_variance_weights(variances, valid)
    usable = weights > 0  # NaN weights (no usable input in the row) compare False
    value = np.where(usable, weights * values, 0.0).sum(axis=-1)
    variance = 1.0 / np.where(usable, 1.0 / variances, 0.0).sum(axis=-1)
    reason = np.where(usable.any(axis=-1), OK, NONE_VALID).astype(np.int8)
    ok, (value, variance) = _finish(reason, (value, 0), (variance, 0))
    return FusedScalar(value, variance, np.nan_to_num(weights), ok, reason)


@_quiet
def fuse_points(positions, covariances, valid=None) -> FusedPoint:
    """Fuse several groups' positions of one reflector with their covariances.

    The matrix form of Barshan & Kuc eq 41, ``x = (sum C_i^-1)^-1 sum C_i^-1 x_i``,
    which is the minimum-variance unbiased linear combination for uncorrelated
    groups and reduces to eq 41 when every ``C_i`` is a multiple of one matrix.

    Parameters
    ----------
    positions : array_like, shape (..., G, 2)
        Each group's estimate of the position, m, one frame.
    covariances : array_like, shape (..., G, 2, 2)
        Their covariances, m^2 (e.g. :func:`position_covariance`).
    valid : array_like of bool, shape (..., G), optional
        Which inputs to use; inputs with a non-finite or singular covariance are
        never used.

    Returns
    -------
    FusedPoint
        ``position`` (..., 2), ``covariance = (sum C_i^-1)^-1`` (..., 2, 2);
        reason NONE_VALID where no input is usable.
    """
    positions = _points("positions", positions, "fuse_points")
    covariances = _real_array("covariances", covariances, "fuse_points")
    if covariances.shape[-2:] != (2, 2) or covariances.ndim < 3:
        raise ValueError(f"fuse_points: 'covariances' must be (..., G, 2, 2), got {covariances.shape}")
    information = _inverse_2x2(covariances)
    usable = np.isfinite(information).all(axis=(-1, -2)) & np.isfinite(positions).all(axis=-1)
    usable &= np.isfinite(covariances).all(axis=(-1, -2))
    if valid is not None:
        usable = usable & np.asarray(valid, dtype=bool)
    information = np.where(usable[..., None, None], information, 0.0)
    weighted = (information @ np.where(usable[..., None], positions, 0.0)[..., None])[..., 0]
    covariance = _inverse_2x2(information.sum(axis=-3))
    position = (covariance @ weighted.sum(axis=-2)[..., None])[..., 0]
    reason = np.where(usable.any(axis=-1), OK, NONE_VALID).astype(np.int8)
    ok, (position, covariance) = _finish(reason, (position, 1), (covariance, 2))
    return FusedPoint(position, covariance, ok, reason)
