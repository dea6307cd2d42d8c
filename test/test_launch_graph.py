"""launch_testing: the launch file on the simulator starts, publishes the topics and exits cleanly.

Runs where ``launch_testing`` and ``launch_testing_ros`` are installed (a ROS 2
install: ``launch_test test/test_launch_graph.py`` or pytest with the
launch_testing plugin) and is skipped with the reason elsewhere.
"""

import time
import unittest
from pathlib import Path

import pytest

pytest.importorskip("launch_testing", reason="`launch_testing` is not installed: it ships with ROS 2")
pytest.importorskip("launch_testing_ros", reason="`launch_testing_ros` is not installed: it ships with ROS 2")

import launch  # noqa: E402
import launch_testing.actions  # noqa: E402
import launch_testing.asserts  # noqa: E402
import rclpy  # noqa: E402
from launch.actions import IncludeLaunchDescription  # noqa: E402
from launch.launch_description_sources import PythonLaunchDescriptionSource  # noqa: E402
from launch_testing_ros import WaitForTopics  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from sonar_ring.msg import Echoes, LandmarkArray  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

LAUNCH_FILE = Path(__file__).resolve().parents[1] / "launch" / "sonar_ring.launch.py"


@pytest.mark.launch_test
def generate_test_description():
    graph = IncludeLaunchDescription(PythonLaunchDescriptionSource(str(LAUNCH_FILE)),
                                     launch_arguments={"source": "simulator"}.items())
    return launch.LaunchDescription([graph, launch_testing.actions.ReadyToTest()])


class TestTopicsAppear(unittest.TestCase):
    def test_reliable_outputs_appear(self):
        topics = [("markers", MarkerArray), ("map/landmarks", LandmarkArray), ("map/markers", MarkerArray),
                  ("map/points", PointCloud2)]
        with WaitForTopics(topics, timeout=30.0) as waiting:
            self.assertEqual(waiting.topics_not_received(), set())

    def test_sensor_data_topics_carry_pings(self):
        # WaitForTopics subscribes reliably; these topics are best effort (sensor-data QoS).
        rclpy.init()
        try:
            node = rclpy.create_node("launch_test_listener")
            seen = {}
            for topic, kind in (("echoes", Echoes), ("landmarks/raw", LandmarkArray), ("landmarks", LandmarkArray)):
                node.create_subscription(kind, topic, lambda m, t=topic: seen.setdefault(t, m), qos_profile_sensor_data)
            deadline = time.monotonic() + 30.0
            while len(seen) < 3 and time.monotonic() < deadline:
                rclpy.spin_once(node, timeout_sec=0.1)
            self.assertEqual(set(seen), {"echoes", "landmarks/raw", "landmarks"})
            self.assertEqual(seen["echoes"].layout, "browne_ring")
            self.assertGreater(len(seen["landmarks"].landmark_class), 0)
        finally:
            rclpy.shutdown()


@launch_testing.post_shutdown_test()
class TestCleanExit(unittest.TestCase):
    def test_exit_codes(self, proc_info):
        launch_testing.asserts.assertExitCodes(proc_info, allowable_exit_codes=[0, -2, -15])
