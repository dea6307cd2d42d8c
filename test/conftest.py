import os

import pytest

# Keep DDS traffic of the tests on this machine, and apart from other runs.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))


@pytest.fixture
def ros():
    """rclpy initialised for one test, shut down after it."""
    import rclpy

    rclpy.init()
    yield
    rclpy.try_shutdown()
