"""Training of kf_nn_grad in the LFC closed loop with the one training task: configs,
TensorBoard logging, resuming, the shipped checkpoint."""

from __future__ import annotations

import json
from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch

from difffilter.models.neural_estimator import load_estimator_checkpoint
from difffilter.train.cli import main
from difffilter.train.export import check_metric
from difffilter.train.task import FilterEstimatorTask, ScenarioDataModule

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted((ROOT / "train" / "configs").glob("*.yaml"))
CKPT = ROOT / "checkpoints" / "lfc_nn_grad.ckpt"

# A tiny problem (short trajectories, few runs) for the tests that really train.
SCENARIO = "lfc_random_attacks"
TINY_DATA = dict(
    scenario=SCENARIO, batch_size=4, batches_per_epoch=2, val_runs=4, steps=120,
    train_seed=11, val_seed=12,
)  # fmt: skip
TINY_MODEL = dict(
    scenario=SCENARIO, filter="kf", areas=2, hidden=6, resid_scale=1.0, residual="predicted",
    standardize=False, lr=0.01, pct_start=0.1, tbptt_steps=40, state_weight=0.0,
    bce_weight=0.05, control_weight=0.01, monitor_scenarios=["lfc_step"], monitor_runs=2,
)  # fmt: skip


def LFCGradModule(**kw):  # noqa: N802 - the LFC configuration of the one task
    return FilterEstimatorTask(**{**TINY_MODEL, **kw})


def LFCDataModule(**kw):  # noqa: N802
    return ScenarioDataModule(**{**TINY_DATA, **kw})


def test_configs_exist():
    assert any(p.name == "lfc.yaml" for p in CONFIGS)


@pytest.mark.parametrize("config", CONFIGS, ids=lambda p: p.name)
def test_every_config_runs_fast_dev_run(config, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # anything a config writes lands in the temporary folder
    monkeypatch.setattr("sys.argv", ["difffilter-train"])  # pytest's own flags are not ours
    code = main(
        [
            "fit",
            "--config",
            str(config),
            "--trainer.fast_dev_run=1",
            f"--trainer.default_root_dir={tmp_path}",
        ]
    )
    assert code == 0
    assert not (tmp_path / "checkpoints").exists()  # no export, no last.ckpt in dev runs


def _tiny_trainer(tmp_path, max_epochs, callbacks=(), logger=False):
    ckpt = pl.callbacks.ModelCheckpoint(
        dirpath=tmp_path / "ckpt", monitor="val/attack_rmse", save_last=True, save_top_k=1
    )
    return pl.Trainer(
        max_epochs=max_epochs,
        accelerator="cpu",
        devices=1,
        logger=logger,
        callbacks=[ckpt, *callbacks],
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        use_distributed_sampler=False,
        default_root_dir=tmp_path,
        log_every_n_steps=1,
    )


class _StopAfterFirstEpoch(pl.Callback):
    """Simulates an interruption: the run stops after epoch 0 (its last.ckpt is on disk)."""

    def on_train_epoch_end(self, trainer, pl_module):
        trainer.should_stop = True


def test_interrupted_training_resumes_from_last_checkpoint(tmp_path):
    pl.seed_everything(0)
    full = LFCGradModule()
    _tiny_trainer(tmp_path / "full", 2).fit(full, LFCDataModule())

    pl.seed_everything(0)
    first = LFCGradModule()
    t1 = _tiny_trainer(tmp_path / "cut", 2, callbacks=[_StopAfterFirstEpoch()])
    t1.fit(first, LFCDataModule())
    last = tmp_path / "cut" / "ckpt" / "last.ckpt"
    assert last.is_file() and t1.current_epoch == 1
    assert not torch.allclose(first.estimator.V, full.estimator.V)

    pl.seed_everything(123)  # the resumed run must not depend on the global seed
    resumed = LFCGradModule()
    t2 = _tiny_trainer(tmp_path / "cut", 2)
    t2.fit(resumed, LFCDataModule(), ckpt_path=last)
    assert t2.global_step == 2 * 2 * 3  # 2 epochs × 2 batches × 3 TBPTT chunks
    for name in ("V", "W", "P", "c"):
        assert torch.allclose(
            getattr(resumed.estimator, name), getattr(full.estimator, name), atol=1e-6
        ), name


def test_tensorboard_events_hold_scalars_images_and_hparams(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    logger = pl.loggers.TensorBoardLogger(tmp_path, name="tb", default_hp_metric=False)
    pl.seed_everything(0)
    module = LFCGradModule()
    lr = pl.callbacks.LearningRateMonitor(logging_interval="step")
    trainer = _tiny_trainer(tmp_path, 1, callbacks=[lr], logger=logger)
    trainer.fit(module, LFCDataModule())
    acc = EventAccumulator(str(logger.log_dir), size_guidance={"images": 0, "scalars": 0})
    acc.Reload()
    scalars = set(acc.Tags()["scalars"])
    for tag in (
        "train/loss",
        "train/attack_mse",
        "train/control_mse",
        "train/grad_norm",
        "lr-AdamW",  # the one learning-rate curve
        "val/attack_rmse",
        "val/auc",
        "val/scenario/lfc_step/attack_rmse",
    ):
        assert tag in scalars, tag
    assert acc.Scalars("val/attack_rmse")[-1].value > 0
    images = set(acc.Tags()["images"])
    assert {"val/attack_estimate", "val/scenario/lfc_step"} <= images
    assert acc.Images("val/scenario/lfc_step")[0].encoded_image_string[:4] == b"\x89PNG"
    assert (Path(logger.log_dir) / "hparams.yaml").is_file()
    hp = (Path(logger.log_dir) / "hparams.yaml").read_text()
    assert "tbptt_steps: 40" in hp and "hidden: 6" in hp
    assert "batch_size: 4" in hp and "train_seed: 11" in hp  # the data's settings too
    assert "train/lr" not in scalars


def test_datamodule_seeds():
    dm = LFCDataModule()
    first = dm.train_batch(0, 0)
    assert torch.equal(first["attack"], dm.train_batch(0, 0)["attack"])  # reproducible
    assert not torch.equal(first["xi"], dm.train_batch(1, 0)["xi"])  # new epoch, new data
    assert not torch.equal(first["xi"], dm.train_batch(0, 1)["xi"])
    assert first["attack"].shape == (4, 120, 10)
    key = next(iter(dm.train_dataloader()))
    assert torch.equal(dm.on_after_batch_transfer(key, 0)["xi"], first["xi"])
    val = next(iter(dm.val_dataloader()))
    assert val["xi"].shape == (4, 120, 10) and not torch.equal(val["xi"], first["xi"])
    with pytest.raises(ValueError, match="differ"):
        LFCDataModule(train_seed=3, val_seed=3)
    assert first["load"].shape == (4, 2) and not torch.equal(first["load"][0], first["load"][1])


@pytest.mark.skipif(not CKPT.is_file(), reason="the shipped checkpoint is produced by training")
def test_shipped_checkpoint_loads_and_reproduces_its_card():
    raw = torch.load(CKPT, map_location="cpu", weights_only=True)
    assert isinstance(raw["state_dict"], dict)
    card = json.loads(CKPT.with_suffix(".json").read_text())
    assert card["torch_version"] and card["seed"]["train_seed"] != card["seed"]["val_seed"]
    assert card["train_time_s"] <= 15 * 60
    _, typed = load_estimator_checkpoint(CKPT)
    assert typed.filter == "kf" and typed.residual == "predicted" and typed.scenario_family == "lfc"
    check = card["check"]
    value = check_metric(CKPT, seed=check["seed"], runs=check["runs"])["value"]
    assert value == pytest.approx(check["value"], rel=1e-6)


def test_loss_terms_by_hand():
    """The attack MSE, the per-area BCE and the control-weighted term of the LFC config."""
    from types import SimpleNamespace

    g = torch.Generator().manual_seed(0)
    attack, est, logits = (torch.randn(2, 5, 10, generator=g) for _ in range(3))
    attack[0, :, :5] = 0  # area 1 of run 0 not attacked
    logits = logits[..., :2]
    task = LFCGradModule(monitor_scenarios=[])
    out = SimpleNamespace(attack=est, means=torch.zeros(2, 5, 10), extras={"area_logits": logits})
    truth = {"attack": attack, "x": torch.zeros(2, 5, 10), "flags": (attack != 0).any(-1)}
    losses = task._losses(out, truth)
    assert losses["attack_mse"].item() == pytest.approx((est - attack).square().mean().item())
    K = task.scenario.feedback_gain(torch.float32)
    du = (est - attack) @ K.T
    assert losses["control_mse"].item() == pytest.approx(du.square().mean().item(), rel=1e-6)
    flags = (attack.reshape(2, 5, 2, 5) != 0).any(-1).float()
    bce = torch.nn.functional.binary_cross_entropy_with_logits(logits, flags)
    assert losses["bce"].item() == pytest.approx(bce.item())
    assert losses["loss"].item() == pytest.approx(
        (losses["attack_mse"] + 0.05 * bce + 0.01 * losses["control_mse"]).item(), rel=1e-6
    )


def test_an_endless_schedule_is_a_clear_cli_error(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    code = main(
        [
            "fit",
            "--config",
            str(ROOT / "train" / "configs" / "lfc.yaml"),
            "--trainer.max_epochs=-1",
            "--trainer.limit_train_batches=1",
            f"--trainer.default_root_dir={tmp_path}",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "max_epochs" in err and "Traceback" not in err


def test_resuming_with_a_longer_schedule_is_refused_clearly(tmp_path):
    # pct_start 0.4: the schedule is batches × chunks long (not its 2-step warm-up floor)
    pl.seed_everything(0)
    _tiny_trainer(tmp_path / "cut", 1).fit(LFCGradModule(pct_start=0.4), LFCDataModule())
    last = tmp_path / "cut" / "ckpt" / "last.ckpt"
    with pytest.raises(ValueError, match="ckpt_path.*schedule has 7 steps but this run needs 12"):
        _tiny_trainer(tmp_path / "cut", 2).fit(
            LFCGradModule(pct_start=0.4), LFCDataModule(), ckpt_path=last
        )


def test_fit_writes_only_inside_its_run_and_export_ships_it(tmp_path, monkeypatch):
    """``fit`` leaves ``checkpoints/`` alone; ``export`` ships the run's estimator (from the
    exported file or the Lightning checkpoint: the same weights, the same evaluation)."""
    import dataclasses

    from difffilter.eval.suite import run_suite
    from difffilter.models import registry

    shipped = {p.name: p.read_bytes() for p in (ROOT / "checkpoints").iterdir()}
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    tiny = [
        "--data.batch_size=2",
        "--data.batches_per_epoch=1",
        "--data.val_runs=2",
        "--data.steps=60",
        "--model.tbptt_steps=30",
        "--model.monitor_runs=1",
    ]
    config = str(ROOT / "train" / "configs" / "lfc.yaml")  # the LFC config of the one task
    assert main(["fit", "--config", config, "--trainer.max_epochs=1", *tiny]) == 0
    run = tmp_path / "lightning_logs" / "lfc_nn_grad" / "version_0"
    assert (run / "lfc_nn_grad.ckpt").is_file() and (run / "lfc_nn_grad.json").is_file()
    assert {p.name: p.read_bytes() for p in (ROOT / "checkpoints").iterdir()} == shipped
    assert not (tmp_path / "checkpoints").exists()
    # resuming continues the same run folder (its TensorBoard curves), not a new version_1
    resume = ["--ckpt_path", str(run / "checkpoints" / "last.ckpt")]
    assert main(["fit", "--config", config, "--trainer.max_epochs=1", *tiny, *resume]) == 0
    assert sorted(p.name for p in run.parent.iterdir()) == ["version_0"]
    # ... but from another folder it logs into a new version there: it took the
    # checkpoint's version_0 and overwrote that folder's own run's export and card
    other = tmp_path / "other" / "lightning_logs" / "lfc_nn_grad" / "version_0"
    other.mkdir(parents=True)
    (other / "lfc_nn_grad.json").write_text("another run's card")
    monkeypatch.chdir(tmp_path / "other")  # (one more epoch: a finished run exports nothing)
    assert main(["fit", "--config", config, "--trainer.max_epochs=2", *tiny, *resume]) == 0
    assert (other / "lfc_nn_grad.json").read_text() == "another run's card"
    assert (other.parent / "version_1" / "lfc_nn_grad.ckpt").is_file()
    monkeypatch.chdir(tmp_path)

    assert main(["export", str(run / "lfc_nn_grad.ckpt"), "--out", "ship/a.ckpt"]) == 0
    assert main(["export", str(run / "lfc_nn_grad.ckpt"), "--out", "ship/a.ckpt"]) == 2  # exists
    best = next((run / "checkpoints").glob("best-*.ckpt"))
    assert main(["export", str(best), "--out", "ship/b.ckpt"]) == 0
    card = json.loads((tmp_path / "ship" / "a.json").read_text())
    assert card["exported_from"].endswith("lfc_nn_grad.ckpt") and "sha256" in card

    # the threshold the validation chose, on the statistic the entry reads, is the entry's
    record = card["observer"]["extra"]["calibration"]
    assert record["threshold"] == card["observer"]["threshold"] != 0.5
    assert record["estimator"] == "kf_nn_grad" and record["confirm"] == 0.01

    sc = dataclasses.replace(registry.get("lfc_step"), duration=0.5)
    numbers = []
    for ckpt in (tmp_path / "ship" / "a.ckpt", tmp_path / "ship" / "b.ckpt", best):
        out = run_suite(sc, runs=2, estimators=("kf_nn_grad",), checkpoint=ckpt, progress=False)
        assert out.checkpoint["used_by"] == ["kf_nn_grad"]
        assert out.outputs["kf_nn_grad"].detection.threshold == record["threshold"]
        numbers.append(out.outputs["kf_nn_grad"].attack)
    torch.testing.assert_close(numbers[0], numbers[1], rtol=0, atol=1e-6)
    torch.testing.assert_close(numbers[1], numbers[2], rtol=0, atol=0)


def test_validate_and_test_take_the_exported_checkpoint(tmp_path, monkeypatch, capsys):
    """``validate``/``test`` load an exported file into the configured module; ``test`` runs
    the LFC test scenarios on difffilter-eval's draws; a mismatched model is refused."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    config = ["--config", str(ROOT / "train" / "configs" / "lfc.yaml"), "--ckpt_path", str(CKPT)]
    # the shipped network was trained before the config's gating and plain innovation (its
    # card's restart and confirmation, the config's, were set by difffilter-train calibrate)
    config += ["--model.gating=false", "--model.features=null"]
    small = ["--data.val_runs=2", "--data.steps=60", "--data.test_runs=2"]
    # a module that would score it otherwise than its threshold was chosen for is refused
    assert main(["validate", *config, *small, "--model.confirm=null"]) == 2
    assert "confirm = 0.01, the configured model has None" in capsys.readouterr().err
    assert main(["validate", *config, *small]) == 0
    assert main(["test", *config, *small]) == 0
    out = capsys.readouterr().out
    assert "loaded the exported estimator" in out and "test/scenario/lfc_step/attack_rmse" in out
    events = list((tmp_path / "lightning_logs").rglob("events.out.tfevents*"))
    assert events  # test metrics and figures go to TensorBoard
    assert main(["test", *config, *small, "--model.hidden=4"]) == 2
    assert "settings" in capsys.readouterr().err


def test_monitor_scenarios_of_another_family_are_refused():
    with pytest.raises(ValueError, match="monitor_scenarios: 'four_tank_bias' is not a lfc"):
        LFCGradModule(monitor_scenarios=["four_tank_bias"])


def test_ddp_on_two_cpu_processes_trains_and_exports_once(tmp_path):
    """``--trainer.strategy ddp --trainer.devices 2`` on CPU (gloo): each process simulates
    its half of the epoch's seeded batches, one process writes the export."""
    import subprocess
    import sys

    tiny = [
        "--data.batch_size=2",
        "--data.batches_per_epoch=2",
        "--data.val_runs=2",
        "--data.steps=60",
        "--model.tbptt_steps=30",
        "--model.monitor_runs=1",
    ]
    cmd = [
        sys.executable,
        "-m",
        "difffilter.train.cli",
        "fit",
        "--config",
        str(ROOT / "train" / "configs" / "lfc.yaml"),
        "--trainer.max_epochs=1",
        "--trainer.strategy=ddp",
        "--trainer.devices=2",
        "--trainer.accelerator=cpu",
        *tiny,
    ]
    done = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.count("exported ") == 1
    run = tmp_path / "lightning_logs" / "lfc_nn_grad" / "version_0"
    estimator, _ = load_estimator_checkpoint(run / "lfc_nn_grad.ckpt")
    assert all(torch.isfinite(p).all() for p in estimator.parameters())
