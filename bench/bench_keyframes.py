"""What SLAM's keyframes buy and cost: the mapper's time per ping against the map's and the pose's errors.

Regenerate ``bench/results/keyframes.md`` (about ten minutes on 2 cores):

    source tools/env.sh && python bench/bench_keyframes.py   # from the repository root

The mapper as it ships (:class:`~sonar_ring.map_builder.MapBuilder`: SLAM and the echo tests) makes a
keyframe every ``slam.keyframe_distance`` of travel or ``slam.keyframe_turn`` of turn, and its smoother
keeps the keyframes of the last ``slam.smoother_lag`` seconds (:class:`~sonar_ring.slam.SlamSettings`); a
keyframe is the costly ping (the smoother's update over its window, the sightings' factors, the air's fit),
the pings between ride on the odometry since it.  This script maps the same runs with each setting of
:data:`SETTINGS` (the spacing's travel in m and turn in rad alike, the rest as it ships): the map
benchmark's realistic runs (``sonar-ring bench --map``: three laps of the room, the
realistic world, seeds 0 up), each run simulated and labelled once, its mappers fed side by side ping by
ping (each first on every other ping), so the time ratios hold on a busy machine (the times themselves,
six mappers in a process and a run on each core, are above one mapper's alone).  Scored by
:func:`sonar_ring.score.score_map` and :func:`~sonar_ring.score.trajectory_error` against the truth.
"""

from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from sonar_ring import pipeline, slam
from sonar_ring.benchmark import worlds
from sonar_ring.benchmark.environment import machine, revision, today, write_report
from sonar_ring.explain import EchoTests
from sonar_ring.geometry import load_layout
from sonar_ring.landmarks import Landmarks
from sonar_ring.map_builder import MapBuilder, MapperSettings
from sonar_ring.ping_stage import Counts, PingStage
from sonar_ring.score import score_map, trajectory_error
from sonar_ring.simulate import load_scene

ROOT = Path(__file__).resolve().parents[1]
RESULT = ROOT / "bench" / "results" / "keyframes.md"
SHIPPED = (slam.SlamSettings().keyframe_distance, slam.SlamSettings().keyframe_turn, slam.SlamSettings().smoother_lag)
SETTINGS = ((0.05, 0.05, SHIPPED[2]), SHIPPED, (0.15, 0.15, SHIPPED[2]), (0.2, 0.2, SHIPPED[2]),
            (*SHIPPED[:2], 2.5), (*SHIPPED[:2], 1.5))
"""``(keyframe_distance m, keyframe_turn rad, smoother_lag s)`` compared: spacings, then windows; the shipped
one second."""


def one_run(seed: int, laps: int) -> list[dict]:
    """One realistic run mapped with each setting: per setting its keyframes, per-ping times (s) and scores."""
    recorded = worlds.simulate_run("realistic", seed, laps)
    layout = load_layout(worlds.LAYOUT)
    stage = PingStage(layout, pipeline.Settings(sigma_speed=pipeline.ROBOT_SIGMA_SPEED))
    stage.load_kernels()
    slam.load_kernels()
    labelled = [stage.label(echoes)[1] if echoes is not None else Landmarks.empty() for echoes in recorded.echoes]
    builders = [MapBuilder(MapperSettings(pose_history=None, layout=layout, echo_tests=EchoTests(),
                                          slam_settings=replace(slam.SlamSettings(), keyframe_distance=distance,
                                                                keyframe_turn=turn, smoother_lag=lag)), Counts())
                for distance, turn, lag in SETTINGS]
    keyframes = [0] * len(SETTINGS)
    for index, builder in enumerate(builders):  # count the keyframes as SLAM's reports of the pings say
        def counted(*args, index=index, add_ping=builder.slam.add_ping, **kwargs):
            report = add_ping(*args, **kwargs)
            keyframes[index] += report.keyframe
            return report

        builder.slam.add_ping = counted
    times = [[] for _ in SETTINGS]
    poses = [[] for _ in SETTINGS]
    for k, (landmarks, odometry) in enumerate(zip(labelled, recorded.odometry, strict=True)):
        stamp = int(round(1e9 * (1.0 + k / layout.ping_rate)))
        order = range(len(SETTINGS)) if k % 2 == 0 else reversed(range(len(SETTINGS)))
        for index in order:
            builder = builders[index]
            builder.add_odometry(stamp, odometry)
            started = time.perf_counter()
            builder.add_ping(stamp, landmarks)
            times[index].append(time.perf_counter() - started)
            poses[index].append(builder.robot_pose)
    scene = load_scene(worlds.SCENE)
    runs = []
    for builder, count, spent, estimate in zip(builders, keyframes, times, poses, strict=True):
        score = score_map(builder.snapshot(), scene, recorded.heard)
        rms, final = trajectory_error(np.array(estimate), recorded.truth)
        runs.append(dict(keyframes=count, times=np.array(spent), complete=score.complete,
                         ghosts=score.ghosts, wrong=score.wrong, point_error=np.median(score.point_error),
                         rms=rms, final=final))
    return runs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=8, help="realistic seeds (default 8)")
    parser.add_argument("--laps", type=int, default=worlds.LAPS, help=f"laps a run (default {worlds.LAPS})")
    parser.add_argument("--output", type=Path, default=RESULT, help="Markdown file to write")
    args = parser.parse_args()
    host, started = machine(), time.perf_counter()
    with ProcessPoolExecutor(len(os.sched_getaffinity(0)), mp_context=get_context("fork")) as pool:
        runs = list(pool.map(one_run, range(args.seeds), [args.laps] * args.seeds))
    shipped = SETTINGS.index(SHIPPED)
    shipped_total = np.array([run[shipped]["times"].sum() for run in runs])
    lines = [
        "# SLAM's keyframes, their spacing and the smoother's window: the mapper's time against the map's errors",
        "",
        "Regenerate: `python bench/bench_keyframes.py` (from the repository root, after `source tools/env.sh`)",
        "",
        f"Machine: {host}.  Revision {revision(ROOT)}, {today()}.",
        "",
        f"The map benchmark's realistic runs ({args.laps} laps of `{worlds.SCENE}`, seeds 0-{args.seeds - 1}), each "
        "mapped by the mapper as it ships (SLAM and the echo tests) with a keyframe every *spacing* of travel (m) "
        "or of turn (rad) and the smoother keeping the keyframes of the last *window* seconds, the mappers side by "
        "side on every ping.  *Keyframes* a run (mean); the mapper's update "
        "a ping, median and p99 over every ping of every run (ms); *time*: each run's total against the shipped "
        "setting's in the same run (median over the runs); *complete*: runs with every heard reflector mapped "
        "once with its class and nothing else (`sonar_ring.score`); *ghosts* and *wrong* entries summed over the "
        "runs; *point error*: each run's median corner and edge error, median over the runs; the pose's error "
        "against the truth, RMS over a run (median and worst run) and at its end (worst run).  Two runs at once, "
        "one a core, six mappers in each: the times are above those of one mapper alone (`sonar-ring bench "
        "--slam-cost`); their ratios are the result.",
        "",
        "| spacing | window | keyframes | update median / p99 | time | complete | ghosts | wrong | point error "
        "| pose RMS: median / worst | final: worst |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for index, (distance, turn, lag) in enumerate(SETTINGS):
        mine = [run[index] for run in runs]
        spent = 1e3 * np.concatenate([run["times"] for run in mine])
        ratio = np.median(np.array([run["times"].sum() for run in mine]) / shipped_total)
        label = f"{distance:g} m, {turn:g} rad | {lag:g} s" + (" (shipped)" if index == shipped else "")
        lines.append(
            f"| {label} | {np.mean([run['keyframes'] for run in mine]):.0f} "
            f"| {np.median(spent):.2f} / {np.percentile(spent, 99):.2f} ms | ×{ratio:.2f} "
            f"| {sum(run['complete'] for run in mine)} of {len(mine)} | {sum(run['ghosts'] for run in mine)} "
            f"| {sum(run['wrong'] for run in mine)} | {1e3 * np.median([run['point_error'] for run in mine]):.1f} mm "
            f"| {1e3 * np.median([run['rms'] for run in mine]):.1f} / {1e3 * max(run['rms'] for run in mine):.1f} mm "
            f"| {1e3 * max(run['final'] for run in mine):.1f} mm |")
        print(lines[-1], flush=True)
    write_report(args.output, lines, started)


if __name__ == "__main__":
    main()
