"""Wall-clock timing shared by the benchmark scripts."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

__all__ = ["best_time", "best_times", "time_registered_estimator"]


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
    return min(_round(fn, min_time, clock) for _ in range(repeats))


def _round(fn: Callable[[], object], min_time: float, clock: Callable[[], float]) -> float:
    """Seconds per call of one round: ``fn`` called until ``min_time`` has passed."""
    n, start = 0, clock()
    while True:
        fn()
        n += 1
        elapsed = clock() - start
        if elapsed >= min_time:
            return elapsed / n


def best_times(
    fns: dict[str, Callable[[], object]],
    repeats: int = 3,
    min_time: float = 0.2,
    clock: Callable[[], float] = time.perf_counter,
) -> dict[str, float]:
    """:func:`best_time` of several functions, their rounds alternating (``a b a b …``):
    what a ratio of two of them needs on a shared machine, where the load changes from
    one second to the next (both see the same load, in turn). ``{name: seconds per call}``."""
    for fn in fns.values():
        fn()  # warm-up
    best = dict.fromkeys(fns, math.inf)
    for _ in range(repeats):
        for name, fn in fns.items():
            best[name] = min(best[name], _round(fn, min_time, clock))
    return best


def time_registered_estimator(scenario: str, estimator: str, runs: int, *, cpu: bool = False):
    """``[(dtype name, wall seconds, CPU seconds or None)]`` of one batched run of the
    registered ``estimator`` on ``runs`` simulated runs of ``scenario`` (seed 0, float64 then
    float32), as the evaluation suite runs it: one intra-op thread, no gradients."""
    import torch

    from difffilter.models import registry
    from difffilter.models.estimators import SuiteContext, get
    from difffilter.models.streams import Streams

    sc, rows = registry.get(scenario), []
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for dtype in (torch.float64, torch.float32):
            model, streams = sc.system(dtype), Streams(0)
            gens = streams.simulation()
            tr = sc.simulate(runs, gens, dtype=dtype, model=model)
            run = get(estimator).factory(SuiteContext(sc, model, runs, streams))
            with torch.no_grad():
                wall = best_time(lambda run=run, tr=tr: run(tr), repeats=3, min_time=0.0)
                cpu_s = (
                    best_time(lambda run=run, tr=tr: run(tr), 3, 0.0, clock=time.process_time)
                    if cpu
                    else None
                )
            rows.append((str(dtype).replace("torch.", ""), wall, cpu_s))
    finally:
        torch.set_num_threads(threads)
    return rows
