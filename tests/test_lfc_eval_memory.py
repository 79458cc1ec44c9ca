"""Closed-loop evaluation in bounded memory and linear time.

A loop records its trajectories and step outputs (a bounded number of tensors per step);
nothing else may accumulate: no autograd graph in evaluation, no growing history in a
carry (the network's windows and the online learners' covariances are replaced, not
appended to). These tests count live tensors instead of timing anything.
"""

from __future__ import annotations

import gc

import pytest
import torch

from difffilter.estimator import Generators
from difffilter.models import registry
from difffilter.models.estimators import SuiteContext
from difffilter.models.lfc_estimators import _BUILDERS
from difffilter.models.neural_estimator import EstimatorCard, NeuralFDIEstimator
from difffilter.models.streams import Streams


def _live_tensors() -> int:
    gc.collect()
    return sum(1 for o in gc.get_objects() if isinstance(o, torch.Tensor))


def _setup(name: str, runs: int, steps: int, monkeypatch):
    sc = registry.get("lfc_random_attacks").with_steps(steps)
    streams = Streams(3)
    draws = sc.exogenous(runs, {k: streams(k) for k in ("plant", "attack")}, dtype=torch.float64)
    ctx = SuiteContext(sc, sc.system(), runs, streams)
    net = NeuralFDIEstimator(init="symmetric", init_scale=0.05, seed=1)
    card = EstimatorCard("lfc", filter="kf", residual="predicted", standardize=False)
    monkeypatch.setattr(
        "difffilter.models.lfc_estimators._checkpoint_network", lambda ctx, name: (net, card)
    )
    return sc, draws, _BUILDERS[name][1](ctx), net


# per step a loop keeps x, y, ỹ, u, the attack's value, flag and change, and the step's
# output (moments, prediction, innovation, likelihood, attack, score, alarm, extras)
PER_STEP = 25


def _numel(value) -> int:
    """Elements of every tensor reachable from a carry (NamedTuples, tuples, dicts)."""
    if isinstance(value, torch.Tensor):
        return value.numel()
    if isinstance(value, dict):
        return sum(_numel(v) for v in value.values())
    if isinstance(value, (tuple, list)) and not isinstance(value, torch.Size):
        return sum(_numel(v) for v in value)
    return 0


@pytest.mark.parametrize("name", ["uncompensated", "kf_nn_ekf", "traditional_ad", "kf_nn_grad"])
def test_evaluation_keeps_only_its_records(name, monkeypatch):
    sc, draws, est, _ = _setup(name, runs=3, steps=60, monkeypatch=monkeypatch)
    counts, step = {}, [0]

    def probe(n):
        step[0] += n
        if step[0] in (10, 60):
            counts[step[0]] = _live_tensors()

    gens = Generators(init=torch.Generator().manual_seed(0))
    with torch.no_grad():
        sc.loop(est, draws, generator=gens)  # warm up: the Kalman gains are cached per step
        loop = sc.loop(est, draws, generator=gens, progress=probe)
    assert counts[60] - counts[10] <= 50 * PER_STEP, counts
    # the estimator's carry is the same size after 10 steps as after 60 (the attacker's
    # state is its table for the horizon)
    with torch.no_grad():
        short = sc.with_steps(10).loop(est, {k: v[:, :10] if v.dim() == 3 else v
                                             for k, v in draws.items()}, generator=gens)  # fmt: skip
    assert _numel(short.state.carry) == _numel(loop.state.carry)
    for value in (loop.trajectories.x, loop.output.means, loop.output.attack):
        if value is not None:
            assert not value.requires_grad and value.grad_fn is None
    assert loop.trajectories.x.shape == (3, 60, 10)


def test_evaluation_equals_the_autograd_path(monkeypatch):
    """Without and with autograd the loop computes the same numbers, and gradients reach the
    network through the closed loop (the controller feeds the estimate back)."""
    sc, draws, est, net = _setup("kf_nn_grad", runs=2, steps=25, monkeypatch=monkeypatch)
    with torch.no_grad():
        plain = sc.loop(est, draws)
    graph = sc.loop(est, draws)
    assert graph.output.attack.grad_fn is not None
    torch.testing.assert_close(plain.output.attack, graph.output.attack.detach(), rtol=0, atol=0)
    torch.testing.assert_close(plain.trajectories.x, graph.trajectories.x.detach(), rtol=0, atol=0)
    graph.trajectories.x.square().sum().backward()  # through the plant: the loop is closed
    assert net.V.grad is not None and torch.isfinite(net.V.grad).all()
    assert float(net.V.grad.abs().sum()) > 0
