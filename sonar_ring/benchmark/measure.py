"""The measurements of the report: accuracy of every method at every noise level, and its speed.

:func:`measure` runs everything and returns a :class:`Results`; the report
(:mod:`sonar_ring.benchmark.report`) only formats it.  Errors are per echo:
the distance of a position from the truth (m) or the signed bearing error
(rad); statistics are over the valid estimates, the invalid share apart.
"""

from __future__ import annotations

import importlib
import sys
import traceback
from dataclasses import dataclass, field

import numpy as np

from sonar_ring import pipeline, uncertainty
from sonar_ring.benchmark import azimuth, classification, least_squares
from sonar_ring.benchmark.methods import BASELINE, BEARING, PRODUCTION, RING_FAMILIES, Batch, Family, truth_of
from sonar_ring.benchmark.scenes import BearingSweep, bearing_sweep, standard_scenes
from sonar_ring.benchmark.timing import best_time, interleaved_best

NOISE_LEVELS = (0.0, 0.3e-6, 1e-6, 2e-6)
"""Time-of-flight noise standard deviations sigma_t of the report, s."""
HEADLINE = 1e-6
"""The noise level of the main table, s."""
PING_ROWS = 144
"""Echo rows of one ping of the ring: 48 pairs, 3 echoes each."""
CRLB_SPAN = np.radians(45.0)
"""Bearings within which the bearing error is compared with the Cramer-Rao bound."""
SWEEP_BANDS = ((0.5, 1.0), (1.0, 2.5), (2.5, 5.0))
"""Distance bands of the bearing sweep, m."""
CLASSIFIER_SIGMA_FLOOR = 10e-9
"""The TOF noise the consistency test is told for exact data, s (it needs a positive one)."""
LSQ_MODELS = ("plane", "corner", "edge")
LSQ_NAME = "per-point least squares (`scipy.optimize.least_squares`)"

STREAMS = {"scene poses": 1, "bearing sweep": 2, "least-squares subsample": 3, "ring TOF noise": 4,
           "sweep noise": 5, "triads": 6, "amplitude bench": 7, "timing inputs": 8}
"""Random streams: every generator is ``numpy.random.default_rng([seed, stream, level])``."""


@dataclass(frozen=True)
class Sizes:
    """How much of everything a run measures."""

    poses_per_scene: int
    room_stride: int
    sweep: int
    batch: int
    ping_calls: int
    repeats: int
    lsq_points: int
    lsq_timed: int
    triad_echoes: int
    bench_trials: int


FULL = Sizes(poses_per_scene=2000, room_stride=1, sweep=200_000, batch=1_000_000, ping_calls=200, repeats=5,
             lsq_points=200, lsq_timed=100, triad_echoes=4000, bench_trials=40)
QUICK = Sizes(poses_per_scene=40, room_stride=40, sweep=4000, batch=20_000, ping_calls=10, repeats=2,
              lsq_points=6, lsq_timed=6, triad_echoes=300, bench_trials=1)


@dataclass(frozen=True)
class Accuracy:
    """Error statistics of one method at one noise level.

    Attributes
    ----------
    rms, p95, worst : float
        Root mean square, 95th percentile and maximum of ``|error|`` over the
        valid estimates (m or rad); NaN when none is valid.
    invalid : float
        Share of the echoes without a valid estimate.
    count : int
        Echoes judged.
    crlb_ratio : float
        Bearings: RMS of ``error / CRLB`` within +-45 deg (NaN otherwise or without noise).
    crlb_bands : tuple of float
        The same per :data:`SWEEP_BANDS`.
    """

    rms: float
    p95: float
    worst: float
    invalid: float
    count: int
    crlb_ratio: float = float("nan")
    crlb_bands: tuple = ()


def accuracy(error: np.ndarray, valid: np.ndarray, **extra) -> Accuracy:
    """Statistics of ``|error|`` (N,) over ``valid`` (N,)."""
    magnitude = np.abs(error[valid])
    count = int(valid.size)
    invalid = 1.0 - valid.mean() if count else float("nan")
    if magnitude.size == 0:
        return Accuracy(float("nan"), float("nan"), float("nan"), invalid, count, **extra)
    return Accuracy(float(np.sqrt(np.mean(magnitude**2))), float(np.percentile(magnitude, 95)),
                    float(magnitude.max()), invalid, count, **extra)


@dataclass
class Row:
    """One method: its accuracy per noise level, its speed and what the plots need.

    Attributes
    ----------
    family, name, role, unit : str
    levels : dict of float to Accuracy
        Per sigma_t (s).
    ns_per_landmark : float
        Batched time per echo, ns (NaN: not timed).
    us_per_ping : float
        Time of one call on :data:`PING_ROWS` echoes, us (NaN: not timed).
    errors : dict of float to ndarray
        Per-echo errors at sigma_t = 0 and :data:`HEADLINE` (NaN where invalid).
    along : ndarray
        What the plots put on the x axis per echo: the true range (m) or bearing (rad).
    same_echoes : dict of float to Accuracy
        Least-squares rows: the production method's accuracy on the same echoes.
    """

    family: str
    name: str
    role: str
    unit: str
    levels: dict = field(default_factory=dict)
    ns_per_landmark: float = float("nan")
    us_per_ping: float = float("nan")
    errors: dict = field(default_factory=dict)
    along: np.ndarray | None = None
    same_echoes: dict = field(default_factory=dict)

    def record(self, sigma: float, error: np.ndarray, valid: np.ndarray, along: np.ndarray, **extra) -> None:
        """Fold in the errors (N,) of one noise level."""
        self.levels[sigma] = accuracy(error, valid, **extra)
        if sigma in (0.0, HEADLINE):
            self.errors[sigma] = np.where(valid, error, np.nan)
            self.along = along


@dataclass
class Results:
    """Everything the report shows."""

    seed: int
    quick: bool
    sizes: Sizes
    sweep_separation: float
    scene_rows: dict
    incomplete_rows: int
    rows: list
    classification: dict
    triads: dict
    pipeline: dict
    graph: dict

    def family(self, name: str) -> list:
        """The rows of one family, in order."""
        return [row for row in self.rows if row.family == name]


def generator(seed: int, stream: str, level: int = 0) -> np.random.Generator:
    """The generator of one random stream (see :data:`STREAMS`)."""
    return np.random.default_rng([seed, STREAMS[stream], level])


def progress_to_stderr(message: str) -> None:
    """Print one step of a run on stderr."""
    print(f"sonar-ring bench: {message}", file=sys.stderr, flush=True)


def _tile(count: int, size: int) -> np.ndarray:
    return np.arange(size) % count


# --------------------------------------------------------------------------- accuracy

def _ring_level(rows_by_key, family: Family, batch: Batch, sigma: float, lsq_index: dict) -> None:
    echoes = family.select(batch)
    truth = truth_of(echoes.rows)
    along = echoes.rows.truth_range
    for method in family.methods:
        estimate, valid = method.solve(echoes)
        rows_by_key[family.name, method.name].record(sigma, np.hypot(*(estimate - truth).T), valid, along)
    if family.name in LSQ_MODELS:
        subset = echoes.take(lsq_index[family.name])
        estimate, valid = least_squares.fit(family.name, subset)
        row = rows_by_key[family.name, LSQ_NAME]
        row.record(sigma, np.hypot(*(estimate - truth_of(subset.rows)).T), valid, subset.rows.truth_range)
        production = next(method for method in family.methods if method.role == PRODUCTION)
        estimate, valid = production.solve(subset)
        row.same_echoes[sigma] = accuracy(np.hypot(*(estimate - truth_of(subset.rows)).T), valid)


def _bearing_level(rows_by_key, sweep: BearingSweep, sigma: float, rng) -> None:
    d1, d2 = sweep.noisy_paths(sigma, rng)
    sigma_bearing = uncertainty.cramer_rao_bound(sweep.separation, sigma, sweep.speed, sweep.bearing)[0]
    within = np.abs(sweep.bearing) <= CRLB_SPAN
    for method in BEARING.methods:
        estimate, valid = method.solve((sweep, d1, d2))
        error = estimate - sweep.bearing
        extra = {}
        if sigma > 0:
            def ratio(mask, error=error, valid=valid):
                usable = mask & valid
                return float(np.sqrt(np.mean(np.square(error[usable] / sigma_bearing[usable]))))

            extra = dict(crlb_ratio=ratio(within),
                         crlb_bands=tuple(ratio(within & (sweep.distance >= low) & (sweep.distance < high))
                                          for low, high in SWEEP_BANDS))
        rows_by_key[BEARING.name, method.name].record(sigma, error, valid, sweep.bearing, **extra)


# --------------------------------------------------------------------------- speed

def _time_methods(rows_by_key, family_name: str, methods, big, ping, sizes: Sizes) -> None:
    """Batched time per echo and time per ping of every timed method of a family, in alternation."""
    timed = {method.name: method.timed for method in methods if method.timed is not None}
    batched = interleaved_best({name: (lambda call=call: call(big)) for name, call in timed.items()}, sizes.repeats)

    def loop(call):
        def run():
            for _ in range(sizes.ping_calls):
                call(ping)
        return run

    per_ping = interleaved_best({name: loop(call) for name, call in timed.items()}, sizes.repeats)
    count = len(big[1]) if isinstance(big, tuple) else len(big)
    for name in timed:
        row = rows_by_key[family_name, name]
        row.ns_per_landmark = batched[name] / count * 1e9
        row.us_per_ping = per_ping[name] / sizes.ping_calls * 1e6


def _time_least_squares(row: Row, model: str, echoes: Batch, sizes: Sizes) -> None:
    subset = echoes.take(np.arange(min(sizes.lsq_timed, len(echoes))))
    seconds = best_time(lambda: least_squares.fit(model, subset), 2) / len(subset)
    row.ns_per_landmark = seconds * 1e9
    row.us_per_ping = seconds * PING_ROWS * 1e6


# --------------------------------------------------------------------------- the other sections

def _classification(scenes, tables_by_level: dict, sizes: Sizes, seed: int) -> dict:
    bench_rng = generator(seed, "amplitude bench")
    counts, theta0 = classification.confusion(sizes.bench_trials, bench_rng)
    per_echo, per_ping = classification.amplitude_rule_times(generator(seed, "timing inputs"), sizes.batch,
                                                             PING_ROWS, sizes.ping_calls, sizes.repeats)
    consistency = {}
    for sigma, table in tables_by_level.items():
        told = max(sigma, CLASSIFIER_SIGMA_FLOOR)
        is_edge, said_edge, said_specular = classification.ring_decisions(scenes.layout, table, told)
        consistency[sigma] = dict(is_edge=is_edge, said_edge=said_edge, said_specular=said_specular, told=told)
    headline = tables_by_level[HEADLINE]
    rows = headline["group"].size
    seconds = best_time(lambda: classification.ring_decisions(scenes.layout, headline, HEADLINE), sizes.repeats)
    return dict(counts=counts, theta0=theta0, amplitude_ns=per_echo * 1e9, amplitude_ping_us=per_ping * 1e6,
                consistency=consistency, consistency_ns=seconds / rows * 1e9, consistency_rows=rows)


def _triads(sizes: Sizes, seed: int) -> dict:
    triad = azimuth.shipped_triad()
    runs = {}
    for level, sigma in enumerate(NOISE_LEVELS):
        timer = azimuth.TIMER if sigma > 0 else 0.0
        repeats = sizes.repeats if sigma == HEADLINE else 1
        runs[sigma] = azimuth.compare_estimators(triad, sigma, sizes.triad_echoes, generator(seed, "triads", level),
                                                 timer=timer, call_size=3, calls=sizes.ping_calls,
                                                 repeats=repeats, call_repeats=repeats)
    return dict(triad=triad.name, runs=runs)


def _pipeline(layout, sizes: Sizes) -> dict:
    """Core time per ping of the nodes' two steps on the graph benchmark's ping (48 pairs x 3 pole echoes)."""
    try:
        graph = importlib.import_module("sonar_ring.benchmark.graph")
    except ImportError as exc:
        return dict(error=f"not measured: {exc}")
    echoes = graph.benchmark_echoes(layout, np.random.default_rng(0))
    settings = pipeline.Settings()
    hypotheses = pipeline.localise_ping(layout, echoes, settings)

    def localise():
        for _ in range(sizes.ping_calls):
            pipeline.localise_ping(layout, echoes, settings)

    def classify():
        for _ in range(sizes.ping_calls):
            pipeline.classify_ping(layout, echoes, hypotheses, settings)

    best = interleaved_best({"localise_ping": localise, "classify_ping": classify}, sizes.repeats)
    return dict(rows=echoes.n_echoes, **{name: seconds / sizes.ping_calls * 1e6 for name, seconds in best.items()})


def _graph(quick: bool) -> dict:
    """The running graph's benchmark (needs rclpy and the built messages), or why it was not run."""
    try:
        importlib.import_module("rclpy")
    except ImportError:
        return dict(error="needs ROS 2 (source tools/env.sh)")
    try:
        graph = importlib.import_module("sonar_ring.benchmark.graph")
        return graph.run(quick=quick)
    except ImportError as exc:
        return dict(error=f"needs ROS 2 and the built package (source tools/env.sh): {exc}")
    except Exception as exc:  # a report of ten sections should not be lost to one failing graph
        traceback.print_exc()
        return dict(error=f"failed: {exc}")


# --------------------------------------------------------------------------- all of it

def measure(seed: int, quick: bool, progress=progress_to_stderr) -> Results:
    """Run every measurement of the report.

    Parameters
    ----------
    seed : int
        Seed of every random stream.
    quick : bool
        Small sizes (:data:`QUICK`): checks the report end to end in seconds;
        its figures are not for reading.
    progress : callable
        Called with a line of text before each step.
    """
    sizes = QUICK if quick else FULL
    progress("simulating the standard scenes")
    scenes = standard_scenes(sizes.poses_per_scene, sizes.room_stride, generator(seed, "scene poses"))
    sweep = bearing_sweep(sizes.sweep, generator(seed, "bearing sweep"))
    rows_by_key = {}
    for family in (BEARING, *RING_FAMILIES):
        for method in family.methods:
            rows_by_key[family.name, method.name] = Row(family.name, method.name, method.role, family.unit)
        if family.name in LSQ_MODELS:
            rows_by_key[family.name, LSQ_NAME] = Row(family.name, LSQ_NAME, BASELINE, family.unit)
    pick = generator(seed, "least-squares subsample")
    lsq_index = {}
    for family in RING_FAMILIES:
        if family.name in LSQ_MODELS:
            count = int(np.isin(scenes.pairs.truth_class, family.classes).sum())
            lsq_index[family.name] = np.sort(pick.choice(count, min(sizes.lsq_points, count), replace=False))

    tables, batches = {}, {}
    for level, sigma in enumerate(NOISE_LEVELS):
        progress(f"accuracy at sigma_t = {sigma * 1e6:g} us")
        tof = scenes.noisy_tof(sigma, generator(seed, "ring TOF noise", level))
        tables[sigma] = dict(scenes.table, tof=tof)
        batches[sigma] = Batch.of(scenes.pairs, scenes.paths(tof))
        with np.errstate(invalid="ignore", divide="ignore"):  # the papers' formulas give NaN where they fail
            for family in RING_FAMILIES:
                _ring_level(rows_by_key, family, batches[sigma], sigma, lsq_index)
            _bearing_level(rows_by_key, sweep, sigma, generator(seed, "sweep noise", level))

    progress(f"timing (batches of {sizes.batch:,} echoes and pings of {PING_ROWS}, best of {sizes.repeats})")
    headline = batches[HEADLINE]
    with np.errstate(invalid="ignore", divide="ignore"):
        for family in RING_FAMILIES:
            echoes = family.select(headline)
            _time_methods(rows_by_key, family.name, family.methods, echoes.take(_tile(len(echoes), sizes.batch)),
                          echoes.take(_tile(len(echoes), PING_ROWS)), sizes)
            if family.name in LSQ_MODELS:
                _time_least_squares(rows_by_key[family.name, LSQ_NAME], family.name, echoes, sizes)
        d1, d2 = sweep.noisy_paths(HEADLINE, generator(seed, "timing inputs"))
        _time_methods(rows_by_key, BEARING.name, BEARING.methods,
                      (sweep, d1[_tile(d1.size, sizes.batch)], d2[_tile(d2.size, sizes.batch)]),
                      (sweep, d1[:PING_ROWS], d2[:PING_ROWS]), sizes)

    progress("classification")
    classified = _classification(scenes, tables, sizes, seed)
    progress("triads")
    triads = _triads(sizes, seed)
    progress("per-ping pipeline")
    core = _pipeline(scenes.layout, sizes)
    progress("graph (ping -> markers)")
    graph = _graph(quick)
    scene_rows = {name: int(np.sum(scenes.pairs.scene == k)) for k, name in enumerate(scenes.names)}
    incomplete = int(scenes.table["group"].size - len(scenes.pairs))
    return Results(seed, quick, sizes, sweep.separation, scene_rows, incomplete, list(rows_by_key.values()),
                   classified, triads, core, graph)

