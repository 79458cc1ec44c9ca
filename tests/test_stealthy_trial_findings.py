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


def test_crafting_leaves_the_callers_gradients_alone():
    """``loss.backward()`` had filled the ``.grad`` of every leaf that requires one: the
    measurements given and the model's matrices took the attack's gradients, added to at
    every iteration (a trial). The attack itself is the same as crafted from plain tensors."""
    import difffilter as df
    from difffilter import fdi
    from difffilter.loop import DrawnNoise, closed_loop
    from difffilter.stealthy import StealthySettings, craft_stealthy_attack

    f64, steps = torch.float64, 30

    def plant(F):
        eye = torch.eye(2, dtype=f64)
        return df.LinearGaussianModel(F, eye, 1e-4 * eye, 1e-3 * eye,
                                      torch.zeros(2, dtype=f64), 1e-3 * eye)  # fmt: skip

    F = torch.diag(torch.tensor([0.95, 0.98], dtype=f64))
    loop = closed_loop(plant(F), steps, noise=DrawnNoise(torch.Generator().manual_seed(3)),
                       x0=torch.zeros(8, 2, dtype=f64))  # fmt: skip
    ys, xs = loop.trajectories.y_true, loop.trajectories.x
    settings = StealthySettings(iterations=4, lr=0.05)

    def craft(model, ys):
        estimator = fdi.GatedFilter(fdi.ChiSquareDetector(2, 0.01), df.KalmanFilter())
        return craft_stealthy_attack(estimator, model, ys, xs, 9.2, far=0.01, onset=10,
                                     settings=settings, warn_far_off=False)  # fmt: skip

    plain = craft(plant(F), ys)
    learnable_F, watched_ys = F.clone().requires_grad_(True), ys.clone().requires_grad_(True)
    watched = craft(plant(learnable_F), watched_ys)
    assert watched_ys.grad is None and learnable_F.grad is None
    assert torch.equal(watched.values, plain.values) and plain.values.abs().sum() > 0
