"""Wall-clock timing for the benchmarks: best of N, and methods timed in alternation."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Hashable, Mapping


def best_time(function: Callable[[], object], repeats: int = 3) -> float:
    """Shortest wall-clock time of ``repeats`` calls of ``function``, s (``time.perf_counter``).

    The minimum, not the mean: on a shared machine other jobs only ever add time.
    """
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - start)
    return best


def interleaved_best(functions: Mapping[Hashable, Callable[[], object]], repeats: int) -> dict:
    """Best-of-``repeats`` time of each function, s, the functions called in turn in every round.

    Alternating spreads a burst of load from other processes over all methods
    alike instead of penalising whichever happened to run during it.
    """
    best = {name: math.inf for name in functions}
    for _ in range(repeats):
        for name, function in functions.items():
            start = time.perf_counter()
            function()
            best[name] = min(best[name], time.perf_counter() - start)
    return best
