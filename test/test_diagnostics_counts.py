"""Every node's ``inputs`` and ``published`` on /diagnostics are what a listener on its topics received.

The three nodes run as separate nodes in one executor (each takes its pings
from DDS, as separate processes do), the driver reading a UDP device that this
test feeds, one frame in 50 ms; the mapper places pings at ``fixed_pose`` and
publishes its map ten times a second.  One frame is a ping the driver refuses
(three receivers on the two-receiver ring): an input, not a publication.
"""

import os
import socket
import time
from dataclasses import replace

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from ros_harness import spin_until
from sensor_msgs.msg import PointCloud2
from sonar_ring.msg import Echoes, LandmarkArray
from test_frames import ring_ping
from test_transport import frame, free_port
from visualization_msgs.msg import MarkerArray

from sonar_ring.frames import encode_echoes
from sonar_ring.ros.driver import Driver
from sonar_ring.ros.localiser import Localiser
from sonar_ring.ros.mapper import Mapper

pytestmark = pytest.mark.ros

OUTPUTS = {"driver": {"echoes": Echoes},
           "localiser": {"landmarks/raw": LandmarkArray, "landmarks": LandmarkArray,
                         "landmarks/pairs": LandmarkArray, "markers": MarkerArray},
           "mapper": {"map/landmarks": LandmarkArray, "map/markers": MarkerArray, "map/points": PointCloud2,
                      "slam/pose": PoseWithCovarianceStamped}}
"""The topics each node's ``published`` counts."""
INPUTS = {"localiser": "echoes", "mapper": "landmarks/pairs"}
"""The topic whose messages each node downstream of the driver counts as ``inputs``."""
ALL_MESSAGES = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""The map topics' QoS with a queue deep enough to keep every map the mapper publishes."""


def test_every_nodes_counts_on_diagnostics_are_what_was_received(ros):
    namespace = f"/counts_{os.getpid()}"
    port = free_port(socket.SOCK_DGRAM)
    nodes = {
        "driver": Driver(namespace=namespace, parameter_overrides=[
            Parameter("source", value="hardware"), Parameter("device", value=f"udp://127.0.0.1:{port}"),
            Parameter("publish_range", value=False)]),
        "localiser": Localiser(namespace=namespace),
        "mapper": Mapper(namespace=namespace, parameter_overrides=[Parameter("use_odometry", value=False),
                                                                    Parameter("map_rate", value=10.0)]),
    }
    listener = rclpy.create_node("counts_listener", namespace=namespace)
    received = {topic: 0 for topics in OUTPUTS.values() for topic in topics}
    for topics in OUTPUTS.values():
        for topic, kind in topics.items():
            qos = ALL_MESSAGES if topic.startswith("map/") else QoSProfile(
                depth=1000, reliability=ReliabilityPolicy.RELIABLE if topic == "slam/pose"
                else qos_profile_sensor_data.reliability)
            listener.create_subscription(kind, topic, lambda _, topic=topic: received.__setitem__(
                topic, received[topic] + 1), qos)
    reported = {}
    listener.create_subscription(DiagnosticArray, "/diagnostics", lambda message: reported.update(
        {status.name.rsplit("/", 1)[-1]: {value.key: value.value for value in status.values}
         for status in message.status if status.name.startswith(f"sonar_ring: {namespace}/")}), 50)
    executor = SingleThreadedExecutor()
    for node in [*nodes.values(), listener]:
        executor.add_node(node)
    assert spin_until(executor, nodes["driver"].reader.connected.is_set, timeout=5)
    spin_until(executor, lambda: False, timeout=1.0)  # discovery between the nodes and the listener

    refused = encode_echoes(replace(ring_ping(99, n=1, k=3), transmitter=np.zeros(1, np.uint8)), sequence=10,
                            device_time_us=1_000_000 + 10 * 33_333)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        for sequence in range(20):
            udp.sendto(refused if sequence == 10 else frame(sequence), ("127.0.0.1", port))
            spin_until(executor, lambda: False, timeout=0.05)
    assert spin_until(executor, lambda: received["landmarks"] == 19, timeout=20)
    settled = time.monotonic() + 2.5  # the last map, then a report of every node after it
    spin_until(executor, lambda: time.monotonic() > settled, timeout=10)

    assert nodes["driver"].health.problems["wrong_receivers_per_group"] == 1
    assert reported["driver"]["inputs"] == "20"
    for name, topics in OUTPUTS.items():
        assert reported[name]["published"] == str(sum(received[topic] for topic in topics)), name
    for name, topic in INPUTS.items():
        assert reported[name]["inputs"] == str(received[topic]), name
    assert received["echoes"] == 19 and received["map/landmarks"] > 0
    # the air's fit (SLAM): nothing to fit from a robot that stands still, the prior (sigma_speed) as it is
    assert reported["mapper"]["speed of sound over the assumed (%)"] == "+0.000 +- 0.350"
    for node in [*nodes.values(), listener]:
        node.destroy_node()
