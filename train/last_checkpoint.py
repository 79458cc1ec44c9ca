"""``last.ckpt`` at the end of every whole epoch, so that an interrupted training loses at
most the epoch it was in, and a resumed one trains the weights the uninterrupted one does.

A ``ModelCheckpoint`` with a ``monitor`` and ``save_last=True`` writes ``last.ckpt`` only
when it also writes a best checkpoint (Lightning 2.6, here; 2.2 wrote it every epoch: "saves
a last.ckpt copy whenever a checkpoint file gets saved"), that is, only in an epoch where
the monitored metric improved. A run stopped after a few epochs without improvement then
resumes from the last improvement and trains those epochs again (an LFC training of 30
epochs, two or three minutes each, stopped in epoch 10 with its ``last.ckpt`` at epoch 5).
:class:`LastCheckpointEveryEpoch` writes the same file at the end of every epoch, so
``--ckpt_path <run>/checkpoints/last.ckpt`` resumes from the epoch the run reached.
``difffilter-train fit`` adds one beside every such callback
(:meth:`~difffilter.train.lightning_cli.DifffilterCLI.before_fit`). Lightning runs the
checkpoint callbacks after every other (its ``_reorder_callbacks``), so this one writes the
file before they see the epoch; the file still holds their state of the epoch: a
``ModelCheckpoint`` changes its state only in an epoch where the monitored metric improved,
and then writes ``last.ckpt`` itself, after this one, with that state.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import lightning.pytorch as pl
from lightning.pytorch.callbacks import ModelCheckpoint

from difffilter.models.atomic_write import write_atomically

__all__ = ["LastCheckpointEveryEpoch", "add_last_every_epoch"]


#: The environment variable through which a command that runs ``fit`` for its user (a
#: sweep) says how to resume after Ctrl-C: "--ckpt_path" is no option of ``sweep``.
RESUME_HINT = "DIFFFILTER_RESUME_HINT"


class LastCheckpointEveryEpoch(pl.Callback):
    """Write ``checkpoint``'s ``last.ckpt`` at the end of every training epoch (after its
    validation, where the epoch has one), where ``checkpoint`` keeps it for improvements
    only (module docstring; why the file holds the checkpoint callbacks' state of the epoch
    though Lightning runs them after this one)."""

    def __init__(self, checkpoint: ModelCheckpoint):
        if not isinstance(checkpoint, ModelCheckpoint):
            raise ValueError(
                f"checkpoint must be a ModelCheckpoint; got {type(checkpoint).__name__}"
            )
        self.checkpoint = checkpoint
        self._written_at_step: int | None = None
        # what the file written at that step holds of the checkpoint callback, and its bytes'
        # digest (whether the callback has rewritten it since)
        self._written_record: tuple | None = None
        self._written_digest: bytes | None = None
        self._whole: bytes | None = None  # last.ckpt as the last whole epoch left it
        self._cut = False
        self._in_an_epoch = False  # whether _whole was read (an epoch began)

    def on_train_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        path = self._path()
        if trainer.is_global_zero and path is not None:
            self._whole = path.read_bytes() if path.is_file() else None
            self._in_an_epoch = True

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if _cut_short(trainer):
            # a validation inside the epoch (``val_check_interval`` < 1): written, the file
            # held part of an epoch, and a resume from it trained other weights than the
            # uninterrupted run (a review: w 1.30 against 1.56)
            return
        self._write(trainer)

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._cut = _cut_short(trainer)
        if self._cut:
            # ``max_steps``/``max_time`` ended the epoch after some of its batches: written, the
            # file counted the epoch done, and a resume skipped the rest of its batches (a
            # user trial: other weights than the uninterrupted run's). Kept at the last whole
            # epoch, a resume trains this one again, on the same seeded batches.
            return
        self._write(trainer)  # an epoch without validation (written once per step count)

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        """After a cut epoch, ``last.ckpt`` as the last whole epoch left it (or none before
        one): Lightning 2.2's own checkpoint callback writes it at the cut epoch's end too,
        after this one (checkpoint callbacks run last)."""
        path = self._path()
        if self._cut and path is not None and trainer.is_global_zero:
            self._restore_whole(path)

    def on_exception(self, trainer: pl.Trainer, pl_module: pl.LightningModule,
                     exception: BaseException) -> None:  # fmt: skip
        """``last.ckpt`` back at the last whole epoch where the checkpoint callback wrote it
        inside the epoch cut now (an improvement at a validation inside the epoch); on
        Ctrl-C, how to resume (a user trial found Lightning's exit 1 and no word)."""
        if not trainer.is_global_zero:
            return
        self._back_to_the_last_whole_epoch(trainer)
        from lightning.pytorch.utilities.exceptions import SIGTERMException

        if not isinstance(exception, (KeyboardInterrupt, SIGTERMException)):
            return
        path = self._path()
        if path is not None and path.is_file() and os.environ.get(RESUME_HINT):
            print(f"interrupted: {os.environ[RESUME_HINT]} (from {path}, the last whole epoch)")
        elif path is not None and path.is_file():
            print(f"interrupted: resume with the same command and --ckpt_path {path} (from "
                  "the last whole epoch; the export is written when the run ends)")  # fmt: skip
        else:
            print("interrupted before the first epoch ended: no last.ckpt to resume from")

    def _back_to_the_last_whole_epoch(self, trainer: pl.Trainer) -> None:
        path = self._path()
        if not self._in_an_epoch or path is None or not path.is_file():
            return  # (before any epoch began, the file is a resumed run's own: left alone)
        if self._written_at_step != trainer.global_step:  # (else written here: an epoch's end)
            self._restore_whole(path)
        elif self._callback_moved_on(path):
            # written here, before the checkpoint callback's turn, which the interrupt cut: the
            # file counts the epoch done with the callback's state of before it (a new best
            # of this epoch unrecorded: a resume exported another epoch's network, a trial)
            self._restore_whole(path)

    def _callback_moved_on(self, path: Path) -> bool:
        """Whether the checkpoint callback's record changed since this callback wrote
        ``path`` (it began saving a new best) and the file is still the one written (the
        callback's own ``last.ckpt``, with its new record, was not written yet)."""
        if _record(self.checkpoint) == self._written_record:
            return False
        return hashlib.sha256(path.read_bytes()).digest() == self._written_digest

    def _restore_whole(self, path: Path) -> None:
        """``last.ckpt`` as the last whole epoch left it, or none where no epoch was whole."""
        if self._whole is None:
            path.unlink(missing_ok=True)
        elif not path.is_file() or path.read_bytes() != self._whole:
            # (whole or not at all: a kill during a plain write had left a truncated file,
            # the run's only resume point, a trial)
            write_atomically(path, self._whole)

    def _path(self) -> Path | None:
        cb = self.checkpoint
        if cb.dirpath is None:
            return None
        return Path(cb.dirpath) / f"{cb.CHECKPOINT_NAME_LAST}{cb.FILE_EXTENSION}"

    def _write(self, trainer: pl.Trainer) -> None:
        if trainer.sanity_checking or trainer.fast_dev_run or trainer.state.fn != "fit":
            return
        path = self._path()
        if path is None or self._written_at_step == trainer.global_step:
            return
        cb = self.checkpoint
        # the callback's own idea of its last file: its next write goes to the same path
        cb.last_model_path = str(path)
        # what the callback's own writes hold: the full state to resume from, unless it keeps
        # weights only (left unset, Lightning logs "`weights_only` was not set" every epoch)
        self._written_record = _record(cb)
        trainer.save_checkpoint(path, weights_only=cb.save_weights_only)
        self._written_at_step = trainer.global_step
        self._written_digest = hashlib.sha256(path.read_bytes()).digest()
        # and the callback's own record that a last.ckpt was written in this run: without
        # it, Lightning 2.6's on_train_end wrote the file again after a run whose epochs all
        # failed to improve (a resumed one), with the epoch counted done, one ahead of the
        # uninterrupted run's (a trial: epoch 4 where it had 3, an export of 5 epochs)
        # (not under save_last="link", where that record names the file to link to)
        if cb.save_last is True:
            cb._last_checkpoint_saved = str(path)


def _record(cb: ModelCheckpoint) -> tuple:
    """What ``cb`` keeps of its best checkpoints (changed as it begins saving a new one)."""
    score = cb.best_model_score
    return (cb.best_model_path, cb.kth_best_model_path, tuple(sorted(cb.best_k_models)),
            None if score is None else float(score))  # fmt: skip


def _cut_short(trainer: pl.Trainer) -> bool:
    """Whether the epoch ending now ran fewer batches than an epoch has."""
    total = trainer.num_training_batches
    done = trainer.fit_loop.epoch_loop.batch_progress.current.completed
    return isinstance(total, int) and done < total


def add_last_every_epoch(trainer: pl.Trainer) -> None:
    """Append a :class:`LastCheckpointEveryEpoch` for each of ``trainer``'s checkpoint
    callbacks that keeps a ``last.ckpt`` and watches a metric (the others write one every
    epoch already)."""
    for cb in list(trainer.checkpoint_callbacks):
        if cb.save_last and cb.monitor is not None:
            trainer.callbacks.append(LastCheckpointEveryEpoch(cb))
