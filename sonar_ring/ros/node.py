"""The base of every sonar_ring node: publishers and subscriptions without default QoS event handlers.

rclpy gives each publisher and subscription handlers that log incompatible QoS
or types; each is a waitable that the executor visits on every wait.  The four
nodes held 40 of them, and in one executor every wait visited them all, five
waits a ping before the nodes were composed (:meth:`SonarNode.follow`).  The
other end of a topic (RViz, your node) still reports an incompatible QoS; a
handler passed explicitly is kept.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""Reliable and transient local, depth 1: the map and the static frames, which a late subscriber still gets."""


class SonarNode(Node):
    """A :class:`rclpy.node.Node` whose publishers and subscriptions have no QoS event handlers by default.

    In one process the nodes can also hand each ping straight to the next one
    (:meth:`follow`), as rclcpp's intra-process communication does: every topic
    is still published, but the next node skips the middleware, the executor
    and the message decoding.
    """

    handoff: Callable | None = None
    """The next node's ``on_ping``, when it follows this one in this process."""
    ping_inputs: tuple = ()
    """The subscriptions that bring this node its pings; :meth:`follow` replaces them."""

    def follow(self, upstream: SonarNode) -> None:
        """Take pings from ``upstream`` in this process (its :meth:`pass_on`) instead of from :attr:`ping_inputs`."""
        for subscription in self.ping_inputs:
            self.destroy_subscription(subscription)
        self.ping_inputs = ()
        upstream.handoff = self.on_ping

    def pass_on(self, *ping) -> float:
        """Hand a ping to the node that follows this one, if any; return the seconds it took there.

        Callers subtract them from their own latency on ``/diagnostics``.
        """
        if self.handoff is None:
            return 0.0
        started = time.perf_counter()
        self.handoff(*ping)
        return time.perf_counter() - started

    def create_publisher(self, *args, **kwargs):
        """:meth:`rclpy.node.Node.create_publisher` without default event handlers."""
        kwargs.setdefault("event_callbacks", PublisherEventCallbacks(use_default_callbacks=False))
        return super().create_publisher(*args, **kwargs)

    def create_subscription(self, *args, **kwargs):
        """:meth:`rclpy.node.Node.create_subscription` without default event handlers."""
        kwargs.setdefault("event_callbacks", SubscriptionEventCallbacks(use_default_callbacks=False))
        return super().create_subscription(*args, **kwargs)
