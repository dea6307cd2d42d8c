"""rosbag2 files (sqlite3 or MCAP) through the ``rosbags`` library: the graph's topics, types and QoS.

Messages stay serialized CDR bytes here: rclpy serializes them
(``rclpy.serialization.serialize_message``), the nodes' own CDR writers do, or
they are received raw, so the results are those of the nodes by construction;
``/tf`` (:func:`tf_message`) is written the same way, tf2_msgs or not.  rosbags
only does the file I/O; it needs the message definitions for the bag's schema
(what Foxglove and ``ros2 bag play`` decode with): the standard ones of ROS 2
Kilted plus this package's ``msg/*.msg``, read from the installed share folder.

Connections are written with the QoS the nodes publish with, so ``ros2 bag
play`` offers the map topics reliable and transient local (a late RViz still
gets the map) and the per-ping topics best effort.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from sensor_msgs.msg import PointCloud2, Range
from visualization_msgs.msg import MarkerArray

from sonar_ring.geometry import CONFIG_DIR, Layout
from sonar_ring.msg import Echoes, LandmarkArray
from sonar_ring.ros.convert import Cdr
from sonar_ring.ros.node import LATCHED
from sonar_ring.ros.ranges import group_frame, range_topic

MSG_DIR = CONFIG_DIR.parent / "msg"
"""This package's interface definitions (``share/sonar_ring/msg`` when installed, ``msg/`` in a checkout)."""

RELIABLE = QoSProfile(depth=10)
TF = QoSProfile(depth=100)
"""``/tf``'s QoS as tf2's broadcaster publishes it (reliable, volatile, depth 100)."""
TF_TYPE = "tf2_msgs/msg/TFMessage"
STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
"""``--storage`` choices."""


class BagError(ValueError):
    """A bag that cannot be read or written; the text names the file and why."""


@dataclass(frozen=True)
class Topic:
    """One topic of the graph: relative name, rclpy message class (or ROS type name) and its QoS.

    A type name (``tf2_msgs/msg/TFMessage``) stands for a type rclpy may not
    have here; the bag library's own types give its schema, :func:`tf_message` its messages.
    """

    name: str
    message: type | str
    qos: QoSProfile

    @property
    def type_name(self) -> str:
        """The ROS type, e.g. ``sonar_ring/msg/Echoes``."""
        return message_type_name(self.message)


GRAPH_TOPICS = (
    Topic("echoes", Echoes, qos_profile_sensor_data),
    Topic("odom", Odometry, RELIABLE),
    Topic("truth/pose", Odometry, RELIABLE),
    Topic("truth", LandmarkArray, RELIABLE),
    Topic("landmarks/raw", LandmarkArray, qos_profile_sensor_data),
    Topic("landmarks", LandmarkArray, qos_profile_sensor_data),
    Topic("landmarks/pairs", LandmarkArray, qos_profile_sensor_data),
    Topic("markers", MarkerArray, RELIABLE),
    Topic("map/landmarks", LandmarkArray, LATCHED),
    Topic("map/markers", MarkerArray, LATCHED),
    Topic("map/points", PointCloud2, LATCHED),
    Topic("slam/pose", PoseWithCovarianceStamped, RELIABLE),
    Topic("/diagnostics", DiagnosticArray, RELIABLE),
    Topic("/tf", TF_TYPE, TF),
    Topic("/tf_static", TF_TYPE, LATCHED),
)
"""The topics the driver (simulator source), localiser and mapper publish, whatever the layout."""

TOPIC = {topic.name: topic for topic in GRAPH_TOPICS}


def range_topics(layout: Layout) -> list[Topic]:
    """The driver's ``range/group_NN`` topics for ``layout``, one per group."""
    return [Topic(range_topic(group), Range, qos_profile_sensor_data) for group in range(layout.n_groups)]


def graph_topics(layout: Layout) -> list[Topic]:
    """Every topic the graph publishes with ``layout``: :data:`GRAPH_TOPICS` and the ranges."""
    return [*GRAPH_TOPICS, *range_topics(layout)]


def tf_message(transforms) -> bytes:
    """A serialized ``tf2_msgs/TFMessage`` (tf2_msgs need not be installed).

    ``transforms`` holds ``(stamp, parent, child, (x, y, z, yaw))`` tuples:
    stamp in ns, the child frame's pose in the parent's, m and rad.  Written
    straight into CDR (:class:`~sonar_ring.ros.convert.Cdr`): the bag library's
    message objects took 25 times as long (measured), and ``sonar-ring
    process`` writes one for every ping and odometry message; the bytes are
    those the bag library writes (``test_markers``).
    """
    cdr = Cdr()
    cdr.pack("I", len(transforms), align=4)
    for stamp, parent, child, (x, y, z, yaw) in transforms:
        cdr.header(*divmod(int(stamp), 10**9), parent)
        cdr.string(child)
        cdr.pack("7d", x, y, z, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2), align=8)
    return bytes(cdr.buffer)


def static_transforms(stamp: int, base_frame: str, sensor_frame: str, sensor_offset, layout: Layout) -> list[tuple]:
    """The ``/tf_static`` of a graph, as :func:`tf_message` takes it: the sensor on the robot, its groups on it."""
    x, y, yaw = sensor_offset
    transforms = [(stamp, base_frame, sensor_frame, (x, y, 0.0, yaw))]
    transforms += [(stamp, sensor_frame, group_frame(sensor_frame, group), (*centre, group_yaw))
                   for group, (centre, group_yaw) in enumerate(zip(layout.group_centre(), layout.group_yaw(),
                                                                  strict=True))]
    return transforms


def message_type_name(message: type | str) -> str:
    """ROS type name of an rclpy message class, e.g. ``nav_msgs/msg/Odometry`` (a type name stays as it is)."""
    if isinstance(message, str):
        return message
    return f"{message.__module__.split('.')[0]}/msg/{message.__name__}"


def absolute(name: str, namespace: str = "") -> str:
    """A topic name resolved in ``namespace`` (``/`` or ``""``: the root), as bags store it."""
    return name if name.startswith("/") else f"{namespace.rstrip('/')}/{name}"


@cache
def typestore():
    """The ROS 2 Kilted types of rosbags plus this package's messages."""
    store = get_typestore(Stores.ROS2_KILTED)
    definitions = sorted(MSG_DIR.glob("*.msg"))
    if not definitions:
        raise BagError(f"no message definitions in {MSG_DIR}: build the package (tools/bootstrap.sh)")
    for path in definitions:
        store.register(get_types_from_msg(path.read_text(), f"sonar_ring/msg/{path.stem}"))
    return store


def bag_qos(profile: QoSProfile) -> Qos:
    """The rosbag2 ``offered_qos_profiles`` entry of an rclpy QoS profile."""
    return Qos(history=QosHistory[profile.history.name], depth=profile.depth,
               reliability=QosReliability[profile.reliability.name], durability=QosDurability[profile.durability.name],
               deadline=QosTime(0, 0), lifespan=QosTime(0, 0), liveliness=QosLiveliness.AUTOMATIC,
               liveliness_lease_duration=QosTime(0, 0), avoid_ros_namespace_conventions=False)


class BagWriter:
    """A new rosbag2 of serialized messages, with a connection per topic added on first use.

    A context manager: the bag is complete (``metadata.yaml`` written) when the
    ``with`` block ends normally; if it ends with an exception, the partial bag
    is removed so the same name can be used again.

    Parameters
    ----------
    path : str or Path
        The bag directory to create; it must not exist.
    storage : str
        ``mcap`` or ``sqlite3``.
    """

    def __init__(self, path, storage: str = "mcap") -> None:
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f"{self.path} exists already: remove it or choose another output")
        self._writer = Writer(self.path, version=Writer.VERSION_LATEST, storage_plugin=STORAGES[storage])
        self._connections = {}

    def __enter__(self) -> BagWriter:
        try:
            self._writer.open()
        except OSError as error:
            raise BagError(f"{self.path}: cannot create the bag ({error.strerror})") from None
        return self

    def __exit__(self, kind, value, traceback) -> None:
        try:
            self._writer.close()
        finally:
            if kind is not None:
                shutil.rmtree(self.path, ignore_errors=True)

    def connection(self, name: str, message: type, qos: QoSProfile):
        """The connection of topic ``name`` (absolute), added with its type and QoS on first use."""
        known = self._connections.get(name)
        if known is None:
            known = self._writer.add_connection(name, message_type_name(message), typestore=typestore(),
                                                offered_qos_profiles=[bag_qos(qos)])
            self._connections[name] = known
        return known

    def write(self, connection, time_ns: int, data: bytes) -> None:
        """Write one serialized message at bag time ``time_ns`` (ns)."""
        self._writer.write(connection, time_ns, data)


class BagReader:
    """An existing rosbag2 (directory, ``.mcap`` or ``.db3`` file), with every failure as :class:`BagError`.

    A context manager; :attr:`connections` lists the topics, :meth:`messages`
    iterates serialized messages in bag-time order.
    """

    def __init__(self, path) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f"{self.path}: no such file or directory")
        try:
            self._reader = Reader(self.path)
        except Exception as error:  # rosbags raises ReaderError, but also KeyError/ValueError on bad metadata
            raise BagError(f"{self.path}: not a readable rosbag2 ({error})") from None

    def __enter__(self) -> BagReader:
        try:
            self._reader.open()
        except Exception as error:  # a truncated MCAP, a corrupt sqlite3 database, bad metadata.yaml
            raise BagError(f"{self.path}: cannot open the bag, it may be truncated or corrupt ({error})") from None
        return self

    def __exit__(self, *exc) -> None:
        self._reader.close()

    @property
    def connections(self) -> list:
        """The bag's connections (``topic``, ``msgtype``, ``msgcount``)."""
        return list(self._reader.connections)

    def messages(self, connections) -> Iterator[tuple]:
        """``(connection, time_ns, data)`` of the given connections in bag-time order."""
        count = 0
        iterator = self._reader.messages(connections=connections)
        while True:
            try:
                item = next(iterator)
            except StopIteration:
                return
            except Exception as error:  # a chunk cut short or garbled: what rosbags raises varies by storage
                raise BagError(f"{self.path}: unreadable after {count} messages, the bag may be truncated or "
                               f"corrupt ({type(error).__name__}: {error})") from None
            count += 1
            yield item
