"""mapper: labelled landmarks of every ping accumulated into a map in ``odom``.

Subscribes ``landmarks`` (sonar_ring/LandmarkArray, sensor frame) and ``odom``
(nav_msgs/Odometry: pose of the robot in ``odom``; the sensor sits at
``sensor_offset`` in the robot frame).  A ping is placed with the robot pose at
its stamp, interpolated between the odometry messages around it; without
odometry (``use_odometry: false``) the robot stays at ``fixed_pose``.

Publishes, reliable and transient local so a late subscriber gets the latest
map, at ``map_rate``: ``map/landmarks`` (sonar_ring/LandmarkArray in
``odom_frame``), ``map/markers`` (MarkerArray with covariance ellipses) and
``map/points`` (sensor_msgs/PointCloud2 of landmark points for costmaps); and
``/diagnostics``.
"""

from __future__ import annotations

import bisect
import time
from collections import deque

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.qos import qos_profile_sensor_data
from rclpy.serialization import serialize_message
from rclpy.subscription import MessageInfo
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from sonar_ring.landmarks import Landmarks
from sonar_ring.mapping import LandmarkMap, Sightings, load_kernels, transform_landmarks
from sonar_ring.msg import LandmarkArray
from sonar_ring.ros.convert import AnyHeader, MessageError, landmarks_from_msg, serialize_landmarks
from sonar_ring.ros.diagnostics import NodeHealth
from sonar_ring.ros.inputs import EXPECTED_FRAME, FUTURE_TOLERANCE, InputGate, stamp_ns
from sonar_ring.ros.markers import covariance_ellipses, landmark_markers, serialize_markers
from sonar_ring.ros.node import LATCHED, SonarNode
from sonar_ring.ros.params import Param, declare
from sonar_ring.ros.run import spin

POSE_HISTORY = 500
"""Odometry messages kept for interpolation (10 s at 50 Hz)."""
PENDING_LIMIT = 32
"""Pings waiting for a later odometry message; the oldest is dropped (and counted) beyond this."""


def _three_numbers(value) -> str | None:
    if len(value) != 3 or not all(np.isfinite(value)):
        return f"must be three finite numbers [x, y, yaw], got {list(value)}"
    return None


PARAMS = [
    Param("odom_frame", "odom", "frame of the map (the odometry's frame)"),
    Param("use_odometry", True, "place pings with nav_msgs/Odometry on `odom`; false: at fixed_pose", read_only=True),
    Param("fixed_pose", [0.0, 0.0, 0.0], "robot pose [x, y, yaw] (m, m, rad) when use_odometry is false",
          check=_three_numbers),
    Param("sensor_offset", [0.0, 0.0, 0.0], "sensor pose [x, y, yaw] in the odometry's child frame",
          check=_three_numbers),
    Param("map_rate", 2.0, "map publications per second", low=0.1, high=50.0),
    Param("min_observations", 2, "sightings a landmark needs before it is published", low=1, high=1000),
    Param("max_points", 2000, "map capacity for corners, edges and unresolved points", low=1, high=100000,
          read_only=True),
    Param("max_walls", 500, "map capacity for walls", low=1, high=100000, read_only=True),
    Param("gate", 9.21, "Mahalanobis gate d^2 for association (9.21: 99 % for 2 dof)", low=0.5, high=100.0,
          read_only=True),
    EXPECTED_FRAME,
    FUTURE_TOLERANCE,
]


def yaw_of(orientation) -> float:
    """Yaw of a quaternion (rotation about z), rad."""
    return float(np.arctan2(2.0 * (orientation.w * orientation.z + orientation.x * orientation.y),
                            1.0 - 2.0 * (orientation.y ** 2 + orientation.z ** 2)))


def compose(pose: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Pose ``offset`` given in the frame of ``pose``, expressed in pose's parent frame."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.array([pose[0] + c * offset[0] - s * offset[1], pose[1] + s * offset[0] + c * offset[1],
                     pose[2] + offset[2]])


def pose_at(stamps, poses, stamp: int) -> np.ndarray | None:
    """Robot pose at ``stamp`` (ns), interpolated in an odometry history; None while no later odometry exists.

    ``stamps`` are the odometry stamps (ns, increasing, indexable), ``poses``
    the matching ``(x, y, yaw)`` arrays (m, m, rad).  A stamp before the first
    odometry gets the first pose.
    """
    index = bisect.bisect_left(stamps, stamp)
    if index == len(stamps):
        return None
    if stamps[index] == stamp or index == 0:
        return poses[index]
    before, after = poses[index - 1], poses[index]
    weight = (stamp - stamps[index - 1]) / (stamps[index] - stamps[index - 1])
    turn = np.arctan2(np.sin(after[2] - before[2]), np.cos(after[2] - before[2]))
    return np.array([*(before[:2] + weight * (after[:2] - before[:2])), before[2] + weight * turn])


def new_map(params: dict) -> LandmarkMap:
    """An empty map with the capacities and gate of the mapper parameters ``params``."""
    return LandmarkMap(max_points=params["max_points"], max_walls=params["max_walls"], gate=params["gate"])


SIGHTING_PROBLEMS = ("not_finite", "degenerate")
"""Sightings the map refused as bad data (:class:`~sonar_ring.mapping.MapCounts` fields)."""
SIGHTING_NOTES = ("ambiguous", "dropped", "evicted")
"""Sightings the map left out by design."""


def integrate(landmark_map: LandmarkMap, landmarks, robot_pose: np.ndarray, sensor_offset) -> dict:
    """Add one ping's landmarks (sensor frame) to the map, the robot at ``robot_pose`` (x, y, yaw in ``odom``).

    ``sensor_offset`` is the sensor pose ``(x, y, yaw)`` in the robot frame.
    Returns the sightings refused or left out in this update, by
    :data:`SIGHTING_PROBLEMS` and :data:`SIGHTING_NOTES` reason.
    """
    return add_sightings(landmark_map, sightings_at(landmark_map, landmarks, robot_pose, sensor_offset))


def sightings_at(landmark_map: LandmarkMap, landmarks, robot_pose: np.ndarray, sensor_offset) -> Sightings | None:
    """The first half of :func:`integrate`: the ping's landmarks in ``odom``, screened with the map's settings.

    Needs nothing of the map's entries, so ``sonar-ring process`` runs it in its workers.
    """
    sensor_pose = compose(robot_pose, np.asarray(sensor_offset, dtype=float))
    return landmark_map.screen(transform_landmarks(landmarks, sensor_pose), sensor_pose)


def add_sightings(landmark_map: LandmarkMap, sightings: Sightings | None) -> dict:
    """The second half of :func:`integrate`, in ping order; what was left out, by reason."""
    before = landmark_map.counts
    landmark_map.add(sightings)
    after = landmark_map.counts
    return {reason: getattr(after, reason) - getattr(before, reason) for reason in SIGHTING_PROBLEMS + SIGHTING_NOTES}


def count_sightings(health, lost: dict) -> None:
    """Count what :func:`integrate` left out: refused sightings as problems, those left out by design as notes.

    ``health`` is a :class:`~sonar_ring.ros.diagnostics.NodeHealth` or anything with its
    ``problem`` and ``note`` methods (``sonar-ring process`` counts the same way).
    """
    for reason in SIGHTING_PROBLEMS:
        health.problem(f"sightings {reason}", count=lost[reason])
    for reason in SIGHTING_NOTES:
        health.note(f"sightings {reason}", lost[reason])


def map_messages(landmark_map: LandmarkMap, header: Header, min_observations: int) -> tuple[bytes, bytes, bytes]:
    """The map as published, serialized: ``map/landmarks``, ``map/markers`` and ``map/points``, in that order.

    Landmarks seen at least ``min_observations`` times; ``header`` names the
    map frame and the stamp.
    """
    snapshot = landmark_map.snapshot(min_observations=min_observations)
    markers = [*landmark_markers(snapshot, "map", lifetime=0.0), covariance_ellipses(snapshot, "map")]
    return (serialize_landmarks(snapshot, header), serialize_markers(markers, header),
            serialize_message(point_cloud(landmark_map.points(min_observations=min_observations), header)))


def point_cloud(points: np.ndarray, header: Header) -> PointCloud2:
    """A PointCloud2 of (P, 2) points at z = 0, float32 x, y, z."""
    xyz = np.zeros((points.shape[0], 3), dtype=np.float32)
    xyz[:, :2] = points
    fields = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
              for i, name in enumerate("xyz")]
    return PointCloud2(header=header, height=1, width=points.shape[0], fields=fields, is_bigendian=False,
                       point_step=12, row_step=12 * points.shape[0], data=xyz.tobytes(), is_dense=True)


class Mapper(SonarNode):
    """Landmarks and odometry in, the map out at ``map_rate``."""

    def __init__(self, **kwargs) -> None:
        super().__init__("mapper", **kwargs)
        self.params = declare(self, PARAMS)
        self.map = new_map(self.params)
        load_kernels()  # now, or the first ping would wait ~0.5 s for them
        self.health = NodeHealth(self, hardware_id="map")
        self._stamps: list[int] = []
        self._poses: deque = deque(maxlen=POSE_HISTORY)
        self._pending: deque = deque()
        self._changed = False
        self._map_landmarks = self.create_publisher(LandmarkArray, "map/landmarks", LATCHED)
        self._map_markers = self.create_publisher(MarkerArray, "map/markers", LATCHED)
        self._map_points = self.create_publisher(PointCloud2, "map/points", LATCHED)
        self._landmarks_gate = InputGate(self, self.health, "landmarks", self.params)
        self._odometry_gate = InputGate(self, self.health, "odom", self.params, frame_param="odom_frame",
                                        on_clock_jump=self._forget_poses)
        self.ping_inputs = (self.create_subscription(LandmarkArray, "landmarks", self._on_landmarks,
                                                     qos_profile_sensor_data),)
        if self.params["use_odometry"]:
            self.create_subscription(Odometry, "odom", self._on_odometry, 50)
        self._timer = self.create_timer(1.0 / self.params["map_rate"], self.publish_map)

    @property
    def pending_pings(self) -> int:
        """Pings received and waiting for odometry at or after their stamp."""
        return len(self._pending)

    # ------------------------------------------------------------------ poses

    def _forget_poses(self) -> None:
        """Time went backwards (bag replayed again): the odometry history no longer applies."""
        self._stamps.clear()
        self._poses.clear()
        self._pending.clear()

    def _on_odometry(self, msg: Odometry, info: MessageInfo) -> None:
        if not self._odometry_gate.admit(msg.header, info):
            return
        stamp = stamp_ns(msg.header)
        pose = msg.pose.pose
        if len(self._stamps) == POSE_HISTORY:
            self._stamps.pop(0)
        self._stamps.append(stamp)
        self._poses.append(np.array([pose.position.x, pose.position.y, yaw_of(pose.orientation)]))
        while self._pending and self._pose_at(self._pending[0][0]) is not None:
            stamp, landmarks = self._pending.popleft()
            self._integrate(landmarks, self._pose_at(stamp))

    def _pose_at(self, stamp: int) -> np.ndarray | None:
        """Robot pose at ``stamp`` (ns), interpolated; None while no later odometry exists."""
        if not self.params["use_odometry"]:
            return np.asarray(self.params["fixed_pose"], dtype=float)
        return pose_at(self._stamps, self._poses, stamp)

    # ------------------------------------------------------------------ landmarks

    def _on_landmarks(self, msg: LandmarkArray, info: MessageInfo) -> None:
        self.health.received()
        if not self._landmarks_gate.admit(msg.header, info):
            return
        try:
            landmarks = landmarks_from_msg(msg)
        except MessageError as error:
            self.health.problem("malformed_message", str(error))
            return
        self._place(stamp_ns(msg.header), landmarks)

    def on_ping(self, header: AnyHeader, landmarks: Landmarks) -> None:
        """A ping's labelled landmarks from the classifier in this process: their header and arrays."""
        self.health.received()
        if self._landmarks_gate.admit(header):
            self._place(stamp_ns(header), landmarks)

    def _place(self, stamp: int, landmarks: Landmarks) -> None:
        """Integrate a ping's landmarks at the robot pose of ``stamp`` (ns), or keep them until odometry comes."""
        if self.params["use_odometry"] and self._stamps and stamp < self._stamps[0]:
            self.health.problem("pose_too_old", "ping older than the odometry history")
            return
        pose = self._pose_at(stamp)
        if pose is None:
            self._pending.append((stamp, landmarks))
            if len(self._pending) > PENDING_LIMIT:
                self._pending.popleft()
                self.health.problem("no_odometry", "no odometry at or after the ping's stamp")
            return
        self._integrate(landmarks, pose)

    def _integrate(self, landmarks: Landmarks, robot_pose: np.ndarray) -> None:
        started = time.perf_counter()
        count_sightings(self.health, integrate(self.map, landmarks, robot_pose, self.params["sensor_offset"]))
        self._changed = True
        self.health.processed(time.perf_counter() - started, published=0)

    def publish_map(self) -> None:
        """Publish the map if it changed since the last time."""
        if not self._changed:
            return
        self._changed = False
        header = Header(stamp=self.get_clock().now().to_msg(), frame_id=self.params["odom_frame"])
        messages = map_messages(self.map, header, self.params["min_observations"])
        for publisher, message in zip((self._map_landmarks, self._map_markers, self._map_points), messages,
                                      strict=True):
            publisher.publish(message)
        self.health.sent(len(messages))


def main(args=None) -> None:
    """Run the mapper until Ctrl-C or shutdown."""
    spin(Mapper, args=args)


if __name__ == "__main__":
    main()
