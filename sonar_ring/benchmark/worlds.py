"""``sonar-ring bench --map``: maps in the ideal world, with each realistic effect alone and in the realistic world.

Scored against the scene over many seeds.  For every world and seed, :func:`simulate_run` simulates ``laps`` laps of the
room with Browne's ring (σ_t = 1 µs, σ_A = 2 %; :class:`sonar_ring.realism.World`)
and keeps what a robot has -- the usable echoes of every ping and the wheel
odometry's pose -- beside the truth.  Every mapper of :data:`MAPPERS` then
builds its map from the same pings (``echoes`` -> :class:`sonar_ring.ping_stage.PingStage`
-> the mapper), and :func:`sonar_ring.score.score_map` scores the final map
against the reflectors the sensor heard.  Runs go to one process per CPU.

The report section lies between :data:`SECTION_BEGIN` and :data:`SECTION_END` of
``BENCHMARKS.md`` (``sonar-ring bench`` keeps it when it rewrites the rest), its
summary table between :data:`SUMMARY_BEGIN` and :data:`SUMMARY_END` of the README.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from sonar_ring import pipeline
from sonar_ring.benchmark import sections
from sonar_ring.benchmark.environment import machine, revision, today
from sonar_ring.explain import EchoTests
from sonar_ring.geometry import load_layout
from sonar_ring.landmarks import Landmarks
from sonar_ring.map_builder import MapBuilder, MapperSettings
from sonar_ring.ping_stage import Counts, PingStage, check_ping
from sonar_ring.realism import EFFECTS, IDEAL, REALISTIC, World
from sonar_ring.score import MapScore, score_map, trajectory_error
from sonar_ring.simulate import DIRECT, Noise, load_scene

SCENE = "room"
LAYOUT = "browne_ring"
NOISE = Noise(tof=1e-6, amplitude=0.02)
SEEDS = 20
"""Seeds of the ``realistic`` world, where the mapper's targets are set."""
EFFECT_SEEDS = 3
"""Seeds of each other world (ideal, one effect alone): where each effect's share of the failures is read."""
LAPS = 3
WORLDS = {"ideal": IDEAL, **{f"{effect} alone": REALISTIC.only(effect) for effect in EFFECTS},
          "realistic": REALISTIC}
"""The worlds of the study: ideal, each effect of the realistic profile alone, realistic."""

README_WORLDS = ("ideal", "spurious alone", "multipath alone", "realistic")
"""The worlds of the README's short table (the section in ``BENCHMARKS.md`` has them all)."""

SECTION_BEGIN = "<!-- sonar-ring bench --map: section -->"
SECTION_END = "<!-- /sonar-ring bench --map: section -->"
TITLE = "## Maps in a real robot's world"
SUMMARY_BEGIN = "<!-- sonar-ring bench --map: summary -->"
SUMMARY_END = "<!-- /sonar-ring bench --map: summary -->"


@dataclass
class Recorded:
    """What a robot had of one run (usable echoes, odometry) and the truth to score it against.

    Attributes
    ----------
    echoes : list of EchoArrays or None
        Each ping's screened echoes (None where nothing was usable).
    odometry, truth : ndarray, shape (P, 3)
        The wheel odometry's pose in ``odom`` and the true pose in the world, per ping.
    heard : ndarray of int
        The scene's reflectors with a direct echo heard by every receiver of its group.
    """

    echoes: list
    odometry: np.ndarray
    truth: np.ndarray
    heard: np.ndarray


@dataclass
class Outcome:
    """One mapper's result on one run.

    Attributes
    ----------
    score : MapScore
    trajectory : tuple of float
        RMS and final error of the mapper's pose estimate (the odometry for a mapper in ``odom``), m.
    label_ms, map_ms : ndarray
        Per ping: localisation and classification, and the mapper's update, ms.
    decision_m : ndarray
        Per point the map told an edge or a corner by its curvature: the distance driven from its first
        sighting to the decision, m (:meth:`~sonar_ring.mapping.LandmarkMap.decision_distances`).
    pose_covariance : ndarray, shape (P, 3, 3)
        Per ping, the covariance of the pose the mapper's echo tests take for it (SLAM's prediction from
        its latest keyframe and the odometry since; zero for a mapper in ``odom``), m^2, m rad, rad^2.
    """

    score: MapScore
    trajectory: tuple
    label_ms: np.ndarray = field(default_factory=lambda: np.empty(0))
    map_ms: np.ndarray = field(default_factory=lambda: np.empty(0))
    decision_m: np.ndarray = field(default_factory=lambda: np.empty(0))
    pose_covariance: np.ndarray = field(default_factory=lambda: np.empty((0, 3, 3)))


def mapped(recorded: Recorded, layout, slam: bool, echo_tests: bool = True) -> Outcome:
    """The mapper's core (:class:`~sonar_ring.map_builder.MapBuilder`) on a run: with SLAM or in ``odom``, echo tests.

    With its echo tests (multipath, impossible, persistence) or without.

    Each ping goes in at its stamp with the odometry of its stamp (``odom``
    starts at the true first pose, and with SLAM ``map`` at ``odom``'s, so
    the map is scored in the world frame); the pose estimate is SLAM's, or
    the odometry.
    """
    stage = PingStage(layout, pipeline.Settings(sigma_speed=pipeline.ROBOT_SIGMA_SPEED))
    tests = EchoTests() if echo_tests else None
    builder = MapBuilder(MapperSettings(slam=slam, pose_history=None, layout=layout, echo_tests=tests), Counts())
    label_ms, map_ms, estimate, covariance = [], [], [], []
    for k, (echoes, pose) in enumerate(zip(recorded.echoes, recorded.odometry, strict=True)):
        stamp = int(round(1e9 * (1.0 + k / layout.ping_rate)))
        builder.add_odometry(stamp, pose)
        covariance.append(np.zeros((3, 3)) if builder.slam is None else builder.slam.pose_at(pose)[1])
        started = time.perf_counter()
        labelled = stage.label(echoes)[1] if echoes is not None else Landmarks.empty()
        placed = time.perf_counter()
        builder.add_ping(stamp, labelled)
        label_ms.append(1e3 * (placed - started))
        map_ms.append(1e3 * (time.perf_counter() - placed))
        estimate.append(builder.robot_pose)
    return Outcome(score_map(builder.snapshot(), load_scene(SCENE), recorded.heard),
                   trajectory_error(np.array(estimate), recorded.truth), np.array(label_ms), np.array(map_ms),
                   builder.landmark_map.decision_distances(), np.array(covariance))


MAPPERS: dict[str, Callable[[Recorded, object], Outcome]] = {
    "odom-frame map": lambda recorded, layout: mapped(recorded, layout, slam=False, echo_tests=False),
    "odom-frame map + echo tests": lambda recorded, layout: mapped(recorded, layout, slam=False),
    "SLAM + echo tests": lambda recorded, layout: mapped(recorded, layout, slam=True),
}
"""The mappers compared, on the same runs: the mapper node with ``slam: false, echo_tests: false`` (the
odometry taken as exact, every echo mapped: the baseline), with the echo tests (``slam: false``), and
as it ships (SLAM and the echo tests)."""


def simulated(world: str, seed: int, count: int):
    """``count`` pings over laps of :data:`SCENE` in world ``world``, seed ``seed``, simulated one by one.

    Yields, per ping, the true pose, the :class:`~sonar_ring.simulate.Ping`,
    the wheel odometry's pose in ``odom`` and the usable echoes
    (:func:`~sonar_ring.ping_stage.check_ping`; None where nothing was usable);
    nothing is kept, so any length of run fits.
    """
    scene, layout = load_scene(SCENE), load_layout(LAYOUT)
    model = World(scene, layout, WORLDS[world], noise=NOISE, seed=seed)
    poses = scene.trajectory.poses(layout.ping_rate)[1]
    for k in range(count):
        pose = poses[k % len(poses)]
        ping = model.ping(pose, k / layout.ping_rate)
        stamp = round(1e9 * k / layout.ping_rate)
        yield pose, ping, model.odometry_pose(pose), check_ping(ping.echoes, layout, Counts(), stamp)


def lap_pings() -> int:
    """Pings in one lap of :data:`SCENE` with :data:`LAYOUT` at its ping rate."""
    return len(load_scene(SCENE).trajectory.poses(load_layout(LAYOUT).ping_rate)[1])


def simulate_run(world: str, seed: int, laps: int, pings: int | None = None) -> Recorded:
    """Simulate ``laps`` laps of :data:`SCENE` (``pings`` stops earlier) in world ``world``, seed ``seed``."""
    total = laps * lap_pings() if pings is None else pings
    echoes, odometry, truth, heard = [], [], [], set()
    for pose, ping, odometry_pose, usable in simulated(world, seed, total):
        odometry.append(odometry_pose)
        truth.append(pose)
        complete = (ping.truth_origin == DIRECT) & np.isfinite(ping.tof).all(axis=1)
        heard.update(ping.truth_reflector[complete].tolist())
        echoes.append(usable)
    return Recorded(echoes, np.array(odometry), np.array(truth), np.array(sorted(heard), dtype=int))


def _job(world: str, seed: int, laps: int, pings: int | None) -> dict[str, Outcome]:
    recorded = simulate_run(world, seed, laps, pings)
    layout = load_layout(LAYOUT)
    return {name: mapper(recorded, layout) for name, mapper in MAPPERS.items()}


def measure(seeds: int = SEEDS, laps: int = LAPS, pings: int | None = None, worlds=tuple(WORLDS),
            jobs: int | None = None, tell=print, effect_seeds: int = EFFECT_SEEDS) -> dict:
    """Every mapper in every world: ``{world: {mapper: [Outcome per seed]}}``.

    ``seeds`` seeds in the ``realistic`` world, ``effect_seeds`` in each other
    (a 3-lap run with SLAM takes about a minute and a half here).
    """
    jobs = jobs or len(os.sched_getaffinity(0))
    work = [(world, seed) for world in worlds for seed in range(seeds if world == "realistic" else effect_seeds)]
    results = {world: {name: [] for name in MAPPERS} for world in worlds}
    with ProcessPoolExecutor(jobs, mp_context=get_context("fork")) as pool:
        futures = {pool.submit(_job, world, seed, laps, pings): (world, seed) for world, seed in work}
        for done, (future, (world, seed)) in enumerate(futures.items(), 1):
            for name, outcome in future.result().items():
                results[world][name].append(outcome)
            tell(f"map study: {done}/{len(work)} runs ({world}, seed {seed})")
    return results


# --------------------------------------------------------------------------- report


def _mean(values) -> str:
    values = np.asarray(values, dtype=float)
    return f"{values.mean():.1f}" if values.size else "—"


def _mm(values) -> str:
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    return f"{1e3 * np.median(values):.1f} mm" if values.size else "—"


def _row(world: str, name: str, outcomes: list[Outcome]) -> str:
    scores = [o.score for o in outcomes]
    heard = [s.total("heard") for s in scores]
    mapped = [s.total("mapped") for s in scores]
    errors = [np.median(s.point_error) if s.point_error.size else np.nan for s in scores]
    fitted = np.array([s.similarity for s in scores])
    fitted = fitted[np.isfinite(fitted).all(axis=1)]
    shapes = [np.median(s.shape_error) if s.shape_error.size else np.nan for s in scores]
    shape = (f"{_mm(shapes)}; ×{np.median(fitted[:, 0]):.4f}, "
             f"{np.degrees(np.median(np.abs(fitted[:, 1]))):.2f}°" if len(fitted) else "—")
    complete = sum(s.complete for s in scores)
    rms, final = [o.trajectory[0] for o in outcomes], [o.trajectory[1] for o in outcomes]
    # how far a run's walls reach past the true walls' ends at most (a costmap's obstacle in free space)
    past = [s.wall_overshoot.max() if s.wall_overshoot.size else np.nan for s in scores]
    past = np.asarray(past)[np.isfinite(past)]
    overshoot = (f"{100 * np.median(past):.1f} / {100 * past.max():.1f} cm, {np.count_nonzero(past <= 0.02)} "
                 f"of {len(scores)}" if past.size else "—")
    classed = sum(all(s.per_class[name].mapped == s.per_class[name].heard and s.per_class[name].wrong_class == 0
                      for name in ("corner", "edge")) for s in scores)
    label = np.concatenate([o.label_ms for o in outcomes])
    update = np.concatenate([o.map_ms for o in outcomes])
    timing = (f"{np.median(label):.2f} / {np.median(update):.2f} ms" if label.size else "—")
    driven = np.concatenate([o.decision_m for o in outcomes])
    decision = f"{np.median(driven):.2f} / {np.percentile(driven, 95):.2f} m" if driven.size else "—"
    return (f"| {world} | {name} | {_mean([s.entries for s in scores])} "
            f"| {_mean(mapped)} of {_mean(heard)} | {_mean([s.total('duplicates') for s in scores])} "
            f"| {_mean([s.ghosts for s in scores])} | {_mean([s.total('wrong_class') for s in scores])} "
            f"| {_mean([s.total('misplaced') for s in scores])} | {_mean([s.undecided for s in scores])} "
            f"| {_mm(errors)} | {shape} | {overshoot} | {complete} of {len(scores)} "
            f"| {100 * np.median(rms):.1f} / {100 * np.median(final):.1f} cm | {classed} of {len(scores)} "
            f"| {decision} | {timing} |")


HEADER = ("| world | mapper | entries | mapped right, of heard | duplicates | ghosts | wrong class | misplaced "
          "| undecided "
          "| median point error | after a similarity fit: point error; scale, rotation "
          "| walls past their ends, median / worst; runs within 2 cm | runs complete "
          "| pose error, RMS / final | runs with every corner and edge right "
          "| driven to tell edge from corner, median / p95 | per ping: label / map |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")


def table(results: dict) -> list[str]:
    """The study's table: per world and mapper, means over the seeds (medians for errors and times)."""
    return [*HEADER, *(_row(world, name, outcomes) for world, by_mapper in results.items()
                       for name, outcomes in by_mapper.items())]


def section(results: dict, seeds: int, effect_seeds: int, laps: int, seconds: float, code: str) -> list[str]:
    """The ``BENCHMARKS.md`` section: how it was made, the table, what the columns mean."""
    return [
        SECTION_BEGIN,
        TITLE,
        "",
        f"Regenerate with `sonar-ring bench --map` (this run: {seeds} seeds in the realistic world and {effect_seeds} "
        f"in each of the other {len(results) - 1}, {laps} laps of the `{SCENE}` scene each, {seconds / 60:.0f} min "
        f"on {len(os.sched_getaffinity(0))} CPUs; "
        f"{today()}; sonar_ring at git {code}; {machine()}).",
        "Each world is the `realistic` profile of `sonar_ring.realism` with only the named effect on (`ideal`: none, "
        "`realistic`: all); every mapper maps the same simulated pings (σ_t = 1 µs, σ_A = 2 %) from the wheel "
        "odometry's poses. Scored by `sonar_ring.score.score_map` against the reflectors the sensor heard: "
        "*mapped right* within 5 cm (walls: 5 cm and 2° of the true line), *ghosts* with no true reflector within "
        "10 cm, *misplaced*: near a reflector of its class but not right (a wall piece turned more than 2° from "
        "the wall it lies on, say); *runs complete* where every heard reflector is mapped once with its class and "
        "no entry is a ghost, a duplicate, of the wrong class, misplaced or undecided (`score.MapScore.complete`); "
        "*runs with every corner and edge right*: every heard corner mapped "
        "CORNER and every heard edge EDGE, none of the wrong class; *driven to tell edge from corner*: the "
        "distance driven from a point's first sighting until its curvature decided it (over the decided points "
        "of every run); *walls past their ends*: how far a run's mapped walls reach beyond the true walls' ends at "
        "most (the median and the worst over the runs, and the runs where it is 2 cm or less); *after a similarity "
        "fit*: the mapped corners and edges carried onto their true points by the scale, rotation and shift that fit "
        "them best (`score.MapScore.similarity`): what is left is the map's shape error, the scale and the rotation "
        "what the whole map is off by (the median of each over the runs, the rotation's size). Means over the "
        "seeds; the point error, the pose errors and the compute per ping are medians (compute with two runs "
        "at once on the machine's CPUs).",
        "",
        *table(results),
        SECTION_END,
    ]


def kept_section(report: Path) -> list[str]:
    """The map section of an existing ``BENCHMARKS.md`` (markers included), or a line that says how to make it."""
    return sections.kept(report, SECTION_BEGIN, SECTION_END, TITLE, "sonar-ring bench --map")


def run(out_dir: Path = Path("."), seeds: int = SEEDS, laps: int = LAPS, pings: int | None = None,
        worlds=tuple(WORLDS), tell=print, effect_seeds: int = EFFECT_SEEDS) -> Path:
    """Measure, and put the section into ``out_dir/BENCHMARKS.md`` and the table into ``out_dir/README.md``.

    ``BENCHMARKS.md`` gets the section appended when it has none (or is
    created); the README's table is replaced only between its markers.
    """
    started = time.perf_counter()
    code = revision(Path(__file__).parent)
    results = measure(seeds, laps, pings, worlds, tell=tell, effect_seeds=effect_seeds)
    lines = section(results, seeds, effect_seeds, laps, time.perf_counter() - started, code)
    report = Path(out_dir) / "BENCHMARKS.md"
    sections.write(report, SECTION_BEGIN, SECTION_END, lines)
    summary = {world: results[world] for world in README_WORLDS if world in results}
    if sections.replace(Path(out_dir) / "README.md", SUMMARY_BEGIN, SUMMARY_END,
                        [SUMMARY_BEGIN, *table(summary), SUMMARY_END]):
        tell(f"updated the map table in {Path(out_dir) / 'README.md'}")
    tell(f"wrote the map section of {report}")
    return report

