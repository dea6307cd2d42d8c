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
receivers), ``AMBIGUOUS`` 8 (two edge solutions in front of the receivers).
An entry carries the code of the first check it fails: the input checks in
the order NOT_FINITE, DEGENERATE (coincident receivers), NEGATIVE,
NO_INTERSECTION, TOO_SHORT, then the model's own (DEGENERATE, NO_INTERSECTION,
BEHIND, AMBIGUOUS).  The messages carry the same codes (``Landmark.msg``).

Numerics
--------
The formulas are arranged so that no step subtracts nearly equal rounded
quantities: the virtual image uses the along-baseline offset
``(d1 - d2)(d1 + d2) / (2D)`` and Heron's product
``(D + d2 - d1)(D - d2 + d1)(d1 + d2 - D)(d1 + d2 + D)`` for its height, so
``d1 ~ d2`` at long range and bearings near +-90 degrees stay accurate to a few
ulps of the inputs; the edge quadratic is solved in the cancellation-free
(citardauq) form.  See ``test/test_localise_hard_cases.py`` for the evidence.

Modules
-------
This module checks the arguments and shapes the results; the closed forms
run compiled in :mod:`sonar_ring.solvers` (which a ping's rows share with the
nodes), and the estimates' covariances are in :mod:`sonar_ring.uncertainty`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sonar_ring import solvers
from sonar_ring.checks import broadcast_shape, flat_copies, points, quiet, real_array
from sonar_ring.solvers import (  # the reason codes, set by the compiled checks
    AMBIGUOUS,
    BEHIND,
    BELOW_HEIGHT,
    DEGENERATE,
    MAX_LENGTH,
    NEGATIVE,
    NO_INTERSECTION,
    NOT_FINITE,
    OK,
    REASONS,
    SOLVERS,
    TOO_SHORT,
)

__all__ = ["AMBIGUOUS", "BEHIND", "BELOW_HEIGHT", "DEGENERATE", "MAX_LENGTH", "MODELS", "NEGATIVE", "NOT_FINITE",
           "NO_INTERSECTION", "OK", "REASONS", "TOO_SHORT", "PlaneEstimate", "PointEstimate", "ScalarEstimate",
           "bearing", "corner", "edge", "horizontal_path", "hypotheses", "load_kernels", "on_axis", "plane",
           "virtual_image"]


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
        :func:`sonar_ring.uncertainty.position_jacobian` uses it.
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


# --------------------------------------------------------------------------- input handling

_GEOMETRY = ("tx", "rx1", "rx2")


def _rows(array: np.ndarray, shape: tuple, core: tuple) -> np.ndarray:
    """``array`` as the solvers' rows: (1, *core) when it is one value for every entry, else (N, *core).

    One value is passed as it is, not copied out to N entries (a ring pair's
    geometry for a batch of echoes); an array of the full shape is flattened
    without a copy where its memory allows.  Every row array is a read-only
    view, so the solvers see one type whatever the caller passed (numba
    compiles a writable array as another).
    """
    if math.prod(array.shape[:array.ndim - len(core)]) == 1:
        rows = array.reshape((1,) + core)
    else:
        rows = np.broadcast_to(array, shape + core).reshape((-1,) + core)
    rows = np.ascontiguousarray(rows).view()
    rows.flags.writeable = False
    return rows


def _solved(caller, models, tx, rx1, rx2, d1, d2) -> dict:
    """The estimates of ``models`` (names of :data:`SOLVERS`) for inputs of any broadcast shape, by name, in order."""
    tx = points("tx", tx, caller)
    rx1 = points("rx1", rx1, caller)
    rx2 = points("rx2", rx2, caller)
    d1 = real_array("d1", d1, caller)
    d2 = real_array("d2", d2, caller)
    shape = broadcast_shape(caller, _GEOMETRY, tx=tx, rx1=rx1, rx2=rx2, d1=d1, d2=d2)
    reason, position, normal, reflection = solvers.solve_rows(
        math.prod(shape), _rows(tx, shape, (2,)), _rows(rx1, shape, (2,)), _rows(rx2, shape, (2,)),
        _rows(d1, shape, ()), _rows(d2, shape, ()), np.array([name in models for name in SOLVERS]))
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


# --------------------------------------------------------------------------- the reflector models

@quiet
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


@quiet
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


@quiet
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


@quiet
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
    :data:`sonar_ring.solvers.NEAR_TRANSMITTER` of the shorter path, ``k`` loses digits to
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


@quiet
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


@quiet
def hypotheses(tx, rx1, rx2, d1, d2, models=tuple(MODELS)) -> dict:
    """Several reflector models of the same echoes, validated once and sharing one virtual image.

    The same results as calling each function of :data:`MODELS`, from one pass
    over the entries that checks each input once and solves the virtual image
    once for planes and corners.

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

    Loading starts numba and reads the cached machine code; a process that
    localises on a deadline pays that at start, not at its first ping.  Runs the
    models alone (:func:`hypotheses`) and for a ping
    (:func:`sonar_ring.solvers.localise_ping_rows`, what ``pipeline.localise_ping``
    uses), with the production argument types.
    """
    hypotheses([0.0, 0.0], [0.0, 0.02], [0.0, -0.02], 1.0, 1.0)
    solvers.localise_ping_rows(np.zeros((1, 3)), np.array([[0.0, 0.02, 0.0], [0.0, -0.02, 0.0]]),
                               np.array([[0, 1]]), np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64),
                               np.full((1, 2), 0.006), 343.0, True, 1e-6, 0.0, np.arange(len(SOLVERS)),
                               np.ones(len(SOLVERS), dtype=np.uint8))


def reflector_paths(tx, rx, position, is_edge) -> np.ndarray:
    """The horizontal paths ``T -> reflector -> R_k`` a landmark implies: the forward model its estimate inverts.

    A plane's foot point, a corner or an undecided point ``G`` (virtual-image
    models: the image ``T' = 2G - T``) gives ``|2G - T - R_k|``; an edge at
    ``P`` gives ``|P - T| + |P - R_k|``.  For the pair that placed it, the two
    paths are the ones it was solved from.

    Parameters
    ----------
    tx : array_like, shape (L, 2)
        Each landmark's transmitter, m.
    rx : array_like, shape (L, K, 2)
        The receivers whose paths are wanted, m.
    position : array_like, shape (L, 2)
        ``G`` or ``P``, same frame, m.
    is_edge : array_like of bool, shape (L,)
        The edge model (else the virtual image's).

    Returns
    -------
    ndarray, shape (L, K)
        Horizontal paths, m.
    """
    # Copies: one array type for the kernel whatever the caller holds (a read-only array is another to numba).
    return solvers.reflector_path_rows(np.array(tx, dtype=float), np.array(rx, dtype=float),
                                       np.array(position, dtype=float), np.array(is_edge, dtype=bool))


# --------------------------------------------------------------------------- the vertical correction and the bearing

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
    d = real_array("d", d, "horizontal_path")
    dz = real_array("dz", dz, "horizontal_path")
    shape = broadcast_shape("horizontal_path", d=d, dz=dz)
    value, reason = solvers.horizontal_rows(*flat_copies(shape, d, dz))
    return ScalarEstimate(value.reshape(shape), reason.reshape(shape) == OK, reason.reshape(shape))


@quiet
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
    d1 = real_array("d1", d1, "bearing")
    d2 = real_array("d2", d2, "bearing")
    separation = real_array("separation", separation, "bearing")
    reason = np.zeros(broadcast_shape("bearing", d1=d1, d2=d2, separation=separation), dtype=np.int8)
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


def _bounded(values: np.ndarray) -> np.ndarray:
    """Finite and at most :data:`MAX_LENGTH` in magnitude (False for NaN)."""
    return np.abs(values) <= MAX_LENGTH


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
