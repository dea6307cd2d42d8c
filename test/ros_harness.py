"""Helpers of the tests that run nodes: spinning until a condition, the map's QoS, the executables."""

import time
from pathlib import Path

from ament_index_python.packages import get_package_prefix
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
    """Path of a node executable of the colcon-built package, found as ``ros2 run sonar_ring NAME`` finds it.

    The ament index, not the first entry of ``AMENT_PREFIX_PATH``: sourcing the
    environment twice puts the venv, which holds no sonar_ring, first.
    """
    return str(Path(get_package_prefix("sonar_ring")) / "lib" / "sonar_ring" / name)
