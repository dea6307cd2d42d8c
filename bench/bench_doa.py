"""Kreczmer's phase-shift azimuth: Table 1, the §7 wall experiment, and three estimators compared.

Regenerate ``bench/results/doa.md`` (about two minutes on one core):

    cd /work/main && .venv/bin/python bench/bench_doa.py

Constants are the paper's: 40 kHz, lambda = 8.7 mm (c = 348 m/s), timer tick 0.33 us.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common import machine  # noqa: E402

from sonar_ring import doa  # noqa: E402
from sonar_ring.geometry import load_layout  # noqa: E402

WAVELENGTH = 8.7e-3
SPEED = 348.0
PERIOD = WAVELENGTH / SPEED
TIMER = 0.33e-6
CROSSING_STD = 0.2e-6
MM, US = 1e-3, 1e-6
DISTANCES = (1.0, 1.5, 2.0)
ROTATIONS = np.arange(-50, 51)
GROSS_ERROR = 10.0  # deg: the wrong lobes of these triads are >= 20 deg away, noise is < 3 deg (3 sigma)
RESULT = ROOT / "bench" / "results" / "doa.md"

PAPER_TABLE_1 = [  # b1, b2 (mm), range (deg), eps, dt (us), min delta phi (deg)
    (11, 15, 50, 0.05, 0.9, 1.2),
    (11, 4, 50, 0.08, 1.4, 2.2),
    (4, 11, 60, 0.4, 1.5, 4.7),
    (4, 11, 50, 0.3, 2.5, 7.8),
]


def best_time(function, repeats=3) -> float:
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - start)
    return best


# --------------------------------------------------------------------------- the triads

class Triad:
    """Receivers (3, 3) and emitter (3,) of a module facing +x, with its eps and max angle."""

    def __init__(self, name, receivers, emitter, eps, max_angle):
        self.name = name
        self.receivers = np.asarray(receivers, dtype=float)
        self.emitter = np.asarray(emitter, dtype=float)
        self.b1, self.b2 = np.linalg.norm(np.diff(self.receivers[:, :2], axis=0), axis=1)
        self.eps = eps
        self.max_angle = max_angle

    def azimuth(self, t01, t02):
        """:func:`doa.azimuth` with this triad's baselines, eps and max angle."""
        return doa.azimuth(t01, t02, self.b1, self.b2, WAVELENGTH, SPEED, self.eps, self.max_angle)


def shipped_triad() -> Triad:
    layout = load_layout("kreczmer_triad")
    robust = doa.robustness(11 * MM, 4 * MM, layout.beam_half_angle, WAVELENGTH, SPEED)
    return Triad(f"shipped kreczmer_triad (b1, b2) = (11, 4) mm, eps = {robust.eps:.2f} (ours, +-60 deg)",
                 layout.group_receivers()[0], layout.transmitters[layout.group_transmitters[0, 0]], robust.eps,
                 layout.beam_half_angle)


def paper_experiment_triad() -> Triad:
    # §7 used eps = 0.3, which Table 1 pairs with (b1, b2) = (4, 11) mm over +-50 deg.
    receivers = [[0.0, 0.0, 0.0], [0.0, -4 * MM, 0.0], [0.0, -15 * MM, 0.0]]
    return Triad("(b1, b2) = (4, 11) mm, eps = 0.3 (the paper's §7 value)", receivers, [0.0, -7.5 * MM, 0.02], 0.3,
                 math.radians(60))


# --------------------------------------------------------------------------- §7 wall experiment

def wall_experiment(triad: Triad, distances, rotations_deg, trials, rng, crossing_std=CROSSING_STD):
    """Phase delays of the emitter's image in a wall, module rotated by alpha about its middle.

    Returns the expected azimuth (eq 9: -alpha) and the delays (N, 2), N = D * R * trials, in
    (distance, rotation, trial) order.
    """
    middle = 0.5 * (triad.receivers[0] + triad.receivers[2])
    distance, alpha, _ = np.meshgrid(distances, np.radians(rotations_deg), np.arange(trials), indexing="ij")
    distance, alpha = distance.ravel(), alpha.ravel()
    normal_angle = -alpha
    plane_offset = distance + np.cos(normal_angle) * middle[0] + np.sin(normal_angle) * middle[1]
    image = doa.wall_image(triad.emitter, plane_offset, normal_angle)
    delays = doa.phase_delays(image[:, :2], triad.receivers[:, :2], WAVELENGTH, SPEED, crossing_std=crossing_std,
                              timer_resolution=TIMER, rng=rng)
    return -alpha, delays


def right_orders(triad: Triad, result, delays, expected):
    """True where the chosen (n1, n2) are the right ones.

    The chosen pair's unwrapped path differences ``c t mod lambda - n lambda`` must match
    ``b sin(expected)`` to within half a wavelength on both baselines; noise moves them by
    ~0.1 mm, a wrong order by a whole wavelength.
    """
    paths = np.mod(SPEED * delays, WAVELENGTH) - np.stack([result.n1, result.n2], axis=-1) * WAVELENGTH
    truth = np.sin(expected)[:, None] * [triad.b1, triad.b1 + triad.b2]
    return (result.candidates == 1) & np.all(np.abs(paths - truth) < WAVELENGTH / 2, axis=-1)


def wall_monte_carlo(triad: Triad, trials: int, rng) -> dict:
    expected, delays = wall_experiment(triad, DISTANCES, ROTATIONS, trials, rng)
    result = triad.azimuth(delays[:, 0], delays[:, 1])
    shape = (len(DISTANCES), ROTATIONS.size, trials)
    error = np.degrees(result.angle - expected).reshape(shape)
    unique = (result.candidates == 1).reshape(shape)
    correct = right_orders(triad, result, delays, expected).reshape(shape)
    good = np.where(correct, error, np.nan)
    return dict(
        three_sigma=3 * np.nanstd(good, axis=2),  # (D, R), deg, over correct solutions
        bias=np.nanmean(good, axis=2),
        unique=unique.mean(axis=2),
        correct=correct.mean(axis=2),
        valid=result.valid.reshape(shape).mean(axis=2),
    )


def noise_sweep(triad: Triad, crossing_stds, trials, rng) -> list[tuple]:
    rows = []
    central = np.abs(ROTATIONS) <= 20
    for crossing_std in crossing_stds:
        expected, delays = wall_experiment(triad, [1.5], ROTATIONS, trials, rng, crossing_std)
        result = triad.azimuth(delays[:, 0], delays[:, 1])
        error = np.degrees(result.angle - expected).reshape(ROTATIONS.size, trials)
        correct = right_orders(triad, result, delays, expected).reshape(ROTATIONS.size, trials)
        three_sigma = 3 * np.nanstd(np.where(correct, error, np.nan)[central])
        budget = doa.timing_error_budget(doa.delay_std(crossing_std, TIMER), TIMER)
        rows.append((crossing_std, budget, correct.mean(axis=1).min(), correct.mean(), three_sigma))
    return rows


# --------------------------------------------------------------------------- the estimators compared

def wrap_path(path):
    """Path difference reduced to [-lambda/2, lambda/2)."""
    return np.mod(path + WAVELENGTH / 2, WAVELENGTH) - WAVELENGTH / 2


def grid_search(t01, t02, b1, b2, grid, chunk=500):
    """Brute force: the grid azimuth whose wrapped delays best fit both measured ones.

    Cost: GLS norm (correlation 0.5) of the two path residuals, each wrapped to one
    wavelength, so the search needs no (n1, n2).  Returns the angle (rad) per echo.
    """
    t01, t02 = np.atleast_1d(t01), np.atleast_1d(t02)
    sines = np.sin(grid)
    best = np.empty(t01.shape)
    for start in range(0, t01.size, chunk):
        part = slice(start, start + chunk)
        r1 = wrap_path(SPEED * t01[part, None] - b1 * sines)
        r2 = wrap_path(SPEED * t02[part, None] - (b1 + b2) * sines)
        best[part] = grid[np.argmin(r1 * r1 + r2 * r2 - r1 * r2, axis=1)]
    return best


def direct_sub_half_wavelength(t01, t02, b2):
    """Eq 1 on the R1 -- R2 pair (b2 = 4 mm < lambda / 2 = 4.35 mm): unambiguous, no search."""
    sine = wrap_path(SPEED * (np.asarray(t02) - np.asarray(t01))) / b2
    return np.arcsin(np.clip(sine, -1.0, 1.0)), np.abs(sine) <= 1.0


def compare_estimators(triad: Triad, crossing_std, n, rng) -> list[tuple]:
    angle = rng.uniform(-math.radians(50), math.radians(50), n)
    distance = rng.uniform(1.0, 4.0, n)  # image distance of a wall 0.5 .. 2 m away
    middle = 0.5 * (triad.receivers[0, :2] + triad.receivers[2, :2])
    source = middle + distance[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    delays = doa.phase_delays(source, triad.receivers[:, :2], WAVELENGTH, SPEED, crossing_std=crossing_std,
                              timer_resolution=TIMER, rng=rng)
    t01, t02 = delays[:, 0], delays[:, 1]
    coarse = np.radians(np.arange(-60, 60.001, 0.1))
    fine = np.radians(np.arange(-60, 60.0001, 0.01))
    methods = [
        ("Kreczmer (n1, n2) search", lambda a, b: _kreczmer(triad, a, b)),
        ("grid search over phi, 0.1 deg", lambda a, b: (grid_search(a, b, triad.b1, triad.b2, coarse), None)),
        ("grid search over phi, 0.01 deg", lambda a, b: (grid_search(a, b, triad.b1, triad.b2, fine), None)),
        ("direct, R1-R2 pair (4 mm < lambda/2)", lambda a, b: direct_sub_half_wavelength(a, b, triad.b2)),
    ]
    rows = []
    scalar_calls = 300
    for name, method in methods:
        estimate, valid = method(t01, t02)
        valid = np.ones(n, dtype=bool) if valid is None else valid
        error = np.degrees(estimate - angle)[valid]
        gross = np.abs(error) > GROSS_ERROR
        batched = best_time(lambda method=method: method(t01, t02)) / n
        one_by_one = best_time(lambda method=method: [method(t01[i], t02[i]) for i in range(scalar_calls)], 7)
        one_by_one /= scalar_calls
        good = error[~gross]
        rows.append((name, 1 - valid.mean(), gross.sum() / n, 3 * good.std(), np.sqrt(np.mean(good**2)),
                     np.abs(error).max(), batched, one_by_one))
    return rows


def _kreczmer(triad: Triad, t01, t02):
    result = triad.azimuth(t01, t02)
    return result.angle, result.valid


# --------------------------------------------------------------------------- report

def table_1_section() -> list[str]:
    lines = ["## Table 1 recomputed (§6.2)", "",
             "Our procedure (`doa.robustness`, dt step 0.1 us, eps step 0.01, azimuth step 0.05 deg, delay errors "
             "handled exactly as intervals) next to the paper's. `exact dt*` is the limit with vanishing steps. "
             "`min dphi`: paper = mean of eq 8 over both pairs at 0 deg (their estimator averages the two arcsines); "
             "ours = worst case of our GLS-fused estimate at 0 deg, at our dt.", "",
             "| b1, b2 [mm] | range | eps paper | eps ours | dt paper [us] | dt ours [us] | exact dt* [us] "
             "| min dphi paper [deg] | min dphi ours [deg] | edge dphi ours [deg] |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for b1, b2, half_range, eps, dt, min_error in PAPER_TABLE_1:
        ours = doa.robustness(b1 * MM, b2 * MM, math.radians(half_range), WAVELENGTH, SPEED)
        exact = doa.robustness(b1 * MM, b2 * MM, math.radians(half_range), WAVELENGTH, SPEED, delay_step=0.001 * US,
                               eps_step=1e-6)
        lines.append(f"| {b1}, {b2} | +-{half_range} | {eps} | {ours.eps:.2f} | {dt} | {ours.delay_error / US:.1f} "
                     f"| {exact.delay_error / US:.3f} | {min_error} | {math.degrees(ours.angle_error_centre):.2f} "
                     f"| {math.degrees(ours.angle_error_edge):.2f} |")
    lines += ["", "Differences: (4, 11) +-60: the paper's eps 0.4 is an artefact of its loop -- at dt = 1.6 us the "
              "correct arcsine argument sin 60 + c dt / 4 mm exceeds 1, no eps can find it, and the loop kept "
              "raising eps until the nearest wrong pair (mismatch lambda/15 mm - 0.176 = 0.404) passed, reporting "
              "0.40; the eps that dt = 1.5 us needs is 0.17. (4, 11) +-50: one step of dt; the exact limit is "
              "2.63 us, and at 2.6 us our eps = 0.29 clears the wrong pair by only 0.0035, so the paper's "
              "constants or rounding (it prints 0.3) flip that step.", ""]
    return lines


def wall_section(triad: Triad, trials, rng) -> list[str]:
    mc = wall_monte_carlo(triad, trials, rng)
    central = np.abs(ROTATIONS) <= 20
    lines = [f"### {triad.name}", "",
             f"{trials} pings per rotation and distance; crossing jitter {CROSSING_STD / US:.1f} us per receiver, "
             f"timer {TIMER / US:.2f} us (delay sigma {doa.delay_std(CROSSING_STD, TIMER) / US:.3f} us, "
             f"budget 3 sigma + tick = {doa.timing_error_budget(doa.delay_std(CROSSING_STD, TIMER), TIMER) / US:.2f}"
             f" us).", "",
             f"- 3 sigma in -20..20 deg: max {mc['three_sigma'][:, central].max():.2f} deg "
             f"(paper: below 2 deg); over -50..50 deg: max {mc['three_sigma'].max():.2f} deg",
             f"- unique solution: min {mc['unique'].min():.4f}, mean {mc['unique'].mean():.4f}; "
             f"unique and correct: min {mc['correct'].min():.4f}; valid (|phi| <= max angle): "
             f"min {mc['valid'].min():.4f}",
             f"- |bias| max {np.abs(mc['bias']).max():.3f} deg", "",
             "| rotation [deg] | " + " | ".join(f"3 sigma {d} m [deg]" for d in DISTANCES)
             + " | bias 1 m [deg] | unique rate (all d) | unique and correct (all d) |",
             "|---|" + "---|" * (len(DISTANCES) + 3)]
    for i, rotation in enumerate(ROTATIONS):
        if rotation % 5:
            continue
        lines.append(f"| {rotation} | " + " | ".join(f"{mc['three_sigma'][k, i]:.2f}" for k in range(len(DISTANCES)))
                     + f" | {mc['bias'][0, i]:+.3f} | {mc['unique'][:, i].mean():.4f} "
                     f"| {mc['correct'][:, i].mean():.4f} |")
    return lines + [""]


def sweep_section(triads, rng) -> list[str]:
    lines = ["### Noise sweep (wall at 1.5 m, 200 pings per 1 deg of rotation)", "",
             "| triad | crossing jitter [us] | budget 3 sigma + tick [us] | min unique-and-correct rate over angles "
             "| mean rate | 3 sigma in -20..20 [deg] |", "|---|---|---|---|---|---|"]
    for triad in triads:
        robust = doa.robustness(triad.b1, triad.b2, math.radians(50), WAVELENGTH, SPEED)
        for row in noise_sweep(triad, [0.1 * US, 0.2 * US, 0.4 * US, 0.6 * US, 1.0 * US], 200, rng):
            lines.append(f"| ({triad.b1 / MM:.0f}, {triad.b2 / MM:.0f}), eps {triad.eps:.2f}, robust dt "
                         f"{robust.delay_error / US:.1f} us | {row[0] / US:.1f} | {row[1] / US:.2f} | {row[2]:.4f} "
                         f"| {row[3]:.4f} | {row[4]:.2f} |")
    return lines + [""]


def estimator_section(triad: Triad, rng) -> list[str]:
    lines = ["## Estimators compared (shipped triad)", "",
             "Near-field point sources, azimuth uniform in -50..50 deg, 1-4 m (a wall's image at 0.5-2 m). "
             "Error statistics exclude invalid results and gross errors (> 10 deg: a wrong lobe for the phase "
             "searches; for the direct estimate, which has a single lobe, noise tails), counted separately. "
             "Time per estimate: batched over all echoes, and one call per echo (scalar inputs, Python loop). "
             "The grid search covers -60..60 deg and minimises the GLS norm of the two wrapped path residuals.",
             ""]
    for crossing_std in (CROSSING_STD, 0.6 * US):
        n = 20000
        rows = compare_estimators(triad, crossing_std, n, rng)
        lines += [f"### crossing jitter {crossing_std / US:.1f} us, timer {TIMER / US:.2f} us, {n} echoes", "",
                  "| method | invalid | gross errors | 3 sigma [deg] | RMS [deg] | max abs [deg] "
                  "| batched [us/estimate] | one call per echo [us] |", "|---|---|---|---|---|---|---|---|"]
        for name, invalid, gross, three_sigma, rms, worst, batched, single in rows:
            lines.append(f"| {name} | {invalid:.4f} | {gross:.4f} | {three_sigma:.3f} | {rms:.3f} | {worst:.2f} "
                         f"| {batched / US:.2f} | {single / US:.0f} |")
        kreczmer, fine = rows[0], rows[2]
        lines += ["", f"Grid search (0.01 deg) / Kreczmer time: batched x{fine[6] / kreczmer[6]:.0f}, "
                  f"per call x{fine[7] / kreczmer[7]:.1f}; direct / Kreczmer 3 sigma: "
                  f"x{rows[3][3] / kreczmer[3]:.1f}.", ""]
    return lines


def main() -> None:
    rng = np.random.default_rng(2017)
    shipped, paper = shipped_triad(), paper_experiment_triad()
    lines = ["# Phase-shift azimuth (Kreczmer 2017) -- `sonar_ring.doa`", "",
             "Regenerate: `cd /work/main && .venv/bin/python bench/bench_doa.py`", "",
             f"Machine: {machine()}.", "",
             f"Constants: lambda = {WAVELENGTH / MM} mm, c = {SPEED} m/s (40 kHz), timer {TIMER / US} us; "
             "random seed 2017.", ""]
    lines += table_1_section()
    lines += ["## §7 wall experiment, Monte Carlo", "",
              f"Walls at {', '.join(str(d) for d in DISTANCES)} m; module rotated -50..50 deg in 1 deg steps "
              "about its middle; expected azimuth -alpha (eq 9). Exact near-field image-source delays, "
              "zero-crossing jitter per receiver before the period wrap, asynchronous timer ticks. "
              "Rows every 5 deg.", ""]
    lines += wall_section(shipped, 1000, rng)
    lines += wall_section(paper, 1000, rng)
    lines += sweep_section([shipped, paper], rng)
    lines += estimator_section(shipped, rng)
    RESULT.parent.mkdir(parents=True, exist_ok=True)
    RESULT.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
