"""What carrying only an echo's still-possible landmark saves per ping: markers and mapper, one landmark or all.

Regenerate ``bench/results/hypotheses.md`` (about ten minutes on 2 cores):

    source tools/env.sh && python bench/bench_hypotheses.py   # from the repository root

The localiser solves every enabled model for every echo row (plane, corner, edge: the evidence compares
them), then keeps one landmark per echo row: the decided class's, or the corner model's while the evidence
decides nothing (:func:`sonar_ring.pipeline.classify_ping`); the mapper works on those, the markers on the
landmarks published of them (:meth:`~sonar_ring.ping_stage.PingStage.publishable`: on a ring one per echo).
The other hypotheses go out on ``landmarks/raw`` only.  This script measures what the alternative would cost:
the same pings' markers (built and serialized, as the localiser publishes them) and the same mapper (as it ships:
SLAM and the echo tests, :class:`~sonar_ring.map_builder.MapBuilder`) fed every valid hypothesis instead, side
by side on every ping of the same run (each first on every other ping), so the ratios hold on a busy machine.
The demo's lap of the room in the realistic world (:mod:`sonar_ring.realism`), each layout's shipped
``sigma_tof``, scored by :func:`sonar_ring.score.score_map`.  Seeded; the timings vary with the machine's load.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from bench_triad_map import shipped_sigma_tof

from sonar_ring import pipeline
from sonar_ring.benchmark.environment import machine, revision, today, write_report
from sonar_ring.explain import EchoTests
from sonar_ring.geometry import load_layout
from sonar_ring.landmarks import Landmarks
from sonar_ring.map_builder import MapBuilder, MapperSettings
from sonar_ring.ping_stage import Counts, PingStage, check_ping
from sonar_ring.realism import REALISTIC, World
from sonar_ring.ros.convert import MessageHeader, Stamp
from sonar_ring.ros.markers import landmark_markers, serialize_markers
from sonar_ring.score import score_map
from sonar_ring.simulate import DIRECT, Noise, load_scene

ROOT = Path(__file__).resolve().parents[1]
RESULT = ROOT / "bench" / "results" / "hypotheses.md"
SCENE = "room"
LAYOUTS = ("browne_ring", "barshan_kuc_array", "kreczmer_two_triads")
MARKER_LIFETIME = 0.5
"""s, the localiser's default ``marker_lifetime``."""


def one_lap(layout_name: str, seed: int) -> dict:
    """One realistic lap of the room: per ping counts and times, carried (one per echo) against all hypotheses."""
    scene, layout = load_scene(SCENE), load_layout(layout_name)
    sigma_tof = shipped_sigma_tof(layout_name)
    world = World(scene, layout, REALISTIC, noise=Noise(tof=sigma_tof, amplitude=0.02), seed=seed)
    stage = PingStage(layout, pipeline.Settings(sigma_tof=sigma_tof, sigma_speed=pipeline.ROBOT_SIGMA_SPEED))
    stage.load_kernels()
    builders = {way: MapBuilder(MapperSettings(pose_history=None, layout=layout, echo_tests=EchoTests()), Counts())
                for way in ("carried", "all")}
    header = MessageHeader(Stamp(1, 0), "sonar_ring")
    counts = {key: [] for key in ("rows", "solved", "valid", "carried", "published")}
    times = {"label": [], **{f"{step} {way}": [] for step in ("markers", "mapper") for way in ("carried", "all")}}
    heard = set()
    for k, pose in enumerate(scene.trajectory.poses(layout.ping_rate)[1]):
        ping = world.ping(pose, k / layout.ping_rate)
        stamp = 10**9 + round(1e9 * k / layout.ping_rate)
        for builder in builders.values():
            builder.add_odometry(stamp, world.odometry_pose(pose))
        complete = (ping.truth_origin == DIRECT) & np.isfinite(ping.tof).all(axis=1)
        heard.update(ping.truth_reflector[complete].tolist())
        usable = check_ping(ping.echoes, layout, Counts(), stamp)
        if usable is None:
            for builder in builders.values():
                builder.add_ping(stamp, Landmarks.empty())
            continue
        started = time.perf_counter()
        hypotheses, carried = stage.label(usable)
        published = stage.publishable(usable, carried)
        times["label"].append(time.perf_counter() - started)
        landmarks = {"carried": carried, "all": hypotheses.select(hypotheses.valid)}
        drawn = {"carried": published, "all": landmarks["all"]}
        for key, value in (("rows", usable.n_echoes), ("solved", len(hypotheses)),
                           ("valid", len(landmarks["all"])), ("carried", len(carried)), ("published", len(published))):
            counts[key].append(value)
        # Alternate which goes first: the second call of a ping runs on warm caches.
        for way in ("carried", "all") if k % 2 == 0 else ("all", "carried"):
            chosen = landmarks[way]
            started = time.perf_counter()
            serialize_markers(landmark_markers(drawn[way], "landmarks", MARKER_LIFETIME), header)
            times[f"markers {way}"].append(time.perf_counter() - started)
            started = time.perf_counter()
            builders[way].add_ping(stamp, chosen)
            times[f"mapper {way}"].append(time.perf_counter() - started)
    truth = np.array(sorted(heard), dtype=int)
    scores = {way: score_map(builder.snapshot(), scene, truth) for way, builder in builders.items()}
    return dict(counts={key: np.array(value) for key, value in counts.items()},
                times={key: np.array(value) for key, value in times.items()},
                entries={way: score.entries for way, score in scores.items()},
                ghosts={way: score.ghosts for way, score in scores.items()})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=3, help="realistic seeds per layout (default 3)")
    parser.add_argument("--output", type=Path, default=RESULT, help="Markdown file to write")
    args = parser.parse_args()
    host, started = machine(), time.perf_counter()
    lines = [
        "# What carrying one landmark per echo saves per ping",
        "",
        "Regenerate: `python bench/bench_hypotheses.py` (from the repository root, after `source tools/env.sh`)",
        "",
        f"Machine: {host}.  Revision {revision(ROOT)}, {today()}.",
        "",
        f"The demo's lap of `{SCENE}`, realistic world, seeds 0-{args.seeds - 1} per layout, every ping.  Per ping "
        "(mean): *echo rows* the localiser takes, *solved* hypotheses (a row per echo and model), *valid* ones, "
        "*carried*: the labelled landmarks (one per echo row with a valid hypothesis), *published*: those on "
        "`landmarks` (one per echo).  Times per ping (median, ms): *label* (localise, classify and publish, the "
        "work both ways share), the markers (built and serialized) of the published landmarks and the mapper as "
        "it ships (SLAM and the echo tests) fed the carried ones, and the same two fed every valid hypothesis "
        "(*all*), on the same pings in the same run, each first on every other ping.  "
        "*Entries / ghosts*: the map after the lap (`sonar_ring.score`), median over the seeds.",
        "",
        "| layout | echo rows | solved | valid | carried | published | label | markers: published / all "
        "| mapper: carried / all | mapper × | entries: carried / all | ghosts: carried / all |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for layout_name in LAYOUTS:
        runs = [one_lap(layout_name, seed) for seed in range(args.seeds)]
        count = {key: np.concatenate([run["counts"][key] for run in runs]).mean() for key in runs[0]["counts"]}
        median = {key: 1e3 * np.median(np.concatenate([run["times"][key] for run in runs]))
                  for key in runs[0]["times"]}
        entries = {way: np.median([run["entries"][way] for run in runs]) for way in ("carried", "all")}
        ghosts = {way: np.median([run["ghosts"][way] for run in runs]) for way in ("carried", "all")}
        lines.append(
            f"| {layout_name} | {count['rows']:.1f} | {count['solved']:.1f} | {count['valid']:.1f} "
            f"| {count['carried']:.1f} | {count['published']:.1f} | {median['label']:.2f} "
            f"| {median['markers carried']:.2f} / {median['markers all']:.2f} "
            f"| {median['mapper carried']:.2f} / {median['mapper all']:.2f} "
            f"| ×{median['mapper all'] / median['mapper carried']:.1f} "
            f"| {entries['carried']:g} / {entries['all']:g} | {ghosts['carried']:g} / {ghosts['all']:g} |")
        print(lines[-1], flush=True)
    write_report(args.output, lines, started)


if __name__ == "__main__":
    main()
