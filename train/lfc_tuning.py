"""Validation grid searches for the LFC estimators' open hyperparameters.

The paper leaves the initial-weight scale, the EKF's process noise, the order of
operations inside a step, the baseline's learning rate and its Luenberger gain open. This
script scores every combination on random attacks of the validation seeds (never the
four test scenarios) and writes the scores and the winners as JSON (default
``reports/lfc_tuning.json``; the shipped ``checkpoints/lfc_tuning.json`` is the provenance
of the defaults in :mod:`difffilter.models.lfc_estimators`, and is only replaced when
asked for by name)::

    python -m difffilter.train.lfc_tuning --runs 16 --out reports/lfc_tuning.json

Score: RMSE of the attack estimate over all channels and steps (``val/attack_rmse``, the
metric ``kf_nn_grad``'s checkpoints are selected on). Settings that break down or
overflow score ``inf``, written as null with ``"diverged": true`` (strict JSON; a grid
whose every point diverged chooses nothing, said on stderr); one that diverges within
float64 scores its huge RMSE (lr = 0.3: 2.7e82).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time
from pathlib import Path

import torch

from difffilter.control import LuenbergerDesign
from difffilter.estimator import Generators
from difffilter.linalg import NumericalBreakdown
from difffilter.models import registry
from difffilter.models.lfc_estimators import (
    EKF_DEFAULTS,
    FINETUNE_DEFAULTS,
    GD_DEFAULTS,
    LFCContext,
    card_options,
    check_lfc_card,
    lfc_estimator,
    paper_network,
)
from difffilter.param_ekf import EKFRule, GradientRule

__all__ = ["validation_batch", "score", "tune", "main"]

VALIDATION_SEED = 2_000_003  # disjoint from the evaluation seeds (0 … 10⁶) and training seeds


def validation_batch(runs: int, seed: int = VALIDATION_SEED) -> dict:
    """Random attacks on all ten channels with plant noise and a random load (float64):
    the draws of ``lfc_random_attacks`` from the named streams of ``seed``."""
    from difffilter.train.task import training_batch

    return training_batch(registry.get("lfc_random_attacks"), runs, seed, torch.float64)


def score(estimator, batch: dict, *, init_seed: int = 1) -> dict:
    """Validation attack RMSE (all channels), state-5 RMSE and wall time of ``estimator``
    in its closed loop on ``batch``."""
    scenario = registry.get("lfc_random_attacks")
    gens = Generators(init=torch.Generator().manual_seed(init_seed))
    start = time.perf_counter()
    try:
        with torch.no_grad():
            loop = scenario.loop(estimator, batch, generator=gens)
    except ValueError as error:
        # a setting that diverges: its NaN input or measurement stops the loop, or its
        # filter's arithmetic breaks down; it scores inf (it had stopped the whole grid,
        # the scores before it lost: an lfc-tuning trial)
        if not (isinstance(error, NumericalBreakdown) or "contains NaN or Inf" in str(error)):
            raise
        wall = time.perf_counter() - start
        return {"attack_rmse": math.inf, "attack_rmse_attacked": math.inf,
                "state5_rmse": math.inf, "wall_s": wall}  # fmt: skip
    wall = time.perf_counter() - start
    err = (loop.output.attack - batch["attack"]).square().mean()
    rmse = float(err.sqrt()) if bool(torch.isfinite(err)) else math.inf
    attacked = batch["attack"] != 0
    att = (loop.output.attack - batch["attack"])[attacked].square().mean()
    s5 = loop.trajectories.x[..., 4].square().mean()
    return {
        "attack_rmse": rmse,
        "attack_rmse_attacked": float(att.sqrt()) if bool(torch.isfinite(att)) else math.inf,
        "state5_rmse": float(s5.sqrt()) if bool(torch.isfinite(s5)) else math.inf,
        "wall_s": wall,
    }


GRIDS = {
    "kf_nn_ekf": {
        "init_scale": [0.01, 0.1, 1.0],
        "process_noise": [0.0, 1e-5, 1e-3],
        "subtract": ["posterior", "prior"],
    },
    "traditional_ad": {
        "init_scale": [0.01, 0.1, 1.0],
        "lr": [1e-3, 1e-2, 1e-1],
        "luenberger_design": ["modal", "robust", "diagonal"],
    },
    # Fine-tuning a trained network: rho(0) must be small, or the first EKF step rewrites it.
    "kf_nn_grad_ekf": {
        "init_cov": [1e-6, 1e-4, 1e-2],
        "process_noise": [0.0, 1e-7],
        "subtract": ["posterior", "prior"],
    },
}


def _estimator(name: str, setting: dict, ctx: LFCContext, checkpoint):
    """The estimator ``name`` with the grid point ``setting`` (the names are translated to
    objects here, once)."""
    rule_kw = {k: v for k, v in setting.items() if k in ("process_noise", "lr", "init_cov")}
    posterior = setting.get("subtract", "posterior") == "posterior"
    if name == "traditional_ad":
        rule = GradientRule(**{**GD_DEFAULTS, **rule_kw})
        s = setting["init_scale"]
        return lfc_estimator(ctx, luenberger=LuenbergerDesign(setting["luenberger_design"]), rule=rule,
                             network=paper_network(s), init_scale=s)  # fmt: skip
    if name == "kf_nn_ekf":
        rule = EKFRule(**{**EKF_DEFAULTS, **rule_kw}, donate=True)
        s = setting["init_scale"]
        return lfc_estimator(ctx, network=paper_network(s), rule=rule, init_scale=s,
                             posterior=posterior)  # fmt: skip
    net, card = checkpoint
    rule = EKFRule(**{**FINETUNE_DEFAULTS, **rule_kw}, donate=True)
    # the observer of the kf_nn_grad_ekf entry, every option of the card (card_options)
    return lfc_estimator(ctx, network=net, rule=rule, posterior=posterior, **card_options(card))


def tune(
    estimators=("kf_nn_ekf", "traditional_ad"),
    *,
    runs: int = 16,
    progress: bool = True,
    ckpt=None,
    log=print,
) -> dict:
    """Score every grid point of ``GRIDS[name]``; returns the table and the chosen settings."""
    from difffilter.models.neural_estimator import checkpoint_sha256

    checkpoint = tuned_checkpoint(estimators, ckpt)
    ctx = LFCContext(dt=0.01)
    batch = validation_batch(runs)
    out = {
        "validation": {
            "runs": runs,
            "seed": VALIDATION_SEED,
            "steps": int(batch["attack"].shape[-2]),  # the validation scenario's horizon
            "metric": "attack RMSE over all channels and steps",
        },
        "grids": {},
        "chosen": {},
        "validated_on": {},
    }
    for name in estimators:
        grid = GRIDS[name]
        keys = list(grid)
        rows = []
        for values in itertools.product(*(grid[k] for k in keys)):
            setting = dict(zip(keys, values))
            res = score(_estimator(name, setting, ctx, checkpoint), batch)
            diverged = not math.isfinite(res["attack_rmse"])
            rows.append({**setting, **res, **({"diverged": True} if diverged else {})})
            if progress:
                log(f"{name} {setting} -> {res['attack_rmse']:.4f} ({res['wall_s']:.0f}s)")
        best = min(rows, key=lambda r: r["attack_rmse"])
        out["grids"][name] = rows
        # each grid's own validation (a later run of one grid had relabelled the others'),
        # and the network a fine-tuning grid tuned
        out["validated_on"][name] = dict(out["validation"]) | (
            {"checkpoint_sha256": checkpoint_sha256(ckpt)} if name == "kf_nn_grad_ekf" else {}
        )
        if best.get("diverged"):  # (an inf score had been "chosen" and written as Infinity)
            print(f"lfc_tuning: every point of the {name} grid diverged: nothing chosen for it",
                  file=sys.stderr)  # fmt: skip
            continue
        out["chosen"][name] = {k: best[k] for k in keys} | {"attack_rmse": best["attack_rmse"]}
    return out


def tuned_checkpoint(estimators, ckpt):
    """``(network, card)`` of ``ckpt`` (``None`` without one), checked: ``kf_nn_grad_ekf``
    fine-tunes a trained LFC network of the 10 ms plant (``ValueError`` naming ``--ckpt``)."""
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    checkpoint = None if ckpt is None else load_estimator_checkpoint(ckpt)
    if "kf_nn_grad_ekf" in estimators and checkpoint is None:
        raise ValueError("tuning kf_nn_grad_ekf needs --ckpt (the trained network)")
    if checkpoint is not None and (why := check_lfc_card(checkpoint[1], 0.01)) is not None:
        raise ValueError(f"--ckpt {ckpt}: {why}")
    return checkpoint


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m difffilter.train.lfc_tuning", description=__doc__, allow_abbrev=False
    )
    p.add_argument("--runs", type=int, default=16)
    p.add_argument(
        "--out",
        type=Path,
        default=Path("reports/lfc_tuning.json"),
        help="output JSON, merged into if it exists (default reports/lfc_tuning.json)",
    )
    p.add_argument(
        "--estimators", nargs="+", default=["kf_nn_ekf", "traditional_ad"], choices=sorted(GRIDS)
    )
    p.add_argument("--ckpt", type=Path, default=None, help="trained network (kf_nn_grad_ekf)")
    args = p.parse_args(argv)
    if args.runs < 1:
        p.error("--runs must be >= 1")
    # the output read before the grid runs: a folder or a file that is not this script's
    # JSON had been found after every point was scored, the scores lost (a trial)
    if args.out.exists() and not args.out.is_file():
        p.error(f"--out {args.out} is not a file: give the JSON file to write (or merge into)")
    previous = {}
    if args.out.is_file():
        try:
            previous = json.loads(args.out.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as error:
            p.error(f"--out {args.out} exists and is not JSON ({error}): give another file")
        if not isinstance(previous, dict):
            p.error(f"--out {args.out} holds JSON of another kind: give another file")
    try:  # (before any grid point: a traceback had said it)
        tuned_checkpoint(args.estimators, args.ckpt)
    except (ValueError, FileNotFoundError) as error:
        p.error(str(error))
    result = tune(args.estimators, runs=args.runs, ckpt=args.ckpt)
    previous.setdefault("grids", {}).update(result["grids"])
    # a grid scored again replaces its choice, and one that chose nothing (every point
    # diverged) leaves none: the file before's choice had stayed beside this run's grid of
    # diverged rows, and the LFC report printed it (a review)
    for name in result["grids"]:
        previous.setdefault("chosen", {}).pop(name, None)
    previous["chosen"].update(result["chosen"])
    previous["validation"] = result["validation"]  # this run's (each grid's: validated_on)
    previous.setdefault("validated_on", {}).update(result.get("validated_on", {}))
    previous["ekf_fixed"] = {k: v for k, v in EKF_DEFAULTS.items() if k != "process_noise"}
    # strict JSON (a diverged point's inf score had been written as bare Infinity) and
    # atomic (a stopped write had left a cut file in place of the merged one)
    from difffilter.eval.report import json_safe
    from difffilter.models.atomic_write import write_json_atomically

    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomically(args.out, json_safe(previous))
    print(json.dumps(result["chosen"], indent=2))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
