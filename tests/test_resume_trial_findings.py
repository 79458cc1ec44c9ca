"""Findings of a red-team trial of interrupted and resumed training (each failed before
its fix)."""

from __future__ import annotations

import os

import lightning.pytorch as pl
import pytest
import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from torch.utils.data import DataLoader, TensorDataset

from difffilter.train.last_checkpoint import add_last_every_epoch

METRIC = [3.0, 2.0, 1.0, 5.0, 5.0]  # the validation metric per epoch: best (min) at epoch 2


class _Tiny(pl.LightningModule):
    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(1))

    def training_step(self, batch, i):
        return ((self.w - batch[0]) ** 2).sum()

    def validation_step(self, batch, i):
        self.log("val/metric", METRIC[self.current_epoch])

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)

    def train_dataloader(self):
        return DataLoader(TensorDataset(torch.tensor([[1.0], [3.0]])), batch_size=1)

    def val_dataloader(self):
        return DataLoader(TensorDataset(torch.ones(1, 1)), batch_size=1)


class _StoppedWhileSaving(ModelCheckpoint):
    """Ctrl-C landing while the callback writes epoch 2's checkpoint named ``window``."""

    window: str | None = None

    def _save_checkpoint(self, trainer, filepath):
        if self.window and trainer.current_epoch == 2 and self.window in os.path.basename(filepath):
            raise KeyboardInterrupt
        super()._save_checkpoint(trainer, filepath)


def _fit(folder, window=None, ckpt_path=None):
    best = _StoppedWhileSaving(dirpath=folder, monitor="val/metric", mode="min",
                               save_last=True, save_top_k=1, filename="best-{epoch:02d}")  # fmt: skip
    best.window = window
    trainer = pl.Trainer(max_epochs=5, callbacks=[best], logger=False, enable_progress_bar=False,
                         enable_model_summary=False, num_sanity_val_steps=0,
                         accelerator="cpu", devices=1)  # fmt: skip
    add_last_every_epoch(trainer)
    torch.manual_seed(0)
    trainer.fit(_Tiny(), ckpt_path=ckpt_path)
    return best


@pytest.mark.parametrize("window", ["best", "last"])
def test_an_interrupt_while_the_new_best_is_saved_resumes_to_the_same_best(tmp_path, window):
    """``last.ckpt`` is written before the checkpoint callback sees the epoch: an interrupt
    during its save of epoch 2's new best (or after it, before its own ``last.ckpt``) left
    the file counting epoch 2 done with the callback's record of before it, and the resumed
    run picked epoch 1's network as its best (a trial: another export)."""
    whole = _fit(tmp_path / "whole")
    try:  # (Lightning 2.6 exits on Ctrl-C; 2.2 shuts down gracefully and returns)
        _fit(tmp_path / "cut", window=window)
    except (KeyboardInterrupt, SystemExit):
        pass
    resumed = _fit(tmp_path / "cut", ckpt_path=tmp_path / "cut" / "last.ckpt")
    assert float(resumed.best_model_score) == float(whole.best_model_score) == 1.0
    assert os.path.basename(resumed.best_model_path).startswith("best-epoch=02")
    assert os.path.isfile(resumed.best_model_path)
    mine = torch.load(resumed.best_model_path, weights_only=True)["state_dict"]["w"]
    truth = torch.load(whole.best_model_path, weights_only=True)["state_dict"]["w"]
    assert torch.equal(mine, truth)


def test_putting_last_ckpt_back_is_atomic(tmp_path, monkeypatch):
    """The file put back at the last whole epoch was written in place (``write_bytes``): a
    kill during it left a truncated ``last.ckpt``, the run's only resume point (a trial)."""
    from pathlib import Path

    from difffilter.train.last_checkpoint import LastCheckpointEveryEpoch

    path = tmp_path / "last.ckpt"
    path.write_bytes(b"the epoch cut short")
    callback = LastCheckpointEveryEpoch(ModelCheckpoint(dirpath=tmp_path))
    callback._whole = b"the last whole epoch" * 100

    def killed(self, data):  # the process dies half-way through a plain write
        with open(self, "wb") as f:
            f.write(data[: len(data) // 2])
        raise KeyboardInterrupt

    monkeypatch.setattr(Path, "write_bytes", killed)
    with pytest.raises(KeyboardInterrupt):
        callback._restore_whole(path)
    assert path.read_bytes() in (b"the epoch cut short", b"the last whole epoch" * 100)
