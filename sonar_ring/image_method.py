"""Sound paths between walls and points: legs that cross a wall, double bounces by the image method.

One geometry for the world and for the map.  The forward model
(:mod:`sonar_ring.simulate`) blocks its paths with :func:`blocked_legs` and
measures its walls with :func:`wall_frames`; the realistic world
(:mod:`sonar_ring.realism`) makes its multipath echoes with :func:`double_bounces`
from the scene's walls and edges; the map's explanation of echoes
(:mod:`sonar_ring.explain`) predicts the same paths from the map's walls and
points with :func:`map_paths`, which bounces by the same functions, matches
echoes to them with :func:`match_rows` and tests landmark hypotheses with
:func:`reflections_blocked`, which blocks by the same test, a wall from its front only;
:func:`explain_rows` runs a ping's match, its rules (:func:`multipath_rows`) and
that test in one call.

Walls are vertical planes given as segments ``[[x0, y0], [x1, y1]]``
(:func:`wall_frames` gives each its start, unit direction, unit normal and
length); points are vertical lines (edges, corners, poles) that diffract.  A
double bounce from transmitter ``T`` to receiver ``R`` is one of

* **wall -> wall** (``a`` then ``b``): the image ``T_ab`` of ``T`` in ``a`` and
  then in ``b``; horizontal length ``|T_ab - R|``; the last bounce is where
  ``R -> T_ab`` crosses ``b``, the first where that point ``-> T_a`` crosses ``a``;
* **wall -> point** (``a`` then ``P``): ``|T_a - P| + |P - R|``, the bounce where
  ``P -> T_a`` crosses ``a``;
* **point -> wall** (``P`` then ``b``): ``|T - P| + |P - R_b|``, the bounce where
  ``P -> R_b`` crosses ``b``;

and a single bounce, an entry's own echo, is a wall's (``|T_b - R|``, the
bounce where ``R -> T_b`` crosses ``b``) or a point's (``|T - P| + |P - R|``).  A
path exists where every bounce lies on its wall's segment (within ``margin`` of
it) and comes from the side the sound arrives on: each crossing is strict, so a
point on a wall's line, or a transducer on it, has no path by that wall.  The
3-D path is ``sqrt(h**2 + dz**2)`` of the horizontal one ``h``, ``dz`` the
transmitter's height above the receiver's.

All positions in one frame (the world's or the map's), m.  The loops are numba
kernels (:mod:`sonar_ring.compiled`): a ping's paths are thousands of scalar
computations, each a few operations, where numpy would spend its time starting
operations.  Their arithmetic is that of the numpy code they replaced, operation
for operation, so the forward model's and the realistic world's echoes are the
same to the last bit.  One module, because a kernel calls kernels of its own
module only.
"""

from __future__ import annotations

import math

import numpy as np

from sonar_ring.compiled import kernel

WALL_WALL, WALL_POINT, POINT_WALL = 0, 1, 2
"""Kinds of double bounce: first reflector then second (:func:`double_bounces`)."""

WALL, POINT = 3, 4
"""Kinds of single bounce, a reflector's own echo (:func:`map_paths` predicts them beside the double bounces)."""

KIND_NAMES = ("wall-wall", "wall-point", "point-wall", "wall", "point")
"""Name of each kind code, indexable by the code."""

_SLACK = 1e-9
"""m and rad added to the pruning's cones, sides and extents, so that rounding never drops a path at their edge."""

_BOX_SLACK = 1e-6
"""m: how much :func:`_leg_blocked` grows the bounding boxes it compares (rounding is below 1e-9 m at 1 km)."""

LEG_END_FRACTION = 1e-9
"""Fraction of a leg's length at either end where crossing a wall is not a
blockage: legs start and end *on* the reflecting walls."""


@kernel
def wall_frames(walls):
    """Start, unit direction, unit normal and length of wall segments.

    Parameters
    ----------
    walls : ndarray, shape (W, 2, 2)
        Segments ``[[x0, y0], [x1, y1]]``, m.

    Returns
    -------
    start, direction, normal : ndarray, shape (W, 2)
        First end point (m), unit vector from it to the second, and that vector
        turned 90 deg counter-clockwise (NaN for a segment of no length).
    length : ndarray, shape (W,)
        m.
    """
    count = walls.shape[0]
    start = np.empty((count, 2))
    direction = np.empty((count, 2))
    normal = np.empty((count, 2))
    length = np.empty(count)
    for w in range(count):
        start[w, 0], start[w, 1] = walls[w, 0, 0], walls[w, 0, 1]
        vector_x, vector_y = walls[w, 1, 0] - walls[w, 0, 0], walls[w, 1, 1] - walls[w, 0, 1]
        length[w] = math.hypot(vector_x, vector_y)
        direction[w, 0], direction[w, 1] = vector_x / length[w], vector_y / length[w]
        normal[w, 0], normal[w, 1] = -direction[w, 1], direction[w, 0]
    return start, direction, normal, length


def load_kernels() -> None:
    """Load the compiled kernels now instead of at the first blocked leg or multipath path.

    A process that simulates or explains pings on a deadline pays numba's start
    here; runs each kernel with the argument types of production.
    """
    walls = np.array([[[0.0, 0.0], [1.0, 0.0]], [[1.0, 0.0], [1.0, 1.0]]])
    blocked_legs(np.zeros((1, 2)), np.ones((1, 2)), walls)
    start, direction, normal, length = wall_frames(walls)
    index = np.zeros(1, dtype=np.int64)
    double_bounces(index, index, index + 1, index, index, start, direction, normal, length, np.zeros((1, 2)),
                   np.full((1, 1, 2), 0.5), np.full((1, 2, 2), 0.5), 0.0)


# --------------------------------------------------------------------------- blocking


@kernel
def blocked_legs(starts, ends, walls):
    """Whether each leg ``starts[i] -> ends[i]`` crosses any wall.

    Parameters
    ----------
    starts, ends : ndarray, shape (n, 2)
        Leg end points, m.
    walls : ndarray, shape (W, 2, 2)
        Wall segments, m.

    Returns
    -------
    ndarray of bool, shape (n,)
        True where a wall crosses the leg strictly between its ends (beyond
        :data:`LEG_END_FRACTION` of its length from each): touching a wall at a
        leg's end (the leg's own reflection point) does not count, nor does
        running along a wall (parallel), nor a leg with a non-finite end.
    """
    hit = np.zeros(starts.shape[0], dtype=np.bool_)
    length = _lengths(walls)
    every_wall = np.zeros(walls.shape[0])  # support 0, least 0: every wall blocks
    for i in range(starts.shape[0]):
        hit[i] = _leg_blocked(starts[i, 0], starts[i, 1], ends[i, 0], ends[i, 1], walls, length, 0.0, every_wall, 0.0)
    return hit


@kernel
def _lengths(walls):
    """Length of each wall (W, 2, 2), m."""
    length = np.empty(walls.shape[0])
    for w in range(walls.shape[0]):
        length[w] = math.hypot(walls[w, 1, 0] - walls[w, 0, 0], walls[w, 1, 1] - walls[w, 0, 1])
    return length


@kernel(inline=True)
def _leg_blocked(x0, y0, x1, y1, walls, length, wall_margin, support, least):
    """:func:`blocked_legs` for one leg ``(x0, y0) -> (x1, y1)``; ``length`` (W,) the walls' lengths, m.

    Crossings within ``wall_margin`` (m) of a wall's ends do not count (0: every crossing does), nor walls
    whose ``support`` (W,) is below ``least``.
    """
    rx, ry = x1 - x0, y1 - y0
    # A crossing lies in both segments' bounding boxes: most walls are skipped before the divisions.  The
    # boxes grow by a slack far above rounding, so the test decides nothing the fractions would not.
    leg_low_x, leg_high_x = min(x0, x1) - _BOX_SLACK, max(x0, x1) + _BOX_SLACK
    leg_low_y, leg_high_y = min(y0, y1) - _BOX_SLACK, max(y0, y1) + _BOX_SLACK
    for w in range(walls.shape[0]):
        if support[w] < least:
            continue
        ax, ay = walls[w, 0, 0], walls[w, 0, 1]
        bx, by = walls[w, 1, 0], walls[w, 1, 1]
        if (max(ax, bx) < leg_low_x or min(ax, bx) > leg_high_x or max(ay, by) < leg_low_y
                or min(ay, by) > leg_high_y):
            continue
        sx, sy = bx - ax, by - ay
        trim = wall_margin / length[w] if wall_margin > 0 else 0.0
        denominator = rx * sy - ry * sx
        apx, apy = ax - x0, ay - y0
        along_leg = (apx * sy - apy * sx) / denominator
        along_wall = (apx * ry - apy * rx) / denominator
        if (denominator != 0 and along_leg > LEG_END_FRACTION and along_leg < 1 - LEG_END_FRACTION
                and along_wall >= trim and along_wall <= 1 - trim):
            return True
    return False


@kernel
def double_bounces(kind, first, second, group, slot, start, direction, normal, length, points, tx, rx, margin):
    """Double-bounce paths by the image method, one candidate per row, every receiver of its group.

    Parameters
    ----------
    kind : ndarray of int, shape (Q,)
        :data:`WALL_WALL`, :data:`WALL_POINT` or :data:`POINT_WALL`.
    first, second : ndarray of int, shape (Q,)
        The first and the second reflector: a row of the walls or of ``points``,
        whichever ``kind`` says.
    group, slot : ndarray of int, shape (Q,)
        The receiver group and its transmitter slot.
    start, direction, normal : ndarray, shape (W, 2)
        The walls as :func:`wall_frames` gives them (contiguous), m.
    length : ndarray, shape (W,)
        m.
    points : ndarray, shape (P, 2)
        Diffracting points, m.
    tx : ndarray, shape (G, M, 2)
        Each group's transmitters, m.
    rx : ndarray, shape (G, K, 2)
        Each group's receivers, m.
    margin : float
        How far beyond a segment's ends a bounce may lie, m (0: on the segment).

    Returns
    -------
    horizontal : ndarray, shape (Q, K)
        Horizontal path length ``T -> first -> second -> R``, m.
    exists : ndarray of bool, shape (Q, K)
        Where the path is geometrically possible (module docstring).
    first_point, last_point : ndarray, shape (Q, K, 2)
        Where the transmitted ray first meets a reflector and where the received
        ray last leaves one, m (meaningful where ``exists``).
    """
    count, receivers = kind.shape[0], rx.shape[1]
    horizontal = np.empty((count, receivers))
    exists = np.zeros((count, receivers), dtype=np.bool_)
    first_point = np.empty((count, receivers, 2))
    last_point = np.empty((count, receivers, 2))
    for q in range(count):
        tx_x, tx_y = tx[group[q], slot[q], 0], tx[group[q], slot[q], 1]
        for k in range(receivers):
            rx_x, rx_y = rx[group[q], k, 0], rx[group[q], k, 1]
            if kind[q] == WALL_WALL:
                path = _wall_wall(tx_x, tx_y, rx_x, rx_y, first[q], second[q], start, direction, normal, length,
                                  margin)
            elif kind[q] == WALL_POINT:
                path = _wall_point(tx_x, tx_y, rx_x, rx_y, first[q], points[second[q], 0], points[second[q], 1],
                                   start, direction, normal, length, margin)
            else:
                path = _point_wall(tx_x, tx_y, rx_x, rx_y, points[first[q], 0], points[first[q], 1], second[q],
                                   start, direction, normal, length, margin)
            horizontal[q, k], exists[q, k] = path[0], path[1]
            first_point[q, k, 0], first_point[q, k, 1] = path[2], path[3]
            last_point[q, k, 0], last_point[q, k, 1] = path[4], path[5]
    return horizontal, exists, first_point, last_point


@kernel(inline=True)
def _side(x, y, wall, start, normal):
    """Signed distance of ``(x, y)`` from the line of ``wall``, positive on its normal's side, m."""
    return (x - start[wall, 0]) * normal[wall, 0] + (y - start[wall, 1]) * normal[wall, 1]


@kernel(inline=True)
def _crossing(inside_x, inside_y, inside_side, image_x, image_y, image_side, wall, start, direction, length, margin):
    """Where segment inside -> image crosses the line of ``wall``, and whether it does so on the segment.

    ``inside_side`` and ``image_side`` are the two points' signed distances
    from the line (opposite signs where it crosses); the crossing is at
    ``inside + inside_side / (inside_side - image_side) (image - inside)`` and
    counts within ``margin`` of the segment's ends.
    """
    crosses = inside_side * image_side < 0
    fraction = inside_side / (inside_side - image_side) if crosses else 0.0
    x = inside_x + fraction * (image_x - inside_x)
    y = inside_y + fraction * (image_y - inside_y)
    along = (x - start[wall, 0]) * direction[wall, 0] + (y - start[wall, 1]) * direction[wall, 1]
    return x, y, crosses and along >= -margin and along <= length[wall] + margin


@kernel(inline=True)
def _wall_wall(tx_x, tx_y, rx_x, rx_y, a, b, start, direction, normal, length, margin):
    """T -> wall ``a`` -> wall ``b`` -> R: ``(horizontal, exists, first x, y, last x, y)``."""
    t_side = _side(tx_x, tx_y, a, start, normal)
    image_a_x, image_a_y = tx_x - 2.0 * t_side * normal[a, 0], tx_y - 2.0 * t_side * normal[a, 1]
    image_a_side = _side(image_a_x, image_a_y, b, start, normal)
    image_ab_x = image_a_x - 2.0 * image_a_side * normal[b, 0]
    image_ab_y = image_a_y - 2.0 * image_a_side * normal[b, 1]
    r_side = _side(rx_x, rx_y, b, start, normal)
    # The last bounce, on wall b: where R -> T_ab crosses it (T_a and R on one side of it).
    last_x, last_y, on_b = _crossing(rx_x, rx_y, r_side, image_ab_x, image_ab_y, -image_a_side, b, start, direction,
                                     length, margin)
    # The first, on wall a: where that point -> T_a crosses it (the point and T on one side of it).
    last_side = _side(last_x, last_y, a, start, normal)
    first_x, first_y, on_a = _crossing(last_x, last_y, last_side, image_a_x, image_a_y, -t_side, a, start, direction,
                                       length, margin)
    horizontal = _norm(image_ab_x - rx_x, image_ab_y - rx_y)
    return horizontal, on_a and on_b and image_a_side * r_side > 0, first_x, first_y, last_x, last_y


@kernel(inline=True)
def _via_wall(p_x, p_y, x, y, wall, start, direction, normal, length, margin):
    """Point P and a transducer X by way of ``wall``: ``(|P - X_w|, exists, bounce x, y)``.

    ``X_w`` is the image of X in the wall; the bounce is where ``P -> X_w``
    crosses it, and exists where that is on the segment (P and X on one side).
    """
    x_side = _side(x, y, wall, start, normal)
    image_x, image_y = x - 2.0 * x_side * normal[wall, 0], y - 2.0 * x_side * normal[wall, 1]
    p_side = _side(p_x, p_y, wall, start, normal)
    bounce_x, bounce_y, on_wall = _crossing(p_x, p_y, p_side, image_x, image_y, -x_side, wall, start, direction,
                                            length, margin)
    return _norm(p_x - image_x, p_y - image_y), on_wall, bounce_x, bounce_y


@kernel(inline=True)
def _wall_point(tx_x, tx_y, rx_x, rx_y, a, p_x, p_y, start, direction, normal, length, margin):
    """T -> wall ``a`` -> point P -> R: ``(horizontal, exists, first x, y, last x, y)``."""
    out, on_wall, bounce_x, bounce_y = _via_wall(p_x, p_y, tx_x, tx_y, a, start, direction, normal, length, margin)
    return out + _norm(p_x - rx_x, p_y - rx_y), on_wall, bounce_x, bounce_y, p_x, p_y


@kernel(inline=True)
def _point_wall(tx_x, tx_y, rx_x, rx_y, p_x, p_y, b, start, direction, normal, length, margin):
    """T -> point P -> wall ``b`` -> R: ``(horizontal, exists, first x, y, last x, y)``."""
    back, on_wall, bounce_x, bounce_y = _via_wall(p_x, p_y, rx_x, rx_y, b, start, direction, normal, length, margin)
    return _norm(p_x - tx_x, p_y - tx_y) + back, on_wall, p_x, p_y, bounce_x, bounce_y


# --------------------------------------------------------------------------- the map's paths to one ping


@kernel
def junctions(walls, points, gap):
    """Which walls meet, and which points lie on a wall: within ``gap`` (m) of each other.

    Parameters
    ----------
    walls : ndarray, shape (W, 2, 2)
        Segments, m.
    points : ndarray, shape (P, 2)
        m.
    gap : float
        m.

    Returns
    -------
    meet : ndarray of bool, shape (W, W)
        Symmetric: the segments cross or come within ``gap`` of each other.
    on_wall : ndarray of bool, shape (W, P)
        The point is within ``gap`` of the segment.
    """
    count = walls.shape[0]
    meet = np.zeros((count, count), dtype=np.bool_)
    on_wall = np.zeros((count, points.shape[0]), dtype=np.bool_)
    # Each wall's bounding box grown by the gap: what lies outside it is farther than the gap.
    box = np.empty((count, 4))
    for w in range(count):
        box[w, 0], box[w, 1] = min(walls[w, 0, 0], walls[w, 1, 0]) - gap, max(walls[w, 0, 0], walls[w, 1, 0]) + gap
        box[w, 2], box[w, 3] = min(walls[w, 0, 1], walls[w, 1, 1]) - gap, max(walls[w, 0, 1], walls[w, 1, 1]) + gap
    for a in range(count):
        for b in range(a + 1, count):
            if box[b, 1] < box[a, 0] or box[b, 0] > box[a, 1] or box[b, 3] < box[a, 2] or box[b, 2] > box[a, 3]:
                continue
            near = _segments_cross(walls, a, b)
            for end in range(2):
                near = near or _segment_distance(walls[b, end, 0], walls[b, end, 1], walls, a) <= gap
                near = near or _segment_distance(walls[a, end, 0], walls[a, end, 1], walls, b) <= gap
            meet[a, b] = meet[b, a] = near
        for p in range(points.shape[0]):
            on_wall[a, p] = (box[a, 0] <= points[p, 0] <= box[a, 1] and box[a, 2] <= points[p, 1] <= box[a, 3]
                             and _segment_distance(points[p, 0], points[p, 1], walls, a) <= gap)
    return meet, on_wall


@kernel
def map_paths(start, direction, normal, length, seen_extent, points, wall_support, point_support, excluded_pair,
              excluded_point, tx, rx, tx_axis, rx_axis, height_offset, transmitter, row_channel, row_paths, pose,
              max_path, acceptance, pose_covariance, xy_sigma, yaw_sigma, sigma_path, sigma_speed, sigma_map,
              gate_sigmas, isotropic, prune, gated, doubles):
    """The paths, double and single bounces, a map of walls and points sends to one ping's channels' receivers.

    The engine of :func:`sonar_ring.explain.predict`, whose docstring gives the
    model, the margins and the pruning.  Paths exist as :func:`double_bounces`
    says (within the extent margin of the segments), fit the receive window
    ``max_path`` (3-D length with ``height_offset``), arrive within the widened acceptance angle
    (and leave a directional transmitter within it), and have no leg that a
    wall crosses where it was seen, away from the leg's reflecting ends and
    the wall's own, if it was seen at least as often as the least seen of the
    path's reflectors (a ghost must not hide the better-seen entries' double
    bounce that explains it; the rule of :func:`sonar_ring.explain.match`'s
    caller for an entry's own echo).  Two
    passes: the candidates that pass the pruning (and, where ``gated``, come
    near a measured row by their lengths); their geometry and tests.

    Parameters
    ----------
    start, direction, normal : ndarray, shape (W, 2)
        The walls as :func:`wall_frames` gives them, m.
    length : ndarray, shape (W,)
        m.
    seen_extent : ndarray, shape (W, 2, 2)
        Where each wall was seen, m: the segment that blocks legs (a wall grown
        to where it ends reflects there, but blocks only where it was seen).
        Walls of no length or with a non-finite value give no path; such
        a seen segment blocks nothing.
    points : ndarray, shape (P, 2)
        Diffracting points, m; non-finite ones give no path.
    wall_support, point_support : ndarray, shape (W,) and (P,)
        How often each wall and point was seen (observations); zeros: every wall blocks.
    excluded_pair : ndarray of bool, shape (W, W)
        Wall pairs whose double bounce is not a path to predict (a corner's own echo).
    excluded_point : ndarray of bool, shape (W, P)
        Wall and point pairs likewise (a wall's end or corner).
    tx, rx : ndarray, shape (G, M, 2) and (G, K, 2)
        Transmitters and receivers, m (:class:`sonar_ring.simulate.Placement`).
    tx_axis, rx_axis : ndarray, shape (G, M, 1, 2) and (G, 1, K, 2)
        Their unit axes.
    height_offset : ndarray, shape (G, M, K)
        Transmitter minus receiver height, m.
    transmitter : ndarray of int, shape (G, M)
        Which transmitter each slot is (what depends on the transmitter alone is computed once).
    row_channel : ndarray of int, shape (N,)
        Channel ``group * M + slot`` of each echo row: the channels to predict.
    row_paths : ndarray, shape (N, K)
        Where ``gated``, the rows' measured paths, m, NaN where not heard.
    pose : ndarray, shape (3,)
        The sensor's pose (x, y, yaw), m and rad.
    max_path : float
        Longest 3-D path the receivers report (the receive window), m.
    acceptance : float
        Acceptance half-angle of the transducers, rad.
    pose_covariance : ndarray, shape (3, 3)
    xy_sigma, yaw_sigma : float
        The pose's position error along its worst direction (m) and its yaw error (rad).
    sigma_path, sigma_speed, sigma_map, gate_sigmas : float
        The tolerance (:class:`sonar_ring.explain.Tolerance`); where ``gated``,
        a path is kept only if some row of its channel is within Mahalanobis
        distance ``gate_sigmas`` of it (:func:`match_rows`).
    isotropic, prune, gated, doubles : bool
        An isotropic emitter (no transmit beam); prune (:mod:`sonar_ring.explain`,
        "Pruning"); keep only paths near a measured row; the double bounces too (else each entry's own
        echo only).

    Returns
    -------
    kind, first, second, group, slot : ndarray of int, shape (Q,)
        Each path's kind, reflectors (rows of the walls or points) and channel, sorted by channel.
    support : ndarray, shape (Q,)
        The observations of its less seen reflector (``wall_support``, ``point_support``).
    path : ndarray, shape (Q, K)
        3-D length to each receiver, m, NaN where that receiver gets none.
    jacobian : ndarray, shape (Q, K, 3)
        Its derivative by the pose (x, y, yaw): ``h / d (e_T + e_R, e_T . (T - S)^perp + e_R . (R - S)^perp)``.
    first_point, last_point : ndarray, shape (Q, K, 2)
        The first and the last reflection, m.
    channel_start : ndarray of int, shape (G * M + 1,)
        The paths of channel ``i`` are rows ``channel_start[i]:channel_start[i + 1]``.
    """
    n_walls, n_points = start.shape[0], points.shape[0]
    slots, receivers = tx.shape[1], rx.shape[1]
    all_channels = tx.shape[0] * slots
    seen_length = _lengths(seen_extent)
    # The margins (sonar_ring.explain, "Tolerance"): a transducer's position error, the transducers being at
    # most ``spread`` from the pose's position; how far a bounce may lie beyond a segment's ends or a wall's
    # crossing from a leg's or a wall's ends (extent), and the acceptance angle's widening, yaw_margin +
    # position_margin / distance.
    spread = 0.0
    for g in range(tx.shape[0]):
        for m in range(slots):
            spread = max(spread, math.hypot(tx[g, m, 0] - pose[0], tx[g, m, 1] - pose[1]))
        for k in range(receivers):
            spread = max(spread, math.hypot(rx[g, k, 0] - pose[0], rx[g, k, 1] - pose[1]))
    position = xy_sigma + spread * yaw_sigma
    extent_margin = gate_sigmas * (position + sigma_map)
    yaw_margin = gate_sigmas * yaw_sigma
    position_margin = gate_sigmas * (2.0 * position + sigma_map)
    # The largest variance of a receiver's path but for the speed's term: |J_xy| <= 2, |J_yaw| <= 2 spread.
    fixed_variance = sigma_path ** 2 + 4.0 * position ** 2 + 8.0 * sigma_map ** 2
    # The rows of each channel (a counting sort), and the channels that have rows.
    row_start = np.zeros(all_channels + 1, dtype=np.int64)
    for n in range(row_channel.shape[0]):
        row_start[row_channel[n] + 1] += 1
    channels = 0
    for i in range(all_channels):
        channels += row_start[i + 1] > 0
        row_start[i + 1] += row_start[i]
    row_order = np.empty(row_channel.shape[0], dtype=np.int64)
    filled = row_start.copy()
    for n in range(row_channel.shape[0]):
        row_order[filled[row_channel[n]]] = n
        filled[row_channel[n]] += 1
    channel_id = np.empty(channels, dtype=np.int64)
    c = 0
    for i in range(all_channels):
        if row_start[i + 1] > row_start[i]:
            channel_id[c] = i
            c += 1

    ends = np.empty((n_walls, 2, 2))
    for w in range(n_walls):
        for axis in range(2):
            ends[w, 0, axis] = start[w, axis] - extent_margin * direction[w, axis]
            ends[w, 1, axis] = start[w, axis] + (length[w] + extent_margin) * direction[w, axis]
    # Range: entries farther than this from the centre give no path.
    reach = 0.5 * max_path + spread + _SLACK
    wall_near = np.ones(n_walls, dtype=np.bool_)
    point_near = np.ones(n_points, dtype=np.bool_)
    # Beam: an entry's paths arrive within ``acceptance + yaw_margin + position_margin / distance`` of a
    # transducer's axis, the distance at least the entry's from the centre less the spread: the widest such
    # cone of each entry, as its half-angle's cosine and sine (NaN: as wide as a half-plane or more, all seen).
    wall_cone = np.full((n_walls, 2), np.nan)
    point_cone = np.full((n_points, 2), np.nan)
    for w in range(n_walls):
        distance = _segment_distance(pose[0], pose[1], ends, w)
        usable = np.isfinite(length[w]) and length[w] > 0 and np.isfinite(start[w, 0]) and np.isfinite(start[w, 1])
        wall_near[w] = usable and (not prune or distance <= reach)
        _widest_cone(wall_cone, w, distance - spread, acceptance, yaw_margin, position_margin, prune)
    for p in range(n_points):
        distance = math.hypot(points[p, 0] - pose[0], points[p, 1] - pose[1])
        point_near[p] = np.isfinite(distance) and (not prune or distance <= reach)
        _widest_cone(point_cone, p, distance - spread, acceptance, yaw_margin, position_margin, prune)
    # Sides of every wall's (extended) ends and of every point from each wall's line.
    end_side = np.empty((n_walls, n_walls, 2))
    point_side = np.empty((n_walls, n_points))
    for a in range(n_walls):
        for b in range(n_walls):
            for end in range(2):
                end_side[a, b, end] = _side(ends[b, end, 0], ends[b, end, 1], a, start, normal)
        for p in range(n_points):
            point_side[a, p] = _side(points[p, 0], points[p, 1], a, start, normal)

    # What each receiver of each channel sees: walls with a part in its cone, with the cone from its image
    # in the wall through that part (where first reflections lie), and points in its cone; a directional
    # transmitter's cone likewise marks what it sends to.
    wall_seen = np.zeros((channels, receivers, n_walls), dtype=np.bool_)
    wall_seen_any = np.zeros((channels, n_walls), dtype=np.bool_)
    mirror = np.zeros((channels, receivers, n_walls, 6))
    point_seen_any = np.zeros((channels, n_points), dtype=np.bool_)
    point_x, point_y = np.ascontiguousarray(points[:, 0]), np.ascontiguousarray(points[:, 1])
    point_cos, point_sin = np.ascontiguousarray(point_cone[:, 0]), np.ascontiguousarray(point_cone[:, 1])
    wall_sent = np.ones((channels, n_walls), dtype=np.bool_)
    point_sent = np.ones((channels, n_points), dtype=np.bool_)
    for c in range(channels):
        g, m = channel_id[c] // slots, channel_id[c] % slots
        for k in range(receivers):
            rx_x, rx_y, axis_x, axis_y = rx[g, k, 0], rx[g, k, 1], rx_axis[g, 0, k, 0], rx_axis[g, 0, k, 1]
            for w in range(n_walls):
                if wall_near[w]:
                    seen, low, high = _part_in_cone(rx_x, rx_y, axis_x, axis_y, wall_cone, ends, w)
                    wall_seen[c, k, w] = seen
                    wall_seen_any[c, w] = wall_seen_any[c, w] or seen
                    if seen and prune:
                        _mirror_cone(mirror, c, k, rx_x, rx_y, w, ends, low, high, start, normal)
            _points_in_cone(point_seen_any[c], rx_x, rx_y, axis_x, axis_y, point_cos, point_sin, point_x, point_y,
                            point_near)
        if not isotropic:
            for w in range(n_walls):
                wall_sent[c, w] = _part_in_cone(tx[g, m, 0], tx[g, m, 1], tx_axis[g, m, 0, 0], tx_axis[g, m, 0, 1],
                                                wall_cone, ends, w)[0]
            point_sent[c] = False
            _points_in_cone(point_sent[c], tx[g, m, 0], tx[g, m, 1], tx_axis[g, m, 0, 0], tx_axis[g, m, 0, 1],
                            point_cos, point_sin, point_x, point_y, point_near)

    # What depends on the transmitter alone, computed once for all its channels: its images in every wall
    # and pair of walls, its distance to every point, and the first bounce of every wall -> point path.
    n_transmitters = 0
    for c in range(channels):
        n_transmitters = max(n_transmitters, transmitter[channel_id[c] // slots, channel_id[c] % slots] + 1)
    double_image = np.empty((n_transmitters, n_walls, n_walls, 2))
    to_point = np.empty((n_transmitters, n_points))
    via_length = np.empty((n_transmitters, n_walls, n_points))
    via_exists = np.zeros((n_transmitters, n_walls, n_points), dtype=np.bool_)
    via_bounce = np.empty((n_transmitters, n_walls, n_points, 2))
    done = np.zeros(n_transmitters, dtype=np.bool_)
    for c in range(channels):
        g, m = channel_id[c] // slots, channel_id[c] % slots
        t = transmitter[g, m]
        if done[t]:
            continue
        done[t] = True
        tx_x, tx_y = tx[g, m, 0], tx[g, m, 1]
        for p in range(n_points):
            to_point[t, p] = math.hypot(points[p, 0] - tx_x, points[p, 1] - tx_y)
        for a in range(n_walls):
            side = _side(tx_x, tx_y, a, start, normal)
            image_x, image_y = tx_x - 2.0 * side * normal[a, 0], tx_y - 2.0 * side * normal[a, 1]
            for b in range(n_walls):
                side = _side(image_x, image_y, b, start, normal)
                double_image[t, a, b, 0] = image_x - 2.0 * side * normal[b, 0]
                double_image[t, a, b, 1] = image_y - 2.0 * side * normal[b, 1]
            for p in range(n_points):
                if wall_near[a] and point_near[p] and not excluded_point[a, p]:
                    (via_length[t, a, p], via_exists[t, a, p], via_bounce[t, a, p, 0],
                     via_bounce[t, a, p, 1]) = _via_wall(points[p, 0], points[p, 1], tx_x, tx_y, a, start, direction,
                                                         normal, length, extent_margin)

    # Pass 1: the candidates that pass the pruning, with their horizontal lengths (walls' bounces not yet
    # placed); where gated, channel by channel, only those near a measured row of their channel, with which
    # rows (bits of the row's place in its channel; the 64th: any from there on).  Near: within the gate at
    # every receiver that heard the row, with the largest variance a pose error could give
    # (:func:`_row_intervals`); a candidate is checked at the first receiver of each row as it is found
    # (most are near none: 350 of 1592 a ping of the explain bench are kept), then at all of them.  These
    # lengths only choose what pass 2 computes again with the bounces placed.  At most: every seen wall or point
    # alone, and last with every entry (a point: every wall) first.
    capacity = 0
    for c in range(channels):
        for w in range(n_walls):
            capacity += (1 + n_walls + n_points) * wall_seen_any[c, w]
        for p in range(n_points):
            capacity += (1 + n_walls) * point_seen_any[c, p]
    kind = np.empty(capacity, dtype=np.int64)
    first = np.empty(capacity, dtype=np.int64)
    second = np.empty(capacity, dtype=np.int64)
    channel = np.empty(capacity, dtype=np.int64)
    horizontal = np.empty((capacity, receivers))
    near_rows = np.zeros(capacity, dtype=np.uint64)
    low, high = _row_intervals(row_paths, gate_sigmas, fixed_variance, sigma_speed)
    squared = np.empty(receivers)
    image_distance = np.empty(receivers)
    baseline = np.empty((receivers, receivers))
    back = np.empty(receivers)
    transmitter_side = np.empty(n_walls)
    receiver_side = np.empty(receivers)
    receiver_image = np.empty((receivers, 2))
    heard_row = np.empty(row_channel.shape[0], dtype=np.int64)
    first_heard = np.empty(row_channel.shape[0], dtype=np.int64)
    in_mirror = np.empty(n_points, dtype=np.bool_)
    first_low = np.empty(row_channel.shape[0])
    first_high = np.empty(row_channel.shape[0])
    count = 0
    for c in range(channels):
        g, m = channel_id[c] // slots, channel_id[c] % slots
        t = transmitter[g, m]
        channel_first = count
        # Each row of the channel at the first receiver that heard it (the gate below asks the same of every
        # receiver that heard a row).
        rows = 0
        for r in range(row_start[channel_id[c]], row_start[channel_id[c] + 1]):
            n = row_order[r]
            for k in range(receivers):
                if low[n, k] <= high[n, k]:
                    heard_row[rows], first_heard[rows], first_low[rows], first_high[rows] = r, k, low[n, k], high[n, k]
                    rows += 1
                    break
        for a in range(n_walls):
            transmitter_side[a] = _side(tx[g, m, 0], tx[g, m, 1], a, start, normal)
        for b in range(n_walls):
            if not wall_seen_any[c, b]:
                continue
            for k in range(receivers):
                receiver_side[k] = _side(rx[g, k, 0], rx[g, k, 1], b, start, normal)
                receiver_image[k, 0] = rx[g, k, 0] - 2.0 * receiver_side[k] * normal[b, 0]
                receiver_image[k, 1] = rx[g, k, 1] - 2.0 * receiver_side[k] * normal[b, 1]
                horizontal[count, k] = _norm(tx[g, m, 0] - receiver_image[k, 0],
                                             tx[g, m, 1] - receiver_image[k, 1])
            kind[count], first[count], second[count], channel[count] = WALL, b, b, c
            count += not gated or _near_first_heard(horizontal, count, height_offset, g, m, first_heard,
                                                   first_low, first_high, rows)
            for a in range(n_walls if doubles else 0):
                if a == b or excluded_pair[a, b] or not wall_near[a] or not wall_sent[c, a]:
                    continue
                if prune:
                    if max(end_side[a, b, 0] * transmitter_side[a], end_side[a, b, 1] * transmitter_side[a]) <= -_SLACK:
                        continue  # no part of b on the transmitter's side of a
                    kept = False
                    for k in range(receivers):
                        kept = kept or (
                            wall_seen[c, k, b]
                            and max(end_side[b, a, 0] * receiver_side[k],
                                    end_side[b, a, 1] * receiver_side[k]) > -_SLACK
                            and _clip_to_wedge(mirror[c, k, b, 0], mirror[c, k, b, 1], mirror[c, k, b, 2],
                                               mirror[c, k, b, 3], mirror[c, k, b, 4], mirror[c, k, b, 5], ends, a)[0])
                    if not kept:
                        continue
                for k in range(receivers):
                    horizontal[count, k] = _norm(double_image[t, a, b, 0] - rx[g, k, 0],
                                                 double_image[t, a, b, 1] - rx[g, k, 1])
                kind[count], first[count], second[count], channel[count] = WALL_WALL, a, b, c
                count += not gated or _near_first_heard(horizontal, count, height_offset, g, m, first_heard,
                                                   first_low, first_high, rows)
            if doubles and prune:
                _points_in_mirror(in_mirror, wall_seen, mirror, c, b, point_side, receiver_side, point_x, point_y)
            for p in range(n_points if doubles else 0):
                if excluded_point[b, p] or not point_near[p] or not point_sent[c, p] or (prune and not in_mirror[p]):
                    continue
                for k in range(receivers):
                    horizontal[count, k] = to_point[t, p] + _norm(points[p, 0] - receiver_image[k, 0],
                                                                  points[p, 1] - receiver_image[k, 1])
                kind[count], first[count], second[count], channel[count] = POINT_WALL, p, b, c
                count += not gated or _near_first_heard(horizontal, count, height_offset, g, m, first_heard,
                                                   first_low, first_high, rows)
        for p in range(n_points):
            if not point_seen_any[c, p]:
                continue
            for k in range(receivers):
                back[k] = _norm(points[p, 0] - rx[g, k, 0], points[p, 1] - rx[g, k, 1])
                horizontal[count, k] = to_point[t, p] + back[k]
            kind[count], first[count], second[count], channel[count] = POINT, p, p, c
            count += not gated or _near_first_heard(horizontal, count, height_offset, g, m, first_heard,
                                                   first_low, first_high, rows)
            for a in range(n_walls if doubles else 0):
                if excluded_point[a, p] or not wall_near[a] or not wall_sent[c, a] or not via_exists[t, a, p]:
                    continue
                for k in range(receivers):
                    horizontal[count, k] = via_length[t, a, p] + back[k]
                kind[count], first[count], second[count], channel[count] = WALL_POINT, a, p, c
                count += not gated or _near_first_heard(horizontal, count, height_offset, g, m, first_heard,
                                                   first_low, first_high, rows)
        if gated:
            near_count = channel_first
            first_row = row_start[channel_id[c]]
            for k in range(receivers):  # once a channel, not for every candidate and row
                for j in range(receivers):
                    baseline[k, j] = math.hypot(rx[g, k, 0] - rx[g, j, 0], rx[g, k, 1] - rx[g, j, 1])
            for q in range(channel_first, count):
                # Every path comes to each receiver from one point X, this far away, after a leg common to all
                # the receivers: the differences between receivers must match too (_differences_near).  A point's
                # paths and a wall -> point path leave the transmitter the same way for every receiver, X the last
                # point or the first one's image in the last wall, fixed in the map; a wall's and a wall -> wall
                # path come from the transmitter's image in its walls, which moves with the pose.
                moving = kind[q] == WALL or kind[q] == WALL_WALL
                for k in range(receivers):
                    squared[k] = horizontal[q, k] ** 2 + height_offset[g, m, k] ** 2
                    image_distance[k] = horizontal[q, k] - (0.0 if moving else via_length[t, first[q], second[q]]
                                                            if kind[q] == WALL_POINT else to_point[t, first[q]])
                mask = np.uint64(0)
                for j in range(rows):
                    if not first_low[j] <= squared[first_heard[j]] <= first_high[j]:
                        continue
                    r = heard_row[j]
                    n = row_order[r]
                    near = True
                    for k in range(receivers):
                        if low[n, k] <= high[n, k]:
                            near = near and low[n, k] <= squared[k] <= high[n, k]
                    near = near and _differences_near(row_paths, n, horizontal, q, squared, image_distance,
                                                      baseline, spread, xy_sigma, yaw_sigma, sigma_path, sigma_speed,
                                                      gate_sigmas, 2.0 if moving else 1.0)
                    if near:
                        mask |= np.uint64(1) << np.uint64(min(r - first_row, 63))
                if mask:
                    kind[near_count], first[near_count], second[near_count] = kind[q], first[q], second[q]
                    channel[near_count], near_rows[near_count] = c, mask
                    near_count += 1
            count = near_count

    # Pass 2: each candidate's geometry, receive window and derivative; where gated, whether a row of its channel is
    # within the gate of it (the Mahalanobis distance of :func:`match_rows`); then beams and blocking.
    out_kind = np.empty(count, dtype=np.int64)
    out_first = np.empty(count, dtype=np.int64)
    out_second = np.empty(count, dtype=np.int64)
    out_group = np.empty(count, dtype=np.int64)
    out_slot = np.empty(count, dtype=np.int64)
    out_support = np.empty(count)
    path = np.empty((count, receivers))
    jacobian = np.empty((count, receivers, 3))
    first_point = np.empty((count, receivers, 2))
    last_point = np.empty((count, receivers, 2))
    channel_start = np.zeros(all_channels + 1, dtype=np.int64)
    scratch = _work_arrays(receivers)
    variance = np.empty((1, receivers))
    kept_count = 0
    for q in range(count):
        g, m = channel_id[channel[q]] // slots, channel_id[channel[q]] % slots
        t = transmitter[g, m]
        a, b = first[q], second[q]
        if kind[q] == WALL_WALL:
            least = min(wall_support[a], wall_support[b])
        elif kind[q] == POINT_WALL:
            least = min(point_support[a], wall_support[b])
        elif kind[q] == WALL_POINT:
            least = min(wall_support[a], point_support[b])
        elif kind[q] == WALL:
            least = wall_support[b]
        else:
            least = point_support[b]
        reaches = False
        for k in range(receivers):
            if kind[q] == WALL_WALL:
                h, exists, first_x, first_y, last_x, last_y = _wall_wall(
                    tx[g, m, 0], tx[g, m, 1], rx[g, k, 0], rx[g, k, 1], a, b, start, direction, normal, length,
                    extent_margin)
            elif kind[q] == POINT_WALL:
                h, exists, first_x, first_y, last_x, last_y = _point_wall(
                    tx[g, m, 0], tx[g, m, 1], rx[g, k, 0], rx[g, k, 1], points[a, 0], points[a, 1], b, start,
                    direction, normal, length, extent_margin)
            elif kind[q] == WALL_POINT:
                h = via_length[t, a, b] + _norm(points[b, 0] - rx[g, k, 0], points[b, 1] - rx[g, k, 1])
                exists, first_x, first_y = True, via_bounce[t, a, b, 0], via_bounce[t, a, b, 1]
                last_x, last_y = points[b, 0], points[b, 1]
            elif kind[q] == WALL:
                h, exists, first_x, first_y = _via_wall(rx[g, k, 0], rx[g, k, 1], tx[g, m, 0], tx[g, m, 1], b, start,
                                                        direction, normal, length, extent_margin)
                last_x, last_y = first_x, first_y
            else:
                h = to_point[t, b] + _norm(points[b, 0] - rx[g, k, 0], points[b, 1] - rx[g, k, 1])
                exists, first_x, first_y, last_x, last_y = True, points[b, 0], points[b, 1], points[b, 0], points[b, 1]
            first_point[kept_count, k, 0], first_point[kept_count, k, 1] = first_x, first_y
            last_point[kept_count, k, 0], last_point[kept_count, k, 1] = last_x, last_y
            distance = math.sqrt(h ** 2 + height_offset[g, m, k] ** 2)
            path[kept_count, k] = distance if exists and distance <= max_path else np.nan
            for axis in range(3):
                jacobian[kept_count, k, axis] = 0.0
            if not np.isfinite(path[kept_count, k]):
                continue
            reaches = True
            out_x, out_y = _unit(tx[g, m, 0] - first_x, tx[g, m, 1] - first_y)
            in_x, in_y = _unit(rx[g, k, 0] - last_x, rx[g, k, 1] - last_y)
            scale = h / distance
            jacobian[kept_count, k, 0] = scale * (out_x + in_x)
            jacobian[kept_count, k, 1] = scale * (out_y + in_y)
            jacobian[kept_count, k, 2] = scale * (out_y * (tx[g, m, 0] - pose[0]) - out_x * (tx[g, m, 1] - pose[1])
                                                  + in_y * (rx[g, k, 0] - pose[0]) - in_x * (rx[g, k, 1] - pose[1]))
        if not reaches:
            continue
        if gated:
            _variances(variance, 0, path, jacobian, kept_count, pose_covariance, sigma_path, sigma_speed, sigma_map)
            near = False
            first_row = row_start[channel_id[channel[q]]]
            for r in range(first_row, row_start[channel_id[channel[q]] + 1]):
                if near or not (near_rows[q] >> np.uint64(min(r - first_row, 63))) & np.uint64(1):
                    continue
                near = (_near_at_every_receiver(row_paths, row_order[r], path, kept_count, variance, 0, gate_sigmas)
                        and _distance2(row_paths, row_order[r], path, jacobian, kept_count, pose_covariance,
                                       sigma_path, sigma_speed, sigma_map, scratch) <= gate_sigmas ** 2)
            if not near:
                continue
        heard = False
        # The legs from the transmitter to the first point and on to the last are one for every receiver that
        # shares those points (a point's own echo, a bounce onto a point): each is tested once.
        first_leg_x, first_leg_y, first_leg_blocked = np.nan, np.nan, False
        middle_leg_x, middle_leg_y, middle_leg_blocked = np.nan, np.nan, False
        for k in range(receivers):
            if not np.isfinite(path[kept_count, k]):
                continue
            first_x, first_y = first_point[kept_count, k, 0], first_point[kept_count, k, 1]
            last_x, last_y = last_point[kept_count, k, 0], last_point[kept_count, k, 1]
            audible = _accepted(last_x, last_y, rx[g, k, 0], rx[g, k, 1], rx_axis[g, 0, k, 0], rx_axis[g, 0, k, 1],
                                acceptance, yaw_margin, position_margin)
            if not isotropic:
                audible = audible and _accepted(first_x, first_y, tx[g, m, 0], tx[g, m, 1], tx_axis[g, m, 0, 0],
                                                tx_axis[g, m, 0, 1], acceptance, yaw_margin, position_margin)
            if audible and not (first_x == first_leg_x and first_y == first_leg_y):
                first_leg_x, first_leg_y = first_x, first_y
                first_leg_blocked = _shortened_leg_blocked(tx[g, m, 0], tx[g, m, 1], first_x, first_y, 0.0,
                                                           extent_margin, seen_extent, seen_length, extent_margin,
                                                           wall_support, least)
                middle_leg_x = np.nan  # its first point moved
            audible = audible and not first_leg_blocked
            if audible and not (first_x == first_leg_x and first_y == first_leg_y and last_x == middle_leg_x
                                and last_y == middle_leg_y):
                middle_leg_x, middle_leg_y = last_x, last_y
                middle_leg_blocked = _shortened_leg_blocked(first_x, first_y, last_x, last_y, extent_margin,
                                                            extent_margin, seen_extent, seen_length, extent_margin,
                                                            wall_support, least)
            audible = audible and not middle_leg_blocked and not _shortened_leg_blocked(
                last_x, last_y, rx[g, k, 0], rx[g, k, 1], extent_margin, 0.0, seen_extent, seen_length,
                extent_margin, wall_support, least)
            if audible:
                heard = True
            else:
                path[kept_count, k] = np.nan
                for axis in range(3):
                    jacobian[kept_count, k, axis] = 0.0
        if heard:
            out_kind[kept_count], out_first[kept_count], out_second[kept_count] = kind[q], a, b
            out_group[kept_count], out_slot[kept_count], out_support[kept_count] = g, m, least
            channel_start[channel_id[channel[q]] + 1] += 1
            kept_count += 1
    for i in range(all_channels):
        channel_start[i + 1] += channel_start[i]
    return (out_kind[:kept_count], out_first[:kept_count], out_second[:kept_count], out_group[:kept_count],
            out_slot[:kept_count], out_support[:kept_count], path[:kept_count], jacobian[:kept_count],
            first_point[:kept_count], last_point[:kept_count], channel_start)


@kernel(inline=True)
def _points_in_mirror(in_mirror, wall_seen, mirror, c, b, point_side, receiver_side, point_x, point_y):
    """Into ``in_mirror`` (P,): which points some receiver of channel ``c`` that sees wall ``b`` hears by way of it.

    A point on the receiver's side of the wall, inside the cone from the receiver's image through the part of
    the wall in its beam (``mirror[c, k, b]``, :func:`_mirror_cone`; :func:`_in_wedge`).  A loop over the points
    for each receiver, which the compiler runs several points at a time.
    """
    in_mirror[:] = False
    for k in range(wall_seen.shape[1]):
        if not wall_seen[c, k, b]:
            continue
        apex_x, apex_y, left_x, left_y = mirror[c, k, b, 0], mirror[c, k, b, 1], mirror[c, k, b, 2], mirror[c, k, b, 3]
        right_x, right_y, side = mirror[c, k, b, 4], mirror[c, k, b, 5], receiver_side[k]
        for p in range(point_x.shape[0]):
            in_mirror[p] |= (point_side[b, p] * side > -_SLACK) & _in_wedge(apex_x, apex_y, left_x, left_y, right_x,
                                                                             right_y, point_x[p], point_y[p])


@kernel(inline=True)
def _near_first_heard(horizontal, q, height_offset, g, m, first_heard, low, high, rows):
    """Whether candidate ``q`` of channel (g, m) is near one of the channel's ``rows`` at its first receiver.

    Near: its squared 3-D length at receiver ``first_heard[j]`` within ``low[j]``..``high[j]`` (m^2), what the
    gate asks of that receiver (:func:`_row_intervals`).
    """
    near = False
    for j in range(rows):  # without a branch per row: which rows are near is as good as random
        k = first_heard[j]
        squared = horizontal[q, k] ** 2 + height_offset[g, m, k] ** 2
        near |= (low[j] <= squared) & (squared <= high[j])
    return near


@kernel(inline=True)
def _norm(x, y):
    """``sqrt(x^2 + y^2)``: the lengths of the paths and their legs.

    Within an ulp or two of ``math.hypot``, which numba calls in libm at several times the cost (7 % of
    :func:`map_paths`' time); no length here comes near the overflow or underflow ``hypot`` guards against.
    """
    return math.sqrt(x * x + y * y)


@kernel
def _row_intervals(row_paths, gate_sigmas, fixed_variance, sigma_speed):
    """The squared 3-D path lengths near each row at each receiver, ``low`` and ``high`` (N, K), m^2.

    Near: ``|measured - d| <= gate_sigmas sqrt(fixed_variance + sigma_speed^2 d^2)``, a
    quadratic inequality in ``d`` whose roots bound an interval (none above when
    ``gate_sigmas sigma_speed >= 1``); widened by a slack against rounding.  NaN rows give
    an empty interval.
    """
    low = np.full(row_paths.shape, np.inf)
    high = np.full(row_paths.shape, -np.inf)
    spread = (gate_sigmas * sigma_speed) ** 2
    for n in range(row_paths.shape[0]):
        for k in range(row_paths.shape[1]):
            measured = row_paths[n, k]
            if not np.isfinite(measured):
                continue
            root = math.sqrt(spread * measured ** 2 + (1.0 - spread) * gate_sigmas ** 2 * fixed_variance)
            lowest = max((measured - root) / (1.0 - spread), 0.0) if spread < 1 else 0.0
            highest = (measured + root) / (1.0 - spread) if spread < 1 else np.inf
            low[n, k] = (max(lowest * (1.0 - 1e-12) - _SLACK, 0.0)) ** 2
            high[n, k] = (highest * (1.0 + 1e-12) + _SLACK) ** 2
    return low, high


@kernel(inline=True)
def _differences_near(row_paths, n, horizontal, q, squared, image_distance, baseline, spread, xy_sigma, yaw_sigma,
                      sigma_path, sigma_speed, gate_sigmas, ends):
    """Whether the differences between row ``n``'s receivers match those of candidate ``q`` within the gate.

    For a path that comes to receiver k from one point X at ``image_distance[k]``
    after a leg common to every receiver: a pose error moves receiver k's path
    less the reference's (the first that heard the row) by ``(J_k - J_r) . delta``.
    With ``e`` the unit vectors from X (``|e_k - e_r| <= 2 b / max |R - X|``, ``b = |R_k -
    R_r|``), ``s = h / d`` and ``rho`` the spread: where X is fixed in the map (a
    point, or a point's image in a wall: ``ends`` 1) only the receivers' ends of
    the paths turn, and ``|J_k - J_r|`` is at most ``s_k |e_k - e_r| + 2 |s_k - s_r|`` in
    (x, y) and ``s_k (|e_k - e_r| rho + b) + 2 rho |s_k - s_r|`` in yaw; where X is the
    transmitter's image in walls (``ends`` 2), it moves with the transmitter by a
    reflection or a rotation, so the transmitter's end turns by as much: ``2 s_k
    |e_k - e_r| + 2 |s_k - s_r|`` and ``s_k (2 |e_k - e_r| rho + b) + 2 rho |s_k - s_r|``.
    The map's error moves every receiver's path alike (:func:`match_rows`' model)
    and cancels; so the squared difference of the
    errors is at most ``gate_sigmas^2 (2 sigma_path^2 + (|dJ_xy| xy_sigma + |dJ_yaw| yaw_sigma)^2
    + sigma_speed^2 (d_k - d_r)^2)`` for a row within the gate (the Mahalanobis
    distance bounds that of any difference).  ``squared`` (K,): the 3-D lengths squared; ``baseline`` (K, K): the
    distances between the channel's receivers, m.
    """
    reference = -1
    for k in range(row_paths.shape[1]):
        if not np.isfinite(row_paths[n, k]):
            continue
        if reference < 0:
            reference = k
            continue
        length, reference_length = math.sqrt(squared[k]), math.sqrt(squared[reference])
        scale, reference_scale = horizontal[q, k] / length, horizontal[q, reference] / reference_length
        turn = 2.0 * baseline[k, reference] / max(image_distance[k], image_distance[reference])
        change = abs(scale - reference_scale)
        along = scale * turn * ends + 2.0 * change
        around = scale * (turn * spread * ends + baseline[k, reference]) + 2.0 * spread * change
        variance = (2.0 * sigma_path ** 2 + (along * xy_sigma + around * yaw_sigma) ** 2
                    + sigma_speed ** 2 * (length - reference_length) ** 2)
        error = (row_paths[n, k] - row_paths[n, reference]) - (length - reference_length)
        if error ** 2 > gate_sigmas ** 2 * variance * (1.0 + 1e-9) + _SLACK ** 2:
            return False
    return True


@kernel
def match_rows(channel, paths, channel_start, kind, support, predicted, jacobian, pose_covariance, sigma_path,
               sigma_speed, sigma_map, gate_sigmas):
    """Each echo row's closest double bounce and closest single bounce of its channel, by Mahalanobis distance.

    The engine of :func:`sonar_ring.explain.match`, whose module docstring gives the covariance.

    Parameters
    ----------
    channel : ndarray of int, shape (N,)
        Each row's channel ``group * M + slot``.
    paths : ndarray, shape (N, K)
        Measured paths, m; NaN where a receiver heard nothing.
    channel_start : ndarray of int, shape (G * M + 1,)
        The predicted paths of channel i are rows ``channel_start[i]:channel_start[i + 1]`` of
    kind, support : ndarray, shape (Q,)
        their kinds, the observations of their less seen reflector,
    predicted, jacobian : ndarray, shape (Q, K) and (Q, K, 3)
        3-D lengths (NaN: not to this receiver) and derivatives by the pose.
    pose_covariance : ndarray, shape (3, 3)
    sigma_path, sigma_speed, sigma_map : float
        m, relative, m.
    gate_sigmas : float
        Paths farther than ``gate_sigmas`` standard deviations from the row at one of
        its receivers are not considered (they cannot be within the gate).

    Returns
    -------
    double, single : ndarray of int, shape (N,)
        The closest double bounce and the closest single bounce; -1 where none
        reaches every receiver that heard the row within the gate there.
    double_distance, single_distance : ndarray, shape (N,)
        Their Mahalanobis distances; inf where none, NaN where no receiver heard the row.
    double_support : ndarray, shape (N,)
        The highest ``support`` of a double bounce within the gate; -inf where none.
    """
    rows = paths.shape[0]
    best = np.full((2, rows), -1, dtype=np.int64)
    distance = np.full((2, rows), np.inf)
    double_support = np.full(rows, -np.inf)
    scratch = _work_arrays(paths.shape[1])
    variance = np.empty(predicted.shape)
    gate2 = gate_sigmas ** 2
    for q in range(predicted.shape[0]):
        _variances(variance, q, predicted, jacobian, q, pose_covariance, sigma_path, sigma_speed, sigma_map)
    for n in range(rows):
        heard = False
        for k in range(paths.shape[1]):
            heard = heard or np.isfinite(paths[n, k])
        if not heard:
            distance[:, n] = np.nan
            continue
        for q in range(channel_start[channel[n]], channel_start[channel[n] + 1]):
            if not _near_at_every_receiver(paths, n, predicted, q, variance, q, gate_sigmas):
                continue
            squared = _distance2(paths, n, predicted, jacobian, q, pose_covariance, sigma_path, sigma_speed, sigma_map,
                                 scratch)
            bounces = 1 if kind[q] == WALL or kind[q] == POINT else 0
            if squared < distance[bounces, n]:
                distance[bounces, n], best[bounces, n] = squared, q
            if bounces == 0 and squared <= gate2 and support[q] > double_support[n]:
                double_support[n] = support[q]
    return best[0], best[1], np.sqrt(distance[0]), np.sqrt(distance[1]), double_support


@kernel
def _work_arrays(receivers):
    """Work arrays for :func:`_distance2`: heard receivers, errors, covariance, covariance times derivative."""
    return (np.empty(receivers, dtype=np.int64), np.empty(receivers), np.empty((receivers, receivers)),
            np.empty((receivers, 3)))


@kernel(inline=True)
def _variances(variance, row, predicted, jacobian, q, pose_covariance, sigma_path, sigma_speed, sigma_map):
    """Into ``variance[row]`` (K,): each receiver's variance of predicted path ``q``, the diagonal of the covariance."""
    for k in range(predicted.shape[1]):
        pose = 0.0
        for i in range(3):
            for j in range(3):
                pose += jacobian[q, k, i] * pose_covariance[i, j] * jacobian[q, k, j]
        variance[row, k] = pose + sigma_speed ** 2 * predicted[q, k] ** 2 + 8.0 * sigma_map ** 2 + sigma_path ** 2


@kernel(inline=True)
def _near_at_every_receiver(paths, n, predicted, q, variance, row, gate_sigmas):
    """Whether path ``q`` reaches every receiver that heard row ``n`` within ``gate_sigmas`` standard deviations there.

    ``variance[row]`` (K,) the path's variances: necessary for a Mahalanobis
    distance within the gate, as ``e^T C^-1 e >= e_k^2 / C_kk``.
    """
    heard = False
    for k in range(paths.shape[1]):
        if np.isfinite(paths[n, k]):
            heard = True
            if not (paths[n, k] - predicted[q, k]) ** 2 <= gate_sigmas ** 2 * variance[row, k]:
                return False
    return heard


@kernel(inline=True)
def _distance2(paths, n, predicted, jacobian, q, pose_covariance, sigma_path, sigma_speed, sigma_map, scratch):
    """Squared Mahalanobis distance of row ``n`` of ``paths`` from predicted path ``q``.

    Over the receivers that heard the row; inf where the path does not reach
    one of them, NaN where none heard it or the covariance is not positive definite.
    """
    heard, error, covariance, spread = scratch
    count = 0
    for k in range(paths.shape[1]):
        if np.isfinite(paths[n, k]):
            if not np.isfinite(predicted[q, k]):
                return np.inf
            heard[count] = k
            count += 1
    if count == 0:
        return np.nan
    for i in range(count):
        k = heard[i]
        error[i] = paths[n, k] - predicted[q, k]
        for j in range(3):
            spread[i, j] = (jacobian[q, k, 0] * pose_covariance[0, j] + jacobian[q, k, 1] * pose_covariance[1, j]
                            + jacobian[q, k, 2] * pose_covariance[2, j])
    for i in range(count):
        for j in range(count):
            row, column = heard[i], heard[j]
            covariance[i, j] = (spread[i, 0] * jacobian[q, column, 0] + spread[i, 1] * jacobian[q, column, 1]
                                + spread[i, 2] * jacobian[q, column, 2]
                                + sigma_speed ** 2 * predicted[q, row] * predicted[q, column] + 8.0 * sigma_map ** 2)
        covariance[i, i] += sigma_path ** 2
    # Cholesky in place, then the squared norm of L^-1 e.
    for j in range(count):
        diagonal = covariance[j, j]
        for i in range(j):
            diagonal -= covariance[j, i] ** 2
        if not diagonal > 0:
            return np.nan
        covariance[j, j] = math.sqrt(diagonal)
        for i in range(j + 1, count):
            value = covariance[i, j]
            for h in range(j):
                value -= covariance[i, h] * covariance[j, h]
            covariance[i, j] = value / covariance[j, j]
    total = 0.0
    for i in range(count):
        value = error[i]
        for h in range(i):
            value -= covariance[i, h] * error[h]
        error[i] = value / covariance[i, i]
        total += error[i] ** 2
    return total


@kernel
def reflections_blocked(points, group, slot, tx, rx, walls, normal, margin):
    """Whether a straight leg to or from each hypothesis' reflection points crosses a wall, the point behind it.

    Parameters
    ----------
    points : ndarray, shape (L, K, 2)
        Where each hypothesis reflects the sound to each receiver of its group, m; NaN: left out.
    group, slot : ndarray of int, shape (L,)
        The group and transmitter slot of its echo.
    tx, rx : ndarray, shape (G, M, 2) and (G, K, 2)
        Transmitters and receivers, m.
    walls : ndarray, shape (W, 2, 2)
        m.
    normal : ndarray, shape (W, 2)
        Each wall's unit normal towards its front, the side it was seen from.
    margin : ndarray, shape (L,)
        m: a wall the point lies less than this behind (across the wall's line:
        a point uncertain by ``margin`` may be on it), or crossed within this of
        its ends, does not count.

    Returns
    -------
    ndarray of bool, shape (L,)
        Some leg transmitter -> point or receiver -> point crosses a wall
        strictly between its ends, from the wall's front, with the point more
        than ``margin`` behind it.  A leg from behind a wall does not count: a
        wall seen from one side only is known to reflect there, and a point
        heard from its other side is evidence against the wall, not against the
        point (a ghost wall mapped in front of a pillar's face must not hide
        the face).
    """
    length = _lengths(walls)
    blocked = np.zeros(points.shape[0], dtype=np.bool_)
    for n in range(points.shape[0]):
        g, m = group[n], slot[n]
        for k in range(points.shape[1]):
            x, y = points[n, k, 0], points[n, k, 1]
            if blocked[n] or not (np.isfinite(x) and np.isfinite(y)):
                continue
            # A corner's, an edge's or an undecided point's legs from the transmitter are one for all receivers.
            same = k > 0 and x == points[n, k - 1, 0] and y == points[n, k - 1, 1]
            blocked[n] = ((not same and _behind_wall(tx[g, m, 0], tx[g, m, 1], x, y, walls, normal, length, margin[n]))
                          or _behind_wall(rx[g, k, 0], rx[g, k, 1], x, y, walls, normal, length, margin[n]))
    return blocked


@kernel(inline=True)
def _behind_wall(x0, y0, x1, y1, walls, normal, length, margin):
    """Whether the leg from ``(x0, y0)`` to the point ``(x1, y1)`` crosses a wall the point lies ``margin`` behind.

    The crossing must lie strictly inside the leg and at least ``margin`` from the wall's ends; the point must
    lie more than ``margin`` (m) behind the wall's line, on the side opposite its ``normal`` (so the leg
    starts in front of it).
    """
    rx, ry = x1 - x0, y1 - y0
    for w in range(walls.shape[0]):
        ax, ay = walls[w, 0, 0], walls[w, 0, 1]
        sx, sy = walls[w, 1, 0] - ax, walls[w, 1, 1] - ay
        denominator = rx * sy - ry * sx
        if denominator == 0:
            continue
        apx, apy = ax - x0, ay - y0
        along_leg = (apx * sy - apy * sx) / denominator
        along_wall = (apx * ry - apy * rx) / denominator
        trim = margin / length[w]
        behind = -((x1 - ax) * normal[w, 0] + (y1 - ay) * normal[w, 1])
        if (along_leg > LEG_END_FRACTION and along_leg < 1.0 and along_wall >= trim and along_wall <= 1.0 - trim
                and behind > margin):
            return True
    return False


@kernel
def landmark_reflections(position, normal, is_plane, group, slot, tx, rx):
    """Where landmark hypotheses reflect each group's transmitter to its receivers, for :func:`reflections_blocked`.

    A plane reflects where :func:`map_paths` puts a wall's single bounce; any other hypothesis at its position.

    Parameters
    ----------
    position, normal : ndarray, shape (L, 2)
        Each hypothesis' position (a point of a plane's line) and a plane's unit normal, m.
    is_plane : ndarray of bool, shape (L,)
    group, slot : ndarray of int, shape (L,)
        The receiver group and transmitter slot of each hypothesis.
    tx, rx : ndarray, shape (G, M, 2) and (G, K, 2)
        Transmitters and receivers, m.

    Returns
    -------
    ndarray, shape (L, K, 2)
        The reflection point, m; for a plane on its (unbounded) line, NaN where
        the transmitter and the receiver are not on one side of it.
    """
    count, receivers = position.shape[0], rx.shape[1]
    direction = np.empty((count, 2))
    for n in range(count):
        direction[n, 0], direction[n, 1] = normal[n, 1], -normal[n, 0]
    length = np.zeros(count)
    points = np.full((count, receivers, 2), np.nan)
    for n in range(count):
        g, m = group[n], slot[n]
        for k in range(receivers):
            if not is_plane[n]:
                points[n, k, 0], points[n, k, 1] = position[n, 0], position[n, 1]
                continue
            _, exists, x, y = _via_wall(rx[g, k, 0], rx[g, k, 1], tx[g, m, 0], tx[g, m, 1], n, position, direction,
                                        normal, length, np.inf)
            if exists:
                points[n, k, 0], points[n, k, 1] = x, y
    return points


@kernel
def _accepted(x, y, transducer_x, transducer_y, axis_x, axis_y, acceptance, yaw_margin, position_margin):
    """Whether ``(x, y)`` is within the widened acceptance angle of a transducer along a unit axis."""
    dx, dy = x - transducer_x, y - transducer_y
    angle = math.atan2(axis_x * dy - axis_y * dx, axis_x * dx + axis_y * dy)
    return abs(angle) <= acceptance + yaw_margin + position_margin / _norm(dx, dy)


@kernel(inline=True)
def _shortened_leg_blocked(x0, y0, x1, y1, start_margin, end_margin, walls, length, wall_margin, support, least):
    """Whether a wall crosses the leg ``(x0, y0) -> (x1, y1)``, less the margins at its ends, inside its own.

    ``length`` (W,) the walls' lengths, m.  Nothing left of the leg: no;
    crossings within ``wall_margin`` (m) of the wall's ends do not count, nor walls whose ``support`` (W,) is
    below ``least``.
    """
    if start_margin == 0.0 and end_margin == 0.0:
        return _leg_blocked(x0, y0, x1, y1, walls, length, wall_margin, support, least)
    dx, dy = x1 - x0, y1 - y0
    leg = _norm(dx, dy)
    if not leg > start_margin + end_margin:
        return False
    return _leg_blocked(x0 + start_margin / leg * dx, y0 + start_margin / leg * dy,
                        x1 - end_margin / leg * dx, y1 - end_margin / leg * dy, walls, length, wall_margin, support,
                        least)


@kernel
def _unit(x, y):
    norm = _norm(x, y)
    return x / norm, y / norm


# --------------------------------------------------------------------------- a ping's landmarks explained


@kernel
def explain_rows(kind, first, second, support, path, jacobian, channel_start, n_walls, n_points, blocking,
                 blocking_normal, tx, rx, group, slot, row_paths, echo, position, row_normal, is_plane, covariance,
                 pose_covariance, sigma_path, sigma_speed, sigma_map, gate_sigmas):
    """Which of one ping's landmark hypotheses the map explains, given :func:`map_paths` of their channels.

    The steps of :func:`sonar_ring.explain.explain_landmarks` after the prediction, in one compiled call (a
    ping's glue between them in numpy cost a third of the call): :func:`match_rows`;
    :func:`multipath_rows`; the rest, :func:`reflections_blocked` from :func:`landmark_reflections` with
    :func:`impossible_margins`; and :func:`own_echoes` of the other rows' closest single bounces.  :func:`map_paths`
    is called apart: compiled into this kernel, its code would be optimised a second time (30 s more to
    compile).

    Parameters
    ----------
    kind, first, second, support, path, jacobian, channel_start
        :func:`map_paths`' paths for the rows' channels (gated by their paths).
    n_walls, n_points : int
        The map's walls and points (W, P).
    blocking, blocking_normal : ndarray, shape (W, 2, 2) and (W, 2)
        The walls that make a hypothesis impossible (their seen extents) and their unit normals towards their fronts.
    tx, rx : ndarray, shape (G, M, 2) and (G, K, 2)
        The transmitters and receivers at the ping's pose, m.
    group, slot : ndarray of int, shape (N,)
        Each hypothesis' receiver group and transmitter slot.
    row_paths : ndarray, shape (N, K)
        The paths each implies, m (NaN: not heard).
    echo : ndarray of int, shape (N,)
        The echo of its ping it came from.
    position, row_normal : ndarray, shape (N, 2)
        Its position and (a plane's) unit normal, map frame, m.
    is_plane : ndarray of bool, shape (N,)
    covariance : ndarray, shape (N, 2, 2)
        Its position's covariance, m^2.
    pose_covariance, sigma_path, sigma_speed, sigma_map, gate_sigmas
        The tolerance, as :func:`match_rows` takes it.

    Returns
    -------
    multipath, impossible : ndarray of bool, shape (N,)
        The map explains the hypothesis' echo as a double bounce (:func:`multipath_rows`), or a leg of it
        crosses a wall's front (and it is not multipath).
    heard : ndarray of bool, shape (W + P,)
        The entries (walls, then points) whose own echo is the closest single bounce, within the gate, of some
        row that is not multipath.
    """
    channel = group * tx.shape[1] + slot
    double, single, double_distance, single_distance, double_support = match_rows(
        channel, row_paths, channel_start, kind, support, path, jacobian, pose_covariance, sigma_path, sigma_speed,
        sigma_map, gate_sigmas)
    multipath = multipath_rows(kind, first, second, support, double, double_distance, single, single_distance,
                               double_support, echo, row_paths, gate_sigmas)
    # Impossible is asked of the rows that are not multipath only (a multipath row stays so): in the realistic
    # world two of three rows are multipath.
    tested = np.flatnonzero(~multipath)
    impossible = np.zeros(multipath.shape[0], dtype=np.bool_)
    impossible[tested] = reflections_blocked(
        landmark_reflections(position[tested], row_normal[tested], is_plane[tested], group[tested], slot[tested], tx,
                             rx), group[tested], slot[tested], tx, rx, blocking, blocking_normal,
        impossible_margins(covariance[tested], gate_sigmas, sigma_map))
    # An echo comes from one reflector: the entry whose own echo is the closest to it within the gate is heard,
    # not every entry within the gate, and none by an echo the map explains as a double bounce (a clutter
    # point mapped beside a wall was heard in 26 of 194 pings by the double bounces its gate took in).
    closest = np.zeros(kind.shape[0], dtype=np.bool_)
    for n in range(single.shape[0]):
        if single_distance[n] <= gate_sigmas and not multipath[n]:
            closest[single[n]] = True
    return multipath, impossible, own_echoes(kind, first, closest, n_walls, n_points)


@kernel
def multipath_rows(kind, first, second, support, double, double_distance, single, single_distance, double_support,
                   echo, paths, gate_sigmas):
    """Which rows are multipath, where an echo may match both a double bounce and a mapped entry's own echo.

    An echo that a double bounce of entries ``A`` and ``B`` explains and the
    single bounce of entry ``X`` explains too is ``X``'s (a pole on the line of
    sight to a wall: the wall's echo passing it) -- unless ``X`` was seen less
    often than both ``A`` and ``B``: a ghost mapped before the map could explain
    it has its own echo in the map, and the better-seen entries explain it.
    ``A`` and ``B`` are the most seen double bounce within the gate
    (``double_support``; one that bounces off ``X`` is seen at most as often as
    ``X``), not the closest: a ghost plane's double bounces off itself are as
    close as the true one, and near a wall's end so is the one off the edge
    there.  Nor is it ``X``'s when it is ``X``'s echo by way of another
    reflector (:func:`_by_way_of_the_entry`).

    Parameters
    ----------
    kind, first, second : ndarray of int, shape (Q,)
        The predicted paths (:func:`map_paths`).
    support : ndarray, shape (Q,)
        The observations of each path's less seen reflector.
    double, double_distance, single, single_distance, double_support : ndarray, shape (N,)
        :func:`match_rows` of the rows.
    echo : ndarray of int, shape (N,)
        Each row's echo in its ping.
    paths : ndarray, shape (N, K)
        Its paths, m.
    gate_sigmas : float

    Returns
    -------
    ndarray of bool, shape (N,)
    """
    rows = double.shape[0]
    near_single = np.empty(rows, dtype=np.bool_)
    for n in range(rows):
        near_single[n] = single_distance[n] <= gate_sigmas
    by_way = _by_way_of_the_entry(near_single, single, single_distance, double, echo, paths, kind, first, second)
    out = np.zeros(rows, dtype=np.bool_)
    for n in range(rows):
        if not double_distance[n] <= gate_sigmas:
            continue
        out[n] = not near_single[n] or by_way[n] or support[single[n]] < double_support[n]
    return out


@kernel
def _by_way_of_the_entry(near, single, single_residual, double, echo, paths, kind, first, second):
    """Which rows are entry ``X``'s echo by way of another reflector, of those ``near`` (N,) ``X``'s own echo.

    ``X`` is each row's closest single bounce ``single`` (N,; a row of the
    prediction, whose ``kind``, ``first`` and ``second`` (Q,) are given), at
    Mahalanobis distance ``single_residual``; ``double`` its closest double
    bounce (-1: none), ``echo`` its echo in its ping and ``paths`` (N, K) its
    paths.

    An entry sends one echo to a channel, and a double bounce off it arrives
    after that echo: its path through ``X``'s reflection point is at least
    ``X``'s own (the triangle inequality; a wall's own echo is the shortest
    path by way of it).  So of a ping's echoes within the gate of ``X``'s own,
    one that is not the closest (by the Mahalanobis distance), is longer than
    the closest (the mean of its finite paths against the closest's) and whose
    closest double bounce is off ``X`` is that double bounce, not ``X``.  With
    the pose known to 2 cm every echo a few centimetres longer than a wall's is
    within the gate of the wall's own: the west wall's echo by way of the
    pillar's edge, 2 cm longer, placed 15-25 cm along the wall and seen over a
    metre of travel, made a wall piece of its own, turned 2.6 deg from the wall.
    """
    count = near.shape[0]
    out = np.zeros(count, dtype=np.bool_)
    closest = np.full(kind.shape[0], -1, dtype=np.int64)
    for n in range(count):
        if near[n] and (closest[single[n]] < 0 or single_residual[n] < single_residual[closest[single[n]]]):
            closest[single[n]] = n
    for n in range(count):
        if not near[n] or double[n] < 0:
            continue
        entry, own, bounce = single[n], closest[single[n]], double[n]
        if echo[n] == echo[own] or not _mean_path(paths, n) > _mean_path(paths, own):
            continue
        if kind[entry] == WALL:
            out[n] = ((kind[bounce] == WALL_WALL and (first[bounce] == first[entry]
                                                     or second[bounce] == first[entry]))
                      or (kind[bounce] == WALL_POINT and first[bounce] == first[entry])
                      or (kind[bounce] == POINT_WALL and second[bounce] == first[entry]))
        else:
            out[n] = ((kind[bounce] == WALL_POINT and second[bounce] == first[entry])
                      or (kind[bounce] == POINT_WALL and first[bounce] == first[entry]))
    return out


@kernel(inline=True)
def _mean_path(paths, row):
    """Mean of row ``row``'s finite paths (NaN where none is)."""
    total, heard = 0.0, 0
    for k in range(paths.shape[1]):
        if np.isfinite(paths[row, k]):
            total += paths[row, k]
            heard += 1
    return total / heard if heard else np.nan


@kernel
def impossible_margins(covariance, gate_sigmas, sigma_map):
    """The margin of :func:`reflections_blocked` for hypotheses of position covariance ``covariance`` (L, 2, 2), m (L,).

    ``gate_sigmas`` times the hypotenuse of the hypothesis' position error along its worst direction (the
    larger eigenvalue's root, in closed form) and the map's ``sigma_map``; 0 where that is not finite.
    """
    margin = np.zeros(covariance.shape[0])
    for i in range(covariance.shape[0]):
        xx, xy, yy = covariance[i, 0, 0], covariance[i, 0, 1], covariance[i, 1, 1]
        largest = 0.5 * (xx + yy) + math.sqrt(0.25 * (xx - yy) ** 2 + xy ** 2)
        if np.isfinite(largest):
            value = gate_sigmas * math.hypot(math.sqrt(max(largest, 0.0)), sigma_map)
            margin[i] = value if np.isfinite(value) else 0.0
    return margin


@kernel
def own_echoes(kind, first, chosen, n_walls, n_points):
    """Which entries (walls, then points) have their own echo among the ``chosen`` (Q,) paths, (W + P,) bool."""
    entries = np.zeros(n_walls + n_points, dtype=np.bool_)
    for q in range(kind.shape[0]):
        if chosen[q] and kind[q] == WALL:
            entries[first[q]] = True
        elif chosen[q] and kind[q] == POINT:
            entries[n_walls + first[q]] = True
    return entries


# --------------------------------------------------------------------------- pruning


@kernel(inline=True)
def _widest_cone(cones, row, distance, acceptance, yaw_margin, position_margin, prune):
    """Into ``cones[row]``: cosine and sine of the widest half-angle at which an entry ``distance`` away is heard.

    Left NaN (seen from anywhere) without pruning, at no distance, or for half-angles of 90 deg or more.
    """
    if not prune or not distance > 0:
        return
    half = acceptance + yaw_margin + position_margin / distance + _SLACK
    if half < 0.5 * math.pi:
        cones[row, 0], cones[row, 1] = math.cos(half), math.sin(half)


@kernel(inline=True)
def _points_in_cone(seen, apex_x, apex_y, axis_x, axis_y, cone_cos, cone_sin, point_x, point_y, near):
    """Marks in ``seen`` (P,) the ``near`` points inside their widest cones at the apex (:func:`_widest_cone`).

    The cones' half-angle cosines and sines (NaN: seen from anywhere) and the points' coordinates as arrays of
    their own, (P,): a loop without a branch, which the compiler runs several points at a time.
    """
    for p in range(point_x.shape[0]):
        dx, dy = point_x[p] - apex_x, point_y[p] - apex_y
        along, across = axis_x * dx + axis_y * dy, axis_x * dy - axis_y * dx
        inside = abs(across) * cone_cos[p] <= along * cone_sin[p] + _SLACK * (abs(dx) + abs(dy))
        seen[p] |= near[p] & (np.isnan(cone_cos[p]) | inside)


@kernel(inline=True)
def _part_in_cone(apex_x, apex_y, axis_x, axis_y, cones, segments, row):
    """The part of ``segments[row]`` inside its widest cone (``cones[row]``) at the apex: ``(any, from, to)``."""
    cos_half, sin_half = cones[row, 0], cones[row, 1]
    if np.isnan(cos_half):
        return True, 0.0, 1.0
    return _clip_to_wedge(apex_x, apex_y, axis_x * cos_half - axis_y * sin_half, axis_x * sin_half + axis_y * cos_half,
                          axis_x * cos_half + axis_y * sin_half, -axis_x * sin_half + axis_y * cos_half, segments, row)


@kernel
def _in_wedge(apex_x, apex_y, left_x, left_y, right_x, right_y, x, y):
    """Whether ``(x, y)`` lies in the wedge from the apex between its right and left edges (< 180 deg), with slack."""
    dx, dy = x - apex_x, y - apex_y
    slack = _SLACK * (abs(dx) + abs(dy)) * (abs(left_x) + abs(left_y) + abs(right_x) + abs(right_y))
    return right_x * dy - right_y * dx >= -slack and dx * left_y - dy * left_x >= -slack


@kernel(inline=True)
def _clip_to_wedge(apex_x, apex_y, left_x, left_y, right_x, right_y, segments, row):
    """The part of ``segments[row]`` (of (S, 2, 2)) inside a wedge (< 180 deg), with slack.

    Returns ``(any, from, to)``, the part's ends as fractions of the segment.
    """
    low, high = 0.0, 1.0
    # Inside is where the cross products with both edges are >= 0; each is linear along the segment.
    start_x, start_y = segments[row, 0, 0] - apex_x, segments[row, 0, 1] - apex_y
    end_x, end_y = segments[row, 1, 0] - apex_x, segments[row, 1, 1] - apex_y
    edges = abs(left_x) + abs(left_y) + abs(right_x) + abs(right_y)
    start_slack = _SLACK * (abs(start_x) + abs(start_y)) * edges
    end_slack = _SLACK * (abs(end_x) + abs(end_y)) * edges
    for edge in range(2):
        if edge == 0:
            at_start = right_x * start_y - right_y * start_x + start_slack
            at_end = right_x * end_y - right_y * end_x + end_slack
        else:
            at_start = start_x * left_y - start_y * left_x + start_slack
            at_end = end_x * left_y - end_y * left_x + end_slack
        if at_start < 0 and at_end < 0:
            return False, 1.0, 0.0
        if at_start < 0:
            low = max(low, at_start / (at_start - at_end))
        elif at_end < 0:
            high = min(high, at_start / (at_start - at_end))
    return low <= high, low, high


@kernel(inline=True)
def _mirror_cone(mirror, c, k, x, y, wall, ends, low, high, start, normal):
    """The cone from the image of ``(x, y)`` in ``wall`` through part of the wall, into ``mirror[c, k, wall]`` (6,).

    The apex, then the left and right edges (not unit vectors) through the part
    ``low..high`` (fractions) of the wall's extended segment ``ends[wall]``.
    """
    side = _side(x, y, wall, start, normal)
    apex_x, apex_y = x - 2.0 * side * normal[wall, 0], y - 2.0 * side * normal[wall, 1]
    ux, uy = ends[wall, 1, 0] - ends[wall, 0, 0], ends[wall, 1, 1] - ends[wall, 0, 1]
    a_x, a_y = ends[wall, 0, 0] + low * ux - apex_x, ends[wall, 0, 1] + low * uy - apex_y
    b_x, b_y = ends[wall, 0, 0] + high * ux - apex_x, ends[wall, 0, 1] + high * uy - apex_y
    if a_x * b_y - a_y * b_x < 0:
        a_x, a_y, b_x, b_y = b_x, b_y, a_x, a_y
    mirror[c, k, wall, 0], mirror[c, k, wall, 1] = apex_x, apex_y
    mirror[c, k, wall, 2], mirror[c, k, wall, 3], mirror[c, k, wall, 4], mirror[c, k, wall, 5] = b_x, b_y, a_x, a_y


@kernel(inline=True)
def _segment_distance(x, y, segments, row):
    """Distance from ``(x, y)`` to ``segments[row]`` (of (S, 2, 2)), m."""
    ux, uy = segments[row, 1, 0] - segments[row, 0, 0], segments[row, 1, 1] - segments[row, 0, 1]
    squared = ux * ux + uy * uy
    along = ((x - segments[row, 0, 0]) * ux + (y - segments[row, 0, 1]) * uy) / squared if squared > 0 else 0.0
    along = min(max(along, 0.0), 1.0)
    return math.hypot(segments[row, 0, 0] + along * ux - x, segments[row, 0, 1] + along * uy - y)


@kernel
def _segments_cross(segments, first, second):
    """Whether ``segments[first]`` and ``segments[second]`` cross: each one's ends strictly either side of the other."""
    crossing = True
    for a, b in ((first, second), (second, first)):
        ux, uy = segments[a, 1, 0] - segments[a, 0, 0], segments[a, 1, 1] - segments[a, 0, 1]
        at_start = ux * (segments[b, 0, 1] - segments[a, 0, 1]) - uy * (segments[b, 0, 0] - segments[a, 0, 0])
        at_end = ux * (segments[b, 1, 1] - segments[a, 0, 1]) - uy * (segments[b, 1, 0] - segments[a, 0, 0])
        crossing = crossing and at_start * at_end < 0
    return crossing
