"""Closed-loop evaluation in bounded memory and linear time (issue 12, part 5).

The evaluation once appended every step's small record tensors to lists and stacked them
at the end; interleaved with each step's large temporaries they fragmented the heap, so
memory grew with every step and the step rate fell over a long run. These tests count
live tensors instead of timing anything: they fail whenever something (a record list, an
autograd graph, a growing history) accumulates per step.
"""

from __future__ import annotations

import gc

import pytest
import torch

from difffilter.models.attack_observer import AttackObserver, ClosedLoop
from difffilter.models.lfc import STATE_DIM, random_attacks
from difffilter.models.lfc_estimators import ESTIMATORS, EstimatorSpec, LFCContext, run_estimator
from difffilter.models.neural_estimator import NeuralFDIEstimator


def _live_tensors() -> int:
    gc.collect()
    return sum(1 for o in gc.get_objects() if isinstance(o, torch.Tensor))


def _data(runs: int, steps: int):
    ctx = LFCContext(dt=0.01)
    g = torch.Generator().manual_seed(3)
    attack = random_attacks(runs, steps, 0.01, generator=g, channels=(2,), min_events=1)
    xi, theta = ctx.plant.sample_noise(runs, steps, g)
    load = torch.tensor([[0.01, 0.0]], dtype=ctx.dtype)
    return ctx, attack, xi, theta, load


def _checkpoint():
    net = NeuralFDIEstimator(init="symmetric", init_scale=0.05, seed=1)
    return net, {"residual_lag": 0}


@pytest.mark.parametrize("name", ["uncompensated", "kf_nn_ekf", "traditional_ad", "kf_nn_grad"])
def test_evaluation_keeps_no_per_step_tensors(name, monkeypatch):
    """The number of live tensors is the same after 10 and after 60 steps of a run."""
    # The Kalman gain schedule is cached per step until it converges (bounded by the horizon,
    # data-independent, 3 small tensors a step): compute it up front so that only what the
    # loop itself keeps is counted.
    init = AttackObserver.__init__

    def warmed(self, *args, **kwargs):
        init(self, *args, **kwargs)
        if self.kind == "kalman":
            self.kalman_schedule(61)

    monkeypatch.setattr(AttackObserver, "__init__", warmed)
    ctx, attack, xi, theta, load = _data(runs=3, steps=60)
    counts = {}
    step = [0]

    def probe(n):
        step[0] += n
        if step[0] in (10, 60):
            counts[step[0]] = _live_tensors()

    rec, _ = run_estimator(
        ESTIMATORS[name],
        ctx,
        attack,
        xi,
        theta,
        load,
        init_seed=0,
        checkpoint=_checkpoint(),
        progress=probe,
    )
    # A list of per-step tensors adds 6-8 tensors per step (300+ over these 50 steps).
    assert counts[60] - counts[10] <= 2, counts
    for field in ("x", "z", "u", "attack_est", "mean", "innovation", "innovation_cov", "logit"):
        value = getattr(rec, field)
        if value is not None:
            assert not value.requires_grad and value.grad_fn is None, field
    assert rec.x.shape == (3, 60, STATE_DIM)


def test_buffered_record_equals_the_autograd_path():
    """Evaluation (buffers filled in place) and training (stacked graph nodes) agree exactly,
    and gradients still reach the network when autograd is on."""
    ctx, attack, xi, theta, load = _data(runs=2, steps=25)
    spec = EstimatorSpec("frozen", network="checkpoint")
    net, obs = _checkpoint()
    rec_eval, _ = run_estimator(
        spec, ctx, attack, xi, theta, load, init_seed=0, checkpoint=(net, obs)
    )
    plant = ctx.plant
    observer = AttackObserver(plant.Ad, plant.Bd, plant.Q, plant.R, network=net, residual_lag=0)
    loop = ClosedLoop(plant, ctx.K1, observer)
    _, rec_grad = loop.run(loop.init(2), attack, xi, theta, load)
    assert rec_grad.attack_est.grad_fn is not None
    for field in ("x", "z", "u", "attack_est", "mean", "innovation", "innovation_cov", "logit"):
        assert torch.equal(getattr(rec_eval, field), getattr(rec_grad, field).detach()), field
    rec_grad.attack_est.square().sum().backward()
    assert net.V.grad is not None and torch.isfinite(net.V.grad).all()
