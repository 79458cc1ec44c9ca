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
        (["fit", *CONFIG, "--scenario"], "--scenario needs a scenario name"),
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
