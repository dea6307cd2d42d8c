"""Landmark SLAM: the robot's pose in ``map`` from its odometry and the landmarks it maps (GTSAM, iSAM2).

The mapper's core when ``slam`` is on.  Per ping, :meth:`LandmarkSlam.add_ping`
takes the labelled landmarks (sensor frame) and the robot's odometry pose
(``odom``) at the ping, and:

1. **predicts** the robot's pose in ``map`` from the latest keyframe's estimate
   and the odometry since (``X = X_k (+) (o_k^-1 (+) o)``), with its uncertainty;
2. **associates** the landmarks with the map in ``map``: the front end is a
   :class:`~sonar_ring.mapping.LandmarkMap` (gates, walls as lines with seen
   extents, points, PLANE vs CORNER over motion), fed with the sightings'
   covariances widened by the pose's uncertainty, so its gates include it;
3. **keeps** each associated sighting as the sensor gave it, relative to the
   latest keyframe (the odometry between the two, a few centimetres, is
   folded in); what it measures is decided at the keyframe, by what its entry
   is then (:meth:`LandmarkSlam._measured`);
4. at a **keyframe** (every ``keyframe_distance`` of travel, ``keyframe_turn``
   of turn or ``keyframe_pings`` pings), adds to the factor graph the
   odometry between the keyframes (``BetweenFactorPose2``), one fused
   measurement per entry seen since the last keyframe, of the sightings that
   agree with the graph (:func:`consistent_sightings`) -- a corner, an edge:
   ``BearingRangeFactor2D``; a wall: a foot-point factor (:func:`wall_factor`)
   on the line ``n(theta) . x = d`` -- and updates the estimate incrementally
   (``IncrementalFixedLagSmoother``: iSAM2 that marginalises keyframes older
   than ``smoother_lag``, so memory stays flat; landmarks stay.  The update's cost
   grows with the keyframes in the window, so the lag is short: the landmarks, which stay, carry
   what the old keyframes knew.  On the same recorded runs (realistic room, 3 laps) 15 s gave the
   same maps and trajectories as 60 s (6 seeds) at a quarter of the p99 cost, 285 -> 76 ms, and
   5 s the same as 15 s (10 seeds) with the p99 14 -> 9 ms).  The new estimates of the landmarks
   go back into the front end.  The keyframe's marginal covariance (the pose's uncertainty for the
   gates and the echo tests) is the smoother's every ``covariance_every`` keyframes and held, turned
   into each keyframe's frame, in between: the marginal costs tens of milliseconds once the map is
   large, and holding it gave better maps (same runs, realistic world, 10 seeds of 3 laps: 18.3
   reflectors of 21 right instead of 15.6, trajectory RMS 2.8 cm instead of 4.0, ghosts 26.6 instead
   of 28.4, the mapper's p99 per ping 260 ms instead of 521).  To it is added the pose's error that the
   graph does not model (``unmodelled_position_sigma``, ``unmodelled_yaw_sigma``).

An entry's sightings from before it is confirmed are **held**, per keyframe, as long as the
smoother keeps that keyframe; when the entry is confirmed they enter the graph at their own
keyframes.  A wall is a wall only after the sensor has moved (an UNKNOWN point until then) and
is confirmed a few pings later: without its first sightings, the graph placed every wall with
the heading the odometry had when it was confirmed, and the odometry's heading noise of the
first decimetres turned the whole map (recorded realistic runs, 3 laps, the four most turned:
seeds 3, 12, 19, 1: -0.52/-0.42/-0.30/-0.27 deg; with them -0.21/+0.06/+0.14/-0.07; the
most turned of the 20 now 0.24 deg).

Only **confirmed** entries enter the graph: an entry must persist
(:meth:`~sonar_ring.mapping.LandmarkMap.persistent`: seen in the front end's
``min_support_pings`` pings, the sensor ``min_support_travel`` from where it
first saw it).  A one-ping phantom never is; a reflector seen from a few poses
is.  Sightings the mapper explained (multipath, impossible:
:mod:`sonar_ring.explain`) are matched by the front end but never measured;
an entry it explains away leaves the graph's output (its variable, unconnected
from then on, is marginalised with the keyframes of its time).  An undecided point
must not pull the pose towards the wrong model:

* an UNKNOWN *sighting* is placed with the corner model (Browne s7), which
  for a convex edge is off across the line of sight by about a degree (the
  same way from the same side: fusing does not average it away) and along it
  by a tenth of a millimetre; until its point is told an edge or a corner
  (:mod:`sonar_ring.curvature`), a point's UNKNOWN sightings keep only their
  range (``undecided_bearing_sigma`` across the line of sight); once told, the
  sighting's position under the point's model counts whole;
* an undecided *entry* (:meth:`~sonar_ring.mapping.LandmarkMap.decided`) never
  enters the graph (nor the published map): an UNKNOWN point -- a plane or a
  fixed point, motion has not told which, or a ghost whose sightings fit
  neither -- and a ring's CORNER_OR_EDGE point until its curvature tells an
  edge from a corner.  A ring's true corners and edges decide within metres;
  what stays undecided is almost all multipath (realistic room, one lap: 256
  of 257), which in the graph bent the trajectory (same 10 recorded runs of 3
  laps: 2.8 cm RMS with it, 1.5 cm without).  Only walls and decided points
  enter.

Re-observing the first lap's landmarks associates with them (the gates include the pose's
uncertainty), which closes the loop without duplicating them.

Faults never raise: an odometry increment faster than ``max_speed`` or
``max_turn_rate`` (a slip, a pushed robot) starts a new **session** -- a new
map from that pose on, never merged with the old one -- and is reported, as is
a stretch of ``no_landmarks_after`` seconds of travel without a confirmed landmark.

Frames (REP 105): ``map`` (the estimate's frame; it starts equal to ``odom`` at
the first ping), ``odom`` (the odometry's), the robot (``base_link``) and the
sensor at ``sensor_offset`` in it.  Units m, rad.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields

import gtsam
import numpy as np

from sonar_ring.air import AirSpeed
from sonar_ring.compiled import kernel
from sonar_ring.curvature import PointModels
from sonar_ring.landmarks import CORNER, EDGE, Landmarks
from sonar_ring.localise import OK, PointEstimate, reflector_paths
from sonar_ring.mapping import LandmarkMap, transform_landmarks, usable_covariance
from sonar_ring.mapping import load_kernels as load_map_kernels
from sonar_ring.poses import (
    compose,
    inverse,
    relative_pose,
    step_covariance,
    turned_covariances,
    turned_pose_covariance,
)
from sonar_ring.uncertainty import position_jacobian

POSE, POINT, WALL = "x", "l", "w"
"""Symbol characters of the graph's keyframe poses, point landmarks and walls."""

AIR_GATE_CHI2 = 10.83
"""A sighting's squared bearing error in its variance above which the air's fit leaves it out (chi-square, 1
degree of freedom, 99.9 %)."""


@dataclass(frozen=True)
class SlamSettings:
    """How the SLAM works; see the module docstring.

    Attributes
    ----------
    keyframe_distance, keyframe_turn : float
        Travel (m) and turn (rad) after which a new keyframe is made.
    keyframe_pings : int
        Pings after which a new keyframe is made even without motion.
    odometry_distance_noise : float
        Odometry noise assumed along the travel, m per sqrt(m) rolled.  These four make the noise of an
        odometry step where the odometry's own covariance does not give it (:func:`~sonar_ring.poses.step_covariance`).
    odometry_heading_noise : float
        Odometry heading noise assumed, rad per sqrt(m) rolled.
    odometry_scale : float
        Relative distance error assumed on top (a scale error, modelled as noise), fraction.
    odometry_heading_bias : float
        Heading error assumed per metre driven on top, rad/m.
    track_width : float
        Distance between the wheels, m: a turn on the spot rolls them ``track_width / 2 * |turn|``.
    sighting_sigma : float
        Unmodelled error of one sighting, m (added to its covariance in the graph).
    undecided_bearing_sigma : float
        Uncertainty across the line of sight (m) given to an UNKNOWN point's sightings.
    wall_end_reach, wall_end_tolerance : float
        A wall ends at a corner or edge within ``wall_end_tolerance`` (m) of its line and ``wall_end_reach``
        (m) of an end of its seen extent (:meth:`LandmarkSlam.published`).  A seen extent runs up to about
        0.25 m past the wall's end where an echo on its line continues it (a double bounce off the wall
        beside it, an edge's echo placed a degree off): the realistic room's pillar faces in 2 of 14
        recorded runs, published as ghosts with a reach of 0.2 m.
    max_speed, max_turn_rate : float
        Odometry increments beyond these (m/s, rad/s, with the ping interval) are a fault.
    no_landmarks_after : float
        Seconds of travel without a confirmed landmark after which the SLAM says so.
    smoother_lag : float
        Seconds of keyframes the smoother keeps; older ones are marginalised.
    relinearize_threshold, relinearize_skip : float, int
        iSAM2's: a variable is relinearised when its estimate moved this much (m, rad), checked every
        ``relinearize_skip`` updates.
    covariance_every : int
        Keyframes between two marginal covariances from the smoother; the keyframes between hold the last
        one, turned into their own frame (:meth:`LandmarkSlam._add_keyframe`).
    unmodelled_position_sigma, unmodelled_yaw_sigma : float
        The pose's error that the graph does not model (m, rad), added to the marginal covariance wherever the
        pose's uncertainty is used: the front end's gates, the echo tests, ``slam/pose``.  The graph fuses the
        sightings as independent and knows nothing of the air's speed error (a scale of the map about its
        origin) or of a residual turn; its marginal alone claimed 8 mm and 0.44 deg where the pose was off by
        11-19 mm and 0.4 deg RMS (recorded realistic runs, 3 laps: NEES 4-10 against 3), and the tighter gates
        left multipath fragments unexplained (ghosts in 3 of 20 runs).  With these, the NEES is 1.5-1.6.
    sighting_gate_chi2 : float
        A sighting since the latest keyframe enters the graph only if it lies within this squared Mahalanobis
        distance (its own covariance) of where the graph's estimate puts its entry, seen from the keyframe's
        estimate corrected by the sightings that agree (:func:`consistent_sightings`).  Fused into one factor
        per entry, a double bounce that the front end associated with a real entry, or that makes a ghost entry
        of its own with a few real echoes, pulls the pose; in the first metres, before the map holds the walls
        that explain it, such a ghost turned the whole map (MAPPING.md).  The air's fit takes every sighting
        (its own gate is on the bearing alone, :data:`AIR_GATE_CHI2`): with this gate, the sightings the air's
        error turns most failed it more often and the fit came out low.
    sigma_path, sigma_speed : float
        One receiver's path noise ``c * sigma_tof`` (m) and the relative error of the speed of sound the nodes
        assume: the air's fit (:mod:`sonar_ring.air`) weighs the sightings by the one and starts from the
        other (0: the assumed speed is taken as right and the map is published as the graph holds it).
    """

    keyframe_distance: float = 0.1
    keyframe_turn: float = 0.1
    keyframe_pings: int = 30
    odometry_distance_noise: float = 0.02
    odometry_heading_noise: float = 0.02
    odometry_scale: float = 0.02
    odometry_heading_bias: float = 0.01
    track_width: float = 0.4
    sighting_sigma: float = 0.002
    undecided_bearing_sigma: float = 0.1
    wall_end_reach: float = 0.3
    wall_end_tolerance: float = 0.03
    relinearize_threshold: float = 0.01
    relinearize_skip: int = 10
    max_speed: float = 2.0
    max_turn_rate: float = 4.0
    no_landmarks_after: float = 5.0
    smoother_lag: float = 5.0
    covariance_every: int = 10
    unmodelled_position_sigma: float = 0.011
    unmodelled_yaw_sigma: float = 0.0066
    sighting_gate_chi2: float = 4.0
    sigma_path: float = 343e-6
    sigma_speed: float = 0.0035


ESTIMATOR_FAILED = "estimator failed"
"""The fault when GTSAM raises in a keyframe's update (an indeterminate system: sightings that leave a variable
unfixed, as a ping of damaged landmarks can give): the session's graph is dropped and a new one starts at the
ping, as after an odometry jump, so the mapper goes on."""


@dataclass
class SlamReport:
    """What one :meth:`LandmarkSlam.add_ping` did.

    Attributes
    ----------
    pose : ndarray, shape (3,)
        The robot's estimated pose in ``map`` at the ping.
    associated : int
        Sightings that went into a confirmed landmark.
    tentative : int
        Sightings that went into an entry not yet in the graph.
    keyframe : bool
        Whether the ping made a keyframe (and the graph was updated).
    inconsistent : int
        Sightings that keyframe left out of the graph, too far from the graph's estimate
        (``sighting_gate_chi2``).
    fault : str
        Empty, or why a new session started: ``odometry jump`` or :data:`ESTIMATOR_FAILED`.
    step_noise_assumed : bool
        Whether the keyframe's odometry step had a covariance with it that did not give the step's noise
        (:func:`~sonar_ring.poses.step_covariance`), so the odometry parameters' noise was taken.
    """

    pose: np.ndarray
    associated: int = 0
    tentative: int = 0
    keyframe: bool = False
    inconsistent: int = 0
    fault: str = ""
    step_noise_assumed: bool = False


@dataclass
class _Confirmed:
    """An entry in the graph: its key and kind (:data:`POINT` or :data:`WALL`)."""

    key: int
    kind: str


@dataclass
class _Seen:
    """Sightings as the sensor gave them, in the robot frame of one keyframe: what they measure is decided later.

    When they are measured (:meth:`LandmarkSlam._measured`), their entry's kind then says how: a wall's foot
    point, a decided point's position under its model, an undecided one's range.  Per sighting: the entry uid
    (n,), the sensor's position (n, 2) and heading (n,), where it was seen from (its group's transmitter,
    :meth:`~sonar_ring.mapping.LandmarkMap.viewpoints_at`) (n, 2), the landmark's position (n, 2) and covariance
    (n, 2, 2) as labelled, its class (n,) and receiver group (n,), and both point models
    (:class:`~sonar_ring.curvature.PointModels`; ``model_valid`` (n,) False where the ping gave none).
    """

    uid: np.ndarray
    sensor: np.ndarray
    heading: np.ndarray
    viewpoint: np.ndarray
    group: np.ndarray
    position: np.ndarray
    covariance: np.ndarray
    landmark_class: np.ndarray
    model_valid: np.ndarray
    edge: np.ndarray
    edge_covariance: np.ndarray
    corner: np.ndarray
    corner_covariance: np.ndarray

    @staticmethod
    def joined(parts: list[_Seen]) -> _Seen:
        """The sightings of ``parts``, in order."""
        return _Seen(*(np.concatenate([getattr(part, name.name) for part in parts]) for name in fields(_Seen)))

    def select(self, rows) -> _Seen:
        """The sightings ``rows`` (an index array or a mask)."""
        return _Seen(*(getattr(self, name.name)[rows] for name in fields(_Seen)))

    def rename(self, old: int, new: int) -> None:
        self.uid[self.uid == old] = new


@dataclass
class _AirRows:
    """Sightings for the air's fit (:meth:`LandmarkSlam._fit_air`), measured at the keyframe ``pose_key``.

    ``is_wall`` (n,) whether each one's entry is a wall (else a corner); ``position`` (n, 2) the sighting by the
    virtual-image model, the keyframe's frame.
    """

    pose_key: int
    seen: _Seen
    is_wall: np.ndarray
    position: np.ndarray


@dataclass
class _Held:
    """The sightings of entries not in the graph yet, at keyframe ``index`` (made at ``time``, s)."""

    index: int
    time: float
    seen: _Seen


# --------------------------------------------------------------------------- factors


def wall_error(pose: gtsam.Pose2, line: np.ndarray, measured: np.ndarray, jacobians=None) -> np.ndarray:
    """Foot-point residual of a wall ``n(theta) . x = d`` (``line = (theta, d)``, map frame) seen from ``pose``.

    The foot of the perpendicular from the robot's origin onto the line, in the
    robot frame, is ``f = s R^T n`` with ``s = d - n . t``; the residual is
    ``f - measured`` (2,).  ``jacobians`` (a list of two, or None) receives
    d(residual)/d(pose) (2, 3), in the pose's body-frame tangent space (GTSAM's
    ``Pose2.retract``), and d(residual)/d(line) (2, 2).
    """
    # Scalars throughout: iSAM2 calls this for every wall factor it relinearises, and small numpy
    # temporaries cost most of the time (24 us a call with them, 3.8 us without, same results to 1e-14).
    theta, distance = float(line[0]), float(line[1])
    x, y, heading = pose.x(), pose.y(), pose.theta()
    # m = R^T n: the normal in the robot frame
    m0, m1 = math.cos(theta - heading), math.sin(theta - heading)
    cos_t, sin_t = math.cos(theta), math.sin(theta)
    s = distance - (cos_t * x + sin_t * y)
    residual = np.array([s * m0 - measured[0], s * m1 - measured[1]])
    if jacobians is not None:
        jacobians[0] = np.array([[-m0 * m0, -m0 * m1, s * m1], [-m1 * m0, -m1 * m1, -s * m0]])
        # d/d(theta): (across . -t) m + s R^T across, with across = (-sin, cos) and R^T across = (-m1, m0)
        pulled = sin_t * x - cos_t * y
        jacobians[1] = np.array([[pulled * m0 - s * m1, m0], [pulled * m1 + s * m0, m1]])
    return residual


def wall_factor(pose_key: int, line_key: int, measured: np.ndarray, noise) -> gtsam.CustomFactor:
    """The factor of a wall's foot point ``measured`` (robot frame, (2,)) with ``noise``: :func:`wall_error`."""

    def error(factor, values, jacobians):
        residual = wall_error(values.atPose2(pose_key), values.atVector(line_key), measured,
                              jacobians)
        return residual

    return gtsam.CustomFactor(noise, [pose_key, line_key], error)


def _foot_points(point: np.ndarray, sensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Feet from the origin onto the lines through ``point`` (n, 2) perpendicular to ``point - sensor``, Jacobians.

    Returns ``f = (n . point) n`` with ``n = (point - sensor) / |point - sensor|`` (n, 2) and
    d f / d point (n, 2, 2) (``sensor`` (n, 2) or (2,) held fixed).
    """
    offset = point - sensor
    distance = np.hypot(offset[:, 0], offset[:, 1])
    normal = offset / distance[:, None]
    along = np.einsum("ni,ni->n", normal, point)
    outer = normal[:, :, None] * normal[:, None, :]
    turn = (np.eye(2) - outer) / distance[:, None, None]  # d n / d point, symmetric
    return along[:, None] * normal, normal[:, :, None] * (normal + np.einsum("nij,nj->ni", turn, point))[:, None, :] \
        + along[:, None, None] * turn


def consistent_sightings(pose: np.ndarray, prior: np.ndarray, position: np.ndarray, covariance: np.ndarray,
                         is_wall: np.ndarray, anchor: np.ndarray, normal: np.ndarray, chi2: float,
                         rounds: int = 3) -> np.ndarray:
    """Which sightings agree with their entries' estimates, seen from a pose that may be off: (n,) bool.

    Parameters
    ----------
    pose : ndarray, shape (3,)
        The robot's estimated pose in map (x, y, yaw; m, rad).
    prior : ndarray, shape (3, 3)
        Covariance of that estimate's error in its body-frame tangent (GTSAM's ``Pose2.retract``).
    position, covariance : ndarray, shapes (n, 2), (n, 2, 2)
        What each sighting measures, in the robot's frame at ``pose`` (m): a point's position, a wall's foot
        point from the robot's origin; and its covariance (m^2).
    is_wall : ndarray of bool, shape (n,)
        Whether each sighting's entry is a wall.
    anchor, normal : ndarray, shape (n, 2)
        Each entry's estimate in map: a point ``anchor``, or the line through it with unit ``normal``.
    chi2 : float
        Largest squared Mahalanobis distance, in the sighting's own covariance, of a sighting that agrees.
    rounds : int
        Fits of the pose's correction.

    The pose's correction ``delta`` (body frame) is fitted first: the weighted least squares of the
    sightings that agree, linearised about ``pose``, with ``prior`` (a slip of the odometry moves every
    sighting alike, a double bounce one); the first round takes every sighting.  A sighting agrees when, after
    ``delta``, its squared Mahalanobis distance is at most ``chi2``.

    Raises ValueError for arrays of other shapes, a ``chi2`` that is not a positive number or ``rounds`` below 1.
    """
    count = len(position)
    shapes = {"pose": (np.shape(pose), (3,)), "prior": (np.shape(prior), (3, 3)),
              "position": (np.shape(position), (count, 2)), "covariance": (np.shape(covariance), (count, 2, 2)),
              "is_wall": (np.shape(is_wall), (count,)), "anchor": (np.shape(anchor), (count, 2)),
              "normal": (np.shape(normal), (count, 2))}
    for name, (shape, wanted) in shapes.items():
        if shape != wanted:
            raise ValueError(f"consistent_sightings: {name} must have shape {wanted}, got {shape}")
    if not (math.isfinite(chi2) and chi2 > 0.0) or rounds < 1:
        raise ValueError(f"consistent_sightings: chi2 must be a positive number and rounds at least 1, got {chi2!r}"
                         f" and {rounds!r}")
    return _agreeing(np.asarray(pose, dtype=float), np.asarray(prior, dtype=float), np.asarray(position, dtype=float),
                     np.asarray(covariance, dtype=float), np.asarray(is_wall, dtype=bool),
                     np.asarray(anchor, dtype=float), np.asarray(normal, dtype=float), float(chi2), int(rounds))


@kernel
def _agreeing(pose, prior, position, covariance, is_wall, anchor, normal, chi2, rounds):
    """:func:`consistent_sightings` of checked arrays, in one compiled call (it runs at every keyframe)."""
    count = position.shape[0]
    expected, jacobian = _expected_measurements(pose, is_wall, anchor, normal)
    error = position - expected
    information = _inverse(covariance)
    # J^T W J (3, 3) and J^T W e (3,) of each sighting
    normal_matrix = np.zeros((count, 3, 3))
    pulled = np.zeros((count, 3))
    for n in range(count):
        for i in range(3):
            weighted_x = jacobian[n, 0, i] * information[n, 0, 0] + jacobian[n, 1, i] * information[n, 1, 0]
            weighted_y = jacobian[n, 0, i] * information[n, 0, 1] + jacobian[n, 1, i] * information[n, 1, 1]
            for j in range(3):
                normal_matrix[n, i, j] = weighted_x * jacobian[n, 0, j] + weighted_y * jacobian[n, 1, j]
            pulled[n, i] = weighted_x * error[n, 0] + weighted_y * error[n, 1]
    prior_information = np.linalg.inv(prior)
    agrees = np.ones(count, dtype=np.bool_)
    for _ in range(rounds):
        system = prior_information.copy()
        total = np.zeros(3)
        for n in range(count):
            if agrees[n]:
                system += normal_matrix[n]
                total += pulled[n]
        delta = np.linalg.solve(system, total)
        for n in range(count):
            left_x = error[n, 0] - (jacobian[n, 0, 0] * delta[0] + jacobian[n, 0, 1] * delta[1]
                                    + jacobian[n, 0, 2] * delta[2])
            left_y = error[n, 1] - (jacobian[n, 1, 0] * delta[0] + jacobian[n, 1, 1] * delta[1]
                                    + jacobian[n, 1, 2] * delta[2])
            w = information[n]
            agrees[n] = (left_x * (w[0, 0] * left_x + w[0, 1] * left_y)
                         + left_y * (w[1, 0] * left_x + w[1, 1] * left_y)) <= chi2
    return agrees


@kernel
def _expected_measurements(pose, is_wall, anchor, normal):
    """What entries measure from the robot at ``pose`` (3,), map: in its frame (n, 2), and d/d(pose) (n, 2, 3).

    A point at ``anchor`` (n, 2) its position; where ``is_wall`` (n,), the line through ``anchor`` with unit
    ``normal`` (n, 2) its foot point from the robot's origin (:func:`wall_error`'s).  The derivative is by the
    pose's body-frame tangent (GTSAM's ``Pose2.retract``): ``e = R^T (a - t)`` moves by ``-d - dtheta e^perp``, a
    foot point ``s m`` (``m = R^T n``, ``s = n . (a - t)``) by ``-(m . d) m - dtheta s m^perp``.
    """
    cos, sin = math.cos(pose[2]), math.sin(pose[2])
    count = anchor.shape[0]
    expected = np.empty((count, 2))
    jacobian = np.zeros((count, 2, 3))
    for n in range(count):
        # the anchor in the robot frame: R^T (a - t)
        offset_x, offset_y = anchor[n, 0] - pose[0], anchor[n, 1] - pose[1]
        if is_wall[n]:
            facing_x = normal[n, 0] * cos + normal[n, 1] * sin  # m = R^T n
            facing_y = -normal[n, 0] * sin + normal[n, 1] * cos
            reach = normal[n, 0] * offset_x + normal[n, 1] * offset_y
            expected[n, 0], expected[n, 1] = reach * facing_x, reach * facing_y
            jacobian[n, 0, 0], jacobian[n, 0, 1] = -facing_x * facing_x, -facing_x * facing_y
            jacobian[n, 1, 0], jacobian[n, 1, 1] = -facing_y * facing_x, -facing_y * facing_y
            jacobian[n, 0, 2], jacobian[n, 1, 2] = reach * facing_y, -reach * facing_x
        else:
            expected[n, 0] = offset_x * cos + offset_y * sin
            expected[n, 1] = -offset_x * sin + offset_y * cos
            jacobian[n, 0, 0] = jacobian[n, 1, 1] = -1.0
            jacobian[n, 0, 2], jacobian[n, 1, 2] = expected[n, 1], -expected[n, 0]
    return expected, jacobian


def _seen(landmarks: Landmarks, models: PointModels | None, uids: np.ndarray, sensor: np.ndarray,
          viewpoint: np.ndarray) -> _Seen:
    """Sightings ``landmarks`` (sensor frame) of the entries ``uids``, the sensor at ``sensor`` in the keyframe.

    ``viewpoint`` (n, 2): where each was seen from, in the keyframe.

    Only the positions and covariances turn (not :func:`~sonar_ring.mapping.transform_landmarks`' every field and
    check: this runs at every ping, on landmarks the front end has just checked).
    """
    count = len(uids)
    rotation = np.array([[np.cos(sensor[2]), -np.sin(sensor[2])], [np.sin(sensor[2]), np.cos(sensor[2])]])
    if models is None:
        models = PointModels(np.full((count, 2), np.nan), np.full((count, 2), np.nan), np.zeros((count, 2, 2)),
                             np.zeros((count, 2, 2)), np.zeros(count), np.zeros(count, bool))
    else:
        models = models.transformed(sensor)
    return _Seen(uids.copy(), np.tile(sensor[:2], (count, 1)), np.full(count, sensor[2]), viewpoint,
                 np.asarray(landmarks.group, dtype=np.int64),
                 np.asarray(landmarks.position, dtype=float) @ rotation.T + sensor[:2],
                 turned_covariances(landmarks.covariance, rotation), np.array(landmarks.landmark_class), models.valid,
                 models.edge, models.edge_covariance, models.corner, models.corner_covariance)


def _usable(covariance) -> np.ndarray | None:
    """``covariance`` where the map takes it (:func:`~sonar_ring.mapping.usable_covariance`), else None."""
    return covariance if covariance is not None and usable_covariance(covariance) else None


def _fused(uid: np.ndarray, measurement: np.ndarray, covariance: np.ndarray):
    """Each entry's measurements fused: information-weighted mean and its covariance.

    Of the measurements (n, 2) with covariances (n, 2, 2) of the entries ``uid`` (n,): the entries (a list,
    ascending), their means (E, 2) and covariances (E, 2, 2).
    """
    entries, index = np.unique(uid, return_inverse=True)
    information = _inverse(covariance)
    total = np.zeros((entries.size, 2, 2))
    np.add.at(total, index, information)
    pulled = np.zeros((entries.size, 2))
    np.add.at(pulled, index, np.einsum("nij,nj->ni", information, measurement))
    fused_covariance = _inverse(total)
    return entries.tolist(), np.einsum("eij,ej->ei", fused_covariance, pulled), fused_covariance


@kernel
def _inverse(matrix):
    """Inverses of (n, 2, 2) matrices in closed form (this module's kernels call it)."""
    out = np.empty(matrix.shape)
    for n in range(matrix.shape[0]):
        determinant = matrix[n, 0, 0] * matrix[n, 1, 1] - matrix[n, 0, 1] * matrix[n, 1, 0]
        out[n, 0, 0], out[n, 0, 1] = matrix[n, 1, 1] / determinant, -matrix[n, 0, 1] / determinant
        out[n, 1, 0], out[n, 1, 1] = -matrix[n, 1, 0] / determinant, matrix[n, 0, 0] / determinant
    return out


# --------------------------------------------------------------------------- the SLAM


def load_kernels() -> None:
    """Load the map's compiled kernels (:func:`sonar_ring.mapping.load_kernels`), the air's fit's and SLAM's own now.

    The air's fit (:meth:`LandmarkSlam._pair_geometry`) takes a sighting's Jacobian by its paths and the
    paths from compiled loops: one sighting 1 m in front of a pair, with the production argument types.
    """
    load_map_kernels()
    transmitter, receivers, position = np.zeros((1, 2)), np.array([[[0.3, 0.02], [0.3, -0.02]]]), np.array([[1.0, 0.0]])
    position_jacobian(PointEstimate(position, np.ones(1, bool), np.full(1, OK, np.int8), "corner"), transmitter,
                      receivers[:, 0], receivers[:, 1])
    reflector_paths(transmitter, receivers, position, np.zeros(1, bool))
    unit = np.tile(np.eye(2), (1, 1, 1))
    consistent_sightings(np.zeros(3), np.eye(3), position, unit, np.zeros(1, bool), position, position, 4.0)
    _inverse(unit)  # the keyframe's fused factors (_fused)


class LandmarkSlam:
    """Keyframe landmark SLAM over a :class:`~sonar_ring.mapping.LandmarkMap` front end (module docstring).

    Parameters
    ----------
    settings : SlamSettings
    front_end : dict, optional
        Keyword arguments of the front end's :class:`~sonar_ring.mapping.LandmarkMap`.
    """

    def __init__(self, settings: SlamSettings = SlamSettings(), front_end: dict | None = None, layout=None):
        self.settings = settings
        # the ring whose pairs the air's fit uses; none where it is off (not a ring, or sigma_speed 0)
        self._plan = layout.plan if layout is not None and layout.kind == "ring" and settings.sigma_speed > 0 else None
        self.air = AirSpeed(settings.sigma_speed)
        self.air_estimate = self.air.fit()
        self._unmodelled = np.diag([settings.unmodelled_position_sigma ** 2, settings.unmodelled_position_sigma ** 2,
                                    settings.unmodelled_yaw_sigma ** 2])
        self._front_end = dict(front_end or {})
        self.sessions = 0
        self._start_session()

    def _start_session(self) -> None:
        parameters = gtsam.ISAM2Params()
        parameters.setRelinearizeThreshold(self.settings.relinearize_threshold)
        parameters.relinearizeSkip = self.settings.relinearize_skip
        self._smoother = gtsam.IncrementalFixedLagSmoother(self.settings.smoother_lag, parameters)
        self.front = LandmarkMap(**self._front_end)
        self._confirmed: dict[int, _Confirmed] = {}
        self._since_keyframe: list[_Seen] = []  # one part per ping
        self._held: list[_Held] = []  # the keyframes still in the smoother's window, oldest first
        self._keyframe = -1  # index of the latest keyframe
        self._keyframe_odometry = None  # its odometry pose
        self._keyframe_odometry_covariance = None  # and that pose's covariance, when it is one the map takes
        self._keyframe_pose = None  # its estimate in map
        self._keyframe_covariance = np.zeros((3, 3))
        self._origin = np.zeros(2)  # the first keyframe's position in map: the published map's scale is about it
        self._keyframe_time = 0.0
        self._pings_since_keyframe = 0
        self._next_landmark = 0
        self._air_rows: list[_AirRows] = []  # the air's sightings measured since the last update
        self.air.start_session()
        self._last_odometry = None
        self._latest_pose = None  # (pose, covariance) in map at the latest ping: pose_at its odometry
        self._last_time = None
        self._last_seen_time = None
        self._ping = 0
        self.sessions += 1

    # ------------------------------------------------------------------ per ping

    def add_ping(self, landmarks: Landmarks, odometry, time: float, sensor_offset=(0.0, 0.0, 0.0),
                 models: PointModels | None = None, explained=None, odometry_covariance=None) -> SlamReport:
        """Add one ping's landmarks (sensor frame) taken with the robot at ``odometry`` (``odom``) at ``time`` s.

        ``odometry_covariance`` (3, 3), that pose's covariance in ``odom`` when the odometry gives one: the
        noise of the odometry's steps is then its growth where it grows (:func:`~sonar_ring.poses.step_covariance`),
        else the parameters' (:class:`SlamSettings`).

        ``models`` are both point models of each landmark (sensor frame,
        :func:`sonar_ring.curvature.point_models`): the front end's evidence
        for edge or corner, and a decided point's measurement.  ``explained``
        (L,) marks the landmarks the caller explained against :meth:`snapshot`
        at :meth:`pose_at` (:mod:`sonar_ring.explain`); a ping that starts a
        new session ignores it (the map it was explained by is gone).

        Returns what it did (:class:`SlamReport`).  Never raises on bad data:
        the front end counts unusable landmarks; a non-finite pose skips the ping.
        """
        odometry = np.asarray(odometry, dtype=float)
        offset = np.asarray(sensor_offset, dtype=float)
        fault = self._check_odometry(odometry, time)
        if fault:
            self._start_session()
        inconsistent, assumed = 0, False
        if self._keyframe < 0:
            self._first_keyframe(odometry, odometry_covariance, time)
        elif self._is_keyframe(odometry):
            try:
                inconsistent, assumed = self._add_keyframe(odometry, odometry_covariance, time)
            except RuntimeError:  # GTSAM's exceptions (an indeterminate system): the graph is not to be trusted
                fault = ESTIMATOR_FAILED
                self._start_session()
                self._first_keyframe(odometry, odometry_covariance, time)
        keyframe = self._pings_since_keyframe == 0
        self._pings_since_keyframe += 1
        self._ping += 1
        self._last_odometry, self._last_time = odometry, time
        step = relative_pose(self._keyframe_odometry, odometry)
        pose = compose(self._keyframe_pose, step)
        covariance = self._pose_covariance(pose, step, self._measured_step(odometry, odometry_covariance))
        self._latest_pose = pose, covariance  # what pose_at gives until the next ping: pose() returns it
        report = SlamReport(pose=self._scaled_pose(pose), keyframe=keyframe, inconsistent=inconsistent, fault=fault,
                            step_noise_assumed=assumed)
        if not len(landmarks):
            return report
        sensor = compose(pose, offset)
        in_map = transform_landmarks(landmarks, sensor)
        extra = self._pose_spread(in_map.position, pose, covariance)
        widened = Landmarks(in_map.landmark_class, in_map.position, in_map.normal, in_map.covariance + extra,
                            in_map.confidence, in_map.segment, in_map.observations, in_map.group, in_map.echo,
                            in_map.valid, in_map.reason)
        models_in_map = None
        if models is not None:
            models_in_map = models.transformed(sensor).widened(extra)
        placed = self.front.update(widened, sensor, models_in_map, None if fault else explained)
        self._follow_renames(placed.renamed)
        for uid in placed.removed.tolist():
            self._confirmed.pop(uid, None)
        self.air.forget(placed.removed)
        stored = placed.uid >= 0
        rows, uids = placed.rows[stored], placed.uid[stored]
        confirmed = np.array([uid in self._confirmed for uid in uids.tolist()], dtype=bool)
        report.associated = int(np.count_nonzero(confirmed))
        report.tentative = int(uids.size - report.associated)
        if report.associated:
            self._last_seen_time = time
        seen_at = compose(step, offset)
        self._since_keyframe.append(_seen(landmarks.select(rows), None if models is None else models.select(rows),
                                          uids, seen_at, self.front.viewpoints_at(landmarks.group[rows], seen_at)))
        return report

    def _check_odometry(self, odometry: np.ndarray, time: float) -> str:
        """``odometry jump`` when the increment since the last ping is faster than the robot can move."""
        if self._last_odometry is None:
            return ""
        forward, sideways, turn = relative_pose(self._last_odometry, odometry)
        interval = max(time - self._last_time, 1e-3)
        s = self.settings
        if math.hypot(forward, sideways) > s.max_speed * interval + 0.02 or abs(turn) > s.max_turn_rate * interval \
                + 0.02:
            return "odometry jump"
        return ""

    @staticmethod
    def _pose_spread(position, pose, covariance) -> np.ndarray:
        """What the pose's uncertainty adds to the covariance of map-frame positions (L, 2): (L, 2, 2).

        A landmark at ``p`` moves by ``dt`` and ``dphi x (p - t)`` when the pose
        moves: ``J = [I, (p - t) turned by 90 deg]`` with the pose's ``covariance``
        (:meth:`_pose_covariance`).
        """
        lever = position - pose[:2]
        jacobian = np.zeros((len(position), 2, 3))
        jacobian[:, 0, 0] = jacobian[:, 1, 1] = 1.0
        jacobian[:, 0, 2], jacobian[:, 1, 2] = -lever[:, 1], lever[:, 0]
        return jacobian @ covariance @ jacobian.transpose(0, 2, 1)

    def _keyframe_covariance_in_map(self) -> np.ndarray:
        """The keyframe's covariance as ``(x, y, yaw)`` in ``map``, (3, 3): its marginal and the unmodelled error.

        The marginal (body-frame tangent) turned into ``map``, plus ``unmodelled_position_sigma`` and
        ``unmodelled_yaw_sigma`` (:class:`SlamSettings`).
        """
        return turned_pose_covariance(self._keyframe_covariance, self._keyframe_pose[2]) + self._unmodelled

    def _pose_covariance(self, pose, step, measured) -> np.ndarray:
        """Covariance (3, 3) in ``map`` of the robot's ``pose`` there, the odometry ``step`` past the keyframe.

        The keyframe's (:meth:`_keyframe_covariance_in_map`) and the step's: ``measured``, the odometry's own
        in the keyframe's frame (:meth:`_measured_step`), turned into ``map``; else the parameters'.
        """
        if measured is None:
            odometry = self._odometry_covariance(step, pose[2])
        else:
            odometry = turned_pose_covariance(self._step_noise(step, measured), self._keyframe_pose[2])
        return self._keyframe_covariance_in_map() + odometry

    def _measured_step(self, odometry, covariance) -> np.ndarray | None:
        """The odometry's covariance (3, 3) of its step from the keyframe to ``odometry`` (``covariance``).

        In the keyframe's frame; None where either pose has no covariance the map takes
        (:func:`~sonar_ring.mapping.usable_covariance`) or it did not grow (:func:`~sonar_ring.poses.step_covariance`).
        """
        if self._keyframe_odometry_covariance is None or _usable(covariance) is None:
            return None
        return step_covariance(self._keyframe_odometry, self._keyframe_odometry_covariance, odometry, covariance)

    def _step_noise(self, step, measured) -> np.ndarray:
        """Covariance (3, 3) of the odometry ``step`` in the keyframe's frame: ``measured``, else the parameters'.

        ``measured`` (:meth:`_measured_step`) with the parameters' floor, a step never known better than to 0.1
        mm and 0.1 mrad (its information stays finite).
        """
        if measured is None:
            return self._odometry_covariance(step, 0.0)
        return measured + 1e-8 * np.eye(3)

    def _odometry_covariance(self, step, yaw: float) -> np.ndarray:
        """Covariance of the odometry ``step`` (forward, sideways, turn) as ``(x, y, yaw)`` in ``map``, (3, 3).

        Of the parameters (:class:`SlamSettings`), with the robot's heading ``yaw``.
        """
        forward, sideways, turn = step
        distance = math.hypot(forward, sideways)
        s = self.settings
        rolled = distance + 0.5 * s.track_width * abs(turn)
        along = s.odometry_distance_noise ** 2 * rolled + (s.odometry_scale * distance) ** 2 + 1e-8
        heading = s.odometry_heading_noise ** 2 * rolled + (s.odometry_heading_bias * distance) ** 2 + 1e-8
        across = along + heading * distance ** 2 / 3.0
        c, s_ = math.cos(yaw), math.sin(yaw)
        rotate = np.array([[c, -s_], [s_, c]])
        covariance = np.zeros((3, 3))
        covariance[:2, :2] = rotate @ np.diag([along, across]) @ rotate.T
        covariance[2, 2] = heading
        return covariance

    def _measured(self, seen: _Seen, is_wall: np.ndarray, entry_class: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What ``seen`` measures of entries that are walls where ``is_wall`` (n,), of class ``entry_class`` (n,).

        Measurement (n, 2) and its covariance (n, 2, 2), in the keyframe's robot frame.  A wall's is the foot of
        the perpendicular from the keyframe's origin onto the wall's line, from the sighting's foot point ``G``
        (on the line, perpendicular to the line of sight from its viewpoint ``S``, the transmitter): the line
        ``n . x = n . G`` with ``n = (G - S) / |G - S|``.  A point's is its position under its entry's decided
        model (an EDGE's edge model, a CORNER's corner model), else the sighting's own keeping only its range
        (module docstring).
        """
        position, covariance = seen.position.copy(), seen.covariance.copy()
        decided = np.zeros(len(position), bool)
        for code, model, model_covariance in ((EDGE, seen.edge, seen.edge_covariance),
                                              (CORNER, seen.corner, seen.corner_covariance)):
            chosen = ~is_wall & seen.model_valid & (entry_class == code)
            position[chosen] = model[chosen]
            covariance[chosen] = model_covariance[chosen]
            decided |= chosen
        covariance += self.settings.sighting_sigma ** 2 * np.eye(2)
        if is_wall.any():
            foot, jacobian = _foot_points(position[is_wall], seen.viewpoint[is_wall])
            position[is_wall] = foot
            covariance[is_wall] = jacobian @ covariance[is_wall] @ jacobian.transpose(0, 2, 1)
        # A point not yet decided may be an edge placed with the corner model, its bearing up to a degree off,
        # the same way from the same side: it keeps only its range (module docstring).
        ranged = ~is_wall & ~decided & (seen.landmark_class != EDGE)
        if ranged.any():
            covariance[ranged] = _without_bearing(position[ranged] - seen.viewpoint[ranged], covariance[ranged],
                                                  self.settings.undecided_bearing_sigma)
        return position, covariance

    def _pair_geometry(self, seen: _Seen, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stretch (n, 2) and covariance (n, 2, 2) of sightings at ``position`` (keyframe frame), that frame.

        (``J d`` and ``sigma_path^2 J J^T`` plus ``sighting_sigma``: ``J`` the corner model's derivative by the
        pair's two paths ``d``, :func:`~sonar_ring.uncertainty.position_jacobian`, the model the sightings of walls
        and corners were placed by.)
        """
        turn = np.empty((len(position), 2, 2))  # sensor frame -> keyframe frame
        turn[:, 0, 0] = turn[:, 1, 1] = np.cos(seen.heading)
        turn[:, 1, 0] = np.sin(seen.heading)
        turn[:, 0, 1] = -turn[:, 1, 0]
        in_sensor = np.einsum("nji,nj->ni", turn, position - seen.sensor)
        transmitter, receivers = self._plan.transmitters[seen.group, 0], self._plan.receivers[seen.group]
        count = len(position)
        corner = PointEstimate(in_sensor, np.ones(count, bool), np.full(count, OK, np.int8), "corner")
        jacobian = turn @ position_jacobian(corner, transmitter, receivers[:, 0], receivers[:, 1])
        paths = reflector_paths(transmitter, receivers, in_sensor, np.zeros(count, bool))
        covariance = self.settings.sigma_path ** 2 * jacobian @ jacobian.transpose(0, 2, 1)
        covariance[:, 0, 0] += self.settings.sighting_sigma ** 2
        covariance[:, 1, 1] += self.settings.sighting_sigma ** 2
        return np.einsum("nij,nj->ni", jacobian, paths), covariance

    def _keep_for_air(self, pose_key: int, seen: _Seen, is_wall: np.ndarray, entry_class: np.ndarray) -> None:
        """Keep the sightings of walls and corners placed by the virtual-image model for :meth:`_fit_air`."""
        corner = ~is_wall & (entry_class == CORNER)
        position = np.where((corner & seen.model_valid)[:, None], seen.corner, seen.position)
        imaged = (is_wall | corner) & ((seen.landmark_class != EDGE) | (corner & seen.model_valid))
        if imaged.any():
            self._air_rows.append(_AirRows(pose_key, seen.select(imaged), is_wall[imaged], position[imaged]))

    def _fit_air(self, estimate: gtsam.Values) -> None:
        """The sightings kept since the last update into :attr:`air` (:mod:`sonar_ring.air`), against ``estimate``.

        A wall's sighting measures the wall's angle (its bearing from the sensor), a corner's the corner across
        the line of sight (map frame); each where the estimate says it should have been, for its stretch and
        its variance: those of the sighting itself follow its noise (its bearing), and weights that do bias the
        fit (by a third of the air's 0.35 % on walls, recorded ideal runs).
        """
        rows, self._air_rows = self._air_rows, []
        for part in rows:
            if not estimate.exists(part.pose_key):
                continue
            pose = estimate.atPose2(part.pose_key)
            seen = part.seen
            # Each entry's estimate: a wall's line (theta, d), a corner's position, both in map; NaN if gone.
            entries, first, index = np.unique(seen.uid, return_index=True, return_inverse=True)
            value = np.full((entries.size, 2), np.nan)
            for row, (uid, wall) in enumerate(zip(entries.tolist(), part.is_wall[first].tolist(), strict=True)):
                record = self._confirmed.get(uid)
                if record is not None and estimate.exists(record.key):
                    value[row] = estimate.atVector(record.key) if wall else estimate.atPoint2(record.key)
            values = value[index]
            x, y, yaw = pose.x(), pose.y(), pose.theta()
            turn = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
            # where each sighting should have been (keyframe frame): a corner's position; on a wall, the foot of
            # the perpendicular from its viewpoint, on the line n . x = d - n . t (n turned into the keyframe)
            expected = (values - (x, y)) @ turn
            wall = part.is_wall
            angle = values[:, 0]  # a wall's: its sightings' bearing is near it plus pi
            normal = np.stack([np.cos(angle - yaw), np.sin(angle - yaw)], axis=-1)
            reach = (values[:, 1] - (np.cos(angle) * x + np.sin(angle) * y)
                     - np.einsum("ni,ni->n", normal, seen.viewpoint))
            expected[wall] = (seen.viewpoint + reach[:, None] * normal)[wall]
            stretch, covariance = self._pair_geometry(seen, expected)
            sight = expected - seen.viewpoint
            distance = np.hypot(sight[:, 0], sight[:, 1])
            across = np.stack([-sight[:, 1], sight[:, 0]], axis=-1) / distance[:, None]
            across_stretch = np.einsum("ni,ni->n", across, stretch)
            variance = np.einsum("ni,nij,nj->n", across, covariance, across)
            observes = across @ turn.T
            measured = np.einsum("ni,ni->n", observes, part.position @ turn.T + (x, y))
            error = np.einsum("ni,ni->n", across, part.position - expected)
            if wall.any():  # the bearing from the viewpoint in map, taken near the wall's angle plus pi
                offset = part.position[wall] - seen.viewpoint[wall]
                facing = angle[wall] + np.pi
                measured[wall] = facing + np.angle(np.exp(1j * (np.arctan2(offset[:, 1], offset[:, 0]) + yaw - facing)))
                observes[wall] = (1.0, 0.0)
                across_stretch[wall] /= distance[wall]
                variance[wall] /= distance[wall] ** 2
                error[wall] /= distance[wall]
            # An echo that is not the entry's (a double bounce the echo tests did not explain, a phantom) is
            # as likely off one way as the other, but not by as much as the noise: left out.
            kept = error ** 2 <= AIR_GATE_CHI2 * variance
            self.air.add(seen.uid[kept], observes[kept], measured[kept], across_stretch[kept], variance[kept])

    def _follow_renames(self, renamed: dict) -> None:
        """Entries that live on under another uid keep their record (a wall absorbing a confirmed one inherits it).

        A point that became a wall leaves its variable behind: the wall is confirmed as a wall of its own.
        """
        if not renamed:
            return
        new_uids = list(renamed.values())
        is_wall = dict(zip(new_uids, self.front.classes_of(new_uids)[0].tolist(), strict=True))
        for old, new in renamed.items():
            record = self._confirmed.pop(old, None)
            if record is not None and new not in self._confirmed and (record.kind == WALL) == is_wall[new]:
                self._confirmed[new] = record
            for seen in [*self._since_keyframe, *(held.seen for held in self._held)]:
                seen.rename(old, new)

    # ------------------------------------------------------------------ keyframes

    def _is_keyframe(self, odometry: np.ndarray) -> bool:
        forward, sideways, turn = relative_pose(self._keyframe_odometry, odometry)
        s = self.settings
        return (math.hypot(forward, sideways) >= s.keyframe_distance or abs(turn) >= s.keyframe_turn
                or self._pings_since_keyframe >= s.keyframe_pings)

    def _first_keyframe(self, odometry: np.ndarray, covariance, time: float) -> None:
        """The session's first keyframe: ``map`` = ``odom`` there (a tight prior); clock of :meth:`no_landmarks`."""
        self._last_seen_time = time
        key = gtsam.symbol(POSE, 0)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        pose = gtsam.Pose2(*odometry)
        graph.add(gtsam.PriorFactorPose2(key, pose, gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-4, 1e-4, 1e-5]))))
        values.insert(key, pose)
        self._smoother.update(graph, values, {key: time})
        self._keyframe, self._keyframe_odometry, self._keyframe_time = 0, odometry.copy(), time
        self._keyframe_odometry_covariance = _usable(covariance)
        self._keyframe_pose = odometry.copy()
        self._origin = odometry[:2].copy()
        self._keyframe_covariance = np.diag([1e-8, 1e-8, 1e-10])
        self._pings_since_keyframe = 0

    def _add_keyframe(self, odometry: np.ndarray, covariance, time: float) -> tuple[int, bool]:
        """Odometry to a new keyframe at this ping, the sightings since the last, promotions; update the estimate.

        ``covariance``: the odometry pose's, or None.  Returns how many sightings were left out as
        inconsistent (:meth:`_consistent`), and whether the odometry step's noise was the parameters' though the
        odometry had a covariance (it did not grow).
        """
        previous, key = gtsam.symbol(POSE, self._keyframe), gtsam.symbol(POSE, self._keyframe + 1)
        step = relative_pose(self._keyframe_odometry, odometry)
        graph, values, timestamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), {key: time, previous: time}
        measured = self._measured_step(odometry, covariance)
        odometry_noise = self._step_noise(step, measured)  # in the previous keyframe's frame
        graph.add(gtsam.BetweenFactorPose2(previous, key, gtsam.Pose2(*step),
                                           gtsam.noiseModel.Gaussian.Covariance(odometry_noise)))
        values.insert(key, gtsam.Pose2(*compose(self._keyframe_pose, step)))
        inconsistent = self._add_measurements(previous, odometry_noise, graph, values)
        # Landmarks stay: only keyframes older than the lag are marginalised (the map's size bounds the rest).
        timestamps.update({record.key: time for record in self._confirmed.values()})
        self._smoother.update(graph, values, timestamps)
        self._keyframe += 1
        estimate = self._smoother.calculateEstimate()
        pose = estimate.atPose2(key)
        self._keyframe_pose = np.array([pose.x(), pose.y(), pose.theta()])
        if self._keyframe % self.settings.covariance_every == 0:
            # the slowest keyframes: the air's fit waits for the next (its sightings' keyframes stay in the window)
            self._keyframe_covariance = self._smoother.marginalCovariance(key)
        else:
            # The smoother's marginal costs tens of ms once the map is large (its root clique holds the
            # landmarks); between two, the landmarks hold the pose about as well as at the last one: that
            # one, turned into this keyframe's body frame.
            adjoint = gtsam.Pose2(*step).inverse().AdjointMap()
            self._keyframe_covariance = adjoint @ self._keyframe_covariance @ adjoint.T
            self._fit_air(estimate)
            self.air_estimate = self.air.fit()
        self._keyframe_odometry, self._keyframe_odometry_covariance = odometry.copy(), _usable(covariance)
        self._keyframe_time = time
        self._pings_since_keyframe = 0
        self._since_keyframe.clear()
        self._write_back(estimate)
        return inconsistent, covariance is not None and measured is None

    def _add_measurements(self, pose_key: int, odometry_noise: np.ndarray, graph, values) -> int:
        """Factors of the sightings since the keyframe ``pose_key`` and of those held for entries confirmed now.

        One fused factor per entry in the graph and keyframe: of the sightings since ``pose_key``, and, for an
        entry confirmed now, of its sightings held at the keyframes before that are still in the smoother's
        window -- a wall's sightings from before it was told a wall (an UNKNOWN point's then) among them, so
        the graph has them from the first ping, when the odometry's heading was still right.  Only a
        persistent, decided wall or point is confirmed (module docstring); the sightings of entries not
        confirmed are held for later, as long as their keyframe stays in the window.  The sightings since
        ``pose_key`` are checked against the graph's estimate (:meth:`_consistent`; ``odometry_noise``: the
        covariance (3, 3) of the odometry step from ``pose_key`` to the new keyframe); the held ones, of entries
        the graph has no estimate of yet, are not.  Returns how many it left out.
        """
        seen = _Seen.joined(self._since_keyframe) if self._since_keyframe else None
        entries = self.front.entries()
        by_uid = {uid: index for index, uid in enumerate(entries.uid.tolist())}
        # The keyframes the smoother has not marginalised: made within its lag of the last update (this
        # keyframe's); a keyframe's timestamp there is the next one's, so never earlier than its own.
        window_start = self._keyframe_time - self.settings.smoother_lag
        self._held = [held for held in self._held if held.time > window_start]
        if seen is None:
            return 0
        uids = np.unique(seen.uid)
        decided, persistent = self.front.decided(uids).tolist(), self.front.persistent(uids).tolist()
        measured, confirmed_now = [], []
        for uid, usable, lasting in zip(uids.tolist(), decided, persistent, strict=True):
            index = by_uid.get(uid)
            if index is None or not usable:
                continue
            if uid not in self._confirmed:
                if not lasting:
                    continue
                self._confirm(uid, WALL if entries.is_wall[index] else POINT, entries, index, values)
                confirmed_now.append(uid)
            measured.append(uid)
        in_graph = np.isin(seen.uid, measured)
        inconsistent = self._add_factors(pose_key, seen.select(in_graph), entries, by_uid, graph, odometry_noise)
        if confirmed_now:
            for held in self._held:
                self._add_factors(gtsam.symbol(POSE, held.index),
                                  held.seen.select(np.isin(held.seen.uid, confirmed_now)), entries, by_uid, graph)
        self._held.append(_Held(self._keyframe, self._keyframe_time, seen.select(~in_graph)))
        return inconsistent

    def _add_factors(self, pose_key: int, seen: _Seen, entries, by_uid: dict, graph, odometry_noise=None) -> int:
        """One fused factor per entry of the graph among ``seen``, taken at the keyframe ``pose_key``.

        With ``odometry_noise``, the covariance (3, 3) of the odometry from the latest keyframe to the next (in
        the latest's frame), ``seen`` are that keyframe's
        sightings, and only those that agree with its estimate and with their entries' count in the graph
        (:meth:`_consistent`); the air's fit takes them all.  Returns how many did not agree.
        """
        if not len(seen.uid):
            return 0
        index = np.array([by_uid.get(uid, -1) for uid in seen.uid.tolist()])
        kinds = [self._confirmed[uid].kind for uid in seen.uid.tolist()]
        is_wall = np.array([kind == WALL for kind in kinds])
        # An entry whose kind changed under the same uid (not in the front end any more) is measured no more.
        same = (index >= 0) & (is_wall == entries.is_wall[np.maximum(index, 0)])
        if not same.all():
            seen, index, is_wall = seen.select(same), index[same], is_wall[same]
        position, covariance = self._measured(seen, is_wall, entries.landmark_class[index])
        if self._plan is not None:
            self._keep_for_air(pose_key, seen, is_wall, entries.landmark_class[index])
        left_out = 0
        if odometry_noise is not None:
            consistent = self._consistent(odometry_noise, position, covariance, is_wall, entries.position[index],
                                          entries.normal[index])
            left_out = len(consistent) - int(np.count_nonzero(consistent))
            seen, position, covariance = seen.select(consistent), position[consistent], covariance[consistent]
        for uid, measurement, spread in zip(*_fused(seen.uid, position, covariance), strict=True):
            record = self._confirmed[uid]
            if record.kind == POINT:
                graph.add(_bearing_range_factor(pose_key, record.key, measurement, spread))
            else:
                graph.add(wall_factor(pose_key, record.key, measurement, gtsam.noiseModel.Gaussian.Covariance(spread)))
        return left_out

    def _consistent(self, odometry_noise: np.ndarray, position: np.ndarray, covariance: np.ndarray, is_wall: np.ndarray,
                    anchor: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """:func:`consistent_sightings` seen from the latest keyframe's estimate in map, (n,) bool.

        The keyframe's estimate is off by the odometry since the keyframe before it (a slip moves every
        sighting alike): the prior of its correction is the keyframe's covariance, the unmodelled error and
        ``odometry_noise`` (3, 3), the covariance of the odometry from it to the next keyframe.
        """
        prior = self._keyframe_covariance + self._unmodelled + odometry_noise
        return consistent_sightings(self._keyframe_pose, prior, position, covariance, is_wall, anchor, normal,
                                    self.settings.sighting_gate_chi2)

    def _confirm(self, uid: int, kind: str, entries, index: int, values) -> None:
        """Add entry ``uid`` to the graph, its initial value the front end's estimate."""
        key = gtsam.symbol(POINT if kind == POINT else WALL, self._next_landmark)
        self._next_landmark += 1
        if kind == POINT:
            values.insert(key, gtsam.Point2(*entries.position[index]))
        else:
            normal = entries.normal[index]
            # n . x = d with n the entry's unit normal (towards the side the wall was seen from)
            values.insert(key, np.array([math.atan2(normal[1], normal[0]), float(normal @ entries.position[index])]))
        self._confirmed[uid] = _Confirmed(key, kind)

    def _write_back(self, estimate: gtsam.Values) -> None:
        """The graph's landmark estimates into the front end, so association uses them."""
        points = [(uid, record.key) for uid, record in self._confirmed.items() if record.kind == POINT]
        walls = [(uid, record.key) for uid, record in self._confirmed.items() if record.kind == WALL]
        if points:
            self.front.set_points([uid for uid, _ in points], [estimate.atPoint2(key) for _, key in points])
        if walls:
            lines = np.array([estimate.atVector(key) for _, key in walls])
            self.front.set_walls([uid for uid, _ in walls], lines[:, 0], lines[:, 1])

    # ------------------------------------------------------------------ output

    @property
    def confirmed(self) -> np.ndarray:
        """Uids of the entries in the graph."""
        return np.array(sorted(self._confirmed), dtype=np.int64)

    def snapshot(self, min_observations: int = 1) -> Landmarks:
        """The map in ``map``: confirmed, decided entries (walls first, then points), as :meth:`LandmarkMap.snapshot`.

        Walls end at the confirmed corners and edges on their lines near their ends (:meth:`published`); the
        map is scaled by the air's speed (:meth:`scaled`).
        """
        landmarks = self.published().snapshot(min_observations=min_observations, only=self.confirmed, decided=True)
        return dataclasses.replace(landmarks, position=self.scaled(landmarks.position),
                                   segment=self.scaled(landmarks.segment),
                                   covariance=landmarks.covariance * self._scale() ** 2)

    def scaled(self, points) -> np.ndarray:
        """Points (..., 2) of the graph's ``map`` as published: scaled by ``1 + e`` about the session's start.

        The graph, its gates and the echo tests keep the sightings as the assumed air made them; what is
        published has the air's estimated speed (``e``: :attr:`air_estimate`, :mod:`sonar_ring.air`).
        """
        return self._origin + self._scale() * (np.asarray(points, dtype=float) - self._origin)

    def _scale(self) -> float:
        return 1.0 + self.air_estimate[0]

    def snapshot_and_uids(self, min_observations: int = 1) -> tuple[Landmarks, np.ndarray]:
        """:meth:`snapshot` as the graph holds it, and the uids of its entries, in its order.

        Not :meth:`scaled`: the echo tests compare it with sightings the assumed air made.  From one
        :meth:`published` copy.
        """
        published, confirmed = self.published(), self.confirmed
        return (published.snapshot(min_observations=min_observations, only=confirmed, decided=True),
                published.snapshot_uids(min_observations, only=confirmed, decided=True))

    def forget(self, uids) -> None:
        """Take the entries ``uids`` out of the map and the graph's confirmed set.

        Their variables and factors stay in the smoother until their keyframes pass the lag, so what they did
        to the poses meanwhile stays too (the echo tests remove a ghost 10 s or more after it entered their map,
        past the default 5 s lag).
        """
        self.front.remove(uids)
        self.air.forget(uids)
        for uid in np.asarray(uids, dtype=np.int64).tolist():
            self._confirmed.pop(uid, None)

    def points(self, min_observations: int = 1) -> np.ndarray:
        """Costmap points of the confirmed entries in ``map``, (P, 2), m (walls ended as in :meth:`snapshot`)."""
        return self.scaled(self.published().points(min_observations=min_observations, only=self.confirmed,
                                                    decided=True))

    def published(self) -> LandmarkMap:
        """The front end with the confirmed walls ended at the confirmed points on their lines near their ends.

        (:meth:`~sonar_ring.mapping.LandmarkMap.walls_ended_at`, within
        ``wall_end_tolerance`` of the line and ``wall_end_reach`` of an end.)
        """
        entries = self.front.entries()
        confirmed = np.isin(entries.uid, self.confirmed)
        walls, points = confirmed & entries.is_wall, confirmed & ~entries.is_wall
        return self.front.walls_ended_at(entries.uid[walls], entries.position[points], self.settings.wall_end_reach,
                                         self.settings.wall_end_tolerance)

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The robot's latest pose in ``map`` ``(x, y, yaw)`` and its covariance (3, 3), in ``map`` as published.

        (:meth:`pose_at` the latest ping's odometry, kept from :meth:`add_ping`; :meth:`scaled`.)
        """
        if self._latest_pose is None:
            return np.zeros(3), np.zeros((3, 3))
        pose, covariance = self._latest_pose
        return self._scaled_pose(pose), covariance * np.outer(*2 * [(self._scale(), self._scale(), 1.0)])

    def _scaled_pose(self, pose: np.ndarray) -> np.ndarray:
        return np.concatenate([self.scaled(pose[:2]), pose[2:]])

    def pose_at(self, odometry, odometry_covariance=None) -> tuple[np.ndarray, np.ndarray]:
        """The robot's pose in the graph's ``map`` and its covariance (3, 3) at the odometry pose ``odometry``.

        ``odometry`` in ``odom``, with its covariance there or None (as :meth:`add_ping`'s); not
        :meth:`scaled` (the echo tests' pose).  Predicted from the latest
        keyframe's estimate and the odometry since; before the first ping,
        ``odometry`` itself (``map`` starts equal to ``odom``) with no uncertainty.
        """
        odometry = np.asarray(odometry, dtype=float)
        if self._keyframe < 0:
            return odometry.copy(), np.zeros((3, 3))
        step = relative_pose(self._keyframe_odometry, odometry)
        pose = compose(self._keyframe_pose, step)
        return pose, self._pose_covariance(pose, step, self._measured_step(odometry, odometry_covariance))

    def map_to_odom(self, pose: np.ndarray) -> np.ndarray:
        """The transform ``map -> odom`` ``(x, y, yaw)``: where ``odom`` lies in ``map`` with the robot at ``pose``.

        ``pose`` is :meth:`pose`'s (``map``, as published), the robot at the latest ping's odometry.
        """
        if self._last_odometry is None:
            return np.zeros(3)
        return compose(pose, inverse(self._last_odometry))

    def no_landmarks(self, time: float) -> bool:
        """Whether no confirmed landmark was seen for ``no_landmarks_after`` s up to ``time`` (in this session)."""
        return self._last_seen_time is not None and time - self._last_seen_time > self.settings.no_landmarks_after


def _without_bearing(sight: np.ndarray, covariance: np.ndarray, sigma: float) -> np.ndarray:
    """Covariances (n, 2, 2) of points seen along ``sight`` (n, 2), at least ``sigma`` (m) across the line of sight."""
    radial = sight / np.hypot(sight[:, 0], sight[:, 1])[:, None]
    across = np.stack([-radial[:, 1], radial[:, 0]], axis=-1)
    extra = np.maximum(sigma ** 2 - np.einsum("ni,nij,nj->n", across, covariance, across), 0.0)
    return covariance + extra[:, None, None] * across[:, :, None] * across[:, None, :]


def _bearing_range_factor(pose_key: int, point_key: int, position: np.ndarray, covariance: np.ndarray):
    """A point at ``position`` (robot frame) with ``covariance`` as a bearing-range measurement."""
    distance = math.hypot(position[0], position[1])
    radial = position / distance
    tangential = np.array([-radial[1], radial[0]])
    jacobian = np.vstack([tangential / distance, radial])  # d(bearing, range)/d(position)
    noise = gtsam.noiseModel.Gaussian.Covariance(jacobian @ covariance @ jacobian.T)
    return gtsam.BearingRangeFactor2D(pose_key, point_key, gtsam.Rot2(math.atan2(position[1], position[0])),
                                      distance, noise)
