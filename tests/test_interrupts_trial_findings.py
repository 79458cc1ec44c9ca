"""Findings of a red-team trial of interrupts and atomic writes: an in-place recalibration
stopped between its two writes, error lines after a failed write, long file names, and the
provenance record under an exported GIT_DIR. Each test failed on the code before its fix."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
from pathlib import Path

import pytest

from difffilter.interrupts import Terminated
from difffilter.models.atomic_write import write_atomically

ROOT = Path(__file__).resolve().parents[1]


def test_a_legal_long_name_is_written_whole(tmp_path):
    # the partial file's name, 30 bytes longer than the target's, passed NAME_MAX (255):
    # a 240-byte name failed, and the clean-up's own error named the partial file
    target = tmp_path / ("r" * 235 + ".json")
    write_atomically(target, "{}\n")
    assert target.read_text() == "{}\n"
    assert [p.name for p in tmp_path.iterdir()] == [target.name]


def test_a_failed_write_is_named_after_the_target_without_an_arrow(tmp_path):
    # "-> None" had ended every such line (filename2 = None is printed by OSError)
    target = tmp_path / "no_such_folder" / "card.json"
    with pytest.raises(FileNotFoundError) as caught:
        write_atomically(target, "{}")
    assert str(caught.value) == f"[Errno 2] No such file or directory: '{target}'"


def test_an_error_about_another_file_the_writer_read_keeps_its_name(tmp_path):
    missing = tmp_path / "missing_source.ckpt"
    with pytest.raises(FileNotFoundError, match="missing_source.ckpt"):
        write_atomically(tmp_path / "card.json", lambda partial: shutil.copyfile(missing, partial))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "sig,error", [(signal.SIGINT, KeyboardInterrupt), (signal.SIGTERM, Terminated)]
)
def test_a_signal_inside_the_deferred_block_is_raised_after_it(sig, error):
    from difffilter.interrupts import signals_deferred, sigterm_as_interrupt

    done = []
    with sigterm_as_interrupt():  # (as the command lines run: SIGTERM raises Terminated)
        previous = signal.getsignal(signal.SIGTERM)
        with pytest.raises(error):
            with signals_deferred():
                os.kill(os.getpid(), sig)
                done.append("first")
                done.append("second")  # (the signal had stopped the block between the two)
        assert signal.getsignal(signal.SIGTERM) is previous
    assert done == ["first", "second"]


def test_a_held_signal_meets_the_handler_it_would_have_met():
    # a SIGINT the process ignores had raised KeyboardInterrupt after the block, and a
    # caller's own SIGTERM handler was skipped for Terminated (a review)
    from difffilter.interrupts import signals_deferred

    calls = []
    old_int = signal.signal(signal.SIGINT, signal.SIG_IGN)
    old_term = signal.signal(signal.SIGTERM, lambda *a: calls.append("term"))
    try:
        with signals_deferred():
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGTERM)
            assert calls == []  # (held)
        assert calls == ["term"]
    finally:
        signal.signal(signal.SIGINT, old_int)
        signal.signal(signal.SIGTERM, old_term)


def _pair(folder: Path) -> Path:
    for ext in (".ckpt", ".json"):
        shutil.copy(ROOT / "checkpoints" / f"four_tank_nn_grad{ext}", folder / f"ft{ext}")
    return folder / "ft.ckpt"


def test_an_in_place_rewrite_stopped_by_a_signal_leaves_a_matching_pair(tmp_path, monkeypatch):
    # calibrate --out SRC --force stopped between the checkpoint and its card had left the
    # new checkpoint beside the old card: the rerun it advised was refused (sha256)
    import difffilter.train.calibrate as calibrate
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    src = _pair(tmp_path)
    estimator, card = load_estimator_checkpoint(src, dtype=None)
    document = json.loads(src.with_suffix(".json").read_text())
    real_replace, calls = os.replace, []

    def replace_after_a_signal(a, b):  # Ctrl-C arrives as the checkpoint is moved in place
        if Path(b) in (src, src.with_suffix(".json")):
            calls.append(b)
            if len(calls) == 1:
                os.kill(os.getpid(), signal.SIGINT)
        real_replace(a, b)

    monkeypatch.setattr(calibrate.os, "replace", replace_after_a_signal)
    new_card = card.__class__(**{**card.to_dict(), "threshold": 0.123})
    with pytest.raises(KeyboardInterrupt):
        calibrate._write_pair(src, estimator, new_card, document, {"threshold": 0.123}, None)
    monkeypatch.undo()
    load_estimator_checkpoint(src)  # (verifies the file against the card beside it)
    assert json.loads(src.with_suffix(".json").read_text())["calibration"] == {"threshold": 0.123}
    assert len(calls) == 2  # (both renames made before the interrupt was raised)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ft.ckpt", "ft.json"]


def test_an_in_place_rewrite_stopped_before_its_renames_keeps_the_old_pair(tmp_path, monkeypatch):
    import difffilter.train.calibrate as calibrate
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    src = _pair(tmp_path)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    estimator, card = load_estimator_checkpoint(src, dtype=None)
    document = json.loads(src.with_suffix(".json").read_text())

    def interrupted(path, doc):
        raise KeyboardInterrupt

    monkeypatch.setattr(calibrate, "write_json_atomically", interrupted)
    with pytest.raises(KeyboardInterrupt):
        calibrate._write_pair(src, estimator, card, document, {}, None)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_the_software_record_ignores_an_exported_git_dir(tmp_path):
    # GIT_DIR of another repository had put that repository's commit in every metrics.json
    other = tmp_path / "other"
    other.mkdir()
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(other)]
    subprocess.run([*git, "init", "-q"], check=True)
    (other / "f").write_text("x")
    subprocess.run([*git, "add", "f"], check=True)
    subprocess.run([*git, "commit", "-q", "-m", "x"], check=True)
    from difffilter.eval import provenance

    truth = provenance._git(Path(provenance.__file__).resolve().parent, "rev-parse", "HEAD")
    os.environ["GIT_DIR"] = str(other / ".git")
    try:
        seen = provenance._git(Path(provenance.__file__).resolve().parent, "rev-parse", "HEAD")
    finally:
        del os.environ["GIT_DIR"]
    other_head = subprocess.run(
        [*git, "rev-parse", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    assert seen == truth and seen != other_head


def test_a_legal_name_of_multibyte_characters_is_written_whole(tmp_path):
    # the partial name had been cut by characters: 62 emoji (253 bytes) made one past 255
    target = tmp_path / ("\N{GRINNING FACE}" * 62 + ".json")
    write_atomically(target, "{}\n")
    assert target.read_text() == "{}\n"
    assert [p.name for p in tmp_path.iterdir()] == [target.name]
