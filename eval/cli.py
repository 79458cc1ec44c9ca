"""``difffilter-eval``: Monte Carlo evaluation of every estimator on a scenario.

Usage::

    difffilter-eval four_tank_bias --runs 100 --out reports/
    difffilter-eval lfc --ckpt checkpoints/lfc_nn_grad.ckpt --runs 20
    difffilter-eval all
    difffilter-eval --list

Each scenario writes ``<out>/<scenario>/{metrics.json, report.md, *.png}`` and
TensorBoard events under ``<out>/<scenario>/tb`` (``tensorboard --logdir <out>``).
Family names (``four_tank``, ``lfc``) select every scenario of that family.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from difffilter.models import registry
from difffilter.runtime import tune_cpu_allocator

from .report import summary_table

__all__ = ["main", "build_parser", "resolve_scenarios", "evaluate"]

#: Scenarios run by `all` and by a family name (variants are reachable by their own names).
FAMILY_DEFAULTS = {
    "four_tank": ["four_tank_bias"],
    "lfc": ["lfc_step", "lfc_sine", "lfc_simultaneous", "lfc_sawtooth"],
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="difffilter-eval",
        description=(
            "Evaluate estimators and detectors on a scenario and write metrics.json, "
            "report.md, plots and TensorBoard logs."
        ),
    )
    p.add_argument(
        "scenario", nargs="?", help="scenario name, family name (four_tank, lfc) or 'all'"
    )
    p.add_argument(
        "--ckpt", type=Path, default=None, help="trained estimator checkpoint (LFC scenarios)"
    )
    p.add_argument(
        "--runs", type=int, default=None, help="Monte Carlo runs (default: the scenario family's)"
    )
    p.add_argument(
        "--out", type=Path, default=Path("reports"), help="output folder (default: reports/)"
    )
    p.add_argument(
        "--seed", type=int, default=0, help="master seed of every random draw (default 0)"
    )
    p.add_argument(
        "--per-channel",
        action="store_true",
        help="also run the LFC per-channel validation (random attacks on each channel, "
        "80 runs x 6 estimators x 1000 steps; its wall time goes into its metrics.json)",
    )
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    p.add_argument("--list", action="store_true", help="list the registered scenarios and exit")
    return p


def resolve_scenarios(name: str) -> list[str]:
    """Expand ``name`` (a scenario, a family or ``all``) to scenario names; ``ValueError`` if unknown."""
    known = registry.names()
    if name == "all":
        out = []
        for family in FAMILY_DEFAULTS:
            out += resolve_scenarios(family) if registry.names(family) else []
        return out
    if name in FAMILY_DEFAULTS:
        members = registry.names(name)
        if not members:
            raise ValueError(f"no scenarios registered for family {name!r}")
        default = FAMILY_DEFAULTS[name]
        return [n for n in (default or members) if n in members]
    if name not in known:
        registry.get(name)  # raises ValueError listing the known names
    return [name]


def evaluate(
    scenarios: Sequence[str],
    *,
    ckpt: Path | None,
    runs: int | None,
    out: Path,
    seed: int,
    progress: bool,
    per_channel: bool = False,
) -> dict:
    """Run the evaluation of every scenario, grouped by family; returns ``{scenario: metrics}``."""
    if runs is not None and runs < 1:
        raise ValueError(f"--runs must be >= 1; got {runs}")
    if ckpt is not None and not Path(ckpt).is_file():
        raise FileNotFoundError(f"--ckpt: no checkpoint file at {ckpt}")
    by_family: dict[str, list[str]] = {}
    for name in scenarios:
        by_family.setdefault(registry.get(name).family, []).append(name)
    results: dict = {}
    for family, names in by_family.items():
        kwargs = {"out": Path(out), "seed": seed, "progress": progress}
        if runs is not None:
            kwargs["runs"] = runs
        if family == "four_tank":
            from difffilter.eval.four_tank import run_four_tank

            results.update(run_four_tank(names, **kwargs))
        elif family == "lfc":
            from difffilter.eval.lfc import run_lfc

            # The per-channel validation is a separate study (its own seeds and run count),
            # as long as the scenarios themselves: only on request.
            pc_runs = {} if per_channel else {"per_channel_runs": 0}
            results.update(run_lfc(names, ckpt=ckpt, **kwargs, **pc_runs))
        else:  # pragma: no cover - a registered family without an evaluator
            raise ValueError(f"no evaluator for scenario family {family!r}")
    return results


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.list:
        for s in registry.all_scenarios():
            print(f"{s.name:28s} [{s.family}] {s.description}")
        return 0
    if not args.scenario:
        parser.error("a scenario name is required (or --list)")
    tune_cpu_allocator()
    try:
        names = resolve_scenarios(args.scenario)
        results = evaluate(
            names,
            ckpt=args.ckpt,
            runs=args.runs,
            out=args.out,
            seed=args.seed,
            progress=not args.no_progress,
            per_channel=args.per_channel,
        )
    except (ValueError, FileNotFoundError) as exc:
        print(f"difffilter-eval: error: {exc}", file=sys.stderr)
        return 2
    print("\n" + summary_table(results) + "\n")
    print(
        f"reports written under {args.out}/ (open the TensorBoard logs with: tensorboard --logdir {args.out})"
    )
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
