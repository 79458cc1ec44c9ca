"""Findings of a red-team trial of the multi-process runs (each failed before its fix)."""

from __future__ import annotations

from pathlib import Path

import pytest

CONFIG = Path(__file__).resolve().parents[1] / "train" / "configs" / "tracking.yaml"


@pytest.mark.parametrize("extra", [["--trainer.devices=2"], ["--trainer.devices", "[0, 1]"],
                                   ["--trainer.strategy=ddp", "--trainer.devices=2"]])  # fmt: skip
def test_a_sweep_refuses_fits_on_several_processes(extra):
    """Lightning's DDP starts its other processes by running the command line again: from a
    sweep's seed they ran a bare difffilter-train, and Lightning killed the sweep (exit 137,
    no error line)."""
    from difffilter.train.sweep import _check_one_process

    with pytest.raises(ValueError, match=r"a sweep trains its seeds one after another"):
        _check_one_process(CONFIG, extra)
    _check_one_process(CONFIG, ["--trainer.devices=1"])
    _check_one_process(CONFIG, [])


def test_a_failed_evaluation_on_several_processes_leaves_no_empty_out(tmp_path, monkeypatch):
    """--devices 1 removed the --out it made when the study was refused; --devices 2 left it
    holding its lock file alone."""
    from difffilter.eval import cli

    monkeypatch.setattr(cli, "_launch", lambda devices, argv: 2)  # a worker's refusal
    out = tmp_path / "out"
    code = cli.main(["four_tank_bias", "--runs", "2", "--devices", "2", "--out", str(out)])
    assert code == 2 and not out.exists()
    out.mkdir()  # a folder the user made: kept
    assert cli.main(["four_tank_bias", "--runs", "2", "--devices", "2", "--out", str(out)]) == 2
    assert out.is_dir()
