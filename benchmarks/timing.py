"""Wall-clock timing shared by the benchmark scripts."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

__all__ = ["best_time"]


def best_time(fn: Callable[[], object], repeats: int = 3, min_time: float = 0.2) -> float:
    """Best wall time of one call of ``fn()`` over ``repeats`` rounds (each round ≥ ``min_time`` s).

    The best round, not the mean, because on a shared 2-core machine the noise is one-sided:
    other processes only ever make a round slower.
    """
    fn()  # warm-up (allocator, lazy initialisation)
    best = math.inf
    for _ in range(repeats):
        n, start = 0, time.perf_counter()
        while True:
            fn()
            n += 1
            elapsed = time.perf_counter() - start
            if elapsed >= min_time:
                break
        best = min(best, elapsed / n)
    return best
