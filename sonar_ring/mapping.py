"""Landmark map: association, fusion, wall segments, PLANE vs fixed point over motion, edge vs corner by curvature.

The map's frame is ``odom`` without SLAM, ``map`` as SLAM's front end
(:mod:`sonar_ring.slam`); below, ``odom`` stands for either.  The mapper core
behind the ``mapper`` node (numpy only).  Per ping the node turns the
labelled landmarks from the sensor frame into ``odom`` with
:func:`transform_landmarks` and hands them to :meth:`LandmarkMap.update` with the
sensor pose; :meth:`LandmarkMap.snapshot` (landmarks) and :meth:`LandmarkMap.points`
(costmap points) give the map to publish.

Map entries
-----------
* **Points** (CORNER, EDGE and still-UNKNOWN reflectors): the fused position in
  information form (``Lambda = sum C_i^-1``, mean by inverse-covariance weights: the
  multivariate form of Barshan & Kuc eq 41).  An UNKNOWN point also carries the
  *plane hypothesis* for the same sightings (below) until its class is known.
* **Walls** (PLANE): a line ``n . (x - a) = delta`` with unit normal
  ``n = (cos theta, sin theta)`` pointing from the wall towards the side it was seen
  from, kept as ``(theta, delta)`` with a 2x2 information matrix about an anchor ``a``
  that is moved to the middle of the segment after every change (so ``theta`` and
  ``delta`` stay nearly uncorrelated), and the extent seen along the wall.

Sightings as line observations
------------------------------
A plane's landmark is the foot point ``G`` of the perpendicular from the transmitter,
and the corner model puts an UNKNOWN reflector at the same point ``G`` (Browne s7),
so every sighting with its viewpoint ``S`` -- its receiver group's transmitter (Browne's
ring: the sensor's origin; a triad module: its emitter; the ``viewpoints`` of
:class:`LandmarkMap`) -- defines a line: the one through ``G`` with normal ``n``
along ``S - G`` (a plane sighting's own normal, oriented towards the sensor).  In
line coordinates about an anchor ``a``, ``z = (theta, n . (G - a))`` with covariance ``J C J^T``, where
``J = [-t^T / r ; n^T - (t . (G - a)) t^T / r]``, ``t`` the unit tangent and
``r = |S - G|``.  A wall is a constant ``z``; a corner is a constant ``G``: both are
two-parameter linear-Gaussian estimates from the same sightings, fused the same way,
with comparable residual sums.

Uncertainty floors
------------------
Every sighting's covariance gets ``sighting_sigma^2 I`` added (what a first-order
covariance misses: a range-and-bearing fix lies on an arc, and with sub-millimetre
range and centimetre bearing errors the arc's sag is comparable with the range
error).  Entries carry a floor ``map_sigma`` that more sightings do not average away
(odometry, speed of sound, calibration, errors shared by consecutive pings), used
when gating and reported by :meth:`LandmarkMap.snapshot`.  Both may be set to 0.

Association (one array operation per ping)
------------------------------------------
Candidates are entries within ``search_radius`` of the sighting (a point's latest
sighting, a wall's segment).  ``d^2``, the Mahalanobis distance of the innovation
with covariance ``C_sighting + C_entry``, must pass ``gate_chi2`` (chi-square, 2 dof):

* CORNER / EDGE sighting -- points of its class, UNKNOWN points, and points
  named CORNER by motion alone; point model;
* PLANE sighting -- walls, and UNKNOWN points under their plane hypothesis;
* UNKNOWN sighting -- any point (UNKNOWN points: the better of the two
  hypotheses) and walls.

Among the candidates within the gate a sighting joins the one with the smallest
``d^2 + ln det C - 2 ln n`` (minus twice the log of its likelihood times a prior
proportional to the entry's sightings ``n``, so a well-known entry beats a vague or
young one); several sightings of a ping may join one entry (overlapping receiver
groups).  A sighting outside every gate but within ``new_entry_gate_chi2`` of some entry
is dropped as ambiguous, so the tails of a known landmark's sightings do not start
duplicates.  The other unmatched sightings are clustered within the ping
(classified ones lead, UNKNOWN ones may join a leader of any class) and each
cluster starts one entry.  A classified sighting that joins an UNKNOWN point, or a
point named by motion alone, gives the point its class (PLANE turns it into a
wall).  A wall whose line and extent match another wall's (gate, gap at most
``search_radius``) absorbs it, unless an EDGE on their line lies between them:
a wall ends at a convex edge, and two walls either side of one are the sides of
a doorway, however near their seen extents have grown.  Likewise a sighting
beyond a wall's seen extent with an EDGE on the line in between does not join
that wall.

PLANE vs CORNER over motion
---------------------------
A corner stays put in ``odom``; the foot point of a plane slides along the wall as
the sensor moves along it, while the line it implies stays put.  For every UNKNOWN
point the map keeps both fits over its ``n`` sightings and their residual sums
``chi2_corner`` and ``chi2_plane`` (each chi-square with ``2 (n - 1)`` degrees of
freedom under its own model).  With ``Delta = chi2_corner - chi2_plane`` (twice the
log ratio of the maximised likelihoods) the point becomes

* a **PLANE** (a wall) when ``Delta >= decision_threshold``,
* a **CORNER** when ``Delta <= -decision_threshold``,

provided that

1. the motion separates the hypotheses: ``lambda = sum w_i (s_i - s_mean)^2 >=
   min_separation``, with ``s_i`` the viewpoint across the first line of
   sight, ``w_i`` the inverse variance of sighting i in that direction and
   ``s_mean`` their ``w``-weighted mean -- the value ``|Delta|`` has on average when
   either hypothesis is true.  A robot driving straight at a reflector or turning on
   the spot has ``lambda = 0`` and tells nothing;
2. the sensor moved at least ``min_baseline`` (m) across that line of sight, a guard
   against odometry and model errors at small scale; and
3. the winning model fits by itself: its ``chi2`` is below the 99.9 % point of
   chi-square with ``2 (n - 1)`` dof (Wilson-Hilferty), so a track that mixed two
   reflectors stays UNKNOWN -- or, for a PLANE, at most :data:`PLANE_SPREAD`
   times its dof.  A wall's first sightings carry its own echoes by way of
   reflectors the map does not hold yet, which no test can explain yet (in
   one realistic run 234 of the north wall's first 340 sightings, each placed
   up to 25 cm along the wall and a few degrees off its line of sight).  The
   line still fits them far better than a point (multipath alone, one run:
   chi-square 11,300 against 138,000 for 2,600 dof), but the test of
   consistency held the wall back for a lap or more, and a ghost wall of the
   double bounce between it and the south wall, which only the north wall
   explains, stayed in the map.

Otherwise the point stays UNKNOWN, placed with the corner model.  The confidence of
a decision is ``1 - exp(-|Delta| / 2)``, one minus the inverse likelihood ratio
(0.99 at the default threshold 9.21, a ratio of 100).  An edge placed with the
corner model also stays put, so motion makes such a point a fixed point,
CORNER_OR_EDGE, until the wavefront's curvature over its sightings tells an edge
from a corner (:mod:`sonar_ring.curvature`); an EDGE or CORNER sighting (labelled
by the ping's own evidence) names it at once.

Memory
------
At most ``max_points`` points and ``max_walls`` walls.  When a new entry needs a
slot in a full table, an entry that never persisted goes first, then the
entry seen least recently (ties: fewest observations); entries seen in the
current ping are never evicted, and new landmarks that find no slot are dropped
and counted.

Bad data never raises in :meth:`LandmarkMap.update`: sightings with ``valid``
False, non-finite fields, a covariance that is not positive definite, an unknown
class code, a zero plane normal or a position at the sensor are skipped and
counted (:class:`MapCounts`); a non-finite pose skips the ping.  Only arguments of
the wrong type or shape raise :class:`ValueError`.

Frames and units: ``odom`` (REP 105), metres, radians counter-clockwise (REP 103).
The pose is taken as exact: the map is consistent in ``odom`` as far as odometry is
(``map_sigma`` absorbs small drift).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field, replace

import numpy as np

from sonar_ring.compiled import kernel
from sonar_ring.curvature import CONSISTENCY_Z, CURVATURE_THRESHOLD, PointModels, chi2_quantile, decide
from sonar_ring.curvature import load_kernels as load_curvature_kernels
from sonar_ring.landmarks import (
    CORNER,
    CORNER_OR_EDGE,
    EDGE,
    PLANE,
    UNKNOWN,
    Landmarks,
    check_landmarks,
    make_landmarks,
)
from sonar_ring.poses import turned_covariances

CHI2_2DOF_99 = 9.2103
"""99 % point of chi-square with 2 degrees of freedom; also ``2 ln 100``."""

CHI2_2DOF_9999 = 18.421
"""99.99 % point of chi-square with 2 degrees of freedom."""

_AMBIGUOUS = -2
"""Association result of a sighting that is neither fused nor allowed to start an entry."""
_EXPLAINED = -3
"""Association result of a sighting the caller explained: neither fused nor starting an entry."""

_MIN_RANGE = 1e-3
"""Sightings closer than this to the sensor (m) define no line of sight."""

_MIN_EXTENT = 0.01
"""Shortest extent (m) over which :func:`_line_floor` spreads the end-point error."""

EDGE_ON_WALL = 0.05
"""m: an EDGE this close to a wall's line ends the wall there (:meth:`LandmarkMap._merge_walls` does not merge
walls across it)."""

PLANE_SPREAD = 4.0
"""A point whose plane hypothesis wins makes a wall while that hypothesis' chi-square is at most this many times
its degrees of freedom (sightings spread up to twice their modelled error), even where it fails the test of
consistency: see the module docstring."""

MAX_COORDINATE = 1e6
"""Largest |coordinate| (m) of a pose or sighting the map takes: beyond it the value is corrupt (and its
squares in the association would overflow), so it is counted like a non-finite one."""


def usable_pose(pose) -> bool:
    """Whether a pose ``(x, y, yaw)`` (m, rad) is one the map takes: finite, its position within the bound.

    (:data:`MAX_COORDINATE`; the mapper's core and its odometry gate check poses with it.)
    """
    pose = np.asarray(pose, dtype=float)
    return bool(np.all(np.isfinite(pose)) and np.all(np.abs(pose[:2]) <= MAX_COORDINATE))


def usable_covariance(covariance) -> bool:
    """Whether a pose's covariance (3, 3) of ``(x, y, yaw)`` is one the map takes.

    Finite, symmetric to round-off (a filter's products need not give the two halves bit for bit alike), no
    negative variance, and no cell beyond :data:`MAX_COORDINATE` squared (a pose uncertain by more is no pose;
    the squares of its spread in the echo tests would overflow).
    """
    covariance = np.asarray(covariance, dtype=float)
    if covariance.shape != (3, 3):
        return False
    # Nine floats: plain Python, where numpy's per-call overhead would be most of a ping's check.
    values = covariance.ravel().tolist()
    if not all(abs(value) <= MAX_COORDINATE ** 2 for value in values):  # NaN fails too
        return False
    (xx, xy, xt), (yx, yy, yt), (tx, ty, tt) = covariance.tolist()
    round_off = 1e-6 * max(abs(value) for value in values) + 1e-15
    return (xx >= 0.0 and yy >= 0.0 and tt >= 0.0 and abs(xy - yx) <= round_off and abs(xt - tx) <= round_off
            and abs(yt - ty) <= round_off)


# --------------------------------------------------------------------------- 2-D helpers

def _rotation(yaw: float) -> np.ndarray:
    cos_yaw, sin_yaw = np.cos(yaw), np.sin(yaw)
    return np.array([[cos_yaw, -sin_yaw], [sin_yaw, cos_yaw]])


@kernel
def _wrap(angle):
    """Angle in [-pi, pi), of a number or an array."""
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def _dot(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]


def _left(vector):
    """The vector turned 90 degrees counter-clockwise."""
    out = np.empty(vector.shape)
    out[..., 0] = -vector[..., 1]
    out[..., 1] = vector[..., 0]
    return out


@kernel(inline=True)
def _inverse_of(m00, m01, m10, m11):
    """The inverse of ``[[m00, m01], [m10, m11]]`` in closed form, as its four entries in the same order."""
    det = m00 * m11 - m01 * m10
    return m11 / det, -m01 / det, -m10 / det, m00 / det


@kernel
def _inverse(matrix):
    """Inverse of (K, 2, 2) matrices in closed form."""
    out = np.empty(matrix.shape)
    for k in range(matrix.shape[0]):
        out[k, 0, 0], out[k, 0, 1], out[k, 1, 0], out[k, 1, 1] = _inverse_of(
            matrix[k, 0, 0], matrix[k, 0, 1], matrix[k, 1, 0], matrix[k, 1, 1])
    return out


def _apply(matrix, vector):
    """``matrix @ vector`` for (..., 2, 2) and (..., 2) of the same leading shape."""
    out = np.empty(vector.shape)
    out[..., 0] = matrix[..., 0, 0] * vector[..., 0] + matrix[..., 0, 1] * vector[..., 1]
    out[..., 1] = matrix[..., 1, 0] * vector[..., 0] + matrix[..., 1, 1] * vector[..., 1]
    return out


@kernel
def _mahalanobis2(vector, covariance):
    """``v^T C^-1 v`` for vectors (K, 2) and covariances (K, 2, 2), without forming the inverse; shape (K,)."""
    out = np.empty(vector.shape[0])
    for k in range(vector.shape[0]):
        out[k] = _mahalanobis2_of(vector[k, 0], vector[k, 1], covariance[k, 0, 0], covariance[k, 0, 1],
                                  covariance[k, 1, 0], covariance[k, 1, 1])
    return out


@kernel(inline=True)
def _mahalanobis2_of(x, y, c00, c01, c10, c11):
    """``v^T C^-1 v`` of one vector ``(x, y)`` and covariance ``[[c00, c01], [c10, c11]]``."""
    return (c11 * x * x - 2.0 * c01 * x * y + c00 * y * y) / (c00 * c11 - c01 * c10)


def _quadratic(vector, matrix):
    """``vector^T matrix vector`` for (..., 2) and (..., 2, 2)."""
    return _dot(vector, _apply(matrix, vector))


@kernel(inline=True)
def _inverse_variance_along(x, y, covariance):
    """``1 / (u^T C u)``: the inverse variance of ``covariance`` (2, 2) along the unit direction ``u = (x, y)``."""
    return 1.0 / (x * (covariance[0, 0] * x + covariance[0, 1] * y) + y * (covariance[1, 0] * x + covariance[1, 1] * y))


@kernel
def _sandwich(jacobian, matrix):
    """``J M J^T`` for (K, 2, 2) arrays ``J`` and symmetric ``M``; exactly symmetric."""
    out = np.empty(matrix.shape)
    for k in range(matrix.shape[0]):
        out[k, 0, 0], out[k, 0, 1], out[k, 1, 1] = _sandwich_of(
            jacobian[k, 0, 0], jacobian[k, 0, 1], jacobian[k, 1, 0], jacobian[k, 1, 1], matrix[k, 0, 0],
            matrix[k, 0, 1], matrix[k, 1, 1])
        out[k, 1, 0] = out[k, 0, 1]
    return out


@kernel(inline=True)
def _sandwich_of(a, b, c, d, xx, xy, yy):
    """``J M J^T`` of one ``J = [[a, b], [c, d]]`` and symmetric ``M``: its entries 00, 01 (= 10), 11."""
    return (a * a * xx + 2.0 * a * b * xy + b * b * yy, a * c * xx + (a * d + b * c) * xy + b * d * yy,
            c * c * xx + 2.0 * c * d * xy + d * d * yy)


@kernel
def _pairs_within(query, points, radius):
    """Index pairs ``(i, j)`` with ``|query[i] - points[j]| <= radius``, by a sweep along x.

    Sorting ``points`` (M, 2) by x limits the distance tests to the strip
    ``|dx| <= radius`` of each query point (N, 2), which for a map spread over a
    room is a small fraction of all N x M pairs.  Pairs come by ``i``, then by
    the points' x (stable).
    """
    order = np.argsort(points[:, 0], kind="mergesort")
    sorted_x = points[order, 0]
    low = np.searchsorted(sorted_x, query[:, 0] - radius, side="left")
    high = np.searchsorted(sorted_x, query[:, 0] + radius, side="right")
    rows = np.empty(int(np.sum(high - low)), dtype=np.int64)
    columns = np.empty(rows.size, dtype=np.int64)
    count = 0
    for i in range(query.shape[0]):
        for j in order[low[i]:high[i]]:
            gap_x, gap_y = query[i, 0] - points[j, 0], query[i, 1] - points[j, 1]
            if gap_x ** 2 + gap_y ** 2 <= radius * radius:
                rows[count], columns[count] = i, j
                count += 1
    return rows[:count], columns[:count]


@kernel(inline=True)
def _gated_score_of(x, y, c00, c01, c10, c11, observations, distance, with_distance, gate_chi2):
    """Mahalanobis ``d^2`` of an innovation ``(x, y)`` with its covariance ``[[c00, c01], [c10, c11]]``, and its score.

    The score ``d^2 + ln det C - 2 ln n`` is minus twice the log of the sighting's
    likelihood times a prior proportional to the entry's sightings so far ``n``
    (``observations``): among the candidates that pass the gate a well-known entry
    beats a vague or young one (a sighting from the tail of a landmark's
    distribution that started an entry of its own does not draw the landmark's
    later sightings away).  Line innovations pass ``distance`` (``r``, used where
    ``with_distance``): the map from a sighting's point to its line coordinates
    has determinant ``1 / r``, so ``+ 2 ln r`` puts their scores on the point
    scale.  The score is inf where ``d^2`` does not pass ``gate_chi2``.
    """
    d2 = _mahalanobis2_of(x, y, c00, c01, c10, c11)
    score = d2 + np.log(c00 * c11 - c01 * c10) - 2.0 * np.log(observations)
    if with_distance:
        score += 2.0 * np.log(distance)
    if not d2 <= gate_chi2:
        score = np.inf
    return d2, score


@kernel
def _point_scores(rows, slots, seen_class, position, covariance, normal, distance, entry_class, by_motion, mean,
                  information, observations, anchor, line, line_information, extent, map_sigma, gate_chi2):
    """Gate distances ``d^2`` and scores of sightings ``rows`` (of the sightings' arrays) against points ``slots``.

    A sighting is tried as a point where the classes allow (not a plane; the
    point UNKNOWN, the sighting UNKNOWN or of its class, or the point's class
    from motion alone), and against an UNKNOWN point's plane hypothesis where it
    may be a plane; ``d^2`` and the score are the smaller of the two (inf where
    neither applies).
    """
    d2 = np.full(rows.size, np.inf)
    score = np.full(rows.size, np.inf)
    for k in range(rows.size):
        row, slot = rows[k], slots[k]
        seen, entry = seen_class[row], entry_class[slot]
        if seen != PLANE and (entry == UNKNOWN or seen == UNKNOWN or seen == entry or by_motion[slot]):
            e00, e01, e10, e11 = _point_entry_covariance_of(information[slot, 0, 0], information[slot, 0, 1],
                                                            information[slot, 1, 0], information[slot, 1, 1],
                                                            map_sigma)
            d2[k], score[k] = _gated_score_of(
                position[row, 0] - mean[slot, 0], position[row, 1] - mean[slot, 1], covariance[row, 0, 0] + e00,
                covariance[row, 0, 1] + e01, covariance[row, 1, 0] + e10, covariance[row, 1, 1] + e11,
                observations[slot], 1.0, False, gate_chi2)
        if entry == UNKNOWN and (seen == UNKNOWN or seen == PLANE):
            line_d2, line_score = _line_score_of(row, slot, position, covariance, normal, distance, anchor, line,
                                                 line_information, extent, observations, map_sigma, gate_chi2)
            d2[k] = _smaller(d2[k], line_d2)
            score[k] = _smaller(score[k], line_score)
    return d2, score


@kernel(inline=True)
def _smaller(a, b):
    """``numpy.minimum`` of two numbers: NaN if either is."""
    return a + b if np.isnan(a) or np.isnan(b) else min(a, b)


@kernel(inline=True)
def _line_score_of(row, slot, position, covariance, normal, distance, anchor, line, information, extent, observations,
                   map_sigma, gate_chi2):
    """``d^2`` and score (:func:`_gated_score_of`) of sighting ``row`` against the line of entry ``slot``.

    The sighting's line coordinates about the entry's anchor (:func:`_line_of_sight`) against the entry's line,
    with the sighting's covariance carried over plus the entry's (:func:`_line_entry_covariance`).
    """
    theta, delta, j00, j01, j10, j11 = _line_of_sight_of(normal[row, 0], normal[row, 1], position[row, 0],
                                                         position[row, 1], anchor[slot, 0], anchor[slot, 1],
                                                         distance[row])
    s00, s01, s11 = _sandwich_of(j00, j01, j10, j11, covariance[row, 0, 0], covariance[row, 0, 1],
                                 covariance[row, 1, 1])
    e00, e01, e10, e11 = _line_entry_covariance_of(information[slot, 0, 0], information[slot, 0, 1],
                                                   information[slot, 1, 0], information[slot, 1, 1], extent[slot, 0],
                                                   extent[slot, 1], map_sigma)
    return _gated_score_of(_wrap(theta - line[slot, 0]), delta - line[slot, 1], s00 + e00, s01 + e01, s01 + e10,
                           s11 + e11, observations[slot], distance[row], True, gate_chi2)


@kernel
def _wall_scores(rows, slots, position, covariance, normal, distance, anchor, line, information, tangent, extent,
                 observations, map_sigma, radius, gate_chi2):
    """Sightings ``rows`` (of the sightings' arrays) near walls ``slots``, and their line ``d^2`` and scores.

    A pair is a candidate where the sighting lies within ``radius`` of the wall's
    segment.  Returns the pairs' sighting rows and wall slots, by sighting, then
    wall, and their ``d^2`` and scores (see :func:`_gated_score_of`).
    """
    near_rows, near_walls = [], []
    for row in rows:
        for wall in slots:
            start_x = anchor[wall, 0] + extent[wall, 0] * tangent[wall, 0]
            start_y = anchor[wall, 1] + extent[wall, 0] * tangent[wall, 1]
            along_x = anchor[wall, 0] + extent[wall, 1] * tangent[wall, 0] - start_x
            along_y = anchor[wall, 1] + extent[wall, 1] * tangent[wall, 1] - start_y
            offset_x, offset_y = position[row, 0] - start_x, position[row, 1] - start_y
            fraction = min(max((offset_x * along_x + offset_y * along_y)
                               / max(along_x * along_x + along_y * along_y, 1e-18), 0.0), 1.0)
            gap_x, gap_y = offset_x - fraction * along_x, offset_y - fraction * along_y
            if gap_x ** 2 + gap_y ** 2 <= radius ** 2:
                near_rows.append(row)
                near_walls.append(wall)
    pair_rows, pair_walls = np.array(near_rows, dtype=np.int64), np.array(near_walls, dtype=np.int64)
    d2 = np.empty(pair_rows.size)
    score = np.empty(pair_rows.size)
    for k in range(pair_rows.size):
        d2[k], score[k] = _line_score_of(pair_rows[k], pair_walls[k], position, covariance, normal, distance, anchor,
                                         line, information, extent, observations, map_sigma, gate_chi2)
    return pair_rows, pair_walls, d2, score


@kernel
def _fuse_lines(line, information, chi2, with_chi2, anchor, axis, extent, slots, rows, normal, position, distance,
                covariance, segment):
    """Fuse sightings ``rows`` (of the sightings' arrays) into the lines ``slots`` of a table, in place.

    Each entry's line ``(theta, delta)`` about its anchor takes the sightings' line
    observations in information form (:func:`_fuse_information`, ``chi2`` where
    ``with_chi2``), ``theta`` wrapped, and its extent along ``axis`` (its unit
    direction, per entry) grows to cover the sightings' segment ends.  Returns
    the entries updated (ascending) and whether each one's extent grew.
    """
    value, jacobian = _line_of_sight(normal[rows], position[rows], anchor[slots], distance[rows])
    innovation = value - line[slots]
    innovation[:, 0] = _wrap(innovation[:, 0])
    updated = np.unique(slots)
    _fuse_information(line, information, chi2, with_chi2, slots, updated, innovation,
                      _inverse(_sandwich(jacobian, covariance[rows])))
    before = extent[updated].copy()
    for slot in updated:
        line[slot, 0] = _wrap(line[slot, 0])
    for k in range(slots.size):
        slot, row = slots[k], rows[k]
        for end in range(2):
            along = ((segment[row, end, 0] - anchor[slot, 0]) * axis[slot, 0]
                     + (segment[row, end, 1] - anchor[slot, 1]) * axis[slot, 1])
            extent[slot, 0] = np.minimum(extent[slot, 0], along)
            extent[slot, 1] = np.maximum(extent[slot, 1], along)
    grew = np.empty(updated.size, dtype=np.bool_)
    for index in range(updated.size):
        grew[index] = extent[updated[index], 0] != before[index, 0] or extent[updated[index], 1] != before[index, 1]
    return updated, grew


@kernel
def _line_floor(extent, sigma):
    """Covariance (K, 2, 2) of ``(theta, delta)`` from an error ``sigma`` at each end of a segment.

    The segment runs from ``s1`` to ``s2`` (``extent`` (K, 2), m along the line from
    its anchor); independent offsets ``u1``, ``u2`` across it at the ends move the
    line by ``theta = -(u2 - u1) / L`` and ``delta = (u1 s2 - u2 s1) / L``.
    """
    out = np.empty((extent.shape[0], 2, 2))
    for k in range(extent.shape[0]):
        out[k, 0, 0], out[k, 0, 1], out[k, 1, 1] = _line_floor_of(extent[k, 0], extent[k, 1], sigma)
        out[k, 1, 0] = out[k, 0, 1]
    return out


@kernel(inline=True)
def _line_floor_of(first, second, sigma):
    """:func:`_line_floor` of one segment from ``first`` to ``second``: its entries 00, 01 (= 10), 11."""
    length2 = np.maximum(second - first, _MIN_EXTENT) ** 2
    return (sigma ** 2 * (2.0 / length2), sigma ** 2 * ((first + second) / length2),
            sigma ** 2 * ((first ** 2 + second ** 2) / length2))


@kernel
def _point_entry_covariance(information, map_sigma):
    """Covariance (K, 2, 2) of point entries against the truth from their information, with the ``map_sigma`` floor."""
    out = np.empty(information.shape)
    for k in range(information.shape[0]):
        out[k, 0, 0], out[k, 0, 1], out[k, 1, 0], out[k, 1, 1] = _point_entry_covariance_of(
            information[k, 0, 0], information[k, 0, 1], information[k, 1, 0], information[k, 1, 1], map_sigma)
    return out


@kernel(inline=True)
def _point_entry_covariance_of(i00, i01, i10, i11, map_sigma):
    """:func:`_point_entry_covariance` of one entry's information ``[[i00, i01], [i10, i11]]``: its four entries."""
    e00, e01, e10, e11 = _inverse_of(i00, i01, i10, i11)
    variance = map_sigma ** 2
    # ``variance * np.eye(2)`` entry by entry, as the array version adds it: -0.0 and NaN come out the same.
    return e00 + variance * 1.0, e01 + variance * 0.0, e10 + variance * 0.0, e11 + variance * 1.0


@kernel
def _line_entry_covariance(information, extent, map_sigma):
    """Covariance (K, 2, 2) of lines (walls, plane hypotheses) from their information, with the end-point floor."""
    out = np.empty(information.shape)
    for k in range(information.shape[0]):
        out[k, 0, 0], out[k, 0, 1], out[k, 1, 0], out[k, 1, 1] = _line_entry_covariance_of(
            information[k, 0, 0], information[k, 0, 1], information[k, 1, 0], information[k, 1, 1], extent[k, 0],
            extent[k, 1], map_sigma)
    return out


@kernel(inline=True)
def _line_entry_covariance_of(i00, i01, i10, i11, first, second, map_sigma):
    """:func:`_line_entry_covariance` of one line's information and extent ``first``, ``second``: its four entries."""
    e00, e01, e10, e11 = _inverse_of(i00, i01, i10, i11)
    f00, f01, f11 = _line_floor_of(first, second, map_sigma)
    return e00 + f00, e01 + f01, e10 + f01, e11 + f11


@kernel
def _mark_seen(target, low, high, ping, sensor, last_seen, pings, unexplained, explained, travel, origin):
    """Mark the entries ``target - low`` of the targets in ``low:high`` seen at ``ping`` from ``sensor`` (2,).

    Once each, however many sightings matched it: the table's support columns (:func:`_add_support`) and
    ``last_seen``, in place.
    """
    seen = np.zeros(high - low, dtype=np.bool_)
    for i in range(target.size):
        if low <= target[i] < high:
            seen[target[i] - low] = True
    for slot in range(seen.size):
        if seen[slot]:
            last_seen[slot] = ping
            pings[slot] += 1
            unexplained[slot] += explained[slot] > 0
            distance = math.hypot(sensor[0] - origin[slot, 0], sensor[1] - origin[slot, 1])
            if np.isnan(distance) or distance > travel[slot]:
                travel[slot] = distance


@kernel(inline=True)
def _explained_once(explained, unexplained, pings, active, slot, min_support_pings):
    """One more ping that explained entry ``slot`` of a table (in place); whether that explains it away (inactive)."""
    explained[slot] += 1
    times = explained[slot]
    gone = times >= min_support_pings and times >= unexplained[slot] and 3 * times >= pings[slot]
    if gone:
        active[slot] = False
    return gone


@kernel
def _explain_away(target, explained, max_points, min_support_pings, point_explained, point_unexplained, point_pings,
                  point_active, wall_explained, wall_unexplained, wall_pings, wall_active):
    """The targets with explained sightings ``_EXPLAINED``, and the slots of the entries explained away.

    The rule and the counts of :meth:`LandmarkMap._explain_away`, for the
    points' and the walls' support columns and ``active`` flags, in place;
    slots as targets (walls from ``max_points``), ascending.  A sighting whose
    entry goes is set to -1 (it starts afresh).
    """
    slots = max_points + wall_active.size
    hit = np.zeros(slots, dtype=np.bool_)
    fused = np.zeros(slots, dtype=np.bool_)
    for i in range(target.size):
        if target[i] >= 0:
            if explained[i]:
                hit[target[i]] = True
            else:
                fused[target[i]] = True  # a ping that also fused a sighting into an entry does not explain it
    ghosts = np.empty(slots, dtype=np.int64)
    count = 0
    for slot in range(slots):
        if not hit[slot] or fused[slot]:
            continue
        if slot < max_points:
            gone = _explained_once(point_explained, point_unexplained, point_pings, point_active, slot,
                                   min_support_pings)
        else:
            gone = _explained_once(wall_explained, wall_unexplained, wall_pings, wall_active, slot - max_points,
                                   min_support_pings)
        if gone:
            ghosts[count] = slot
            count += 1
    out = target.copy()
    for i in range(out.size):
        if explained[i]:
            out[i] = _EXPLAINED
        elif out[i] >= max_points and not wall_active[out[i] - max_points]:
            out[i] = -1
        elif 0 <= out[i] < max_points and not point_active[out[i]]:
            out[i] = -1
    return out, ghosts[:count]


@kernel
def _add_motion(baseline, motion, slots, viewpoint_along, weight):
    """Widen each point's ``baseline`` (M, 2) to its sightings' viewpoints ``viewpoint_along`` (K,); add the sums.

    ``motion`` (M, 3) gathers ``sum w``, ``sum w s`` and ``sum w s^2`` of the sightings' places ``s`` and
    weights ``w`` (K,) per point ``slots`` (K,), in the sightings' order; NaN stays NaN, as in numpy.
    """
    for k in range(slots.size):
        slot, along = slots[k], viewpoint_along[k]
        baseline[slot, 0] = _smaller(baseline[slot, 0], along)
        baseline[slot, 1] = -_smaller(-baseline[slot, 1], -along)
        motion[slot, 0] += weight[k]
        motion[slot, 1] += weight[k] * along
        motion[slot, 2] += weight[k] * along ** 2


@kernel
def _best_targets(count, row, candidate, d2, score, new_entry_gate_chi2):
    """Each of ``count`` sightings' entry: its candidate (K,) of lowest finite ``score`` (ties: lowest ``candidate``).

    A sighting with no candidate of finite score gets ``_AMBIGUOUS`` where its
    nearest ``d2`` is within ``new_entry_gate_chi2`` (too near an entry to start
    one; a NaN distance is not), else -1 (start a new entry).
    """
    nearest = np.full(count, np.inf)
    best_score = np.full(count, np.inf)
    target = np.full(count, -1, dtype=np.int64)
    for i in range(row.size):
        r = row[i]
        if np.isnan(d2[i]) or d2[i] < nearest[r]:
            nearest[r] = d2[i]
        if np.isfinite(score[i]) and (target[r] < 0 or score[i] < best_score[r]
                                      or (score[i] == best_score[r] and candidate[i] < target[r])):
            best_score[r], target[r] = score[i], candidate[i]
    for r in range(count):
        if target[r] < 0 and nearest[r] <= new_entry_gate_chi2:
            target[r] = _AMBIGUOUS
    return target


@kernel
def _best_entries(seen_class, position, covariance, normal, distance, point_active, latest, point_class, by_motion,
                  mean, point_information, point_observations, point_anchor, point_line, point_line_information,
                  point_extent, wall_active, wall_anchor, wall_line, wall_information, wall_tangent, wall_normal,
                  wall_extent, wall_observations, max_points, map_sigma, search_radius, gate_chi2,
                  new_entry_gate_chi2):
    """:meth:`LandmarkMap._associate`: each sighting's entry (:func:`_best_targets`) among the points and walls.

    The sightings' arrays (:class:`Sightings`) and the two tables' (``_Points``, ``_Walls``).  Candidates are
    the active points whose latest sighting lies within ``search_radius`` (scored by :func:`_point_scores`:
    ``d^2`` the smaller over the models the classes allow, inf if none, the score that of the best model
    within the gate, :func:`_gated_score_of`) and, for UNKNOWN and PLANE sightings, the active walls whose
    seen segment does (:func:`_wall_scores`).  A sighting is no candidate of a wall when an EDGE on the
    wall's line lies between its seen extent and the sighting (:func:`_edges_past_extents`): the other side
    of a doorway, the jamb's own echo placed along the line, is not this wall's, however near (a seen
    extent grown across a doorway sighting by sighting reached the wall beyond it, 1.8 m past the wall's end
    in one realistic run of 20); a sighting within the extent always may join.  One compiled call, as the
    mapper makes it every ping.
    """
    point_slots = np.flatnonzero(point_active)
    row, column = _pairs_within(position, latest[point_slots], search_radius)
    point_candidate = point_slots[column]
    point_d2, point_score = _point_scores(row, point_candidate, seen_class, position, covariance, normal, distance,
                                          point_class, by_motion, mean, point_information, point_observations,
                                          point_anchor, point_line, point_line_information, point_extent, map_sigma,
                                          gate_chi2)
    line_like = np.flatnonzero((seen_class == UNKNOWN) | (seen_class == PLANE))
    wall_row, walls, wall_d2, wall_score = _wall_scores(line_like, np.flatnonzero(wall_active), position, covariance,
                                                        normal, distance, wall_anchor, wall_line, wall_information,
                                                        wall_tangent, wall_extent, wall_observations, map_sigma,
                                                        search_radius, gate_chi2)
    beyond = _edges_past_extents(walls, position[wall_row], wall_anchor, wall_tangent, wall_normal, wall_extent,
                                 point_active, point_class, mean)
    wall_d2[beyond] = np.inf
    wall_score[beyond] = np.inf
    return _best_targets(seen_class.size, np.concatenate((row, wall_row)),
                         np.concatenate((point_candidate, max_points + walls)), np.concatenate((point_d2, wall_d2)),
                         np.concatenate((point_score, wall_score)), new_entry_gate_chi2)


@kernel
def _edges_between(walls, first, second, anchor, tangent, normal, active, entry_class, mean):
    """Whether an active EDGE lies on the line of each wall ``walls`` (K,) strictly between ``first`` and ``second``.

    On the line: within :data:`EDGE_ON_WALL` of it (the walls are recentred: their
    lines pass their anchors); ``first`` and ``second`` (K,) are positions along the
    wall's tangent from its anchor, m.  The points' ``active``, ``entry_class`` and
    ``mean`` (slots, 2), the walls' ``anchor``, ``tangent`` and ``normal`` (slots, 2).
    """
    between = np.zeros(walls.size, dtype=np.bool_)
    for e in range(active.size):
        if not active[e] or entry_class[e] != EDGE:
            continue
        for k in range(walls.size):
            w = walls[k]
            offset_x, offset_y = mean[e, 0] - anchor[w, 0], mean[e, 1] - anchor[w, 1]
            along = offset_x * tangent[w, 0] + offset_y * tangent[w, 1]
            across = offset_x * normal[w, 0] + offset_y * normal[w, 1]
            between[k] = between[k] or (abs(across) <= EDGE_ON_WALL and (along - first[k]) * (along - second[k]) < 0)
    return between


@kernel
def _edges_past_extents(walls, position, anchor, tangent, normal, extent, active, entry_class, mean):
    """Whether an active EDGE lies on the line of each wall ``walls`` (K,) between its seen extent and ``position``.

    ``position`` (K, 2), m.  Between the extent's end nearest to the position's place along the line
    and that place (none for a position within the extent); the arrays as
    :func:`_edges_between` takes them, and the walls' ``extent`` (slots, 2), m.
    """
    along = np.empty(walls.size)
    nearest = np.empty(walls.size)
    for k in range(walls.size):
        w = walls[k]
        along[k] = (position[k, 0] - anchor[w, 0]) * tangent[w, 0] + (position[k, 1] - anchor[w, 1]) * tangent[w, 1]
        nearest[k] = min(max(along[k], extent[w, 0]), extent[w, 1])
    return _edges_between(walls, along, nearest, anchor, tangent, normal, active, entry_class, mean)


@kernel
def _match_walls(keep, other, anchor, line, information, normal, tangent, extent, map_sigma):
    """:meth:`LandmarkMap._wall_matches` of walls ``other`` against walls ``keep`` (K,), from the wall table."""
    count = keep.size
    innovation = np.empty((count, 2))
    jacobian = np.zeros((count, 2, 2))
    along = np.empty((count, 2))
    gap = np.empty(count)
    for k in range(count):
        a, b = keep[k], other[k]
        lever_x, lever_y = anchor[b, 0] - anchor[a, 0], anchor[b, 1] - anchor[a, 1]
        innovation[k, 0] = _wrap(line[b, 0] - line[a, 0])
        innovation[k, 1] = line[b, 1] + (normal[b, 0] * lever_x + normal[b, 1] * lever_y) - line[a, 1]
        jacobian[k, 0, 0] = jacobian[k, 1, 1] = 1.0
        jacobian[k, 1, 0] = tangent[b, 0] * lever_x + tangent[b, 1] * lever_y
        for end in range(2):
            end_x = anchor[b, 0] + extent[b, end] * tangent[b, 0]
            end_y = anchor[b, 1] + extent[b, end] * tangent[b, 1]
            along[k, end] = (end_x - anchor[a, 0]) * tangent[a, 0] + (end_y - anchor[a, 1]) * tangent[a, 1]
        gap[k] = np.maximum(np.minimum(along[k, 0], along[k, 1]) - extent[a, 1],
                            extent[a, 0] - np.maximum(along[k, 0], along[k, 1]))
    covariance = _sandwich(jacobian, _inverse(information[other]))
    floors = (_line_entry_covariance(information[keep], extent[keep], map_sigma)
              + _sandwich(jacobian, _line_floor(extent[other], map_sigma)))
    return _mahalanobis2(innovation, floors + covariance), gap, innovation, covariance, along


def _pose(pose, caller: str) -> np.ndarray:
    try:
        pose = np.asarray(pose, dtype=float)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{caller}: pose must be numeric (x, y, yaw), got {pose!r}") from error
    if pose.shape != (3,):
        raise ValueError(f"{caller}: pose must have shape (3,) as (x, y, yaw), got shape {pose.shape}")
    return pose


def transform_landmarks(landmarks: Landmarks, pose) -> Landmarks:
    """Landmarks from the sensor frame into ``odom``, given the sensor pose.

    Parameters
    ----------
    landmarks : Landmarks
        L landmarks in the sensor frame.
    pose : array_like, shape (3,)
        Sensor pose ``(x, y, yaw)`` in ``odom``, m and rad.  A non-finite pose gives
        non-finite landmarks (which :meth:`LandmarkMap.update` counts and skips).

    Returns
    -------
    Landmarks
        The same landmarks in ``odom``: positions and segment end points
        ``R p + (x, y)``, normals ``R n``, covariances ``R C R^T`` with ``R`` the
        rotation by ``yaw``; every other field unchanged.

    Raises
    ------
    ValueError
        If ``landmarks`` is not a :class:`Landmarks` with consistent shapes or
        ``pose`` is not three numbers.
    """
    check_landmarks(landmarks, "transform_landmarks")
    pose = _pose(pose, "transform_landmarks")
    rotation = _rotation(pose[2])
    # Built directly: dataclasses.replace walks the fields in Python (twice a ping in the mapper).
    return Landmarks(landmark_class=landmarks.landmark_class, position=landmarks.position @ rotation.T + pose[:2],
                     normal=landmarks.normal @ rotation.T,
                     covariance=turned_covariances(landmarks.covariance, rotation), confidence=landmarks.confidence,
                     segment=landmarks.segment @ rotation.T + pose[:2],
                     observations=landmarks.observations, group=landmarks.group, echo=landmarks.echo,
                     valid=landmarks.valid, reason=landmarks.reason)


# --------------------------------------------------------------------------- counters

@dataclass
class MapCounts:
    """What :meth:`LandmarkMap.update` did with its input, summed since construction.

    For the sightings of accepted pings,
    ``sightings == invalid + not_finite + degenerate + explained + ambiguous + fused + created + dropped``.

    Attributes
    ----------
    pings : int
        Updates with a finite pose.
    rejected_pings : int
        Updates skipped because the pose was not finite or beyond
        :data:`MAX_COORDINATE` (their sightings are not counted below).
    sightings : int
        Landmarks passed to accepted updates.
    invalid : int
        Landmarks flagged ``valid = False`` upstream.
    not_finite : int
        Landmarks flagged valid whose position, covariance, segment or (planes)
        normal holds NaN or infinity, or whose position or segment lies beyond
        :data:`MAX_COORDINATE` or standard deviation exceeds it.
    degenerate : int
        Landmarks with a covariance that is not positive definite, an unknown
        class code, a zero plane normal or a position at the sensor.
    explained : int
        Sightings the caller explained (multipath, impossible: ``explained`` of
        :meth:`LandmarkMap.update`): counted against the entry they match, never fused,
        never an entry of their own.
    explained_away : int
        Entries removed because the map came to explain their sightings (:meth:`LandmarkMap.update`).
    ambiguous : int
        Sightings outside every entry's gate but inside some entry's
        ``new_entry_gate_chi2``: neither fused nor allowed to start an entry.
    fused : int
        Sightings merged into an entry (including into one started in the same ping).
    created : int
        Entries started.
    dropped : int
        Sightings not stored because the map was full of entries seen in the same ping.
    evicted : int
        Entries removed to make room.
    resolved_plane, resolved_fixed : int
        UNKNOWN points turned into walls / fixed points (CORNER_OR_EDGE) by the motion test.
    resolved_corner, resolved_edge : int
        Fixed points told a corner / an edge by their curvature.
    merged_walls : int
        Walls absorbed into another wall.
    """

    pings: int = 0
    rejected_pings: int = 0
    sightings: int = 0
    invalid: int = 0
    not_finite: int = 0
    degenerate: int = 0
    explained: int = 0
    explained_away: int = 0
    ambiguous: int = 0
    fused: int = 0
    created: int = 0
    dropped: int = 0
    evicted: int = 0
    resolved_plane: int = 0
    resolved_fixed: int = 0
    resolved_corner: int = 0
    resolved_edge: int = 0
    merged_walls: int = 0


# --------------------------------------------------------------------------- state

@dataclass(frozen=True, eq=False)
class Sightings:
    """The usable landmarks of one ping in ``odom``, with their lines of sight (:meth:`LandmarkMap.usable_sightings`).

    Attributes
    ----------
    offered, invalid, not_finite, degenerate : int
        Landmarks offered, and those left out as in :class:`MapCounts`.
    rows : ndarray of int, shape (N,)
        Index of each sighting among the landmarks offered.
    landmark_class : ndarray of uint8, shape (N,)
    position : ndarray, shape (N, 2)
        ``G``, m.
    covariance, information : ndarray, shape (N, 2, 2)
        Covariance of ``G`` with the ``sighting_sigma`` floor (m^2) and its inverse.
    normal : ndarray, shape (N, 2)
        Unit normal of the sighting's line, towards its viewpoint.
    distance : ndarray, shape (N,)
        ``r = |S - G|``, m, ``S`` the viewpoint.
    segment : ndarray, shape (N, 2, 2)
        Observed end points, m.
    confidence : ndarray, shape (N,)
    group : ndarray of uint16, shape (N,)
    sensor : ndarray, shape (2,)
        The sensor's position, m.
    viewpoint : ndarray, shape (N, 2)
        Where each sighting was seen from, ``S``: its group's transmitter (:class:`LandmarkMap`'s
        ``viewpoints``), m.
    models : PointModels or None
        Both point models' positions of each sighting (:mod:`sonar_ring.curvature`), same frame.
    explained : ndarray of bool, shape (N,)
        Sightings the caller explained as multipath or impossible.
    """

    rows: np.ndarray
    landmark_class: np.ndarray
    position: np.ndarray
    covariance: np.ndarray
    information: np.ndarray
    normal: np.ndarray
    distance: np.ndarray
    segment: np.ndarray
    confidence: np.ndarray
    group: np.ndarray
    sensor: np.ndarray
    viewpoint: np.ndarray
    models: PointModels | None
    explained: np.ndarray
    offered: int
    invalid: int
    not_finite: int
    degenerate: int

    def line(self, rows, anchor):
        """Line observations ``(theta, delta)`` of sightings ``rows`` about ``anchor`` (K, 2).

        Returns the values (K, 2) and their covariances ``J C J^T`` (K, 2, 2).
        """
        value, jacobian = _line_of_sight(self.normal[rows], self.position[rows], anchor, self.distance[rows])
        return value, _sandwich(jacobian, self.covariance[rows])


@dataclass(frozen=True)
class Entries:
    """The entries of a :class:`LandmarkMap` (:meth:`LandmarkMap.entries`), E of them.

    Attributes
    ----------
    uid : ndarray of int, shape (E,)
        Each entry's stable number.
    is_wall : ndarray of bool, shape (E,)
    landmark_class : ndarray of uint8, shape (E,)
        PLANE for walls; a point's class (UNKNOWN while undecided).
    position : ndarray, shape (E, 2)
        A wall's middle (on its line), a point's fused position, m.
    normal : ndarray, shape (E, 2)
        A wall's unit normal towards the side it was seen from; zero for points.
    observations : ndarray of int, shape (E,)
        Sightings fused.
    """

    uid: np.ndarray
    is_wall: np.ndarray
    landmark_class: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    observations: np.ndarray


@dataclass(frozen=True)
class Placed:
    """Where :meth:`LandmarkMap.add` put one ping's usable sightings.

    Attributes
    ----------
    rows : ndarray of int, shape (N,)
        Index of each usable sighting among the landmarks given (:attr:`Sightings.rows`).
    uid : ndarray of int, shape (N,)
        The entry each went into (a stable number, :meth:`LandmarkMap.entries`), -1 where it was
        ambiguous or found no room.
    renamed : dict of int to int
        Entries of this update that live on under another uid: an UNKNOWN point that became a wall, a
        wall absorbed by another (old uid to new).
    removed : ndarray of int
        Entries this update removed: explained away (:attr:`MapCounts.explained_away`) or evicted.
    """

    rows: np.ndarray
    uid: np.ndarray
    renamed: dict
    removed: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))


@kernel
def _line_of_sight(normal, position, anchor, distance):
    """Line coordinates ``(theta, delta)`` (K, 2) of sightings about ``anchor`` (K, 2), and their Jacobian.

    ``J`` (K, 2, 2) is the derivative by the sighting's point (see the module
    docstring); ``normal``, ``position`` (K, 2) and ``distance`` (K,) of the sightings.
    """
    count = normal.shape[0]
    value = np.empty((count, 2))
    jacobian = np.empty((count, 2, 2))
    for k in range(count):
        (value[k, 0], value[k, 1], jacobian[k, 0, 0], jacobian[k, 0, 1], jacobian[k, 1, 0],
         jacobian[k, 1, 1]) = _line_of_sight_of(normal[k, 0], normal[k, 1], position[k, 0], position[k, 1],
                                                anchor[k, 0], anchor[k, 1], distance[k])
    return value, jacobian


@kernel(inline=True)
def _line_of_sight_of(normal_x, normal_y, x, y, anchor_x, anchor_y, distance):
    """:func:`_line_of_sight` of one sighting: ``theta``, ``delta`` and ``J``'s entries 00, 01, 10, 11."""
    tangent_x, tangent_y = -normal_y, normal_x
    offset_x, offset_y = x - anchor_x, y - anchor_y
    along = (tangent_x * offset_x + tangent_y * offset_y) / distance
    return (np.arctan2(normal_y, normal_x), normal_x * offset_x + normal_y * offset_y, -tangent_x / distance,
            -tangent_y / distance, normal_x - along * tangent_x, normal_y - along * tangent_y)


@kernel
def _usable_rows(landmark_class, valid, position, covariance, segment, normal, viewpoint, sighting_variance):
    """:meth:`LandmarkMap._usable_sightings` of L landmarks in ``odom``, each seen from its ``viewpoint`` (L, 2).

    A landmark is usable when valid, finite and within :data:`MAX_COORDINATE`
    (position, segment, covariance, a plane's normal; the covariance's entries
    within its square), and sound: a known class, a positive definite
    covariance, away from its viewpoint and, for a plane, a normal of about unit
    length.  Returns the usable rows (K,), their symmetrised covariances plus
    ``sighting_variance I`` and inverses (K, 2, 2), their line normals towards
    the viewpoint (a plane's own, else the line of sight) (K, 2) and distances
    (K,), and the counts of invalid, not finite and degenerate landmarks (3,).
    """
    count = landmark_class.shape[0]
    usable = np.zeros(count, dtype=np.bool_)
    counts = np.zeros(3, dtype=np.int64)
    symmetric = np.empty((count, 3))
    for k in range(count):
        if not valid[k]:
            counts[0] += 1
            continue
        plane = landmark_class[k] == PLANE
        xx, xy, yy = covariance[k, 0, 0], 0.5 * (covariance[k, 0, 1] + covariance[k, 1, 0]), covariance[k, 1, 1]
        symmetric[k, 0], symmetric[k, 1], symmetric[k, 2] = xx, xy, yy
        finite = (abs(xx) <= MAX_COORDINATE ** 2 and abs(xy) <= MAX_COORDINATE ** 2
                  and abs(yy) <= MAX_COORDINATE ** 2)
        for axis in range(2):
            finite = (finite and abs(position[k, axis]) <= MAX_COORDINATE and abs(segment[k, 0, axis]) <= MAX_COORDINATE
                      and abs(segment[k, 1, axis]) <= MAX_COORDINATE)
        # A plane's normal: its components' sum finite (huge components overflow it, as NaN and inf do).
        finite = finite and (np.isfinite(normal[k, 0] + normal[k, 1]) or not plane)
        if not finite:
            counts[1] += 1
            continue
        distance = np.hypot(viewpoint[k, 0] - position[k, 0], viewpoint[k, 1] - position[k, 1])
        if not (landmark_class[k] <= EDGE and xx > 0 and xx * yy - xy * xy > 0 and distance > _MIN_RANGE
                and (np.hypot(normal[k, 0], normal[k, 1]) > 0.5 or not plane)):
            counts[2] += 1
            continue
        usable[k] = True
    keep = np.flatnonzero(usable)
    kept_covariance = np.empty((keep.size, 2, 2))
    information = np.empty((keep.size, 2, 2))
    line_normal = np.empty((keep.size, 2))
    distances = np.empty(keep.size)
    for row in range(keep.size):
        k = keep[row]
        xx, xy, yy = symmetric[k, 0] + sighting_variance, symmetric[k, 1], symmetric[k, 2] + sighting_variance
        kept_covariance[row, 0, 0], kept_covariance[row, 0, 1] = xx, xy
        kept_covariance[row, 1, 0], kept_covariance[row, 1, 1] = xy, yy
        det = xx * yy - xy * xy
        information[row, 0, 0], information[row, 1, 1] = yy / det, xx / det
        information[row, 0, 1] = information[row, 1, 0] = -xy / det
        distance = np.hypot(viewpoint[k, 0] - position[k, 0], viewpoint[k, 1] - position[k, 1])
        sight_x, sight_y = (viewpoint[k, 0] - position[k, 0]) / distance, (viewpoint[k, 1] - position[k, 1]) / distance
        if landmark_class[k] == PLANE:
            length = np.hypot(normal[k, 0], normal[k, 1])
            given_x, given_y = normal[k, 0] / length, normal[k, 1] / length
            # Upstream conventions differ on the sign of a plane's normal; the wall faces the sensor.
            flip = -1.0 if given_x * sight_x + given_y * sight_y < 0 else 1.0
            line_normal[row, 0], line_normal[row, 1] = given_x * flip, given_y * flip
        else:
            line_normal[row, 0], line_normal[row, 1] = sight_x, sight_y
        distances[row] = distance
    return keep, kept_covariance, information, line_normal, distances, counts


def _add_support(table, capacity: int) -> None:
    """A table's support columns: what makes an entry persistent, and what the map explains of it.

    ``pings`` the pings that saw it, ``origin`` the sensor position of its first
    sighting and ``travel`` the farthest the sensor was from there at a later
    one (m); ``explained`` the pings with an explained sighting matching it, and
    ``unexplained`` those that fused one after the first of them; ``first_driven``
    the map's odometer (:attr:`LandmarkMap.driven`) at its first sighting, m.
    """
    table.pings = np.zeros(capacity, np.int64)
    table.first_driven = np.zeros(capacity)
    table.origin = np.zeros((capacity, 2))
    table.travel = np.zeros(capacity)
    table.explained = np.zeros(capacity, np.int64)
    table.unexplained = np.zeros(capacity, np.int64)


def _start_support(table, slots, sensor, driven: float) -> None:
    table.pings[slots] = 1
    table.first_driven[slots] = driven
    table.origin[slots] = sensor
    table.travel[slots] = 0.0
    table.explained[slots] = 0
    table.unexplained[slots] = 0


def _absorb_support(table, keep: int, other: int) -> None:
    """Entry ``keep`` takes over entry ``other``'s support (same table)."""
    table.pings[keep] += table.pings[other]
    table.travel[keep] = max(table.travel[keep], table.travel[other],
                             float(np.hypot(*(table.origin[keep] - table.origin[other]))))
    table.explained[keep] += table.explained[other]
    table.unexplained[keep] += table.unexplained[other]
    table.first_driven[keep] = min(table.first_driven[keep], table.first_driven[other])


class _Points:
    """Fixed-capacity table of point entries; row r is in use where ``active[r]``."""

    def __init__(self, capacity: int):
        self.active = np.zeros(capacity, bool)
        self.landmark_class = np.zeros(capacity, np.uint8)
        self.by_motion = np.zeros(capacity, bool)  # class from the motion test alone: CORNER_OR_EDGE
        # Point (corner) model: fused position, information matrix, residual chi-square.
        self.mean = np.zeros((capacity, 2))
        self.information = np.zeros((capacity, 2, 2))
        self.chi2 = np.zeros(capacity)
        # Plane hypothesis while UNKNOWN: (theta, delta) about the first sighting, as for walls.
        self.anchor = np.zeros((capacity, 2))
        self.line = np.zeros((capacity, 2))
        self.line_information = np.zeros((capacity, 2, 2))
        self.line_chi2 = np.zeros(capacity)
        # Along the tangent of the first line of sight, from the anchor: the extent of the
        # sightings and of their viewpoints (the motion baseline), m.
        self.across = np.zeros((capacity, 2))
        self.extent = np.zeros((capacity, 2))
        self.baseline = np.zeros((capacity, 2))
        # Sums over sightings of w, w s and w s^2, with s the viewpoint along that
        # tangent and w the inverse variance of the sighting along it: the separation.
        self.motion = np.zeros((capacity, 3))
        self.latest = np.zeros((capacity, 2))  # latest sighting, for the candidate search
        self.observations = np.zeros(capacity, np.int64)
        self.last_seen = np.zeros(capacity, np.int64)
        _add_support(self, capacity)
        self.group = np.zeros(capacity, np.uint16)
        self.confidence_sum = np.zeros(capacity)
        self.confidence_count = np.zeros(capacity)
        self.uid = np.full(capacity, -1, np.int64)
        # Edge or corner (sonar_ring.curvature): both models' fits over the sightings that had both, each weighted
        # by its own covariance, and the sums of W d and d^T W d of their differences d, W the corner model's
        # weight (the separation, with the corner fit's information).
        self.corner_fit = np.zeros((capacity, 2))
        self.edge_fit = np.zeros((capacity, 2))
        self.corner_information = np.zeros((capacity, 2, 2))
        self.edge_information = np.zeros((capacity, 2, 2))
        self.corner_chi2 = np.zeros(capacity)
        self.edge_chi2 = np.zeros(capacity)
        self.difference = np.zeros((capacity, 3))  # sum W d (2), sum (d^T W d - separation noise)
        self.modelled = np.zeros(capacity, np.int64)  # sightings with both models
        self.curvature_decided = np.zeros(capacity, bool)
        self.decision_distance = np.full(capacity, np.nan)  # m driven from the first sighting to the decision


class _Walls:
    """Fixed-capacity table of walls; row r is in use where ``active[r]``.

    Between updates every wall's anchor is the middle of its segment on its line
    (``delta = 0``, extent symmetric) and ``normal``/``tangent`` match ``theta``.
    """

    def __init__(self, capacity: int):
        self.active = np.zeros(capacity, bool)
        self.anchor = np.zeros((capacity, 2))
        self.line = np.zeros((capacity, 2))
        self.information = np.zeros((capacity, 2, 2))
        self.normal = np.zeros((capacity, 2))
        self.tangent = np.zeros((capacity, 2))
        self.extent = np.zeros((capacity, 2))
        self.observations = np.zeros(capacity, np.int64)
        self.last_seen = np.zeros(capacity, np.int64)
        _add_support(self, capacity)
        self.group = np.zeros(capacity, np.uint16)
        self.confidence_sum = np.zeros(capacity)
        self.confidence_count = np.zeros(capacity)
        self.uid = np.full(capacity, -1, np.int64)

    def end_points(self, rows):
        """Segment end points, shape (K, 2, 2), m."""
        return self.anchor[rows][:, None, :] + self.extent[rows][:, :, None] * self.tangent[rows][:, None, :]

    def coordinates(self, rows, points):
        """Where ``points`` (P, 2) lie from walls ``rows`` (K,): along each one's tangent and normal from its anchor.

        (K, P) each, m; the second is the distance from the line of a recentred wall (:meth:`recentre`).
        """
        offset = points[None, :, :] - self.anchor[rows][:, None, :]
        return np.einsum("kpi,ki->kp", offset, self.tangent[rows]), np.einsum("kpi,ki->kp", offset, self.normal[rows])

    def recentre(self, rows) -> None:
        """Move the anchors of walls ``rows`` to the middle of their segments, on the line.

        About a new anchor ``a'``, ``delta' = delta + n(theta) . (a - a')``, linear in
        ``theta`` with slope ``t . (a - a') = -s_mid``; the information transforms
        with that Jacobian.
        """
        _recentre(self.anchor, self.line, self.information, self.normal, self.tangent, self.extent, rows)


@kernel
def _recentre(anchor, line, information, normal, tangent, extent, rows):
    """:meth:`_Walls.recentre` of the walls ``rows``, in place."""
    for row in rows:
        theta = line[row, 0]
        normal_x, normal_y = np.cos(theta), np.sin(theta)
        middle = 0.5 * (extent[row, 0] + extent[row, 1])
        # J^-T Lambda J^-1 with J^-1 = [[1, 0], [middle, 1]], written out.
        xx, xy, yy = information[row, 0, 0], information[row, 0, 1], information[row, 1, 1]
        information[row, 0, 0] = xx + 2.0 * middle * xy + middle * middle * yy
        information[row, 0, 1] = information[row, 1, 0] = xy + middle * yy
        anchor[row, 0] += line[row, 1] * normal_x + middle * -normal_y
        anchor[row, 1] += line[row, 1] * normal_y + middle * normal_x
        line[row, 1] = 0.0
        extent[row, 0] -= middle
        extent[row, 1] -= middle
        normal[row, 0], normal[row, 1] = normal_x, normal_y
        tangent[row, 0], tangent[row, 1] = -normal_y, normal_x


@kernel
def _add_differences(difference, modelled, slots, pulled, statistic):
    """Add each sighting's pull (K, 2) and statistic (K,) to ``difference[slot]`` (M, 3) and count it, in order."""
    for k in range(slots.size):
        difference[slots[k], 0] += pulled[k, 0]
        difference[slots[k], 1] += pulled[k, 1]
        difference[slots[k], 2] += statistic[k]
        modelled[slots[k]] += 1


@kernel
def _add_confidences(slots, rows, distinct, seen_class, confidence, confidence_sum, confidence_count):
    """Add the confidences of the classified sightings ``rows`` (K,) and their count to their entries ``slots`` (K,).

    ``distinct`` are the distinct ``slots``, ascending.  Per entry the sums come first, in the sightings'
    order, then go to its totals ``confidence_sum`` and ``confidence_count`` (M,), in place.
    """
    added = np.zeros((distinct.size, 2))
    for k in range(slots.size):
        classified = seen_class[rows[k]] != UNKNOWN
        index = np.searchsorted(distinct, slots[k])
        added[index, 0] += confidence[rows[k]] if classified else 0.0
        added[index, 1] += 1.0 if classified else 0.0
    for index in range(distinct.size):
        confidence_sum[distinct[index]] += added[index, 0]
        confidence_count[distinct[index]] += added[index, 1]


@kernel
def _fuse_point_sightings(slots, rows, seen_class, position, seen_information, confidence, normal, distance,
                          covariance, segment, viewpoint, mean, information, chi2, latest, observations, entry_class,
                          by_motion, curvature_decided, confidence_sum, confidence_count, line, line_information,
                          line_chi2, anchor, across, extent, baseline, motion):
    """Merge sightings ``rows`` (of the sightings' arrays, :class:`Sightings`) into points ``slots`` (K,), in place.

    The points' arrays are the table's (``_Points``).  Each point's position takes its sightings in
    information form (:func:`_fuse_information`, its chi-square summed), its latest sighting and their count;
    an UNKNOWN point's plane hypothesis (only while UNKNOWN: :func:`_fuse_lines`), extent and motion
    baseline (:func:`_add_motion`, each sighting weighted by its inverse variance across the first line of
    sight) take them too.  A classified sighting names the class of a point that is UNKNOWN or was named by
    motion alone (which cannot tell an edge from a corner), until the curvature decides (of several in a ping,
    the last); the confidences of the classified sightings add up.
    """
    count = slots.size
    distinct = np.unique(slots)
    innovation = np.empty((count, 2))
    weight = np.empty((count, 2, 2))
    for k in range(count):
        innovation[k, 0] = position[rows[k], 0] - mean[slots[k], 0]
        innovation[k, 1] = position[rows[k], 1] - mean[slots[k], 1]
        weight[k] = seen_information[rows[k]]
    _fuse_information(mean, information, chi2, True, slots, distinct, innovation, weight)
    for k in range(count):
        latest[slots[k]] = position[rows[k]]
        observations[slots[k]] += 1
    still_open = np.flatnonzero(entry_class[slots] == UNKNOWN)
    if still_open.size:
        open_slots, open_rows = slots[still_open], rows[still_open]
        _fuse_lines(line, line_information, line_chi2, True, anchor, across, extent, open_slots, open_rows, normal,
                    position, distance, covariance, segment)
        viewpoint_along = np.empty(still_open.size)
        across_weight = np.empty(still_open.size)
        for k in range(still_open.size):
            slot, row = open_slots[k], open_rows[k]
            across_x, across_y = across[slot, 0], across[slot, 1]
            viewpoint_along[k] = ((viewpoint[row, 0] - anchor[slot, 0]) * across_x
                                  + (viewpoint[row, 1] - anchor[slot, 1]) * across_y)
            across_weight[k] = _inverse_variance_along(across_x, across_y, covariance[row])
        _add_motion(baseline, motion, open_slots, viewpoint_along, across_weight)
    namer = np.full(distinct.size, -1, dtype=np.int64)
    any_classified = False
    for k in range(count):
        slot = slots[k]
        if seen_class[rows[k]] == UNKNOWN:
            continue
        any_classified = True
        if (entry_class[slot] == UNKNOWN or by_motion[slot]) and not curvature_decided[slot]:
            index = np.searchsorted(distinct, slot)
            namer[index] = max(namer[index], k)
    for index in range(distinct.size):
        if namer[index] >= 0:
            slot = distinct[index]
            entry_class[slot] = seen_class[rows[namer[index]]]
            confidence_sum[slot] = confidence_count[slot] = 0.0
            by_motion[slot] = False
    if any_classified:
        _add_confidences(slots, rows, distinct, seen_class, confidence, confidence_sum, confidence_count)


@kernel
def _fuse_model_sightings(slots, rows, valid, corner, edge, corner_covariance, edge_covariance, separation_noise,
                          curvature_decided, modelled, corner_fit, edge_fit, corner_information, edge_information,
                          corner_chi2, edge_chi2, difference):
    """Fuse the point models of sightings ``rows`` into points ``slots`` (K,), in place.

    The models' arrays are :class:`~sonar_ring.curvature.PointModels`', the points' the table's (``_Points``).
    Only the sightings that have both models, and into points the curvature has not decided (nothing reads
    their two fits again): each model's fit in information form (:func:`_fuse_information`, started at a
    point's first such sighting), and the sums of the corner model's pull ``W d`` and of ``d^T W d`` less the
    separation noise of the differences ``d`` of the two models.
    """
    keep = np.flatnonzero(valid[rows] & ~curvature_decided[slots])
    if keep.size == 0:
        return
    rows, slots = rows[keep], slots[keep]
    weight = _inverse(corner_covariance[rows])
    edge_weight = _inverse(edge_covariance[rows])
    first = modelled[slots] == 0  # its first sighting with both models: the fits start there
    for k in range(slots.size):
        if first[k]:
            corner_fit[slots[k]] = corner[rows[k]]
            edge_fit[slots[k]] = edge[rows[k]]
    distinct = np.unique(slots)
    _fuse_information(corner_fit, corner_information, corner_chi2, True, slots, distinct,
                      corner[rows] - corner_fit[slots], weight)
    _fuse_information(edge_fit, edge_information, edge_chi2, True, slots, distinct, edge[rows] - edge_fit[slots],
                      edge_weight)
    pulled = np.empty((slots.size, 2))
    statistic = np.empty(slots.size)
    for k in range(slots.size):
        d_x, d_y = edge[rows[k], 0] - corner[rows[k], 0], edge[rows[k], 1] - corner[rows[k], 1]
        pulled[k, 0] = weight[k, 0, 0] * d_x + weight[k, 0, 1] * d_y
        pulled[k, 1] = weight[k, 1, 0] * d_x + weight[k, 1, 1] * d_y
        statistic[k] = (d_x * pulled[k, 0] + d_y * pulled[k, 1]) - separation_noise[rows[k]]
    _add_differences(difference, modelled, slots, pulled, statistic)


@kernel
def _fuse_wall_sightings(slots, rows, seen_class, normal, position, distance, covariance, segment, confidence, line,
                         information, anchor, wall_normal, tangent, extent, observations, confidence_sum,
                         confidence_count):
    """Merge sightings ``rows`` (of the sightings' arrays, :class:`Sightings`) into walls ``slots`` (K,), in place.

    The walls' arrays are the table's (``_Walls``): each wall's line takes its sightings (:func:`_fuse_lines`),
    its count and the confidences of the classified ones; its anchor moves to the middle of its seen
    segment (:func:`_recentre`).  Returns the walls whose segment grew, ascending.
    """
    updated, grew = _fuse_lines(line, information, np.zeros(0), False, anchor, tangent, extent, slots, rows, normal,
                                position, distance, covariance, segment)
    for k in range(slots.size):
        observations[slots[k]] += 1
    _add_confidences(slots, rows, updated, seen_class, confidence, confidence_sum, confidence_count)
    _recentre(anchor, line, information, wall_normal, tangent, extent, updated)
    return updated[grew]


@kernel
def _clusters(position, covariance, seen_class, radius, gate_chi2):
    """Each of K sightings' cluster: the index of the sighting that leads it.

    In order, a sighting not yet in a cluster leads one, which every sighting not yet in one joins that lies
    within ``radius`` and the Mahalanobis gate ``gate_chi2`` of it (their covariances summed) and is of its
    class or UNKNOWN.  ``position`` (K, 2), ``covariance`` (K, 2, 2), ``seen_class`` (K,).  Returns (K,).
    """
    lead, member = _pairs_within(position, position, radius)  # by leader, each with itself
    joins = ((_mahalanobis2(position[lead] - position[member], covariance[lead] + covariance[member]) <= gate_chi2)
             & ((seen_class[member] == seen_class[lead]) | (seen_class[member] == UNKNOWN)))
    lead, member = lead[joins], member[joins]
    first = np.searchsorted(lead, np.arange(seen_class.size + 1))
    cluster = np.full(seen_class.size, -1, dtype=np.int64)
    for k in range(seen_class.size):
        if cluster[k] < 0:
            for pair in range(first[k], first[k + 1]):
                if cluster[member[pair]] < 0:
                    cluster[member[pair]] = k
    return cluster


@kernel
def _start_point_rows(slots, rows, uids, ping, seen_class, position, seen_information, normal, distance, covariance,
                      segment, viewpoint, group, confidence, active, uid, entry_class, by_motion, mean, information,
                      chi2, anchor, line, line_information, line_chi2, across, extent, baseline, motion, latest,
                      observations, last_seen, entry_group, confidence_sum, confidence_count, corner_fit, edge_fit,
                      corner_information, edge_information, corner_chi2, edge_chi2, difference, modelled,
                      curvature_decided, decision_distance):
    """New points ``slots`` (K,) from sightings ``rows`` (K,) of the ping ``ping``, in the table's arrays.

    The sightings' arrays (:class:`Sightings`) and the points' (``_Points``), with their new ``uids`` (K,).
    Each point starts at its sighting: its position and information, its plane hypothesis about it
    (:func:`_line_of_sight`), its extent and motion baseline along the line of sight's tangent, its
    confidence where classified; its model fits empty.  (Its support: :func:`_start_support`.)
    """
    value, jacobian = _line_of_sight(normal[rows], position[rows], position[rows], distance[rows])
    plane_information = _inverse(_sandwich(jacobian, covariance[rows]))
    for k in range(slots.size):
        slot, row = slots[k], rows[k]
        x, y = position[row, 0], position[row, 1]
        tangent_x, tangent_y = -normal[row, 1], normal[row, 0]
        classified = seen_class[row] != UNKNOWN
        active[slot] = True
        uid[slot] = uids[k]
        entry_class[slot] = seen_class[row]
        by_motion[slot] = False
        mean[slot, 0], mean[slot, 1] = x, y
        information[slot] = seen_information[row]
        chi2[slot] = 0.0
        anchor[slot, 0], anchor[slot, 1] = x, y
        line[slot] = value[k]
        line_information[slot] = plane_information[k]
        line_chi2[slot] = 0.0
        across[slot, 0], across[slot, 1] = tangent_x, tangent_y
        first = (segment[row, 0, 0] - x) * tangent_x + (segment[row, 0, 1] - y) * tangent_y
        second = (segment[row, 1, 0] - x) * tangent_x + (segment[row, 1, 1] - y) * tangent_y
        extent[slot, 0], extent[slot, 1] = np.minimum(first, second), np.maximum(first, second)
        viewpoint_along = (viewpoint[row, 0] - x) * tangent_x + (viewpoint[row, 1] - y) * tangent_y
        baseline[slot, 0] = baseline[slot, 1] = viewpoint_along
        weight = _inverse_variance_along(tangent_x, tangent_y, covariance[row])
        motion[slot, 0], motion[slot, 1] = weight, weight * viewpoint_along
        motion[slot, 2] = weight * viewpoint_along ** 2
        latest[slot, 0], latest[slot, 1] = x, y
        observations[slot] = 1
        last_seen[slot] = ping
        entry_group[slot] = group[row]
        confidence_sum[slot] = confidence[row] if classified else 0.0
        confidence_count[slot] = 1.0 if classified else 0.0
        corner_fit[slot] = edge_fit[slot] = 0.0
        corner_information[slot] = edge_information[slot] = 0.0
        corner_chi2[slot] = edge_chi2[slot] = 0.0
        difference[slot] = 0.0
        modelled[slot] = 0
        curvature_decided[slot] = False
        decision_distance[slot] = np.nan


@kernel
def _classes_of(uids, wall_uid, wall_active, point_uid, point_active, point_class):
    """:meth:`LandmarkMap.classes_of`: each active slot's uid found among the sorted ``uids`` (K,)."""
    is_wall = np.zeros(uids.size, dtype=np.bool_)
    entry_class = np.full(uids.size, UNKNOWN, dtype=np.uint8)
    order = np.argsort(uids)
    ordered = uids[order]
    for table in range(2):
        table_uid, active = (wall_uid, wall_active) if table == 0 else (point_uid, point_active)
        for slot in range(table_uid.size):
            if not active[slot]:
                continue
            k = np.searchsorted(ordered, table_uid[slot])
            while k < ordered.size and ordered[k] == table_uid[slot]:
                is_wall[order[k]] = table == 0
                entry_class[order[k]] = PLANE if table == 0 else point_class[slot]
                k += 1
    return is_wall, entry_class


@kernel
def _fuse_information(mean, information, chi2, with_chi2, slots, rows, innovation, weight):
    """Fuse observations into entries in information form, all at once, in place.

    For each entry, minimises ``(x - x0)^T Lambda0 (x - x0) + sum (z_i - x)^T W_i (z_i - x)``
    (Barshan & Kuc eq 41 for vectors): ``Lambda = Lambda0 + sum W_i``,
    ``x = x0 + Lambda^-1 sum W_i nu_i`` with ``nu_i = z_i - x0``; the minimum is added
    to ``chi2`` where ``with_chi2``, which makes it the batch residual sum of all sightings.
    Arrays ``mean`` (M, 2), ``information`` (M, 2, 2), ``chi2`` (M,) are updated at
    ``slots`` (K,) with innovations (K, 2) and weights (K, 2, 2); ``rows`` are the
    distinct ``slots``, ascending.
    """
    # Per row: sums of W (00, symmetric 01, 11), of W nu (x, y) and of nu^T W nu.
    sums = np.zeros((rows.size, 6))
    for k in range(slots.size):
        row = np.searchsorted(rows, slots[k])
        w00, w01, w10, w11 = weight[k, 0, 0], weight[k, 0, 1], weight[k, 1, 0], weight[k, 1, 1]
        pull_x = w00 * innovation[k, 0] + w01 * innovation[k, 1]
        pull_y = w10 * innovation[k, 0] + w11 * innovation[k, 1]
        sums[row, 0] += w00
        sums[row, 1] += 0.5 * (w01 + w10)
        sums[row, 2] += w11
        sums[row, 3] += pull_x
        sums[row, 4] += pull_y
        sums[row, 5] += innovation[k, 0] * pull_x + innovation[k, 1] * pull_y
    for row in range(rows.size):
        m = rows[row]
        a = information[m, 0, 0] + sums[row, 0]
        b = information[m, 0, 1] + sums[row, 1]
        c = information[m, 1, 0] + sums[row, 1]
        d = information[m, 1, 1] + sums[row, 2]
        det = a * d - b * c
        step_x = d / det * sums[row, 3] + -b / det * sums[row, 4]
        step_y = -c / det * sums[row, 3] + a / det * sums[row, 4]
        mean[m, 0] += step_x
        mean[m, 1] += step_y
        information[m, 0, 0], information[m, 0, 1], information[m, 1, 0], information[m, 1, 1] = a, b, c, d
        if with_chi2:
            chi2[m] += sums[row, 5] - (sums[row, 3] * step_x + sums[row, 4] * step_y)


# --------------------------------------------------------------------------- the map

class LandmarkMap:
    """Labelled landmarks accumulated in ``odom`` (see the module docstring).

    Parameters
    ----------
    max_points : int
        Capacity for point entries (corners, edges, unresolved reflectors).
    max_walls : int
        Capacity for walls.
    sighting_sigma : float
        Unmodelled error of one sighting, m: ``sighting_sigma^2 I`` is added to every
        sighting's covariance.  It covers the arc a range-and-bearing fix traces,
        which a first-order covariance with sub-millimetre range and centimetre
        bearing errors misses, and timing quantisation.
    map_sigma : float
        Error of a map entry that more sightings do not average away, m (odometry,
        speed of sound, calibration, errors shared by consecutive pings from nearly
        the same place): ``map_sigma^2 I`` is added to a point's covariance, and an
        independent ``map_sigma`` across each end of a wall, for gating and in
        :meth:`snapshot`.
    gate_chi2 : float
        The gate of association and wall merging, a squared Mahalanobis distance
        ``d^2`` (a chi-square value, 2 dof); default the 99 % point.
    new_entry_gate_chi2 : float
        A sighting starts a new entry only if its ``d^2`` from every candidate
        exceeds this (default the 99.99 % point); between ``gate_chi2`` and it the
        sighting is dropped as ambiguous, so gate misses of a known landmark do not
        start duplicates.  At least ``gate_chi2``.
    decision_threshold : float
        ``|chi2_corner - chi2_plane|`` needed to resolve an UNKNOWN point by motion
        (twice the log likelihood ratio; 9.21 is 100:1).
    min_separation : float
        How far apart the two hypotheses' predictions must be before motion may
        decide: ``lambda = sum w_i (s_i - s_mean)^2`` (weighted by ``w_i``) over the
        sightings, with ``s_i`` the viewpoint across the first line of sight
        and ``w_i`` the sighting's inverse variance along it -- the value ``Delta``
        takes on average when either hypothesis is true.  25 is a 5-sigma difference.
    min_baseline : float
        Spread of the viewpoints across the first line of sight needed before
        motion may decide, m.
    search_radius : float
        Only entries this close are association candidates (a point's latest
        sighting, a wall's segment), and walls merge only across gaps below it, m.
    wall_point_spacing : float
        Largest spacing of the points :meth:`points` puts along a wall, m.
    curvature_threshold : float
        ``|chi2_corner - chi2_edge|`` needed to tell a fixed point an edge or a
        corner (:mod:`sonar_ring.curvature`; 13.8 is 1000:1), with ``min_separation``.
    min_support_pings : int
        Pings an entry must be seen in to be persistent (:meth:`persistent`).
    min_support_travel : float
        How far the sensor must have moved between its first sighting and a later
        one, m: an echo that repeats only while the robot stands still (a person
        standing by it, noise locked to the ping) is not enough.
    viewpoints : array_like, shape (G, 2), optional
        Where each receiver group sees its echoes from, in the sensor frame, m: its transmitter
        (:meth:`~sonar_ring.geometry.Layout.group_viewpoint`).  A wall's echo returns from the foot of the
        perpendicular from there, and an undecided point's plane hypothesis is the line through it
        perpendicular to the line of sight from there: a transmitter off the sensor's origin (a triad module
        at the robot's side) turns both by up to its offset over the range.  Default: every group at the
        origin (Browne's ring, whose emitter is there); a landmark of a group beyond ``G`` is seen from the
        origin too.

    Raises
    ------
    ValueError
        If a capacity is not an integer >= 1, a sigma is negative or not finite,
        another parameter is not positive and finite, ``new_entry_gate_chi2 < gate_chi2``, or ``viewpoints``
        is not a finite (G, 2) array.
    """

    def __init__(self, *, max_points: int = 1000, max_walls: int = 200, sighting_sigma: float = 0.002,
                 map_sigma: float = 0.001, gate_chi2: float = CHI2_2DOF_99,
                 new_entry_gate_chi2: float = CHI2_2DOF_9999,
                 decision_threshold: float = CHI2_2DOF_99, min_separation: float = 25.0, min_baseline: float = 0.1,
                 search_radius: float = 0.5, wall_point_spacing: float = 0.05,
                 curvature_threshold: float = CURVATURE_THRESHOLD, min_support_pings: int = 5,
                 min_support_travel: float = 0.05, viewpoints=None):
        for name, value in (("max_points", max_points), ("max_walls", max_walls),
                            ("min_support_pings", min_support_pings)):
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
                raise ValueError(f"LandmarkMap: {name} must be an integer >= 1, got {value!r}")
        numbers = {"sighting_sigma": sighting_sigma, "map_sigma": map_sigma, "gate_chi2": gate_chi2,
                   "new_entry_gate_chi2": new_entry_gate_chi2, "decision_threshold": decision_threshold,
                   "min_separation": min_separation, "min_baseline": min_baseline, "search_radius": search_radius,
                   "wall_point_spacing": wall_point_spacing, "curvature_threshold": curvature_threshold,
                   "min_support_travel": min_support_travel}
        for name, value in numbers.items():
            if isinstance(value, bool) or not isinstance(value, int | float | np.number) or not np.isfinite(value):
                raise ValueError(f"LandmarkMap: {name} must be a finite number, got {value!r}")
            may_be_zero = name.endswith("sigma") or name == "min_support_travel"
            if value < 0 or (value == 0 and not may_be_zero):
                raise ValueError(f"LandmarkMap: {name} must be {'>= 0' if may_be_zero else '> 0'}, got {value!r}")
        if new_entry_gate_chi2 < gate_chi2:
            raise ValueError(f"LandmarkMap: new_entry_gate_chi2 ({new_entry_gate_chi2}) must be at least "
                             f"gate_chi2 ({gate_chi2})")
        viewpoints = np.zeros((0, 2)) if viewpoints is None else np.array(viewpoints, dtype=float)
        if viewpoints.ndim != 2 or viewpoints.shape[1] != 2 or not np.all(np.isfinite(viewpoints)):
            raise ValueError(f"LandmarkMap: viewpoints must be a finite (G, 2) array, got {viewpoints!r}")
        self.max_points = int(max_points)
        self.max_walls = int(max_walls)
        self.sighting_sigma = float(sighting_sigma)
        self.map_sigma = float(map_sigma)
        self.gate_chi2 = float(gate_chi2)
        self.new_entry_gate_chi2 = float(new_entry_gate_chi2)
        self.decision_threshold = float(decision_threshold)
        self.min_separation = float(min_separation)
        self.min_baseline = float(min_baseline)
        self.search_radius = float(search_radius)
        self.wall_point_spacing = float(wall_point_spacing)
        self.curvature_threshold = float(curvature_threshold)
        self.min_support_pings = int(min_support_pings)
        self.min_support_travel = float(min_support_travel)
        self.viewpoints = viewpoints
        """Each receiver group's viewpoint in the sensor frame (G, 2), m (empty: all at the origin)."""
        self._viewpoint_rows = np.vstack([viewpoints, np.zeros((1, 2))])  # a group beyond them: the origin
        self._points = _Points(self.max_points)
        self._walls = _Walls(self.max_walls)
        self._counts = MapCounts()
        self._ping = 0
        self.driven = 0.0
        """The map's odometer: how far the sensor has moved over the pings it was given, m."""
        self._last_sensor: np.ndarray | None = None
        self._next_uid = 0
        self._renamed: dict[int, int] = {}  # this update's entries that became (or merged into) another
        self._removed: list[int] = []  # this update's entries explained away or evicted

    def __len__(self) -> int:
        """Number of map entries (points and walls)."""
        return int(np.count_nonzero(self._points.active) + np.count_nonzero(self._walls.active))

    @property
    def counts(self) -> MapCounts:
        """A copy of the counters (see :class:`MapCounts`)."""
        return replace(self._counts)

    # ------------------------------------------------------------------ update

    def update(self, landmarks: Landmarks, sensor_pose, models: PointModels | None = None,
               explained=None) -> Placed:
        """Add one ping's landmarks, already in ``odom``: :meth:`usable_sightings`, then :meth:`add`; where each went.

        Parameters
        ----------
        landmarks : Landmarks
            The ping's landmarks in ``odom`` (see :func:`transform_landmarks`), with
            covariances; planes with normals and segments, UNKNOWN ones localised
            with the corner model.
        sensor_pose : array_like, shape (3,)
            Sensor pose ``(x, y, yaw)`` in ``odom`` at the ping, m and rad; its
            position is the origin of every line of sight.
        models : PointModels, optional
            Both point models of each landmark, in ``odom`` (:func:`sonar_ring.curvature.point_models`):
            the evidence that tells an edge from a corner.
        explained : array_like of bool, shape (L,), optional
            Landmarks the caller explained (multipath, impossible: :mod:`sonar_ring.explain`).
            Each is matched to the map like any other but never fused and never
            starts an entry; an entry that comes to be matched by explained
            sightings only is removed (explained away: a ghost mapped before the
            map could explain it, :meth:`_explain_away`).

        Raises
        ------
        ValueError
            If ``landmarks`` is not a :class:`Landmarks` with consistent shapes or
            ``sensor_pose`` is not three numbers.  Bad data is counted, never raised.
        """
        return self.add(self.usable_sightings(landmarks, sensor_pose, models, explained))

    def usable_sightings(self, landmarks: Landmarks, sensor_pose, models: PointModels | None = None,
                         explained=None) -> Sightings | None:
        """The usable landmarks of one ping as sightings, the others counted by kind; None for a bad pose.

        Uses the map's settings, never its entries, so any map with the same
        settings gives the same sightings.  Parameters and errors as :meth:`update`.
        """
        check_landmarks(landmarks, "LandmarkMap.usable_sightings")
        pose = _pose(sensor_pose, "LandmarkMap.usable_sightings")
        if not usable_pose(pose):
            return None
        explained = np.zeros(len(landmarks), bool) if explained is None else np.asarray(explained, dtype=bool)
        if explained.shape != (len(landmarks),):
            raise ValueError(f"LandmarkMap.usable_sightings: explained must have shape ({len(landmarks)},), "
                             f"got {explained.shape}")
        return self._usable_sightings(landmarks, pose, models, explained)

    def add(self, sightings: Sightings | None) -> Placed:
        """Associate and fuse one ping's sightings (:meth:`usable_sightings`); None counts a rejected ping.

        Returns where each usable sighting went (:class:`Placed`).
        """
        self._renamed = {}
        self._removed = []
        if sightings is None:
            self._counts.rejected_pings += 1
            return Placed(np.empty(0, np.int64), np.empty(0, np.int64), {})
        self._ping += 1
        self._counts.pings += 1
        if self._last_sensor is not None:
            self.driven += float(np.hypot(*(sightings.sensor - self._last_sensor)))
        self._last_sensor = sightings.sensor
        self._counts.sightings += sightings.offered
        self._counts.invalid += sightings.invalid
        self._counts.not_finite += sightings.not_finite
        self._counts.degenerate += sightings.degenerate
        if sightings.landmark_class.size == 0:
            return Placed(sightings.rows, np.empty(0, np.int64), {})
        target = self._associate(sightings)
        if sightings.explained.any():
            target = self._explain_away(target, sightings.explained)
        self._mark_seen(target, sightings.sensor)
        self._counts.ambiguous += int(np.count_nonzero(target == _AMBIGUOUS))
        target, leader, new_walls = self._start_entries(sightings, target)
        self._counts.dropped += int(np.count_nonzero(target == -1))
        fusing = (target >= 0) & ~leader
        self._counts.fused += int(np.count_nonzero(fusing))
        is_wall = target >= self.max_points
        touched_points = self._fuse_points(sightings, np.flatnonzero(fusing & ~is_wall), target)
        grown_walls = self._fuse_walls(sightings, np.flatnonzero(fusing & is_wall), target)
        made_walls = self._resolve(touched_points)
        self._merge_walls(np.unique(np.concatenate([new_walls, grown_walls, made_walls])))
        return Placed(sightings.rows, self._uids_of(target), dict(self._renamed),
                      np.asarray(self._removed, dtype=np.int64))

    def _explain_away(self, target, explained):
        """Count explained sightings against the entries they match; remove the entries they explain away.

        An entry is explained away once ``min_support_pings`` pings matched it
        only with explained sightings, at least as many as fused one after the
        first of them and a third as many as ever fused one: a ghost mapped
        before the map could explain it goes soon after the map can, a
        reflector whose echo a prediction sometimes mimics stays, and one seen
        for long is not undone by a few pings (a ghost wall that hides it for a
        while).  Returns the targets with the explained sightings' set to
        ``_EXPLAINED`` (neither fused nor started).
        """
        self._counts.explained += int(np.count_nonzero(explained))
        p, w = self._points, self._walls
        target, ghosts = _explain_away(target, explained, self.max_points, self.min_support_pings, p.explained,
                                       p.unexplained, p.pings, p.active, w.explained, w.unexplained, w.pings,
                                       w.active)
        self._removed.extend(p.uid[ghosts[ghosts < self.max_points]].tolist())
        self._removed.extend(w.uid[ghosts[ghosts >= self.max_points] - self.max_points].tolist())
        self._counts.explained_away += ghosts.size
        return target

    def _uids_of(self, target) -> np.ndarray:
        """The entry uid each sighting ended in (its target slot's, through this update's renames); -1 for none."""
        uid = np.full(target.size, -1, np.int64)
        point = (target >= 0) & (target < self.max_points)
        wall = target >= self.max_points
        uid[point] = self._points.uid[target[point]]
        uid[wall] = self._walls.uid[target[wall] - self.max_points]
        if self._renamed:  # most pings rename nothing
            for index in np.flatnonzero(uid >= 0):
                while uid[index] in self._renamed:
                    uid[index] = self._renamed[uid[index]]
        return uid

    def _new_uids(self, count: int) -> np.ndarray:
        uids = np.arange(self._next_uid, self._next_uid + count, dtype=np.int64)
        self._next_uid += count
        return uids

    def _usable_sightings(self, landmarks: Landmarks, pose: np.ndarray, models: PointModels | None,
                          explained: np.ndarray) -> Sightings:
        """The usable landmarks, the sensor at ``pose``; the unusable ones counted by kind (point models, if given)."""
        # Copies (np.array) in the types load_kernels compiled, whatever arrays the caller's landmarks hold
        # (a read-only one is another type to numba); the kernel only reads them.
        position = np.array(landmarks.position, dtype=float)
        segment = np.array(landmarks.segment, dtype=float)
        viewpoint = self.viewpoints_at(landmarks.group, pose)
        keep, covariance, information, normal, distance, counts = _usable_rows(
            np.array(landmarks.landmark_class, dtype=np.uint8), np.array(landmarks.valid, dtype=bool), position,
            np.array(landmarks.covariance, dtype=float), segment, np.array(landmarks.normal, dtype=float),
            viewpoint, self.sighting_sigma ** 2)
        return Sightings(
            rows=keep,
            landmark_class=landmarks.landmark_class[keep].astype(np.uint8),
            position=position[keep],
            covariance=covariance,
            information=information,
            normal=normal,
            distance=distance,
            segment=segment[keep],
            confidence=np.asarray(landmarks.confidence, float)[keep],
            group=np.asarray(landmarks.group)[keep].astype(np.uint16),
            sensor=pose[:2],
            viewpoint=viewpoint[keep],
            models=None if models is None else models.select(keep),
            explained=explained[keep],
            offered=len(landmarks),
            invalid=int(counts[0]),
            not_finite=int(counts[1]),
            degenerate=int(counts[2]),
        )

    def viewpoints_at(self, group, pose) -> np.ndarray:
        """Where landmarks of receiver groups ``group`` (L,) are seen from, the sensor at ``pose`` ``(x, y, yaw)``.

        (L, 2), m, in the frame ``pose`` is given in (:attr:`viewpoints`, as :func:`transform_landmarks` moves
        positions).
        """
        row = np.minimum(np.asarray(group, dtype=np.int64), len(self.viewpoints))
        return self._viewpoint_rows[row] @ _rotation(pose[2]).T + pose[:2]

    # ------------------------------------------------------------------ association

    def _point_covariance(self, slots):
        """Covariance of points ``slots`` against the truth, with the ``map_sigma`` floor, (K, 2, 2)."""
        return _point_entry_covariance(self._points.information[slots], self.map_sigma)

    def _wall_covariance(self, slots):
        """Covariance of the lines of walls ``slots``, with the floor, (K, 2, 2)."""
        return _line_entry_covariance(self._walls.information[slots], self._walls.extent[slots], self.map_sigma)

    def _associate(self, s: Sightings) -> np.ndarray:
        """Best entry for each sighting, all sightings against the whole map at once (:func:`_best_entries`).

        Returns, per sighting, a point slot, ``max_points +`` a wall slot, -1 (start a
        new entry) or ``_AMBIGUOUS``.
        """
        p, w = self._points, self._walls
        return _best_entries(s.landmark_class, s.position, s.covariance, s.normal, s.distance, p.active, p.latest,
                             p.landmark_class, p.by_motion, p.mean, p.information, p.observations, p.anchor, p.line,
                             p.line_information, p.extent, w.active, w.anchor, w.line, w.information, w.tangent,
                             w.normal, w.extent, w.observations, self.max_points, self.map_sigma, self.search_radius,
                             self.gate_chi2, self.new_entry_gate_chi2)

    def _mark_seen(self, target, sensor) -> None:
        """The ping's matched entries: seen now, their support grown (a ping counts once per entry)."""
        for table, low, high in ((self._points, 0, self.max_points),
                                 (self._walls, self.max_points, self.max_points + self.max_walls)):
            _mark_seen(target, low, high, self._ping, sensor, table.last_seen, table.pings, table.unexplained,
                       table.explained, table.travel, table.origin)

    # ------------------------------------------------------------------ new entries

    def _start_entries(self, s: Sightings, target):
        """Cluster the unmatched sightings of the ping and start one entry per cluster.

        Returns the completed targets (-1 where dropped for want of room), a mask of
        the sightings that started an entry (leaders, already stored) and the slots
        of the new walls.
        """
        leader = np.zeros(target.size, bool)
        unmatched = np.flatnonzero(target == -1)
        if unmatched.size == 0:
            return target, leader, np.empty(0, np.int64)
        # Classified sightings lead; an UNKNOWN one may join a leader of any class.
        order = unmatched[np.argsort(s.landmark_class[unmatched] == UNKNOWN, kind="stable")]
        cluster = _clusters(s.position[order], s.covariance[order], s.landmark_class[order], self.search_radius,
                            self.gate_chi2)
        heads = np.unique(cluster)
        is_wall = s.landmark_class[order[heads]] == PLANE
        slot_of_head = np.full(order.size, -1)
        slot_of_head[heads[~is_wall]] = self._start_points(s, order[heads[~is_wall]])
        wall_slots = self._start_walls(s, order[heads[is_wall]])
        slot_of_head[heads[is_wall]] = np.where(wall_slots >= 0, self.max_points + wall_slots, -1)
        target = target.copy()
        target[order] = slot_of_head[cluster]
        leader[order[heads]] = slot_of_head[heads] >= 0
        self._counts.created += int(np.count_nonzero(leader))
        return target, leader, wall_slots[wall_slots >= 0]

    def _allocate(self, table, count: int) -> np.ndarray:
        """Up to ``count`` free rows of ``table``, evicting entries that do not persist, then the least recently seen.

        An echo that never repeats fills the table as fast as the robot pings; a reflector that persists is
        evicted only when nothing else is left.
        """
        free = np.flatnonzero(~table.active)
        if free.size < count:
            old = np.flatnonzero(table.active & (table.last_seen < self._ping))
            victims = old[np.lexsort((table.observations[old], table.last_seen[old],
                                      self._supported(table)[old]))][:count - free.size]
            table.active[victims] = False
            self._removed.extend(table.uid[victims].tolist())
            self._counts.evicted += victims.size
            free = np.sort(np.concatenate([free, victims]))
        return free[:count]

    def _start_points(self, s: Sightings, rows) -> np.ndarray:
        """New points from sightings ``rows``; their slots, -1 where the table is full."""
        slots = self._allocate(self._points, rows.size)
        out = np.full(rows.size, -1)
        out[:slots.size] = slots
        rows = rows[:slots.size]
        p = self._points
        _start_point_rows(slots, rows, self._new_uids(slots.size), self._ping, s.landmark_class, s.position,
                          s.information, s.normal, s.distance, s.covariance, s.segment, s.viewpoint, s.group,
                          s.confidence, p.active, p.uid, p.landmark_class, p.by_motion, p.mean, p.information, p.chi2,
                          p.anchor, p.line, p.line_information, p.line_chi2, p.across, p.extent, p.baseline, p.motion,
                          p.latest, p.observations, p.last_seen, p.group, p.confidence_sum, p.confidence_count,
                          p.corner_fit, p.edge_fit, p.corner_information, p.edge_information, p.corner_chi2,
                          p.edge_chi2, p.difference, p.modelled, p.curvature_decided, p.decision_distance)
        _start_support(p, slots, s.sensor, self.driven)
        self._fuse_models(s, rows, slots)
        return out

    def _start_walls(self, s: Sightings, rows) -> np.ndarray:
        """New walls from plane sightings ``rows``; their slots, -1 where the table is full."""
        slots = self._allocate(self._walls, rows.size)
        out = np.full(rows.size, -1)
        out[:slots.size] = slots
        rows = rows[:slots.size]
        w = self._walls
        position = s.position[rows]
        value, covariance = s.line(rows, position)
        along = _dot(s.segment[rows] - position[:, None, :], _left(s.normal[rows])[:, None, :])
        w.active[slots] = True
        w.uid[slots] = self._new_uids(slots.size)
        w.anchor[slots] = position
        w.line[slots] = value
        w.information[slots] = _inverse(covariance)
        w.extent[slots, 0], w.extent[slots, 1] = along.min(axis=1), along.max(axis=1)
        w.observations[slots] = 1
        w.last_seen[slots] = self._ping
        _start_support(w, slots, s.sensor, self.driven)
        w.group[slots] = s.group[rows]
        w.confidence_sum[slots] = s.confidence[rows]
        w.confidence_count[slots] = 1.0
        w.recentre(slots)
        return out

    # ------------------------------------------------------------------ fusion

    def _fuse_points(self, s: Sightings, rows, target):
        """Merge sightings ``rows`` into their points; the slots of all points stored to this ping.

        :func:`_fuse_point_sightings`, then the point models (:meth:`_fuse_models`).
        """
        stored = target[(target >= 0) & (target < self.max_points)]
        if rows.size:
            p, slots = self._points, target[rows]
            _fuse_point_sightings(slots, rows, s.landmark_class, s.position, s.information, s.confidence, s.normal,
                                  s.distance, s.covariance, s.segment, s.viewpoint, p.mean, p.information, p.chi2,
                                  p.latest, p.observations, p.landmark_class, p.by_motion, p.curvature_decided,
                                  p.confidence_sum, p.confidence_count, p.line, p.line_information, p.line_chi2,
                                  p.anchor, p.across, p.extent, p.baseline, p.motion)
            self._fuse_models(s, rows, slots)
        return np.unique(stored)

    def _fuse_models(self, s: Sightings, rows, slots) -> None:
        """Fuse the point models of sightings ``rows`` (those that have both) into points ``slots``.

        (:func:`_fuse_model_sightings`.)
        """
        if s.models is None:
            return
        p, m = self._points, s.models
        _fuse_model_sightings(slots, rows, m.valid, m.corner, m.edge, m.corner_covariance, m.edge_covariance,
                              m.separation_noise, p.curvature_decided, p.modelled, p.corner_fit, p.edge_fit,
                              p.corner_information, p.edge_information, p.corner_chi2, p.edge_chi2, p.difference)

    def _fuse_walls(self, s: Sightings, rows, target):
        """Merge sightings ``rows`` into their walls (:func:`_fuse_wall_sightings`); the walls whose segment grew."""
        if rows.size == 0:
            return np.empty(0, np.int64)
        w = self._walls
        return _fuse_wall_sightings(target[rows] - self.max_points, rows, s.landmark_class, s.normal, s.position,
                                    s.distance, s.covariance, s.segment, s.confidence, w.line, w.information,
                                    w.anchor, w.normal, w.tangent, w.extent, w.observations, w.confidence_sum,
                                    w.confidence_count)

    # ------------------------------------------------------------------ classes over motion

    def _resolve(self, slots) -> np.ndarray:
        """Decide the UNKNOWN points among ``slots`` by motion; the slots of walls made from points."""
        p = self._points
        open_slots = slots[p.landmark_class[slots] == UNKNOWN]
        named_plane = slots[p.landmark_class[slots] == PLANE]
        if open_slots.size == 0 and named_plane.size == 0:
            self._tell_edges_from_corners(slots)
            return np.empty(0, np.int64)
        difference = p.chi2[open_slots] - p.line_chi2[open_slots]
        winner = np.where(difference > 0, p.line_chi2[open_slots], p.chi2[open_slots])
        dof = 2.0 * (p.observations[open_slots] - 1)
        total, first, second = p.motion[open_slots].T
        separation = second - first ** 2 / total
        decided = ((p.baseline[open_slots, 1] - p.baseline[open_slots, 0] >= self.min_baseline)
                   & (separation >= self.min_separation)
                   & (np.abs(difference) >= self.decision_threshold)
                   & ((winner <= chi2_quantile(dof, CONSISTENCY_Z))
                      | ((difference > 0) & (winner <= PLANE_SPREAD * dof))))
        confidence = 1.0 - np.exp(-0.5 * np.abs(difference))
        fixed = decided & (difference < 0)
        plane = decided & (difference > 0)
        p.landmark_class[open_slots[fixed]] = CORNER_OR_EDGE
        p.by_motion[open_slots[fixed]] = True
        p.confidence_sum[open_slots[decided]] = confidence[decided]
        p.confidence_count[open_slots[decided]] = 1.0
        self._counts.resolved_fixed += int(np.count_nonzero(fixed))
        self._counts.resolved_plane += int(np.count_nonzero(plane))
        self._tell_edges_from_corners(slots)
        return self._points_to_walls(np.concatenate([named_plane, open_slots[plane]]))

    def _tell_edges_from_corners(self, slots) -> None:
        """Decide the fixed points among ``slots`` (CORNER_OR_EDGE, or named by a ping) by their curvature.

        :func:`sonar_ring.curvature.decide` on the points' two fits; a decision is
        final, with confidence ``1 - exp(-|Delta| / 2)``, and the point takes the
        winner's position.
        """
        p = self._points
        kind = p.landmark_class[slots]
        fixed = (kind == CORNER_OR_EDGE) | (kind == CORNER) | (kind == EDGE)
        slots = slots[fixed & ~p.curvature_decided[slots] & (p.modelled[slots] >= 2)]
        if slots.size == 0:
            return
        separation = p.difference[slots, 2] - _quadratic(p.difference[slots, :2], _inverse(p.corner_information[slots]))
        edge, corner, confidence = decide(p.corner_chi2[slots], p.edge_chi2[slots], separation, p.modelled[slots],
                                          self.curvature_threshold, self.min_separation)
        decided = edge | corner
        p.landmark_class[slots[edge]] = EDGE
        p.landmark_class[slots[corner]] = CORNER
        p.mean[slots[edge]] = p.edge_fit[slots[edge]]
        p.mean[slots[corner]] = p.corner_fit[slots[corner]]
        p.curvature_decided[slots[decided]] = True
        p.decision_distance[slots[decided]] = self.driven - p.first_driven[slots[decided]]
        p.by_motion[slots[decided]] = False
        p.confidence_sum[slots[decided]] = confidence[decided]
        p.confidence_count[slots[decided]] = 1.0
        self._counts.resolved_edge += int(np.count_nonzero(edge))
        self._counts.resolved_corner += int(np.count_nonzero(corner))

    def _points_to_walls(self, slots) -> np.ndarray:
        """Turn points ``slots`` into walls from their plane hypotheses; the new wall slots.

        A point that finds no room among the walls stays an UNKNOWN point.
        """
        if slots.size == 0:  # most pings that reach here turn nothing into a wall
            return np.empty(0, np.int64)
        p, w = self._points, self._walls
        walls = self._allocate(w, slots.size)
        p.landmark_class[slots[walls.size:]] = UNKNOWN
        slots = slots[:walls.size]
        w.active[walls] = True
        w.uid[walls] = self._new_uids(walls.size)
        self._renamed.update(zip(p.uid[slots].tolist(), w.uid[walls].tolist(), strict=True))
        w.anchor[walls] = p.anchor[slots]
        w.line[walls] = p.line[slots]
        w.information[walls] = p.line_information[slots]
        # The extent was measured along the first line of sight's tangent, within a
        # degree or so of the wall's.
        theta = p.line[slots, 0]
        tangent = np.stack([-np.sin(theta), np.cos(theta)], axis=-1)
        w.extent[walls] = np.sort(p.extent[slots] * _dot(tangent, p.across[slots])[:, None], axis=1)
        w.observations[walls] = p.observations[slots]
        w.last_seen[walls] = p.last_seen[slots]
        for column in ("pings", "origin", "travel", "explained", "unexplained", "first_driven"):
            getattr(w, column)[walls] = getattr(p, column)[slots]
        w.group[walls] = p.group[slots]
        w.confidence_sum[walls] = p.confidence_sum[slots]
        w.confidence_count[walls] = p.confidence_count[slots]
        p.active[slots] = False
        w.recentre(walls)
        return walls

    # ------------------------------------------------------------------ wall merging

    def _wall_matches(self, keep, other):
        """Compare walls ``other`` with walls ``keep`` (K,), about ``keep``'s anchors.

        Returns the gate ``d^2`` (with both floors), the gap between the segments (m,
        negative where they overlap), ``other``'s line innovation and its covariance
        without floor (for fusion), and ``other``'s end points along ``keep`` (K, 2).
        """
        w = self._walls
        return _match_walls(keep, other, w.anchor, w.line, w.information, w.normal, w.tangent, w.extent,
                            self.map_sigma)

    def _merge_walls(self, slots) -> None:
        """Let walls ``slots`` absorb every wall that matches them (gate, gap), until none does."""
        w = self._walls
        pending = slots
        while pending.size:
            others = np.flatnonzero(w.active)
            keep = np.repeat(pending, others.size)
            other = np.tile(others, pending.size)
            distinct = keep != other
            keep, other = keep[distinct], other[distinct]
            if keep.size == 0:
                return
            d2, gap, _, _, along = self._wall_matches(keep, other)
            hits = np.flatnonzero((d2 <= self.gate_chi2) & (gap <= self.search_radius))
            middle = 0.5 * (w.extent[keep[hits], 0] + w.extent[keep[hits], 1])
            hits = hits[~self._edge_between(keep[hits], middle, along[hits].mean(axis=1))]
            survivors = []
            for k in hits[np.argsort(d2[hits], kind="stable")]:
                a, b = keep[k], other[k]
                if w.active[a] and w.active[b]:
                    # The wall seen more often absorbs the other.
                    survivor, absorbed = (a, b) if w.observations[a] >= w.observations[b] else (b, a)
                    self._absorb_wall(survivor, absorbed)
                    survivors.append(survivor)
            pending = np.unique(np.asarray(survivors, dtype=np.int64))

    def _edge_between(self, walls, first, second) -> np.ndarray:
        """Whether an EDGE on the line of each wall ``walls`` (K,) lies strictly between ``first`` and ``second`` (K,).

        Both are positions along the wall's tangent from its anchor, m.  A wall ends at a convex edge: two walls
        on one line with an edge between their middles are the two sides of a doorway, however close their seen
        extents have come (an edge's echo placed a degree off, or a double bounce on the line, runs a seen extent
        past the wall's end), not one wall; and a sighting on the line beyond an edge past the wall's seen extent
        is not this wall's (:func:`_best_entries`).
        """
        p, w = self._points, self._walls
        return _edges_between(walls, first, second, w.anchor, w.tangent, w.normal, p.active, p.landmark_class, p.mean)

    def _absorb_wall(self, keep: int, other: int) -> None:
        w = self._walls
        keep_row, other_row = np.array([keep]), np.array([other])
        _, _, innovation, covariance, along = self._wall_matches(keep_row, other_row)
        _fuse_information(w.line, w.information, np.zeros(0), False, keep_row, keep_row,
                          np.ascontiguousarray(innovation, dtype=float), _inverse(covariance))
        w.line[keep, 0] = _wrap(w.line[keep, 0])
        w.extent[keep] = min(w.extent[keep, 0], along.min()), max(w.extent[keep, 1], along.max())
        w.observations[keep] += w.observations[other]
        w.last_seen[keep] = max(w.last_seen[keep], w.last_seen[other])
        _absorb_support(w, keep, other)
        w.confidence_sum[keep] += w.confidence_sum[other]
        w.confidence_count[keep] += w.confidence_count[other]
        w.active[other] = False
        self._renamed[int(w.uid[other])] = int(w.uid[keep])
        self._counts.merged_walls += 1
        w.recentre(keep_row)

    # ------------------------------------------------------------------ entries by uid

    def entries(self) -> Entries:
        """Every entry of the map: walls first, then points, each in table order (:class:`Entries`)."""
        w, p = self._walls, self._points
        walls, points = np.flatnonzero(w.active), np.flatnonzero(p.active)
        return Entries(
            uid=np.concatenate([w.uid[walls], p.uid[points]]),
            is_wall=np.concatenate([np.ones(walls.size, bool), np.zeros(points.size, bool)]),
            landmark_class=np.concatenate([np.full(walls.size, PLANE, np.uint8), p.landmark_class[points]]),
            position=np.concatenate([w.anchor[walls], p.mean[points]]),
            normal=np.concatenate([w.normal[walls], np.zeros((points.size, 2))]),
            observations=np.concatenate([w.observations[walls], p.observations[points]]),
        )

    def classes_of(self, uids) -> tuple[np.ndarray, np.ndarray]:
        """Whether each entry ``uids`` (K,) is a wall, and its class (PLANE for a wall), shape (K,) each.

        False and UNKNOWN where no active entry has the uid.  The same as looking the uids up in
        :meth:`entries`, without building them.
        """
        w, p = self._walls, self._points
        return _classes_of(np.asarray(uids, dtype=np.int64), w.uid, w.active, p.uid, p.active, p.landmark_class)

    def _slots(self, table, uids) -> np.ndarray:
        """The slots of ``table`` holding the active entries ``uids`` (-1 where none does)."""
        active = np.flatnonzero(table.active)
        by_uid = dict(zip(table.uid[active].tolist(), active.tolist(), strict=True))
        return np.array([by_uid.get(uid, -1) for uid in np.asarray(uids).tolist()], dtype=np.int64)

    def set_points(self, uids, position) -> None:
        """Move the points ``uids`` (K,) to ``position`` (K, 2) (a better estimate: a smoother's); others ignored."""
        slots = self._slots(self._points, np.asarray(uids, dtype=np.int64))
        found = slots >= 0
        self._points.mean[slots[found]] = np.asarray(position, dtype=float)[found]

    def set_walls(self, uids, theta, distance) -> None:
        """Move the walls ``uids`` (K,) to the lines ``n(theta) . x = distance`` (K,), keeping their seen extents.

        Each wall's middle moves perpendicularly onto its new line; others ignored.
        """
        slots = self._slots(self._walls, np.asarray(uids, dtype=np.int64))
        found = slots >= 0
        slots, theta, distance = slots[found], np.asarray(theta, float)[found], np.asarray(distance, float)[found]
        w = self._walls
        normal = np.stack([np.cos(theta), np.sin(theta)], axis=-1)
        w.anchor[slots] -= (_dot(normal, w.anchor[slots]) - distance)[:, None] * normal
        w.line[slots] = np.stack([theta, np.zeros(theta.size)], axis=-1)
        w.normal[slots] = normal
        w.tangent[slots] = _left(normal)

    def walls_ended_at(self, uids, points, reach: float, tolerance: float) -> LandmarkMap:
        """A copy of the map whose walls ``uids`` end at the points ``points`` (P, 2) on their lines near their ends.

        A wall ends at a corner or an edge.  A point within ``tolerance`` (m) of
        a wall's line and within ``reach`` (m) of an end of its seen extent, the
        nearest to that end, becomes that end: the extent grows or shrinks to it
        (what the wall's sightings near its ends, bearing-limited, blur).  A wall
        whose two ends both become the same point is that point's echoes seen
        along a line (a doorway jamb's, placed a degree off while the sensor
        passes), not a wall: the copy leaves it out.  For output: this map is
        unchanged, so what it maps next does not depend on when it was published.
        """
        ended = copy.copy(self)
        ended._walls = copy.deepcopy(self._walls)
        slots = ended._slots(ended._walls, np.asarray(uids, dtype=np.int64))
        slots = slots[slots >= 0]
        points = np.asarray(points, dtype=float).reshape(-1, 2)
        if not slots.size or not points.size:
            return ended
        w = ended._walls
        along, across = w.coordinates(slots, points)
        on_line = np.abs(across) <= tolerance
        end_point = np.full((slots.size, 2), -1)
        for end in (0, 1):
            gap = np.where(on_line, np.abs(along - w.extent[slots, end][:, None]), np.inf)
            nearest = np.argmin(gap, axis=1)
            close = gap[np.arange(slots.size), nearest] <= reach
            w.extent[slots[close], end] = along[close, nearest[close]]
            end_point[close, end] = nearest[close]
        w.extent[slots] = np.sort(w.extent[slots], axis=1)
        w.recentre(slots)
        w.active[slots[(end_point[:, 0] >= 0) & (end_point[:, 0] == end_point[:, 1])]] = False
        return ended

    # ------------------------------------------------------------------ output

    def decision_distances(self) -> np.ndarray:
        """How far the sensor moved from each point's first sighting until its curvature told it an edge or a corner.

        (D,) m, one per active point :mod:`sonar_ring.curvature` decided (the
        map's odometer, :attr:`driven`: the distance driven, not the straight
        line).
        """
        p = self._points
        return p.decision_distance[p.active & p.curvature_decided].copy()

    def persistent(self, uids) -> np.ndarray:
        """Which entries ``uids`` (K,) persist; (K,) bool (False for an entry not in the map).

        Persistent: seen in ``min_support_pings`` pings, the sensor ``min_support_travel`` from its first
        sighting's position at a later one.
        An echo that never repeats (clutter, noise) is never persistent; a real
        reflector seen briefly while passing (5 pings over 5 cm: a sixth of a
        second at 0.3 m/s) is.
        """
        persistent = np.zeros(len(uids), bool)
        for table in (self._points, self._walls):
            slots = self._slots(table, uids)
            found = slots >= 0
            persistent[found] = self._supported(table)[slots[found]]
        return persistent

    def decided(self, uids) -> np.ndarray:
        """Which entries ``uids`` (K,) are decided; (K,) bool (False for an entry not in the map).

        Decided: a wall, or a point of a known class -- not UNKNOWN, and not CORNER_OR_EDGE while its
        sightings carry curvature evidence (:mod:`sonar_ring.curvature`: a ring's) that has not yet told
        an edge from a corner.  A fixed point whose sensor gives no such evidence (a triad's) is decided
        as CORNER_OR_EDGE.
        """
        decided = np.zeros(len(uids), bool)
        walls, points = self._slots(self._walls, uids), self._slots(self._points, uids)
        decided[walls >= 0] = True
        decided[points >= 0] = self._decided_points()[points[points >= 0]]
        return decided

    def _decided_points(self) -> np.ndarray:
        """Which rows of the points table are decided (:meth:`decided`)."""
        p = self._points
        # A ring's true corners and edges decide within metres; what stays undecided there is,
        # in the realistic world, almost only multipath that no model fits.
        awaiting = (p.landmark_class == CORNER_OR_EDGE) & (p.modelled > 0)
        return (p.landmark_class != UNKNOWN) & ~awaiting

    def _supported(self, table) -> np.ndarray:
        """Which rows of ``table`` have the support of a persistent entry (:meth:`persistent`)."""
        return (table.pings >= self.min_support_pings) & (table.travel >= self.min_support_travel)

    def snapshot(self, min_observations: int = 1, only=None, persistent: bool = False,
                 decided: bool = False) -> Landmarks:
        """The map as landmarks in ``odom``: walls first, then points, each in table order.

        Parameters
        ----------
        min_observations : int
            Leave out entries with fewer sightings (1 keeps everything).
        only : array_like of int, optional
            Only these entries (uids, :meth:`entries`).
        persistent : bool
            Only the persistent entries (:meth:`persistent`).
        decided : bool
            Leave out the UNKNOWN points (neither motion nor a ping has told what they are), and the
            CORNER_OR_EDGE points whose sightings carry curvature evidence (:mod:`sonar_ring.curvature`:
            a ring's) until it tells them an edge or a corner; a fixed point whose sensor gives no such
            evidence (a triad's) stays in as CORNER_OR_EDGE.

        Returns
        -------
        Landmarks
            Walls: PLANE, ``position`` the middle of the segment, ``normal`` towards
            the side the wall was seen from, ``segment`` the seen extent's end points;
            the covariance has the line's offset variance at the middle (with the
            ``map_sigma`` floor) across the wall and, along it, that of a point spread
            evenly over the segment (``L^2 / 12``) plus the same.  Points: their class
            (UNKNOWN while undecided, placed with the corner model), fused position,
            covariance with the ``map_sigma`` floor, the point twice as ``segment``.
            ``observations`` counts the sightings; ``confidence`` is the motion test's
            ``1 - exp(-|Delta| / 2)`` for a class decided by motion, else the mean
            confidence of the classified sightings (0 if none); ``group`` is the first
            sighting's; ``echo`` 0; all valid.
        """
        walls, points = self._chosen(min_observations, only, persistent, decided)
        w, p = self._walls, self._points
        normal, tangent = w.normal[walls], w.tangent[walls]
        offset_variance = self._wall_covariance(walls)[:, 1, 1]
        along_variance = (w.extent[walls, 1] - w.extent[walls, 0]) ** 2 / 12.0 + offset_variance
        wall_covariance = (offset_variance[:, None, None] * normal[:, :, None] * normal[:, None, :]
                           + along_variance[:, None, None] * tangent[:, :, None] * tangent[:, None, :])
        count = walls.size + points.size

        def mean_confidence(table, rows):
            return table.confidence_sum[rows] / np.maximum(table.confidence_count[rows], 1.0)

        return Landmarks(
            landmark_class=np.concatenate([np.full(walls.size, PLANE), p.landmark_class[points]]).astype(np.uint8),
            position=np.concatenate([w.anchor[walls], p.mean[points]]),
            normal=np.concatenate([normal, np.zeros((points.size, 2))]),
            covariance=np.concatenate([wall_covariance, self._point_covariance(points)]),
            confidence=np.concatenate([mean_confidence(w, walls), mean_confidence(p, points)]).astype(np.float32),
            segment=np.concatenate([w.end_points(walls), np.repeat(p.mean[points][:, None, :], 2, axis=1)]),
            observations=np.concatenate([w.observations[walls], p.observations[points]]).astype(np.uint32),
            group=np.concatenate([w.group[walls], p.group[points]]).astype(np.uint16),
            echo=np.zeros(count, np.uint32),
            valid=np.ones(count, bool),
            reason=np.zeros(count, np.uint8),
        )

    def snapshot_uids(self, min_observations: int = 1, only=None, persistent: bool = False,
                      decided: bool = False) -> np.ndarray:
        """The uids of :meth:`snapshot`'s entries, in its order (walls, then points), (E,)."""
        walls, points = self._chosen(min_observations, only, persistent, decided)
        return np.concatenate([self._walls.uid[walls], self._points.uid[points]])

    def remove(self, uids) -> None:
        """Take the entries ``uids`` (K,) out of the map (uids it does not hold are ignored)."""
        uids = np.asarray(uids, dtype=np.int64)
        for table in (self._walls, self._points):
            slots = self._slots(table, uids)
            table.active[slots[slots >= 0]] = False

    def _chosen(self, min_observations: int, only, persistent: bool, decided: bool) -> tuple[np.ndarray, np.ndarray]:
        """Slots of the walls and points chosen as :meth:`snapshot` says."""
        chosen = []
        for table in (self._walls, self._points):
            keep = table.active & (table.observations >= min_observations)
            if persistent:
                keep &= self._supported(table)
            if decided and table is self._points:
                keep &= self._decided_points()
            if only is not None:
                keep &= np.isin(table.uid, np.asarray(only, dtype=np.int64))
            chosen.append(np.flatnonzero(keep))
        return chosen[0], chosen[1]

    def points(self, min_observations: int = 1, only=None, persistent: bool = False,
               decided: bool = False) -> np.ndarray:
        """Landmark points for a costmap, shape (P, 2), ``odom``, m.

        Every wall is sampled from end to end at equal steps no longer than
        ``wall_point_spacing`` (at least its two end points), followed by the fused
        position of every point entry (corners, edges and UNKNOWN reflectors), in the
        order of :meth:`snapshot`.

        Parameters
        ----------
        min_observations : int
            Leave out entries with fewer sightings.
        only : array_like of int, optional
            Only these entries (uids, :meth:`entries`).
        persistent : bool
            Only the persistent entries (:meth:`persistent`).
        decided : bool
            Leave out the UNKNOWN points.
        """
        walls, points = self._chosen(min_observations, only, persistent, decided)
        w, p = self._walls, self._points
        ends = w.end_points(walls)
        length = w.extent[walls, 1] - w.extent[walls, 0]
        samples = np.ceil(length / self.wall_point_spacing).astype(np.int64) + 1
        samples = np.maximum(samples, 2)
        wall = np.repeat(np.arange(walls.size), samples)
        index = np.arange(wall.size) - np.repeat(np.cumsum(samples) - samples, samples)
        fraction = (index / (samples[wall] - 1))[:, None]
        along_walls = ends[wall, 0] + fraction * (ends[wall, 1] - ends[wall, 0])
        return np.concatenate([along_walls.reshape(-1, 2), p.mean[points]])


def load_kernels() -> None:
    """Load the map's compiled kernels now instead of at the first update.

    Loading starts numba and reads the cached machine code of each kernel; a
    process that maps on a deadline pays that at start.  A scratch map sees
    two walls, a corner, an edge on their line and two unknown reflectors
    (one explained in the later pings) from three poses, with their point models,
    looks up its entries' classes and makes its snapshot: every kernel's path
    with the production argument types.  The point models' own loop
    (:func:`sonar_ring.curvature.load_kernels`) too.
    """
    load_curvature_kernels()
    scratch = LandmarkMap()
    spread = np.array([[-0.02, 0.0], [0.02, 0.0]])
    classes = np.array([PLANE, PLANE, CORNER, UNKNOWN, EDGE, UNKNOWN])
    covariance = np.tile(1e-4 * np.eye(2), (6, 1, 1))
    for x in (0.0, 0.2, 0.4):
        position = np.array([[x, 1.0], [x + 2.0, 1.0], [1.5, -1.2], [-1.0, 0.5], [3.5, 1.0], [0.5, -2.5]])
        models = PointModels(position, position, covariance, covariance, np.zeros(6), classes != PLANE)
        normal = np.zeros((6, 2))
        normal[:2, 1] = 1.0
        placed = scratch.update(make_landmarks(classes, position, normal=normal, covariance=covariance,
                                               segment=position[:, None, :] + spread,
                                               confidence=np.array([0.9, 0.9, 0.9, 0.0, 0.9, 0.0])),
                                (x, 0.0, 0.0), models, np.array([False] * 5 + [x > 0.0]))
        scratch.classes_of(placed.uid)
    scratch.snapshot()
