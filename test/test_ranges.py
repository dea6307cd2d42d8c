"""The driver's Range output for Nav2 (REP 117) and the static frames RViz needs to draw its cones."""

import importlib.util
import math
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
import yaml
from numpy.testing import assert_allclose
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Range
from std_msgs.msg import Header

from sonar_ring.echoes import EchoArrays
from sonar_ring.geometry import load_layout
from sonar_ring.ros import ranges
from sonar_ring.ros.driver import Driver
from sonar_ring.ros.node import LATCHED
from sonar_ring.ros.ranges import MIN_RANGE, group_frame, group_transforms, range_messages, range_topic

pytestmark = pytest.mark.ros

RING = load_layout("browne_ring")
C = 343.0


def test_group_frames_sit_at_each_pair_facing_its_axis():
    transforms = group_transforms(RING, "sonar_ring", Header().stamp)
    assert [t.child_frame_id for t in transforms] == [f"sonar_ring/group_{g:02d}" for g in range(RING.n_groups)]
    for transform, centre, yaw in zip(transforms, RING.group_centre(), RING.group_yaw(), strict=True):
        assert transform.header.frame_id == "sonar_ring"
        q = transform.transform.rotation
        assert_allclose([q.x, q.y, q.z**2 + q.w**2], [0.0, 0.0, 1.0], atol=1e-15)
        # x of the group frame, rotated into the sensor frame, is the pair's facing
        assert_allclose([q.w**2 - q.z**2, 2 * q.w * q.z], [math.cos(yaw), math.sin(yaw)], atol=1e-12)
        t = transform.transform.translation
        assert_allclose([t.x, t.y, t.z], centre, atol=1e-15)


def test_ranges_follow_rep_117():
    tof = np.array([[2.0, 2.1], [1.0, np.nan], [3.0, 3.0], [1e-5, 1e-5]]) / C
    echoes = EchoArrays(RING.name, C, np.array([3, 3, 7, 9]), np.zeros(4, int), tof, np.empty((4, 0)),
                        np.empty((4, 0)))
    header = Header(frame_id="base_sonar")
    header.stamp.sec = 12
    messages = range_messages(RING, echoes, header)
    assert len(messages) == RING.n_groups
    ranges = np.array([m.range for m in messages])
    assert ranges[3] == pytest.approx(0.5)  # the nearest echo of the group, half its path
    assert ranges[7] == pytest.approx(1.5)
    assert ranges[9] == -math.inf  # nearer than MIN_RANGE: too close
    assert 0.5 * 1e-5 < MIN_RANGE
    assert np.all(ranges[np.setdiff1d(np.arange(RING.n_groups), [3, 7, 9])] == math.inf)  # heard nothing
    for group, message in enumerate(messages):
        assert message.header.frame_id == group_frame("base_sonar", group) == f"base_sonar/group_{group:02d}"
        assert message.header.stamp.sec == 12
        assert message.radiation_type == Range.ULTRASOUND
        assert message.field_of_view == pytest.approx(2 * RING.beam_half_angle)
        assert message.min_range == MIN_RANGE and message.max_range == RING.max_range
    empty = EchoArrays(RING.name, C, np.zeros(0, int), np.zeros(0, int), np.empty((0, 2)), np.empty((0, 0)),
                       np.empty((0, 0)))
    assert all(m.range == math.inf for m in range_messages(RING, empty, header))


@pytest.fixture
def ros():
    rclpy.init()
    yield
    rclpy.try_shutdown()


def spin_until(executor, done, seconds=10.0):
    deadline = time.monotonic() + seconds
    while not done() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)


def test_driver_publishes_one_range_per_group_and_ping(ros):
    driver = Driver(parameter_overrides=[Parameter("scene", value="single_wall"), Parameter("ping_rate", value=50.0),
                                         Parameter("sigma_tof", value=0.0)])
    listener = rclpy.create_node("range_listener")
    received = []
    for group in range(RING.n_groups):
        listener.create_subscription(Range, range_topic(group), received.append, qos_profile_sensor_data)
    executor = SingleThreadedExecutor()
    executor.add_node(driver)
    executor.add_node(listener)
    spin_until(executor, lambda: len(received) >= 4 * RING.n_groups)
    by_stamp = {}
    for message in received:
        by_stamp.setdefault((message.header.stamp.sec, message.header.stamp.nanosec), []).append(message)
    complete = [ping for ping in by_stamp.values() if len(ping) == RING.n_groups]
    assert complete, "no complete ping of Range messages"
    ping = complete[0]
    assert sorted(m.header.frame_id for m in ping) == [group_frame("sonar_ring", g) for g in range(RING.n_groups)]
    finite = [m.range for m in ping if math.isfinite(m.range)]
    assert finite and all(MIN_RANGE <= r <= RING.max_range for r in finite)  # the wall, in front of some pairs
    assert any(m.range == math.inf for m in ping)  # pairs facing away heard nothing


def test_range_topics_without_subscribers_get_nothing_and_one_gets_its_own(ros, monkeypatch):
    built = []

    def counting(layout, echoes, header, groups=None):
        built.append(list(groups))
        return range_messages(layout, echoes, header, groups)

    monkeypatch.setattr(ranges, "range_messages", counting)
    monkeypatch.setattr(ranges, "LISTENERS_PERIOD", 0.05)
    namespace = "/lazy_ranges"  # apart from the subscribers earlier tests may leave until garbage collection
    driver = Driver(namespace=namespace, parameter_overrides=[Parameter("scene", value="single_wall"),
                                                              Parameter("ping_rate", value=50.0)])
    executor = SingleThreadedExecutor()
    executor.add_node(driver)
    spin_until(executor, lambda: driver.pings_published >= 5)
    assert built == [], "no subscriber: no Range built"
    listener = rclpy.create_node("one_range_listener")
    received = []
    listener.create_subscription(Range, f"{namespace}/{range_topic(7)}", received.append, qos_profile_sensor_data)
    executor.add_node(listener)
    spin_until(executor, lambda: len(received) >= 3)
    assert len(received) >= 3 and {m.header.frame_id for m in received} == {group_frame("sonar_ring", 7)}
    assert built and all(groups == [7] for groups in built)


@pytest.mark.skipif(importlib.util.find_spec("tf2_msgs") is None,
                    reason="tf2_msgs ships with ROS 2, not with PyPI: the /tf_static output needs a ROS 2 install")
def test_driver_publishes_the_group_frames_on_tf_static(ros):
    from tf2_msgs.msg import TFMessage

    driver = Driver(parameter_overrides=[Parameter("scene", value="single_wall")])
    listener = rclpy.create_node("tf_listener")
    received = []
    listener.create_subscription(TFMessage, "/tf_static", received.append, LATCHED)  # late: transient local
    executor = SingleThreadedExecutor()
    executor.add_node(driver)
    executor.add_node(listener)
    spin_until(executor, lambda: received)
    children = {t.child_frame_id for message in received for t in message.transforms}
    assert children == {group_frame("sonar_ring", g) for g in range(RING.n_groups)}


def test_the_rviz_config_draws_every_pair_of_the_ring():
    config = yaml.safe_load((Path(__file__).resolve().parents[1] / "config" / "sonar_ring.rviz").read_text())
    displays = config["Visualization Manager"]["Displays"]
    cones = next(d for d in displays if d["Class"] == "rviz_common/Group" and d["Name"].startswith("Range cones"))
    assert [d["Topic"]["Value"] for d in cones["Displays"]] == [range_topic(g) for g in range(RING.n_groups)]
    assert all(d["Topic"]["Reliability Policy"] == "Best Effort" for d in cones["Displays"])  # sensor-data QoS
