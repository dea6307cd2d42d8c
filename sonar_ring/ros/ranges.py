"""The driver's Range output for Nav2: one ``sensor_msgs/Range`` topic per group, and the groups' frames.

A ping gives one message on each ``range/group_NN`` (Nav2's range layer takes
a list of topics, one sensor each; 48 messages at once on one topic would
overflow a sensor-data subscription's queue of 5) that has a subscriber: the
driver looks for subscribers once a second (:class:`RangeOutput`), as lazy
publishers of image_transport do, because 48 messages a ping cost their
building and publishing even when nobody listens.

``sensor_msgs/Range`` describes a cone along +x of its frame (REP 117), so each
receiver group gets a frame ``<frame_id>/group_NN`` at the centre of its
receivers, x along the group's facing.  The driver publishes them once on
``/tf_static`` (reliable, transient local, as tf2's static broadcaster does)
when ``tf2_msgs`` is installed -- it is with every ROS 2 distribution, but not
on PyPI; without it the driver says so once and RViz / Nav2 need the frames
from elsewhere (e.g. the robot's URDF, with these poses).
"""

from __future__ import annotations

import math
import time

import numpy as np
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Range

from sonar_ring.echoes import EchoArrays
from sonar_ring.geometry import Layout
from sonar_ring.ros.convert import header_message
from sonar_ring.ros.node import LATCHED, SonarNode

MIN_RANGE = 0.02
"""m: nearer echoes are reported as -inf (too close, REP 117)."""
LISTENERS_PERIOD = 1.0
"""s between looks for each range topic's subscribers; a new subscriber waits at most this long."""


def range_topic(group: int) -> str:
    """Relative topic of group ``group``'s Range messages: one topic per sensor, as Nav2's range layer expects."""
    return f"range/group_{group:02d}"


def range_publishers(node: SonarNode, layout: Layout) -> list:
    """One sensor-data publisher per group on :func:`range_topic`.

    ``node`` is a :class:`~sonar_ring.ros.node.SonarNode`: with QoS event
    handlers, 48 publishers would double the work of every executor wait.
    """
    return [node.create_publisher(Range, range_topic(group), qos_profile_sensor_data)
            for group in range(layout.n_groups)]


class RangeOutput:
    """The Range publishers of a node (:func:`range_publishers`); each ping goes out on the topics someone reads.

    Parameters
    ----------
    node : SonarNode
        The publishing node.
    layout : Layout
        Its sensor: one topic per group.
    """

    def __init__(self, node: SonarNode, layout: Layout) -> None:
        self._layout = layout
        self._publishers = range_publishers(node, layout)
        self._listened: list[int] = []
        self._next_look = -math.inf

    def publish(self, echoes: EchoArrays, header) -> None:
        """Publish a ping's :func:`range_messages` on the topics with subscribers."""
        now = time.monotonic()
        if now >= self._next_look:
            self._listened = [group for group, publisher in enumerate(self._publishers)
                              if publisher.get_subscription_count()]
            self._next_look = now + LISTENERS_PERIOD
        if self._listened:
            for group, message in zip(self._listened, range_messages(self._layout, echoes, header, self._listened),
                                      strict=True):
                self._publishers[group].publish(message)


def group_frame(frame_id: str, group: int) -> str:
    """Name of group ``group``'s frame under the sensor frame ``frame_id``."""
    return f"{frame_id}/group_{group:02d}"


def group_transforms(layout: Layout, frame_id: str, stamp) -> list[TransformStamped]:
    """One transform per group: ``frame_id`` -> :func:`group_frame`, at the receivers' centre, x along the facing.

    Translations in m (including the receivers' height), rotations about z by the
    group's yaw; ``stamp`` is a ``builtin_interfaces/Time``.
    """
    transforms = []
    for group, (centre, yaw) in enumerate(zip(layout.group_centre(), layout.group_yaw(), strict=True)):
        transform = TransformStamped()
        transform.header.stamp = stamp
        transform.header.frame_id = frame_id
        transform.child_frame_id = group_frame(frame_id, group)
        transform.transform.translation.x, transform.transform.translation.y, transform.transform.translation.z = (
            float(value) for value in centre)
        transform.transform.rotation.z = math.sin(0.5 * float(yaw))
        transform.transform.rotation.w = math.cos(0.5 * float(yaw))
        transforms.append(transform)
    return transforms


def publish_group_frames(node: Node, layout: Layout, frame_id: str):
    """Publish the group frames on ``/tf_static``; return the publisher, or None without ``tf2_msgs``."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        node.get_logger().info("tf2_msgs is not installed: the range frames <frame_id>/group_NN are not published "
                               "on /tf_static; give them to tf from elsewhere (e.g. the URDF)")
        return None
    publisher = node.create_publisher(TFMessage, "/tf_static", LATCHED)
    publisher.publish(TFMessage(transforms=group_transforms(layout, frame_id, node.get_clock().now().to_msg())))
    return publisher



def range_messages(layout: Layout, echoes: EchoArrays, header, groups=None) -> list[Range]:
    """One REP 117 Range per group of ``layout`` (or of ``groups``, in that order) for a ping.

    Each is framed :func:`group_frame` of ``header.frame_id``.

    Each group's range is its nearest echo's half path ``c * min(tof) / 2`` (m);
    ``+inf`` when the group heard nothing, ``-inf`` when the echo is nearer than
    :data:`MIN_RANGE`.  Field of view: twice the receivers' acceptance
    half-angle; maximum range: the layout's.
    """
    nearest = np.full(layout.n_groups, np.inf)
    if echoes.n_echoes:
        with np.errstate(all="ignore"):
            half_path = 0.5 * echoes.speed_of_sound * np.nanmin(echoes.tof, axis=1)
        np.minimum.at(nearest, echoes.group.astype(np.int64), half_path)
    nearest[nearest < MIN_RANGE] = -np.inf
    field_of_view = 2.0 * float(layout.beam_half_angle)
    stamp = header_message(header).stamp
    messages = []
    for group in range(layout.n_groups) if groups is None else groups:
        value = float(nearest[group])
        message = Range(radiation_type=Range.ULTRASOUND, field_of_view=field_of_view, min_range=MIN_RANGE,
                        max_range=float(layout.max_range), range=value)
        message.header.stamp = stamp
        message.header.frame_id = group_frame(header.frame_id, group)
        messages.append(message)
    return messages
