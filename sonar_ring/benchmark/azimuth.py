"""Phase-shift azimuth of a Kreczmer triad: his (n1, n2) search against a grid search and a sub-lambda/2 pair.

Constants are the paper's: 40 kHz, lambda = 8.7 mm (c = 348 m/s), timer tick
0.33 us.  Sources are near-field points (a wall's image) in front of the
shipped ``kreczmer_triad``; the phase delays come from
:func:`sonar_ring.doa.phase_delays` with zero-crossing jitter and the timer.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sonar_ring import doa
from sonar_ring.benchmark.timing import best_time
from sonar_ring.geometry import load_layout

WAVELENGTH = 8.7e-3
SPEED = 348.0
TIMER = 0.33e-6
MM, US = 1e-3, 1e-6
MAX_SOURCE_ANGLE = math.radians(50.0)
GROSS_ERROR = math.radians(10.0)
"""An error this large is a wrong lobe: the shipped triad's wrong lobes are >= 20 deg away, noise < 3 deg (3 sigma)."""


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
    """The shipped ``kreczmer_triad`` layout, (b1, b2) = (11, 4) mm, with its robust eps over its beam."""
    layout = load_layout("kreczmer_triad")
    robust = doa.robustness(11 * MM, 4 * MM, layout.beam_half_angle, WAVELENGTH, SPEED)
    return Triad(f"shipped kreczmer_triad (b1, b2) = (11, 4) mm, eps = {robust.eps:.2f} (ours, +-60 deg)",
                 layout.group_receivers()[0], layout.transmitters[layout.group_transmitters[0, 0]], robust.eps,
                 layout.beam_half_angle)


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


def estimators(triad: Triad) -> list[tuple[str, str, Callable]]:
    """``(name, role, estimate(t01, t02) -> (angle, valid or None))`` of each method compared."""
    coarse = np.radians(np.arange(-60, 60.001, 0.1))
    fine = np.radians(np.arange(-60, 60.0001, 0.01))

    def kreczmer(t01, t02):
        result = triad.azimuth(t01, t02)
        return result.angle, result.valid

    return [
        ("Kreczmer (n1, n2) search", "production", kreczmer),
        ("grid search over phi, 0.1 deg", "baseline",
         lambda a, b: (grid_search(a, b, triad.b1, triad.b2, coarse), None)),
        ("grid search over phi, 0.01 deg", "baseline",
         lambda a, b: (grid_search(a, b, triad.b1, triad.b2, fine), None)),
        ("direct, R1-R2 pair (4 mm < lambda/2)", "baseline",
         lambda a, b: direct_sub_half_wavelength(a, b, triad.b2)),
    ]


@dataclass(frozen=True)
class EstimatorRun:
    """One estimator on one set of echoes.

    Attributes
    ----------
    name, role : str
    error : ndarray, shape (n,)
        Estimated minus true azimuth, rad; NaN where not valid.
    valid : ndarray of bool, shape (n,)
    batched : float
        Time per estimate in one call over all n echoes, s (best of ``repeats``).
    per_call : float
        Time of one call with ``call_size`` echoes, s (best of ``call_repeats`` loops of ``calls`` calls).
    """

    name: str
    role: str
    error: np.ndarray
    valid: np.ndarray
    batched: float
    per_call: float


def compare_estimators(triad: Triad, crossing_std: float, n: int, rng: np.random.Generator, *, timer: float = TIMER,
                       call_size: int = 1, calls: int = 300, repeats: int = 3,
                       call_repeats: int = 7) -> list[EstimatorRun]:
    """Every estimator of :func:`estimators` on the same n near-field echoes.

    Sources at azimuths uniform in -50..50 deg and 1-4 m from the triad's middle
    (a wall's image at 0.5-2 m); delays with zero-crossing jitter ``crossing_std``
    (s) and a timer of tick ``timer`` (s, 0 for exact times).
    """
    angle = rng.uniform(-MAX_SOURCE_ANGLE, MAX_SOURCE_ANGLE, n)
    distance = rng.uniform(1.0, 4.0, n)
    middle = 0.5 * (triad.receivers[0, :2] + triad.receivers[2, :2])
    source = middle + distance[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    delays = doa.phase_delays(source, triad.receivers[:, :2], WAVELENGTH, SPEED, crossing_std=crossing_std,
                              timer_resolution=timer, rng=rng)
    t01, t02 = delays[:, 0], delays[:, 1]
    runs = []
    for name, role, method in estimators(triad):
        estimate, valid = method(t01, t02)
        valid = np.ones(n, dtype=bool) if valid is None else valid
        batched = best_time(lambda method=method: method(t01, t02), repeats) / n
        # One echo: scalar arguments, as a caller looping over echoes passes them.
        args = (t01[0], t02[0]) if call_size == 1 else (t01[:call_size], t02[:call_size])

        def loop(method=method, args=args):
            for _ in range(calls):
                method(*args)

        per_call = best_time(loop, call_repeats) / calls
        runs.append(EstimatorRun(name, role, np.where(valid, estimate - angle, np.nan), valid, batched, per_call))
    return runs
