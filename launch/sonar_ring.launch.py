"""The sonar_ring graph: driver -> localiser -> mapper, and RViz on request.

    ros2 launch sonar_ring sonar_ring.launch.py                      # hardware, Browne ring
    ros2 launch sonar_ring sonar_ring.launch.py source:=simulator    # default room scene
    ros2 launch sonar_ring sonar_ring.launch.py source:=simulator scene:=single_pole rviz:=true
    ros2 launch sonar_ring sonar_ring.launch.py source:=topic use_sim_time:=true   # bag replay
    ros2 launch sonar_ring sonar_ring.launch.py single_process:=true cpus:=1         # lowest latency

Node parameters come from config/params/<layout>.yaml unless ``params_file`` names
another file; the arguments below override them.
"""

import re
import shlex

from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution, PythonExpression
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

NODES = ("driver", "localiser", "mapper")

ARGUMENTS = {
    "layout": ("browne_ring", "sensor layout: a name in config/layouts"),
    "params_file": ("", "node parameters YAML (default: config/params/<layout>.yaml)"),
    "source": ("hardware", "where echoes come from: hardware, topic or simulator"),
    "device": ("udp://0.0.0.0:5600", "hardware device: serial:///dev/ttyUSB0?baud=921600, udp://HOST:PORT, "
               "tcp://HOST:PORT"),
    "scene": ("room", "simulator scene: a name in config/scenes or a YAML path"),
    "namespace": ("", "namespace of every node and relative topic"),
    "use_sim_time": ("false", "use /clock (bag replay)"),
    "rviz": ("false", "start RViz with config/sonar_ring.rviz"),
    "single_process": ("false", "run the three nodes in one process (one executor)"),
    "cpus": ("", "CPUs the sonar_ring processes run on, as taskset -c takes them (e.g. 1 or 2-3); empty: any. "
             "On one CPU a ping's middleware threads and executor share its cache: lower, steadier latency"),
}


def generate_launch_description() -> LaunchDescription:
    """Declare the arguments and the nodes."""
    share = FindPackageShare("sonar_ring")
    config = {name: LaunchConfiguration(name) for name in ARGUMENTS}
    params_file = PythonExpression(["'", config["params_file"], "' or '", share, "/config/params/",
                                    config["layout"], ".yaml'"])
    overrides = {
        "use_sim_time": PythonExpression(["'", config["use_sim_time"], "'.lower() == 'true'"]),
        "layout": config["layout"],
        "source": config["source"],
        "device": config["device"],
        "scene": config["scene"],
    }
    parameters = [params_file, overrides]

    def sonar_ring_processes(context: LaunchContext) -> list[Node]:
        # exec_name: under taskset, a process would be labelled after it (taskset-1).
        separate = [
            Node(package="sonar_ring", executable=name, name=name, namespace=config["namespace"],
                 parameters=parameters, output="screen", prefix=cpu_prefix(context, name), exec_name=name,
                 condition=UnlessCondition(config["single_process"]))
            for name in NODES
        ]
        # No name: a name would rename every node of the process; the parameters go to all of them.
        together = Node(package="sonar_ring", executable="graph", namespace=config["namespace"],
                        parameters=parameters, output="screen", prefix=cpu_prefix(context, "graph"),
                        exec_name="graph", condition=IfCondition(config["single_process"]))
        return [*separate, together]

    rviz = Node(package="rviz2", executable="rviz2", name="rviz2", namespace=config["namespace"],
                arguments=["-d", PathJoinSubstitution([share, "config", "sonar_ring.rviz"])],
                parameters=[{"use_sim_time": overrides["use_sim_time"]}], condition=IfCondition(config["rviz"]))
    declared = [DeclareLaunchArgument(name, default_value=default, description=text)
                for name, (default, text) in ARGUMENTS.items()]
    return LaunchDescription([*declared, OpaqueFunction(function=sonar_ring_processes), rviz])


def cpu_prefix(context: LaunchContext, executable: str) -> str | None:
    """The process prefix of ``executable``: None (launch's own) without ``cpus``, else ``taskset -c <cpus>``.

    With ``cpus``, ``--launch-prefix`` (gdb, valgrind) follows taskset, so what
    it runs inherits the CPUs, where ``--launch-prefix-filter`` lets it: a node
    given its own prefix is no longer filtered by launch itself.
    """
    cpus = context.launch_configurations.get("cpus", "")
    if not cpus:
        return None
    prefix = f"taskset -c {shlex.quote(cpus)}"
    launch_prefix = context.launch_configurations.get("launch-prefix", "")
    if launch_prefix and re.match(context.launch_configurations.get("launch-prefix-filter", ""), executable):
        prefix += f" {launch_prefix}"
    return prefix
