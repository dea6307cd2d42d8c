"""``sonar-ring bench --slam-cost``: what the mapper with SLAM costs on this machine, against its targets.

Three measurements, each judged against its target (:data:`MEDIAN_TARGET_MS`,
:data:`P99_TARGET_MS`, :data:`GROWTH_TARGET`, :data:`SPEED_TARGET`):

1. **Per ping** (:func:`per_ping`): the mapper's core,
   :class:`~sonar_ring.map_builder.MapBuilder` with its defaults (SLAM and the
   echo tests on: the mapper node's), maps ``laps`` laps of the room in the
   realistic world (:func:`sonar_ring.benchmark.worlds.simulated`, seed 0:
   the pings of ``sonar-ring bench --map``'s realistic runs), each ping
   labelled by :meth:`sonar_ring.ping_stage.PingStage.label_and_publish_many` first; the time of each
   ``add_ping`` (its odometry is already there, so it maps at once).  For the
   split, the builder's echo tests (``MapBuilder._explain``), the
   :func:`~sonar_ring.explain.explain_landmarks` it calls and the SLAM update
   (``LandmarkSlam.add_ping``) are wrapped in timers for the run: a
   measurement only, what they do is unchanged, and a part the mapper no
   longer has is reported as not measured.
2. **Memory** (:func:`memory_run`): a fresh Python process (:func:`memory`:
   nothing of the first measurement is in its heap) maps ``minutes`` of the same world at
   the ring's ping rate, laps repeated, each ping simulated and labelled as it
   is mapped (nothing is held), and reads its resident set size every
   ``sample_every`` pings (psutil where installed, else ``/proc/self/statm``).
   The growth is the size at the end over the size at the end of the warm-up
   (``warmup`` minutes: the map of the room is built and the smoother's lag
   filled long before).  The run stops early when it has taken ``budget``
   seconds of wall time, and says so.
3. **process** (:func:`process_speed`): ``sonar-ring record-sim room BAG
   --laps N`` records the realistic world, then ``sonar-ring process BAG OUT
   --quiet`` (SLAM on: its default) is timed as a whole command, start of the
   interpreter to its exit, ``runs`` times; the speed is the bag's data
   duration (as the command prints it) over the median wall time.  Two
   recordings (:data:`BAG_LAPS`): the demo's one lap, which the target is
   judged on (the command's start weighs most there), and the per-ping run's
   three laps.

The section lies between :data:`SECTION_BEGIN` and :data:`SECTION_END` of
``BENCHMARKS.md``; ``sonar-ring bench`` and ``sonar-ring bench --map`` keep it.
"""

from __future__ import annotations

import itertools
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sonar_ring import map_builder, pipeline
from sonar_ring.benchmark import sections, worlds
from sonar_ring.benchmark.environment import machine, revision, today
from sonar_ring.geometry import load_layout
from sonar_ring.landmarks import Landmarks
from sonar_ring.map_builder import MapBuilder, MapperSettings
from sonar_ring.ping_stage import Counts, PingStage

WORLD = "realistic"
SEED = 0
LAPS = 3
MINUTES = 30.0
WARMUP_MINUTES = 5.0
SAMPLE_EVERY = 900
"""Pings between two readings of the resident set size (30 s at the ring's 30 Hz)."""
BUDGET_MINUTES = 60.0
"""Wall time after which the memory run stops, whatever it reached."""
BAG_LAPS = (1, LAPS)
"""Laps of the recordings ``sonar-ring process`` is timed on: the first is the target's."""
RUNS = 5

MEDIAN_TARGET_MS = 2.0
P99_TARGET_MS = 10.0
"""Target: the mapper's update per ping, median and 99th percentile, ms."""
GROWTH_TARGET = 0.05
"""Target: resident set growth after warm-up over a 30-minute run, fraction."""
SPEED_TARGET = 10.0
"""Target: ``sonar-ring process`` with SLAM, times real time."""

SECTION_BEGIN = "<!-- sonar-ring bench --slam-cost: section -->"
SECTION_END = "<!-- /sonar-ring bench --slam-cost: section -->"
TITLE = "## Cost of the mapper with SLAM"
COMMAND = "sonar-ring bench --slam-cost"

ECHO_TESTS, EXPLAIN, SLAM = "echo tests", "explain_landmarks", "SLAM"
PARTS = (ECHO_TESTS, EXPLAIN, SLAM)
"""The parts of ``add_ping`` timed apart: ``MapBuilder._explain``, the ``explain_landmarks`` it calls,
``LandmarkSlam.add_ping``."""


# --------------------------------------------------------------------------- the pings


def labelled_pings(count: int, seed: int = SEED, batch: int = 64):
    """``(stamp ns, odometry pose, labelled landmarks)`` of ``count`` pings of the room in the realistic world.

    Simulated (:func:`~sonar_ring.benchmark.worlds.simulated`) and labelled
    (:meth:`~sonar_ring.ping_stage.PingStage.label_and_publish_many`, with a robot's settings) ``batch``
    at a time, as they are taken; ping ``k`` is stamped ``1 + k / ping_rate`` s.
    """
    layout = load_layout(worlds.LAYOUT)
    stage = PingStage(layout, pipeline.Settings(sigma_speed=pipeline.ROBOT_SIGMA_SPEED))
    pings = worlds.simulated(WORLD, seed, count)
    first = 0
    while taken := [(odometry, echoes) for _, _, odometry, echoes in itertools.islice(pings, batch)]:
        usable = [index for index, (_, echoes) in enumerate(taken) if echoes is not None]
        labels = stage.label_and_publish_many([taken[index][1] for index in usable])
        labelled = dict(zip(usable, (landmarks for _, landmarks, _ in labels), strict=True))
        for index, (odometry, _) in enumerate(taken):
            stamp = int(round(1e9 * (1.0 + (first + index) / layout.ping_rate)))
            yield stamp, odometry, labelled.get(index, Landmarks.empty())
        first += len(taken)


def new_builder() -> MapBuilder:
    """The mapper's core as the mapper node makes it by default (SLAM, echo tests), for :data:`worlds.LAYOUT`.

    Its compiled kernels are loaded first, as the node loads them at its start.
    """
    builder = MapBuilder(MapperSettings(layout=load_layout(worlds.LAYOUT)), Counts())
    builder.load_kernels()
    return builder


def _map_sizes(builder: MapBuilder) -> dict:
    """Entries of the front end, entries in the SLAM's graph, SLAM sessions."""
    slam = builder.slam
    return {"entries": int(builder.landmark_map.entries().uid.size),
            "confirmed": int(slam.confirmed.size) if slam is not None else 0,
            "sessions": int(slam.sessions) if slam is not None else 0}


# --------------------------------------------------------------------------- 1. per ping


class _PartTimer:
    """Seconds spent in each of :data:`PARTS` during one ping, from wrapped calls (a measurement only)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.keyframe = False

    def reset(self) -> None:
        self.seconds.clear()
        self.keyframe = False

    def wrap(self, function, part: str):
        def timed(*args, **kwargs):
            started = time.perf_counter()
            result = function(*args, **kwargs)
            self.seconds[part] = self.seconds.get(part, 0.0) + time.perf_counter() - started
            if part == SLAM:
                self.keyframe = bool(getattr(result, "keyframe", False))
            return result

        return timed


def _instrument(builder: MapBuilder, timer: _PartTimer) -> tuple[set, object]:
    """Wrap the builder's parts in ``timer``; returns the parts measured and the original ``explain_landmarks``."""
    measured = set()
    if callable(getattr(builder, "_explain", None)):
        builder._explain = timer.wrap(builder._explain, ECHO_TESTS)
        measured.add(ECHO_TESTS)
    original = getattr(map_builder, "explain_landmarks", None)
    if original is not None:
        map_builder.explain_landmarks = timer.wrap(original, EXPLAIN)
        measured.add(EXPLAIN)
    if builder.slam is not None and callable(getattr(builder.slam, "add_ping", None)):
        builder.slam.add_ping = timer.wrap(builder.slam.add_ping, SLAM)
        measured.add(SLAM)
    return measured, original


@dataclass
class PerPing:
    """The mapper's update per ping over a run (:func:`per_ping`).

    Attributes
    ----------
    total : ndarray
        ``add_ping`` per ping, ms.
    parts : dict of str to ndarray
        Per part of :data:`PARTS` that was measured, its time per ping, ms.
    keyframe : ndarray of bool
        Whether the ping made a SLAM keyframe.
    lap : int
        Pings per lap.
    sizes : dict
        Map entries, entries in the graph and sessions at the end (:func:`_map_sizes`).
    problems : dict
        What the builder refused, by reason.
    load : tuple of float
        The load average at the end of the run.
    """

    total: np.ndarray
    parts: dict
    keyframe: np.ndarray
    lap: int
    sizes: dict = field(default_factory=dict)
    problems: dict = field(default_factory=dict)
    load: tuple = ()


def per_ping(laps: int = LAPS, pings: int | None = None, tell=print) -> PerPing:
    """Time ``add_ping`` over ``laps`` laps (``pings`` stops earlier), with its parts (module docstring)."""
    lap = worlds.lap_pings()
    count = laps * lap if pings is None else pings
    builder = new_builder()
    timer = _PartTimer()
    measured, original = _instrument(builder, timer)
    total, keyframe, parts = [], [], {part: [] for part in measured}
    try:
        for k, (stamp, odometry, landmarks) in enumerate(labelled_pings(count)):
            builder.add_odometry(stamp, odometry)
            timer.reset()
            started = time.perf_counter()
            builder.add_ping(stamp, landmarks)
            total.append(time.perf_counter() - started)
            keyframe.append(timer.keyframe)
            for part in measured:
                parts[part].append(timer.seconds.get(part, 0.0))
            if (k + 1) % lap == 0 or k + 1 == count:
                tell(f"slam cost: per ping, {k + 1}/{count} pings mapped")
    finally:
        if original is not None:
            map_builder.explain_landmarks = original
    return PerPing(1e3 * np.array(total), {part: 1e3 * np.array(times) for part, times in parts.items()},
                   np.array(keyframe, dtype=bool), lap, _map_sizes(builder), dict(builder.health.problems),
                   os.getloadavg())


# --------------------------------------------------------------------------- 2. memory


def resident_bytes() -> float:
    """The resident set size of this process, bytes (psutil, else ``/proc/self/statm``); NaN without either."""
    try:
        import psutil
    except ImportError:
        pass
    else:
        return float(psutil.Process().memory_info().rss)
    try:
        with open("/proc/self/statm") as statm:
            return float(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return float("nan")


def memory_run(minutes: float = MINUTES, sample_every: int = SAMPLE_EVERY, budget: float = 60 * BUDGET_MINUTES,
               verbose: bool = True) -> dict:
    """Map ``minutes`` of the realistic room here, reading the resident set size every ``sample_every`` pings.

    Returns ``samples`` (one dict per reading: ``ping``, ``minute`` simulated,
    ``wall`` s, ``rss`` bytes, ``median_ms`` and ``p99_ms`` of ``add_ping``
    since the reading before, and :func:`_map_sizes`), ``pings`` asked,
    ``stopped`` (empty, or why the run ended early), ``problems`` and the
    ``load`` average at the end.  Run it in a process of its own
    (:func:`memory`).
    """
    rate = load_layout(worlds.LAYOUT).ping_rate
    count = int(round(minutes * 60.0 * rate))
    builder = new_builder()
    samples = [dict(ping=0, minute=0.0, wall=0.0, rss=resident_bytes(), median_ms=float("nan"),
                    p99_ms=float("nan"), **_map_sizes(builder))]
    window, stopped, started = [], "", time.perf_counter()
    for k, (stamp, odometry, landmarks) in enumerate(labelled_pings(count)):
        builder.add_odometry(stamp, odometry)
        begun = time.perf_counter()
        builder.add_ping(stamp, landmarks)
        window.append(time.perf_counter() - begun)
        if (k + 1) % sample_every and k + 1 != count:
            continue
        wall = time.perf_counter() - started
        samples.append(dict(ping=k + 1, minute=(k + 1) / rate / 60.0, wall=wall, rss=resident_bytes(),
                            median_ms=1e3 * float(np.median(window)), p99_ms=1e3 * float(np.percentile(window, 99)),
                            **_map_sizes(builder)))
        window = []
        if verbose:
            last = samples[-1]
            print(f"slam cost: memory, {last['minute']:.1f} of {minutes:g} simulated min, "
                  f"{last['rss'] / 2**20:.0f} MiB, {wall / 60:.1f} min of wall time", file=sys.stderr, flush=True)
        if wall > budget and k + 1 < count:
            stopped = (f"stopped at the wall-time budget ({budget / 60:.0f} min) after {samples[-1]['minute']:.1f} "
                       f"of {minutes:g} simulated minutes")
            break
    return dict(samples=samples, pings=count, stopped=stopped, problems=dict(builder.health.problems),
                load=os.getloadavg())


def memory(minutes: float = MINUTES, sample_every: int = SAMPLE_EVERY, budget: float = 60 * BUDGET_MINUTES) -> dict:
    """:func:`memory_run` in a fresh Python process, so its heap holds nothing of this one's; its progress on stderr.

    The process is ``python -m sonar_ring.benchmark.slam_cost`` (not a
    multiprocessing child, which would run the ``sonar-ring`` script again).
    """
    arguments = json.dumps(dict(minutes=minutes, sample_every=sample_every, budget=budget))
    done = subprocess.run([sys.executable, "-m", "sonar_ring.benchmark.slam_cost", arguments], stdout=subprocess.PIPE,
                          text=True)
    lines = done.stdout.strip().splitlines()
    if done.returncode != 0 or not lines:
        return dict(error=f"the memory run failed (exit status {done.returncode})")
    return json.loads(lines[-1])


def growth(run: dict, warmup: float = WARMUP_MINUTES) -> dict:
    """The resident set after warm-up: at its end (``base``), at the end of the run, the peak, and the growths.

    Empty when the run did not go past the warm-up.
    """
    after = [sample for sample in run["samples"] if sample["minute"] >= warmup]
    if len(after) < 2:
        return {}
    base, end = after[0], after[-1]
    peak = max(sample["rss"] for sample in after)
    return dict(base=base, end=end, peak=peak, growth=end["rss"] / base["rss"] - 1.0,
                peak_growth=peak / base["rss"] - 1.0)


# --------------------------------------------------------------------------- 3. process


PROCESSED = re.compile(r"processed (\d+) pings \(([\d.]+) s of data.*\) in ([\d.]+) s: ([\d.]+)x real time")


def sonar_ring_command() -> list[str]:
    """The ``sonar-ring`` command: the installed script where it is on the PATH, else this Python's module."""
    script = shutil.which("sonar-ring")
    return [script] if script else [sys.executable, "-m", "sonar_ring.cli"]


def process_speed(laps: int | None = LAPS, pings: int | None = None, runs: int = RUNS, tell=print) -> dict:
    """Record a bag of the realistic room, then time ``sonar-ring process`` on it ``runs`` times (module docstring).

    Returns ``pings``, ``data_seconds`` (as the command prints it), ``wall``
    (s per run), ``inside`` (the command's own seconds, opening the bag to
    closing the output), ``record`` (the command that made the bag) and
    ``load`` at the end; or ``error`` when a command failed.
    """
    command = sonar_ring_command()
    with tempfile.TemporaryDirectory(prefix="slam_cost_") as scratch:
        bag = Path(scratch) / "bag"
        record = ["record-sim", worlds.SCENE, "--world", WORLD, "--seed", str(SEED), "--quiet",
                  *(["--laps", str(laps)] if pings is None else ["--pings", str(pings)])]
        done = subprocess.run([*command, *record[:2], str(bag), *record[2:]], capture_output=True, text=True)
        if done.returncode != 0:
            return dict(error=f"`sonar-ring record-sim` failed: {_last_line(done)}")
        wall, inside, found = [], [], None
        for run in range(runs):
            out = Path(scratch) / f"out_{run}"
            started = time.perf_counter()
            done = subprocess.run([*command, "process", str(bag), str(out), "--quiet"], capture_output=True,
                                  text=True)
            wall.append(time.perf_counter() - started)
            found = PROCESSED.search(done.stdout)
            if done.returncode != 0 or found is None:
                return dict(error=f"`sonar-ring process` failed: {_last_line(done)}")
            inside.append(float(found.group(3)))
            shutil.rmtree(out, ignore_errors=True)
            tell(f"slam cost: sonar-ring process ({' '.join(record[-2:])}), run {run + 1}/{runs}: {wall[-1]:.2f} s")
    return dict(pings=int(found.group(1)), data_seconds=float(found.group(2)), wall=wall, inside=inside,
                record="sonar-ring " + " ".join([*record[:2], "BAG", *record[2:]]), load=os.getloadavg())


def _last_line(done: subprocess.CompletedProcess) -> str:
    lines = (done.stderr or done.stdout or "").strip().splitlines()
    return lines[-1] if lines else f"exit status {done.returncode}"


# --------------------------------------------------------------------------- report


def _met(ok: bool) -> str:
    return "**met**" if ok else "**missed**"


def _ms(values: np.ndarray, q: float | None = None) -> str:
    if not values.size:
        return "—"
    return f"{np.median(values) if q is None else np.percentile(values, q):.2f} ms"


def _mib(value: float) -> str:
    return f"{value / 2**20:.1f} MiB" if np.isfinite(value) else "—"


def _load(load) -> str:
    return ", ".join(f"{x:.1f}" for x in load)


def _per_ping_target(result: PerPing) -> tuple[str, str, str]:
    median, p99 = np.median(result.total), np.percentile(result.total, 99)
    ok = median <= MEDIAN_TARGET_MS and p99 <= P99_TARGET_MS
    verdict = _met(ok) + ("" if ok else f" (median ×{median / MEDIAN_TARGET_MS:.2f}, p99 ×{p99 / P99_TARGET_MS:.2f} "
                                        "the target)")
    return (f"mapper update per ping (`MapBuilder.add_ping`, SLAM and echo tests): median ≤ {MEDIAN_TARGET_MS:g} ms, "
            f"p99 ≤ {P99_TARGET_MS:g} ms",
            f"median {median:.2f} ms, p99 {p99:.2f} ms over {result.total.size} pings", verdict)


def _memory_target(run: dict, minutes: float, warmup: float) -> tuple[str, str, str]:
    target = (f"memory flat over a {minutes:g}-minute run: resident growth ≤ {100 * GROWTH_TARGET:g} % after "
              f"warm-up ({warmup:g} min)")
    if "error" in run:
        return target, run["error"], "not measured"
    found = growth(run, warmup)
    if not found:
        return target, run["stopped"] or "the run ended within the warm-up", "not measured"
    base, end = found["base"], found["end"]
    figures = (f"{100 * found['growth']:+.1f} % ({_mib(base['rss'])} at {base['minute']:.1f} min, "
               f"{_mib(end['rss'])} at {end['minute']:.1f} min; peak {100 * found['peak_growth']:+.1f} %)")
    verdict = _met(found["growth"] <= GROWTH_TARGET)
    if run["stopped"]:
        figures += f"; {run['stopped']}"
        verdict += f" up to {found['end']['minute']:.1f} min; not measured to {minutes:g} min"
    return target, figures, verdict


def _process_target(speeds: list[dict]) -> tuple[str, str, str]:
    """The target's row: judged on the first recording, the others' speeds after it."""
    target = f"`sonar-ring process` with SLAM ≥ {SPEED_TARGET:g}× real time"
    first, *others = speeds
    if "error" in first:
        return target, first["error"], "not measured"
    ratio = _ratio(first)
    figures = (f"×{ratio:.1f}: {first['data_seconds']:.1f} s of data in {statistics.median(first['wall']):.2f} s "
               f"(median of {_runs(len(first['wall']))} of the whole command)")
    figures += "".join(f"; {other['pings']} pings: ×{_ratio(other):.1f} ({other['data_seconds']:.1f} s in "
                       f"{statistics.median(other['wall']):.2f} s)" for other in others if "error" not in other)
    return (target, figures,
            _met(ratio >= SPEED_TARGET) + ("" if ratio >= SPEED_TARGET else f" (×{SPEED_TARGET / ratio:.1f} short)"))


def _ratio(speed: dict) -> float:
    """Times real time: the bag's data over the median wall time of the whole command."""
    return speed["data_seconds"] / statistics.median(speed["wall"])


def _runs(count: int) -> str:
    return f"{count} run" + ("" if count == 1 else "s")


def _part_cells(values: np.ndarray | None) -> str:
    return "not measured" if values is None else f"{_ms(values)} / {_ms(values, 99)}"


def _per_ping_table(result: PerPing) -> list[str]:
    """Per lap and over the run: add_ping, keyframe and other pings, and the parts."""
    spans = [(f"lap {1 + start // result.lap}", slice(start, start + result.lap))
             for start in range(0, result.total.size, result.lap)]
    if len(spans) > 1:
        spans.append(("all", slice(0, result.total.size)))
    rows = ["| pings | count | keyframes | `add_ping` median / p99 / max | at a keyframe: median / p99 "
            "| other pings: median / p99 | echo tests (`_explain`) median / p99 | of which `explain_landmarks` "
            "| SLAM (`LandmarkSlam.add_ping`) | the rest |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for name, span in spans:
        total, keyframe = result.total[span], result.keyframe[span]
        parts = {part: result.parts[part][span] if part in result.parts else None for part in PARTS}
        rest = None
        if parts[ECHO_TESTS] is not None and parts[SLAM] is not None:
            rest = total - parts[ECHO_TESTS] - parts[SLAM]
        rows.append(f"| {name} | {total.size} | {int(keyframe.sum())} | {_ms(total)} / {_ms(total, 99)} / "
                    f"{total.max():.1f} ms | {_part_cells(total[keyframe])} | {_part_cells(total[~keyframe])} "
                    f"| {_part_cells(parts[ECHO_TESTS])} | {_part_cells(parts[EXPLAIN])} | {_part_cells(parts[SLAM])} "
                    f"| {_part_cells(rest)} |")
    return rows


def _memory_table(run: dict, rows: int = 13) -> list[str]:
    """Readings spread over the run (at most ``rows``, the last always)."""
    samples = run["samples"]
    picked = sorted({round(i) for i in np.linspace(0, len(samples) - 1, min(rows, len(samples)))})
    lines = ["| simulated | pings | resident set | `add_ping` since the reading before: median / p99 "
             "| map entries / in the graph | SLAM sessions | wall time |",
             "|---|---|---|---|---|---|---|"]
    for index in picked:
        s = samples[index]
        timing = "—" if not np.isfinite(s["median_ms"]) else f"{s['median_ms']:.2f} / {s['p99_ms']:.2f} ms"
        lines.append(f"| {s['minute']:.1f} min | {s['ping']} | {_mib(s['rss'])} | {timing} | {s['entries']} / "
                     f"{s['confirmed']} | {s['sessions']} | {s['wall'] / 60:.1f} min |")
    return lines


def section(result: PerPing, run: dict, speeds: list[dict], settings: dict, seconds: float, code: str,
            quick: bool) -> list[str]:
    """The ``BENCHMARKS.md`` section: how it was made, the targets, the three tables."""
    command = COMMAND + (" --quick" if quick else "")
    note = " A `--quick` run: small sizes, to check that the section is produced; its figures are not for reading." \
        if quick else ""
    memory_lines = (["Not measured: " + run["error"] + "."] if "error" in run else
                    [f"A fresh process mapped {settings['minutes']:g} simulated minutes ({run['pings']} pings at the "
                     f"ring's rate, laps of the room repeated; {run['stopped'] or 'to the end'}), reading its resident "
                     f"set size every {settings['sample_every']} pings; load average at the end "
                     f"{_load(run['load'])}. Refused by the mapper: {_problems(run['problems'])}.", "",
                     *_memory_table(run)])
    process_lines = []
    for speed in speeds:
        if "error" in speed:
            process_lines += ["Not measured: " + speed["error"] + ".", ""]
            continue
        wall = speed["wall"]
        process_lines += [
            f"`{speed['record']}` ({speed['pings']} pings, {speed['data_seconds']:.1f} s of data), then "
            f"`sonar-ring process BAG OUT --quiet` (SLAM on, `--jobs` one per CPU: the defaults) timed as a whole "
            f"command, {_runs(len(wall))}: {', '.join(f'{w:.2f}' for w in wall)} s (median "
            f"{statistics.median(wall):.2f} s, ×{_ratio(speed):.1f} real time); the command's own time, opening the "
            f"bag to closing the output, median {statistics.median(speed['inside']):.2f} s. Load average at the end "
            f"{_load(speed['load'])}.", ""]
    process_lines = [
        "The target is judged on the first recording, the demo's lap, the shorter: the command's start (the "
        "interpreter, its imports and the compiled kernels: a second or two) weighs more there than over the "
        "per-ping run's laps.", "",
        *process_lines[:-1]]
    return [
        SECTION_BEGIN,
        TITLE,
        "",
        f"Regenerate with `{command}` (this run took {seconds / 60:.0f} min; {today()}; sonar_ring at git {code}; "
        f"{machine()}).{note}",
        "The mapper's core (`MapBuilder`, defaults: SLAM and echo tests on) on the room in the realistic world "
        f"(`sonar_ring.realism`, seed {SEED}, σ_t = 1 µs, σ_A = 2 %), the pings labelled by the pipeline first. "
        "The ping → markers latency is not here: the map comes after the markers, and `sonar-ring bench` measures "
        "that latency (the graph's targets).",
        "",
        "| target | this run | verdict |",
        "|---|---|---|",
        "| {} | {} | {} |".format(*_per_ping_target(result)),
        "| {} | {} | {} |".format(*_memory_target(run, settings["minutes"], settings["warmup"])),
        "| {} | {} | {} |".format(*_process_target(speeds)),
        "",
        "### Per ping",
        "",
        f"{result.total.size} pings ({result.total.size / result.lap:.2f} laps of {result.lap}), each ping's "
        "`add_ping` timed with `time.perf_counter` (its odometry already in, so it is mapped at once). The parts are "
        "timed by wrapping the builder's `_explain` (the echo tests: the pose estimate, the published map and "
        "`explain_landmarks`) and `LandmarkSlam.add_ping` for the run; the rest is the curvature models and the "
        "bookkeeping. Median / p99 per column (they do not add up). At the end: "
        f"{result.sizes.get('entries', 0)} map entries, {result.sizes.get('confirmed', 0)} in the graph, "
        f"{result.sizes.get('sessions', 0)} session(s); refused: {_problems(result.problems)}; load average at the "
        f"end {_load(result.load)}.",
        "",
        *_per_ping_table(result),
        "",
        f"### Memory over {settings['minutes']:g} minutes",
        "",
        *memory_lines,
        "",
        "### `sonar-ring process` with SLAM",
        "",
        *process_lines,
        SECTION_END,
    ]


def _problems(problems: dict) -> str:
    return ", ".join(f"{count} {reason}" for reason, count in sorted(problems.items())) or "nothing"


def kept_section(report: Path) -> list[str]:
    """The section of an existing ``BENCHMARKS.md`` (markers included), or a line that says how to make it."""
    return sections.kept(report, SECTION_BEGIN, SECTION_END, TITLE, COMMAND)


def run(out_dir: Path = Path("."), laps: int = LAPS, pings: int | None = None, minutes: float = MINUTES,
        warmup: float = WARMUP_MINUTES, sample_every: int = SAMPLE_EVERY, budget: float = 60 * BUDGET_MINUTES,
        bag_laps: tuple = BAG_LAPS, bag_pings: tuple = (), runs: int = RUNS, quick: bool = False,
        tell=print) -> Path:
    """Measure the three costs and put the section into ``out_dir/BENCHMARKS.md`` (appended when it has none).

    ``laps`` (``pings`` stops earlier) for the time per ping; ``minutes``,
    ``warmup`` (minutes), ``sample_every`` (pings) and ``budget`` (s of wall
    time) for the memory run; ``bag_laps`` (the recordings' laps; ``bag_pings``,
    when given: their pings instead) and ``runs`` for ``sonar-ring process``.
    ``quick`` only marks the section's figures as not for reading.
    """
    started = time.perf_counter()
    code = revision(Path(__file__).parent)
    result = per_ping(laps, pings, tell)
    recordings = [(None, count) for count in bag_pings] or [(count, None) for count in bag_laps]
    speeds = [process_speed(laps, pings, runs, tell) for laps, pings in recordings]
    tell(f"slam cost: memory over {minutes:g} simulated minutes in a process of its own (at most {budget / 60:.0f} "
         "min of wall time)")
    footprint = memory(minutes, sample_every, budget)
    settings = dict(minutes=minutes, warmup=warmup, sample_every=sample_every)
    lines = section(result, footprint, speeds, settings, time.perf_counter() - started, code, quick)
    report = Path(out_dir) / "BENCHMARKS.md"
    sections.write(report, SECTION_BEGIN, SECTION_END, lines)
    tell(f"wrote the SLAM cost section of {report}")
    return report


if __name__ == "__main__":  # the memory run's own process (:func:`memory`): its arguments in, its result out, as JSON
    print(json.dumps(memory_run(**json.loads(sys.argv[1]))))
