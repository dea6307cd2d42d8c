"""Running nodes: one per process (``ros2 run``) or several in one executor."""

from __future__ import annotations

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor


def spin(*node_classes, args=None) -> None:
    """Create the nodes and spin them in one executor until Ctrl-C or shutdown.

    One class is the ``main()`` of a node executable; several make the
    single-process graph (components sharing one executor).
    """
    rclpy.init(args=args)
    nodes = []
    try:
        nodes = [cls() for cls in node_classes]
        executor = SingleThreadedExecutor()
        for node in nodes:
            executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
