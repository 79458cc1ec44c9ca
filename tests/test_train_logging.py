"""One logging contract for every training config: a one-epoch run of one small batch
writes HPARAMS data, a learning-rate tag, the training loss and at least one image
(read back from the TensorBoard events with EventAccumulator)."""

from __future__ import annotations

from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from difffilter.train.cli import main

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted(p.stem for p in (ROOT / "train" / "configs").glob("*.yaml"))
SMALL = {  # what each config needs beside the common small settings
    "four_tank": ["--model.init_args.num_particles=20"],
    "tracking": ["--model.init_args.num_particles=20"],
    "robot": ["--data.init_args.steps=45"],  # its report reads the estimate at k = 44
    # its threats start at k = 10…60 (and the report reads k = 44)
    "robot_threats": ["--data.init_args.steps=70", "--data.init_args.val_runs=8"],
    # its threats start at k = 5…60: the validation runs need attacked steps for val/auc
    "four_tank_threats": ["--data.init_args.steps=100", "--data.init_args.val_runs=8"],
    "lfc": ["--model.init_args.monitor_runs=1", "--model.init_args.tbptt_steps=10"],
}


def test_every_config_is_covered():
    assert set(CONFIGS) == {
        "four_tank",
        "four_tank_ekf",
        "four_tank_threats",
        "generic",
        "lfc",
        "robot",
        "robot_threats",
        "tracking",
    }


@pytest.mark.parametrize("config", CONFIGS)
def test_a_short_run_logs_hparams_learning_rate_loss_and_figures(config, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    argv = ["fit", "--config", str(ROOT / "train" / "configs" / f"{config}.yaml"),
            "--data.init_args.batch_size=2", "--data.init_args.batches_per_epoch=1",
            "--data.init_args.val_runs=4", "--data.init_args.steps=20",
            "--model.init_args.hidden=4", "--trainer.max_epochs=1",
            "--trainer.log_every_n_steps=1", *SMALL.get(config, [])]  # fmt: skip
    # a later option wins: the robot's longer horizon replaces the common one
    assert main(argv) == 0
    (run,) = (tmp_path / "lightning_logs").glob("*/version_0")
    events = EventAccumulator(str(run))
    events.Reload()
    tags = events.Tags()
    assert events.PluginTagToContent("hparams"), "no HPARAMS data"
    assert any(t.startswith("lr-") for t in tags["scalars"]), tags["scalars"]
    assert "train/loss" in tags["scalars"] and "val/threshold" in tags["scalars"]
    assert tags["images"], "no figure"
    # the validation's figure at the step of its scalars (it was one step later; the EKF
    # trainer's, at its optimizer steps, one per time step, far later)
    figure_steps = [e.step for e in events.Images("val/attack_estimate")]
    assert figure_steps == [e.step for e in events.Scalars("val/threshold")], figure_steps
    # the best score beside the settings where the curves end (the EKF trainer's had gone
    # to its optimizer steps: 3,200 beside curves ending at 31 in a trial's robot run)
    if _log_hyperparams_takes_step():
        (best,) = events.Scalars("hp/best_val_score")
        assert best.step in (figure_steps[-1], figure_steps[-1] + 1), (best.step, figure_steps)
    # the card's description names a distribution over threats where one was trained on (a
    # trial's said its scenario alone)
    import json

    (card,) = [c for c in (json.loads(p.read_text()) for p in run.glob("*.json"))
               if "description" in c]  # fmt: skip
    across = "its attacks drawn from a distribution over threats (" in card["description"]
    assert across == config.endswith("_threats"), card["description"]


def test_a_run_with_another_logger_ends_cleanly_and_records_its_best_score(tmp_path, monkeypatch):
    """The best validation score goes beside the settings with any logger (TensorBoard's
    HPARAMS view takes both; a CSV logger once failed at the end of fit on the pair)."""
    import csv

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    argv = ["fit", "--config", str(ROOT / "train" / "configs" / "four_tank.yaml"),
            "--data.init_args.batch_size=2", "--data.init_args.batches_per_epoch=1",
            "--data.init_args.val_runs=4", "--data.init_args.steps=20",
            "--model.init_args.hidden=4", "--trainer.max_epochs=1",
            "--model.init_args.num_particles=20",
            "--trainer.logger=lightning.pytorch.loggers.CSVLogger",
            "--trainer.logger.save_dir=csv_logs"]  # fmt: skip
    assert main(argv) == 0
    (metrics,) = (tmp_path / "csv_logs").rglob("metrics.csv")
    rows = list(csv.DictReader(metrics.open()))
    assert any(r.get("hp/best_val_score") for r in rows)


def _log_hyperparams_takes_step() -> bool:
    """Whether this Lightning's TensorBoardLogger.log_hyperparams takes a step (2.3 on)."""
    import inspect

    from lightning.pytorch.loggers import TensorBoardLogger

    return "step" in inspect.signature(TensorBoardLogger.log_hyperparams).parameters


def test_the_best_score_beside_the_settings_is_at_the_step_the_run_ended(tmp_path, monkeypatch):
    """TensorBoard's hp/best_val_score went to step 0 (a resumed run's too), left of every
    curve; with a Lightning whose log_hyperparams takes a step it is at the run's last."""
    import json

    _one_epoch_run(tmp_path, monkeypatch)
    run = tmp_path / "lightning_logs" / "four_tank_nn_grad" / "version_0"
    (event,) = EventAccumulator(str(run)).Reload().Scalars("hp/best_val_score")
    card = json.loads((run / "four_tank_nn_grad.json").read_text())
    # the gradient trainer steps once a batch: its global_step counts the batches
    assert event.step == (card["global_step"] if _log_hyperparams_takes_step() else 0)
    assert event.value == pytest.approx(card["best_val_score"])


def _one_epoch_run(tmp_path, monkeypatch, code: int = 0) -> list[str]:
    """A tiny four-tank fit of one epoch in ``tmp_path``, ending with exit ``code`` (Ctrl-C:
    130, returned or raised as ``SystemExit`` as the Lightning version does); returns its
    options (to resume)."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    small = ["--config", str(ROOT / "train" / "configs" / "four_tank.yaml"),
             "--data.init_args.batch_size=2", "--data.init_args.batches_per_epoch=1",
             "--data.init_args.val_runs=4", "--data.init_args.steps=20",
             "--model.init_args.hidden=4", "--model.init_args.num_particles=20"]  # fmt: skip
    try:
        got = main(["fit", *small, "--trainer.max_epochs=1"])
    except SystemExit as exit_:
        got = exit_.code
    assert got == code
    return small


def test_a_finished_run_resumed_for_more_epochs_exports_a_matching_pair(tmp_path, monkeypatch):
    """Its first export's card once stayed beside the new file during the second export,
    whose own loads checked against it: 'does not match the sha256', exit 2."""
    import json

    from difffilter.models.neural_estimator import load_estimator_checkpoint, weights_sha256

    small = _one_epoch_run(tmp_path, monkeypatch)
    run = tmp_path / "lightning_logs" / "four_tank_nn_grad" / "version_0"
    last = run / "checkpoints" / "last.ckpt"
    assert main(["fit", *small, "--trainer.max_epochs=2", f"--ckpt_path={last}"]) == 0
    exported = sorted((tmp_path / "lightning_logs").rglob("four_tank_nn_grad.ckpt"))
    assert exported
    for path in exported:
        load_estimator_checkpoint(path)  # each pair matches
        card = json.loads(path.with_suffix(".json").read_text())
        assert card["weights_sha256"] == weights_sha256(path)


def test_resuming_a_finished_run_keeps_its_export_and_counts_the_whole_training_time(
    tmp_path, monkeypatch, capsys
):  # fmt: skip
    """A user trial: resuming a run that had reached max_epochs re-exported it with a card
    of nothing (best_val_score null, no validation metrics, train_time_s 0.009); and a
    resumed run's card counted only its last process's seconds."""
    import json

    small = _one_epoch_run(tmp_path, monkeypatch)
    run = tmp_path / "lightning_logs" / "four_tank_nn_grad" / "version_0"
    card_path = run / "four_tank_nn_grad.json"
    first = json.loads(card_path.read_text())
    last = run / "checkpoints" / "last.ckpt"
    capsys.readouterr()
    assert main(["fit", *small, "--trainer.max_epochs=1", f"--ckpt_path={last}"]) == 0
    assert "nothing to train" in capsys.readouterr().out
    assert json.loads(card_path.read_text()) == first  # the card as it was
    assert not list((tmp_path / "lightning_logs").rglob("version_1/four_tank_nn_grad.json"))
    assert main(["fit", *small, "--trainer.max_epochs=2", f"--ckpt_path={last}"]) == 0
    cards = [json.loads(p.read_text()) for p in
             (tmp_path / "lightning_logs").rglob("four_tank_nn_grad.json")]  # fmt: skip
    (resumed,) = [c for c in cards if c["global_step"] == 2 * first["global_step"]]
    assert resumed["train_time_s"] > first["train_time_s"]  # the first epoch's seconds too
    assert resumed["best_val_score"] is not None and resumed["metrics_last_validation"]


def test_ctrl_c_while_exporting_leaves_no_card_less_file_and_says_how_to_export(
    tmp_path, monkeypatch, capsys
):  # fmt: skip
    """Ctrl-C during the export's check left a checkpoint without its card and a resume hint
    whose resume trains nothing; the file goes now and the message names the export."""
    import signal

    from difffilter.models.neural_estimator import load_estimator_checkpoint

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("difffilter.train.export.check_metric", interrupt)
    handler = signal.getsignal(signal.SIGINT)  # Lightning ignores SIGINT after an interrupt
    try:
        _one_epoch_run(tmp_path, monkeypatch, code=130)
    finally:
        signal.signal(signal.SIGINT, handler)
    run = tmp_path / "lightning_logs" / "four_tank_nn_grad" / "version_0"
    assert not (run / "four_tank_nn_grad.ckpt").exists()
    out = capsys.readouterr().out
    source = out.split("export it with: difffilter-train export ")[1].split(" --out")[0]
    assert Path(source).is_file() and "interrupted while exporting" in out
    monkeypatch.undo()
    monkeypatch.chdir(tmp_path)
    assert main(["export", source, "--out", str(tmp_path / "shipped.ckpt")]) == 0
    load_estimator_checkpoint(tmp_path / "shipped.ckpt")


def test_resuming_a_finished_run_whose_export_was_interrupted_exports_it(
    tmp_path, monkeypatch, capsys
):  # fmt: skip
    """A sweep trial: stopped while a finished run's export was written (the file without
    its card removed), the run resumed from ``last.ckpt`` trained nothing and exported
    nothing, and a sweep stopped at that seed for good. Now the resume exports the weights
    the checkpoint callback had chosen."""
    import json

    small = _one_epoch_run(tmp_path, monkeypatch)
    run = tmp_path / "lightning_logs" / "four_tank_nn_grad" / "version_0"
    first = json.loads((run / "four_tank_nn_grad.json").read_text())
    for suffix in (".ckpt", ".json"):  # the interrupted export
        (run / "four_tank_nn_grad").with_suffix(suffix).unlink()
    capsys.readouterr()
    last = run / "checkpoints" / "last.ckpt"
    assert main(["fit", *small, "--trainer.max_epochs=1", f"--ckpt_path={last}"]) == 0
    assert "its export was not written: exporting it now" in capsys.readouterr().out
    (card_path,) = (tmp_path / "lightning_logs").rglob("four_tank_nn_grad.json")
    card = json.loads(card_path.read_text())
    assert card["weights_sha256"] == first["weights_sha256"]
    assert card["best_val_score"] == first["best_val_score"]
