"""Findings of a red-team trial of the LFC family's report sections (each failed before
its fix)."""

from __future__ import annotations

import json
import math

import pytest
import torch

import difffilter.eval.families.lfc as family
from difffilter.models import registry
from difffilter.models.lfc import PAPER_ATTACK_CHANNELS, STATE_NAMES, LFCScenario, scenario_attack

NAMES = ["kf_nn_ekf", "traditional_ad", "kf_nn_gd", "luenberger_nn_ekf"]


def test_a_diverged_channel_is_missing_not_nan_and_never_the_lowest(tmp_path, monkeypatch):
    """A diverged loop's per-channel RMSE (NaN) had been written as a bare NaN token,
    bolded as the channel's lowest, and counted as a loss in the paper's ordering."""
    assert family._finite_or_none(math.nan) is None and family._finite_or_none(0.2) == 0.2
    table = {n: {s: 0.1 * (i + 1) for s in STATE_NAMES} for i, n in enumerate(NAMES)}
    table["kf_nn_ekf"]["dPtu_1"] = None  # what per_channel_attack_rmse gives a diverged loop
    table["zero_estimate"] = dict.fromkeys(STATE_NAMES, 1.0)
    monkeypatch.setattr(family, "per_channel_attack_rmse", lambda *a, **k: table)
    family.per_channel_validation(None, seed=0, out=tmp_path, runs_per_channel=1, steps=10)
    text = (tmp_path / "lfc_per_channel" / "metrics.json").read_text()
    doc = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in metrics.json"))
    assert doc["estimators"]["kf_nn_ekf"]["attack_rmse"] is None
    report = (tmp_path / "lfc_per_channel" / "report.md").read_text()
    assert "dPtu_1: traditional_ad" in report.split("Lowest RMSE per channel: ")[1]
    est = {"kf_nn_ekf": {"attack_rmse_eq43": 0.3, "state5_rmse": 0.2},
           "traditional_ad": {"attack_rmse_eq43": 0.4, "state5_rmse": 0.2},
           "uncompensated": {"state5_rmse": 0.2}}  # fmt: skip
    said = family._explain(registry.get("lfc_step"), table, est)
    assert "on 9 of 9 with both numbers" in said and "not judged" in said


def test_the_attacked_channels_are_checked_against_the_papers_signals():
    """``attacked_channels`` was not checked: scenario III left at its default (2,) scored
    eq. 43 on one of its two channels (0.57 where the zero estimate's is 1.02), (2, 2) twice,
    and -1 as ace_int_2."""
    t = torch.arange(1, 1001, dtype=torch.float64) * 0.01
    for kind, channels in PAPER_ATTACK_CHANNELS.items():  # the table is the signals' own
        hit = scenario_attack(kind, t).abs().sum(0).nonzero().flatten().tolist()
        assert tuple(hit) == channels
    common = dict(name="x", family="lfc", description="", duration=10.0)
    with pytest.raises(ValueError, match=r"simultaneous attack are \(2, 7\)"):
        LFCScenario(attack="simultaneous", **common)
    for bad in ((2, 2), (-1,), (10,), (), (True,)):
        with pytest.raises(ValueError, match="attacked_channels must be distinct"):
            LFCScenario(attack="random", attacked_channels=bad, **common)
    LFCScenario(attack="simultaneous", attacked_channels=(7, 2), **common)
    LFCScenario(attack="random", attacked_channels=(0, 5), **common)


@pytest.mark.parametrize("missing", ["kf_nn_gd", "luenberger_nn_ekf", "traditional_ad"])
def test_the_two_changes_of_the_paper_are_counted_on_the_channels_with_both_numbers(missing):
    """A diverged channel (``None``) of ``kf_nn_gd``, ``luenberger_nn_ekf`` or
    ``traditional_ad`` stopped the whole LFC report in the last sentence ("'<' not supported
    between instances of 'NoneType' and 'float'")."""
    table = {n: dict.fromkeys(STATE_NAMES, 0.2) for n in family.PER_CHANNEL}
    for s in STATE_NAMES[:3]:  # both changes help on three channels
        table["kf_nn_gd"][s] = table["luenberger_nn_ekf"][s] = 0.1
    est = {"kf_nn_ekf": {"attack_rmse_eq43": 0.1, "state5_rmse": 0.1},
           "traditional_ad": {"attack_rmse_eq43": 0.2}, "uncompensated": {"state5_rmse": 0.1}}  # fmt: skip
    full = family._explain(registry.get("lfc_step"), table, est)
    assert "kf_nn_gd) helps on 3/10 channels" in full and "luenberger_nn_ekf) on 3/10." in full
    table[missing][STATE_NAMES[0]] = None
    said = family._explain(registry.get("lfc_step"), table, est)
    helped = "3/10" if missing == "luenberger_nn_ekf" else "2/9 with both numbers"
    assert f"kf_nn_gd) helps on {helped} channels" in said
