"""A Lightning checkpoint runs with the model settings it was trained with: a command that
gives others is refused, naming each. Lightning (from 2.3) reads the checkpoint's settings
into the config before any hook, so a training trial's resumed fit with ``hidden 32``,
``lr 0.001`` and ``filter ukf`` trained on with 16, 0.01 and ekf, and a ``test`` with
``restart 0.01`` scored the network without it, both without a word (the settings check
compared the checkpoint with itself)."""

from __future__ import annotations

from pathlib import Path

import pytest

from difffilter.train.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_a_checkpoint_given_other_model_settings_is_refused_and_its_own_resume(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    base = ["--config", str(ROOT / "train" / "configs" / "robot.yaml"),
            "--data.init_args.batches_per_epoch=2", "--data.init_args.batch_size=2",
            "--data.init_args.val_runs=4", "--data.init_args.calibration_runs=4",
            "--trainer.enable_progress_bar=false", "--trainer.logger=false",
            f"--trainer.default_root_dir={tmp_path / 'run'}"]  # fmt: skip
    assert main(["fit", *base, "--trainer.max_epochs=1"]) == 0
    ckpt = f"--ckpt_path={tmp_path / 'run' / 'checkpoints' / 'last.ckpt'}"
    capsys.readouterr()
    for command, given, named in (
        ("fit", ["--model.init_args.hidden=32", "--model.init_args.filter=ukf"],
         "--model.init_args.filter: 'ekf' → 'ukf'; --model.init_args.hidden: 16 → 32"),
        ("test", ["--model.init_args.restart=0.01"], "--model.init_args.restart: None → 0.01"),
        ("fit", ["--seed_everything=3"], "--seed_everything: the network's seed 0 → 3"),
    ):  # fmt: skip
        assert main([command, *base, "--trainer.max_epochs=2", *given, ckpt]) == 2, command
        err = capsys.readouterr().err
        assert "this command gives the model other settings than the checkpoint" in err
        assert named in err
    assert main(["fit", *base, "--trainer.max_epochs=2", ckpt]) == 0  # its own: resumes
    assert main(["test", *base, ckpt]) == 0


@pytest.mark.parametrize("value, expected", [(None, {}), ({"a": (1, 2)}, {"a": [1, 2]})])
def test_settings_compare_as_plain_values(value, expected):
    from difffilter.train.lightning_cli import _plain

    assert _plain(value) == expected
