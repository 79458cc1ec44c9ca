"""``difffilter-eval``: Monte Carlo evaluation of every estimator on a scenario.

Usage::

    difffilter-eval four_tank_bias --runs 100 --out reports/
    difffilter-eval lfc --ckpt checkpoints/lfc_nn_grad.ckpt --runs 20
    difffilter-eval all
    difffilter-eval --list

Each scenario writes ``<out>/<scenario>/{metrics.json, report.md, *.png}`` and
TensorBoard events under ``<out>/<scenario>/tb`` (``tensorboard --logdir <out>``).
A family name (``four_tank``, ``lfc``, …) selects its headline scenarios.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from pathlib import Path

from difffilter.models import registry
from difffilter.runtime import tune_cpu_allocator

from .report import summary_table, write_report
from .suite import run_suite

__all__ = ["main", "build_parser", "resolve_scenarios", "evaluate", "check_output_folder"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="difffilter-eval",
        description=(
            "Evaluate estimators and detectors on a scenario and write metrics.json, "
            "report.md, plots and TensorBoard logs."
        ),
    )
    p.add_argument("scenario", nargs="?", help="scenario name, family name or 'all' (see --list)")
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
    """Expand ``name`` (a scenario, a family or ``all``) to scenario names; ``ValueError`` if unknown.

    ``all`` and a family name run the scenarios marked ``headline``; variants are run by
    their own names.
    """
    if name == "all":
        return registry.names(headline_only=True)
    if name in registry.families():
        return registry.names(name, headline_only=True) or registry.names(name)
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
    """Evaluate every scenario; returns ``{scenario: metrics}``.

    A scenario runs the generic Monte Carlo suite and report writer unless it names its
    family's own evaluation (``Scenario.evaluator``, ``"module:function"``), which is
    called once with all the scenarios of the call that name it.
    """
    if runs is not None and (isinstance(runs, bool) or not isinstance(runs, int) or runs < 1):
        raise ValueError(f"--runs must be an integer >= 1; got {runs!r}")
    if ckpt is not None and not Path(ckpt).is_file():
        raise FileNotFoundError(f"--ckpt: no checkpoint file at {ckpt}")
    grouped: dict[str, list[str]] = {}
    for name in scenarios:
        evaluator = registry.get(name).evaluator
        grouped.setdefault(evaluator or "", []).append(name)
    results: dict = {}
    for evaluator, names in grouped.items():
        if evaluator:
            module, func = evaluator.split(":")
            run = getattr(importlib.import_module(module), func)
            kwargs = {"out": Path(out), "seed": seed, "progress": progress, "ckpt": ckpt}
            kwargs["per_channel"] = per_channel  # a family's optional extra study
            if runs is not None:
                kwargs["runs"] = runs
            results.update(run(names, **kwargs))
            continue
        for name in names:
            result = run_suite(registry.get(name), runs=runs, seed=seed, progress=progress)
            results[name] = write_report(Path(out) / name, result)
    return results


def check_output_folder(out: Path) -> None:
    """Create ``out`` and prove it writable; ``ValueError`` naming ``--out`` otherwise."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out: {out} exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".difffilter-write-check"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise ValueError(f"--out: cannot write to {out} ({exc.strerror or exc})") from None


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
        check_output_folder(args.out)  # before any work, not after the whole evaluation
        if args.runs is not None and args.runs < 1:
            raise ValueError(f"--runs must be an integer >= 1; got {args.runs}")
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
