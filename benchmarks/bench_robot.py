"""Throughput of ``mdpf_fused_ci`` (lidar robot: two MDPF locals fused by covariance intersection).

``bench_mdpf_fused()`` returns one dict per dtype: 100 runs × 100 particles × 2 local
estimators × 100 steps in one batched program, one intra-op thread as in the evaluation
suite, in run-steps per second (target ≥ 5,000 on the 2-core machine), by wall time (the
target's measure) and by this process's CPU time (what the run costs when other processes
share the two cores; the 1-minute load average is printed beside it: at a load above 2
the wall figure measures the neighbours as much as the filter). ``make bench`` prints it;
alone: ``python benchmarks/bench.py --only-robot`` or ``python benchmarks/bench_robot.py``.

Evaluation runs in float64 (the scenario's default dtype); float32 agrees to float32
precision up to resampling flips (position RMSE within 0.1 %) and ``torch.randn`` alone,
one draw per particle and state component per step, costs ~5× more in float64 on this CPU.
"""

from __future__ import annotations

import os

from timing import time_registered_estimator

from difffilter.models import registry

__all__ = ["bench_mdpf_fused", "TARGET_RATE"]

TARGET_RATE = 5_000


def bench_mdpf_fused(runs: int = 100, steps: int = 100) -> list[dict]:
    particles = registry.get("robot_actuator_attack").num_particles
    rows = []
    for dtype, seconds, cpu in time_registered_estimator(
        "robot_actuator_attack", "mdpf_fused_ci", runs, cpu=True
    ):
        rate, cpu_rate = runs * steps / seconds, runs * steps / cpu
        verdict = "met" if rate >= TARGET_RATE else f"MISSED ({rate / TARGET_RATE:.2f} of 5,000)"
        rows.append({"dtype": dtype, "B": runs, "N": particles, "T": steps, "seconds": seconds,
                     "run_steps_per_s": rate, "cpu_seconds": cpu, "run_steps_per_cpu_s": cpu_rate,
                     "load_average": os.getloadavg()[0], "target": verdict})  # fmt: skip
    return rows


if __name__ == "__main__":
    for r in bench_mdpf_fused():
        print(r)
