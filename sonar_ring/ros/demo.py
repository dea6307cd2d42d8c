"""demo: the whole graph on a simulated scene for one lap, recorded, drawn and scored.

Runs driver (simulator source) -> localiser -> mapper in one
process, in real time (the driver pings at the layout's rate), with the
layout's shipped node parameters (``config/params/<layout>.yaml``, as the
launch file gives them), in the
``realistic`` world by default (drifting wheel odometry, missed, spurious,
multipath and late echoes, the air's true speed of sound: :mod:`sonar_ring.realism`;
``--world ideal`` for the forward model alone), follows the ping stream with a
progress bar, and leaves in the output folder (``demo_output/``):

* ``bag/`` -- a rosbag2 (MCAP) of every topic of the graph, written from raw
  subscriptions as the messages arrived: for ``ros2 bag play``, Foxglove or
  ``sonar-ring process``;
* ``map.png`` -- the scene's true walls, corners and edges, the robot's true
  path and its odometry, and the estimated map by class with 2-sigma
  covariance ellipses;
* ``summary.txt`` -- what it prints: the world, landmarks per class,
  classification accuracy of the decided ones and position error against the
  simulator's ``truth`` topic, per-ping compute time per node, the map and its
  score against the scene (:func:`sonar_ring.score.score_map`), the odometry's error.

    demo [--scene room] [--layout browne_ring] [--laps 1] [--pings N] [--seed 0] [--world realistic]
         [--realism FIELD=VALUE ...] [--out demo_output]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.experimental import EventsExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from rclpy.serialization import deserialize_message

from sonar_ring import poses
from sonar_ring.cli import realism_field
from sonar_ring.geometry import load_layout, shipped_params
from sonar_ring.landmarks import CLASS_NAMES, CORNER_OR_EDGE, UNKNOWN
from sonar_ring.msg import LandmarkArray
from sonar_ring.progress import progress_bar
from sonar_ring.realism import PROFILES, air_speed
from sonar_ring.ros.bag import TOPIC, BagWriter, absolute, graph_topics, static_transforms, tf_message
from sonar_ring.ros.convert import echoes_from_cdr, landmarks_from_msg
from sonar_ring.ros.driver import BASE_FRAME, REALISM_PREFIX
from sonar_ring.ros.executor import DirectExecutor
from sonar_ring.ros.graph import NODES, compose
from sonar_ring.ros.inputs import stamp_ns
from sonar_ring.ros.mapper import odometry_pose
from sonar_ring.ros.node import SonarNode
from sonar_ring.ros.offline import describe
from sonar_ring.ros.run import CONFIG_ERRORS
from sonar_ring.score import heard_reflectors, score_map, trajectory_error

RECORDER = "demo_recorder"
"""Node name of the recorder."""
RECORDING_DEPTH = 100
"""Messages a recording subscription keeps between two spins: the driver publishes a Range per group at once."""
QUIET_SECONDS = 0.3
"""The recorder closes the bag once told to stop and nothing arrived for this long."""
RECORDER_READY = "recorder ready"
"""What the recorder prints on its standard output once its subscriptions exist."""
HUNG_RECORDER_SECONDS = 300.0
"""Last resort against a hung recorder process: it starts in seconds, and is waited for as long as it takes
(longer on a busy machine), but not for ever."""
DRAIN_SECONDS = 3.0
"""Longest wait, after the last ping, for the nodes downstream to finish it."""


def record(bag_path: Path, layout: str, stop, ready=lambda: None) -> None:
    """Record every topic of the graph into a new bag, as ``ros2 bag record`` would: run in a process of its own.

    Raw subscriptions to the topics of the graph with ``layout`` (a name or a
    path), written at their arrival time; ``ready()`` is called once they all
    exist.  After ``stop`` (an event) is set,
    the bag is closed as soon as nothing arrived for :data:`QUIET_SECONDS`.
    A process of its own keeps the recording (a Range per group of every
    ping) from stealing the graph's interpreter time, which would inflate the
    nodes' measured compute time.
    """
    rclpy.init()
    try:
        with BagWriter(bag_path) as writer:
            node = rclpy.create_node(RECORDER)
            last = [time.monotonic()]
            sensor = load_layout(layout)
            made = None if _tf_message_class() is not None else _TransformsFromTopics(writer, sensor)

            def keep(connection, raw: bytes) -> None:
                now = node.get_clock().now().nanoseconds
                writer.write(connection, now, raw)
                last[0] = time.monotonic()
                if made is not None:
                    made.take(connection.topic, now, raw)

            for topic in subscribed_topics(sensor):
                message = topic.message if not isinstance(topic.message, str) else _tf_message_class()
                qos = QoSProfile(depth=max(topic.qos.depth, RECORDING_DEPTH), reliability=topic.qos.reliability,
                                 durability=topic.qos.durability)
                connection = writer.connection(absolute(topic.name), topic.message, topic.qos)
                node.create_subscription(message, topic.name, lambda raw, c=connection: keep(c, raw), qos, raw=True)
            ready()
            executor = EventsExecutor()
            executor.add_node(node)
            while not (stop.is_set() and time.monotonic() - last[0] > QUIET_SECONDS):
                executor.spin_once(timeout_sec=0.05)
    finally:
        rclpy.try_shutdown()


def subscribed_topics(layout) -> list:
    """The graph's topics the recorder subscribes: all, but tf without tf2_msgs (:class:`_TransformsFromTopics`)."""
    return [topic for topic in graph_topics(layout)
            if not isinstance(topic.message, str) or _tf_message_class() is not None]


def _tf_message_class():
    """``tf2_msgs.msg.TFMessage``, or None where tf2_msgs is not installed (PyPI's ROS 2 wheels)."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        return None
    return TFMessage


class _TransformsFromTopics:
    """What the graph would publish on ``/tf`` and ``/tf_static``, made from its topics where tf2_msgs is missing.

    ``/tf_static`` at the first echoes: the sensor on the robot (the mapper's
    ``sensor_offset``, zero in the demo) and its receiver groups;
    ``/tf``: ``odom -> base_link`` per odometry message and ``map -> odom`` per
    ``slam/pose`` (the robot's pose in ``map`` after its odometry pose at the
    same stamp), written by :func:`~sonar_ring.ros.bag.tf_message` (the bag library's types for the schema).
    """

    def __init__(self, writer: BagWriter, layout) -> None:
        self._writer = writer
        self._layout = layout
        self._tf = writer.connection("/tf", TOPIC["/tf"].message, TOPIC["/tf"].qos)
        self._static = None
        self._odometry = poses.PoseHistory(limit=None)

    def take(self, topic: str, time_ns: int, raw: bytes) -> None:
        """A message the recorder wrote: ``raw`` on ``topic`` (absolute) at bag time ``time_ns``."""
        if topic == "/echoes" and self._static is None:
            self._static = self._writer.connection("/tf_static", TOPIC["/tf_static"].message,
                                                   TOPIC["/tf_static"].qos)
            frame = echoes_from_cdr(raw)[0].frame_id
            self._writer.write(self._static, time_ns, tf_message(static_transforms(
                time_ns, BASE_FRAME, frame, (0.0, 0.0, 0.0), self._layout)))
        elif topic == "/odom":
            message = deserialize_message(raw, Odometry)
            stamp, pose = stamp_ns(message.header), odometry_pose(message)
            self._odometry.add(stamp, pose)
            self._writer.write(self._tf, time_ns, tf_message([(stamp, message.header.frame_id,
                                                                message.child_frame_id, (pose[0], pose[1], 0.0,
                                                                                         pose[2]))]))
        elif topic == "/slam/pose":
            message = deserialize_message(raw, PoseWithCovarianceStamped)
            stamp = stamp_ns(message.header)
            odometry = self._odometry.at(stamp)
            if odometry is None:
                return
            pose = message.pose.pose
            in_map = (pose.position.x, pose.position.y, poses.yaw_of(pose.orientation))
            x, y, yaw = poses.compose(in_map, poses.inverse(odometry))
            self._writer.write(self._tf, time_ns, tf_message([(stamp, message.header.frame_id, "odom",
                                                                (x, y, 0.0, yaw))]))


def record_until_stdin_closes(bag_path: str, layout: str) -> None:
    """:func:`record` in the recorder process: says :data:`RECORDER_READY` on stdout, stops when stdin closes."""
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    record(Path(bag_path), layout, stop, ready=lambda: print(RECORDER_READY, flush=True))


def _start_recorder(bag_path: Path, layout: str) -> subprocess.Popen:
    """A fresh interpreter running :func:`record_until_stdin_closes`.

    A new process rather than a fork: a fork of a process that has run ROS
    before inherits middleware state that breaks discovery.  ``-P`` keeps the
    working directory off ``sys.path``, where a source checkout's
    ``sonar_ring`` (without the generated messages) would shadow the installed one.
    """
    code = f"from sonar_ring.ros.demo import record_until_stdin_closes as r; r({str(bag_path)!r}, {layout!r})"
    return subprocess.Popen([sys.executable, "-P", "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)


def _wait_for_recorder(listener, recorder: subprocess.Popen, executor, topics) -> None:
    """Spin until the recorder says it is ready and each topic (absolute names) shows its subscription.

    So the first ping is recorded.  No fixed window: an interpreter's start
    and imports take seconds, more on a busy machine, and discovery follows;
    only the recorder exiting, or :data:`HUNG_RECORDER_SECONDS`, ends the wait.
    """
    ready = threading.Event()

    def read_stdout() -> None:
        for line in recorder.stdout:  # read to the end, so the pipe never fills
            if line.strip() == RECORDER_READY:
                ready.set()

    threading.Thread(target=read_stdout, daemon=True).start()
    deadline = time.monotonic() + HUNG_RECORDER_SECONDS
    while not (ready.is_set() and all(any(info.node_name == RECORDER
                                          for info in listener.get_subscriptions_info_by_topic(name))
                                      for name in topics)):
        if recorder.poll() is not None:
            raise RuntimeError(f"the recorder exited (code {recorder.returncode}) before it was ready")
        if time.monotonic() > deadline:
            raise RuntimeError(f"the recorder was not ready and discovered after {HUNG_RECORDER_SECONDS:g} s")
        executor.spin_once(timeout_sec=0.05)


def _stamp_key(msg) -> tuple[int, int]:
    return msg.header.stamp.sec, msg.header.stamp.nanosec


def run(scene: str, layout: str, laps: int, seed: int, out: Path, pings: int | None = None,
        world: str = "realistic", realism: dict | None = None) -> dict:
    """Run the graph for ``laps`` of the scene's trajectory (or ``pings`` pings); record into ``out/bag``.

    ``world`` is the driver's profile and ``realism`` replaces single fields of it.
    Returns the summary figures, the map and the robot's paths for the picture.
    """
    bag_path = out / "bag"
    if bag_path.exists():
        shutil.rmtree(bag_path)
    out.mkdir(parents=True, exist_ok=True)
    overrides = [Parameter("source", value="simulator"), Parameter("scene", value=scene),
                 Parameter("layout", value=layout), Parameter("loops", value=laps), Parameter("seed", value=seed),
                 Parameter("world", value=world),
                 *(Parameter(REALISM_PREFIX + name, value=float(value)) for name, value in (realism or {}).items())]
    shipped = shipped_params(load_layout(layout).name)
    recorder = _start_recorder(bag_path, layout)
    rclpy.init(args=["--ros-args", "--params-file", str(shipped)] if shipped else None)
    try:
        nodes = [cls(parameter_overrides=overrides) for cls in NODES]
        compose(nodes)
        driver, localiser, mapper = nodes
        total = pings or driver.pings_per_lap * laps
        listener = SonarNode("demo_listener")  # no QoS event handlers: the executor keeps its direct path
        found, truth, odometry, true_pose, estimate = {}, {}, {}, {}, {}
        subscribe = listener.create_subscription
        subscribe(LandmarkArray, "landmarks", lambda m: found.__setitem__(_stamp_key(m), m), qos_profile_sensor_data)
        subscribe(LandmarkArray, "truth", lambda m: truth.__setitem__(_stamp_key(m), m), 100)
        subscribe(Odometry, "odom", lambda m: odometry.__setitem__(_stamp_key(m), odometry_pose(m)), 100)
        subscribe(Odometry, "truth/pose", lambda m: true_pose.__setitem__(_stamp_key(m), odometry_pose(m)), 100)
        subscribe(PoseWithCovarianceStamped, "slam/pose", lambda m: estimate.__setitem__(_stamp_key(m), (
            m.pose.pose.position.x, m.pose.pose.position.y, poses.yaw_of(m.pose.pose.orientation))), 100)
        executor = DirectExecutor()
        for node in [localiser, mapper, listener]:
            executor.add_node(node)
        _wait_for_recorder(listener, recorder, executor,
                           [absolute(topic.name) for topic in subscribed_topics(driver.layout)])
        executor.add_node(driver)
        started = time.monotonic()
        bar = progress_bar(total)
        while driver.pings_published < total:
            executor.spin_once(timeout_sec=0.05)
            bar.update(driver.pings_published - bar.n)
        bar.close()
        executor.remove_node(driver)
        deadline = time.monotonic() + DRAIN_SECONDS
        # Until the mapper has every ping, and each one's odometry: the final map must hold them all.
        while ((mapper.health.received_count < driver.pings_published or mapper.pending_pings)
               and time.monotonic() < deadline):
            executor.spin_once(timeout_sec=0.02)
        elapsed = time.monotonic() - started
        mapper.publish_map()
        flush = time.monotonic() + QUIET_SECONDS
        while time.monotonic() < flush:
            executor.spin_once(timeout_sec=0.02)
        recorder.stdin.close()
        if recorder.wait(timeout=HUNG_RECORDER_SECONDS) != 0:
            raise RuntimeError(f"the recorder failed (exit code {recorder.returncode}); {bag_path} is incomplete")
        figures = _score(found, truth)
        latency = {node.get_name(): float(np.median(node.health.latencies())) * 1e3 for node in nodes}
        snapshot = mapper.builder.snapshot()
        stamps = sorted(set(odometry) & set(true_pose))
        paths = {"true path": np.array([true_pose[k] for k in stamps]).reshape(-1, 3),
                 "odometry": np.array([odometry[k] for k in stamps]).reshape(-1, 3)}
        errors = {"odometry": trajectory_error(paths["odometry"], paths["true path"])} if stamps else {}
        estimated = sorted(set(estimate) & set(true_pose))
        if estimated:
            paths["SLAM"] = np.array([estimate[k] for k in estimated])
            errors["SLAM"] = trajectory_error(paths["SLAM"], np.array([true_pose[k] for k in estimated]))
        heard = heard_reflectors(driver.scene, *_truth_in_world(truth, true_pose))
        slam = mapper.builder.slam
        air = None if slam is None or slam.settings.sigma_speed == 0.0 else \
            (*slam.air_estimate, air_speed(driver.scene, driver.realism, 0.0) / driver.scene.speed_of_sound - 1.0)
        return {
            **figures, "pings": total, "seconds": elapsed, "latency_ms": latency, "world": world,
            "effects": driver.realism.effects(),
            "map": {name: int(np.count_nonzero(snapshot.landmark_class == c)) for c, name in enumerate(CLASS_NAMES)},
            # odom starts at the true first pose, and map at odom's first pose: the map frame is the scene's
            "map_score": score_map(snapshot, driver.scene, heard), "map_frame": mapper.builder.frame,
            "pose_errors": errors, "air": air,
            "snapshot": snapshot, "scene": driver.scene, "paths": paths, "bag": bag_path,
        }
    finally:
        rclpy.try_shutdown()
        if recorder.poll() is None:
            recorder.terminate()
            recorder.wait()


def _score(found: dict, truth: dict) -> dict:
    """Landmarks per class, accuracy of the decided ones, position error: the pings with both messages.

    Landmarks of an echo of no reflector (truth not valid: multipath, clutter,
    a late echo) have no true class or position; they are counted apart.
    """
    pairs = [(landmarks_from_msg(found[k]), landmarks_from_msg(truth[k])) for k in found if k in truth]
    classes = np.concatenate([f.landmark_class for f, _ in pairs] + [np.empty(0, np.uint8)])
    real = np.concatenate([t.valid[f.echo] for f, t in pairs] + [np.empty(0, bool)])
    true_classes = np.concatenate([t.landmark_class[f.echo] for f, t in pairs] + [np.empty(0, np.uint8)])
    error = np.concatenate([np.linalg.norm(f.position - t.position[f.echo], axis=1) for f, t in pairs]
                           + [np.empty(0)])[real]
    decided = (classes != UNKNOWN) & real
    return {
        "landmarks": int(classes.size),
        "per_class": {name: int(np.count_nonzero(classes == c)) for c, name in enumerate(CLASS_NAMES[:CORNER_OR_EDGE])},
        "of_no_reflector": int(np.count_nonzero(~real)),
        "decided_correct": float(np.mean(classes[decided] == true_classes[decided])) if decided.any() else None,
        "error_percentiles": tuple(np.percentile(error, [50, 95]).tolist()) if error.size else None,
    }


def _truth_in_world(truth: dict, true_pose: dict):
    """Classes, positions and normals of the truth messages' rows in the world frame (the pings with a true pose)."""
    classes, positions, normals = [np.empty(0, np.uint8)], [np.empty((0, 2))], [np.empty((0, 2))]
    for key, message in truth.items():
        if key not in true_pose:
            continue
        rows = landmarks_from_msg(message)
        x, y, yaw = true_pose[key]
        rotation = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])  # row vectors: R^T
        classes.append(rows.landmark_class[rows.valid])
        positions.append(rows.position[rows.valid] @ rotation + (x, y))
        normals.append(rows.normal[rows.valid] @ rotation)
    return np.concatenate(classes), np.concatenate(positions), np.concatenate(normals)


def summary_text(figures: dict) -> str:
    """The printed summary."""
    score = figures["map_score"]
    effects = ", ".join(figures["effects"]) or "none"
    lines = [
        f"sonar_ring demo: {figures['pings']} pings in {figures['seconds']:.1f} s, {figures['world']} world "
        f"(effects: {effects})",
        "  landmarks per class: " + ", ".join(f"{n} {name}" for name, n in figures["per_class"].items())
        + (f" ({figures['of_no_reflector']} from echoes of no reflector)" if figures["of_no_reflector"] else ""),
        "  classification: " + (f"{100 * figures['decided_correct']:.1f} % of decided landmarks correct"
                                if figures["decided_correct"] is not None else "no decisions"),
        "  position error: " + ("no landmarks" if figures["error_percentiles"] is None else
                                "median {:.1f} mm, 95th percentile {:.1f} mm".format(
                                    *(1e3 * e for e in figures["error_percentiles"]))),
        "  compute per ping (median): "
        + ", ".join(f"{name} {ms:.2f} ms" for name, ms in figures["latency_ms"].items()),
        "  map: " + ", ".join(f"{n} {name}" for name, n in figures["map"].items()),
        "  map score: " + "; ".join(f"{s.mapped} of {s.heard} {name}s mapped" for name, s in score.per_class.items())
        + f"; {score.total('duplicates')} duplicate, {score.ghosts} ghost, {score.total('wrong_class')} wrong class, "
          f"{score.total('misplaced')} misplaced, {score.undecided} undecided",
    ]
    errors = []
    if score.point_error.size:
        errors.append(f"corners and edges median {1e3 * np.median(score.point_error):.1f} mm")
    if score.wall_offset.size:
        errors.append(f"walls median {1e3 * np.median(score.wall_offset):.1f} mm, "
                      f"up to {1e2 * score.wall_overshoot.max():.1f} cm past their ends")
    if errors:
        lines.append("  map error (mapped entries): " + ", ".join(errors))
    if figures.get("air") is not None:
        error, sigma, true_error = figures["air"]
        lines.append(f"  speed of sound (SLAM's fit): {100 * error:+.2f} +- {100 * sigma:.2f} % over the assumed "
                     f"(the air's at the start: {100 * true_error:+.2f} %)")
    if figures["pose_errors"]:
        lines.append("  pose error: " + "; ".join(f"{name} RMS {1e2 * rms:.1f} cm, final {1e2 * final:.1f} cm"
                                                 for name, (rms, final) in figures["pose_errors"].items()))
    return "\n".join(lines)


def write_outputs(figures: dict, out: Path) -> str:
    """``map.png`` and ``summary.txt`` in ``out``; returns the summary with the list of outputs."""
    from sonar_ring import plot  # matplotlib only here, after the run

    found = ", ".join(f"{n} {name}" for name, n in figures["map"].items() if n)
    plot.save_map_png(out / "map.png", figures["scene"], figures["paths"], figures["snapshot"],
                      f"{figures['scene'].name}, {figures['world']} world: map after {figures['pings']} pings "
                      f"({found or 'empty'}), in {figures['map_frame']}")
    text = "\n".join([
        summary_text(figures),
        f"wrote {describe(figures['bag'])}, {out / 'map.png'}, {out / 'summary.txt'}",
        f"  replay: ros2 bag play {figures['bag']}    offline: sonar-ring process {figures['bag']} OUT_BAG",
    ])
    (out / "summary.txt").write_text(text + "\n")
    return text


def main(argv=None) -> int:
    """Parse the arguments, run, write the outputs, print the summary."""
    parser = argparse.ArgumentParser(prog="demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="room", help="scene name or YAML path (default: room)")
    parser.add_argument("--layout", default="browne_ring", help="layout name or YAML path (default: browne_ring)")
    parser.add_argument("--laps", type=int, default=1, help="laps of the scene trajectory (default: 1)")
    parser.add_argument("--pings", type=int, help="stop after this many pings (default: the laps)")
    parser.add_argument("--seed", type=int, default=0, help="noise seed (default: 0)")
    parser.add_argument("--world", choices=tuple(PROFILES), default="realistic",
                        help="the world's effects: realistic (drifting odometry, missed, spurious, multipath and late "
                             "echoes, the air's speed of sound) or ideal (the forward model) (default: realistic)")
    parser.add_argument("--realism", action="append", type=realism_field, default=[], metavar="FIELD=VALUE",
                        help="replace one field of the world's profile (e.g. multipath_gain=0); repeat for several")
    parser.add_argument("--out", type=Path, default=Path("demo_output"), help="output folder (default: demo_output)")
    args = parser.parse_args(argv)
    try:
        figures = run(args.scene, args.layout, args.laps, args.seed, args.out, args.pings, args.world,
                      dict(args.realism))
        print(write_outputs(figures, args.out))
    except (*CONFIG_ERRORS, ValueError, OSError, RuntimeError) as error:
        print(f"demo: error: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
