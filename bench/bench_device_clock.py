"""Device clock benchmark: how far the published stamps are from the instant each transmitter fired.

Regenerate ``bench/results/device_clock.md`` and ``bench/plots/device_clock_error.png``
(about half a minute), from the repository root with its environment sourced:

    python bench/bench_device_clock.py

The case the driver is held to: the device clock runs 50 ppm fast from its own epoch,
each frame's transport delay is uniform over 0..10 ms, and the sender stalls
once for 100 ms (the frames fired meanwhile arrive together when it ends).
:class:`sonar_ring.device_clock.DeviceClock` stamps every frame as the driver
does; the error is its stamp minus the true firing time.  ``--seeds N`` changes
the number of independent runs per rate (default 50); every random number comes
from the seeds, so a rerun reproduces the file except for the timing line.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from sonar_ring.benchmark.environment import machine
from sonar_ring.device_clock import DeviceClock

ROOT = Path(__file__).resolve().parents[1]

RESULT = ROOT / "bench" / "results" / "device_clock.md"
FIGURE = ROOT / "bench" / "plots" / "device_clock_error.png"
DRIFT = 50e-6
MAX_DELAY = 0.010
STALL = 0.1
RATES = {30: 120.0, 100: 60.0, 300: 30.0, 1000: 10.0}
"""Frames per second (30: the Browne ring's ping rate) and seconds of frames per run."""
WARM_UP = 2.0
SPANS_30_HZ = ((0, 2), (2, 5), (5, 10), (10, 20), (20, 30), (30, 60), (60, 120))
"""Stretches of time since the first frame, s, for the table of the ring's rate."""
BOOT_EPOCH_NS = 1_750_000_000 * 10**9


def run(rate: float, seconds: float, seed: int) -> dict[str, np.ndarray]:
    """One run: per frame its time since the first one (s), and the stamp errors of the estimate and on arrival (s).

    ``bound`` is what an estimate that knew the drift would do at best: the
    least delay of any frame so far.
    """
    rng = np.random.default_rng(seed)
    fired = np.arange(round(rate * seconds)) / rate
    delay = rng.uniform(0.0, MAX_DELAY, fired.size)
    stall_at = rng.uniform(WARM_UP, seconds - STALL)
    stalled = (fired >= stall_at) & (fired < stall_at + STALL)
    delay[stalled] += stall_at + STALL - fired[stalled]
    start = rng.uniform(1.0, 3600.0)  # the device booted this long before its first frame
    device_us = np.round((start + fired) * (1 + DRIFT) * 1e6).astype(np.int64)
    fired_ns = BOOT_EPOCH_NS + np.round((start + fired) * 1e9).astype(np.int64)
    arrival_ns = fired_ns + np.round(delay * 1e9).astype(np.int64)
    clock = DeviceClock()
    stamps = np.array([clock.stamp(int(d), int(a)) for d, a in zip(device_us, arrival_ns, strict=True)])
    return {"since_start": fired, "device": (stamps - fired_ns) * 1e-9, "arrival": delay,
            "bound": np.minimum.accumulate(delay)}


def runs(rate: float, seconds: float, seeds: int) -> dict[str, np.ndarray]:
    """:func:`run` for ``seeds`` seeds, concatenated."""
    results = [run(rate, seconds, seed) for seed in range(seeds)]
    return {key: np.concatenate([result[key] for result in results]) for key in results[0]}


def micro(values: np.ndarray, q: float) -> str:
    return f"{np.percentile(np.abs(values), q) * 1e6:,.0f}"


def rate_table(by_rate: dict, seeds: int) -> list[str]:
    lines = [f"## Stamp error after a {WARM_UP:g} s warm-up, by frame rate", "",
             f"|stamp - true firing time| over every frame from {WARM_UP:g} s after the first one, {seeds} runs per "
             "rate (each with its own stall time and device boot time), in µs.  `on arrival`: the frame's arrival "
             "as its stamp, what the driver published before.", "",
             "| frames/s | run [s] | stamps | median | p90 | p99 | p99.9 | max | within 0.1 ms [%] | on arrival: "
             "median | p99 | max |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for rate, result in by_rate.items():
        after = result["since_start"] >= WARM_UP
        error, arrival = result["device"][after], result["arrival"][after]
        lines.append(f"| {rate} | {RATES[rate]:g} | {error.size:,} | {micro(error, 50)} | {micro(error, 90)} | "
                     f"{micro(error, 99)} | {micro(error, 99.9)} | {micro(error, 100)} | "
                     f"{100 * np.mean(np.abs(error) <= 1e-4):.2f} | {micro(arrival, 50)} | {micro(arrival, 99)} | "
                     f"{micro(arrival, 100)} |")
    return [*lines, ""]


def ring_table(result: dict, seeds: int) -> list[str]:
    lines = ["## At the ring's 30 Hz, by time since the first frame", "",
             f"|stamp - true firing time| in µs over {seeds} runs.  `bound`: the least delay of any frame so far, "
             "what an estimate that knew the drift would reach at best (the line's error comes from the fastest "
             "frames' delays, here one frame in a hundred within 0.1 ms of the truth).", "",
             "| since start [s] | median | p99 | max | bound: median | bound: p99 |", "|---|---|---|---|---|---|"]
    for low, high in SPANS_30_HZ:
        within = (result["since_start"] >= low) & (result["since_start"] < high)
        error, bound = result["device"][within], result["bound"][within]
        lines.append(f"| {low}-{high} | {micro(error, 50)} | {micro(error, 99)} | {micro(error, 100)} | "
                     f"{micro(bound, 50)} | {micro(bound, 99)} |")
    return [*lines, ""]


def cost() -> str:
    """Seconds per :meth:`DeviceClock.stamp` call, median of five repetitions of 30 000 frames."""
    result = []
    device_us = np.arange(30_000) * 33_333
    arrival = BOOT_EPOCH_NS + device_us * 1000 + np.random.default_rng(0).integers(0, 10_000_000, device_us.size)
    pairs = list(zip(device_us.tolist(), arrival.tolist(), strict=True))
    for _ in range(5):
        clock = DeviceClock()
        started = time.perf_counter()
        for d, a in pairs:
            clock.stamp(d, a)
        result.append((time.perf_counter() - started) / len(pairs))
    return f"Cost: {np.median(result) * 1e6:.1f} µs per frame (median of five runs of 30 000 frames)."


def figure(by_rate: dict, path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    plot = Figure(figsize=(11, 4.2))
    cdf, over_time = plot.subplots(1, 2)
    for rate, result in by_rate.items():
        after = np.sort(np.abs(result["device"][result["since_start"] >= WARM_UP])) * 1e3
        cdf.plot(after, np.arange(1, after.size + 1) / after.size, label=f"device clock, {rate} frames/s")
    arrival = np.sort(by_rate[30]["arrival"][by_rate[30]["since_start"] >= WARM_UP]) * 1e3
    cdf.plot(arrival, np.arange(1, arrival.size + 1) / arrival.size, "k--", label="on arrival")
    cdf.axvline(0.1, color="grey", lw=0.8)
    cdf.set(xscale="log", xlim=(1e-4, 200), xlabel="|stamp - firing time| [ms]", ylabel="fraction of stamps",
            title=f"After a {WARM_UP:g} s warm-up")
    cdf.legend(loc="upper left", fontsize=8)
    ring = by_rate[30]
    edges = np.arange(0, RATES[30] + 1, 2.0)
    which = np.digitize(ring["since_start"], edges) - 1
    centres = (edges[:-1] + edges[1:]) / 2
    for q, style, name in ((50, "-", "median"), (99, "--", "p99"), (100, ":", "max")):
        values = [np.percentile(np.abs(ring["device"][which == i]), q) * 1e3 for i in range(len(centres))]
        over_time.plot(centres, values, style, color="tab:blue", label=f"device clock, {name}")
    bound = [np.percentile(ring["bound"][which == i], 50) * 1e3 for i in range(len(centres))]
    over_time.plot(centres, bound, color="tab:grey", label="bound (drift known), median")
    over_time.axhline(0.1, color="grey", lw=0.8)
    over_time.set(yscale="log", xlabel="time since the first frame [s]", ylabel="|stamp - firing time| [ms]",
                  title="The ring's 30 Hz, in 2 s bins")
    over_time.legend(fontsize=8)
    plot.tight_layout()
    FigureCanvasAgg(plot)
    path.parent.mkdir(parents=True, exist_ok=True)
    plot.savefig(path, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=50, help="runs per frame rate (default 50)")
    args = parser.parse_args()
    by_rate = {rate: runs(rate, seconds, args.seeds) for rate, seconds in RATES.items()}
    lines = ["# Device clock -- `sonar_ring.device_clock`", "",
             "Regenerate: `python bench/bench_device_clock.py` (from the repository root, environment sourced).", "",
             f"Machine: {machine()}.", "",
             f"Case: device clock {DRIFT * 1e6:g} ppm fast, transport delay uniform over 0..{MAX_DELAY * 1e3:g} ms "
             f"per frame, one {STALL * 1e3:g} ms stall of the sender per run (at a random time after the warm-up); "
             "frames in the device's order.  Seeds 0..N-1.", "",
             f"![Stamp error distribution](../plots/{FIGURE.name})", ""]
    lines += rate_table(by_rate, args.seeds)
    lines += ring_table(by_rate[30], args.seeds)
    lines += [cost(), ""]
    figure(by_rate, FIGURE)
    RESULT.parent.mkdir(parents=True, exist_ok=True)
    RESULT.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
