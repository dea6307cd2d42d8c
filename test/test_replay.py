"""Replay: a live run recorded to rosbag2 (MCAP, via rosbags) and played back on sim time gives the same landmarks.

``ros2 bag play`` is not installable here, so the test plays the bag itself:
``/clock`` first, then each echo message at its recorded time, into a fresh
localiser running with ``use_sim_time``.
"""

import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from numpy.testing import assert_array_equal
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosgraph_msgs.msg import Clock
from sonar_ring.msg import Echoes, LandmarkArray

from sonar_ring.ros.bag import typestore
from sonar_ring.ros.convert import landmarks_from_msg
from sonar_ring.ros.driver import Driver
from sonar_ring.ros.localiser import Localiser

pytestmark = pytest.mark.ros

PINGS = 40


def stamp_ns(msg):
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def record_live_run(bag: Path):
    """The simulator-driven graph for PINGS pings; echoes and landmarks written to an MCAP bag."""
    rclpy.init()
    try:
        overrides = [Parameter("scene", value="room"), Parameter("ping_rate", value=60.0)]
        nodes = [Driver(parameter_overrides=overrides), Localiser()]
        recorder = rclpy.create_node("recorder")
        recorded = {"echoes": [], "landmarks": []}
        for topic, kind in (("echoes", Echoes), ("landmarks", LandmarkArray)):
            recorder.create_subscription(kind, topic, lambda raw, t=topic: recorded[t].append(raw),
                                         qos_profile_sensor_data, raw=True)
        executor = SingleThreadedExecutor()
        for node in [*nodes, recorder]:
            executor.add_node(node)
        deadline = time.monotonic() + 30
        while len(recorded["landmarks"]) < PINGS and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
    finally:
        rclpy.shutdown()
    store = typestore()
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for topic, kind in (("echoes", "sonar_ring/msg/Echoes"), ("landmarks", "sonar_ring/msg/LandmarkArray")):
            connection = writer.add_connection(f"/{topic}", kind, typestore=store)
            for raw in recorded[topic]:
                message = store.deserialize_cdr(raw, kind)
                writer.write(connection, message.header.stamp.sec * 10**9 + message.header.stamp.nanosec, raw)
    return len(recorded["echoes"])


def replay(bag: Path):
    """Play the bag's echoes with /clock into a sim-time localiser; return landmarks by stamp."""
    with Reader(bag) as reader:
        echoes = [(t, bytes(raw)) for connection, t, raw in reader.messages()
                  if connection.topic == "/echoes"]
    rclpy.init()
    try:
        sim_time = [Parameter("use_sim_time", value=True)]
        nodes = [Localiser(parameter_overrides=sim_time)]
        player = rclpy.create_node("player")
        clock = player.create_publisher(Clock, "/clock", QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        publisher = player.create_publisher(Echoes, "echoes", qos_profile_sensor_data)
        found = {}
        player.create_subscription(LandmarkArray, "landmarks", lambda m: found.__setitem__(stamp_ns(m), m),
                                   qos_profile_sensor_data)
        executor = SingleThreadedExecutor()
        for node in [*nodes, player]:
            executor.add_node(node)
        deadline = time.monotonic() + 10
        while not (publisher.get_subscription_count() >= 2 and clock.get_subscription_count() >= 2) \
                and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        for stamp, raw in echoes:
            message = Clock()
            message.clock.sec, message.clock.nanosec = divmod(stamp, 10**9)
            clock.publish(message)
            publisher.publish(raw)
            # Paced like a player: the next ping goes out once this one came through (or after 2 s).
            deadline = time.monotonic() + 2
            while stamp not in found and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.01)
        assert nodes[0].get_clock().now().nanoseconds == echoes[-1][0], "the localiser must follow /clock"
    finally:
        rclpy.shutdown()
    return found


def test_replayed_bag_gives_the_landmarks_of_the_live_run(tmp_path):
    bag = tmp_path / "live"
    assert record_live_run(bag) >= PINGS
    store = typestore()
    with Reader(bag) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {
            "/echoes": "sonar_ring/msg/Echoes", "/landmarks": "sonar_ring/msg/LandmarkArray"}
        live = {t: bytes(raw) for c, t, raw in reader.messages() if c.topic == "/landmarks"}
    replayed = replay(bag)
    common = sorted(set(live) & set(replayed))
    assert len(common) >= PINGS - 2  # best-effort delivery may drop the odd ping
    compared = 0
    for stamp in common:
        expected = store.deserialize_cdr(live[stamp], "sonar_ring/msg/LandmarkArray")
        got = landmarks_from_msg(replayed[stamp])
        assert_array_equal(got.landmark_class, expected.landmark_class)
        assert_array_equal(got.position, np.asarray(expected.position).reshape(-1, 2))
        assert_array_equal(got.covariance, np.asarray(expected.covariance).reshape(-1, 2, 2))
        assert_array_equal(got.confidence, expected.confidence)
        compared += len(got)
    assert compared > 100
