"""Findings of a red-team trial of serialisation: a covert attack's loop resumed from a
saved state, and a plant's fingerprint across instances. Each test failed on the code
before its fix."""

from __future__ import annotations

import copy
import io

import pytest
import torch

import difffilter as df
import difffilter.threats as th
from difffilter.loop import ReplayedNoise, StateFeedback, closed_loop

F64 = torch.float64


def _plant(a: float = 0.98) -> df.LinearGaussianModel:
    eye = torch.eye(2, dtype=F64)
    return df.LinearGaussianModel(
        torch.tensor([[1.0, 0.1], [0.0, a]], dtype=F64), torch.tensor([[1.0, 0.0]], dtype=F64),
        0.01 * eye, 0.25 * torch.eye(1, dtype=F64), torch.zeros(2, dtype=F64), eye,
        B=torch.tensor([[0.0], [0.1]], dtype=F64),
    )  # fmt: skip


def _loop_kwargs(B: int, T: int) -> dict:
    g = [torch.Generator().manual_seed(s) for s in (1, 2)]
    noise = ReplayedNoise(0.1 * torch.randn(B, T, 2, dtype=F64, generator=g[0]),
                          0.5 * torch.randn(B, T, 1, dtype=F64, generator=g[1]))  # fmt: skip
    return dict(noise=noise, controller=StateFeedback(torch.tensor([[0.5, 0.8]], dtype=F64)),
                estimator=df.KalmanFilter())  # fmt: skip


def _saved(state):
    buffer = io.BytesIO()
    torch.save(state, buffer)
    buffer.seek(0)
    return torch.load(buffer, weights_only=False)


@pytest.mark.parametrize("how", ["torch.save", "deepcopy", "rebuilt"])
def test_a_covert_loop_resumes_from_a_saved_state_or_an_equal_attack(how):
    # the attack's plant (a module) had been compared by identity: the loop's own state
    # restored by torch.load or deepcopy, or Covert built again on an equal plant, was refused
    B, T, K = 2, 12, 5
    plant = _plant()
    x0 = torch.randn(B, 2, dtype=F64, generator=torch.Generator().manual_seed(3))
    signal = th.Bias(0.5, onset=2, channel="actuator")
    attack = th.Covert(signal, plant)
    kw = _loop_kwargs(B, T)
    full = closed_loop(plant, T, x0=x0, attack=attack, **kw)
    first = closed_loop(plant, K, x0=x0, attack=attack, horizon=T, **kw)
    state = {"torch.save": _saved, "deepcopy": copy.deepcopy, "rebuilt": lambda s: s}[how](
        first.state
    )
    given = th.Covert(signal, _plant()) if how == "rebuilt" else attack
    rest = closed_loop(plant, T - K, state=state, attack=given, horizon=T, **kw)
    assert torch.equal(rest.output.means, full.output.means[:, K:])


def test_a_covert_attack_on_another_plant_is_still_refused():
    B, T, K = 2, 12, 5
    plant = _plant()
    x0 = torch.zeros(B, 2, dtype=F64)
    signal = th.Bias(0.5, onset=2, channel="actuator")
    kw = _loop_kwargs(B, T)
    first = closed_loop(plant, K, x0=x0, attack=th.Covert(signal, plant), horizon=T, **kw)
    with pytest.raises(ValueError, match="Covert"):
        closed_loop(plant, T - K, state=first.state, attack=th.Covert(signal, _plant(0.5)),
                    horizon=T, **kw)  # fmt: skip


def test_two_tracking_plants_built_alike_have_one_fingerprint():
    # the fast sampler's memo held the covariance's memory address: every tracking plant
    # had its own fingerprint (calibrations never reused, a trained checkpoint's plant
    # always read as changed)
    from difffilter.models.calibration_cache import model_fingerprint
    from difffilter.models.tracking import TrackingModel

    a, b = TrackingModel(), TrackingModel()
    a.simulate(3, (2,), generator=torch.Generator().manual_seed(0))  # (its memo renewed)
    assert model_fingerprint(a) == model_fingerprint(b)
    with torch.no_grad():
        b.process_noise.cov.mul_(2.0)
    assert model_fingerprint(a) != model_fingerprint(b)
