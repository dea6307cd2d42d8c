"""demo: the whole graph on a simulated scene for one lap, then a summary.

Runs driver (simulator source) -> localiser -> classifier -> mapper in one
process, follows the ping stream with a progress bar, and prints what was found
against the simulator's ground truth: landmarks per class, classification
accuracy of the decided ones, position error, and per-ping compute time.

    demo [--scene room] [--layout browne_ring] [--laps 1] [--seed 0]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data

from sonar_ring.landmarks import CLASS_NAMES, UNKNOWN
from sonar_ring.msg import LandmarkArray
from sonar_ring.ros.convert import landmarks_from_msg
from sonar_ring.ros.graph import NODES

CHI2_2DOF_3SIGMA = 11.83


def _progress(done: int, total: int, width: int = 40) -> None:
    filled = int(width * done / max(total, 1))
    sys.stderr.write(f"\r  pings [{'#' * filled}{'.' * (width - filled)}] {done}/{total}")
    sys.stderr.flush()


def run(scene: str, layout: str, laps: int, seed: int) -> dict:
    """Run the graph for ``laps`` of the scene's trajectory; return the summary figures."""
    overrides = [Parameter("source", value="simulator"), Parameter("scene", value=scene),
                 Parameter("layout", value=layout), Parameter("loops", value=laps), Parameter("seed", value=seed)]
    rclpy.init()
    try:
        nodes = [cls(parameter_overrides=overrides) for cls in NODES]
        driver, localiser, classifier, mapper = nodes
        listener = rclpy.create_node("demo_listener")
        found, truth = {}, {}

        def key(msg):
            return msg.header.stamp.sec, msg.header.stamp.nanosec

        listener.create_subscription(LandmarkArray, "landmarks", lambda m: found.__setitem__(key(m), m),
                                     qos_profile_sensor_data)
        listener.create_subscription(LandmarkArray, "truth", lambda m: truth.__setitem__(key(m), m), 100)
        executor = SingleThreadedExecutor()
        for node in [*nodes, listener]:
            executor.add_node(node)
        total = driver.pings_per_lap * laps
        started = time.monotonic()
        shown = -1
        while driver.pings_published < total:
            executor.spin_once(timeout_sec=0.05)
            if driver.pings_published != shown:
                shown = driver.pings_published
                _progress(shown, total)
        drain = time.monotonic() + 1.0
        while time.monotonic() < drain:
            executor.spin_once(timeout_sec=0.02)
        sys.stderr.write("\n")
        elapsed = time.monotonic() - started
        pairs = [(landmarks_from_msg(found[k]), landmarks_from_msg(truth[k])) for k in found if k in truth]
        classes = np.concatenate([f.landmark_class for f, _ in pairs])
        true_classes = np.concatenate([t.landmark_class[f.echo] for f, t in pairs])
        error = np.concatenate([np.linalg.norm(f.position - t.position[f.echo], axis=1) for f, t in pairs])
        latency = {node.get_name(): float(np.median(node.health.latencies())) * 1e3 for node in nodes}
        decided = classes != UNKNOWN
        snapshot = mapper.map.snapshot(min_observations=2)
        return {
            "pings": total, "seconds": elapsed, "landmarks": int(classes.size),
            "per_class": {CLASS_NAMES[c]: int(np.count_nonzero(classes == c)) for c in range(4)},
            "decided_correct": float(np.mean(classes[decided] == true_classes[decided])) if decided.any() else None,
            "error_median": float(np.median(error)), "error_p95": float(np.percentile(error, 95)),
            "latency_ms": latency,
            "map": {CLASS_NAMES[c]: int(np.count_nonzero(snapshot.landmark_class == c)) for c in range(4)},
        }
    finally:
        rclpy.try_shutdown()


def summary_text(figures: dict) -> str:
    """The printed summary."""
    lines = [
        f"sonar_ring demo: {figures['pings']} pings in {figures['seconds']:.1f} s",
        "  landmarks per class: " + ", ".join(f"{n} {name}" for name, n in figures["per_class"].items()),
        "  classification: " + (f"{100 * figures['decided_correct']:.1f} % of decided landmarks correct"
                                if figures["decided_correct"] is not None else "no decisions"),
        f"  position error: median {1e3 * figures['error_median']:.1f} mm, "
        f"95th percentile {1e3 * figures['error_p95']:.1f} mm",
        "  compute per ping (median): "
        + ", ".join(f"{name} {ms:.2f} ms" for name, ms in figures["latency_ms"].items()),
        "  map: " + ", ".join(f"{n} {name}" for name, n in figures["map"].items()),
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    """Parse the arguments, run, print the summary."""
    parser = argparse.ArgumentParser(prog="demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="room", help="scene name or YAML path (default: room)")
    parser.add_argument("--layout", default="browne_ring", help="layout name or YAML path (default: browne_ring)")
    parser.add_argument("--laps", type=int, default=1, help="laps of the scene trajectory (default: 1)")
    parser.add_argument("--seed", type=int, default=0, help="noise seed (default: 0)")
    args = parser.parse_args(argv)
    print(summary_text(run(args.scene, args.layout, args.laps, args.seed)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
