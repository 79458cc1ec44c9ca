"""``difffilter-train calibrate``: a checkpoint's alarm threshold for a false-alarm rate.

A learned estimator alarms when its score exceeds the threshold its card carries. This
command chooses that threshold the way the evaluation calibrates every detector
(:func:`difffilter.metrics.threshold_for`), on attack-free runs of the card's
training scenario, and checks it on other attack-free runs::

    τ_α = the smallest score τ with #{calibration steps with s > τ} ≤ ⌊α n⌋
    measured rate = #{check steps with s > τ_α} / #check steps

Both sets of runs come from seeds of their own (``Streams(seed)`` streams
``checkpoint-calibration`` and ``checkpoint-calibration/check``, default ``seed`` 5),
never the evaluation's (``--seed 0`` and its ``far-calibration`` stream) nor training's.
The estimator runs as the evaluation runs it (its registered entry: the suite's particle
filter, its own closed loop where the scenario has one).

It writes a new checkpoint (the weights unchanged, the card's ``threshold`` and
``target_false_alarm_rate`` set) and its card, with a ``calibration`` entry holding the
target, both sets of runs, the measured rates and, where the estimator names it, the
statistic the threshold is for (``score``: e.g. the LFC head's ``"attack probability"``,
:attr:`difffilter.Detection.statistic`), and, where the calibration's alarms cluster in a
few runs, ``clustered`` (their count and the independent alarms they are worth,
:func:`difffilter.eval.calibration.alarm_clustering`; the command then says to calibrate
on more runs); like ``export`` it replaces an existing
``--out`` only with ``--force``::

    difffilter-train calibrate checkpoints/four_tank_nn_grad.ckpt --far 0.01 \\
        --out checkpoints/four_tank_nn_grad.ckpt --force

``--restart α`` (``off``: none) sets how the estimator runs before its threshold is chosen:
the card's ``restart``, the false-alarm rate of the χ²-gated copy from which a Gaussian
filter's compensation restarts (:class:`~difffilter.fdi.neural.NeuralCompensation`);
``--confirm β`` (``off``: none) the card's ``confirm``, the rate of that copy's χ² test that
must alarm with the network for its score to count; ``--reject ρ`` (``off``: none) the
card's ``reject``, the rate of the χ² test of the compensated innovation where failing it
the filter keeps its prediction. The scores, and so the threshold, are those of the
estimator so configured.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

from difffilter._checks import check_rate
from difffilter.fdi.neural import restart_applies
from difffilter.interrupts import signals_deferred, stop_words
from difffilter.models.atomic_write import sibling_name, write_json_atomically
from difffilter.models.neural_estimator import RUN_OPTIONS

from .common import check_checkpoint_out, load_source

__all__ = ["calibrate_checkpoint", "estimator_name", "main"]

#: The master seed of the calibration runs (differs from every default study seed).
CALIBRATION_SEED = 5
#: ``restart`` / ``confirm`` / ``reject`` left as the card has it.
KEEP = "keep"


def estimator_name(card) -> str:
    """The registry entry that evaluates a checkpoint of ``card``: the card's ``estimator``,
    else ``pf_nn_<trainer>`` for a particle filter and ``gaussian_nn_<trainer>`` for the
    Kalman-type filters (the cards written before the entry was recorded)."""
    if card.estimator:
        return card.estimator
    return f"{'pf' if card.filter == 'pf' else 'gaussian'}_nn_{card.trainer}"


def _scores(scenario, name: str, path, runs: int, seed: int, progress: bool):
    """``(scores [runs, T], statistic)``: the detection scores of estimator ``name``
    (checkpoint ``path``) on ``runs`` attack-free runs of ``scenario`` from master seed
    ``seed``, and what they are (:attr:`~difffilter.Detection.statistic`, or ``None``)."""
    from difffilter.eval.suite import run_suite

    result = run_suite(scenario.with_threat(None), runs=runs, seed=seed, estimators=[name],
                       checkpoint={name: str(path)}, progress=progress)  # fmt: skip
    if name not in result.outputs:
        why = result.skipped.get(name, "it did not run")
        raise ValueError(f"{path}: {name} cannot run on {scenario.name}: {why}")
    det = result.outputs[name].detection
    if det is None or det.scores is None:
        raise ValueError(f"{path}: {name} gives no detection scores to calibrate")
    return det.scores, det.statistic


def _new_check(src: Path, scored: Path, card) -> dict | None:
    """The card's reproducibility check (``difffilter-train export``'s) of the estimator as it
    now runs (``scored``: ``src``, or a file of its restart, confirm or reject changed), where
    ``src``'s card has one: recomputed at every calibration, so that a card recalibrated after
    the library's numbers moved states what it gives now (the tracking card's had kept its
    export's 0.73555 beside today's 0.73457: a trial). ``None`` where there is none."""
    from .export import check_metric

    card_json = src.with_suffix(".json")
    old = (
        json.loads(card_json.read_text(encoding="utf-8")).get("check")
        if card_json.is_file()
        else None
    )
    if old is None:
        return None
    plant = _check_scenario(src, old.get("scenario", card.scenario))
    if plant is None:  # (a plant of one's own that this process cannot load: a review)
        changed = scored != src
        fate = "left out (the estimator runs otherwise now)" if changed else "kept as it was"
        print(f"note: the card's check was made on {old.get('scenario')!r}, which is not "
              f"registered here: {fate}; calibrate with the plant's module or YAML file "
              "loadable to recompute it", file=sys.stderr)  # fmt: skip
        return None if changed else old
    now = check_metric(scored, seed=old["seed"], runs=old["runs"], scenario=plant)
    if scored == src and now["value"] == old["value"]:
        return old  # (as it was, its note included)
    options = ("" if scored == src else " with "
               + ", ".join(f"{o} {getattr(card, o)}" for o in RUN_OPTIONS))  # fmt: skip
    return {**now, "note": f"recomputed by difffilter-train calibrate{options} (before: "
                           f"{old['value']:.6g})"}  # fmt: skip


def _check_scenario(src: Path, name: str):
    """The scenario the card's check ran on: ``name`` as registered here, else the file or
    module the fit was given where it loads as ``name``; ``None`` where neither does."""
    from difffilter.models import registry

    for given in (name, _fit_scenario(src)):
        if given is None:
            continue
        try:
            found = registry.get(given)
        except ValueError:
            continue
        if found.name == name:
            return found
    return None


def _fit_scenario(src: Path) -> str | None:
    """The scenario as ``fit`` was given it, from the checkpoint's JSON card
    (``model_config.scenario``), where it names a plug-in (``module:object``) or a YAML file
    that a new process can load (the card's ``scenario`` is the registered name, which a new
    process knows only for the built-in scenarios); else ``None``."""
    from difffilter.models.yaml_scenario import is_yaml_path

    sidecar = Path(src).with_suffix(".json")
    try:
        given = json.loads(sidecar.read_text(encoding="utf-8"))["model_config"]["scenario"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if isinstance(given, str) and (":" in given or is_yaml_path(given)):
        return given
    return None


def calibrate_checkpoint(
    src,
    out,
    *,
    far: float = 0.01,
    runs: int | None = None,
    seed: int = CALIBRATION_SEED,
    force: bool = False,
    progress: bool = True,
    restart: float | None | str = KEEP,
    confirm: float | None | str = KEEP,
    reject: float | None | str = KEEP,
    scenario: str | None = None,
) -> dict:
    """Calibrate the checkpoint ``src`` to the false-alarm rate ``far`` and write it to
    ``out`` (module docstring); ``runs`` per set (default the scenario's); ``scenario``:
    where the attack-free runs come from, a name, ``package.module:object`` or YAML file
    (default: the card's training scenario, as ``fit`` was given it where the JSON card
    beside ``src`` names a plug-in or a YAML file, else by its registered name);
    ``restart``: the
    card's restart rate to calibrate with (``None``: none; default: the card's); ``confirm``
    likewise the card's confirmation rate, ``reject`` its rejection rate. Returns
    the card's ``calibration`` entry. ``ValueError`` for a bad argument or a checkpoint
    that cannot be calibrated, ``FileNotFoundError`` if ``src`` does not exist."""
    from difffilter.eval.calibration import alarm_clustering
    from difffilter.metrics import threshold_for
    from difffilter.models import registry
    from difffilter.models.neural_estimator import (
        load_estimator_checkpoint,
        save_estimator_checkpoint,
    )
    from difffilter.models.plant_match import training_plant_notes
    from difffilter.models.streams import Streams

    src, out = Path(src), Path(out)
    if not 0.0 < float(far) < 1.0:
        raise ValueError(f"--far must lie in (0, 1) (a rate per step); got {far!r}")
    if runs is not None and (isinstance(runs, bool) or not isinstance(runs, int) or runs < 1):
        raise ValueError(f"--runs must be a positive integer; got {runs!r}")
    estimator, card = load_source(src)  # the weights unchanged
    check_checkpoint_out(out, force=force, replacing=src)
    if card.scenario is None:
        raise ValueError(f"{src}: its card names no training scenario to calibrate on")
    as_shipped = card
    for option, value in zip(RUN_OPTIONS, (restart, confirm, reject), strict=True):
        if value != KEEP:
            rate = None if value is None else check_rate(value, f"--{option}", unset="off")
            card = dataclasses.replace(card, **{option: rate})
    if card.restart is not None and not restart_applies(card.filter == "pf", card.channel):
        # (a docs trial met "inner must be a Gaussian filter … (got ParticleFilter, …)")
        raise ValueError(
            f"--restart: the restart runs an uncompensated copy of a Gaussian filter against "
            f"sensor attacks; this network runs in the {card.filter} filter against "
            f"{card.channel} attacks (--restart off)"
        )
    if card.confirm is not None and card.restart is None:
        raise ValueError("--confirm reads the χ² test of the restart's gated copy: the card "
                         "needs a restart rate too (--restart RATE)")  # fmt: skip
    try:
        scenario = registry.get(scenario or _fit_scenario(src) or card.scenario)
    except ValueError as error:
        if scenario is not None:
            raise ValueError(f"--scenario: {error}") from None
        raise ValueError(
            f"the card's training scenario {card.scenario!r} is not registered here ({error}); "
            "give it with --scenario package.module:object, or the YAML file's path from this "
            "folder (the card records it as fit was given it, from fit's folder)"
        ) from None
    if scenario.family != card.scenario_family:
        raise ValueError(
            f"--scenario {scenario.name}: of family {scenario.family!r}; the checkpoint was "
            f"trained on {card.scenario_family!r} scenarios"
        )
    # the training file edited since, or --scenario another plant of the family: the
    # threshold is then for that plant (said, as difffilter-eval says it, not refused)
    for line in training_plant_notes([(str(src), src)], [scenario.name], flag=""):
        print(line, file=sys.stderr)
    name, runs = estimator_name(card), runs or scenario.runs
    streams, start = Streams(seed), time.time()
    fit_seed = streams.seed_of("checkpoint-calibration")
    check_seed = streams.seed_of("checkpoint-calibration/check")
    with tempfile.TemporaryDirectory() as tmp:
        scored = src
        if any(getattr(card, o) != getattr(as_shipped, o) for o in RUN_OPTIONS):
            # the scores of the estimator as configured
            scored = Path(tmp) / src.name
            save_estimator_checkpoint(scored, estimator, card)
        fitted, statistic = _scores(scenario, name, scored, runs, fit_seed, progress)
        threshold = threshold_for(fitted, far)
        if not math.isfinite(threshold):  # (a card's JSON had held bare Infinity: a trial)
            raise ValueError(
                f"{src}: the attack-free scores of {name} on {scenario.name} are not finite "
                f"where the threshold for {far:g} falls (it would be {threshold}): the "
                "estimator's statistic overflows or was never computed there; nothing written"
            )
        checked, _ = _scores(scenario, name, scored, runs, check_seed, progress)
        check = _new_check(src, scored, card)
    calibration = {
        "target": float(far), "estimator": name, "scenario": scenario.name, "runs": runs,
        **({} if statistic is None else {"score": statistic}),
        **{o: getattr(card, o) for o in RUN_OPTIONS if getattr(card, o) is not None},
        # the master seed reproduces both (``--seed``); the streams' seeds are derived
        # a particle filter's threshold is for the particles it was scored with (the
        # scenario's: load_estimator's default, learned_estimator.calibrated_particles)
        **({"num_particles": int(scenario.num_particles)} if card.filter == "pf" else {}),
        "steps": int(fitted.shape[-1]), "master_seed": int(seed), "seed": fit_seed,
        "check_seed": check_seed,
        "threshold": threshold, "previous_threshold": card.threshold,
        "measured_on_calibration": float((fitted > threshold).double().mean()),
        "measured_on_check": float((checked > threshold).double().mean()),
        "time_s": time.time() - start,
    }  # fmt: skip
    clustered = alarm_clustering(fitted, threshold)
    if clustered is not None:  # (as a study's report says it: a trial met 0.35 % on the
        # check runs and 1.39 % on 2,000 fresh ones, 18 % of the runs holding the alarms)
        calibration["clustered"] = clustered
    # the card inside the checkpoint says which entry's score τ is for (an entry with
    # another score, e.g. LFC's online fine-tuning of the same network, keeps its own)
    new_card = dataclasses.replace(card, threshold=threshold, target_false_alarm_rate=float(far),
                                   estimator=name, extra={**card.extra, "calibration": calibration})  # fmt: skip
    document = _source_card(src, estimator, as_shipped)
    _write_pair(out, estimator, new_card, document, calibration, check)
    load_estimator_checkpoint(out)  # the pair loads and matches its card
    return calibration


def _source_card(src: Path, estimator, card) -> dict:
    """The card ``src`` comes with, to which the calibration is added: its ``.json`` beside
    it; for a training run's Lightning checkpoint (no card of its own) the card ``export``
    writes of it, with the configs, epochs and plant fingerprint the file records (they
    had been lost: a training trial); ``{}`` else."""
    import torch

    from .export import lightning_card

    beside = src.with_suffix(".json")
    if beside.is_file():
        return json.loads(beside.read_text(encoding="utf-8"))
    blob = torch.load(src, map_location="cpu", weights_only=True)
    if "pytorch-lightning_version" not in blob:
        return {}
    return {**lightning_card(blob, src, estimator, card), "exported_from": str(src)}


def _write_pair(out: Path, estimator, card, document: dict, calibration: dict, check) -> None:
    """The checkpoint ``out`` and its card, written beside their final names first and then
    moved into place together, with Ctrl-C and SIGTERM held for the two renames: stopped
    between two plain writes of an in-place ``--out SRC``, the new checkpoint had stood
    beside the old card, which the rerun (verifying SRC against its card) refused."""
    from difffilter.models.neural_estimator import save_estimator_checkpoint, weights_sha256

    card_path = out.with_suffix(".json")
    staged, staged_card = (_staged_name(p) for p in (out, card_path))
    try:
        digest = save_estimator_checkpoint(staged, estimator, card)
        document.update(name=document.get("name", out.stem), checkpoint=out.name, sha256=digest,
                        weights_sha256=weights_sha256(staged), observer=card.to_dict(),
                        calibration=calibration)  # fmt: skip
        if check is None:  # (none, or one that no longer describes the estimator)
            document.pop("check", None)
        else:
            document["check"] = check
        write_json_atomically(staged_card, document)
        with signals_deferred():
            os.replace(staged, out)
            os.replace(staged_card, card_path)
    except OSError as exc:  # named after --out, not the staged files beside it
        if exc.errno is None:
            raise
        raise type(exc)(exc.errno, exc.strerror, str(out)) from exc
    finally:
        for leftover in (staged, staged_card):
            with contextlib.suppress(OSError):
                leftover.unlink(missing_ok=True)


def _staged_name(path: Path) -> Path:
    """Where ``path`` is written before it is moved into place (:func:`sibling_name`: the
    checkpoint's and its card's names kept apart and within the file system's limit)."""
    return sibling_name(path, f"{os.getpid()}.staged")


def _rate_option(value: str, option: str):
    """``--restart`` / ``--confirm`` / ``--reject`` as :func:`calibrate_checkpoint` takes it: :data:`KEEP`,
    ``None`` for ``off``, else the rate as a float (``ValueError`` naming the option)."""
    if value in (KEEP, "off"):
        return None if value == "off" else KEEP
    try:
        return float(value)
    except ValueError:
        raise ValueError(f"--{option} must be a rate in (0, 1) or off; got {value!r}") from None


def _signature(path: Path) -> tuple | None:
    """``(mtime_ns, size)`` of ``path``, ``None`` where there is no file."""
    try:
        stat = path.stat()
    except OSError:
        return None
    return stat.st_mtime_ns, stat.st_size


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="difffilter-train calibrate",
        allow_abbrev=False,  # `--device cuda` had been read as --devices, "invalid int"
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("src", type=Path, help="an exported estimator (.ckpt, with its card), or a "
                   "training run's Lightning checkpoint")  # fmt: skip
    p.add_argument("--out", type=Path, required=True, help="where to write it (and its card)")
    p.add_argument("--far", type=float, default=0.01, help="target false-alarm rate (0.01)")
    p.add_argument("--runs", type=int, default=None,
                   help="attack-free runs per set (default: the scenario's)")  # fmt: skip
    p.add_argument("--seed", type=int, default=CALIBRATION_SEED,
                   help=f"master seed of the calibration runs ({CALIBRATION_SEED})")  # fmt: skip
    p.add_argument("--force", action="store_true", help="replace an existing --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--scenario", default=None, metavar="NAME|module:object|FILE.yaml",
                   help="the scenario of the attack-free runs (default: the card's training "
                        "scenario; one of your own by package.module:object or its YAML file's "
                        "path from this folder)")  # fmt: skip
    p.add_argument("--restart", default=KEEP, metavar="RATE|off",
                   help="the restart rate to run and calibrate with (default: the card's)")  # fmt: skip
    p.add_argument("--confirm", default=KEEP, metavar="RATE|off",
                   help="the rate of the restart copy's χ² test that must alarm with the network "
                        "(default: the card's)")  # fmt: skip
    p.add_argument("--reject", default=KEEP, metavar="RATE|off",
                   help="the rate of the compensated innovation's χ² test where failing it keeps "
                        "the prediction (default: the card's)")  # fmt: skip
    args = p.parse_args(argv)
    if args.seed < 0:  # (Streams said "seed must be …", naming no option)
        p.error(f"--seed must be an integer >= 0; got {args.seed}")
    before = _signature(args.out)
    try:
        cal = calibrate_checkpoint(args.src, args.out, far=args.far, runs=args.runs,
                                   seed=args.seed, force=args.force,
                                   progress=not args.no_progress,
                                   restart=_rate_option(args.restart, "restart"),
                                   confirm=_rate_option(args.confirm, "confirm"),
                                   reject=_rate_option(args.reject, "reject"),
                                   scenario=args.scenario)  # fmt: skip
    except (ValueError, FileNotFoundError) as exc:
        print(f"difffilter-train calibrate: error: {exc}", file=sys.stderr)
        return 2
    except (OSError, RuntimeError) as exc:  # --out not writable after all (torch.save's error)
        print(f"difffilter-train calibrate: error: --out {args.out}: cannot write it ({exc})",
              file=sys.stderr)  # fmt: skip
        return 2
    except KeyboardInterrupt as exc:  # (a traceback of 22 frames before: a training trial)
        # --out is written at the end, the checkpoint and its card moved into place together
        # (signals held): a pair is either the old one or the new one
        touched = _signature(args.out) != before
        what, code = stop_words(exc)  # (SIGTERM: 143)
        print(f"difffilter-train calibrate: {what}: "
              + (f"{args.out} was being written; rerun the same command with --force"
                 if touched else f"nothing was written to {args.out}; rerun the same command"),
              file=sys.stderr)  # fmt: skip
        return code
    print(
        f"wrote {args.out}: {cal['estimator']} alarms above {cal['threshold']:.6g}"
        f"{' (' + cal['score'] + ')' if 'score' in cal else ''} (was "
        f"{cal['previous_threshold']:.6g}); false alarms {100 * cal['measured_on_calibration']:.2f} % "
        f"on the calibration runs, {100 * cal['measured_on_check']:.2f} % on {cal['runs']} other "
        f"attack-free run{'s' if cal['runs'] != 1 else ''} of {cal['scenario']} (target "
        f"{100 * cal['target']:g} %)"
    )
    from difffilter.eval.calibration import (
        RESOLVED,
        WELL_RESOLVED,
        resolution_note,
        sampling_note,
    )

    n = cal["runs"] * cal["steps"]
    if cal["target"] * n < RESOLVED:  # (as difffilter-eval's reports say it)
        print(f"note: {resolution_note(cal['target'], n, '--runs')}")
    elif cal["target"] * n < WELL_RESOLVED:
        print(f"note: {sampling_note(cal['target'], n, cal['steps'])}")
    if "clustered" in cal:
        c = cal["clustered"]
        print(f"note: the {c['alarms']:,} alarms on the calibration runs cluster in a few of "
              f"the {cal['runs']} runs (worth {c['effective_alarms']:.1f} independent ones), "
              "so the threshold rests on those runs and its rate on fresh runs may be far "
              "from the target (the check runs' rate too); give more --runs")  # fmt: skip
    from difffilter.eval.acceptance import TOLERANCES

    low, high = (cal["target"] * f for f in TOLERANCES["fpr_band"])
    if not low <= cal["measured_on_check"] <= high:  # (the other notes can miss it: a trial)
        print(f"note: on the {cal['runs']} check runs the threshold alarms on "
              f"{100 * cal['measured_on_check']:.2f} % of the steps, outside [{100 * low:g} %, "
              f"{100 * high:g} %] (the band the evaluation's acceptance holds a calibrated "
              "detector to): the threshold does not keep its rate on other runs of this size; "
              "give more --runs")  # fmt: skip
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
