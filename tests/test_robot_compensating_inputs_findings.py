"""A robot-loop trial's findings on Remark 1's controller (``CompensatingInputs``): past the
end of its table it had repeated the last row, so a loop of more steps than rows ran on a
copy of ``u_{T−1}``, and a loop resumed from a state at the table's end drove its first step
with ``u_{T−1}`` (5 where the table held 6), where ``KnownInputs`` refuses both; and without
an estimator, or with one that estimates no attack, it failed on ``None`` in torch."""

from __future__ import annotations

import pytest
import torch

from difffilter.estimator import Generators
from difffilter.fdi.mdpf import AdaptiveParticleFilter
from difffilter.loop import DrawnNoise, closed_loop
from difffilter.models.robot import DEG, RobotModel
from difffilter.models.robot_estimators import CompensatingInputs, FusedLocals

F64 = torch.float64
B, T = 2, 6


def _setup():
    model = RobotModel()
    us = torch.zeros(B, T + 2, 2, dtype=F64)
    us[..., 0] = torch.arange(T + 2, dtype=F64)  # a speed that varies: u_k = k
    us[..., 1] = 5 * DEG
    x0 = model.initial.mean.expand(B, 3).clone()
    return model, us, x0


def _loop(model, us, x0, steps, compensate=False, **kw):
    est = FusedLocals(AdaptiveParticleFilter(10, forgetting=0.7, attack_cov0=10.0))
    gens = Generators(*(torch.Generator().manual_seed(s) for s in (1, 2, 3)))
    return closed_loop(model, steps, noise=DrawnNoise(torch.Generator().manual_seed(0)),
                       x0=x0, estimator=est, generator=gens,
                       controller=CompensatingInputs(us, compensate=compensate), **kw)  # fmt: skip


def test_a_loop_longer_than_the_table_is_refused():
    model, us, x0 = _setup()
    with pytest.raises(ValueError, match="the input u_6 that drives step 7 contains NaN"):
        _loop(model, us[:, :T], x0, T + 2)
    # within the table: the commanded inputs, row by row
    sent = _loop(model, us, x0, T).trajectories.us
    torch.testing.assert_close(sent, us[:, :T], rtol=0, atol=0)


def test_a_loop_resumed_at_the_end_of_its_table_is_refused_and_within_it_goes_on():
    model, us, x0 = _setup()
    first = _loop(model, us[:, :T], x0, T)
    with pytest.raises(ValueError, match=r"its last input u_6 is not finite"):
        _loop(model, us, None, 2, state=first.state)
    # a first chunk given the whole table leaves u_T, and the resumed step is driven by it
    first = _loop(model, us, x0, T)
    again = _loop(model, us, None, 2, state=first.state)
    torch.testing.assert_close(again.trajectories.us, us[:, T:], rtol=0, atol=0)


def test_compensation_without_an_attack_estimate_is_named():
    model, us, x0 = _setup()
    ctl = CompensatingInputs(us)
    with pytest.raises(ValueError, match="this loop has no estimator"):
        ctl(1, None, None)

    class NoAttack:
        attack = None

    with pytest.raises(ValueError, match=r"carries none \(out.attack is None\)"):
        ctl(1, None, NoAttack())
    assert torch.equal(CompensatingInputs(us, compensate=False)(1, None, None), us[:, 1])
