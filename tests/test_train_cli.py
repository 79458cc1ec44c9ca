"""difffilter-train's user errors: one line naming what is wrong, exit 2, no usage dump and
no traceback; its --help names export."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from difffilter.train.cli import main

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ["--config", str(ROOT / "train" / "configs" / "four_tank.yaml")]


def _error_lines(capsys) -> list[str]:
    err = capsys.readouterr().err
    return [line for line in err.splitlines() if not line.startswith(("INFO", "Seed set"))]


@pytest.mark.parametrize(
    ("argv", "why"),
    [
        (["fit", "--config", "nope.yaml"], "File does not exist"),
        (["fit", *CONFIG, "--model.init_args.hidden=abc"], 'Parser key "hidden"'),
        (["fit", *CONFIG, "--data.init_args.batch_size=0"], "batch_size must be a positive"),
        (["fit", *CONFIG, "--trainer.max_epochs=-2"], "max_epochs"),
        (
            ["fitt"],
            "unknown command 'fitt'; choose from fit, validate, test, predict, export, calibrate, sweep",
        ),
        (["fit", *CONFIG, "--scenario"], "--scenario needs a scenario name"),
        # no run folder: its checkpoints and export went to the working folder (a trial)
        (["fit", *CONFIG, "--trainer.logger=false"], "give --trainer.default_root_dir DIR"),
    ],
)
def test_a_bad_command_line_is_one_line_and_exit_2(argv, why, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    assert main(argv) == 2
    lines = _error_lines(capsys)
    assert len(lines) == 1 and lines[0].startswith("difffilter-train: error:"), lines
    assert why in lines[0] and "Union subtypes" not in lines[0]
    assert not (tmp_path / "lightning_logs").exists()  # a failed start leaves no run folder


def test_export_to_an_unwritable_place_is_one_line_and_exit_2(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    shipped = ROOT / "checkpoints" / "four_tank_nn_grad.ckpt"
    assert main(["export", str(shipped), "--out", str(blocker / "x.ckpt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out" in err[0] and "Traceback" not in err[0]


def test_help_names_every_command_without_importing_lightning(capsys, monkeypatch):
    import subprocess
    import sys

    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    assert main(["--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "difffilter-train export SRC --out FILE" in text
    for command in ("fit", "validate", "test", "predict", "export", "calibrate", "sweep"):
        assert f" {command} " in text
    assert main([]) == 2  # no command: the same text, exit 2
    # --help is answered before torch or Lightning is imported (it used to take 10-20 s)
    probe = ("import sys; from difffilter.train.cli import main; from difffilter.eval.cli "
             "import main as ev; main(['--help']); "
             "exec('try:\\n ev([\\'--help\\'])\\nexcept SystemExit: pass'); "
             "print(sorted(m for m in ('torch', 'lightning') if m in sys.modules))")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "[]"


def test_every_command_runs_on_one_thread_unless_difffilter_threads_says(
    tmp_path, monkeypatch, capsys
):
    """The Lightning commands and ``export``/``calibrate``/``sweep`` alike: one intra-op
    thread by default, ``DIFFFILTER_THREADS`` otherwise, a clear error for a bad value."""
    import torch

    before = torch.get_num_threads()
    missing = ["export", str(tmp_path / "missing.ckpt"), "--out", str(tmp_path / "x.ckpt")]
    try:
        monkeypatch.setenv("DIFFFILTER_THREADS", "two")
        assert main(["calibrate", "a.ckpt", "--out", "b.ckpt"]) == 2
        assert _error_lines(capsys) == [
            "difffilter-train: error: DIFFFILTER_THREADS must be a positive integer; got 'two'"
        ]
        monkeypatch.setenv("DIFFFILTER_THREADS", "2")
        assert main(missing) == 2 and torch.get_num_threads() == 2
        monkeypatch.delenv("DIFFFILTER_THREADS")
        assert main(missing) == 2 and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_export_never_writes_over_a_card_without_force(tmp_path, capsys):
    """The card is ``--out`` with suffix ``.json``: an ``--out`` without ``.ckpt`` once
    replaced the card of another file, and a card alone was overwritten silently."""
    import shutil

    shipped = ROOT / "checkpoints" / "four_tank_nn_grad.ckpt"
    ship = tmp_path / "ship"
    ship.mkdir()
    for suffix in (".ckpt", ".json"):
        shutil.copyfile(
            shipped.with_suffix(suffix), (ship / "four_tank_nn_grad").with_suffix(suffix)
        )
    card = (ship / "four_tank_nn_grad.json").read_text()
    other = ROOT / "checkpoints" / "four_tank_nn_ekf.ckpt"
    assert main(["export", str(other), "--out", str(ship / "four_tank_nn_grad")]) == 2
    assert "--out must name a .ckpt file" in capsys.readouterr().err
    (ship / "four_tank_nn_grad.ckpt").unlink()  # the card alone is there
    assert main(["export", str(other), "--out", str(ship / "four_tank_nn_grad.ckpt")]) == 2
    assert "four_tank_nn_grad.json exists; pass --force" in capsys.readouterr().err
    assert (ship / "four_tank_nn_grad.json").read_text() == card


def test_export_keeps_the_weights_dtype(tmp_path):
    """A float64 network trained under Lightning is exported in float64 (once cast to
    float32 on the way)."""
    import torch

    from difffilter.models.neural_estimator import load_estimator_checkpoint
    from difffilter.train.export import export

    net, card = load_estimator_checkpoint(ROOT / "checkpoints" / "four_tank_nn_grad.ckpt")
    assert next(net.parameters()).dtype == torch.float64  # loaded in float64 by default
    state = {k: v + 1e-12 for k, v in net.state_dict().items()}  # below float32's resolution
    src = tmp_path / "last.ckpt"  # what a training run's ModelCheckpoint holds
    torch.save({"pytorch-lightning_version": "2.5.0", "epoch": 3, "global_step": 48,
                "state_dict": {f"estimator.{k}": v for k, v in state.items()},
                "hyper_parameters": {}, "difffilter_estimator_config": net.config(),
                "difffilter_observer": card.to_dict()}, src)  # fmt: skip
    export(src, tmp_path / "out.ckpt")
    back, _ = load_estimator_checkpoint(tmp_path / "out.ckpt", dtype=None)
    for (name, a), b in zip(state.items(), back.state_dict().values(), strict=True):
        assert b.dtype == torch.float64 and torch.equal(a, b), name


def test_export_names_its_source_argument(tmp_path, capsys):
    """A missing or foreign source is named as the command names it (``src``, not ``ckpt``)."""
    from difffilter.train.export import main as export_main

    assert export_main([str(tmp_path / "none.ckpt"), "--out", str(tmp_path / "o.ckpt")]) == 2
    assert "error: src: no checkpoint file at" in capsys.readouterr().err
    (tmp_path / "text.ckpt").write_text("hello")
    assert export_main([str(tmp_path / "text.ckpt"), "--out", str(tmp_path / "o.ckpt")]) == 2
    err = capsys.readouterr().err
    assert "error: src: " in err and "not a weights-only torch checkpoint" in err
    # a user trial: torch's advice came along (load it with weights_only=False, file an
    # issue), and calibrate named its source "ckpt" and complained of --out first
    import pickle

    with open(tmp_path / "pickled.ckpt", "wb") as f:
        pickle.dump({"a": object}, f)  # not weights only: torch adds its advice
    assert export_main([str(tmp_path / "pickled.ckpt"), "--out", str(tmp_path / "o.ckpt")]) == 2
    err = capsys.readouterr().err
    assert "not a weights-only torch checkpoint (UnpicklingError: Unsupported operand" in err
    assert "weights_only` set to `False`" not in err and "file an issue" not in err
    from difffilter.train.calibrate import main as calibrate_main

    (tmp_path / "taken.ckpt").write_text("")
    for run in (export_main, calibrate_main):
        assert run([str(tmp_path / "none.ckpt"), "--out", str(tmp_path / "taken.ckpt")]) == 2
        assert "error: src: no checkpoint file at" in capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1


def test_a_checkpoints_card_given_for_the_checkpoint_is_named_as_such(capsys):
    """A user trial: ``--ckpt checkpoints/four_tank_nn_grad.json`` (the card beside the
    checkpoint) was refused as "does not match the sha256 recorded in the card"."""
    from difffilter.eval.cli import main as eval_main
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    card = "checkpoints/four_tank_nn_grad.json"
    with pytest.raises(ValueError, match=r"ckpt: checkpoints/four_tank_nn_grad.json is a "
                       r"checkpoint's card \(JSON\), not the checkpoint: give "
                       r"checkpoints/four_tank_nn_grad.ckpt"):  # fmt: skip
        load_estimator_checkpoint(card)
    assert eval_main(["four_tank_bias", "--ckpt", card, "--runs", "2"]) == 2
    assert "error: --ckpt: checkpoints/four_tank_nn_grad.json is a checkpoint's card" in (
        capsys.readouterr().err
    )


def test_a_fit_stopped_before_its_first_validation_says_its_export_is_unvalidated(
    tmp_path, monkeypatch, capsys
):
    """A user trial: ``--trainer.max_steps`` inside the first epoch exported weights no
    validation had seen, with "ship it with: difffilter-train export …"."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    args = ["fit", "--config", str(ROOT / "train" / "configs" / "robot.yaml"),
            "--trainer.max_epochs=2", "--data.init_args.batches_per_epoch=3",
            "--data.init_args.val_runs=4", "--trainer.enable_progress_bar=false"]  # fmt: skip
    assert main([*args, "--trainer.max_steps=200"]) == 0  # 100 EKF steps a batch
    out = capsys.readouterr().out
    assert "never validated (the run stopped before its first validation" in out
    assert "ship it with" not in out
    card = tmp_path / "lightning_logs" / "robot_nn_ekf" / "version_0" / "robot_nn_ekf.json"
    doc = json.loads(card.read_text())
    assert doc["best_val_score"] is None
    # no epoch was trained whole (a trial: Lightning's current_epoch counts the cut one)
    assert doc["epochs"] == 0 and doc["global_step"] == 200


def test_an_export_of_a_lightning_checkpoint_carries_the_runs_settings_and_score(tmp_path):
    """A user trial: exported from a run's ``best-*.ckpt``, the card lacked the configs,
    the monitor and the validation score that a fit's own export records."""
    import torch

    from difffilter.models.neural_estimator import load_estimator_checkpoint
    from difffilter.train.export import export

    net, card = load_estimator_checkpoint(ROOT / "checkpoints" / "four_tank_nn_grad.ckpt")
    key = ("ModelCheckpoint{'monitor': 'val/auc', 'mode': 'max', 'every_n_train_steps': 0, "
           "'every_n_epochs': 1, 'train_time_interval': None}")  # fmt: skip
    blob = {"pytorch-lightning_version": "2.6.6", "epoch": 3, "global_step": 48,
            "state_dict": {f"estimator.{k}": v for k, v in net.state_dict().items()},
            "hyper_parameters": {"scenario": "four_tank_bias", "hidden": 16, "_class_path": "x"},
            "datamodule_hyper_parameters": {"scenario": "four_tank_bias", "train_seed": 11},
            "difffilter_estimator_config": net.config(), "difffilter_observer": card.to_dict(),
            "callbacks": {key: {"monitor": "val/auc", "current_score": torch.tensor(0.93),
                                "best_model_score": torch.tensor(0.93),
                                "best_model_path": "/elsewhere/best-epoch=03.ckpt"},
                          "ExportEstimator": {"train_time_s": 12.5}}}  # fmt: skip
    torch.save(blob, tmp_path / "best-epoch=03.ckpt")
    torch.save(blob, tmp_path / "last.ckpt")
    for name in ("best-epoch=03.ckpt", "last.ckpt"):
        export(tmp_path / name, tmp_path / "out" / f"{name}.ckpt".replace("=", "_"))
    best = json.loads((tmp_path / "out" / "best-epoch_03.ckpt.json").read_text())
    assert best["model_config"] == {"scenario": "four_tank_bias", "hidden": 16}
    # written at the end of epoch index 3: four epochs, as a fit's own card counts them
    assert best["data_config"]["train_seed"] == 11 and best["epochs"] == 4
    assert best["train_time_s"] == 12.5  # the time so far, which the checkpoint carries
    assert best["monitor"] == {"metric": "val/auc", "mode": "max"}
    assert best["val_score"] == best["best_val_score"] == pytest.approx(0.93)
    last = json.loads((tmp_path / "out" / "last.ckpt.json").read_text())
    # a file without the task's record of its epoch's validation, and not the callback's
    # best: its current_score may be another epoch's (a trial), so no score is claimed
    assert last["val_score"] is None and "best_val_score" not in last


def test_training_commands_print_no_lightning_noise(tmp_path, monkeypatch, caplog, recwarn):
    """A user trial: every command printed a cloud logger's advertisement and torch's
    deprecation of a check inside Lightning, and each seed of a sweep Lightning's warning
    that both ``args`` and ``sys.argv`` were given (``sys.argv`` was the sweep's)."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train", "sweep", "--seeds", "0"])
    with caplog.at_level("INFO"):
        assert main(["fit", "--config", str(ROOT / "train" / "configs" / "robot.yaml"),
                     "--trainer.fast_dev_run=1"]) == 0  # fmt: skip
    assert not [r for r in caplog.records if "Tip:" in r.getMessage()]
    said = [str(w.message) for w in recwarn]
    assert not [m for m in said if "LeafSpec" in m or "args parameter is intended" in m], said
    import sys

    assert sys.argv == ["difffilter-train", "sweep", "--seeds", "0"]  # given back


def test_the_weights_digest_is_the_same_for_the_same_weights_in_another_file(tmp_path):
    """A retrained network's export has another file sha256 than the shipped one (the cards
    inside differ) even with the shipped weights; ``weights_sha256`` is the same, and a
    calibration keeps it (test_calibrate_checkpoint)."""
    import torch

    from difffilter.models.neural_estimator import (
        checkpoint_sha256,
        load_estimator_checkpoint,
        weights_sha256,
    )
    from difffilter.train.export import export

    shipped = ROOT / "checkpoints" / "robot_nn_ekf.ckpt"
    shipped_card = json.loads(shipped.with_suffix(".json").read_text())
    net, card = load_estimator_checkpoint(shipped, dtype=torch.float32)  # as trained
    blob = {"pytorch-lightning_version": "2.6.6", "epoch": 1, "global_step": 8,
            "state_dict": {f"estimator.{k}": v for k, v in net.state_dict().items()},
            "difffilter_estimator_config": net.config(),
            "difffilter_observer": {**card.to_dict(), "threshold": 0.5}}  # fmt: skip
    torch.save(blob, tmp_path / "last.ckpt")
    with pytest.raises(ValueError, match="Lightning checkpoint.*export it first"):
        weights_sha256(tmp_path / "last.ckpt")
    out = export(tmp_path / "last.ckpt", tmp_path / "retrained.ckpt")
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["sha256"] == checkpoint_sha256(out) != shipped_card["sha256"]
    assert card["weights_sha256"] == shipped_card["weights_sha256"] == weights_sha256(shipped)
    other = dict(net.state_dict(), W=net.state_dict()["W"] + 1e-7)
    assert weights_sha256(other) != weights_sha256(net.state_dict())
    for name in ("four_tank_nn_ekf", "four_tank_nn_grad", "lfc_nn_grad", "tracking_nn_grad"):
        path = ROOT / "checkpoints" / f"{name}.ckpt"
        recorded = json.loads(path.with_suffix(".json").read_text())["weights_sha256"]
        assert recorded == weights_sha256(path), name
