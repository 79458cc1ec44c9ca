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


@pytest.mark.parametrize(
    ("dtype", "values", "truth"),
    [
        (torch.uint8, [20, 0], math.sqrt(200)),  # 0 − 20 wrapped to 236 in uint8
        (torch.int8, [20, 0], math.sqrt(200)),  # 20² overflowed int8
        (torch.int16, [200], 200.0),
        (torch.int32, [50000], 50000.0),  # 50000² overflowed int32: NaN
    ],
)
def test_rmse_of_small_integer_types_takes_the_difference_in_floating_point(dtype, values, truth):
    """A second trial: the cast came after the difference and the square, in the input's own
    integer type (by hand: √mean(e²) in Python floats)."""
    e = torch.tensor(values, dtype=dtype)
    assert rmse(e, torch.zeros_like(e)).item() == pytest.approx(truth, rel=1e-15)
    assert rmse(torch.zeros_like(e), e).item() == pytest.approx(truth, rel=1e-15)


def test_rates_by_size_reads_0_1_integer_flags_as_a_mask_and_refuses_other_values():
    """Integer flags had indexed whole runs: 0.125 where 1 alarmed of 4 attacked steps is
    0.25, and with one run an IndexError that named nothing."""
    from difffilter.eval.scoring import rates_by_size

    flags = torch.tensor([[1, 1, 0, 0], [0, 0, 1, 1]])
    alarms = torch.tensor([[True, False, False, False], [False] * 4])
    sizes = torch.ones(2, 4)
    (row,) = rates_by_size(alarms, flags, sizes, [0, 2])
    assert (row["steps"], row["rate"]) == (4, 0.25)
    (row,) = rates_by_size(alarms[:1], flags[:1], sizes[:1], [0, 2])
    assert (row["steps"], row["rate"]) == (2, 0.5)
    with pytest.raises(ValueError, match="flags must be bool"):
        rates_by_size(alarms, flags * 2, sizes, [0, 2])
    with pytest.raises(ValueError, match="alarms must be bool"):
        rates_by_size(alarms.double() * 0.5, flags, sizes, [0, 2])


def test_a_rate_just_below_one_gives_the_lowest_score_not_minus_infinity():
    """A trial of the JSON writers: ⌊α n⌋'s round-off guard made it n for α within 1e-12 of
    1, and the threshold −inf, which ``calibrate`` wrote into a card as ``-Infinity``."""
    from difffilter.metrics import threshold_for

    scores = torch.arange(10.0)
    assert threshold_for(scores, 0.9999999999999) == 0.0  # nine of ten alarm above it
    assert threshold_for(scores, 0.29) == 7.0 and threshold_for(scores, 0.3) == 6.0
