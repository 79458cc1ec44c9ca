"""``make demo``: the main job on the shipped defaults.

1. The library's filters on the attack-free four-tank plant
   (:func:`difffilter.models.four_tank_estimators.filter_comparison`): state RMSE and time
   per step of the linearised KF, the EKF, the UKF and the bootstrap and Kalman-proposal PFs.
2. ``difffilter-eval all``: every headline scenario, each with its shipped checkpoint where
   it has one, reports under ``--out``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from difffilter.models.four_tank_estimators import filter_comparison

__all__ = ["main"]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m difffilter.eval.demo", description=__doc__.splitlines()[0]
    )
    p.add_argument("--out", type=Path, default=Path("reports"))
    p.add_argument(
        "--runs",
        type=int,
        default=None,
        help="Monte Carlo runs of the evaluations (default: each family's)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--skip-eval", action="store_true", help="only the filter comparison")
    args = p.parse_args(argv)

    print("== Filters on the four-tank plant (no attack; 100 runs × 100 steps, float64) ==")
    print(f"{'filter':22s} {'state RMSE (cm)':>16s} {'time/step (s)':>14s}")
    for name, row in filter_comparison(seed=args.seed).items():
        print(f"{name:22s} {row['state_rmse']:16.5f} {row['time_per_step_s']:14.2e}")
    print(
        "(state RMSE against the simulated truth, over all runs, steps and the four levels; the PFs use N = 1000)"
    )
    if args.skip_eval:
        return 0

    from difffilter.eval.cli import evaluate, resolve_scenarios
    from difffilter.eval.report import summary_table

    scenarios = resolve_scenarios("all")
    print(f"\n== Evaluations: {', '.join(scenarios)} -> {args.out}/ ==")
    results = evaluate(
        scenarios,
        ckpt=None,  # each scenario's shipped checkpoint
        runs=args.runs,
        out=args.out,
        seed=args.seed,
        progress=True,
        # The LFC per-channel validation (80 runs per estimator, about as costly as the four
        # scenarios together) stays off: `make demo` takes about 6 minutes on 2 cores without it.
        # `difffilter-eval lfc --per-channel` runs it.
        per_channel=False,
    )
    print("\n" + summary_table(results))
    print(
        f"\nReports: {args.out}/<scenario>/report.md; TensorBoard: .venv/bin/tensorboard --logdir {args.out}"
    )
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
