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


def launched_nodes(**configurations):
    """The Node actions of the launch file with these launch configurations (over the defaults), and the context."""
    from launch import LaunchContext
    from launch.actions import OpaqueFunction
    from launch_ros.actions import Node

    description = load_description()
    context = LaunchContext()
    context.launch_configurations.update({argument.name: argument.default_value[0].text if argument.default_value
                                          else "" for argument in description.get_launch_arguments()})
    context.launch_configurations.update(configurations)
    nodes = []
    for entity in description.entities:
        if isinstance(entity, OpaqueFunction):  # the sonar_ring processes, made when their prefix is known
            nodes += entity.execute(context)
        elif isinstance(entity, Node):
            nodes.append(entity)
    return nodes, context


def test_launch_file_starts_the_three_nodes_rviz_and_the_single_process_graph():
    nodes, _ = launched_nodes()
    executables = sorted(node.node_executable for node in nodes)
    assert executables == sorted(["driver", "localiser", "mapper", "graph", "rviz2"])


def test_cpus_runs_the_sonar_ring_processes_under_taskset_before_any_launch_prefix():
    from launch.utilities import perform_substitutions

    for cpus, launch_prefix, expected in (("", "", ""), ("1", "", "taskset -c 1"),
                                          ("0,2-3", "gdb --args", "taskset -c 0,2-3 gdb --args"),
                                          ("", "gdb --args", "gdb --args")):
        nodes, context = launched_nodes(cpus=cpus, **{"launch-prefix": launch_prefix})
        for node in nodes:
            prefix = perform_substitutions(context, node.process_description.prefix)
            if node.node_executable == "rviz2":
                assert "taskset" not in prefix
                continue
            assert prefix == expected
            # labelled after the executable, not after taskset
            assert perform_substitutions(context, node.process_description.name) == node.node_executable


def test_cpus_keeps_the_launch_prefix_filter():
    # A process given its own prefix is not filtered by launch: without cpus the nodes get none (launch's
    # own prefix and filter apply); with cpus, cpu_prefix applies the filter itself.
    spec = importlib.util.spec_from_file_location("sonar_ring_launch", LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    _, context = launched_nodes(cpus="", **{"launch-prefix": "gdb --args", "launch-prefix-filter": "localiser"})
    assert module.cpu_prefix(context, "localiser") is None
    _, context = launched_nodes(cpus="1", **{"launch-prefix": "gdb --args", "launch-prefix-filter": "localiser"})
    assert module.cpu_prefix(context, "localiser") == "taskset -c 1 gdb --args"
    assert module.cpu_prefix(context, "mapper") == "taskset -c 1"
    _, context = launched_nodes(cpus="1 2")
    assert module.cpu_prefix(context, "graph") == "taskset -c '1 2'"  # one argument, as given
