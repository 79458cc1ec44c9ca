"""Throughput of ``mdpf_fused_ci`` (lidar robot: two MDPF locals fused by covariance intersection).

``bench_mdpf_fused()`` returns one dict per dtype: 100 runs × 100 particles × 2 local
estimators × 100 steps in one batched program, one intra-op thread as in the evaluation
suite, in run-steps per second (target ≥ 5,000 on the 2-core machine). ``make bench``
prints it; alone: ``python benchmarks/bench.py --only-robot`` or ``python benchmarks/bench_robot.py``.
"""

from __future__ import annotations

import torch
from timing import best_time

from difffilter.eval.estimators import SuiteContext, get
from difffilter.eval.streams import Streams
from difffilter.models import registry

__all__ = ["bench_mdpf_fused"]

TARGET_RATE = 5_000


def bench_mdpf_fused(runs: int = 100, steps: int = 100) -> list[dict]:
    sc = registry.get("robot_actuator_attack")
    rows = []
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for dtype in (torch.float64, torch.float32):
            model = sc.system(dtype)
            streams = Streams(0)
            tr = sc.simulate(
                runs,
                {k: streams(k) for k in ("plant", "attack", "schedule")},
                dtype=dtype,
                model=model,
            )
            run = get("mdpf_fused_ci").factory(SuiteContext(sc, model, runs, streams))
            with torch.no_grad():
                seconds = best_time(lambda run=run, tr=tr: run(tr), repeats=3, min_time=0.0)
            rate = runs * steps / seconds
            rows.append({"dtype": str(dtype).replace("torch.", ""), "B": runs, "N": sc.num_particles, "T": steps,
                         "seconds": seconds, "run_steps_per_s": rate, "target": rate >= TARGET_RATE})  # fmt: skip
    finally:
        torch.set_num_threads(threads)
    return rows


if __name__ == "__main__":
    for r in bench_mdpf_fused():
        print(r)
