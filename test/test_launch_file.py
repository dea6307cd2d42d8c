"""The launch file parses and declares the documented arguments and nodes.

``launch`` and ``launch_ros`` come with a ROS 2 install, not from PyPI, so this
runs where they are installed and says so where they are not.
"""

import importlib.util
from pathlib import Path

import pytest

launch = pytest.importorskip("launch", reason="`launch` is not installed: it ships with ROS 2, not PyPI")
pytest.importorskip("launch_ros", reason="`launch_ros` is not installed: it ships with ROS 2, not PyPI")

LAUNCH_FILE = Path(__file__).resolve().parents[1] / "launch" / "sonar_ring.launch.py"


def load_description():
    spec = importlib.util.spec_from_file_location("sonar_ring_launch", LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.generate_launch_description()


def test_launch_file_declares_the_documented_arguments():
    arguments = {a.name: a.default_value for a in load_description().get_launch_arguments()}
    assert set(arguments) == {"layout", "params_file", "source", "device", "scene", "namespace", "use_sim_time",
                              "rviz", "single_process", "cpus"}


def test_launch_file_starts_the_four_nodes_rviz_and_the_single_process_graph():
    from launch_ros.actions import Node

    nodes = [entity for entity in load_description().entities if isinstance(entity, Node)]
    executables = sorted(node.node_executable for node in nodes)
    assert executables == sorted(["driver", "localiser", "classifier", "mapper", "graph", "rviz2"])


def test_cpus_runs_the_sonar_ring_processes_under_taskset_before_any_launch_prefix():
    from launch import LaunchContext
    from launch.utilities import perform_substitutions
    from launch_ros.actions import Node

    nodes = [entity for entity in load_description().entities if isinstance(entity, Node)]
    ours = [node for node in nodes if node.node_executable != "rviz2"]
    rviz = next(node for node in nodes if node.node_executable == "rviz2")
    for cpus, launch_prefix, expected in (("", "", []), ("1", "", ["taskset", "-c", "1"]),
                                          ("0,2-3", "gdb --args", ["taskset", "-c", "0,2-3", "gdb", "--args"]),
                                          ("", "gdb --args", ["gdb", "--args"])):
        context = LaunchContext()
        context.launch_configurations.update({"cpus": cpus, "launch-prefix": launch_prefix})
        for node in ours:
            assert perform_substitutions(context, node.process_description.prefix).split() == expected
            # labelled after the executable, not after taskset
            assert perform_substitutions(context, node.process_description.name) == node.node_executable
        assert "taskset" not in perform_substitutions(context, rviz.process_description.prefix)
