"""Running nodes: one per process (``ros2 run``) or several in one executor."""

from __future__ import annotations

from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.logging import get_logger

from sonar_ring.geometry import LayoutError
from sonar_ring.ros.executor import DirectExecutor
from sonar_ring.ros.params import ParameterError
from sonar_ring.simulate import SceneError
from sonar_ring.transport import DeviceError

CONFIG_ERRORS = (LayoutError, SceneError, DeviceError, ParameterError)
"""What a node refuses to start with: a bad layout, scene, device address or parameter."""


def _interrupted(error: BaseException) -> bool:
    """Whether ``error`` is Ctrl-C arriving inside a compiled kernel.

    numba's dispatcher reports the pending KeyboardInterrupt as a SystemError,
    once for every compiled call it passes through (a kernel loading another),
    so the interrupt may sit several causes deep.
    """
    seen = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, KeyboardInterrupt):
            return True
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return False


def spin(*node_classes, args=None, setup: Callable[[list], None] | None = None) -> None:
    """Create the nodes and spin them in one executor (:class:`DirectExecutor`) until Ctrl-C or shutdown.

    One class is the ``main()`` of a node executable; several make the
    single-process graph (components sharing one executor), which ``setup``
    (called with the nodes) may wire together.  A configuration
    error (:data:`CONFIG_ERRORS`) is logged as one line naming the file or
    parameter, the field and the expected value, and the process exits with
    status 1, without a traceback.
    """
    rclpy.init(args=args)
    nodes = []
    starting = "sonar_ring"
    try:
        for cls in node_classes:
            starting = cls.__name__.lower()
            nodes.append(cls())
        if setup is not None:
            starting = "sonar_ring"
            setup(nodes)
        executor = DirectExecutor()
        for node in nodes:
            executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except SystemError as error:
        if not _interrupted(error):
            raise
    except CONFIG_ERRORS as error:
        get_logger(starting).fatal(f"cannot start: {error}")
        raise SystemExit(1) from None
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
