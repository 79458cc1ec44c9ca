"""Findings of a red-team trial of the metrics (each failed before its fix)."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.metrics import alarm_rate_since_attack, rmse, roc_curve


def test_rmse_of_integer_tensors_is_taken_in_floating_point():
    """torch's mean refused a Long input with an error naming neither argument."""
    got = rmse(torch.tensor([1, 2, 3]), torch.tensor([1, 2, 5]))
    assert got.dtype == torch.float64 and got.item() == pytest.approx(math.sqrt(4 / 3))
    assert rmse(torch.tensor([3, 4]), 0).item() == pytest.approx(math.sqrt(12.5))


def test_alarm_rate_since_attack_refuses_fractional_edges():
    """Edges of 1.5 and 2.7 had been read as 1 and 2 without a word (other bins, other
    rates)."""
    flags = torch.tensor([[True, False, False, False]])
    alarms = torch.tensor([[False, True, False, False]])
    with pytest.raises(ValueError, match=r"edges must be increasing integers.*1\.5"):
        alarm_rate_since_attack(alarms, flags, (1.5, 2.7))
    rates, counts = alarm_rate_since_attack(alarms, flags, (1.0, 2))  # whole floats: fine
    assert counts.tolist() == [1, 2] and rates.tolist() == [1.0, 0.0]


def test_the_roc_curves_first_threshold_is_never_alarm_even_over_infinite_scores():
    """The first point is (0, 0) under +∞ (never alarm); an infinite score is reached at
    point 1 (documented: the trial read thresholds[0] as "score ≥ +∞")."""
    scores = torch.tensor([math.inf, math.inf, 1.0, 2.0, 3.0])
    labels = torch.tensor([True, False, True, False, False])
    fpr, tpr, thr = roc_curve(scores, labels)
    assert (fpr[0], tpr[0]) == (0, 0) and thr[0] == thr[1] == math.inf
    assert fpr[1] == pytest.approx(1 / 3) and tpr[1] == 0.5


def test_the_leaderboard_writes_into_a_folder_it_makes(tmp_path):
    """write_leaderboard failed on a missing folder (the other writers make theirs)."""
    from difffilter.eval.leaderboard import write_leaderboard

    results = {"a": {"estimators": {"kf": {"state_rmse": 0.1}}, "far": None}}
    path = write_leaderboard(tmp_path / "new" / "deeper", results)
    assert path.exists() and (tmp_path / "new" / "deeper" / "leaderboard.json").exists()
