"""Findings of a trial of the evaluation command: a study refused after its ``--out`` was
made and locked (an unknown threat, ``--far off`` or ``--devices 2`` with ``--threats``)
left that folder behind holding only ``.difffilter.lock`` (the default ``reports/`` in the
working folder); the four-tank high-noise figures' ``time_per_step_s`` was 0.0 (tested in
``test_four_tank_eval.py``)."""

from __future__ import annotations

import pytest

from difffilter.eval.cli import main


@pytest.mark.parametrize(
    "options, why",
    [
        (["--threats", "nosuch"], "nosuch"),
        (["--threats", "bias", "--far", "off"], "--far off"),
        (["--threats", "bias", "--devices", "2"], "--devices"),
    ],
)
def test_a_refused_study_leaves_no_out_folder_it_made(tmp_path, capsys, options, why):
    out = tmp_path / "made" / "reports"
    assert (
        main(["four_tank_bias", "--runs", "2", "--out", str(out), "--no-progress", *options]) == 2
    )
    assert why in capsys.readouterr().err
    assert not out.exists()


def test_a_refused_study_keeps_a_folder_that_was_there(tmp_path):
    out = tmp_path / "reports"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["four_tank_bias", "--out", str(out), "--no-progress", "--threats", "nosuch"]) == 2
    assert (out / "notes.txt").read_text() == "mine"
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["four_tank_bias", "--out", str(empty), "--no-progress", "--threats", "x"]) == 2
    assert empty.is_dir()  # (not made by the study: kept, empty or not)
