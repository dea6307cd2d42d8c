"""Throughput of the scene simulator's forward model (`sonar_ring.simulate`).

Regenerate ``bench/results/simulate.md`` (under a minute on one core):

    source tools/env.sh && python bench/bench_simulate.py   # from the repository root

Each case simulates one lap of the room scene's trajectory (sampled at the
layout's ping rate) with the paper-level noise of the ``sonar-ring simulate``
defaults plus 1 us of TOF noise, ``repeats`` times; the table gives the best
and the median lap, and pings per CPU-second (less sensitive to other jobs).
Timings depend on the machine and on its load, which the file records.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from sonar_ring.benchmark.environment import machine
from sonar_ring.geometry import load_layout
from sonar_ring.simulate import Noise, Simulator, load_scene

ROOT = Path(__file__).resolve().parents[1]

RESULT = ROOT / "bench" / "results" / "simulate.md"
NOISE = Noise(tof=1e-6, amplitude=0.02)
CASES = [  # scene, layout; the first is the headline figure
    ("room", "browne_ring"),
    ("room", "barshan_kuc_pair"),
    ("room", "barshan_kuc_array"),
    ("room", "kreczmer_triad"),
    ("single_wall", "browne_ring"),
]


def measure(scene_name: str, layout_name: str, repeats: int) -> dict:
    scene, layout = load_scene(scene_name), load_layout(layout_name)
    simulator = Simulator(scene, layout)
    room = load_scene("room")  # every case drives the room's lap, so the pose sets match
    times, poses = room.trajectory.poses(layout.ping_rate)
    laps, cpu, echoes = [], [], 0
    for repeat in range(repeats):
        rng = np.random.default_rng(repeat)
        start, start_cpu = time.perf_counter(), time.process_time()
        pings = simulator.run(poses, times, noise=NOISE, rng=rng)
        laps.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
        echoes = sum(p.n_echoes for p in pings)
    laps = np.array(laps)
    reflectors = scene.n_reflectors
    paths = reflectors * layout.n_groups * layout.group_transmitters.shape[1] * layout.receivers_per_group
    return dict(scene=scene_name, layout=layout_name, pings=len(poses), reflectors=reflectors, paths=paths,
                echoes=echoes / len(poses), best=len(poses) / laps.min(), median=len(poses) / np.median(laps),
                cpu=len(poses) / np.median(cpu))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="laps per case (default 5)")
    parser.add_argument("--output", type=Path, default=RESULT, help="Markdown file to write")
    args = parser.parse_args()
    host = machine()
    rows = [measure(scene, layout, args.repeats) for scene, layout in CASES]
    head = rows[0]
    lines = [
        "# Scene simulator throughput -- `sonar_ring.simulate`",
        "",
        "Regenerate: `python bench/bench_simulate.py` (from the repository root, after `source tools/env.sh`)",
        "",
        f"Machine: {host}; single process.",
        "",
        f"Headline: **{head['median']:.0f} pings/s** (median lap; best {head['best']:.0f}; "
        f"{head['cpu']:.0f} per CPU-second) for the room scene with Browne's 48-pair ring, "
        f"{head['echoes']:.1f} echoes per ping.",
        "",
        "Each case: one lap of the room's trajectory (`config/scenes/room.yaml`, 0.3 m/s) sampled at the layout's "
        f"ping rate, {args.repeats} laps, noise sigma_t = 1 us and sigma_A = 0.02 A_max from seeded generators. "
        "`paths` = reflectors x groups x transmitters per group x receivers per group: the (reflector, "
        "transmitter, receiver) combinations the model evaluates per ping.",
        "",
        "| scene | layout | pings per lap | reflectors | paths | echoes / ping | pings/s (median) | pings/s (best) "
        "| pings per CPU-s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['layout']} | {r['pings']} | {r['reflectors']} | {r['paths']} | "
                     f"{r['echoes']:.1f} | {r['median']:.0f} | {r['best']:.0f} | {r['cpu']:.0f} |")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
