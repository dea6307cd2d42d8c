"""Sound paths between walls and points: legs that cross a wall, double bounces by the image method.

One geometry for the world and for the map: the forward model
(:mod:`sonar_ring.simulate`) blocks its paths with :func:`blocked_legs`, the realistic
world (:mod:`sonar_ring.realism`) makes its multipath echoes with
:func:`double_bounces` from the scene's walls and edges, and the map's explanation
of echoes (:mod:`sonar_ring.explain`) predicts the same paths from the map's walls
and points, with the same functions.

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
  ``P -> R_b`` crosses ``b``.

A path exists where every bounce lies on its wall's segment (within ``margin``
of it) and comes from the side the sound arrives on: each crossing is strict, so
a point on a wall's line, or a transducer on it, has no path by that wall.

All positions in one frame (the world's or the map's), m.  The loops are numba
kernels (:mod:`sonar_ring.compiled`): a ping's paths are thousands of scalar
computations, each a few operations, where numpy would spend its time starting
operations.  Their arithmetic is that of the numpy code they replaced, operation
for operation, so the realistic world's echoes are the same to the last bit.
"""

from __future__ import annotations

import math

import numpy as np

from sonar_ring.compiled import kernel

WALL_WALL, WALL_POINT, POINT_WALL = 0, 1, 2
"""Kinds of double bounce: first reflector then second (:func:`double_bounces`)."""

KIND_NAMES = ("wall-wall", "wall-point", "point-wall")
"""Name of each kind code, indexable by the code."""

LEG_END_FRACTION = 1e-9
"""Fraction of a leg's length at either end where crossing a wall is not a
blockage: legs start and end *on* the reflecting walls."""


def wall_frames(walls) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Start, unit direction, unit normal and length of wall segments.

    Parameters
    ----------
    walls : ndarray, shape (W, 2, 2)
        Segments ``[[x0, y0], [x1, y1]]`` of non-zero length, m.

    Returns
    -------
    start, direction, normal : ndarray, shape (W, 2)
        First end point (m), unit vector from it to the second, and that vector
        turned 90 deg counter-clockwise.
    length : ndarray, shape (W,)
        m.
    """
    start = walls[:, 0]
    vector = walls[:, 1] - walls[:, 0]
    length = np.hypot(vector[:, 0], vector[:, 1])
    direction = vector / length[:, None]
    normal = np.stack([-direction[:, 1], direction[:, 0]], axis=-1)
    return start, direction, normal, length


def load_kernels() -> None:
    """Load the compiled kernels now instead of at the first blocked leg or multipath path.

    A process that simulates or explains pings on a deadline pays numba's start
    here; runs each kernel with the argument types of production.
    """
    walls = np.array([[[0.0, 0.0], [1.0, 0.0]], [[1.0, 0.0], [1.0, 1.0]]])
    blocked_legs(np.zeros((1, 2)), np.ones((1, 2)), walls)
    start, direction, normal, length = (np.ascontiguousarray(a) for a in wall_frames(walls))
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
    for i in range(starts.shape[0]):
        hit[i] = _leg_blocked(starts[i, 0], starts[i, 1], ends[i, 0], ends[i, 1], walls)
    return hit


@kernel
def _leg_blocked(x0, y0, x1, y1, walls):
    """:func:`blocked_legs` for one leg ``(x0, y0) -> (x1, y1)``."""
    rx, ry = x1 - x0, y1 - y0
    for w in range(walls.shape[0]):
        ax, ay = walls[w, 0, 0], walls[w, 0, 1]
        sx, sy = walls[w, 1, 0] - ax, walls[w, 1, 1] - ay
        denominator = rx * sy - ry * sx
        apx, apy = ax - x0, ay - y0
        along_leg = (apx * sy - apy * sx) / denominator
        along_wall = (apx * ry - apy * rx) / denominator
        if (denominator != 0 and along_leg > LEG_END_FRACTION and along_leg < 1 - LEG_END_FRACTION
                and along_wall >= 0 and along_wall <= 1):
            return True
    return False


# --------------------------------------------------------------------------- double bounces


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


@kernel
def _side(x, y, wall, start, normal):
    """Signed distance of ``(x, y)`` from the line of ``wall``, positive on its normal's side, m."""
    return (x - start[wall, 0]) * normal[wall, 0] + (y - start[wall, 1]) * normal[wall, 1]


@kernel
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


@kernel
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
    horizontal = math.hypot(image_ab_x - rx_x, image_ab_y - rx_y)
    return horizontal, on_a and on_b and image_a_side * r_side > 0, first_x, first_y, last_x, last_y


@kernel
def _wall_point(tx_x, tx_y, rx_x, rx_y, a, p_x, p_y, start, direction, normal, length, margin):
    """T -> wall ``a`` -> point P -> R: ``(horizontal, exists, first x, y, last x, y)``."""
    t_side = _side(tx_x, tx_y, a, start, normal)
    image_x, image_y = tx_x - 2.0 * t_side * normal[a, 0], tx_y - 2.0 * t_side * normal[a, 1]
    p_side = _side(p_x, p_y, a, start, normal)
    bounce_x, bounce_y, on_wall = _crossing(p_x, p_y, p_side, image_x, image_y, -t_side, a, start, direction, length,
                                            margin)
    horizontal = math.hypot(p_x - image_x, p_y - image_y) + math.hypot(p_x - rx_x, p_y - rx_y)
    return horizontal, on_wall, bounce_x, bounce_y, p_x, p_y


@kernel
def _point_wall(tx_x, tx_y, rx_x, rx_y, p_x, p_y, b, start, direction, normal, length, margin):
    """T -> point P -> wall ``b`` -> R: ``(horizontal, exists, first x, y, last x, y)``."""
    r_side = _side(rx_x, rx_y, b, start, normal)
    image_x, image_y = rx_x - 2.0 * r_side * normal[b, 0], rx_y - 2.0 * r_side * normal[b, 1]
    p_side = _side(p_x, p_y, b, start, normal)
    bounce_x, bounce_y, on_wall = _crossing(p_x, p_y, p_side, image_x, image_y, -r_side, b, start, direction, length,
                                            margin)
    horizontal = math.hypot(p_x - tx_x, p_y - tx_y) + math.hypot(p_x - image_x, p_y - image_y)
    return horizontal, on_wall, p_x, p_y, bounce_x, bounce_y
