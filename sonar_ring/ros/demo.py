"""demo: the whole graph on a simulated scene for one lap, recorded, drawn and scored.

Runs driver (simulator source) -> localiser -> classifier -> mapper in one
process, in real time (the driver pings at the layout's rate), follows the ping
stream with a progress bar, and leaves in the output folder (``demo_output/``):

* ``bag/`` -- a rosbag2 (MCAP) of every topic of the graph, written from raw
  subscriptions as the messages arrived: for ``ros2 bag play``, Foxglove or
  ``sonar-ring process``;
* ``map.png`` -- the scene's true walls, corners and edges, the robot's path and
  the estimated map by class with 2-sigma covariance ellipses;
* ``summary.txt`` -- what it prints: landmarks per class, classification
  accuracy of the decided ones and position error against the simulator's
  ``truth`` topic, per-ping compute time per node, and the map.

    demo [--scene room] [--layout browne_ring] [--laps 1] [--pings N] [--seed 0] [--out demo_output]
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
from rclpy.experimental import EventsExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, qos_profile_sensor_data

from sonar_ring.geometry import load_layout
from sonar_ring.landmarks import CLASS_NAMES, CORNER, EDGE, PLANE, UNKNOWN
from sonar_ring.msg import LandmarkArray
from sonar_ring.progress import progress_bar
from sonar_ring.ros.bag import BagWriter, absolute, graph_topics
from sonar_ring.ros.convert import landmarks_from_msg
from sonar_ring.ros.executor import DirectExecutor
from sonar_ring.ros.graph import NODES, compose
from sonar_ring.ros.node import SonarNode
from sonar_ring.ros.offline import describe
from sonar_ring.ros.run import CONFIG_ERRORS

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
MATCH_DISTANCE = 0.05
"""m: a map entry within this of a true reflector of its class counts as right."""


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

            def keep(connection, raw: bytes) -> None:
                writer.write(connection, node.get_clock().now().nanoseconds, raw)
                last[0] = time.monotonic()

            for topic in graph_topics(load_layout(layout)):
                qos = QoSProfile(depth=max(topic.qos.depth, RECORDING_DEPTH), reliability=topic.qos.reliability,
                                 durability=topic.qos.durability)
                connection = writer.connection(absolute(topic.name), topic.message, topic.qos)
                node.create_subscription(topic.message, topic.name, lambda raw, c=connection: keep(c, raw), qos,
                                         raw=True)
            ready()
            executor = EventsExecutor()
            executor.add_node(node)
            while not (stop.is_set() and time.monotonic() - last[0] > QUIET_SECONDS):
                executor.spin_once(timeout_sec=0.05)
    finally:
        rclpy.try_shutdown()


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


def run(scene: str, layout: str, laps: int, seed: int, out: Path, pings: int | None = None) -> dict:
    """Run the graph for ``laps`` of the scene's trajectory (or ``pings`` pings); record into ``out/bag``.

    Returns the summary figures, the map and the robot's path for the picture.
    """
    bag_path = out / "bag"
    if bag_path.exists():
        shutil.rmtree(bag_path)
    out.mkdir(parents=True, exist_ok=True)
    overrides = [Parameter("source", value="simulator"), Parameter("scene", value=scene),
                 Parameter("layout", value=layout), Parameter("loops", value=laps), Parameter("seed", value=seed)]
    recorder = _start_recorder(bag_path, layout)
    rclpy.init()
    try:
        nodes = [cls(parameter_overrides=overrides) for cls in NODES]
        compose(nodes)
        driver, localiser, classifier, mapper = nodes
        total = pings or driver.pings_per_lap * laps
        listener = SonarNode("demo_listener")  # no QoS event handlers: the executor keeps its direct path
        found, truth = {}, {}
        listener.create_subscription(LandmarkArray, "landmarks", lambda m: found.__setitem__(_stamp_key(m), m),
                                     qos_profile_sensor_data)
        listener.create_subscription(LandmarkArray, "truth", lambda m: truth.__setitem__(_stamp_key(m), m), 100)
        executor = DirectExecutor()
        for node in [localiser, classifier, mapper, listener]:
            executor.add_node(node)
        _wait_for_recorder(listener, recorder, executor,
                           [absolute(topic.name) for topic in graph_topics(driver.layout)])
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
        snapshot = mapper.map.snapshot(min_observations=mapper.params["min_observations"])
        robot_path = np.tile(driver.scene.trajectory.poses(driver.layout.ping_rate)[1], (laps, 1))[:total] \
            if driver.scene.trajectory is not None else driver.scene.sensor_pose[None, :]
        return {
            **figures, "pings": total, "seconds": elapsed, "latency_ms": latency,
            "map": {CLASS_NAMES[c]: int(np.count_nonzero(snapshot.landmark_class == c)) for c in range(4)},
            "map_score": map_against_scene(snapshot, driver.scene),
            "snapshot": snapshot, "scene": driver.scene, "robot_path": robot_path, "bag": bag_path,
        }
    finally:
        rclpy.try_shutdown()
        if recorder.poll() is None:
            recorder.terminate()
            recorder.wait()


def _score(found: dict, truth: dict) -> dict:
    """Landmarks per class, accuracy of the decided ones, position error: the pings with both messages."""
    pairs = [(landmarks_from_msg(found[k]), landmarks_from_msg(truth[k])) for k in found if k in truth]
    classes = np.concatenate([f.landmark_class for f, _ in pairs] + [np.empty(0, np.uint8)])
    true_classes = np.concatenate([t.landmark_class[f.echo] for f, t in pairs] + [np.empty(0, np.uint8)])
    error = np.concatenate([np.linalg.norm(f.position - t.position[f.echo], axis=1) for f, t in pairs]
                           + [np.empty(0)])
    decided = classes != UNKNOWN
    return {
        "landmarks": int(classes.size),
        "per_class": {CLASS_NAMES[c]: int(np.count_nonzero(classes == c)) for c in range(4)},
        "decided_correct": float(np.mean(classes[decided] == true_classes[decided])) if decided.any() else None,
        "error_percentiles": tuple(np.percentile(error, [50, 95]).tolist()) if error.size else None,
    }


def _distance_to_segments(points, segments) -> np.ndarray:
    """Distance of each point (P, 2) to each segment (S, 2, 2), shape (P, S), m."""
    start, along = segments[:, 0], segments[:, 1] - segments[:, 0]
    offset = points[:, None, :] - start[None, :, :]
    t = np.clip(np.sum(offset * along, axis=-1) / np.maximum(np.sum(along * along, axis=-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(offset - t[..., None] * along, axis=-1)


def map_against_scene(snapshot, scene) -> dict:
    """Per decided class of the map: (entries within :data:`MATCH_DISTANCE` of a true reflector of it, entries).

    A wall is right when both ends of its extent lie on one true wall; a corner
    or an edge when the nearest true corner or edge is of its class.
    """
    score = {}
    walls = snapshot.select(snapshot.landmark_class == PLANE)
    if len(walls) and len(scene.walls):
        near = np.maximum(*(_distance_to_segments(walls.segment[:, end], scene.walls) for end in (0, 1)))
        score["plane"] = (int(np.count_nonzero(near.min(axis=1) <= MATCH_DISTANCE)), len(walls))
    elif len(walls):
        score["plane"] = (0, len(walls))
    true_points = np.concatenate([scene.corner_point.reshape(-1, 2), scene.edges.reshape(-1, 2)])
    true_class = np.repeat([CORNER, EDGE], [len(scene.corner_point), len(scene.edges)])
    for code in (CORNER, EDGE):
        points = snapshot.select(snapshot.landmark_class == code)
        if not len(points):
            continue
        right = 0
        if len(true_points):
            distance = np.linalg.norm(points.position[:, None, :] - true_points[None, :, :], axis=-1)
            nearest = distance.argmin(axis=1)
            right = int(np.count_nonzero((distance.min(axis=1) <= MATCH_DISTANCE) & (true_class[nearest] == code)))
        score[CLASS_NAMES[code]] = (right, len(points))
    return score


def summary_text(figures: dict) -> str:
    """The printed summary."""
    lines = [
        f"sonar_ring demo: {figures['pings']} pings in {figures['seconds']:.1f} s",
        "  landmarks per class: " + ", ".join(f"{n} {name}" for name, n in figures["per_class"].items()),
        "  classification: " + (f"{100 * figures['decided_correct']:.1f} % of decided landmarks correct"
                                if figures["decided_correct"] is not None else "no decisions"),
        "  position error: " + ("no landmarks" if figures["error_percentiles"] is None else
                                "median {:.1f} mm, 95th percentile {:.1f} mm".format(
                                    *(1e3 * e for e in figures["error_percentiles"]))),
        "  compute per ping (median): "
        + ", ".join(f"{name} {ms:.2f} ms" for name, ms in figures["latency_ms"].items()),
        "  map: " + ", ".join(f"{n} {name}" for name, n in figures["map"].items()),
        "  map vs scene: " + (", ".join(f"{right} of {n} {name}" for name, (right, n) in figures["map_score"].items())
                              + f" at a true reflector of their class (within {100 * MATCH_DISTANCE:g} cm)"
                              if figures["map_score"] else "no plane, corner or edge mapped"),
    ]
    return "\n".join(lines)


def write_outputs(figures: dict, out: Path) -> str:
    """``map.png`` and ``summary.txt`` in ``out``; returns the summary with the list of outputs."""
    from sonar_ring import plot  # matplotlib only here, after the run

    found = ", ".join(f"{n} {name}" for name, n in figures["map"].items() if n)
    plot.save_map_png(out / "map.png", figures["scene"], figures["robot_path"], figures["snapshot"],
                      f"{figures['scene'].name}: map after {figures['pings']} pings ({found or 'empty'})")
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
    parser.add_argument("--out", type=Path, default=Path("demo_output"), help="output folder (default: demo_output)")
    args = parser.parse_args(argv)
    try:
        figures = run(args.scene, args.layout, args.laps, args.seed, args.out, args.pings)
        print(write_outputs(figures, args.out))
    except (*CONFIG_ERRORS, ValueError, OSError, RuntimeError) as error:
        print(f"demo: error: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
