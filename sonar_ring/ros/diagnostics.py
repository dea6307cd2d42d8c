"""Per-node health on ``/diagnostics``: input rate, latency, and problems by reason.

A node calls :meth:`NodeHealth.received` for every input message,
:meth:`NodeHealth.processed` with the time it took and the messages it
published, :meth:`NodeHealth.sent` for messages published apart from an input
(the mapper's map), :meth:`NodeHealth.problem` for every bad input or dropped
item (counted by reason, a warning logged at most every 5 s per reason, and the
status WARN), and :meth:`NodeHealth.note` for expected losses (an echo one
receiver of a pair missed) that are counted but are no fault.
Once a second the counts go out as a ``diagnostic_msgs/DiagnosticArray``.
"""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from std_msgs.msg import Header

WARN_THROTTLE_S = 5.0
LATENCY_WINDOW = 1000


class NodeHealth:
    """Counters of one node, published on ``/diagnostics`` every ``period`` seconds.

    Attributes
    ----------
    problems : Counter
        Total problems by reason since start.
    notes : Counter
        Expected losses by reason since start.
    received_count, published_count : int
        Inputs taken and outputs published since start.
    extra_values : callable or None
        Returns more ``{key: value}`` pairs of the node's own for each report (the driver's device clock).
    """

    def __init__(self, node: Node, hardware_id: str = "", period: float = 1.0) -> None:
        self._node = node
        self._hardware_id = hardware_id
        self._publisher = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._timer = node.create_timer(period, self.publish)
        self._arrivals: deque[float] = deque(maxlen=LATENCY_WINDOW)
        self._latency: deque[float] = deque(maxlen=LATENCY_WINDOW)
        self._reported: Counter[str] = Counter()
        self._warned: dict[str, float] = {}
        self.problems: Counter[str] = Counter()
        self.notes: Counter[str] = Counter()
        self.received_count = 0
        self.published_count = 0
        self.extra_values: Callable[[], dict[str, str]] | None = None

    def received(self) -> None:
        """Count one input message."""
        self.received_count += 1
        self._arrivals.append(time.monotonic())

    def processed(self, seconds: float, published: int = 1) -> None:
        """Record the compute time of one input and how many messages it produced."""
        self._latency.append(seconds)
        self.sent(published)

    def sent(self, count: int) -> None:
        """Count ``count`` messages published (:meth:`processed` counts those of an input; this, others: a map)."""
        self.published_count += count

    def problem(self, reason: str, detail: str = "", count: int = 1) -> None:
        """Count ``count`` problems of kind ``reason``; warn at most every ``WARN_THROTTLE_S`` per reason.

        The throttle is per reason, so a flood of one kind does not hide the
        first of another; the warning says how many there were so far.
        """
        if count <= 0:
            return
        self.problems[reason] += count
        now = time.monotonic()
        if now - self._warned.get(reason, -WARN_THROTTLE_S) >= WARN_THROTTLE_S:
            self._warned[reason] = now
            total = f"{reason} ({self.problems[reason]} so far)"
            self._node.get_logger().warning(f"{total}: {detail}" if detail else total)

    def note(self, reason: str, count: int = 1) -> None:
        """Count ``count`` expected losses of kind ``reason`` (no warning)."""
        if count > 0:
            self.notes[reason] += count

    def latencies(self) -> np.ndarray:
        """Recent compute times, s, oldest first (at most the last 1000)."""
        return np.asarray(self._latency)

    def rate(self) -> float:
        """Input messages per second over the recent window."""
        if len(self._arrivals) < 2:
            return 0.0
        span = self._arrivals[-1] - self._arrivals[0]
        return (len(self._arrivals) - 1) / span if span > 0 else 0.0

    def status(self) -> DiagnosticStatus:
        """The node's status now: WARN when problems grew since the last report."""
        latency = self.latencies() * 1e3
        new_problems = self.problems - self._reported
        values = {
            "input rate (Hz)": f"{self.rate():.2f}",
            "inputs": str(self.received_count),
            "published": str(self.published_count),
            "latency median (ms)": f"{np.median(latency):.3f}" if latency.size else "n/a",
            "latency p99 (ms)": f"{np.percentile(latency, 99):.3f}" if latency.size else "n/a",
        }
        if self.extra_values is not None:
            values.update(self.extra_values())
        values.update({f"problems: {reason}": str(n) for reason, n in sorted(self.problems.items())})
        values.update({f"counted: {reason}": str(n) for reason, n in sorted(self.notes.items())})
        level = DiagnosticStatus.WARN if new_problems else DiagnosticStatus.OK
        message = ", ".join(f"{n} {reason}" for reason, n in sorted(new_problems.items())) or "ok"
        return DiagnosticStatus(level=level, name=f"sonar_ring: {self._node.get_fully_qualified_name()}",
                                message=message, hardware_id=self._hardware_id,
                                values=[KeyValue(key=k, value=v) for k, v in values.items()])

    def publish(self) -> None:
        """Send the status on ``/diagnostics``."""
        status = self.status()
        self._reported = Counter(self.problems)
        header = Header(stamp=self._node.get_clock().now().to_msg())
        self._publisher.publish(DiagnosticArray(header=header, status=[status]))
