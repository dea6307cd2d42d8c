"""The mapper's core: pings placed at the robot's pose at their stamps, and the map they build.

One object for the ``mapper`` node and ``sonar-ring process`` (which feed it
the same messages in the same order, so they build the same map).  It keeps
the odometry (:class:`~sonar_ring.poses.PoseHistory`), holds a ping back until
the odometry covers its stamp, and maps it:

* ``slam`` on (default): :class:`~sonar_ring.slam.LandmarkSlam` estimates the
  robot's pose in ``map`` from the odometry and the landmarks, the map is in
  ``map``;
* ``slam`` off: the pose is the odometry's, the map a
  :class:`~sonar_ring.mapping.LandmarkMap` in ``odom``.

Before a ping's landmarks reach the map, the map explains what it can
(``echo_tests``, :func:`sonar_ring.explain.explain_landmarks`, at the pose
estimate with its uncertainty, against the published map): a landmark whose
echo is a double bounce of mapped entries (``multipath explained``) or whose
path crosses a mapped wall (``impossible``) is matched to the map but never
mapped, and an entry that such echoes explain away is removed; so is an entry the
map says should have been heard in many pings and that was heard in few of them
(``not heard where expected``: a ghost seen in a burst).  Only
persistent entries are published
(:meth:`~sonar_ring.mapping.LandmarkMap.persistent`; with SLAM only they enter
the graph): an echo that never repeats is never mapped.

What it leaves out is counted on ``health`` (anything with ``problem(reason,
detail, count)`` and ``note(reason, count)``: the node's
:class:`~sonar_ring.ros.diagnostics.NodeHealth`, ``process``'s tally):
``pose_too_old``, ``no_odometry``, ``sightings not_finite`` and
``sightings degenerate`` (problems), ``multipath explained``, ``impossible``,
``explained away``, ``not heard where expected``, ``sightings ambiguous``, ``sightings dropped``,
``sightings evicted`` (notes); with SLAM also ``odometry_jump`` (a new map
session starts) and ``no_landmarks`` (a stretch of travel without a confirmed
landmark) as problems.  :meth:`MapBuilder.not_persistent` says how many
entries are held back.  Nothing raises on bad data.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from sonar_ring.curvature import point_models
from sonar_ring.explain import EchoTests, audible, explain_landmarks, known_map
from sonar_ring.explain import load_kernels as load_explain_kernels
from sonar_ring.geometry import Layout
from sonar_ring.landmarks import Landmarks
from sonar_ring.mapping import LandmarkMap, MapCounts, transform_landmarks, usable_covariance, usable_pose
from sonar_ring.poses import PoseHistory, compose, pose_covariance_at
from sonar_ring.slam import LandmarkSlam, SlamSettings
from sonar_ring.slam import load_kernels as load_slam_kernels

PENDING_LIMIT = 32
"""Pings waiting for a later odometry message; the oldest is dropped (and counted) beyond this."""

SIGHTING_PROBLEMS = ("not_finite", "degenerate")
"""Sightings the map refused as bad data (:class:`~sonar_ring.mapping.MapCounts` fields)."""
SIGHTING_NOTES = ("ambiguous", "dropped", "evicted", "explained_away")
"""Sightings the map left out by design."""


@dataclass(frozen=True)
class MapperSettings:
    """What the mapper does; the mapper node's parameters map onto it.

    Attributes
    ----------
    slam : bool
        Estimate the pose (SLAM, map in ``map_frame``) or take the odometry's (map in ``odom_frame``).
    use_odometry : bool
        Place pings with the odometry; False: at ``fixed_pose``.
    use_odometry_covariance : bool
        With SLAM, take the odometry's noise from its pose covariance where that grows
        (:meth:`MapBuilder.add_odometry`); False: always from ``slam_settings``' odometry noise.
    fixed_pose, sensor_offset : tuple of float
        The robot's pose without odometry, and the sensor's pose in the robot frame, ``(x, y, yaw)``.
    map_frame, odom_frame : str
        Frame names (REP 105).
    max_points, max_walls : int
        Capacities of the map.
    gate_chi2 : float
        The association gate, a squared Mahalanobis distance (:class:`~sonar_ring.mapping.LandmarkMap`).
    min_observations : int
        Sightings an entry needs before it is published.
    slam_settings : SlamSettings
    pose_history : int or None
        Odometry poses kept (None: all, for a whole bag).
    layout : Layout or None
        The sensor: where each receiver group sees its echoes from (its transmitter:
        :meth:`~sonar_ring.geometry.Layout.group_viewpoint`; None: the sensor's origin); on a
        single-emitter ring each point sighting's two models
        (:func:`sonar_ring.curvature.point_models`) tell edges from corners over motion;
        the echo tests need it.
    echo_tests : EchoTests or None
        Explain each ping's landmarks by the map before mapping them, and (without
        SLAM) publish only persistent entries; None: neither (every entry seen
        ``min_observations`` times is published).
    min_support_pings, min_support_travel : int, float
        What makes an entry persistent (:class:`~sonar_ring.mapping.LandmarkMap`).
    """

    slam: bool = True
    use_odometry: bool = True
    use_odometry_covariance: bool = True
    fixed_pose: tuple = (0.0, 0.0, 0.0)
    sensor_offset: tuple = (0.0, 0.0, 0.0)
    map_frame: str = "map"
    odom_frame: str = "odom"
    max_points: int = 2000
    max_walls: int = 500
    gate_chi2: float = 9.21
    min_observations: int = 2
    slam_settings: SlamSettings = field(default_factory=SlamSettings)
    pose_history: int | None = 500
    layout: Layout | None = None
    echo_tests: EchoTests | None = field(default_factory=EchoTests)
    min_support_pings: int = 5
    min_support_travel: float = 0.05


@dataclass(frozen=True)
class PublishedMap:
    """The map as the mapper publishes it (:meth:`MapBuilder.published`).

    Attributes
    ----------
    frame : str
        The map's frame (:attr:`MapBuilder.frame`).
    landmarks : Landmarks
        Its entries (:meth:`MapBuilder.snapshot`), in ``frame``.
    points : ndarray
        (P, 2) costmap points (:meth:`MapBuilder.points`), m, in ``frame``.
    explained : dict of str to ndarray
        The latest ping's landmarks the map explained, by how: positions (P, 2), m, in ``frame``.
    """

    frame: str
    landmarks: Landmarks
    points: np.ndarray
    explained: dict


class MapBuilder:
    """Pings and odometry in, the map (and, with SLAM, the robot's pose in ``map``) out (module docstring).

    Parameters
    ----------
    settings : MapperSettings
    health
        Where refusals are counted (``problem``, ``note``).
    """

    def __init__(self, settings: MapperSettings, health):
        self.settings = settings
        self.health = health
        self.history = PoseHistory(settings.pose_history)
        self._pending: deque = deque()
        front = dict(max_points=settings.max_points, max_walls=settings.max_walls, gate_chi2=settings.gate_chi2,
                     min_support_pings=settings.min_support_pings, min_support_travel=settings.min_support_travel,
                     viewpoints=None if settings.layout is None else settings.layout.group_viewpoint())
        self.slam = LandmarkSlam(settings.slam_settings, front, settings.layout) if settings.slam else None
        self._odom_map = None if settings.slam else LandmarkMap(**front)
        self._counts = MapCounts()
        self._no_landmarks = False
        self.changed = False
        self.robot_pose = None
        """The robot's pose in the map's frame ``(x, y, yaw)`` at the latest ping mapped, None before the first."""
        self.latest_stamp = None
        """Stamp (ns) of the latest ping mapped."""
        self.explained = {"multipath": np.empty((0, 2)), "impossible": np.empty((0, 2))}
        """The latest ping's landmarks the map explained, by how: positions (P, 2) in the map's frame."""
        self._known, self._known_age = None, 0  # the map the echo tests use, and the pings since it was made
        self._known_uids = np.empty(0, np.int64)  # its entries' uids (walls, then points)
        self._expected = np.empty(0, np.int64)  # the entries this ping should hear (audible) ...
        self._heard = np.empty(0, np.int64)  # ... and those whose own echo it heard
        self._hearing: dict[int, list[int]] = {}  # uid -> [pings that should have heard it, pings that did]
        self._pings_explained = 0

    def load_kernels(self) -> None:
        """Load the compiled kernels this mapper runs now, instead of at its first pings.

        The map's and SLAM's (:func:`sonar_ring.slam.load_kernels`) and, where the echo tests are on, theirs
        (:func:`sonar_ring.explain.load_kernels`).
        """
        load_slam_kernels()
        if self.settings.echo_tests is not None and self.settings.layout is not None:
            load_explain_kernels()

    @property
    def frame(self) -> str:
        """The map's frame: ``map_frame`` with SLAM, else ``odom_frame``."""
        return self.settings.map_frame if self.slam else self.settings.odom_frame

    @property
    def pending(self) -> int:
        """Pings waiting for odometry at or after their stamp."""
        return len(self._pending)

    # ------------------------------------------------------------------ input

    def add_odometry(self, stamp: int, pose, covariance=None) -> int:
        """The robot's odometry pose ``(x, y, yaw)`` in ``odom`` at ``stamp`` (ns); returns the pings it placed.

        ``covariance`` (3, 3): the pose's in ``odom``, or None; SLAM takes the odometry's noise from its growth
        (:meth:`~sonar_ring.slam.LandmarkSlam.add_ping`).  All zeros is none (ROS's "unknown"); one that is not
        a covariance the map takes (:func:`~sonar_ring.mapping.usable_covariance`) is none too, counted
        ``bad_odometry_covariance``: the pose is kept.  With ``use_odometry_covariance`` false every
        covariance is none, unread.
        """
        if not self.settings.use_odometry_covariance:
            covariance = None
        elif covariance is not None:
            covariance = np.asarray(covariance, dtype=float)
            if not covariance.any():
                covariance = None
            elif not usable_covariance(covariance):
                self.health.problem("bad_odometry_covariance", "odometry covariance not finite, not symmetric, "
                                    "with a negative variance or beyond (10^6 m)^2: the odometry parameters' noise "
                                    "taken")
                covariance = None
        self.history.add(stamp, pose, covariance)
        placed = 0
        while self._pending and self.history.at(self._pending[0][0]) is not None:
            self._map(*self._pending.popleft())
            placed += 1
        return placed

    def forget_odometry(self) -> None:
        """Time went backwards (a bag replayed again): the odometry history and waiting pings no longer apply."""
        self.history.clear()
        self._pending.clear()

    def give_up_waiting(self) -> None:
        """No more odometry will come (a bag ended): the waiting pings are dropped (``no_odometry``)."""
        self.health.problem("no_odometry", "no odometry at or after the ping's stamp", count=len(self._pending))
        self._pending.clear()

    def add_ping(self, stamp: int, landmarks: Landmarks) -> bool:
        """A ping's labelled landmarks (sensor frame) at ``stamp`` (ns); True when mapped now, False when not (yet).

        A ping older than the odometry history is dropped (``pose_too_old``);
        one after the latest odometry waits for it (``no_odometry`` when more
        than :data:`PENDING_LIMIT` wait).  Landmarks of a group the layout does
        not have are dropped (``unknown_group``; the echo tests and the point
        models look the group up), the rest of the ping mapped.
        """
        layout = self.settings.layout
        if layout is not None and len(landmarks) and landmarks.group.max() >= layout.n_groups:
            known = landmarks.group < layout.n_groups
            self.health.problem("unknown_group", f"landmark of group {landmarks.group[~known][0]}, not of the "
                                f"layout's 0..{layout.n_groups - 1}", int(np.count_nonzero(~known)))
            landmarks = landmarks.select(known)
        if not self.settings.use_odometry:
            self._map(stamp, landmarks)
            return True
        if self.history.too_old(stamp):
            self.health.problem("pose_too_old", "ping older than the odometry history")
            return False
        if self.history.at(stamp) is None:
            self._pending.append((stamp, landmarks))
            if len(self._pending) > PENDING_LIMIT:
                self._pending.popleft()
                self.health.problem("no_odometry", "no odometry at or after the ping's stamp")
            return False
        self._map(stamp, landmarks)
        return True

    def _map(self, stamp: int, landmarks: Landmarks) -> None:
        odometry = self.history.at(stamp) if self.settings.use_odometry else np.asarray(self.settings.fixed_pose,
                                                                                           dtype=float)
        if not usable_pose(odometry):
            self.health.problem("not_finite_pose", "odometry pose not finite or beyond 10^6 m")
            return
        covariance = self.history.covariance_at(stamp) if self.settings.use_odometry else None
        offset = np.asarray(self.settings.sensor_offset, dtype=float)
        layout = self.settings.layout
        explained = self._explain(landmarks, odometry, covariance, offset)
        models = None if layout is None else point_models(layout, landmarks,
                                                           None if explained is None else ~explained)
        if self.slam is None:
            sensor = compose(odometry, offset)
            self.landmark_map.update(transform_landmarks(landmarks, sensor), sensor,
                                     None if models is None else models.transformed(sensor), explained)
            self._hear()
            self.robot_pose = odometry
        else:
            report = self.slam.add_ping(landmarks, odometry, stamp * 1e-9, offset, models, explained, covariance)
            if report.fault:  # a new session: its entries are not the tests' map's
                self._known, self._expected, self._hearing = None, np.empty(0, np.int64), {}
            self._hear()
            self.robot_pose = report.pose
            if report.fault:
                self.health.problem(report.fault.replace(" ", "_"), f"{report.fault}: a new map session starts")
            self.health.note("sightings inconsistent with the map", report.inconsistent)
            self.health.note("odometry covariance not growing", int(report.step_noise_assumed))
            no_landmarks = self.slam.no_landmarks(stamp * 1e-9)
            if no_landmarks and not self._no_landmarks:
                self.health.problem("no_landmarks",
                                    f"no known landmark for {self.slam.settings.no_landmarks_after:g} s")
            self._no_landmarks = no_landmarks
        self._count_sightings()
        self.latest_stamp = stamp
        self.changed = True

    def _explain(self, landmarks: Landmarks, odometry: np.ndarray, covariance, offset: np.ndarray) -> np.ndarray | None:
        """Which landmarks the published map explains (module docstring), counted; None without the tests.

        ``odometry`` and its ``covariance`` (or None) place the robot (SLAM's :meth:`pose_at`).
        """
        tests, layout = self.settings.echo_tests, self.settings.layout
        if tests is None or layout is None or not len(landmarks):
            return None
        if self.slam is None:
            robot, covariance = odometry, np.zeros((3, 3))
        else:
            robot, covariance = self.slam.pose_at(odometry, covariance)
        if self._known is None or self._known_age >= tests.refresh_pings:
            snapshot, self._known_uids = self.snapshot_and_uids()
            self._known, self._known_age = known_map(snapshot, tests), 0
            # Counters of entries the map no longer holds (merged, removed) go with them.
            held = set(self._known_uids.tolist())
            self._hearing = {uid: counts for uid, counts in self._hearing.items() if uid in held}
        self._known_age += 1
        sensor = compose(robot, offset)
        sensor_covariance = pose_covariance_at(robot, covariance, offset)
        explained = explain_landmarks(landmarks, layout, sensor, sensor_covariance, self._known, tests)
        self._pings_explained += 1
        if tests.unheard_after > 0 and self._pings_explained % tests.hearing_every == 0:
            self._expected = self._known_uids[audible(self._known, layout, sensor, sensor_covariance, tests)]
            self._heard = self._known_uids[explained.heard]
        self.explained = {"multipath": explained.position[explained.multipath],
                          "impossible": explained.position[explained.impossible]}
        self.health.note("multipath explained", int(np.count_nonzero(explained.multipath)))
        self.health.note("impossible", int(np.count_nonzero(explained.impossible)))
        return explained.any

    def _hear(self) -> None:
        """Count, for each entry this ping should have heard, whether a landmark matched its own echo.

        An entry heard in fewer than ``unheard_fraction`` of ``unheard_after`` or more such pings leaves the
        map (:class:`~sonar_ring.explain.EchoTests`).
        """
        tests = self.settings.echo_tests
        expected, self._expected = self._expected, np.empty(0, np.int64)
        if not expected.size:
            return
        heard = set(self._heard.tolist())
        gone = []
        for uid in expected.tolist():
            counts = self._hearing.setdefault(uid, [0, 0])
            counts[0] += 1
            counts[1] += uid in heard
            if counts[0] >= tests.unheard_after and counts[1] < tests.unheard_fraction * counts[0]:
                gone.append(uid)
        if gone:
            if self.slam is not None:
                self.slam.forget(gone)
            else:
                self.landmark_map.remove(gone)
            for uid in gone:
                del self._hearing[uid]
            self._known = None  # the tests' map loses them at the next ping
            self.health.note("not heard where expected", len(gone))

    def _count_sightings(self) -> None:
        """What the map refused or left out since the last ping, on ``health``."""
        counts = self.landmark_map.counts
        if self.slam is not None and counts.pings < self._counts.pings:  # a new session's map starts at zero
            self._counts = MapCounts()
        for reason in SIGHTING_PROBLEMS:
            self.health.problem(f"sightings {reason}", count=getattr(counts, reason) - getattr(self._counts, reason))
        for reason in SIGHTING_NOTES:
            self.health.note(f"sightings {reason}", getattr(counts, reason) - getattr(self._counts, reason))
        self._counts = counts

    # ------------------------------------------------------------------ output

    @property
    def landmark_map(self) -> LandmarkMap:
        """The map of landmarks: SLAM's front end (its current session's), or the odom-frame map."""
        return self.slam.front if self.slam is not None else self._odom_map

    def snapshot(self) -> Landmarks:
        """The map in :attr:`frame`, entries seen ``min_observations`` times.

        With SLAM: those in its graph; with the echo tests: the persistent ones.
        """
        if self.slam is not None:
            return self.slam.snapshot(self.settings.min_observations)
        return self.landmark_map.snapshot(self.settings.min_observations, persistent=self._tested,
                                          decided=self._tested)

    def published(self) -> PublishedMap:
        """The map as published: its frame, :meth:`snapshot`, :meth:`points` and the latest ping's explained landmarks.

        One value that leaves the mapper's process whole (``sonar-ring process`` maps in a process of its own).
        """
        return PublishedMap(self.frame, self.snapshot(), self.points(), self.explained)

    def snapshot_and_uids(self) -> tuple[Landmarks, np.ndarray]:
        """The map the echo tests compare a ping's sightings with, and the uids of its entries, in its order.

        :meth:`snapshot`, but with SLAM as the graph holds it, not scaled by the air's fit
        (:meth:`~sonar_ring.slam.LandmarkSlam.snapshot_and_uids`): the sightings were made with the assumed air.
        """
        if self.slam is not None:
            return self.slam.snapshot_and_uids(self.settings.min_observations)
        return self.snapshot(), self.landmark_map.snapshot_uids(self.settings.min_observations,
                                                                persistent=self._tested, decided=self._tested)

    def points(self) -> np.ndarray:
        """Costmap points of :meth:`snapshot`, (P, 2), in :attr:`frame`."""
        if self.slam is not None:
            return self.slam.points(self.settings.min_observations)
        return self.landmark_map.points(self.settings.min_observations, persistent=self._tested, decided=self._tested)

    @property
    def _tested(self) -> bool:
        return self.settings.echo_tests is not None

    def not_persistent(self) -> int:
        """Entries of the map held back from :meth:`snapshot` because they do not (yet) persist."""
        entries = self.landmark_map.entries()
        return int(np.count_nonzero(~self.landmark_map.persistent(entries.uid)))
