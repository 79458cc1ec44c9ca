"""``last.ckpt`` follows every epoch (``difffilter.train.last_checkpoint``): a run whose
monitored metric stopped improving, interrupted, resumes where it was, not from its last
improvement."""

from __future__ import annotations

from types import SimpleNamespace

import lightning.pytorch as pl
import pytest
import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from torch.utils.data import DataLoader, TensorDataset

from difffilter.train.last_checkpoint import LastCheckpointEveryEpoch, add_last_every_epoch
from difffilter.train.lightning_cli import DifffilterCLI

BATCHES = 2


class _Worsening(pl.LightningModule):
    """One weight; its validation metric is the epoch number, so it never improves after
    the first epoch (a ``mode="min"`` checkpoint saves its best at epoch 0 only)."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(1))

    def training_step(self, batch, batch_idx):
        return ((self.w - batch[0]) ** 2).sum()

    def validation_step(self, batch, batch_idx):
        self.log("val/metric", float(self.current_epoch))

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)

    def train_dataloader(self):
        return DataLoader(TensorDataset(torch.ones(BATCHES, 1)), batch_size=1)

    def val_dataloader(self):
        return DataLoader(TensorDataset(torch.ones(1, 1)), batch_size=1)


class _StopAfter(pl.Callback):
    """An interruption: the run stops after epoch ``epoch``."""

    def __init__(self, epoch: int):
        self.epoch = epoch

    def on_train_epoch_end(self, trainer, pl_module):
        if trainer.current_epoch == self.epoch:
            trainer.should_stop = True


class _CountBatches(pl.Callback):
    def __init__(self):
        self.batches = 0

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.batches += 1


def _trainer(folder, epochs: int, *extra, weights_only: bool = False, max_steps: int = -1
             ) -> pl.Trainer:  # fmt: skip
    best = ModelCheckpoint(dirpath=folder, monitor="val/metric", mode="min", save_last=True,
                           save_top_k=1, filename="best-{epoch:02d}",
                           save_weights_only=weights_only)  # fmt: skip
    trainer = pl.Trainer(
        max_epochs=epochs, max_steps=max_steps, callbacks=[best, *extra], logger=False,
        enable_progress_bar=False,
        enable_model_summary=False, num_sanity_val_steps=0, accelerator="cpu", devices=1,
    )  # fmt: skip
    add_last_every_epoch(trainer)
    return trainer


def _epoch_of(path) -> int:
    return torch.load(path, map_location="cpu", weights_only=True)["epoch"]


def test_last_checkpoint_follows_every_epoch_not_only_the_improvements(tmp_path):
    _trainer(tmp_path, 3).fit(_Worsening())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["best-epoch=00.ckpt", "last.ckpt"]
    assert _epoch_of(tmp_path / "last.ckpt") == 2  # the epoch reached, not the best one (0)


@pytest.mark.parametrize("weights_only", [False, True])
def test_last_checkpoint_holds_what_the_callbacks_own_files_hold(tmp_path, weights_only, caplog):
    with caplog.at_level("INFO", logger="lightning.pytorch"):
        _trainer(tmp_path, 3, weights_only=weights_only).fit(_Worsening())
    last = torch.load(tmp_path / "last.ckpt", map_location="cpu", weights_only=True)
    best = torch.load(tmp_path / "best-epoch=00.ckpt", map_location="cpu", weights_only=True)
    # the optimizer's state (what a resume needs) unless the callback keeps weights only
    assert ("optimizer_states" in last) is (not weights_only)
    assert sorted(last) == sorted(best)
    assert "was not set" not in caplog.text


def test_an_interrupted_run_resumes_at_the_epoch_it_reached(tmp_path):
    cut = _trainer(tmp_path, 4, _StopAfter(2))
    cut.fit(_Worsening())
    assert cut.current_epoch == 3 and _epoch_of(tmp_path / "last.ckpt") == 2

    count = _CountBatches()
    resumed = _trainer(tmp_path, 4, count)
    resumed.fit(_Worsening(), ckpt_path=tmp_path / "last.ckpt")
    assert count.batches == BATCHES  # it trained epoch 3 alone (not 1, 2 and 3 again)
    assert resumed.global_step == 4 * BATCHES
    # the epoch it reached, as the uninterrupted run's: Lightning's own end-of-training
    # write had left it at 4, counted done (a trial: an export then said 5 epochs of 4)
    assert _epoch_of(tmp_path / "last.ckpt") == 3
    # the best checkpoint's own bookkeeping came back with it: still epoch 0's file
    best = resumed.checkpoint_callback
    assert best.best_model_path.endswith("best-epoch=00.ckpt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["best-epoch=00.ckpt", "last.ckpt"]


def test_fit_adds_it_beside_a_monitored_checkpoint_only(tmp_path):
    monitored = ModelCheckpoint(dirpath=tmp_path, monitor="val/metric", save_last=True)
    every_epoch = ModelCheckpoint(dirpath=tmp_path / "b", save_last=True)  # no monitor
    no_last = ModelCheckpoint(dirpath=tmp_path / "c", monitor="val/other")
    trainer = pl.Trainer(callbacks=[monitored, every_epoch, no_last], logger=False,
                         enable_progress_bar=False, accelerator="cpu", devices=1)  # fmt: skip
    DifffilterCLI.before_fit(SimpleNamespace(trainer=trainer))
    added = [cb for cb in trainer.callbacks if isinstance(cb, LastCheckpointEveryEpoch)]
    assert [cb.checkpoint for cb in added] == [monitored]
    # after the checkpoint callbacks, so that the file holds their state of the epoch
    assert trainer.callbacks.index(added[0]) > trainer.callbacks.index(no_last)


def test_fast_dev_run_gets_none(tmp_path):
    monitored = ModelCheckpoint(dirpath=tmp_path, monitor="val/metric", save_last=True)
    trainer = pl.Trainer(callbacks=[monitored], logger=False, fast_dev_run=True,
                         enable_progress_bar=False, accelerator="cpu", devices=1)  # fmt: skip
    DifffilterCLI.before_fit(SimpleNamespace(trainer=trainer))
    assert not any(isinstance(cb, LastCheckpointEveryEpoch) for cb in trainer.callbacks)
    assert monitored.save_last is False and monitored.save_top_k == 0


def test_it_needs_a_model_checkpoint():
    with pytest.raises(ValueError, match="checkpoint must be a ModelCheckpoint; got str"):
        LastCheckpointEveryEpoch("last.ckpt")


def test_an_epoch_cut_short_by_max_steps_is_trained_again_whole_on_resume(tmp_path):
    """A user trial: ``--trainer.max_steps`` stopped epoch 1 after one of its two batches,
    ``last.ckpt`` counted the epoch done, and the resume went on with epoch 2: a batch
    skipped, other weights than the uninterrupted run's. Now the file stays at epoch 0."""
    whole = _trainer(tmp_path / "whole", 4)
    whole.fit(reference := _Worsening())
    trainer = _trainer(tmp_path / "cut", 4, max_steps=3)
    trainer.fit(_Worsening())
    assert trainer.global_step == 3 and _epoch_of(tmp_path / "cut" / "last.ckpt") == 0
    count = _CountBatches()
    resumed = _trainer(tmp_path / "cut", 4, count)
    resumed.fit(model := _Worsening(), ckpt_path=tmp_path / "cut" / "last.ckpt")
    assert count.batches == 3 * BATCHES and resumed.global_step == 4 * BATCHES
    assert torch.equal(model.w, reference.w)


def test_ctrl_c_says_how_to_resume(tmp_path, capsys):
    """A user trial: Ctrl-C ended a fit with exit 1 and no word on resuming."""
    cb = LastCheckpointEveryEpoch(ModelCheckpoint(dirpath=tmp_path, monitor="val", save_last=True))
    trainer = SimpleNamespace(is_global_zero=True)
    cb.on_exception(trainer, None, KeyboardInterrupt())
    assert "no last.ckpt to resume from" in capsys.readouterr().out
    (tmp_path / "last.ckpt").write_bytes(b"x")
    cb.on_exception(trainer, None, KeyboardInterrupt())
    assert f"--ckpt_path {tmp_path / 'last.ckpt'}" in capsys.readouterr().out
    cb.on_exception(trainer, None, ValueError("not an interruption"))
    assert capsys.readouterr().out == ""
    # a sweep runs the fit: --ckpt_path is none of its options (a trial followed the advice)
    import os

    from difffilter.train.last_checkpoint import RESUME_HINT

    os.environ[RESUME_HINT] = "rerun the same difffilter-train sweep command"
    try:
        cb.on_exception(trainer, None, KeyboardInterrupt())
    finally:
        del os.environ[RESUME_HINT]
    said = capsys.readouterr().out
    assert "rerun the same difffilter-train sweep command" in said and "--ckpt_path" not in said


def test_a_resume_that_changes_the_runs_settings_is_refused(tmp_path):
    """A user trial resumed a threat-distribution run without its threats: the last epochs
    trained on the scenario's own attack and the card said the network never saw the
    threats; another --seed_everything recorded seeds that reproduce neither half."""
    from difffilter.train.lightning_cli import _check_resumed_settings

    path = tmp_path / "last.ckpt"
    torch.save({"hyper_parameters": {"lr": 0.01, "_instantiator": "x"},
                "datamodule_hyper_parameters": {"threats": {"own": {"weight": 0.3}},
                                                "train_seed": 1}}, path)  # fmt: skip
    model = SimpleNamespace(hparams={"lr": 0.01})
    same = SimpleNamespace(hparams={"threats": {"own": {"weight": 0.3}}, "train_seed": 1})
    _check_resumed_settings(str(path), model, same)  # the same settings: resumes
    other = SimpleNamespace(hparams={"threats": None, "train_seed": 51})
    with pytest.raises(ValueError, match=r"threats: \{'own'.*→ None; --data.init_args.train_seed: "
                       r"1 → 51\): resume with the run's own settings"):  # fmt: skip
        _check_resumed_settings(str(path), model, other)
    _check_resumed_settings(None, model, other)  # a new run: nothing to compare


def test_a_new_fit_into_a_folder_that_holds_a_run_is_refused(tmp_path):
    """A training trial: two fits with --trainer.logger false --trainer.default_root_dir run
    (or a TensorBoard logger given the same version) ended with the second run's
    last.ckpt, config.yaml, export and card in place of the first's, silently."""
    from difffilter.train.lightning_cli import _fixed_run_folder, _refuse_a_used_run_folder

    run = tmp_path / "run"
    no_logger = {"trainer": {"default_root_dir": str(run)}}
    assert _fixed_run_folder(no_logger, False, None) == run
    tb = {"save_dir": str(tmp_path), "name": "mass", "version": 0}
    assert _fixed_run_folder({"trainer": {}}, {}, tb) == tmp_path / "mass" / "version_0"
    named = {**tb, "version": "seed_3"}
    assert _fixed_run_folder({"trainer": {}}, {}, named) == tmp_path / "mass" / "seed_3"
    assert _fixed_run_folder({"trainer": {}}, {}, {**tb, "version": None}) is None  # the next free
    _refuse_a_used_run_folder(run)  # nothing there yet
    run.mkdir()
    (run / "config.yaml").write_text("x: 1\n")  # a run that died before its first checkpoint
    _refuse_a_used_run_folder(run)
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "last.ckpt").write_bytes(b"")  # not a checkpoint torch reads
    with pytest.raises(ValueError, match=r"holds a run already \(checkpoints/last.ckpt\): a new "
                       r"fit would replace its checkpoints, export and card; none of them is a "
                       r"training run's checkpoint to resume from"):  # fmt: skip
        _refuse_a_used_run_folder(run)
    torch.save({"pytorch-lightning_version": "2.6.0", "state_dict": {}},
               run / "checkpoints" / "last.ckpt")  # fmt: skip
    with pytest.raises(ValueError, match=r"holds a run already \(checkpoints/last.ckpt\): a new "
                       r"fit would replace its checkpoints, export and card; resume it with "
                       r"--ckpt_path .*last.ckpt"):  # fmt: skip
        _refuse_a_used_run_folder(run)
    # exported estimators only (the repository's own checkpoints/, default_root_dir .): the
    # hint had offered one of them, of another family, which the resume refused in turn
    shipped = tmp_path / "repo"
    (shipped / "checkpoints").mkdir(parents=True)
    from difffilter.models.neural_estimator import CHECKPOINT_FORMAT

    torch.save({"format": CHECKPOINT_FORMAT, "state_dict": {}},
               shipped / "checkpoints" / "mass_nn_grad.ckpt")  # fmt: skip
    with pytest.raises(ValueError, match="none of them is a training run's checkpoint") as err:
        _refuse_a_used_run_folder(shipped)
    assert "--ckpt_path" not in str(err.value)
    other = tmp_path / "other"
    other.mkdir()
    (other / "mass_nn_grad.ckpt").write_bytes(b"")  # an export alone
    with pytest.raises(ValueError, match=r"holds a run already \(mass_nn_grad.ckpt\)"):
        _refuse_a_used_run_folder(other)


def test_lightnings_last_and_best_are_refused_where_nothing_stands_behind_them(tmp_path):
    """A training trial: ``fit --ckpt_path last`` trained from scratch and ``test --ckpt_path
    last`` scored the initial weights, with Lightning's warning alone: it looks for
    ``last.ckpt`` in the new run's own folder. Where the command fixes a folder that holds
    one, the name stays Lightning's (it resumes from it)."""
    from difffilter.train.lightning_cli import _refuse_a_name_with_nothing_behind

    tb = {"save_dir": str(tmp_path), "name": "mass"}

    def cfg(ckpt, logger=None, root=None, dirpath=None):
        logger = (
            {"class_path": "TensorBoardLogger", "init_args": dict(tb)} if logger is None else logger
        )
        callbacks = [{"class_path": "ModelCheckpoint", "init_args": {"dirpath": dirpath}}]
        return {"ckpt_path": ckpt, "trainer": {"logger": logger, "default_root_dir": root,
                                               "callbacks": callbacks}}  # fmt: skip

    with pytest.raises(ValueError, match=r"--ckpt_path last: .*a new version that holds none "
                                         r"\(it would train from scratch\); give the checkpoint file"):  # fmt: skip
        _refuse_a_name_with_nothing_behind(cfg("last"), "fit")
    older = tmp_path / "mass" / "version_0" / "checkpoints"
    older.mkdir(parents=True)
    (older / "last.ckpt").write_bytes(b"x")
    with pytest.raises(ValueError, match=r"\(it would test the initial weights\); give the file, "
                                         r"e.g. --ckpt_path .*version_0/checkpoints/last.ckpt"):  # fmt: skip
        _refuse_a_name_with_nothing_behind(cfg("last"), "test")
    with pytest.raises(ValueError, match=r"--ckpt_path best: .*a fit run in this same process"):
        _refuse_a_name_with_nothing_behind(cfg("best"), "fit")
    # a folder the command fixes, holding last.ckpt: Lightning's name, left to it
    _refuse_a_name_with_nothing_behind(cfg("last", {**{"init_args": {**tb, "version": 0}}}), "fit")
    root = tmp_path / "root"
    (root / "checkpoints").mkdir(parents=True)
    (root / "checkpoints" / "last.ckpt").write_bytes(b"x")
    _refuse_a_name_with_nothing_behind(cfg("last", False, root=str(root)), "fit")
    _refuse_a_name_with_nothing_behind(cfg("last", dirpath=str(root / "checkpoints")), "fit")
    with pytest.raises(ValueError, match="--ckpt_path last"):  # fixed, but empty
        _refuse_a_name_with_nothing_behind(cfg("last", False, root=str(tmp_path / "new")), "fit")
    _refuse_a_name_with_nothing_behind(cfg(str(older / "last.ckpt")), "fit")  # a path: not ours
