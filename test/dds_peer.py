"""A second process for the DDS round-trip test: publishes every sample until killed."""

import sys
import time

import rclpy
from message_samples import SAMPLE_NAMES, sample_message
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sonar_ring.msg import Echoes


def main() -> None:
    topic = sys.argv[1]
    rclpy.init()
    node = rclpy.create_node("dds_peer")
    publisher = node.create_publisher(Echoes, topic, QoSProfile(depth=len(SAMPLE_NAMES),
                                                                reliability=ReliabilityPolicy.RELIABLE))
    messages = [sample_message(name) for name in SAMPLE_NAMES]
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        for message in messages:
            publisher.publish(message)
        time.sleep(0.2)
    rclpy.shutdown()


if __name__ == "__main__":
    main()
