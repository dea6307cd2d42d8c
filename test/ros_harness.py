"""Helpers of the tests that run nodes: spinning until a condition, the map's QoS, the executables."""

import os
import time
from pathlib import Path

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

MAP_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""What a map subscriber asks for: reliable and transient local, so a late subscriber gets the latest map."""


def spin_until(executor, done, timeout):
    """Spin ``executor`` until ``done()`` is true or ``timeout`` seconds pass; return ``done()``."""
    deadline = time.monotonic() + timeout
    while not done() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return done()


def executable(name):
    """Path of a node executable of the colcon-built package (``ros2 run sonar_ring NAME``)."""
    return str(Path(os.environ["AMENT_PREFIX_PATH"].split(":")[0]) / "lib" / "sonar_ring" / name)
