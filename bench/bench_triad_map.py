"""Kreczmer triads on the room's lap: which walls they can hear, and the map one lap gives.

Regenerate ``bench/results/triad_map.md`` (a few minutes):

    source tools/env.sh && python bench/bench_triad_map.py   # from the repository root

A triad's ping names no class (its emitter sits within 7.5 mm of its receivers), so what its map decides,
motion decides: a wall becomes a wall once its foot points slide along it, which they do only while the
robot passes the wall, not while it drives straight at it.  A triad hears a wall only near the wall's normal
(its receivers' beam, 60 deg either side).  Two parts:

* **What the mounts can hear**: the demo's lap of ``config/scenes/room.yaml`` in the ideal world, every ping's
  direct echoes by the simulator's truth: per wall, the pings that heard it and how far its foot points slid
  (the extent motion can see).  For one module, turned from the robot's heading by each of a few angles, and
  for ``kreczmer_two_triads`` (one module either side, turned +-60 deg).
* **One lap's map**: the mapper as it ships (SLAM and the echo tests, :class:`~sonar_ring.map_builder.MapBuilder`)
  on one lap in the ideal and the realistic world (:mod:`sonar_ring.realism`), the TOF noise and the
  localiser's ``sigma_tof`` those of the layout's shipped parameters (``config/params/<layout>.yaml``),
  scored by :func:`sonar_ring.score.score_map`.  Seeded: a rerun on the same versions gives the same file but
  for the date and the revision.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import yaml

from sonar_ring import pipeline
from sonar_ring.benchmark.environment import machine, revision, today, write_report
from sonar_ring.explain import EchoTests
from sonar_ring.geometry import config_path, load_layout
from sonar_ring.landmarks import CORNER, CORNER_OR_EDGE, EDGE, PLANE, Landmarks
from sonar_ring.map_builder import MapBuilder, MapperSettings
from sonar_ring.ping_stage import Counts, PingStage, check_ping
from sonar_ring.realism import IDEAL, REALISTIC, World
from sonar_ring.score import score_map, trajectory_error
from sonar_ring.simulate import DIRECT, Noise, Simulator, load_scene

ROOT = Path(__file__).resolve().parents[1]
RESULT = ROOT / "bench" / "results" / "triad_map.md"
SCENE = "room"
LAYOUTS = ("kreczmer_triad", "kreczmer_two_triads")
MOUNTS_DEG = (0.0, -45.0, -60.0, -90.0, 60.0, 90.0)
"""One module's turns from the robot's heading (the robot drives the lap anticlockwise: the room's walls lie to its
right, the pillar to its left)."""
WORLDS = {"ideal": IDEAL, "realistic": REALISTIC}
SLID_M = 0.3
"""m: a wall whose foot points slid this far along it is one motion can tell from a point."""


def shipped_sigma_tof(layout_name: str) -> float:
    """The localiser's ``sigma_tof`` in the layout's shipped parameters, s (the simulator driver's too)."""
    values = yaml.safe_load(config_path("params", layout_name).read_text())
    return float(values["/**/localiser"]["ros__parameters"]["sigma_tof"])


def hearing(layout, scene, mount: float) -> dict:
    """Per wall name, ``(pings, slide)``: pings of a lap that heard it directly, how far (m) its foot points spread.

    The sensor is turned ``mount`` (rad) from the robot's heading.
    """
    simulator = Simulator(scene, layout)
    walls = np.flatnonzero(scene.reflector_class == PLANE)
    foot = {int(wall): [] for wall in walls}
    for pose in scene.trajectory.poses(layout.ping_rate)[1]:
        sensor = pose + (0.0, 0.0, mount)
        ping = simulator.ping(sensor)
        c, s = math.cos(sensor[2]), math.sin(sensor[2])
        heard = (ping.truth_origin == DIRECT) & np.isin(ping.truth_reflector, walls)
        for reflector in np.unique(ping.truth_reflector[heard]):
            points = ping.truth_position[heard & (ping.truth_reflector == reflector)]
            foot[int(reflector)].append(points[0] @ np.array([[c, s], [-s, c]]) + sensor[:2])
    return {scene.reflector_names[wall]: (len(points), float(np.ptp(np.array(points), axis=0).max()) if points
                                          else 0.0) for wall, points in foot.items()}


def one_lap(layout_name: str, world: str, seed: int) -> dict:
    """The shipped mapper on one lap of the room, seed ``seed``: the score and the pose error."""
    scene, layout = load_scene(SCENE), load_layout(layout_name)
    sigma_tof = shipped_sigma_tof(layout_name)
    model = World(scene, layout, WORLDS[world], noise=Noise(tof=sigma_tof, amplitude=0.02), seed=seed)
    stage = PingStage(layout, pipeline.Settings(sigma_tof=sigma_tof, sigma_speed=pipeline.ROBOT_SIGMA_SPEED))
    builder = MapBuilder(MapperSettings(pose_history=None, layout=layout, echo_tests=EchoTests()), Counts())
    truth, estimate, heard = [], [], set()
    for k, pose in enumerate(scene.trajectory.poses(layout.ping_rate)[1]):
        ping = model.ping(pose, k / layout.ping_rate)
        stamp = 10**9 + round(1e9 * k / layout.ping_rate)
        builder.add_odometry(stamp, model.odometry_pose(pose))
        usable = check_ping(ping.echoes, layout, Counts(), stamp)
        builder.add_ping(stamp, stage.label(usable)[1] if usable is not None else Landmarks.empty())
        complete = (ping.truth_origin == DIRECT) & np.isfinite(ping.tof).all(axis=1)
        heard.update(ping.truth_reflector[complete].tolist())
        truth.append(pose)
        estimate.append(builder.robot_pose)
    snapshot = builder.snapshot()
    score = score_map(snapshot, scene, np.array(sorted(heard), dtype=int))
    return dict(walls=score.per_class["plane"].mapped, walls_heard=score.per_class["plane"].heard,
                claimed=int(np.isin(snapshot.landmark_class, (CORNER, EDGE)).sum()),
                fixed=int(np.count_nonzero(snapshot.landmark_class == CORNER_OR_EDGE)), ghosts=score.ghosts,
                misplaced=score.total("misplaced"),
                trajectory=trajectory_error(np.array(estimate), np.array(truth)))


def _spread(values) -> str:
    """Median [min, max] of counts over runs."""
    values = np.array(values)
    return f"{np.median(values):g} [{values.min()}, {values.max()}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=10, help="realistic seeds per layout (default 10)")
    parser.add_argument("--output", type=Path, default=RESULT, help="Markdown file to write")
    args = parser.parse_args()
    host, started = machine(), time.perf_counter()
    scene = load_scene(SCENE)
    names = [scene.reflector_names[i] for i in np.flatnonzero(scene.reflector_class == PLANE)]
    mounts = [(f"kreczmer_triad turned {mount:+.0f} deg", load_layout("kreczmer_triad"), math.radians(mount))
              for mount in MOUNTS_DEG] + [("kreczmer_two_triads", load_layout("kreczmer_two_triads"), 0.0)]
    lines = [
        "# Kreczmer triads on the room's lap: the walls they can hear, and one lap's map",
        "",
        "Regenerate: `python bench/bench_triad_map.py` (from the repository root, after `source tools/env.sh`)",
        "",
        f"Machine: {host}.  Revision {revision(ROOT)}, {today()}.",
        "",
        f"## What the mounts can hear (ideal world, the simulator's truth, one lap of `{SCENE}`)",
        "",
        f"Per wall: pings that heard it directly / how far its foot points slid (m).  *Passed*: walls whose foot "
        f"points slid {SLID_M} m or more, which motion can tell from a point.",
        "",
        "| sensor | passed, of 10 | " + " | ".join(names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    for label, layout, mount in mounts:
        heard = hearing(layout, scene, mount)
        passed = sum(slide >= SLID_M for _, slide in heard.values())
        lines.append(f"| {label} | {passed} | " + " | ".join(
            f"{heard[name][0]} / {heard[name][1]:.2f}" if heard[name][0] else "—" for name in names) + " |")
        print(label, "done", flush=True)
    lines += [
        "",
        "## One lap's map (SLAM and the echo tests, as the mapper ships)",
        "",
        f"The ideal world with seed 0, the realistic world with seeds 0-{args.seeds - 1}; TOF noise and the "
        "localiser's `sigma_tof` from the layout's shipped parameters.  *Walls*: mapped right (within 5 cm and "
        "2 deg, `sonar_ring.score`), of the 10 and of those heard; *fixed points*: CORNER_OR_EDGE entries (a "
        "triad's corners and edges: its pings carry no curvature), *claimed*: entries named CORNER or EDGE; "
        "*ghosts*: entries near no reflector.  Median over the runs, [min, max].",
        "",
        "| layout | world | runs | walls mapped, of 10 | walls heard | fixed points | claimed CORNER or EDGE "
        "| ghosts | misplaced | pose error RMS / final |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for layout_name in LAYOUTS:
        for world, seeds in (("ideal", [0]), ("realistic", list(range(args.seeds)))):
            runs = [one_lap(layout_name, world, seed) for seed in seeds]
            spread = {key: _spread([run[key] for run in runs]) for key in
                      ("walls", "walls_heard", "fixed", "claimed", "ghosts", "misplaced")}
            rms = np.array([run["trajectory"][0] for run in runs])
            final = np.array([run["trajectory"][1] for run in runs])
            lines.append(f"| {layout_name} | {world} | {len(runs)} | {spread['walls']} | {spread['walls_heard']} "
                         f"| {spread['fixed']} | {spread['claimed']} | {spread['ghosts']} | {spread['misplaced']} "
                         f"| {100 * np.median(rms):.1f} / {100 * np.median(final):.1f} cm |")
            print(layout_name, world, "done", flush=True)
    write_report(args.output, lines, started)


if __name__ == "__main__":
    main()
