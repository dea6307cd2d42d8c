"""The graph over rosbag2 files, in bag time and without DDS: ``sonar-ring process`` and ``sonar-ring record-sim``.

:func:`process_bag` runs the localiser and mapper over the echoes
recorded in a bag and writes what they publish to a new bag;
:func:`record_sim` writes what the driver's simulator source publishes.
Both call what the nodes call -- :class:`sonar_ring.ros.inputs.TopicCheck`,
:func:`sonar_ring.ping_stage.check_ping` and :class:`~sonar_ring.ping_stage.PingStage`, :mod:`sonar_ring.ros.convert`,
:mod:`sonar_ring.ros.markers`, the mapper's core (:class:`~sonar_ring.map_builder.MapBuilder`,
with SLAM by default) and its :func:`~sonar_ring.ros.mapper.map_messages` and
:func:`~sonar_ring.ros.mapper.serialize_pose`, the driver's message builders
-- on rclpy messages serialized by rclpy (markers, landmarks and the pose
written straight into CDR, as the nodes publish them), so each output message
is the one the live graph publishes for the same input; rosbags only reads and
writes the files.

Bag time replaces the node clocks: a ping's outputs are written at its echoes'
bag time with its echoes' header, and the map at ``map_rate`` ticks of bag time
(the first one ``1 / map_rate`` after the first ping), when it changed.

The localiser's work on a ping needs nothing of other pings
(:class:`~sonar_ring.ping_stage.PingStage`), so ``process`` runs it on batches
of pings at once (:class:`LocaliserWork`), in worker processes where there are
cores to spare; the mapper needs every ping before, and is the longest work, so
it runs in order in a process of its own (:class:`MappingWork`); the reading,
the header check and the writing stay in order in the main process, which
writes each ping's outputs once the mapper has mapped it.

``process`` also writes what tf would carry (:func:`~sonar_ring.ros.bag.tf_message`;
the bag library's types give the schema, so without tf2_msgs): ``/tf_static``
once (the robot's ``base_frame`` to the sensor frame at ``sensor_offset``, and
the receiver groups' frames) and ``/tf`` (``odom -> base_frame`` per odometry
message; ``map -> odom`` per ping with SLAM), so a viewer can place the map and
the sensor-frame markers together.
"""

from __future__ import annotations

import contextlib
import itertools
import multiprocessing
import os
import time
from collections import Counter, deque
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import Header

from sonar_ring.echoes import EchoArrays
from sonar_ring.geometry import Layout, LayoutError, load_layout, shipped_params
from sonar_ring.landmarks import CLASS_NAMES, Landmarks
from sonar_ring.map_builder import MapBuilder, PublishedMap
from sonar_ring.ping_stage import Counts, PingStage, check_ping
from sonar_ring.progress import progress_bar
from sonar_ring.realism import World, scene_realism
from sonar_ring.ros import driver, localiser, mapper
from sonar_ring.ros.bag import (
    TOPIC,
    BagError,
    BagReader,
    BagWriter,
    absolute,
    range_topics,
    static_transforms,
    tf_message,
)
from sonar_ring.ros.convert import MessageError, echoes_from_cdr, echoes_to_msg, serialize_landmarks
from sonar_ring.ros.driver import (
    DEFAULT_SPEED_OF_SOUND,
    WORLD_FRAME,
    odometry_message,
    truth_message,
    usable_echoes,
)
from sonar_ring.ros.inputs import TopicCheck, stamp_ns
from sonar_ring.ros.markers import landmark_markers, serialize_markers
from sonar_ring.ros.params import file_values
from sonar_ring.ros.ranges import range_messages
from sonar_ring.simulate import Noise, load_scene

ECHOES_TYPE = TOPIC["echoes"].type_name
ODOMETRY_TYPE = TOPIC["odom"].type_name
NODE_PARAMS = {"localiser": localiser.PARAMS, "mapper": mapper.PARAMS}
"""The nodes ``process`` stands in for, with their parameter lists."""
SIM_START_NS = 10**9
"""Stamp of the first simulated ping, ns: trajectory time plus 1 s (a zero stamp means "latest" to tf and RViz)."""


class BagTime:
    """The clock of ``sonar-ring process``: the bag time of the message being read, ns.

    Given to :class:`~sonar_ring.ros.inputs.TopicCheck` in place of a node's
    clock, so the checks refuse what the nodes refuse on replay with
    ``use_sim_time`` (empty or wrong frame, stamps ahead of bag time, duplicate
    and out-of-order stamps).
    """

    def __init__(self) -> None:
        self.nanoseconds = 0

    def __call__(self) -> int:
        """The bag time, ns."""
        return self.nanoseconds


def node_values(params_file) -> dict:
    """Parameter values of the localiser and mapper, by node name, from a parameters file or defaults."""
    if params_file is None:
        return {node: {p.name: p.default for p in params} for node, params in NODE_PARAMS.items()}
    return {node: file_values(params_file, node, params) for node, params in NODE_PARAMS.items()}


# --------------------------------------------------------------------------- process


@dataclass
class ProcessReport:
    """What :func:`process_bag` did.

    Attributes
    ----------
    pings : int
        Echo messages read.
    seconds : float
        Wall-clock time of the run, s.
    data_seconds : float
        Bag time from the first to the last echo message, s.
    layout : str
        Layout the echoes were processed with.
    params_file : str
        Parameters file used, or ``defaults``.
    per_class : Counter
        Labelled landmarks written, by class name.
    map_per_class : Counter
        Landmarks of the final maps (all echo topics), by class name.
    problems : Counter
        Inputs refused or lost, by reason.
    notes : Counter
        Expected losses (no fault, e.g. an empty ping), by reason.
    skipped : list of str
        Topics asked for or looked for that could not be used, and why.
    maps : dict of str to Landmarks
        The final map of each echoes topic, as published (in its map frame).
    """

    pings: int = 0
    seconds: float = 0.0
    data_seconds: float = 0.0
    layout: str = ""
    params_file: str = "defaults"
    per_class: Counter = field(default_factory=Counter)
    map_per_class: Counter = field(default_factory=Counter)
    problems: Counter = field(default_factory=Counter)
    notes: Counter = field(default_factory=Counter)
    skipped: list = field(default_factory=list)
    maps: dict = field(default_factory=dict)


@dataclass(frozen=True)
class PingOutput:
    """What the localiser makes of one ping.

    Attributes
    ----------
    problems, notes : dict of str to int
        Refusals and expected losses of :func:`~sonar_ring.ping_stage.check_ping`, by reason.
    messages : tuple of bytes
        Serialized ``landmarks/raw``, ``landmarks``, ``landmarks/pairs`` and ``markers`` messages;
        empty when the ping was refused.
    per_class : ndarray of int or None
        The published landmarks (``landmarks``) per class code; None when the ping was refused.
    labelled : Landmarks or None
        The pairs' labelled landmarks, for the mapper; None when the ping was refused.
    """

    problems: dict
    notes: dict
    messages: tuple = ()
    per_class: np.ndarray | None = None
    labelled: Landmarks | None = None


@dataclass(frozen=True)
class LocaliserWork:
    """What the localiser node does to a ping, as ``process`` runs it: its stage, and the markers' lifetime (s).

    It needs no other ping, so it runs in worker processes (:func:`ordered_map`);
    a ping's output does not depend on where it ran.
    """

    stage: PingStage
    marker_lifetime: float

    def outputs(self, pings: list[tuple[Header, EchoArrays]]) -> list[PingOutput]:
        """Check, localise, label and draw decoded Echoes messages as the localiser does, one output per message.

        ``pings`` holds each message's header and arrays (:func:`~sonar_ring.ros.convert.echoes_from_cdr`).
        The checked pings go through :meth:`~sonar_ring.ping_stage.PingStage.label_and_publish_many`
        together, which gives each ping what the node gives it alone.
        """
        counts = [Counts() for _ in pings]
        checked = [check_ping(echoes, self.stage.layout, count, stamp_ns(header))
                   for (header, echoes), count in zip(pings, counts, strict=True)]
        usable = [index for index, echoes in enumerate(checked) if echoes is not None]
        # The messages carry the arrays' own dtypes, so the node's message round trips are lossless and skipped.
        labels = dict(zip(usable, self.stage.label_and_publish_many([checked[i] for i in usable]), strict=True))
        outputs = []
        for index, ((header, _), count) in enumerate(zip(pings, counts, strict=True)):
            if index not in labels:
                outputs.append(PingOutput(dict(count.problems), dict(count.notes)))
                continue
            hypotheses, labelled, published = labels[index]
            data = (serialize_landmarks(hypotheses, header),
                    serialize_landmarks(published, header),
                    serialize_landmarks(labelled, header),
                    serialize_markers(landmark_markers(published, "landmarks", self.marker_lifetime), header))
            per_class = np.bincount(published.landmark_class, minlength=len(CLASS_NAMES))
            outputs.append(PingOutput(dict(count.problems), dict(count.notes), data, per_class, labelled))
        return outputs


_worker: LocaliserWork | None = None
"""The work of this worker process (set by :func:`_start_worker`)."""


def _start_worker(work: LocaliserWork) -> None:
    global _worker
    _worker = work
    work.stage.load_kernels()


def _work(batch: list[bytes]) -> list[PingOutput]:
    return _worker.outputs([echoes_from_cdr(data) for data in batch])


@contextlib.contextmanager
def stage_workers(work: LocaliserWork, workers: int):
    """``workers`` forked processes that run ``work`` (a process pool), or None when ``workers`` is 0.

    The workers start at once and load the stage's compiled kernels while this
    process opens the bag and reads the odometry, so the first batch does not
    wait for them.
    """
    if workers < 1:
        yield None
        return
    context = multiprocessing.get_context("fork")
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_start_worker, initargs=(work,)) as pool:
        pool.submit(int)  # the pool forks its workers at the first task
        yield pool


def ordered_map(work: LocaliserWork, items, workers: ProcessPoolExecutor | None = None, ahead: int = 2,
                batch: int = 64):
    """``(item, output)`` for ``(ping, data, item)`` in ``items``, in order: the work's output.

    The output is that of ``ping`` (header and arrays decoded from the serialized
    message ``data``, :meth:`LocaliserWork.outputs`).

    The work runs on ``batch`` messages at a time.
    Without ``workers`` it runs here; with them (:func:`stage_workers`) the
    batches go to the workers as serialized messages (``data``), while this
    process, which reads and writes, goes on.  At most ``ahead`` batches are
    in flight, so a long bag is streamed, not loaded.
    """
    chunks = iter(lambda: list(itertools.islice(items, batch)), [])
    if workers is None:
        for chunk in chunks:
            outputs = work.outputs([ping for ping, *_ in chunk])
            yield from zip([item for *_, item in chunk], outputs, strict=True)
        return
    pending = deque()
    for chunk in itertools.chain(chunks, [None]):
        if chunk is not None:
            pending.append(([item for *_, item in chunk], workers.submit(_work, [data for _, data, _ in chunk])))
        while pending and (chunk is None or len(pending) >= ahead):
            chunk_items, future = pending.popleft()
            yield from zip(chunk_items, future.result(), strict=True)


@dataclass(frozen=True)
class MapperOutput:
    """What the mapper publishes at one ping, for ``process`` to write.

    Attributes
    ----------
    map : tuple or None
        ``(time_ns, PublishedMap)``: the map at the ``map_rate`` tick of bag time before the ping
        (:meth:`~sonar_ring.map_builder.MapBuilder.published`), when it changed since the tick before.
    pose : tuple or None
        With SLAM, once the ping is mapped: ``(stamp, pose, covariance, map_to_odom)``, the ping's stamp (ns),
        the robot's pose ``(x, y, yaw)`` in ``map`` with its covariance (3, 3)
        (:meth:`~sonar_ring.slam.LandmarkSlam.pose`) and the ``map -> odom`` transform ``(x, y, yaw)``.
    """

    map: tuple | None = None
    pose: tuple | None = None


class MappingWork:
    """The mapper of each echoes topic over its pings, in bag-time order: the node's core and its map ticks.

    The mappers' work is the longest of ``process`` and needs every ping before, so it runs on its own: in one
    process (:func:`mapping_process`) beside this one's reading, localising and writing.

    Parameters
    ----------
    values : dict
        Parameter values by node name (:func:`node_values`).
    layout : Layout
    topics : list of str
        The echoes topics, one mapper each.
    """

    def __init__(self, values: dict, layout: Layout, topics: list[str]) -> None:
        settings = replace(mapper.mapper_settings(values["mapper"]), pose_history=None, layout=layout)
        self._counts = Counts()
        self._builders = {topic: MapBuilder(settings, self._counts) for topic in topics}
        self._map_period = int(round(1e9 / values["mapper"]["map_rate"]))
        self._next_map: dict[str, int | None] = dict.fromkeys(topics)

    def load_kernels(self) -> None:
        """Load the mappers' compiled kernels now (:meth:`~sonar_ring.map_builder.MapBuilder.load_kernels`)."""
        for builder in self._builders.values():
            builder.load_kernels()

    def add_odometry(self, odometry: dict) -> None:
        """Each topic's whole odometry: ``(stamps, poses, covariances)`` (:func:`_read_odometry`) or None, by topic."""
        for topic, history in odometry.items():
            for stamp, pose, covariance in zip(*history, strict=True) if history is not None else ():
                self._builders[topic].add_odometry(stamp, pose, covariance)

    def outputs(self, pings: list[tuple]) -> list[MapperOutput]:
        """Map ``(topic, time_ns, stamp, labelled)`` pings in order, one output each.

        ``time_ns`` is the ping's bag time, ``stamp`` its header's (ns), ``labelled`` its labelled landmarks
        (:class:`PingOutput`), None when the localiser refused it (the map still ticks).
        """
        return [self._ping(*ping) for ping in pings]

    def _ping(self, topic: str, time_ns: int, stamp: int, labelled: Landmarks | None) -> MapperOutput:
        builder = self._builders[topic]
        tick = self._tick(topic, time_ns)
        if labelled is None or not builder.add_ping(stamp, labelled) or builder.slam is None:
            return MapperOutput(tick)
        pose, covariance = builder.slam.pose()
        return MapperOutput(tick, (builder.latest_stamp, pose, covariance, builder.slam.map_to_odom(pose)))

    def _tick(self, topic: str, time_ns: int) -> tuple | None:
        """The map at the last tick up to ``time_ns`` if it changed (the ticks start ``1 / map_rate`` after a ping)."""
        builder, next_map = self._builders[topic], self._next_map[topic]
        if next_map is None:
            self._next_map[topic] = time_ns + self._map_period
            return None
        if next_map > time_ns:
            return None
        self._next_map[topic] += ((time_ns - next_map) // self._map_period + 1) * self._map_period
        return self._changed_map(builder, next_map)

    @staticmethod
    def _changed_map(builder: MapBuilder, time_ns: int) -> tuple | None:
        if not builder.changed:
            return None
        builder.changed = False
        return time_ns, builder.published()

    def finish(self) -> tuple[dict, dict, dict]:
        """The end of the bag: each topic's last map and final map, and the mappers' counts.

        Returns ``({topic: (last, final)}, problems, notes)``: ``last`` the map at the tick after the last ping if
        it changed (``(time_ns, PublishedMap)``, else None), ``final`` the map as published (Landmarks).  Pings
        after the last odometry are not mapped (``no_odometry``).
        """
        maps = {}
        for topic, builder in self._builders.items():
            builder.give_up_waiting()
            last = None if self._next_map[topic] is None else self._changed_map(builder, self._next_map[topic])
            maps[topic] = last, builder.snapshot()
        return maps, dict(self._counts.problems), dict(self._counts.notes)


class _MappingHere:
    """The mappers in this process (``--jobs 1``): each call runs at once, its result a done future."""

    def __init__(self, work: MappingWork) -> None:
        self._work = work

    def submit(self, method: str, *args) -> Future:
        done = Future()
        done.set_result(getattr(self._work, method)(*args))
        return done


class _MappingProcess:
    """The mappers in a forked process of their own: each call queued there, in order (a pool of one)."""

    def __init__(self, pool: ProcessPoolExecutor) -> None:
        self._pool = pool

    def submit(self, method: str, *args) -> Future:
        return self._pool.submit(_map, method, *args)


_mapping: MappingWork | None = None
"""The mappers of the mapping process (set by :func:`_start_mapping`)."""


def _start_mapping(values: dict, layout: Layout, topics: list[str]) -> None:
    global _mapping
    _mapping = MappingWork(values, layout, topics)
    _mapping.load_kernels()


def _map(method: str, *args):
    return getattr(_mapping, method)(*args)


@contextlib.contextmanager
def mapping_process(values: dict, layout: Layout, topics: list[str], separate: bool):
    """The topics' mappers (:class:`MappingWork`): in a forked process of their own if ``separate``, else here.

    Either takes ``submit(method, *args)`` and returns a future of the method's result; the calls run in order.
    The process starts at once and loads the mappers' compiled kernels (numba's start, the largest fixed cost)
    while this one reads the odometry and localises the first pings.
    """
    if not separate:
        yield _MappingHere(MappingWork(values, layout, topics))
        return
    context = multiprocessing.get_context("fork")
    with ProcessPoolExecutor(1, mp_context=context, initializer=_start_mapping,
                             initargs=(values, layout, topics)) as pool:
        pool.submit(int)  # the pool forks its process at the first task
        yield _MappingProcess(pool)


def mapped_in_order(mapping, items, batch: int = 64, ahead: int = 3):
    """``(item, output, mapped)`` for ``((topic, time_ns, header), output)`` in ``items``: what the mapper made of it.

    ``output`` is the ping's :class:`PingOutput`, ``mapped`` its :class:`MapperOutput`.  The pings go to
    ``mapping`` (:func:`mapping_process`) ``batch`` at a time, at most ``ahead`` batches in flight, so the mappers
    always have the next batch while this process writes the last one, and a long bag is streamed, not loaded.
    """
    chunks = iter(lambda: list(itertools.islice(items, batch)), [])
    pending = deque()
    for chunk in itertools.chain(chunks, [None]):
        if chunk is not None:
            pings = [(topic, time_ns, stamp_ns(header), output.labelled) for (topic, time_ns, header), output in chunk]
            pending.append((chunk, mapping.submit("outputs", pings)))
        while pending and (chunk is None or len(pending) >= ahead):
            done, future = pending.popleft()
            for (item, output), mapped in zip(done, future.result(), strict=True):
                yield item, output, mapped


class OfflineGraph:
    """The input check of one echoes topic, and the writing of its outputs and its mapper's, in bag-time order.

    The per-ping work between them is a :class:`~sonar_ring.ping_stage.PingStage`; the mapper's is
    :class:`MappingWork` (the node's core, :class:`~sonar_ring.map_builder.MapBuilder`, with the whole
    odometry of the bag).

    Parameters
    ----------
    values : dict
        Parameter values by node name (:func:`node_values`).
    namespace : str
        Namespace of the echoes topic; the outputs are written in it.
    odometry : tuple or None
        ``(stamps, poses, covariances)``: odometry stamps (ns, increasing, list
        of int), robot poses (O, 3) ``(x, y, yaw)`` in the odometry frame (m,
        rad) and their covariances (list of (3, 3), as the messages give them:
        :meth:`~sonar_ring.map_builder.MapBuilder.add_odometry` judges them);
        None where the mapper places every ping at its ``fixed_pose``.  Written on ``/tf``.
    writer : BagWriter
        Where the outputs go.
    counts : Counts
        Where refused inputs are counted.
    layout : Layout
        The sensor (its group frames go on ``/tf_static``).
    """

    OUTPUTS = ("landmarks/raw", "landmarks", "landmarks/pairs", "markers", "map/landmarks", "map/markers", "map/points",
               "slam/pose")

    def __init__(self, values: dict, namespace: str, odometry, writer: BagWriter, counts: Counts,
                 layout: Layout) -> None:
        self._mapper = values["mapper"]
        self._odometry = odometry if odometry is not None else ([], np.empty((0, 3)), [])
        self._odometry_written = 0
        self._writer = writer
        self._counts = counts
        self._clock = BagTime()
        self._check = TopicCheck(self._clock, counts, "echoes", values["localiser"])
        self._connections = {name: writer.connection(absolute(name, namespace), TOPIC[name].message, TOPIC[name].qos)
                             for name in self.OUTPUTS + ("/tf", "/tf_static")}
        self._layout = layout
        self._static_written = False
        self.per_class = np.zeros(len(CLASS_NAMES), dtype=np.int64)

    def admit(self, time_ns: int, data: bytes) -> tuple[Header, EchoArrays] | None:
        """The header and arrays of the Echoes message recorded at bag time ``time_ns`` (ns).

        None when the localiser would refuse it (:meth:`~sonar_ring.ros.inputs.TopicCheck.take_echoes`).
        """
        self._clock.nanoseconds = time_ns
        return self._check.take_echoes(data, None)

    def write(self, time_ns: int, header: Header, output: PingOutput, mapped: MapperOutput) -> None:
        """Write a ping's outputs at ``time_ns`` as the live graph publishes them.

        The map's tick before the ping, the odometry's transforms, the localiser's messages and the mapper's pose.
        """
        if mapped.map is not None:
            self._write_map(*mapped.map)
        self._transforms_until(time_ns, header.frame_id)
        self._counts.problems.update(output.problems)
        self._counts.notes.update(output.notes)
        if output.per_class is None:
            return
        for name, data in zip(("landmarks/raw", "landmarks", "landmarks/pairs", "markers"), output.messages,
                              strict=True):
            self._writer.write(self._connections[name], time_ns, data)
        self.per_class += output.per_class
        if mapped.pose is not None:
            self._write_pose(time_ns, *mapped.pose)

    def _write_pose(self, time_ns: int, stamp: int, pose, covariance, map_to_odom) -> None:
        """``slam/pose`` and ``map -> odom`` on ``/tf`` at the latest ping mapped, as the live mapper publishes them."""
        header = Header(frame_id=self._mapper["map_frame"])
        header.stamp.sec, header.stamp.nanosec = divmod(stamp, 10**9)
        self._writer.write(self._connections["slam/pose"], time_ns, mapper.serialize_pose(pose, covariance, header))
        x, y, yaw = map_to_odom
        self._writer.write(self._connections["/tf"], time_ns, tf_message([
            (stamp, self._mapper["map_frame"], self._mapper["odom_frame"], (x, y, 0.0, yaw))]))

    def _transforms_until(self, time_ns: int, sensor_frame: str) -> None:
        """``/tf_static`` before the first ping; ``odom -> base_frame`` of every odometry up to ``time_ns``."""
        if not self._static_written:
            self._static_written = True
            self._writer.write(self._connections["/tf_static"], time_ns, tf_message(static_transforms(
                time_ns, self._mapper["base_frame"], sensor_frame, self._mapper["sensor_offset"], self._layout)))
        stamps, poses, _ = self._odometry
        while self._odometry_written < len(stamps) and stamps[self._odometry_written] <= time_ns:
            stamp, pose = stamps[self._odometry_written], poses[self._odometry_written]
            self._writer.write(self._connections["/tf"], stamp, tf_message([
                (stamp, self._mapper["odom_frame"], self._mapper["base_frame"], (pose[0], pose[1], 0.0, pose[2]))]))
            self._odometry_written += 1

    def _write_map(self, time_ns: int, published: PublishedMap) -> None:
        header = Header(frame_id=published.frame)
        header.stamp.sec, header.stamp.nanosec = divmod(time_ns, 10**9)
        for name, data in zip(("map/landmarks", "map/markers", "map/points"), mapper.map_messages(published, header),
                              strict=True):
            self._writer.write(self._connections[name], time_ns, data)

    def finish(self, last: tuple | None) -> None:
        """Write the map at the tick after the last ping (``(time_ns, PublishedMap)``), if it changed."""
        if last is not None:
            self._write_map(*last)


def _topics_by_name(bag: BagReader) -> dict:
    topics = {}
    for connection in bag.connections:
        topics.setdefault(connection.topic, []).append(connection)
    return topics


def _echo_topics(topics: dict, requested, report: ProcessReport) -> list[str]:
    """The echoes topics to process: ``requested`` (names) or every topic of type Echoes; the rest reported."""
    if not requested:
        return sorted(name for name, connections in topics.items() if connections[0].msgtype == ECHOES_TYPE)
    chosen = []
    for name in dict.fromkeys(absolute(n) for n in requested):
        if name not in topics:
            report.skipped.append(f"{name}: not in the bag")
        elif topics[name][0].msgtype != ECHOES_TYPE:
            report.skipped.append(f"{name}: type {topics[name][0].msgtype}, not {ECHOES_TYPE}")
        else:
            chosen.append(name)
    return chosen


def _namespace(topic: str) -> str:
    return topic.rsplit("/", 1)[0]


def _read_odometry(bag: BagReader, connections, mapper_values: dict, counts: Counts):
    """Odometry stamps (ns, list), poses (O, 3) and covariances (list) of a topic, as the mapper's gate takes them.

    (:func:`~sonar_ring.ros.mapper.usable_odometry`.)
    """
    clock = BagTime()
    check = TopicCheck(clock, counts, "odom", mapper_values, frame_param="odom_frame")
    stamps, poses, covariances = [], [], []
    for _, time_ns, data in bag.messages(connections):
        try:
            msg = deserialize_message(data, Odometry)
        except Exception:  # rclpy raises a bare RuntimeError/TypeError for CDR it cannot decode
            counts.problem("undecodable_odometry")
            continue
        clock.nanoseconds = time_ns
        if check.admit(msg.header) and (odometry := mapper.usable_odometry(msg, counts)) is not None:
            stamps.append(stamp_ns(msg.header))
            poses.append(odometry[0])
            covariances.append(odometry[1])
    return stamps, np.array(poses, dtype=float).reshape(-1, 3), covariances


def _layout_of(bag: BagReader, connections, layout):
    """The layout given, or the one the first echoes message names."""
    if layout is not None:
        return load_layout(layout)
    for _, _, data in bag.messages(connections):
        try:
            name = echoes_from_cdr(data)[1].layout
        except MessageError:  # the next message may be readable
            continue
        try:
            return load_layout(name)
        except LayoutError as error:
            raise LayoutError(f"the echoes name layout {name!r}, which is not shipped ({error}); "
                              "give it with --layout") from None
    raise BagError(f"{bag.path}: no readable echoes message to take the layout from; give --layout")


def process_bag(in_path, out_path, *, layout=None, params_file=None, echoes_topics=None, odom_topic=None,
                storage: str = "mcap", jobs: int | None = None, progress: bool = True) -> ProcessReport:
    """Run the localiser and mapper over a bag's echoes; write their outputs to a new bag.

    Parameters
    ----------
    in_path, out_path : str or Path
        Input rosbag2 (directory, ``.mcap`` or ``.db3``); output bag directory
        (must not exist; removed again if the run fails).
    layout : str, optional
        Layout name or YAML path; default the one the echoes name.
    params_file : str or Path, optional
        Node parameters (``config/params/<layout>.yaml`` format); default the
        shipped file of the layout.
    echoes_topics : list of str, optional
        Echoes topics; default every topic of type ``sonar_ring/msg/Echoes``.
        Each is processed by its own graph, its outputs written in its namespace.
    odom_topic : str, optional
        Odometry for the mapper, relative to each echoes topic's namespace
        (default ``odom``); without it the mapper uses ``fixed_pose``.
    storage : str
        ``mcap`` or ``sqlite3``, for the output.
    jobs : int, optional
        Processes in all: this one (reading, the input checks and writing, in
        order), one for the mappers (:func:`mapping_process`) and ``jobs - 2``
        workers for the localiser's work (2: it runs here); 1 does everything
        here; default one per CPU this process may use.
    progress : bool
        Draw a progress bar on stderr (in a terminal: :func:`~sonar_ring.progress.progress_bar`).

    Raises
    ------
    BagError, LayoutError, ParameterError
        One line naming the file or topic and the problem.
    """
    started = time.perf_counter()
    report = ProcessReport()
    counts = Counts()
    with BagReader(in_path) as bag:
        topics = _topics_by_name(bag)
        chosen = _echo_topics(topics, echoes_topics, report)
        if not chosen:
            found = ", ".join(f"{name} ({c[0].msgtype})" for name, c in sorted(topics.items())) or "none"
            skipped = "".join(f"{reason}; " for reason in report.skipped)
            raise BagError(f"{in_path}: no usable echoes topic (type {ECHOES_TYPE}): {skipped}the bag has {found}")
        namespaces = [_namespace(name) for name in chosen]
        if len(set(namespaces)) != len(namespaces):
            raise BagError(f"{', '.join(chosen)}: two echoes topics in one namespace would write the same outputs; "
                           "choose one with --echoes-topic")
        echo_connections = [c for name in chosen for c in topics[name]]
        sensor = _layout_of(bag, echo_connections, layout)
        report.layout = sensor.name
        if params_file is None:
            params_file = shipped_params(sensor.name)
        report.params_file = str(params_file or "defaults")
        values = node_values(params_file)
        work = LocaliserWork(PingStage(sensor, localiser.settings_from(values["localiser"])),
                             values["localiser"]["marker_lifetime"])
        jobs = jobs or len(os.sched_getaffinity(0))
        stage_jobs = max(jobs - 2, 0)
        with mapping_process(values, sensor, chosen, separate=jobs > 1) as mapping, \
                stage_workers(work, stage_jobs) as workers, BagWriter(out_path, storage) as writer:
            graphs, odometry = {}, {}
            for name, namespace in zip(chosen, namespaces, strict=True):
                odometry[name] = None
                if values["mapper"]["use_odometry"]:
                    odometry[name] = _odometry_for(bag, topics, absolute(odom_topic or "odom", namespace),
                                                  values["mapper"], counts, report, explicit=odom_topic is not None)
                graphs[name] = OfflineGraph(values, namespace, odometry[name], writer, counts, sensor)
            odometry_added = mapping.submit("add_odometry", odometry)
            bar = progress_bar(sum(c.msgcount for c in echo_connections), enabled=progress)
            times = []

            def admitted():
                for connection, time_ns, data in bag.messages(echo_connections):
                    times.append(time_ns)
                    ping = graphs[connection.topic].admit(time_ns, data)
                    if ping is not None:
                        yield ping, data, (connection.topic, time_ns, ping[0])
                    bar.update(1)

            localised = ordered_map(work, admitted(), workers, ahead=2 * stage_jobs)
            for (name, time_ns, header), output, mapped in mapped_in_order(mapping, localised):
                graphs[name].write(time_ns, header, output, mapped)
            bar.close()
            odometry_added.result()
            maps, problems, notes = mapping.submit("finish").result()
            counts.problems.update(problems)
            counts.notes.update(notes)
            for name, graph in graphs.items():
                last, report.maps[name] = maps[name]
                graph.finish(last)
                report.per_class.update(dict(zip(CLASS_NAMES, graph.per_class.tolist(), strict=True)))
                per_class = np.bincount(report.maps[name].landmark_class, minlength=len(CLASS_NAMES))
                report.map_per_class.update(dict(zip(CLASS_NAMES, per_class.tolist(), strict=True)))
    report.pings = len(times)
    report.data_seconds = (times[-1] - times[0]) * 1e-9 if times else 0.0
    report.problems, report.notes = counts.problems, counts.notes
    report.seconds = time.perf_counter() - started
    return report


def _odometry_for(bag: BagReader, topics: dict, name: str, mapper_values: dict, counts: Counts,
                  report: ProcessReport, explicit: bool):
    """The odometry history of topic ``name``, or None (reported) when the bag has none there."""
    connections = topics.get(name)
    if connections is None or connections[0].msgtype != ODOMETRY_TYPE:
        why = "not in the bag" if connections is None else f"type {connections[0].msgtype}, not {ODOMETRY_TYPE}"
        if explicit or connections is not None:
            report.skipped.append(f"{name}: {why}")
        report.skipped.append(f"map at fixed_pose {list(mapper_values['fixed_pose'])}: no odometry on {name}")
        return None
    return _read_odometry(bag, connections, mapper_values, counts)


# --------------------------------------------------------------------------- record-sim


@dataclass
class RecordReport:
    """What :func:`record_sim` wrote: pings, their bag-time span (s), the wall-clock time (s), problems."""

    pings: int = 0
    data_seconds: float = 0.0
    seconds: float = 0.0
    problems: Counter = field(default_factory=Counter)


def record_sim(scene, out_path, *, layout="browne_ring", laps: int = 1, pings: int | None = None, seed: int = 0,
               sigma_t: float | None = None, sigma_a: float | None = None, world: str = "realistic", realism=None,
               with_range: bool = True, frame_id: str = "sonar_ring", storage: str = "mcap",
               progress: bool = True) -> RecordReport:
    """Write what the driver's simulator source publishes over ``laps`` of the scene's trajectory to a new bag.

    ``pings`` stops earlier, after that many pings.

    Topics ``/echoes``, ``/odom`` (the wheel odometry), ``/truth/pose`` (the
    true pose in ``world``), ``/truth`` and (``with_range``)
    ``/range/group_NN``, with the driver's QoS (not ``/tf_static``: the
    driver's group frames need tf2_msgs).  Ping k is stamped (and written at) trajectory time
    ``k / ping_rate`` plus :data:`SIM_START_NS`; a scene without a trajectory
    pings at its ``sensor_pose``, one ping per lap.  The noise (``sigma_t``,
    s; ``sigma_a`` relative to A_max; default the driver's ``sigma_tof`` and
    ``sigma_amplitude`` in the layout's shipped parameters, else its defaults), the ``world`` profile with the
    ``realism`` field overrides (:mod:`sonar_ring.realism`) and the seed mean
    what the driver's ``sigma_tof``, ``sigma_amplitude``, ``world``,
    ``realism.*`` and ``seed`` mean, so with the same values the echoes and
    the odometry are the driver's.
    """
    started = time.perf_counter()
    scene = load_scene(scene)
    sensor = load_layout(layout)
    driver_values = file_values(shipped_params(sensor.name) or {}, "driver", driver.PARAMS)
    sigma_t = driver_values["sigma_tof"] if sigma_t is None else sigma_t
    sigma_a = driver_values["sigma_amplitude"] if sigma_a is None else sigma_a
    rate = sensor.ping_rate
    simulated = World(scene, sensor, scene_realism(scene, world, realism, where="--realism"),
                      noise=Noise(tof=sigma_t, amplitude=sigma_a), seed=seed, ping_rate=rate)
    poses = scene.trajectory.poses(rate)[1] if scene.trajectory is not None else scene.sensor_pose[None, :]
    counts = Counts()
    report = RecordReport()
    total = laps * len(poses) if pings is None else min(pings, laps * len(poses))
    bar = progress_bar(total, enabled=progress)
    with BagWriter(out_path, storage) as writer:
        topics = [TOPIC["echoes"], TOPIC["odom"], TOPIC["truth/pose"], TOPIC["truth"],
                  *(range_topics(sensor) if with_range else [])]
        connection = {topic.name: writer.connection(absolute(topic.name), topic.message, topic.qos)
                      for topic in topics}
        ranges = [topic.name for topic in topics[4:]]
        for k in range(total):
            pose = poses[k % len(poses)]
            ping = simulated.ping(pose, k / rate)
            odometry = simulated.odometry_pose(pose)
            stamp = SIM_START_NS + round(k * 1e9 / rate)
            header = Header(frame_id=frame_id)
            header.stamp.sec, header.stamp.nanosec = divmod(stamp, 10**9)
            kept = usable_echoes(ping.echoes, sensor, counts, stamp, DEFAULT_SPEED_OF_SOUND)
            messages = [("odom", odometry_message(odometry, header)),
                        ("truth/pose", odometry_message(pose, header, frame_id=WORLD_FRAME)),
                        ("truth", truth_message(ping, header))]
            if kept is not None:
                messages.insert(0, ("echoes", echoes_to_msg(kept, header)))
                if with_range:
                    messages += zip(ranges, range_messages(sensor, kept, header), strict=True)
            for name, message in messages:
                writer.write(connection[name], stamp, serialize_message(message))
            bar.update(1)
        bar.close()
    report.pings = total
    report.data_seconds = (total - 1) / rate if total else 0.0
    report.problems = counts.problems
    report.seconds = time.perf_counter() - started
    return report


def describe(path) -> str:
    """``PATH (N MB)`` of a written bag, for the command's last line."""
    size = sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file())
    return f"{path} ({size / 1e6:.1f} MB)"
