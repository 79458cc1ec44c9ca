"""``difffilter-train export``: ship a trained estimator, explicitly.

``fit`` writes only inside its run folder (``lightning_logs/<name>/version_<n>/``, where
``ExportEstimator`` leaves ``<name>.ckpt`` and its card). Copying a result to the shipped
``checkpoints/`` is this command::

    difffilter-train export lightning_logs/lfc_nn_grad/version_3/lfc_nn_grad.ckpt \\
        --out checkpoints/lfc_nn_grad.ckpt --force

The source is an exported estimator file (checked against its card's sha256 and copied
byte for byte, with its card) or a Lightning checkpoint of a run (its estimator is
written in the exported format with a new card). An existing ``--out`` is only replaced
with ``--force``.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from pathlib import Path

import lightning.pytorch as pl
import torch

from difffilter.models.atomic_write import write_atomically, write_json_atomically
from difffilter.models.neural_estimator import (
    checkpoint_sha256,
    load_estimator_checkpoint,
    save_estimator_checkpoint,
    weights_sha256,
)
from difffilter.models.plant_match import PLANT_FINGERPRINT
from difffilter.models.yaml_scenario import SCENARIO_FILE_DIGEST

from .adversarial import kept_an_attack
from .common import check_checkpoint_out, load_source

__all__ = ["export", "main", "ExportEstimator", "check_metric"]


def check_metric(path, *, seed: int = 20, runs: int = 4, scenario=None) -> dict:
    """The card's reproducibility check of the exported estimator at ``path``: its attack
    RMSE on ``runs`` runs of its training scenario (``difffilter-eval``'s draws of
    ``seed``, float64), run as the evaluation runs it (its registered estimator, in its
    own closed loop where the scenario has one). A test recomputes it from the file.
    ``scenario``: that scenario where the registry of this process does not know the
    card's name (a plant of one's own, loaded from its file), else ``None``."""
    from difffilter.loop import LoopResult
    from difffilter.models import estimators, registry
    from difffilter.models.streams import Streams

    _, card = load_estimator_checkpoint(path)
    scenario = registry.get(card.scenario) if scenario is None else scenario
    streams = Streams(seed)
    model = scenario.system(torch.float64)
    with torch.no_grad():  # the one process that exports runs it (no process group)
        traj = scenario.simulate(runs, streams.simulation(), model=model)
        ctx = estimators.SuiteContext(scenario, model, runs, streams, checkpoint=path)
        out = estimators.get(card.estimator).factory(ctx)(traj)
    if isinstance(out, LoopResult):  # its own closed loop: its own truth
        traj, out = out.trajectories, out.output
    value = float((out.attack - traj.attack).square().mean().sqrt())
    if not math.isfinite(value):  # (written as bare NaN into the card, non-standard JSON,
        # and never equal to itself at the next calibration: a trial of the cards)
        raise ValueError(
            f"{path}: the card's check, the attack RMSE of {card.estimator} on {runs} runs of "
            f"{card.scenario} (seed {seed}), is {value}: the estimator diverges there, and "
            "no card is written with it"
        )
    return {"metric": "attack_rmse", "scenario": card.scenario, "seed": seed, "runs": runs,
            "value": value}  # fmt: skip


def _calibration_entry(est_card) -> dict:
    """``{"calibration": …}`` where the threshold came from (``calibrate`` records it there
    as well), or nothing: the card's top-level copy of the observer card's record (a user
    trial read ``card["calibration"]`` and found nothing after a fit; an export of the run's
    Lightning checkpoint had left it out again, a trial of the export)."""
    record = est_card.extra.get("calibration")
    return {} if record is None else {"calibration": record}


def export(src: str | Path, out: str | Path, *, force: bool = False) -> Path:
    """Write the estimator of ``src`` to ``out`` (and ``out`` with suffix ``.json``, its card).

    ``ValueError`` if ``out`` exists without ``force`` or ``src`` is not an estimator
    checkpoint (``FileNotFoundError`` if it does not exist). Returns ``out``.
    """
    src, out = Path(src), Path(out)
    if out.resolve() == src.resolve():
        raise ValueError(f"--out: {out} is the source itself")
    # verified; its weights in their own dtype (a float64 network stays float64)
    estimator, est_card = load_source(src)
    check_checkpoint_out(out, force=force)
    out.parent.mkdir(parents=True, exist_ok=True)
    card_src = src.with_suffix(".json")
    blob = torch.load(src, map_location="cpu", weights_only=True)
    if "pytorch-lightning_version" not in blob:  # already exported: the same bytes
        write_atomically(out, lambda partial: shutil.copyfile(src, partial))
        card = json.loads(card_src.read_text(encoding="utf-8")) if card_src.is_file() else {}
        digest = checkpoint_sha256(out)
    else:
        digest = save_estimator_checkpoint(out, estimator, est_card)
        card = lightning_card(blob, src, estimator, est_card)
    card.update(checkpoint=out.name, sha256=digest, weights_sha256=weights_sha256(out),
                exported_from=str(src))  # fmt: skip
    card.setdefault("name", out.stem)
    write_json_atomically(out.with_suffix(".json"), card)
    load_estimator_checkpoint(out)  # the shipped pair loads and matches its card
    return out


def lightning_card(blob: dict, src: Path, estimator, est_card) -> dict:
    """The card of the estimator of a training run's Lightning checkpoint ``src`` (its
    loaded ``blob``), less the file's own entries (``checkpoint``, digests): what ``export``
    writes, and ``calibrate`` of such a file starts from (its card had lost the configs,
    epochs and the plant's fingerprint: a training trial)."""
    return {
        "estimator_config": estimator.config(),
        "observer": est_card.to_dict(),
        # as a fit's card names them (the shipped-checkpoint hint matches cards on
        # them: an export of a run's Lightning file had been offered nowhere)
        "estimator": est_card.estimator,
        "scenario_family": est_card.scenario_family,
        **_lightning_record(blob, src),
        "torch_version": torch.__version__,
        **_calibration_entry(est_card),
    }


def _lightning_record(blob: dict, src: Path) -> dict:
    """What a training run's Lightning checkpoint says of itself, for the card of its export
    (a user trial: the card lacked the configs and the validation score a fit's export has):
    the task's and the data's settings, its epoch and step, and the monitored validation
    score of these weights (``val_score``: the validation of the epoch the file was written
    at, as the task records it; for an older file, the checkpoint callback's score where the
    file is its best, else ``None``; also ``best_val_score`` where the file is that best)."""
    hp, data = blob.get("hyper_parameters"), blob.get("datamodule_hyper_parameters")
    record = {
        "selected_checkpoint": src.name,
        "model_config": _plain(dict(hp)) if isinstance(hp, dict) else None,
        "data_config": _plain(dict(data)) if isinstance(data, dict) else None,
        # a Lightning checkpoint is written at an epoch's end and records its 0-based index
        # (a fit's card counts the epochs: 3 where the same weights' last.ckpt said 2)
        "epochs": None if blob.get("epoch") is None else int(blob["epoch"]) + 1,
        "global_step": blob.get("global_step"),
        "lightning_version": blob.get("pytorch-lightning_version"),
    }
    if blob.get(SCENARIO_FILE_DIGEST) is not None:  # the plant file training read
        record["scenario_file_sha256"] = blob[SCENARIO_FILE_DIGEST]
    if blob.get(PLANT_FINGERPRINT) is not None:  # the plant training built
        record["scenario_plant_sha256"] = blob[PLANT_FINGERPRINT]
    if (craftings := adversarial_craftings(blob)) is not None:
        record["adversarial_craftings"] = craftings
    if (drawn := threats_drawn(blob)) is not None:
        record["threats_drawn"] = drawn
    for state in (blob.get("callbacks") or {}).values():  # the training time so far
        if isinstance(state, dict) and state.get("train_time_s") is not None:
            record["train_time_s"] = float(state["train_time_s"])
    validated = blob.get("difffilter_validation") or {}
    own = validated.get("metrics") if validated.get("epoch") == blob.get("epoch") else None
    for key, state in (blob.get("callbacks") or {}).items():
        if key.startswith("ModelCheckpoint") and state.get("monitor"):
            mode = "max" if "'mode': 'max'" in key else "min"
            record["monitor"] = {"metric": state["monitor"], "mode": mode}
            best = state.get("best_model_path")
            is_best = bool(best) and Path(best).name == src.name
            if own is not None and state["monitor"] in own:  # the score of these weights
                score = own[state["monitor"]]
            else:  # (an older checkpoint: the callback's score is these weights' only in
                # its best file; a last.ckpt of an epoch that did not improve held another's)
                score = state.get("current_score") if is_best else None
            record["val_score"] = None if score is None else float(score)
            if is_best and state.get("best_model_score") is not None:
                record["best_val_score"] = float(state["best_model_score"])
            break
    return record


def adversarial_craftings(blob: dict) -> int | None:
    """How many attacks adversarial training had crafted when the weights of a Lightning
    checkpoint were saved (``None``: no adversary). The weights a fit selects may predate
    the first crafting (crafting starts in the second epoch, and the checkpoint is chosen on
    the validation score): a trial's card credited adversarial training that its weights
    never had; :func:`difffilter.eval.coverage.training_coverage` reads this. Only the
    craftings that kept an attack count: one that kept none left the batches as they were
    (counted, a card had credited an adversary whose weights met no attack: a red-team
    trial)."""
    state = blob.get("difffilter_adversary")
    if not isinstance(state, dict):
        return None
    return sum(1 for entry in state.get("history") or () if kept_an_attack(entry))


def threats_drawn(blob: dict) -> dict[str, int] | None:
    """``{threat name: runs}`` of the training batches a network trained across threats had
    met when a Lightning checkpoint was saved (the data module's state, which Lightning
    keeps under the module's class name), or ``None`` (trained on its scenario's attack, or
    a checkpoint written before it was counted). :func:`difffilter.eval.coverage.training_coverage`
    reads it: a component never drawn was not trained on."""
    for state in blob.values():
        if isinstance(state, dict) and isinstance(state.get("threats_drawn"), dict):
            return {str(k): int(v) for k, v in state["threats_drawn"].items()}
    return None


def _whole_epochs(trainer) -> int:
    """The epochs trained whole: ``current_epoch``, less the last one where ``max_steps`` or
    ``max_time`` cut it short (Lightning advances ``current_epoch`` past a cut epoch: a
    card said 2 epochs of a run whose last whole epoch was its first)."""
    epochs = int(trainer.current_epoch)
    progress = getattr(getattr(trainer.fit_loop, "epoch_loop", None), "batch_progress", None)
    ready = getattr(getattr(progress, "current", None), "ready", None)
    total = trainer.num_training_batches
    if isinstance(ready, int) and isinstance(total, int) and 0 < ready < total and epochs > 0:
        return epochs - 1
    return epochs


def _plain(config: dict) -> dict:
    """JSON-ready copy of a hyperparameter dict (tuples → lists, private keys dropped)."""
    return {
        k: (list(v) if isinstance(v, tuple) else v)
        for k, v in config.items()
        if not k.startswith("_")
    }


class ExportEstimator(pl.Callback):
    """At the end of ``fit``, export the best checkpoint's estimator (weights only) and a card.

    The module names the file and adds to the card: ``export_name()`` (the file's stem),
    ``card()`` (the :class:`~difffilter.models.neural_estimator.EstimatorCard`: what
    evaluation needs beside the weights) and ``export_card(trainer, estimator)`` (its own
    card entries).

    Args:
        path: the ``.ckpt`` to write; default ``<run folder>/<export_name>.ckpt`` (the
            logger's ``version_<n>`` folder), so that ``fit`` writes only inside its run.
            Shipping a result to ``checkpoints/`` is the explicit ``difffilter-train
            export``. The card goes next to the file with the suffix ``.json``.
        enabled: ``False`` turns the export off.

    Nothing is exported under ``fast_dev_run``.
    """

    def __init__(self, path: str | None = None, enabled: bool = True):
        super().__init__()
        self.path = None if path is None else Path(path)
        self.enabled = bool(enabled)
        self._start = None
        self._before = 0.0  # training seconds of the processes before a resume
        self._trained = False  # a batch trained in this process
        self._exporting = None  # (file, checkpoint it comes from) while the export is written

    def on_fit_start(self, trainer, pl_module):
        self._start = time.time()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self._trained = True

    def _train_time(self) -> float | None:
        return None if self._start is None else self._before + time.time() - self._start

    def state_dict(self) -> dict:
        # the seconds so far ride in every checkpoint, so that a resumed run's card counts
        # the whole training, not its last process (a user trial: 19.7 s against 44.8 s)
        return {"train_time_s": self._train_time()}

    def load_state_dict(self, state_dict: dict) -> None:
        self._before = float(state_dict.get("train_time_s") or 0.0)

    def on_exception(self, trainer, pl_module, exception):
        """Ctrl-C while the export was written (its check runs the estimator for seconds):
        the file without its card goes, and the message says how to export what training
        ended with (resuming from ``last.ckpt`` trains nothing and exports it then: the
        run's folder holds no card, :meth:`on_fit_end`)."""
        if self._exporting is None or not isinstance(exception, KeyboardInterrupt):
            return
        path, source = self._exporting
        self._exporting = None
        if not path.with_suffix(".json").is_file():
            path.unlink(missing_ok=True)
        print(f"interrupted while exporting {path}: the training had ended, no export was "
              f"written; resume the run (--ckpt_path {source}) to export it, or export it "
              f"with: difffilter-train export {source} --out <file>")  # fmt: skip

    def on_fit_end(self, trainer, pl_module):
        if not self.enabled or trainer.fast_dev_run:
            return
        # trainer.log_dir is a collective under DDP: every process asks, one writes
        name = pl_module.export_name()
        path = self.path or Path(trainer.log_dir or trainer.default_root_dir) / f"{name}.ckpt"
        finished = not self._trained and trainer.ckpt_path
        # its export, here or in the run the checkpoint comes from (the folder above
        # checkpoints/): a resumed fit logs to a new version folder
        earlier = finished and next(
            (p for p in (path, Path(trainer.ckpt_path).resolve().parent.parent / path.name)
             if p.with_suffix(".json").is_file()), None)  # fmt: skip
        if earlier:
            # a resumed run that had finished and exported: exporting again would replace its
            # card with one of less (no validation ran here: no metrics of the last one)
            if trainer.is_global_zero:
                print(f"nothing to train: {trainer.ckpt_path} had reached the end of its "
                      f"training (epoch {trainer.current_epoch}, step {trainer.global_step}); "
                      f"its export is {earlier} (to train on, raise "
                      "--trainer.max_epochs)")  # fmt: skip
            return
        if not trainer.is_global_zero:
            return
        if finished:
            # one that had finished but whose export was interrupted (its file removed, no
            # card): exported now, from the weights its checkpoint callback chose. A sweep
            # had stopped at that seed for good ("fit exported no estimator": a sweep trial)
            print(f"{trainer.ckpt_path} had reached the end of its training, and its export "
                  f"was not written: exporting it now (the card's last-validation metrics "
                  "are not known here)")  # fmt: skip
        best_path, best_score, monitor = None, None, None
        for cb in trainer.callbacks:
            if isinstance(cb, pl.callbacks.ModelCheckpoint) and cb.best_model_path:
                best_path, best_score = cb.best_model_path, cb.best_model_score
                # what chose the weights, and which way is better: a sweep ranks seeds by it
                monitor = None if cb.monitor is None else {"metric": cb.monitor, "mode": cb.mode}
        # of the adversary and of the threats drawn, when the selected weights were saved
        craftings = drawn = None
        dm = trainer.datamodule
        if best_path:  # the selected weights (and their buffers, e.g. a threshold)
            blob = torch.load(best_path, map_location="cpu", weights_only=True)
            pl_module.load_state_dict(blob["state_dict"])
            craftings, drawn = adversarial_craftings(blob), threats_drawn(blob)
        else:
            if getattr(pl_module, "adversary", None) is not None:
                craftings = pl_module.adversary.kept_craftings()
            if getattr(dm, "threats", None) is not None:
                drawn = dict(dm.threats_drawn)
        # the weights chosen, or else where the training ended, for Ctrl-C's message
        self._exporting = (path, best_path or _last_checkpoint(trainer) or "<last.ckpt>")
        est_card = pl_module.card()
        # a card of an earlier export (a resumed run that had finished) would not match the
        # new file, and every load below (the check's evaluation too) checks the card beside
        # it: it goes now, and is written again below
        path.with_suffix(".json").unlink(missing_ok=True)
        digest = save_estimator_checkpoint(path, pl_module.estimator, est_card)
        estimator, _ = load_estimator_checkpoint(path, expected_sha256=digest)
        metrics = {
            k: float(v)
            for k, v in trainer.callback_metrics.items()
            if k.startswith("val/") and torch.as_tensor(v).numel() == 1
        }
        card = {
            "name": name,
            "checkpoint": path.name,
            "sha256": digest,
            "weights_sha256": weights_sha256(path),
            "selected_checkpoint": Path(best_path).name if best_path else None,
            "best_val_score": None if best_score is None else float(best_score),
            "monitor": monitor,
            "metrics_last_validation": metrics,
            "model_config": _plain(dict(pl_module.hparams)),
            "data_config": None if dm is None else _plain(dict(dm.hparams)),
            "observer": est_card.to_dict(),
            "epochs": _whole_epochs(trainer),
            "global_step": trainer.global_step,
            "train_time_s": self._train_time(),
            "torch_version": torch.__version__,
            "lightning_version": pl.__version__,
            **pl_module.export_card(trainer, estimator),
            **_calibration_entry(est_card),
            "check": check_metric(path),
            **({} if craftings is None else {"adversarial_craftings": craftings}),
            **({} if drawn is None else {"threats_drawn": drawn}),
        }
        write_json_atomically(path.with_suffix(".json"), card)
        self._exporting = None
        watched = any(isinstance(cb, pl.callbacks.ModelCheckpoint) and cb.monitor
                      for cb in trainer.callbacks)  # fmt: skip
        if watched and not best_path:  # (max_steps/max_time before the first validation)
            print(f"exported {path}: the weights training stopped at, never validated (the "
                  "run stopped before its first validation, so no checkpoint was chosen and "
                  "the card's best_val_score is null); train at least one whole epoch")  # fmt: skip
            return
        print(f"exported {path} (ship it with: difffilter-train export {path} --out <file>)")


def _last_checkpoint(trainer) -> str | None:
    """The ``last.ckpt`` a checkpoint callback of ``trainer`` wrote, if any."""
    for cb in trainer.callbacks:
        if isinstance(cb, pl.callbacks.ModelCheckpoint) and cb.last_model_path:
            return cb.last_model_path
    return None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="difffilter-train export",
        allow_abbrev=False,  # `--device cuda` had been read as --devices, "invalid int"
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("src", type=Path, help="exported estimator (.ckpt) or Lightning checkpoint")
    p.add_argument("--out", type=Path, required=True, help="where to write it (and its card)")
    p.add_argument("--force", action="store_true", help="replace an existing --out")
    args = p.parse_args(argv)
    try:
        out = export(args.src, args.out, force=args.force)
    except (ValueError, FileNotFoundError) as exc:
        print(f"difffilter-train export: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # --out not writable (a file where a folder must be, no permission)
        where = exc.filename or args.out
        print(f"difffilter-train export: error: --out {args.out}: cannot write {where} "
              f"({exc.strerror or exc})", file=sys.stderr)  # fmt: skip
        return 2
    print(f"wrote {out} and {out.with_suffix('.json')} (sha256 {checkpoint_sha256(out)})")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
