"""The base of every sonar_ring node: publishers and subscriptions without default QoS event handlers.

rclpy gives each publisher and subscription handlers that log incompatible QoS
or types; each is a waitable that the executor visits on every wait.  The four
nodes hold 40 of them, and in one executor (the ``graph`` and the demo) they
made every wait 0.53 ms instead of 0.31 ms, about 1 ms per ping over its five
callbacks.  The other end of a topic (RViz, your node) still reports an
incompatible QoS; a handler passed explicitly is kept.
"""

from __future__ import annotations

from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""Reliable and transient local, depth 1: the map and the static frames, which a late subscriber still gets."""


class SonarNode(Node):
    """A :class:`rclpy.node.Node` whose publishers and subscriptions have no QoS event handlers by default."""

    def create_publisher(self, *args, **kwargs):
        """:meth:`rclpy.node.Node.create_publisher` without default event handlers."""
        kwargs.setdefault("event_callbacks", PublisherEventCallbacks(use_default_callbacks=False))
        return super().create_publisher(*args, **kwargs)

    def create_subscription(self, *args, **kwargs):
        """:meth:`rclpy.node.Node.create_subscription` without default event handlers."""
        kwargs.setdefault("event_callbacks", SubscriptionEventCallbacks(use_default_callbacks=False))
        return super().create_subscription(*args, **kwargs)
