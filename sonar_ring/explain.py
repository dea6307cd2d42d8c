"""Echoes the map explains before they become landmarks: multipath, and reflectors that cannot be there.

A room returns more than its reflectors' echoes: sound bounces twice (wall then
wall, wall then an edge, an edge then a wall), and a single-bounce model sees a
reflector where there is none, mirrored behind a wall.  The map already holds
the walls and points that make those paths, so it can predict them and keep the
echoes they explain out of the map.  Per ping, at the sensor's estimated pose in
the map frame (:func:`sonar_ring.simulate.place`), the mapper calls:

* :func:`predict` -- the paths the map's walls (grown to where they end) and
  points (corners, edges, undecided: all may diffract) send to the receivers
  of the ping's echo rows: every double bounce, by the image method of
  :mod:`sonar_ring.image_method` (the realistic world's own code), and every
  entry's own single-bounce echo; each path exists geometrically, fits the
  receive window, reaches the receiver within its acceptance angle, leaves a
  directional transmitter within it and crosses no mapped wall where it was
  seen, unless that wall was seen less often than the path's reflectors (a
  ghost wall, grown or not, must not hide the double bounces that explain
  it).  Given the
  rows' measured paths it keeps only the paths that can match one of them;
* :func:`match` -- a row is :data:`MULTIPATH` when a predicted double bounce of
  its group and transmitter is within the gate of the paths ``c * tof`` of every
  receiver that heard it, and no mapped reflector's own echo is: an echo as long
  as a mapped reflector's own (a pole on the line of sight to a wall: the
  wall's echo passing it) may be that reflector's, and its landmark is where the
  map already has one -- it is left to the mapper (:func:`explain_landmarks`
  gives it to the double bounce whose reflectors were both seen more often,
  and a later echo than the entry's own to a double bounce off the entry: an
  entry sends one echo to a channel);
* :func:`impossible` -- a landmark hypothesis whose straight legs from the
  transmitter or to its receivers cross a mapped wall from the side it was seen
  from is not a reflector there (:func:`reflection_points` gives where the legs
  end).  A wall seen from one side is known to reflect on that side only: a
  hypothesis heard through it from the other side is evidence against the
  wall, not against the hypothesis (a ghost plane mapped in front of a pillar's
  face, seen from the far side of the pillar, must not hide the face).

What the map cannot predict is not excluded here: walls it has not seen, or has
seen shorter than they are, leave their multipath unexplained.  That is for the
mapper's persistence test.

Model
-----
Two walls whose segments come within ``junction`` of each other meet in a
corner: their double bounce is the corner's own echo, a landmark, never
multipath (the realistic world leaves out its corners' pairs the same way).  A
point within ``junction`` of a wall's segment is that wall's end or corner: its
paths by that wall are its own echo.  A wall does not pair with itself.  Points
diffract: a map's corner is predicted as a point too, not as the double bounce
of its walls.

Tolerance (:class:`Tolerance`)
------------------------------
The measured paths ``m_k = c * tof_k`` of the receivers ``k`` that heard a row
are compared with a predicted path's ``d_k`` through the Mahalanobis distance
``r = sqrt(e^T C^-1 e)``, ``e = m - d``, with

    C_kl = sigma_path^2 delta_kl + J_k Sigma J_l^T + sigma_speed^2 d_k d_l + 8 sigma_map^2

* ``sigma_path``: each receiver's own path noise (``c * sigma_tof``);
* ``Sigma``: the covariance of the pose ``(x, y, yaw)`` and ``J_k = dd_k/d(x, y, yaw)``.
  By Fermat's principle the bounce points do not move to first order, so
  ``dh/dT = e_T = (T - A) / |T - A|`` and ``dh/dR = e_R = (R - B) / |R - B|`` (``A``
  the first reflection, ``B`` the last), and ``dd = h / d dh`` (3-D path ``d``,
  horizontal ``h``): ``J = h / d [e_T + e_R, e_T . (T - S)^perp + e_R . (R - S)^perp]``
  with ``S`` the pose's position and ``v^perp = (-v_y, v_x)``.  A pose error moves
  every receiver's path alike: the term is correlated, so a row must still
  match the predicted differences between its receivers within ``sigma_path``;
* ``sigma_speed``: the relative error of the speed of sound, which scales all paths;
* ``sigma_map``: the position error of a map entry; each of a path's two
  reflectors moved by it changes every receiver's path by up to twice as much.

A path matches a row when ``r <= gate_sigmas``.  Under Gaussian errors a true match
fails a gate of 4 with probability 6e-5 (one receiver heard the row), 3.4e-4
(two) or 1.1e-3 (three).

The same uncertainty widens what :func:`predict` keeps: a transducer's position
in the map is uncertain by ``sigma_position = sqrt(max eig Sigma_xy) + rho
sigma_yaw`` (``rho`` the transducers' largest distance from ``S``), so a bounce may
lie ``gate_sigmas (sigma_position + sigma_map)`` beyond a segment's ends, a path may
arrive ``gate_sigmas (sigma_yaw + (2 sigma_position + sigma_map) / distance)`` outside
the acceptance angle, and a wall blocks a leg only where it crosses it farther
than ``gate_sigmas (sigma_position + sigma_map)`` from the leg's reflecting ends and
from the wall's own ends (:func:`impossible` likewise, by its ``margin``).  All
are 0 for an exact pose and map.

Pruning (``prune=True``)
------------------------
Before it computes a path, :func:`predict` keeps only the entries and pairs that
can give one for the channel; every test follows from the path's existence, so
none drops a path that exists (the tests compare pruned and unpruned
predictions on random poses), and each has a slack of 1e-9 against rounding:

* **range**: every reflection of a path within the receive window ``D`` lies within
  ``D / 2 + rho`` of ``S`` (``|S - A| <= |T - A| + rho`` and ``|S - A| <= rho + |A - B| +
  |B - R|``; summed, ``2 |S - A| <= D + 2 rho``): entries farther away are dropped;
* **beam**: the last reflection lies in a receiver's acceptance cone, widened by
  the margin above at the entry's least distance from a transducer (at least its
  distance from ``S`` less ``rho``): a wall is kept for a receiver when part of its
  segment is inside the cone, a point when it is inside; a directional
  transmitter's cone likewise keeps the first entries;
* **mirror**: unfolding the last bounce, the first reflection lies on the line
  from the receiver's image in the last wall through the last bounce: inside the
  cone from that image through the part of the wall in the beam.  Only points
  inside it and walls that cross it are kept as first entries;
* **facing**: every bounce is strict: the first wall has part of the last wall
  on the transmitter's side, the last wall part of the first wall, or the point,
  on the receiver's side;
* **rows**: given the measured paths, a pair's lengths are compared with the
  rows of its channel before its bounces are placed, with the largest variance
  any pose error could give (``|J_xy| <= 2``, ``|J_yaw| <= 2 rho``), and so are the
  differences between receivers, with a bound on how a pose error changes them
  (every path reaches the receivers from one point after a common leg: a point,
  a point's image in a wall, or the transmitter's image in the walls, which
  moves with the pose: :func:`sonar_ring.image_method.map_paths`); then, with
  its derivative, by the Mahalanobis distance itself, before its legs are tested
  for blocking.  Each is a necessary condition of a match: the Mahalanobis
  distance bounds that of any one receiver or difference.

What depends on the transmitter alone (its images in the walls, its distance to
the points, the first bounce of every wall -> point path) is computed once per
ping for all the groups it serves.  ``prune=False`` pairs every entry with every
other for every channel (the reference the tests and the benchmark compare with).

Frames and units: the map frame (``map`` or ``odom``), metres, radians, seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sonar_ring import image_method, solvers
from sonar_ring.compiled import kernel
from sonar_ring.geometry import Layout
from sonar_ring.landmarks import CORNER, CORNER_OR_EDGE, EDGE, PLANE, Landmarks, check_landmarks, make_landmarks
from sonar_ring.simulate import Placement, place

NONE, MULTIPATH = 0, 1
"""Labels of an echo row (:attr:`Explanation.label`): not explained, or a predicted double bounce."""

JUNCTION = 0.1
"""m: walls this close meet in a corner; a point this close to a wall is its end or corner (module docstring)."""


@dataclass(frozen=True)
class Tolerance:
    """How far a measured echo may be from a predicted path (module docstring, "Tolerance").

    Attributes
    ----------
    sigma_path : float
        Standard deviation of one receiver's measured path ``c * tof``, m (> 0).
    pose_covariance : ndarray, shape (3, 3)
        Covariance of the sensor pose ``(x, y, yaw)`` in the map frame, m^2,
        m rad, rad^2; zero for an exact pose.  NaN: nothing is explained.
    sigma_speed : float
        Relative standard deviation of the speed of sound (0.0035: 0.35 %).
    sigma_map : float
        Standard deviation of a map entry's position, m.
    gate_sigmas : float
        Largest Mahalanobis distance of a match, not squared: standard deviations (> 0).
    """

    sigma_path: float
    pose_covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    sigma_speed: float = 0.0
    sigma_map: float = 0.0
    gate_sigmas: float = 4.0

    def __post_init__(self):
        covariance = np.asarray(self.pose_covariance, dtype=float)
        if covariance.shape != (3, 3):
            raise ValueError(f"Tolerance: pose_covariance must have shape (3, 3), got {covariance.shape}")
        object.__setattr__(self, "pose_covariance", covariance)
        for name, low_open in (("sigma_path", True), ("sigma_speed", False), ("sigma_map", False),
                               ("gate_sigmas", True)):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and (value > 0 or not low_open)
                    and value >= 0):
                bound = "> 0" if low_open else ">= 0"
                raise ValueError(f"Tolerance: field '{name}' must be a finite number {bound}, got {value!r}")

    @property
    def yaw_sigma(self) -> float:
        """Standard deviation of the pose's yaw, rad (NaN for a covariance that is not one)."""
        variance = float(self.pose_covariance[2, 2])
        return math.sqrt(variance) if variance >= 0 else math.nan

    @property
    def xy_sigma(self) -> float:
        """Standard deviation of the pose's position along its worst direction, m (the larger eigenvalue's root)."""
        (xx, xy), (_, yy) = self.pose_covariance[:2, :2].tolist()  # the larger eigenvalue in closed form
        largest = 0.5 * (xx + yy) + math.sqrt(0.25 * (xx - yy) ** 2 + xy ** 2)
        return math.sqrt(largest) if largest >= 0 else math.nan


@dataclass(frozen=True)
class Prediction:
    """The paths the map sends to one ping's receivers, Q of them, K receivers each.

    Double bounces, and each entry's own single-bounce echo; sorted by channel
    ``group * M + slot`` (M transmitter slots per group).

    Attributes
    ----------
    group, slot : ndarray of int, shape (Q,)
        Receiver group and transmitter slot of each path.
    kind : ndarray of int, shape (Q,)
        A double bounce, :data:`~sonar_ring.image_method.WALL_WALL`,
        ``WALL_POINT`` or ``POINT_WALL``, or a single one, ``WALL`` or ``POINT``
        (:data:`~sonar_ring.image_method.KIND_NAMES`).
    first, second : ndarray of int, shape (Q,)
        The first and the second reflector: rows of the ``walls`` or ``points``
        given to :func:`predict`, as ``kind`` says (the same twice for a single bounce).
    support : ndarray, shape (Q,)
        Observations of the less seen of the two (:func:`predict`'s supports; 0 where not given).
    path : ndarray, shape (Q, K)
        3-D path length transmitter -> first -> second -> receiver k, m; NaN where
        receiver k gets no such path.
    jacobian : ndarray, shape (Q, K, 3)
        Derivative of ``path`` by the pose ``(x, y, yaw)``, m/m and m/rad.
    first_point, last_point : ndarray, shape (Q, K, 2)
        Where the path first meets a reflector and where it last leaves one, map frame, m.
    channel_start : ndarray of int, shape (G * M + 1,)
        Paths of channel c are rows ``channel_start[c]:channel_start[c + 1]``.
    """

    group: np.ndarray
    slot: np.ndarray
    kind: np.ndarray
    first: np.ndarray
    second: np.ndarray
    support: np.ndarray
    path: np.ndarray
    jacobian: np.ndarray
    first_point: np.ndarray
    last_point: np.ndarray
    channel_start: np.ndarray

    def __len__(self) -> int:
        return int(self.kind.shape[0])


@dataclass(frozen=True)
class Explanation:
    """What :func:`match` says of each of N echo rows.

    Attributes
    ----------
    label : ndarray of uint8, shape (N,)
        :data:`MULTIPATH` or :data:`NONE`.
    best : ndarray of int, shape (N,)
        Row of the :class:`Prediction` of the double bounce closest to the echo
        (its kind, reflectors and bounce points), -1 where no double bounce
        reaches every receiver that heard it.
    residual : ndarray, shape (N,)
        Mahalanobis distance of the echo from that path; inf where ``best`` is
        -1, NaN where no receiver heard the row.
    direct : ndarray of int, shape (N,)
        Likewise the closest single bounce: a mapped reflector's own echo.
    direct_residual : ndarray, shape (N,)
        Its Mahalanobis distance.
    double_support : ndarray, shape (N,)
        The most seen double bounce within the gate, by the observations of its
        less seen reflector (:attr:`Prediction.support`); -inf where there is none.
    """

    label: np.ndarray
    best: np.ndarray
    residual: np.ndarray
    direct: np.ndarray
    direct_residual: np.ndarray
    double_support: np.ndarray


# --------------------------------------------------------------------------- public functions


def predict(walls, points, placement: Placement, layout: Layout, group, transmitter, tolerance: Tolerance, *,
            paths=None, seen=None, wall_support=None, point_support=None, max_path: float | None = None,
            junction: float = JUNCTION, prune: bool = True, doubles: bool = True) -> Prediction:
    """The paths of the map, double and single bounces, for the channels of one ping's echo rows.

    Parameters
    ----------
    walls : array_like, shape (W, 2, 2)
        The map's walls as segments, map frame, m: where they reflect (their seen
        extents, or grown to where they end: :func:`walls_to_their_ends`).  Rows
        with a non-finite value or no length are left out.
    points : array_like, shape (P, 2)
        The map's points (corners, edges, undecided), m.  Non-finite rows are left out.
    placement : Placement
        The sensor's transducers in the map frame at the ping's estimated pose
        (:func:`sonar_ring.simulate.place`).
    layout : Layout
        The sensor (heights, acceptance angle, emitter kind).
    group, transmitter : array_like of int, shape (N,)
        Receiver group and transmitter of each echo row; every channel they
        name is predicted once.
    tolerance : Tolerance
        Widens the existence, beam and blocking tests by the pose's and the
        map's uncertainty (module docstring).
    paths : array_like, shape (N, K), optional
        The rows' measured paths ``c * tof``, m (NaN: not heard).  Given, only
        the paths that can match a row of their channel (:func:`match`) are
        kept -- what can matter for this ping -- and only they are tested for
        beams and blocking.  Not given, every path.
    seen : array_like, shape (W, 2, 2), optional
        Where each of ``walls`` was seen (its seen extent), m: what blocks a
        path's legs; default ``walls``.  A wall grown to where it is taken to end
        reflects there but blocks only where it was seen: a ghost wall grown
        metres to a fixed point would hide the very double bounces that explain
        it (realistic room: 26 of 129 sampled sightings of ghosts explained with
        the grown walls blocking, 106 with the seen ones).
    wall_support, point_support : array_like, shape (W,) and (P,), optional
        How often each wall and point was seen (observations).  Given, a wall
        blocks a path only if it was seen at least as often as the least seen
        of the path's reflectors: a ghost wall lies on the legs of the double
        bounce that makes it (5 of 50 sampled sightings of the ghosts a ghost
        wall's seen extent still blocked were explained, 36 with this rule).
        Default: every wall blocks.
    max_path : float, optional
        Longest path the receivers report (the receive window), m; default ``2 * layout.max_range``.
    junction : float
        m: see :data:`JUNCTION`.
    prune : bool
        False to pair every entry with every other for every channel.
    doubles : bool
        False for each entry's own echo only (what the map should hear: :func:`audible`).

    Raises
    ------
    ValueError
        On arrays of the wrong shape, groups or transmitters the layout does not
        have, or a placement of another layout.
    """
    walls, points = _map_arrays(walls, points, "predict")
    seen = walls if seen is None else _segments(seen, "predict", "seen")
    wall_support = _support(wall_support, len(walls), "wall_support", "predict")
    point_support = _support(point_support, len(points), "point_support", "predict")
    if seen.shape != walls.shape:
        raise ValueError(f"predict: seen must have the shape of walls {walls.shape}, got {seen.shape}")
    group, slot = _channels(layout, group, transmitter, "predict")
    _check_placement(placement, layout, "predict")
    row_paths = np.empty((group.size, layout.receivers_per_group)) if paths is None else _row_paths(
        paths, group.size, layout, "predict")
    max_path = 2.0 * layout.max_range if max_path is None else float(max_path)
    return _predict(_MapGeometry.of(walls, points, seen, wall_support, point_support, junction), placement, layout,
                    group, slot, row_paths, paths is not None, tolerance, max_path, prune, doubles)


def match(prediction: Prediction, layout: Layout, group, transmitter, paths, tolerance: Tolerance, *,
          direct_wins: bool = True) -> Explanation:
    """Which echo rows a predicted double bounce explains, and no mapped reflector's own echo does.

    Parameters
    ----------
    prediction : Prediction
        :func:`predict`'s paths for these rows' channels.
    layout : Layout
    group, transmitter : array_like of int, shape (N,)
        Receiver group and transmitter of each row.
    paths : array_like, shape (N, K)
        Measured path lengths ``c * tof``, m; NaN where a receiver heard nothing.
    tolerance : Tolerance
    direct_wins : bool
        Whether a row a mapped entry's own echo also explains is left unexplained.

    Returns
    -------
    Explanation
        A row is :data:`MULTIPATH` when its closest double bounce is within the
        tolerance's gate and (``direct_wins``) its closest single bounce is not.  A row every
        receiver of which heard nothing, or whose paths are not finite, is not
        explained.

    Raises
    ------
    ValueError
        On arrays of the wrong shape, or groups and transmitters the layout does not have.
    """
    group, slot = _channels(layout, group, transmitter, "match")
    paths = _row_paths(paths, group.size, layout, "match")
    if prediction.channel_start.shape != (layout.n_groups * layout.group_transmitters.shape[1] + 1,):
        raise ValueError("match: the prediction is of another layout")
    return _match(prediction, layout, group, slot, paths, tolerance, direct_wins)


def impossible(points, placement: Placement, layout: Layout, group, transmitter, walls, normals,
               margin) -> np.ndarray:
    """Which landmark hypotheses cannot be reflectors: a straight leg of theirs crosses a mapped wall's front.

    Parameters
    ----------
    points : array_like, shape (L, K, 2)
        Where each hypothesis reflects the sound to each receiver of its group,
        map frame, m (:func:`reflection_points`): the vertex of a corner, edge or
        undecided point for every receiver, a plane's reflection point on its
        wall for each.  NaN for a receiver to leave out.
    placement : Placement
        The transducers in the map frame (:func:`sonar_ring.simulate.place`).
    layout : Layout
    group, transmitter : array_like of int, shape (L,)
        Receiver group and transmitter of the echo each hypothesis came from.
    walls : array_like, shape (W, 2, 2)
        The map's wall segments, m; non-finite rows are left out.
    normals : array_like, shape (W, 2)
        Each wall's normal towards the side it was seen from (its front; any
        length but zero): a wall blocks only legs that cross it from there.
    margin : float or array_like, shape (L,)
        m: a wall crossing a leg within this of the hypothesis' end does not
        count -- the wall the hypothesis lies on (a plane's own wall, the walls
        a corner or a wall's end joins), placed apart from it by noise.  About
        ``gate_sigmas`` times the hypothesis' and the map's position uncertainty.

    Returns
    -------
    ndarray of bool, shape (L,)
        True where a leg from the transmitter to a reflection point, or from one
        to its receiver, crosses a mapped wall strictly between its ends, from
        the wall's front, the point more than ``margin`` behind it.  A
        hypothesis seen through a gap between mapped walls (a doorway) is not
        impossible.  Non-finite points are never impossible.

    Raises
    ------
    ValueError
        On arrays of the wrong shape, groups or transmitters the layout does not
        have, a zero or non-finite normal, or a negative margin.
    """
    group, slot = _channels(layout, group, transmitter, "impossible")
    points = np.ascontiguousarray(points, dtype=float)
    if points.shape != (group.size, layout.receivers_per_group, 2):
        raise ValueError(f"impossible: points must have shape ({group.size}, {layout.receivers_per_group}, 2) "
                         f"(hypotheses, receivers, xy), got {points.shape}")
    margin = np.asarray(margin, dtype=float)
    if margin.shape not in ((), (group.size,)) or (margin.size and margin.min() < 0):
        raise ValueError(f"impossible: margin must be a number >= 0 or one per hypothesis ({group.size},), "
                         f"got {margin!r}")
    _check_placement(placement, layout, "impossible")
    walls = _segments(walls, "impossible")
    normals = _unit_normals(normals, walls, "impossible")
    margin = np.full(group.size, float(margin)) if margin.ndim == 0 else np.ascontiguousarray(margin)
    return _impossible(points, placement, group, slot, walls, normals, margin)


def facing(walls, point) -> np.ndarray:
    """Each wall's unit normal towards ``point``: :func:`impossible`'s ``normals`` of walls all seen from there.

    ``walls`` (W, 2, 2), ``point`` (2,), m; returns (W, 2) (a wall whose line
    passes through ``point`` gets its left normal).
    """
    walls = _segments(walls, "facing")
    point = np.asarray(point, dtype=float)
    if point.shape != (2,):
        raise ValueError(f"facing: point must have shape (2,), got {point.shape}")
    start, _, left, _ = image_method.wall_frames(walls)
    side = np.einsum("wi,wi->w", point - start, left)
    return np.where(side[:, None] < 0.0, -left, left)


def reflection_points(landmarks: Landmarks, placement: Placement, layout: Layout, transmitter) -> np.ndarray:
    """Where each landmark hypothesis reflects the sound to each receiver of its group, for :func:`impossible`.

    Parameters
    ----------
    landmarks : Landmarks
        Hypotheses in the map frame (L of them), each with the ``group`` of its echo.
    placement : Placement
        The transducers in the map frame.
    layout : Layout
    transmitter : array_like of int, shape (L,)
        Transmitter of the echo each landmark came from.

    Returns
    -------
    ndarray, shape (L, K, 2)
        A plane's reflection points on the line through its ``position`` with
        its ``normal`` (the image of the transmitter in it, seen from each
        receiver); any other class's ``position`` for every receiver.  NaN where
        a receiver is not on the plane's transmitter side, or the normal is zero.
    """
    group, slot = _channels(layout, landmarks.group.astype(np.int64), transmitter, "reflection_points")
    _check_placement(placement, layout, "reflection_points")
    return image_method.landmark_reflections(np.ascontiguousarray(landmarks.position, dtype=float),
                                             np.ascontiguousarray(landmarks.normal, dtype=float),
                                             landmarks.landmark_class == PLANE, group, slot, placement.tx,
                                             placement.rx)


@dataclass(frozen=True)
class EchoTests:
    """The mapper's tests of a ping's landmarks against its map (:func:`explain_landmarks`); its parameters.

    Attributes
    ----------
    sigma_path : float
        One receiver's path noise ``c * sigma_tof``, m (1 us: 0.343 mm).
    sigma_speed : float
        Relative error of the speed of sound the nodes assume (2 K: 0.35 %).
    sigma_map : float
        Position error of a map entry, m.
    gate_sigmas : float
        Largest Mahalanobis distance of a match, not squared (:class:`Tolerance`).
    wall_reach : float
        m: a mapped wall is taken to reach the nearest corner, edge or fixed point
        on its line (within ``wall_tolerance``) beyond an end of its seen extent,
        up to this far (:func:`walls_to_their_ends`).
    wall_tolerance : float
        m: how close to a wall's line such a point must lie.
    refresh_pings : int
        Pings between two refreshes of the map the tests use (its walls grown, its points):
        the map changes slowly, so its preparation need not be paid every ping.
    unheard_after, unheard_fraction : int, float
        A map entry whose own echo the map predicts (:func:`audible`) in ``unheard_after`` of the pings
        it checks or more, and which was heard in fewer than ``unheard_fraction`` of them, leaves the map:
        a ghost seen in a burst of a few pings that the poses since did not hear (0 pings: never).
    hearing_every : int
        Pings between two such checks (:func:`audible` costs about 0.27 ms for a map of 35 entries).
    """

    sigma_path: float = 343e-6
    sigma_speed: float = 0.0035
    sigma_map: float = 0.005
    gate_sigmas: float = 4.0
    wall_reach: float = 2.0
    wall_tolerance: float = 0.05
    refresh_pings: int = 10
    unheard_after: int = 100
    unheard_fraction: float = 0.05
    hearing_every: int = 3

    def __post_init__(self):
        Tolerance(self.sigma_path, sigma_speed=self.sigma_speed, sigma_map=self.sigma_map,
                  gate_sigmas=self.gate_sigmas)
        if not (self.unheard_after >= 0 and 0.0 <= self.unheard_fraction <= 1.0 and self.hearing_every >= 1):
            raise ValueError(f"EchoTests: unheard_after must be >= 0, unheard_fraction in 0..1 and hearing_every "
                             f">= 1, got {self.unheard_after}, {self.unheard_fraction}, {self.hearing_every}")


@dataclass(frozen=True)
class Explained:
    """What :func:`explain_landmarks` says of L landmarks of one ping.

    Attributes
    ----------
    multipath : ndarray of bool, shape (L,)
        Its echo matches a double bounce of the map's entries (and no entry's own echo).
    impossible : ndarray of bool, shape (L,)
        Not multipath, but a leg of its path crosses a mapped wall.
    position : ndarray, shape (L, 2)
        Each landmark's position in the map's frame, m, for drawing (all NaN when none was tested).
    heard : ndarray of bool, shape (W + P,)
        Each entry of the map (walls, then points) whose own echo is the closest single bounce to the echo
        of a landmark that is not multipath, within the gate: an echo comes from one reflector, and a
        clutter point mapped beside the double bounces its gate takes in is not heard by them.
    """

    multipath: np.ndarray
    impossible: np.ndarray
    position: np.ndarray
    heard: np.ndarray

    @classmethod
    def nothing(cls, position: np.ndarray, entries: int) -> Explained:
        """Nothing explained of landmarks placed at ``position`` (L, 2), and none of a map's ``entries`` heard."""
        count = len(position)
        return cls(np.zeros(count, bool), np.zeros(count, bool), position, np.zeros(entries, bool))

    @property
    def any(self) -> np.ndarray:
        """Explained either way, (L,)."""
        return self.multipath | self.impossible


def walls_to_their_ends(segments, points, reach: float, tolerance: float, snap: float = 0.2) -> np.ndarray:
    """Walls grown along their lines to where they end: a corner with another wall, or a fixed point; (W, 2, 2), m.

    A wall is mapped over the part the sensor saw specular echoes from -- the
    robot's path along it, bounded by the beams -- but a double bounce may
    reflect anywhere on it.  A wall ends where it meets another wall or at an
    edge (a jamb, a pillar):

    * an end with one of ``points`` on the wall's line (within ``tolerance``)
      within ``snap`` of it, either side, ends there (the seen extent is
      bearing-limited: it overshoots or stops short of a jamb by centimetres);
    * else, two walls at more than 30 degrees whose lines cross beyond an end of
      each (or within ``tolerance`` inside it), within ``reach`` of both ends,
      meet there: both grow to the crossing;
    * else, an end grows to the nearest of ``points`` on its line beyond it,
      within ``reach``.

    A doorway stays open (its jambs stop the walls either side); a wall end that
    meets nothing keeps its seen extent.

    Parameters
    ----------
    segments : array_like, shape (W, 2, 2)
        The walls' seen extents, m.
    points : array_like, shape (P, 2)
        Fixed points: corners, edges, fixed points undecided between the two, m.
    reach, tolerance, snap : float
        m.
    """
    grown = np.array(segments, dtype=float).reshape(-1, 2, 2)
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    if not len(grown):
        return grown
    start = grown[:, 0].copy()
    length = np.linalg.norm(grown[:, 1] - start, axis=-1)
    tangent = (grown[:, 1] - start) / np.where(length > 0, length, 1.0)[:, None]
    # Beyond-end gap of a position along each wall: < 0 before the start, > length after the end.
    target = np.full((len(grown), 2), np.nan)  # per end: the position along the wall it ends at
    if len(points):
        offset = points[None, :, :] - start[:, None, :]  # (W, P, 2)
        along = np.einsum("wpi,wi->wp", offset, tangent)
        across = np.abs(offset[..., 0] * tangent[:, None, 1] - offset[..., 1] * tangent[:, None, 0])
        on_line = (across <= tolerance) & (length[:, None] > 0)
        for end, gap in ((0, -along), (1, along - length[:, None])):  # > 0 beyond the end
            near = np.where(on_line & (np.abs(gap) <= snap), np.abs(gap), np.inf)
            nearest = np.argmin(near, axis=1)
            found = np.isfinite(near[np.arange(len(grown)), nearest])
            target[found, end] = along[found, nearest[found]]
    best = np.where(np.isnan(target), np.inf, -np.inf)  # per end: how far a crossing grows it, m
    cross = tangent[:, None, 0] * tangent[None, :, 1] - tangent[:, None, 1] * tangent[None, :, 0]  # sin of the angle
    steep = (np.abs(cross) > 0.5) & (length[:, None] > 0) & (length[None, :] > 0)
    i, j = np.nonzero(steep)
    if i.size:
        offset = start[j] - start[i]
        along_i = (offset[:, 0] * tangent[j, 1] - offset[:, 1] * tangent[j, 0]) / cross[i, j]
        along_j = (offset[:, 0] * tangent[i, 1] - offset[:, 1] * tangent[i, 0]) / cross[i, j]
        gap_i = np.maximum(-along_i, along_i - length[i])
        gap_j = np.maximum(-along_j, along_j - length[j])
        meet = (gap_i >= -tolerance) & (gap_i <= reach) & (gap_j >= -tolerance) & (gap_j <= reach)
        for wall, position, gap in zip(i[meet], along_i[meet], np.maximum(gap_i[meet], 0.0), strict=True):
            end = int(position > 0.5 * length[wall])
            if gap < best[wall, end]:
                best[wall, end], target[wall, end] = gap, position
    if len(points):
        for end, gap in ((0, -along), (1, along - length[:, None])):
            gap = np.where(on_line & (gap > 0.0) & (gap <= reach), gap, np.inf)
            nearest = np.argmin(gap, axis=1)
            distance = gap[np.arange(len(grown)), nearest]
            free = np.isnan(target[:, end]) & np.isfinite(distance)
            target[free, end] = along[free, nearest[free]]
    for end in (0, 1):
        found = np.isfinite(target[:, end])
        grown[found, end] = start[found] + target[found, end, None] * tangent[found]
    return grown


def landmark_paths(landmarks: Landmarks, placement: Placement, layout: Layout) -> np.ndarray:
    """The 3-D paths ``c * tof`` each landmark implies for every receiver of its group, (L, K), m.

    ``landmarks`` in the frame of ``placement`` (of the sensor at its pose).
    The horizontal paths of the landmark's own model
    (:func:`sonar_ring.localise.reflector_paths`: for the pair that placed it,
    the ones it was solved from; a plane, a corner or an undecided point by its
    virtual image, an edge by itself) with each receiver's height offset.

    Raises
    ------
    ValueError
        On landmarks of inconsistent shapes, a group not of the layout, or a placement of another layout.
    """
    check_landmarks(landmarks, "landmark_paths")
    _check_placement(placement, layout, "landmark_paths")
    # Copies in the types load_kernels compiled, as explain_landmarks takes them.
    group = np.array(landmarks.group, dtype=np.int64)
    outside = np.flatnonzero((group < 0) | (group >= layout.n_groups))
    if outside.size:
        raise ValueError(f"landmark_paths: group must be in 0..{layout.n_groups - 1}, got {group[outside[0]]}")
    return solvers.grouped_path_rows(placement.tx, placement.rx, layout.plan.height_offset, group,
                                     np.array(landmarks.position, dtype=float),
                                     np.asarray(landmarks.landmark_class) == EDGE)


@dataclass(frozen=True)
class KnownMap:
    """A map as the echo tests use it (:func:`known_map`): W walls, P points, as contiguous float arrays.

    Attributes
    ----------
    seen : ndarray, shape (W, 2, 2)
        The walls' seen extents, m (what blocks a landmark: :func:`impossible`).
    normals : ndarray, shape (W, 2)
        Each wall's unit normal towards the side it was seen from.
    walls : ndarray, shape (W, 2, 2)
        The walls grown to where they end (:func:`walls_to_their_ends`; what reflects a double bounce), m.
    points : ndarray, shape (P, 2)
        Corners, edges, fixed points, m.
    wall_support, point_support : ndarray, shape (W,), (P,)
        Each entry's observations.
    reflecting, heard : _MapGeometry
        The grown walls and the points as :func:`predict` takes them, and the seen extents and the points
        (what :func:`audible` predicts): computed once per map, not per ping.
    unit_normals : ndarray, shape (W, 2)
        ``normals`` scaled to unit length, as :func:`impossible` takes them.

    Raises
    ------
    ValueError
        On arrays of the wrong shape, or a zero or non-finite normal of a wall.
    """

    seen: np.ndarray
    normals: np.ndarray
    walls: np.ndarray
    points: np.ndarray
    wall_support: np.ndarray
    point_support: np.ndarray
    reflecting: _MapGeometry = field(init=False, repr=False, compare=False)
    heard: _MapGeometry = field(init=False, repr=False, compare=False)
    unit_normals: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        walls, points = _map_arrays(self.walls, self.points, "KnownMap")
        seen = _segments(self.seen, "KnownMap", "seen")
        if seen.shape != walls.shape:
            raise ValueError(f"KnownMap: seen must have the shape of walls {walls.shape}, got {seen.shape}")
        wall_support = _support(self.wall_support, len(walls), "wall_support", "KnownMap")
        point_support = _support(self.point_support, len(points), "point_support", "KnownMap")
        for name, value in (("seen", seen), ("walls", walls), ("points", points), ("wall_support", wall_support),
                            ("point_support", point_support)):
            object.__setattr__(self, name, value)  # as checked: contiguous float arrays
        object.__setattr__(self, "reflecting", _MapGeometry.of(walls, points, seen, wall_support, point_support,
                                                               JUNCTION))
        object.__setattr__(self, "heard", _MapGeometry.of(seen, points, None, wall_support, point_support, JUNCTION))
        object.__setattr__(self, "unit_normals", _unit_normals(self.normals, seen, "KnownMap"))

    def __len__(self) -> int:
        return len(self.seen) + len(self.points)


def known_map(entries: Landmarks, tests: EchoTests) -> KnownMap:
    """The map ``entries`` (walls as PLANE with their ``segment``; points) prepared for :func:`explain_landmarks`."""
    wall = entries.landmark_class == PLANE
    points = np.asarray(entries.position, dtype=float)[~wall]
    fixed = np.isin(entries.landmark_class[~wall], (CORNER, EDGE, CORNER_OR_EDGE))
    seen = np.asarray(entries.segment, dtype=float)[wall]
    observations = np.asarray(entries.observations, dtype=float)
    grown = walls_to_their_ends(seen, points[fixed], tests.wall_reach, tests.wall_tolerance)
    return KnownMap(seen, np.asarray(entries.normal, dtype=float)[wall], grown, points,
                    observations[wall], observations[~wall])


def audible(known: KnownMap, layout: Layout, sensor_pose, sensor_covariance, tests: EchoTests) -> np.ndarray:
    """Which entries of the map (walls, then points) should be heard by some receiver from ``sensor_pose``.

    An entry's own echo (a wall's over its seen extent, a point's) reaches a receiver of some group in its
    beam and range and crosses no wall seen at least as often (:func:`predict` with the pose's
    covariance in the tolerance, single bounces only), (W + P,) bool.
    """
    if len(known) == 0:
        return np.zeros(0, bool)
    tolerance = Tolerance(tests.sigma_path, sensor_covariance, tests.sigma_speed, tests.sigma_map, tests.gate_sigmas)
    groups = np.arange(layout.n_groups)
    prediction = _predict(known.heard, place(layout, sensor_pose), layout, groups, np.zeros(groups.size, np.int64),
                          np.empty((groups.size, layout.receivers_per_group)), False, tolerance,
                          2.0 * layout.max_range, True, False)
    return image_method.own_echoes(prediction.kind, prediction.first, np.isfinite(prediction.path).any(axis=1),
                                   len(known.seen), len(known.points))


def explain_landmarks(landmarks: Landmarks, layout: Layout, sensor_pose, sensor_covariance, known: KnownMap,
                      tests: EchoTests) -> Explained:
    """Which of one ping's landmarks the map explains, as multipath or as impossible.

    The echo of each landmark is the paths it implies (:func:`landmark_paths`);
    the map's walls (grown to where they end) and points make the paths
    :func:`predict` gives at the sensor's pose, with the pose's covariance in
    the tolerance; :func:`match` labels multipath (an entry's own echo does
    not save it if the entry was seen less than the double bounce's, nor a
    later echo than the entry's own that a double bounce off it explains:
    :func:`sonar_ring.image_method.multipath_rows`), :func:`impossible` the rest whose
    legs cross a wall's seen extent from its front (margin: ``gate_sigmas`` times the landmark's and
    the map's position error).  The steps after the landmarks' paths run as one compiled call
    (:func:`sonar_ring.image_method.explain_rows`).  A layout whose groups have several
    transmitters (whose landmark does not say which one sent) is not tested.

    Parameters
    ----------
    landmarks : Landmarks
        L labelled landmarks of one ping, sensor frame.
    layout : Layout
    sensor_pose : array_like, shape (3,)
        The sensor's estimated pose ``(x, y, yaw)`` in the map's frame.
    sensor_covariance : array_like, shape (3, 3)
        Its covariance.
    known : KnownMap
        The map, in its frame (:func:`known_map`).
    tests : EchoTests

    Returns
    -------
    Explained
    """
    check_landmarks(landmarks, "explain_landmarks")
    count = len(landmarks)
    if count == 0 or len(known) == 0 or layout.group_transmitters.shape[1] != 1:
        return Explained.nothing(np.full((count, 2), np.nan), len(known))
    # Only what the tests use goes into the map's frame (not transform_landmarks' every field), and the rows
    # they take, in one compiled call: the glue around the kernels was a quarter of this function's time.
    placement = place(layout, sensor_pose)
    # Copies (np.array) in the types load_kernels compiled, whatever arrays the caller's landmarks hold (a
    # read-only one is another type to numba).
    in_map, rows, group, position, normal, is_plane, is_edge, echo, covariance, bad = _rows_in_map(
        np.array(landmarks.position, dtype=float), np.array(landmarks.normal, dtype=float),
        np.array(landmarks.valid, dtype=bool), np.array(landmarks.group, dtype=np.int64),
        np.array(landmarks.landmark_class, dtype=np.uint8), np.array(landmarks.echo, dtype=np.int64),
        np.array(landmarks.covariance, dtype=float), placement.rotation, placement.pose, layout.n_groups)
    if bad >= 0:
        raise ValueError(f"explain_landmarks: group must be in 0..{layout.n_groups - 1}, got {landmarks.group[bad]}")
    if rows.size == 0:
        return Explained.nothing(np.full((count, 2), np.nan), len(known))
    out = Explained.nothing(in_map, len(known))
    slot = np.zeros(rows.size, np.int64)
    tolerance = Tolerance(tests.sigma_path, sensor_covariance, tests.sigma_speed, tests.sigma_map, tests.gate_sigmas)
    paths = solvers.grouped_path_rows(placement.tx, placement.rx, layout.plan.height_offset, group, position, is_edge)
    # The map's arrays and the rows are checked once (KnownMap, _rows_in_map): the private step of predict, not
    # the public function that checks them again at every ping; match, the rules above and impossible run as
    # one compiled call.
    prediction = _predict(known.reflecting, placement, layout, group, slot, paths, True, tolerance,
                          2.0 * layout.max_range, True, True)
    out.multipath[rows], out.impossible[rows], out.heard[:] = image_method.explain_rows(
        prediction.kind, prediction.first, prediction.second, prediction.support, prediction.path,
        prediction.jacobian, prediction.channel_start, len(known.seen), len(known.points), known.seen,
        known.unit_normals, placement.tx, placement.rx, group, slot, paths, echo, position, normal, is_plane,
        covariance, tolerance.pose_covariance, tolerance.sigma_path, tolerance.sigma_speed, tolerance.sigma_map,
        tolerance.gate_sigmas)
    return out


def load_kernels() -> None:
    """Load the compiled kernels now instead of at the first ping the mapper explains.

    Runs each with the argument types of production (and those of
    :mod:`sonar_ring.image_method`'s kernels it uses).
    """
    from sonar_ring.geometry import load_layout

    image_method.load_kernels()
    layout = load_layout("browne_ring")
    pose, covariance = np.array([0.5, 0.5, 0.0]), np.diag([1e-4, 1e-4, 1e-4])
    placement = place(layout, pose)
    walls = np.array([[[0.0, 0.0], [2.0, 0.0]], [[2.0, 0.0], [2.0, 2.0]]])
    points = np.array([[1.0, 1.5]])
    rows = np.zeros(1, dtype=np.int64)
    tolerance = Tolerance(sigma_path=1e-3)
    paths = np.ones((1, layout.receivers_per_group))
    match(predict(walls, points, placement, layout, rows, rows, tolerance, paths=paths), layout, rows, rows, paths,
          tolerance)
    plane = make_landmarks([PLANE], [[1.0, 0.0]], normal=[[0.0, 1.0]])
    landmark_paths(plane, placement, layout)
    impossible(reflection_points(plane, placement, layout, rows), placement, layout, rows, rows, walls,
               [[0.0, 1.0], [-1.0, 0.0]], 0.01)
    known = KnownMap(walls, facing(walls, pose[:2]), walls, points, np.ones(len(walls)), np.ones(len(points)))
    tests = EchoTests()
    explain_landmarks(plane, layout, pose, covariance, known, tests)
    audible(known, layout, pose, covariance, tests)


# --------------------------------------------------------------------------- checks and set-up


@dataclass(frozen=True)
class _MapGeometry:
    """A map's walls and points as :func:`sonar_ring.image_method.map_paths` takes them, checked.

    What depends on the map alone, computed once per map (:class:`KnownMap` holds two: its walls grown to where
    they end and its walls' seen extents): the walls' frames (:func:`sonar_ring.image_method.wall_frames`), the
    junctions within ``junction`` m, the walls' seen extents (W, 2, 2), the points (P, 2) and the supports.
    """

    frames: tuple
    seen: np.ndarray
    points: np.ndarray
    wall_support: np.ndarray
    point_support: np.ndarray
    excluded_pair: np.ndarray
    excluded_point: np.ndarray

    @classmethod
    def of(cls, walls, points, seen, wall_support, point_support, junction: float) -> _MapGeometry:
        """From checked contiguous arrays (:func:`predict`'s); ``seen`` None: the walls themselves."""
        seen = walls if seen is None else seen
        return cls(image_method.wall_frames(walls), seen, points, wall_support, point_support,
                   *image_method.junctions(walls, points, junction))


def _predict(geometry: _MapGeometry, placement: Placement, layout: Layout, group, slot, row_paths, gated: bool,
             tolerance: Tolerance, max_path: float, prune: bool, doubles: bool) -> Prediction:
    """:func:`predict` of a checked map and checked rows: groups and transmitter slots (N,), paths (N, K)."""
    start, direction, normal, length = geometry.frames
    (kind, first, second, path_group, path_slot, support, path, jacobian, first_point, last_point,
     channel_start) = image_method.map_paths(
        start, direction, normal, length, geometry.seen, geometry.points, geometry.wall_support,
        geometry.point_support, geometry.excluded_pair, geometry.excluded_point, placement.tx, placement.rx,
        placement.tx_axis, placement.rx_axis, layout.plan.height_offset, layout.group_transmitters,
        group * layout.group_transmitters.shape[1] + slot, row_paths, placement.pose, max_path, layout.beam_half_angle,
        tolerance.pose_covariance, tolerance.xy_sigma, tolerance.yaw_sigma, tolerance.sigma_path, tolerance.sigma_speed,
        tolerance.sigma_map, tolerance.gate_sigmas, layout.isotropic_emitter, prune, gated, doubles)
    return Prediction(group=path_group, slot=path_slot, kind=kind, first=first, second=second, support=support,
                      path=path, jacobian=jacobian, first_point=first_point, last_point=last_point,
                      channel_start=channel_start)


def _match(prediction: Prediction, layout: Layout, group, slot, paths, tolerance: Tolerance,
           direct_wins: bool) -> Explanation:
    """:func:`match` of checked rows: their groups and transmitter slots (N,) and paths (N, K), contiguous."""
    channel = group * layout.group_transmitters.shape[1] + slot
    best, direct, residual, direct_residual, double_support = image_method.match_rows(
        channel, paths, prediction.channel_start, prediction.kind, prediction.support, prediction.path,
        prediction.jacobian, tolerance.pose_covariance, tolerance.sigma_path, tolerance.sigma_speed,
        tolerance.sigma_map, tolerance.gate_sigmas)
    # An echo that a mapped reflector's own echo explains as well may be that reflector's: not multipath.
    label = np.where((residual <= tolerance.gate_sigmas)
                     & ~(direct_wins & (direct_residual <= tolerance.gate_sigmas)), MULTIPATH, NONE)
    return Explanation(label=label.astype(np.uint8), best=best, residual=residual, direct=direct,
                       direct_residual=direct_residual, double_support=double_support)


def _impossible(points, placement: Placement, group, slot, walls, unit_normals, margin) -> np.ndarray:
    """:func:`impossible` of checked arrays: points (L, K, 2), walls (W, 2, 2), unit normals (W, 2), margins (L,)."""
    return image_method.reflections_blocked(np.ascontiguousarray(points, dtype=float), group, slot, placement.tx,
                                            placement.rx, walls, unit_normals, margin)


def _segments(segments, caller: str, name: str = "walls") -> np.ndarray:
    """Wall segments (W, 2, 2) as a contiguous float array, the shape checked."""
    segments = np.ascontiguousarray(segments, dtype=float)
    if segments.ndim != 3 or segments.shape[1:] != (2, 2):
        raise ValueError(f"{caller}: {name} must have shape (W, 2, 2) (segments of two points), got {segments.shape}")
    return segments


def _unit_normals(normals, walls: np.ndarray, caller: str) -> np.ndarray:
    """The normals (W, 2) of ``walls`` scaled to unit length, checked (a wall left out may have any)."""
    normals = np.ascontiguousarray(normals, dtype=float)
    if normals.shape != (len(walls), 2):
        raise ValueError(f"{caller}: normals must have shape ({len(walls)}, 2), one per wall, got {normals.shape}")
    unit, bad = _scaled_to_unit(normals, walls)
    if bad >= 0:
        raise ValueError(f"{caller}: normals must be finite and not zero, got {normals!r}")
    return unit


def _map_arrays(walls, points, caller: str):
    """The map's walls (W, 2, 2) and points (P, 2) as contiguous float arrays, their shapes checked."""
    walls = _segments(walls, caller)
    points = np.ascontiguousarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 2:
        raise ValueError(f"{caller}: points must have shape (P, 2), got {points.shape}")
    return walls, points


def _support(support, count: int, name: str, caller: str) -> np.ndarray:
    """Observations of ``count`` entries as a float array (zeros when not given), checked."""
    if support is None:
        return np.zeros(count)
    support = np.ascontiguousarray(support, dtype=float)
    if support.shape != (count,):
        raise ValueError(f"{caller}: {name} must have shape ({count},), got {support.shape}")
    return support


def _channels(layout: Layout, group, transmitter, caller: str):
    """Each row's group and transmitter slot (int64), checked against the layout."""
    group = np.asarray(group)
    transmitter = np.asarray(transmitter)
    if group.ndim != 1 or transmitter.shape != group.shape:
        raise ValueError(f"{caller}: group and transmitter must be 1-D and of one length, got shapes "
                         f"{group.shape} and {transmitter.shape}")
    if group.size and not (group.dtype.kind in "iu" and transmitter.dtype.kind in "iu"):
        raise ValueError(f"{caller}: group and transmitter must be integers, got {group.dtype} and "
                         f"{transmitter.dtype}")
    group = group.astype(np.int64, copy=False)
    slot, bad = _slots(group, transmitter.astype(np.int64, copy=False), layout.group_transmitters)
    if bad >= 0:
        if not 0 <= group[bad] < layout.n_groups:
            raise ValueError(f"{caller}: group must be in 0..{layout.n_groups - 1}, got {group[bad]}")
        raise ValueError(f"{caller}: transmitter {transmitter[bad]} is not one of group {group[bad]}'s "
                         f"{layout.group_transmitters[group[bad]].tolist()}")
    return group, slot


def _check_placement(placement: Placement, layout: Layout, caller: str) -> None:
    slots, receivers = layout.group_transmitters.shape[1], layout.receivers_per_group
    if placement.tx.shape != (layout.n_groups, slots, 2) or placement.rx.shape != (layout.n_groups, receivers, 2):
        raise ValueError(f"{caller}: the placement is of another layout (tx {placement.tx.shape}, "
                         f"rx {placement.rx.shape}; layout {layout.name!r} has ({layout.n_groups}, {slots}, 2) "
                         f"and ({layout.n_groups}, {receivers}, 2))")


def _row_paths(paths, rows: int, layout: Layout, caller: str) -> np.ndarray:
    """The rows' measured paths as a contiguous (N, K) float array."""
    paths = np.ascontiguousarray(paths, dtype=float)
    if paths.shape != (rows, layout.receivers_per_group):
        raise ValueError(f"{caller}: paths must have shape ({rows}, {layout.receivers_per_group}) "
                         f"(rows, receivers), got {paths.shape}")
    return paths


# --------------------------------------------------------------------------- kernels


@kernel
def _slots(group, transmitter, group_transmitters):
    """The slot of each row's transmitter in its group's ``group_transmitters`` row, and the first row without.

    A row has no slot when its group or its transmitter is unknown (-1 there); the first such row is -1 when
    every row has one.
    """
    slot = np.full(group.shape[0], -1, dtype=np.int64)
    bad = -1
    for n in range(group.shape[0]):
        if 0 <= group[n] < group_transmitters.shape[0]:
            for m in range(group_transmitters.shape[1]):
                if group_transmitters[group[n], m] == transmitter[n] and slot[n] < 0:
                    slot[n] = m
        if slot[n] < 0 and bad < 0:
            bad = n
    return slot, bad


@kernel
def _rows_in_map(position, normal, valid, group, landmark_class, echo, covariance, rotation, pose, n_groups):
    """One ping's L landmarks (sensor frame) in the map's frame, and the rows the echo tests take.

    ``position`` (L, 2) turned by ``rotation`` (2, 2) and moved to the pose's position (NaN stays NaN); the rows:
    valid landmarks of finite position, with their group, map-frame position and normal (N, 2), whether each is
    a plane or an edge, its echo and its covariance (N, 2, 2, as given: the margins' eigenvalue does not turn).
    The last value is the first of those rows whose group is not in ``0..n_groups - 1`` (-1: none).  The arrays
    have L rows each (:func:`sonar_ring.landmarks.check_landmarks`).
    """
    count = position.shape[0]
    turned = np.ascontiguousarray(rotation.T)
    # The product in BLAS, as numpy's ``@`` (of two or more rows the same numbers; one row may differ in the last bit).
    in_map = np.ascontiguousarray(position) @ turned
    normal_in_map = np.ascontiguousarray(normal) @ turned
    used = np.zeros(count, dtype=np.bool_)
    bad = -1
    for n in range(count):
        in_map[n, 0] += pose[0]
        in_map[n, 1] += pose[1]
        used[n] = valid[n] and np.isfinite(in_map[n, 0]) and np.isfinite(in_map[n, 1])
        if used[n] and not 0 <= group[n] < n_groups and bad < 0:
            bad = n
    rows = np.flatnonzero(used)
    size = rows.shape[0]
    row_group = np.empty(size, dtype=np.int64)
    row_position = np.empty((size, 2))
    row_normal = np.empty((size, 2))
    is_plane = np.empty(size, dtype=np.bool_)
    is_edge = np.empty(size, dtype=np.bool_)
    row_echo = np.empty(size, dtype=np.int64)
    row_covariance = np.empty((size, 2, 2))
    for i in range(size):
        n = rows[i]
        row_group[i] = group[n]
        for axis in range(2):
            row_position[i, axis] = in_map[n, axis]
            row_normal[i, axis] = normal_in_map[n, axis]
        is_plane[i] = landmark_class[n] == PLANE
        is_edge[i] = landmark_class[n] == EDGE
        row_echo[i] = echo[n]
        row_covariance[i] = covariance[n]
    return in_map, rows, row_group, row_position, row_normal, is_plane, is_edge, row_echo, row_covariance, bad


@kernel
def _scaled_to_unit(normals, walls):
    """``normals`` (W, 2) over their lengths, and the first wall whose normal is not finite or zero (-1: none).

    Only walls (W, 2, 2) with finite ends count; the normals of the others are left as they are.
    """
    unit = np.empty_like(normals)
    bad = -1
    for w in range(normals.shape[0]):
        used = (np.isfinite(walls[w, 0, 0]) and np.isfinite(walls[w, 0, 1]) and np.isfinite(walls[w, 1, 0])
                and np.isfinite(walls[w, 1, 1]))
        length = math.hypot(normals[w, 0], normals[w, 1])
        if used and not (np.isfinite(length) and length > 0) and bad < 0:
            bad = w
        scale = length if used else 1.0
        unit[w, 0], unit[w, 1] = normals[w, 0] / scale, normals[w, 1] / scale
    return unit, bad
