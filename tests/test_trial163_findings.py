"""Findings of a user trial (trial163): training the neural estimator on a plant of one's
own, interrupting and resuming it, calibrating, evaluating and sweeping it."""

from __future__ import annotations

import json
import signal
import warnings
from pathlib import Path

from conftest import small_four_tank_fit

from difffilter.train.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_a_resume_after_an_epoch_that_did_not_improve_keeps_that_epochs_points(
    tmp_path, monkeypatch
):
    """Interrupted in its third epoch after a second epoch whose validation did not improve
    the monitored metric, the run's ``last.ckpt`` is the one ``LastCheckpointEveryEpoch``
    wrote at that validation's end, before Lightning counted the epoch's last batch
    (``_batches_that_stepped`` one short of the step the resumed run goes on at). The resumed
    run must hide only the cut epoch's points: the second epoch's validation (step 5) and its
    last training point stay, as they would in the uninterrupted run (the trial's two-state
    plant lost val/auc of epoch 2 and train/loss at step 23 in TensorBoard)."""
    from lightning.pytorch.callbacks import ModelCheckpoint
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from difffilter.train.task import FilterEstimatorTask

    improves = ModelCheckpoint.check_monitor_top_k

    def only_the_first_epoch_improves(self, trainer, current=None):
        return trainer.current_epoch == 0 and improves(self, trainer, current)

    def interrupt(self, outputs, batch, batch_idx):
        if self.current_epoch == 2 and batch_idx == 1:
            raise KeyboardInterrupt

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    monkeypatch.setattr(ModelCheckpoint, "check_monitor_top_k", only_the_first_epoch_improves)
    small = small_four_tank_fit(max_epochs=4)
    monkeypatch.setattr(FilterEstimatorTask, "on_train_batch_end", interrupt, raising=False)
    handler = signal.getsignal(signal.SIGINT)  # Lightning ignores SIGINT after an interrupt
    try:
        try:
            got = main(["fit", *small])
        except SystemExit as exit_:
            got = exit_.code
    finally:
        signal.signal(signal.SIGINT, handler)
    assert got == 130  # Ctrl-C: as difffilter-eval
    run = tmp_path / "lightning_logs" / "four_tank_nn_grad" / "version_0"
    interrupted = EventAccumulator(str(run)).Reload()
    assert [e.step for e in interrupted.Scalars("val/threshold")] == [2, 5]
    monkeypatch.delattr(FilterEstimatorTask, "on_train_batch_end")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main(["fit", *small, f"--ckpt_path={run / 'checkpoints' / 'last.ckpt'}"]) == 0
    # the resumed epoch ends without a validation: Lightning's hint that the monitored key
    # was never logged blamed the user's code (a trial's friction)
    said = [str(w.message) for w in caught]
    assert not [m for m in said if "could not find the monitored key" in m], said
    events = EventAccumulator(str(run)).Reload()
    assert [e.step for e in events.Scalars("train/loss")] == list(range(12))
    assert [e.step for e in events.Scalars("val/threshold")] == [2, 5, 8, 11]


PLANT_YAML = """\
name: trial163_heater
family: trial163_lab
description: two-zone heater, bias on the first temperature sensor
dt: 0.1
runs: 4
steps: 30
plant:
  F: [[0.9, 0.05], [0.05, 0.9]]
  H: [[1.0, 0.0], [0.0, 1.0]]
  Q: 1.0e-3
  R: 1.0e-2
  P0: 1.0e-2
attack: {kind: bias, value: 0.3, entries: [0], onset: 10, share: 0.5}
"""


def test_a_sweep_of_a_plant_of_ones_own_judges_it_again_in_a_new_process(
    tmp_path, monkeypatch, isolated_registry
):
    """A sweep of a YAML plant judges each seed on the training scenario (its family has no
    headline scenarios but those ``fit`` registered in the process). Run again in a new
    process (``--validation-only`` first, as the README says, then the same command
    without it; or a finished sweep rerun), no ``fit`` runs and the plant is not registered:
    the sweep judged every seed on no scenario at all, an empty table and exit 0 (the
    trial). It must judge them on the plant the checkpoints were trained on."""
    from difffilter.train.sweep import main as sweep_main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    (tmp_path / "heater.yaml").write_text(PLANT_YAML)
    args = ["--config", str(ROOT / "train" / "configs" / "generic.yaml"), "--seeds", "0",
            "--out", "sw", "--runs", "4", "--no-progress", "--validation-only", "--",
            "--scenario", "heater.yaml", "--data.init_args.batch_size=2",
            "--data.init_args.batches_per_epoch=1", "--data.init_args.val_runs=4",
            "--model.init_args.hidden=4", "--trainer.max_epochs=1"]  # fmt: skip
    assert sweep_main(args) == 0
    # a new process: the plant that fit registered is not known there
    isolated_registry._REGISTRY.pop("trial163_heater")
    isolated_registry._ORIGINS.pop("trial163_heater")
    args.remove("--validation-only")
    assert sweep_main(args) == 0
    doc = json.loads((tmp_path / "sw" / "sweep.json").read_text())
    assert list(doc["per_seed"]["0"]["scenarios"]) == ["trial163_heater"]
    assert list(doc["summary"]) == ["trial163_heater"]
