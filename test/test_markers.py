"""Messages written straight into CDR (RViz markers, landmark arrays, SLAM's pose, tf): the ones rclpy (or, for tf,
the bag library) serializes from objects.

CDR leaves the padding bytes unspecified (rclpy's are whatever the buffer held), so
the check is: same length, and the same message when either is decoded.
"""

from dataclasses import replace

import numpy as np
import pytest
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point, PoseWithCovarianceStamped
from numpy.testing import assert_allclose
from rclpy.serialization import deserialize_message, serialize_message
from sonar_ring.msg import LandmarkArray
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from sonar_ring.landmarks import CORNER, EDGE, PLANE, UNKNOWN, make_landmarks
from sonar_ring.ros.bag import TF_TYPE, tf_message, typestore
from sonar_ring.ros.convert import landmarks_from_msg, landmarks_to_msg, serialize_landmarks
from sonar_ring.ros.mapper import serialize_pose
from sonar_ring.ros.markers import (
    MIN_ALPHA,
    MarkerParts,
    covariance_ellipses,
    landmark_markers,
    serialize_markers,
)

pytestmark = pytest.mark.ros


def reference_message(parts: list[MarkerParts], header: Header) -> MarkerArray:
    """The same markers built from message objects, as rclpy users do."""
    markers = []
    for part in parts:
        whole = int(part.lifetime)
        marker = Marker(header=header, ns=part.ns, id=0, type=part.type, action=Marker.ADD,
                        lifetime=Duration(sec=whole, nanosec=int(round((part.lifetime - whole) * 1e9))))
        marker.pose.orientation.w = 1.0
        marker.scale.x, marker.scale.y, marker.scale.z = (float(v) for v in part.scale)
        marker.color = ColorRGBA(r=part.color[0], g=part.color[1], b=part.color[2], a=part.color[3])
        marker.points = [Point(x=float(x), y=float(y)) for x, y in part.points]
        marker.colors = [ColorRGBA(r=float(r), g=float(g), b=float(b), a=float(a)) for r, g, b, a in part.colors]
        markers.append(marker)
    return MarkerArray(markers=markers)


def assert_same_as_rclpy(parts, message_header):
    ours = serialize_markers(parts, message_header)
    theirs = serialize_message(reference_message(parts, message_header))
    assert len(ours) == len(theirs)
    assert deserialize_message(ours, MarkerArray) == deserialize_message(theirs, MarkerArray)
    return ours


def header(frame_id="sonar_ring") -> Header:
    message = Header(frame_id=frame_id)
    message.stamp.sec, message.stamp.nanosec = 1_700_000_123, 456_789_012
    return message


def some_landmarks():
    rng = np.random.default_rng(3)
    count = 23
    classes = np.array([UNKNOWN, PLANE, CORNER, EDGE])[rng.integers(0, 4, count)]
    covariance = np.einsum("nij,nkj->nik", *(2 * [rng.normal(0, 0.01, (count, 2, 2))]))
    normal = rng.normal(size=(count, 2))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return make_landmarks(classes, rng.uniform(-3, 3, (count, 2)), normal=normal, covariance=covariance,
                          confidence=np.where(classes == EDGE, rng.uniform(0, 1, count), 0.0),
                          segment=rng.uniform(-3, 3, (count, 2, 2)), valid=rng.random(count) > 0.1)


def test_landmark_arrays_serialize_exactly_as_rclpy_does():
    landmarks = some_landmarks()
    covariance = landmarks.covariance.copy()
    covariance[0] = np.nan  # what a lost covariance looks like: carried, not dropped
    for chosen in (replace(landmarks, covariance=covariance), landmarks.select(np.zeros(len(landmarks), dtype=bool))):
        ours = serialize_landmarks(chosen, header())
        theirs = serialize_message(landmarks_to_msg(chosen, header()))
        if len(chosen):
            assert len(ours) == len(theirs)
        # Empty, rmw's buffer is longer than Fast CDR writes: its size counts the alignment of empty sequences.
        decoded = deserialize_message(ours, LandmarkArray)
        assert decoded.header == header()
        round_trip = landmarks_from_msg(decoded)
        for name in ("landmark_class", "position", "normal", "covariance", "confidence", "segment", "observations",
                     "group", "echo", "valid", "reason"):
            np.testing.assert_array_equal(getattr(round_trip, name), getattr(chosen, name), err_msg=name)


def test_ping_markers_serialize_exactly_as_rclpy_does():
    parts = landmark_markers(some_landmarks(), "landmarks", lifetime=0.5)
    # unknown, plane, corner, edge, corner or edge (the map's class: none in a ping, its namespace kept)
    assert [p.type for p in parts] == [Marker.POINTS, Marker.LINE_LIST, Marker.POINTS, Marker.POINTS, Marker.POINTS]
    assert any(len(p.colors) for p in parts)  # the edges' confidences differ: per-point colours
    data = assert_same_as_rclpy(parts, header())
    decoded = deserialize_message(data, MarkerArray)
    assert [m.ns for m in decoded.markers] == ["landmarks/unknown", "landmarks/plane", "landmarks/corner",
                                               "landmarks/edge", "landmarks/corner_or_edge"]
    assert decoded.markers[0].lifetime.nanosec == 500_000_000
    edge = decoded.markers[3]
    assert len(edge.colors) == len(edge.points) > 0
    assert all(MIN_ALPHA <= c.a <= 1.0 for c in edge.colors)


def test_map_markers_with_ellipses_and_empty_markers_serialize_exactly():
    landmarks = some_landmarks()
    parts = [*landmark_markers(landmarks, "map", lifetime=0.0), covariance_ellipses(landmarks, "map")]
    assert len(parts[-1].points) == 2 * 16 * np.sum(landmarks.valid & (landmarks.landmark_class != PLANE))
    for frame in ("odom", "", "ödom/ünïcode"):
        assert_same_as_rclpy(parts, header(frame))
    nothing = landmark_markers(landmarks.select(np.zeros(len(landmarks), dtype=bool)), "map", lifetime=1.25)
    assert all(len(p.points) == 0 for p in nothing)
    assert_same_as_rclpy(nothing, header())
    assert_same_as_rclpy([], header())


def test_points_keep_their_float64_positions():
    landmarks = some_landmarks()
    parts = landmark_markers(landmarks, "landmarks", lifetime=0.0)
    decoded = deserialize_message(serialize_markers(parts, header()), MarkerArray)
    corners = landmarks.position[landmarks.valid & (landmarks.landmark_class == CORNER)]
    assert_allclose([(p.x, p.y, p.z) for p in decoded.markers[2].points], np.column_stack([corners, 0 * corners[:, 0]]),
                    rtol=0, atol=0)


def test_alpha_is_per_point_only_where_the_alphas_differ():
    """Confidences that differ can round to one float32 alpha: one colour then, as for equal ones."""
    for confidence, per_point in (([0.99999994, 0.9999999], False), ([0.0, 1e-9], False), ([0.2, 0.9], True),
                                  ([0.5, np.nan], True)):
        landmarks = make_landmarks([EDGE, EDGE], [[1.0, 0.0], [2.0, 0.0]], confidence=confidence)
        edges = landmark_markers(landmarks, "landmarks", lifetime=0.0)[EDGE]
        alpha = MIN_ALPHA + (1.0 - MIN_ALPHA) * np.clip(np.float32(confidence), 0.0, 1.0)
        assert len(edges.colors) == (2 if per_point else 0)
        assert edges.color[3] == float(alpha[0])


def test_slam_pose_serializes_exactly_as_rclpy_does():
    rng = np.random.default_rng(5)
    for frame in ("map", "", "mäp/x"):  # frame lengths that leave the pose's doubles 0, 4 and 7 bytes to align
        pose = rng.uniform(-5, 5, 3)
        spread = rng.normal(0, 0.01, (3, 3))
        covariance = spread @ spread.T
        ours = serialize_pose(pose, covariance, header(frame))
        reference = PoseWithCovarianceStamped(header=header(frame))
        reference.pose.pose.position.x, reference.pose.pose.position.y = pose[0], pose[1]
        reference.pose.pose.orientation.z, reference.pose.pose.orientation.w = np.sin(pose[2] / 2), np.cos(pose[2] / 2)
        full = np.zeros((6, 6))
        full[np.ix_([0, 1, 5], [0, 1, 5])] = covariance
        reference.pose.covariance = full.reshape(-1)
        theirs = serialize_message(reference)
        assert len(ours) == len(theirs)
        assert deserialize_message(ours, PoseWithCovarianceStamped) == reference


def test_tf_messages_are_the_bytes_of_the_bag_librarys_types():
    """tf2_msgs need not be installed: the reference is the bag library's own TFMessage, byte for byte."""
    store = typestore()
    types = store.types
    rng = np.random.default_rng(6)
    frames = ["", "a", "odom", "base_link", "sonar_ring/group_07", "ünïcode"]
    time, stamped, vector, quaternion = (types[name] for name in (
        "builtin_interfaces/msg/Time", "std_msgs/msg/Header", "geometry_msgs/msg/Vector3",
        "geometry_msgs/msg/Quaternion"))
    for count in (0, 1, 3, 9):
        transforms = [(int(rng.integers(0, 2**40)), *rng.choice(frames, 2).tolist(), tuple(rng.uniform(-4, 4, 4)))
                      for _ in range(count)]
        items = []
        for stamp, parent, child, (x, y, z, yaw) in transforms:
            sec, nanosec = divmod(stamp, 10**9)
            items.append(types["geometry_msgs/msg/TransformStamped"](
                header=stamped(stamp=time(sec=sec, nanosec=nanosec), frame_id=parent), child_frame_id=child,
                transform=types["geometry_msgs/msg/Transform"](
                    translation=vector(x=x, y=y, z=z),
                    rotation=quaternion(x=0.0, y=0.0, z=np.sin(yaw / 2), w=np.cos(yaw / 2)))))
        assert tf_message(transforms) == bytes(store.serialize_cdr(types[TF_TYPE](transforms=items), TF_TYPE))


def test_error_handling():
    fine = {"ns": "x", "type": Marker.POINTS, "scale": (0.1, 0.1, 0.0), "color": (1.0, 1.0, 1.0, 1.0),
            "points": np.zeros((2, 2)), "colors": np.empty((0, 4))}
    MarkerParts(**fine)
    for change, message in [({"scale": (0.1, 0.1)}, "scale needs 3 values"),
                            ({"color": (1.0, 0.0, 0.0)}, "color 4"),
                            ({"points": np.zeros((2, 3))}, "points must be"),
                            ({"colors": np.zeros((1, 4))}, "colors (P, 4)"),
                            ({"lifetime": -1.0}, "lifetime must be"),
                            ({"lifetime": float("nan")}, "lifetime must be")]:
        with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
            MarkerParts(**{**fine, **change})
