"""difffilter-train's user errors: one line naming what is wrong, exit 2, no usage dump and
no traceback; its --help names export."""

from __future__ import annotations

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
        (["fitt"], "invalid choice"),
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


def test_help_names_export(capsys, monkeypatch):
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    with pytest.raises(SystemExit) as exit_:
        main(["--help"])
    assert exit_.value.code == 0
    assert "difffilter-train export SRC --out FILE" in " ".join(capsys.readouterr().out.split())
