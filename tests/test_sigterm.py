"""SIGTERM (a batch scheduler's stop) ends the commands as Ctrl-C does, with one line and
exit code 143: ``difffilter-train fit`` had exited 0 (Lightning's SIGTERMException is a
SystemExit without a code), as if the training had finished, and said nothing of its
``last.ckpt``; ``difffilter-eval`` had ended silently (tests/test_eval_write_safety.py)."""

from __future__ import annotations

import os
import signal

import pytest
from conftest import small_four_tank_fit

from difffilter.interrupts import Terminated, sigterm_as_interrupt, stop_words
from difffilter.train.cli import main


def test_sigterm_as_interrupt_raises_terminated_and_restores_the_handler():
    def mine(signum, frame):
        raise AssertionError("the caller's handler ran inside the block")

    previous = signal.signal(signal.SIGTERM, mine)
    try:
        with pytest.raises(Terminated), sigterm_as_interrupt():
            os.kill(os.getpid(), signal.SIGTERM)
        assert signal.getsignal(signal.SIGTERM) is mine
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert stop_words(Terminated()) == ("terminated (SIGTERM)", 143)
    assert stop_words(KeyboardInterrupt()) == ("interrupted", 130)


def test_a_terminated_fit_exits_143_keeps_last_ckpt_and_resumes(tmp_path, monkeypatch, capsys):
    from difffilter.train.task import FilterEstimatorTask

    def terminate(self, outputs, batch, batch_idx):
        if self.current_epoch == 1 and batch_idx == 1:
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    small = [*small_four_tank_fit(max_epochs=3), "--no-progress"]
    monkeypatch.setattr(FilterEstimatorTask, "on_train_batch_end", terminate, raising=False)
    sigint, sigterm = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        got = main(["fit", *small])
    finally:
        signal.signal(signal.SIGINT, sigint)
    assert got == 143
    assert signal.getsignal(signal.SIGTERM) == sigterm
    captured = capsys.readouterr()
    last = (
        tmp_path
        / "lightning_logs"
        / "four_tank_nn_grad"
        / "version_0"
        / "checkpoints"
        / "last.ckpt"
    )
    assert f"--ckpt_path {last}" in captured.out
    assert captured.err.splitlines()[-1].startswith("difffilter-train: terminated (SIGTERM): ")
    monkeypatch.delattr(FilterEstimatorTask, "on_train_batch_end")
    assert main(["fit", *small, f"--ckpt_path={last}"]) == 0
