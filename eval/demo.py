"""``make demo``: the main job on the shipped defaults.

1. Filters on the four-tank plant (docs/scenarios.md, four-tank; no attack): simulate 100 runs,
   run the linearised KF, the EKF, the UKF and the bootstrap and Kalman-proposal PFs,
   and print the state RMSE of each against the truth and its time per step.
2. The evaluations: ``difffilter-eval`` on the four-tank bias attack and on the
   load-frequency-control scenarios with the shipped checkpoint, writing reports under
   ``--out``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

import difffilter as df
from difffilter.models.four_tank import FourTankModel
from difffilter.particle import KalmanProposal, particle_filter

__all__ = ["filter_comparison", "main"]


def linearised_four_tank(model: FourTankModel) -> tuple[df.LinearGaussianModel, torch.Tensor]:
    """The four-tank model linearised at its fixed point ``x*``: ``δx_{k+1} = F δx_k + w``.

    Returns the linear model (in deviation coordinates) and ``x*`` to shift by.
    """
    x_star = model.initial.mean
    F = model.transition_jacobian(x_star, None, 0)
    lin = df.LinearGaussianModel(
        F,
        model.G,
        model.process_noise.cov,
        model.measurement_noise.cov,
        torch.zeros_like(x_star),
        model.initial.cov,
    )
    return lin, x_star


def _timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


@torch.no_grad()
def filter_comparison(
    runs: int = 100, steps: int = 100, particles: int = 1000, seed: int = 0
) -> dict[str, dict[str, float]]:
    """State RMSE (against the simulated truth, all runs, steps and components) per filter."""
    model = FourTankModel(dtype=torch.float64)
    gen = torch.Generator().manual_seed(seed)
    xs, ys, _ = model.simulate(steps, (runs,), generator=gen)
    lin, x_star = linearised_four_tank(model)
    filters = {
        "kf_linearised": lambda: df.kalman_filter(lin, ys - x_star).means + x_star,
        "ekf": lambda: df.extended_kalman_filter(model, ys).means,
        "ukf": lambda: df.unscented_kalman_filter(model, ys).means,
        "pf_bootstrap": lambda: (
            particle_filter(
                model,
                ys,
                num_particles=particles,
                generator=torch.Generator().manual_seed(seed + 1),
            ).means
        ),
        "pf_kalman_proposal": lambda: (
            particle_filter(
                model,
                ys,
                num_particles=particles,
                proposal=KalmanProposal(),
                generator=torch.Generator().manual_seed(seed + 1),
            ).means
        ),
    }
    table = {}
    for name, run in filters.items():
        means, seconds = _timed(run)
        table[name] = {
            "state_rmse": float(df.metrics.rmse(means, xs)),
            "time_per_step_s": seconds / steps,
        }
    return table


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
    ckpt = Path("checkpoints/lfc_nn_grad.ckpt")
    print(f"\n== Evaluations: {', '.join(scenarios)} -> {args.out}/ ==")
    results = evaluate(
        scenarios,
        ckpt=ckpt if ckpt.is_file() else None,
        runs=args.runs,
        out=args.out,
        seed=args.seed,
        progress=True,
        # The LFC per-channel validation (80 runs per estimator, about as costly as the four
        # scenarios together) stays off: `make demo` must finish in 5 minutes on 2 cores.
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
