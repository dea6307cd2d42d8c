"""mapper: labelled landmarks of every ping and the odometry into a map, with SLAM in ``map`` by default.

Subscribes ``landmarks/pairs`` (sonar_ring/LandmarkArray, sensor frame: one
landmark per echo row, independent sightings) and ``odom``
(nav_msgs/Odometry: the robot, ``base_frame``, in ``odom``; the sensor sits at
``sensor_offset`` in the robot frame).  A ping is placed at the robot's pose at
its stamp, interpolated between the odometry messages around it; without
odometry (``use_odometry: false``) the robot stays at ``fixed_pose``.  The
work is the core's :class:`~sonar_ring.map_builder.MapBuilder`:

* ``slam: true`` (default): the robot's pose in ``map_frame`` is estimated from
  the odometry and the landmarks (:mod:`sonar_ring.slam`); the map is in
  ``map_frame``; per ping the pose goes out on ``slam/pose``
  (geometry_msgs/PoseWithCovarianceStamped) and the ``map_frame -> odom_frame``
  transform on ``/tf`` (where tf2_msgs is installed);
* ``slam: false``: the odometry is taken as exact, the map is in ``odom_frame``.

Publishes, reliable and transient local so a late subscriber gets the latest
map, at ``map_rate``: ``map/landmarks`` (sonar_ring/LandmarkArray),
``map/markers`` (MarkerArray with covariance ellipses) and ``map/points``
(sensor_msgs/PointCloud2 of landmark points for costmaps); and ``/diagnostics``.
"""

from __future__ import annotations

import math
import time

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped
from nav_msgs.msg import Odometry
from rclpy.qos import qos_profile_sensor_data
from rclpy.serialization import serialize_message
from rclpy.subscription import MessageInfo
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from sonar_ring.explain import EchoTests
from sonar_ring.geometry import load_layout
from sonar_ring.landmarks import Landmarks
from sonar_ring.map_builder import MapBuilder, MapperSettings, PublishedMap
from sonar_ring.mapping import usable_pose
from sonar_ring.msg import LandmarkArray
from sonar_ring.poses import yaw_of
from sonar_ring.ros.convert import AnyHeader, Cdr, MessageError, landmarks_from_msg, serialize_landmarks
from sonar_ring.ros.diagnostics import NodeHealth
from sonar_ring.ros.inputs import EXPECTED_FRAME, FUTURE_TOLERANCE, TopicCheck, node_clock, stamp_ns
from sonar_ring.ros.markers import covariance_ellipses, explained_markers, landmark_markers, serialize_markers
from sonar_ring.ros.node import LATCHED, SonarNode
from sonar_ring.ros.params import Param, declare
from sonar_ring.ros.run import spin
from sonar_ring.slam import SlamSettings


def _three_numbers(value) -> str | None:
    if len(value) != 3 or not all(np.isfinite(value)):
        return f"must be three finite numbers [x, y, yaw], got {list(value)}"
    return None


SLAM_PREFIX = "slam."
"""The SLAM's parameters: ``slam.<field>`` of :class:`~sonar_ring.slam.SlamSettings` (read-only)."""

SLAM_PARAMS = [
    Param(SLAM_PREFIX + "keyframe_distance", SlamSettings.keyframe_distance, "travel between keyframes, m",
          low=0.01, high=10.0, read_only=True),
    Param(SLAM_PREFIX + "keyframe_turn", SlamSettings.keyframe_turn, "turn between keyframes, rad", low=0.01,
          high=3.0, read_only=True),
    Param(SLAM_PREFIX + "odometry_distance_noise", SlamSettings.odometry_distance_noise,
          "odometry noise along the travel, m per sqrt(m), where the odometry's covariance does not grow", low=1e-4,
          high=1.0, read_only=True),
    Param(SLAM_PREFIX + "odometry_heading_noise", SlamSettings.odometry_heading_noise,
          "odometry heading noise, rad per sqrt(m), where the odometry's covariance does not grow", low=1e-4,
          high=1.0, read_only=True),
    Param(SLAM_PREFIX + "odometry_scale", SlamSettings.odometry_scale, "odometry distance scale error, fraction",
          low=0.0, high=0.5, read_only=True),
    Param(SLAM_PREFIX + "max_speed", SlamSettings.max_speed, "faster odometry is a fault (a jump), m/s", low=0.1,
          high=100.0, read_only=True),
    Param(SLAM_PREFIX + "max_turn_rate", SlamSettings.max_turn_rate, "faster odometry turns are a fault, rad/s",
          low=0.1, high=100.0, read_only=True),
    Param(SLAM_PREFIX + "no_landmarks_after", SlamSettings.no_landmarks_after,
          "seconds without a known landmark before a warning (no_landmarks)", low=0.1, high=3600.0, read_only=True),
    Param(SLAM_PREFIX + "sighting_gate_chi2", SlamSettings.sighting_gate_chi2,
          "a sighting further from the graph's estimate of its landmark than this squared Mahalanobis distance "
          "(its own covariance) is left out of the graph", low=1.0, high=1e6, read_only=True),
    Param(SLAM_PREFIX + "smoother_lag", SlamSettings.smoother_lag,
          "seconds of keyframes the smoother keeps (older ones are marginalised: memory stays flat)", low=1.0,
          high=3600.0, read_only=True),
]

ECHO_TESTS_PREFIX = "echo_tests."
"""The echo tests' parameters: ``echo_tests.<field>`` of :class:`~sonar_ring.explain.EchoTests` (read-only)."""

ECHO_TESTS_PARAMS = [
    Param(ECHO_TESTS_PREFIX + "sigma_map", EchoTests.sigma_map, "position error of a map entry, m", low=0.0,
          high=1.0, read_only=True),
    Param(ECHO_TESTS_PREFIX + "gate_sigmas", EchoTests.gate_sigmas,
          "largest Mahalanobis distance (not squared) of a match to a predicted path", low=0.5, high=20.0,
          read_only=True),
]

PARAMS = [
    Param("layout", "browne_ring", "sensor layout: a name in config/layouts or a YAML path (a ring's echoes tell "
          "edges from corners over motion)", read_only=True),
    Param("slam", True, "estimate the robot's pose from odometry and landmarks and map in map_frame; false: map in "
          "odom_frame at the odometry's pose", read_only=True),
    Param("map_frame", "map", "frame of the map and of slam/pose with SLAM (REP 105)", read_only=True),
    Param("odom_frame", "odom", "the odometry's frame (the map's without SLAM)"),
    Param("base_frame", "base_link", "the robot's frame (the odometry's child frame)", read_only=True),
    Param("use_odometry", True, "place pings with nav_msgs/Odometry on `odom`; false: at fixed_pose", read_only=True),
    Param("use_odometry_covariance", True, "with SLAM, take the odometry's noise from the growth of its pose "
          "covariance where it grows; false: always from the slam.odometry_* parameters (for odometry whose "
          "covariance leaves out its systematic errors)", read_only=True),
    Param("fixed_pose", [0.0, 0.0, 0.0], "robot pose [x, y, yaw] (m, m, rad) when use_odometry is false",
          check=_three_numbers, read_only=True),
    Param("sensor_offset", [0.0, 0.0, 0.0], "sensor pose [x, y, yaw] in the robot frame", check=_three_numbers,
          read_only=True),
    Param("map_rate", 2.0, "map publications per second", low=0.1, high=50.0),
    Param("min_observations", 2, "sightings a landmark needs before it is published", low=1, high=1000,
          read_only=True),
    Param("max_points", 2000, "map capacity for corners, edges and unresolved points", low=1, high=100000,
          read_only=True),
    Param("max_walls", 500, "map capacity for walls", low=1, high=100000, read_only=True),
    Param("gate_chi2", 9.21, "association gate, a squared Mahalanobis distance d^2 (9.21: 99 % for 2 dof)",
          low=0.5, high=100.0, read_only=True),
    Param("echo_tests", True, "explain each ping's landmarks by the map (multipath, impossible) before mapping them "
          "and publish only entries that persist; false: map every echo", read_only=True),
    Param("min_support_pings", MapperSettings.min_support_pings,
          "pings a landmark must be seen in to persist (be published; with SLAM, enter the graph)", low=1,
          high=1000, read_only=True),
    Param("min_support_travel", MapperSettings.min_support_travel,
          "how far the sensor must have moved from where it first saw a landmark for it to persist, m", low=0.0,
          high=10.0, read_only=True),
    Param("sigma_path", EchoTests.sigma_path, "one receiver's path noise c * sigma_tof, m (the echo tests' "
          "tolerance; with SLAM, the weight of a sighting in the air's fit)", low=1e-6, high=0.1, read_only=True),
    Param("relative_sigma_speed", EchoTests.sigma_speed, "relative error of the speed of sound the nodes assume, a "
          "fraction (the localiser's sigma_speed over the speed; the echo tests' tolerance; with SLAM, where the "
          "air's fit starts; 0: the map keeps the assumed speed)", low=0.0, high=0.1, read_only=True),
    EXPECTED_FRAME,
    FUTURE_TOLERANCE,
    *SLAM_PARAMS,
    *ECHO_TESTS_PARAMS,
]


def mapper_settings(values: dict) -> MapperSettings:
    """The core's settings from the mapper's parameter values (:data:`PARAMS`)."""
    noise = {"sigma_path": values["sigma_path"], "sigma_speed": values["relative_sigma_speed"]}
    slam = SlamSettings(**noise, **{p.name.removeprefix(SLAM_PREFIX): values[p.name] for p in SLAM_PARAMS})
    tests = EchoTests(**noise, **{p.name.removeprefix(ECHO_TESTS_PREFIX): values[p.name] for p in ECHO_TESTS_PARAMS})
    return MapperSettings(slam=values["slam"], use_odometry=values["use_odometry"],
                          use_odometry_covariance=values["use_odometry_covariance"],
                          layout=load_layout(values["layout"]),
                          fixed_pose=tuple(values["fixed_pose"]), sensor_offset=tuple(values["sensor_offset"]),
                          map_frame=values["map_frame"], odom_frame=values["odom_frame"],
                          max_points=values["max_points"], max_walls=values["max_walls"],
                          gate_chi2=values["gate_chi2"], min_observations=values["min_observations"],
                          slam_settings=slam,
                          echo_tests=tests if values["echo_tests"] else None,
                          min_support_pings=values["min_support_pings"],
                          min_support_travel=values["min_support_travel"])


def odometry_pose(msg: Odometry) -> tuple[float, float, float]:
    """The robot's ``(x, y, yaw)`` of an Odometry message, m and rad.

    The yaw is NaN when the orientation is not a rotation (:func:`~sonar_ring.poses.yaw_of`).
    """
    pose = msg.pose.pose
    return pose.position.x, pose.position.y, yaw_of(pose.orientation)


_PLANAR_CELLS = [0, 1, 5, 6, 7, 11, 30, 31, 35]
"""The cells of a pose's 6 x 6 covariance (x, y, z, roll, pitch, yaw; row-major) that are ``(x, y, yaw)``'s."""


def odometry_covariance(msg: Odometry) -> np.ndarray:
    """The ``(x, y, yaw)`` block (3, 3) of an Odometry message's pose covariance, m^2, m rad and rad^2."""
    return np.asarray(msg.pose.covariance, dtype=float)[_PLANAR_CELLS].reshape(3, 3)


def usable_odometry(msg: Odometry, health) -> tuple[tuple[float, float, float], np.ndarray] | None:
    """:func:`odometry_pose` and :func:`odometry_covariance`; None for a message whose pose the map does not take.

    The mapper's input gate for odometry (the node's and ``sonar-ring process``'s).  A pose the map does not
    take (:func:`~sonar_ring.mapping.usable_pose`; an orientation that is not a rotation has a NaN yaw) drops
    the message, counted ``bad_odometry_pose`` on ``health``: the odometry on either side of it places the
    pings around it.  The covariance is the core's to judge
    (:meth:`~sonar_ring.map_builder.MapBuilder.add_odometry`).
    """
    pose = odometry_pose(msg)
    if not usable_pose(pose):
        health.problem("bad_odometry_pose", "odometry position not finite or beyond 10^6 m, or orientation not a "
                       "rotation")
        return None
    return pose, odometry_covariance(msg)


def map_messages(published: PublishedMap, header: Header) -> tuple[bytes, bytes, bytes]:
    """The map as published, serialized: ``map/landmarks``, ``map/markers`` and ``map/points``, in that order.

    ``published`` is :meth:`~sonar_ring.map_builder.MapBuilder.published`; ``header`` names its frame and the stamp.
    """
    markers = [*landmark_markers(published.landmarks, "map", lifetime=0.0),
               covariance_ellipses(published.landmarks, "map"), *explained_markers(published.explained, "map")]
    return (serialize_landmarks(published.landmarks, header), serialize_markers(markers, header),
            serialize_message(point_cloud(published.points, header)))


def point_cloud(points: np.ndarray, header: Header) -> PointCloud2:
    """A PointCloud2 of (P, 2) points at z = 0, float32 x, y, z."""
    xyz = np.zeros((points.shape[0], 3), dtype=np.float32)
    xyz[:, :2] = points
    fields = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
              for i, name in enumerate("xyz")]
    return PointCloud2(header=header, height=1, width=points.shape[0], fields=fields, is_bigendian=False,
                       point_step=12, row_step=12 * points.shape[0], data=xyz.tobytes(), is_dense=True)


def serialize_pose(pose: np.ndarray, covariance: np.ndarray, header: AnyHeader) -> bytes:
    """``slam/pose``, serialized: the robot's pose ``(x, y, yaw)`` and its covariance (3, 3) in the 6x6, ``header``.

    A ``geometry_msgs/PoseWithCovarianceStamped`` (:meth:`~sonar_ring.slam.LandmarkSlam.pose`) written straight
    into CDR (:class:`~sonar_ring.ros.convert.Cdr`), as ``rclpy.serialization.serialize_message`` writes it;
    publishers take it as it is.  Building the message object and serializing it took 6 times as long
    (measured), at every ping ``sonar-ring process`` maps.
    """
    full = np.zeros(36)
    full[_POSE_COVARIANCE_CELLS] = np.asarray(covariance, dtype=float).reshape(-1)
    cdr = Cdr()
    cdr.header(header.stamp.sec, header.stamp.nanosec, header.frame_id)
    cdr.pack("7d", pose[0], pose[1], 0.0, 0.0, 0.0, math.sin(pose[2] / 2), math.cos(pose[2] / 2), align=8)
    cdr.pack("36d", *full, align=8)  # a fixed-size array: no length
    return bytes(cdr.buffer)


_POSE_COVARIANCE_CELLS = [6 * row + column for row in (0, 1, 5) for column in (0, 1, 5)]
"""Cells of a pose's 6x6 covariance (x, y, z, roll, pitch, yaw) that hold ``x, y, yaw``'s 3x3, row by row."""


def transform_message(pose, header: Header, child_frame: str) -> TransformStamped:
    """``header.frame_id -> child_frame`` at ``pose`` ``(x, y, yaw)``, stamped ``header``."""
    transform = TransformStamped(header=header, child_frame_id=child_frame)
    transform.transform.translation.x, transform.transform.translation.y = float(pose[0]), float(pose[1])
    transform.transform.rotation.z, transform.transform.rotation.w = math.sin(pose[2] / 2), math.cos(pose[2] / 2)
    return transform


class Mapper(SonarNode):
    """Landmarks and odometry in, the map out at ``map_rate`` (and, with SLAM, the pose per ping)."""

    def __init__(self, **kwargs) -> None:
        super().__init__("mapper", **kwargs)
        self.params = declare(self, PARAMS)
        self.health = NodeHealth(self, hardware_id="map")
        self.builder = MapBuilder(mapper_settings(self.params), self.health)
        self.health.extra_values = self._diagnostic_values
        self.builder.load_kernels()  # now, or the first pings would wait for them
        self._map_landmarks = self.create_publisher(LandmarkArray, "map/landmarks", LATCHED)
        self._map_markers = self.create_publisher(MarkerArray, "map/markers", LATCHED)
        self._map_points = self.create_publisher(PointCloud2, "map/points", LATCHED)
        self._tf = self._tf_message = None
        if self.params["slam"]:
            self._pose_publisher = self.create_publisher(PoseWithCovarianceStamped, "slam/pose", 10)
            self._transform_publisher()
        self._landmarks_check = TopicCheck(node_clock(self), self.health, "landmarks/pairs", self.params)
        self._odometry_check = TopicCheck(node_clock(self), self.health, "odom", self.params, frame_param="odom_frame",
                                        on_clock_jump=self.builder.forget_odometry)
        self.ping_inputs = (self.create_subscription(LandmarkArray, "landmarks/pairs", self._on_landmarks,
                                                     qos_profile_sensor_data),)
        if self.params["use_odometry"]:
            self.create_subscription(Odometry, "odom", self._on_odometry, 50)
        self._timer = self.create_timer(1.0 / self.params["map_rate"], self.publish_map)

    def _transform_publisher(self) -> None:
        """A ``/tf`` publisher, or none (said once) where tf2_msgs is not installed."""
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            self.get_logger().info("tf2_msgs is not installed: map -> odom is not published on /tf; slam/pose has "
                                   "the robot's pose in map")
            return
        self._tf_message = TFMessage
        self._tf = self.create_publisher(TFMessage, "/tf", 100)

    def _diagnostic_values(self) -> dict[str, str]:
        values = {"not persistent (entries held back)": str(self.builder.not_persistent())}
        if self.builder.slam is not None and self.builder.slam.settings.sigma_speed > 0.0:
            error, sigma = self.builder.slam.air_estimate
            values["speed of sound over the assumed (%)"] = f"{100.0 * error:+.3f} +- {100.0 * sigma:.3f}"
        return values

    @property
    def pending_pings(self) -> int:
        """Pings received and waiting for odometry at or after their stamp."""
        return self.builder.pending

    @property
    def map(self):
        """The map of landmarks (SLAM's front end, or the odom-frame map)."""
        return self.builder.landmark_map

    # ------------------------------------------------------------------ input

    def _on_odometry(self, msg: Odometry, info: MessageInfo) -> None:
        if not self._odometry_check.admit(msg.header, info):
            return
        odometry = usable_odometry(msg, self.health)
        if odometry is None:
            return
        started = time.perf_counter()
        placed = self.builder.add_odometry(stamp_ns(msg.header), *odometry)
        if placed:
            self._mapped(started, placed)

    def _on_landmarks(self, msg: LandmarkArray, info: MessageInfo) -> None:
        self.health.received()
        if not self._landmarks_check.admit(msg.header, info):
            return
        try:
            landmarks = landmarks_from_msg(msg)
        except MessageError as error:
            self.health.problem("malformed_message", str(error))
            return
        self._place(stamp_ns(msg.header), landmarks)

    def on_ping(self, header: AnyHeader, landmarks: Landmarks) -> None:
        """A ping's labelled landmarks from the localiser in this process: their header and arrays."""
        self.health.received()
        if self._landmarks_check.admit(header):
            self._place(stamp_ns(header), landmarks)

    def _place(self, stamp: int, landmarks: Landmarks) -> None:
        started = time.perf_counter()
        if self.builder.add_ping(stamp, landmarks):
            self._mapped(started, 1)

    def _mapped(self, started: float, pings: int) -> None:
        """Pings went into the map: the pose (SLAM) at the latest, and their compute time."""
        if self.params["slam"]:
            header = self._header(self.builder.latest_stamp, self.params["map_frame"])
            pose, covariance = self.builder.slam.pose()
            self._pose_publisher.publish(serialize_pose(pose, covariance, header))
            self.health.sent(1)
            if self._tf is not None:
                transform = transform_message(self.builder.slam.map_to_odom(pose), header, self.params["odom_frame"])
                self._tf.publish(self._tf_message(transforms=[transform]))
                self.health.sent(1)
        seconds = (time.perf_counter() - started) / pings
        for _ in range(pings):
            self.health.processed(seconds, published=0)

    @staticmethod
    def _header(stamp: int, frame: str) -> Header:
        header = Header(frame_id=frame)
        header.stamp.sec, header.stamp.nanosec = divmod(stamp, 10**9)
        return header

    # ------------------------------------------------------------------ output

    def publish_map(self) -> None:
        """Publish the map if it changed since the last time."""
        if not self.builder.changed:
            return
        self.builder.changed = False
        published = self.builder.published()
        header = Header(stamp=self.get_clock().now().to_msg(), frame_id=published.frame)
        messages = map_messages(published, header)
        for publisher, message in zip((self._map_landmarks, self._map_markers, self._map_points), messages,
                                      strict=True):
            publisher.publish(message)
        self.health.sent(len(messages))


def main(args=None) -> None:
    """Run the mapper until Ctrl-C or shutdown."""
    spin(Mapper, args=args)


if __name__ == "__main__":
    main()
