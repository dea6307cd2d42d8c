"""Helpers of the tests that run nodes: spinning until a condition, the map's QoS, the executables."""

import os
import shutil
import signal
import subprocess
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


EXIT_SECONDS = 20
"""How long a node process is given to exit after Ctrl-C (SIGINT) before it counts as hung."""


def start_node(name, namespace, *parameters):
    """Run the node executable ``name`` in ``namespace`` with ``parameters`` (``"name:=value"``) as ``ros2 run`` does.

    Python's fault handler is on in it, so :func:`stop_nodes` can have a hung node print where it hangs.
    """
    arguments = [argument for parameter in parameters for argument in ("-p", parameter)]
    return subprocess.Popen([executable(name), "--ros-args", "-r", f"__ns:={namespace}", *arguments],
                            env={**os.environ, "PYTHONFAULTHANDLER": "1"})


def stop_nodes(processes):
    """Ctrl-C to each process of :func:`start_node`; their exit codes, in order.

    A process still running :data:`EXIT_SECONDS` later is aborted (SIGABRT): its fault handler prints
    every thread's stack into the test's output, and its code is ``-SIGABRT``.  Before that, where gdb is
    installed, every thread's native stack is printed too: a node hung in the middleware's C++ (CI saw the
    mapper's ``destroy_node`` not return once) shows only its Python caller to the fault handler.
    """
    for process in processes:
        process.send_signal(signal.SIGINT)
    deadline = time.monotonic() + EXIT_SECONDS
    codes = []
    for process in processes:
        try:
            codes.append(process.wait(timeout=max(deadline - time.monotonic(), 0.1)))
        except subprocess.TimeoutExpired:
            _print_native_stacks(process.pid)
            process.send_signal(signal.SIGABRT)
            codes.append(process.wait(timeout=EXIT_SECONDS))
    return codes


def _print_native_stacks(pid):
    """Every thread's native stack of process ``pid`` (gdb attached in batch mode), printed; nothing without gdb."""
    gdb = shutil.which("gdb")
    if gdb is None:
        return
    done = subprocess.run([gdb, "-p", str(pid), "-batch", "-ex", "thread apply all bt"], capture_output=True,
                          text=True, timeout=120, check=False)
    print(f"native stacks of hung process {pid}:\n{done.stdout}{done.stderr}")
