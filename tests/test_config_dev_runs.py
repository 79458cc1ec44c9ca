"""Every training config runs a Lightning ``fast_dev_run`` in ``make test``: one training
batch and one validation batch through ``difffilter-train fit --config <config>``, on a
few short runs (``batch_size``, ``val_runs``, ``calibration_runs`` 2, a 60-step horizon,
one run per monitored scenario), so that a config whose classes, options or values no
longer fit the task fails in the fast suite, not first in a user's training. The same
``fast_dev_run`` on each config's own sizes is in the ``slow`` group
(``tests/test_lfc_train.py::test_every_config_runs_fast_dev_run``, 0.8–19 s a config)."""

from __future__ import annotations

from pathlib import Path

import pytest

from difffilter.train.cli import main

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted((ROOT / "train" / "configs").glob("*.yaml"))
#: The sizes a short development run overrides (each config keeps every other setting).
SHORT = (
    "--data.init_args.batch_size=2", "--data.init_args.val_runs=2",
    "--data.init_args.calibration_runs=2", "--data.init_args.steps=60",
    "--model.init_args.monitor_runs=1",
)  # fmt: skip


def test_the_configs_are_found():
    names = {p.name for p in CONFIGS}
    assert {"four_tank.yaml", "lfc.yaml", "robot.yaml", "tracking.yaml"} <= names


@pytest.mark.parametrize("config", CONFIGS, ids=lambda p: p.name)
def test_every_config_runs_a_short_fast_dev_run(config, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # anything a config writes lands in the temporary folder
    monkeypatch.setattr("sys.argv", ["difffilter-train"])  # pytest's own flags are not ours
    args = ["fit", "--config", str(config), "--trainer.fast_dev_run=1",
            f"--trainer.default_root_dir={tmp_path}", *SHORT]  # fmt: skip
    assert main(args) == 0
    assert not (tmp_path / "checkpoints").exists()  # no export, no last.ckpt in dev runs
    assert not (tmp_path / "lightning_logs").exists()  # a dev run logs nowhere


def test_a_config_that_no_longer_fits_the_task_fails_its_short_run(tmp_path, monkeypatch, capsys):
    """The check can fail: a config naming an option the task does not have is refused."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    text = (ROOT / "train" / "configs" / "four_tank.yaml").read_text()
    bad = tmp_path / "bad.yaml"
    head = "model:\n  class_path: difffilter.train.task.FilterEstimatorTask\n  init_args:\n"
    assert head in text
    bad.write_text(text.replace(head, head + "    no_such_option: 1\n"))
    args = ["fit", "--config", str(bad), "--trainer.fast_dev_run=1",
            f"--trainer.default_root_dir={tmp_path}", *SHORT]  # fmt: skip
    assert main(args) != 0
    assert "no_such_option" in capsys.readouterr().err
