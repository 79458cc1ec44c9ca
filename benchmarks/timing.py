"""Wall-clock timing shared by the benchmark scripts."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

__all__ = ["best_time"]


def best_time(
    fn: Callable[[], object],
    repeats: int = 3,
    min_time: float = 0.2,
    clock: Callable[[], float] = time.perf_counter,
) -> float:
    """Best wall time of one call of ``fn()`` over ``repeats`` rounds (each round ≥ ``min_time`` s).

    The best round, not the mean, because on a shared 2-core machine the noise is one-sided:
    other processes only ever make a round slower. ``clock=time.process_time`` measures
    the CPU time of this process instead (what a single-threaded run costs when other
    processes take turns on the cores; not a wall-clock figure).
    """
    fn()  # warm-up (allocator, lazy initialisation)
    best = math.inf
    for _ in range(repeats):
        n, start = 0, clock()
        while True:
            fn()
            n += 1
            elapsed = clock() - start
            if elapsed >= min_time:
                break
        best = min(best, elapsed / n)
    return best
