"""Findings of a red-team trial of the crafted attacks (each failed before its fix)."""

from __future__ import annotations

import pytest
import torch

from difffilter.models import registry


def test_the_same_rate_bias_finds_the_weakest_where_the_rate_is_not_monotone(monkeypatch):
    """A particle filter's alarm rate goes up and down with k (resampling): the bisection
    over [hi/2, hi] had returned k = 1.0 where 0.30 already alarmed as often."""
    from difffilter.eval import stealthy

    def rate(k: float) -> float:  # reaches 0.01 at k = 0.3, dips below it from 0.5 to 0.9
        if k < 0.3:
            return 0.002 + 0.02 * k
        return 0.006 if 0.5 <= k < 0.9 else 0.011

    def judge(*args, **kwargs):
        return lambda attack: {"alarm_rate": rate(attack.k), "state_error": attack.k}

    monkeypatch.setattr(stealthy, "_judge", judge)
    sc = registry.get("four_tank_bias")
    got = stealthy.same_rate_bias(sc, "normal_pf", 0.01, 0.5, onset=5, runs=2, seed=0)
    assert got["matched"] and got["k_sigma"] == pytest.approx(0.3, abs=1e-3)
    # a monotone rate: the same k as the bisection's, to its resolution (2⁻¹³ of hi)
    monkeypatch.setattr(stealthy, "_judge", lambda *a, **k: lambda attack: {
        "alarm_rate": 0.02 + 0.01 * attack.k, "state_error": attack.k})  # fmt: skip
    got = stealthy.same_rate_bias(sc, "normal_pf", 0.035, 0.5, onset=5, runs=2, seed=0)
    assert got["k_sigma"] == pytest.approx(1.5, abs=2 / 8192)


def test_the_adversarys_runs_are_flagged_where_an_attacked_entry_arrived():
    """Every step from the onset had been flagged, steps that received nothing too (48 of
    142 under every third packet lost), where the closed loop flags only those received."""
    from difffilter.train.adversarial import Adversary
    from difffilter.train.task import training_batch

    base = registry.get("four_tank_bias")
    lossy = torch.ones(100, 4, dtype=torch.bool)
    lossy[::3] = False

    class Lossy:
        closed_loop = False

        def __init__(self, sc=base):
            self.sc = sc

        def with_threat(self, threat):
            return Lossy(self.sc.with_threat(threat))

        def simulate(self, runs, gens, **kw):
            return self.sc.simulate(runs, gens, **kw)._replace(
                mask=lossy.expand(runs, 100, 4).clone()
            )

    adversary = Adversary(runs=2)
    adversary.onset = 30
    adversary.attack = torch.zeros(100, 4)
    adversary.attack[29:] = 0.1
    out = adversary.augment(training_batch(Lossy(), 2, 7, torch.float32), Lossy(), 5, torch.float32)
    flags, mask = out["flags"][2:], out["mask"][2:]
    want = (torch.arange(1, 101) >= 30) & mask.any(-1)
    assert torch.equal(flags, want) and int(flags.sum()) == 2 * 47
