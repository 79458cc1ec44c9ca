"""Throughput of ``mdpf_fused_ci`` (lidar robot: two MDPF locals fused by covariance intersection).

``bench_mdpf_fused()`` returns one dict per dtype: 100 runs × 100 particles × 2 local
estimators × 100 steps in one batched program, one intra-op thread as in the evaluation
suite, in run-steps per second (target ≥ 5,000 on the 2-core machine). ``make bench``
prints it; alone: ``python benchmarks/bench.py --only-robot`` or ``python benchmarks/bench_robot.py``.
"""

from __future__ import annotations

from timing import time_registered_estimator

from difffilter.models import registry

__all__ = ["bench_mdpf_fused"]

TARGET_RATE = 5_000


def bench_mdpf_fused(runs: int = 100, steps: int = 100) -> list[dict]:
    particles = registry.get("robot_actuator_attack").num_particles
    rows = []
    for dtype, seconds, _ in time_registered_estimator(
        "robot_actuator_attack", "mdpf_fused_ci", runs
    ):
        rate = runs * steps / seconds
        rows.append({"dtype": dtype, "B": runs, "N": particles, "T": steps, "seconds": seconds,
                     "run_steps_per_s": rate, "target": rate >= TARGET_RATE})  # fmt: skip
    return rows


if __name__ == "__main__":
    for r in bench_mdpf_fused():
        print(r)
