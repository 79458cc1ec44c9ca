"""Neural FDI estimator, attack-compensating observers and the secure closed loop."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import difffilter
from difffilter.models.attack_observer import AttackObserver, ClosedLoop
from difffilter.models.control import lqr
from difffilter.models.lfc import LFCPlant, scenario_attack
from difffilter.models.neural_estimator import (
    NeuralFDIEstimator,
    build_delta,
    load_estimator_checkpoint,
    save_estimator_checkpoint,
)


@pytest.fixture(scope="module")
def plant():
    return LFCPlant()


def test_estimator_shapes_and_init():
    net = NeuralFDIEstimator(a=2, b=4, hidden=7, init_scale=0.05, seed=3)
    assert net.V.shape == (2, 7, 30) and net.W.shape == (2, 5, 7)
    assert 0 <= net.V.min() and net.V.max() <= 0.05  # s·U[0, 1]
    sym = NeuralFDIEstimator(init="symmetric", init_scale=0.2)
    assert sym.V.min() < 0 < sym.V.max() and sym.V.abs().max() <= 0.2
    delta = torch.randn(6, 4, 2, 30, dtype=torch.float64)
    attack, logit = net(delta)
    assert attack.shape == (6, 4, 2, 5) and logit.shape == (6, 4, 2)
    # Eq. (8) by hand for one area.
    i = 1
    by_hand = net.W[i] @ torch.tanh(net.V[i] @ delta[0, 0, i])
    assert torch.allclose(attack[0, 0, i], by_hand)
    # Same seed, same weights; different seed, different weights.
    assert torch.equal(NeuralFDIEstimator(seed=3).V, NeuralFDIEstimator(seed=3).V)
    assert not torch.equal(NeuralFDIEstimator(seed=3).V, NeuralFDIEstimator(seed=4).V)
    headless = NeuralFDIEstimator(detection_head=False)
    assert headless(torch.zeros(2, 30, dtype=torch.float64))[1] is None


def test_input_scaling_is_a_reparametrisation():
    a = NeuralFDIEstimator(resid_scale=0.01, seed=1)
    b = NeuralFDIEstimator(seed=1)
    with torch.no_grad():
        b.V.copy_(a.V / a.in_scale)
        b.W.copy_(a.W)
    delta = torch.randn(3, 2, 30, dtype=torch.float64)
    assert torch.allclose(a(delta)[0], b(delta)[0])
    # The per-area template used by the online learners agrees with the stacked network.
    tmpl = a.area_template()
    with torch.no_grad():
        tmpl.W.copy_(a.W[0])
        tmpl.V.copy_(a.V[0])
    assert torch.allclose(tmpl(delta[:, 0]), a(delta)[0][:, 0])


def test_estimator_bad_arguments():
    with pytest.raises(ValueError, match="hidden"):
        NeuralFDIEstimator(hidden=0)
    with pytest.raises(ValueError, match="init_scale"):
        NeuralFDIEstimator(init_scale=-1.0)
    with pytest.raises(ValueError, match="init"):
        NeuralFDIEstimator(init="normal")
    with pytest.raises(ValueError, match="delta"):
        NeuralFDIEstimator()(torch.zeros(3, 2, 29, dtype=torch.float64))


def test_build_delta_orders_channels_per_area():
    B, a, b = 1, 2, 3
    attack_hist = torch.arange(a * 10, dtype=torch.float64).reshape(B, a, 10)
    resid_hist = 100 + torch.arange(b * 10, dtype=torch.float64).reshape(B, b, 10)
    delta = build_delta(attack_hist, resid_hist, 2)
    assert delta.shape == (1, 2, 25)
    # Area 2 (index 1): M̂_{k-1} channels 5..9, then M̂_{k-2}, then the residuals.
    assert delta[0, 1, :5].tolist() == [5, 6, 7, 8, 9]
    assert delta[0, 1, 5:10].tolist() == [15, 16, 17, 18, 19]
    assert delta[0, 1, 10:15].tolist() == [105, 106, 107, 108, 109]
    assert delta[0, 0, 20:25].tolist() == [120, 121, 122, 123, 124]


def test_checkpoint_roundtrip_and_errors(tmp_path):
    net = NeuralFDIEstimator(hidden=6, resid_scale=0.1, seed=9, dtype=torch.float32)
    path = tmp_path / "est.ckpt"
    save_estimator_checkpoint(path, net, {"residual_lag": 0, "dt": 0.01})
    raw = torch.load(path, weights_only=True)  # never a pickled module
    assert set(raw) >= {"format", "estimator_config", "state_dict", "observer"}
    loaded, obs = load_estimator_checkpoint(path)
    assert obs == {"residual_lag": 0, "dt": 0.01} and loaded.V.dtype == torch.float64
    assert torch.allclose(loaded.V.float(), net.V) and loaded.resid_scale == 0.1
    with pytest.raises(FileNotFoundError):
        load_estimator_checkpoint(tmp_path / "missing.ckpt")
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="ckpt"):
        load_estimator_checkpoint(bad)
    raw["estimator_config"]["hidden"] = 7
    torch.save(raw, bad)
    with pytest.raises(ValueError, match="does not match"):
        load_estimator_checkpoint(bad)


def test_kalman_schedule_equals_the_batched_kalman_filter(plant):
    """The cached gain schedule reproduces difffilter.kalman_step run on every run."""
    obs = AttackObserver(plant.Ad, plant.Bd, plant.Q, plant.R)
    model = obs.observer_model()
    g = torch.Generator().manual_seed(0)
    B, T = 3, 40
    zs = 0.05 * torch.randn(B, T, 10, generator=g, dtype=torch.float64)
    us = 0.05 * torch.randn(B, T, 2, generator=g, dtype=torch.float64)
    state = obs.init(B)
    ref = difffilter.GaussianState(
        torch.zeros(B, 10, dtype=torch.float64), 1e-2 * torch.eye(10, dtype=torch.float64)
    )
    for t in range(T):
        state, out = obs.step(state, zs[:, t], us[:, t])
        ref, ref_out = difffilter.kalman_step(model, ref, zs[:, t], u=us[:, t])
        assert torch.allclose(out.mean, ref.mean, atol=1e-12)
        assert torch.allclose(out.innovation, ref_out.innovation, atol=1e-12)
        assert torch.allclose(out.innovation_cov, ref_out.innovation_cov, atol=1e-14)


class _OracleObserver:
    """A Kalman observer whose attack estimate is the true attack (duck-types AttackObserver)."""

    def __init__(self, plant, alpha):
        self.inner = AttackObserver(plant.Ad, plant.Bd, plant.Q, plant.R)
        self.alpha = alpha

    def init(self, runs, params=None):
        return self.inner.init(runs)

    def step(self, state, z, u):
        k = state.k
        new, out = self.inner.step(state, z - self.alpha[:, k - 1], u)
        return new, dataclasses.replace(out, attack=self.alpha[:, k - 1].expand_as(z))


def test_secure_controller_with_a_perfect_estimate_undoes_the_attack(plant):
    K1, _ = lqr(plant.A, plant.B)
    g = torch.Generator().manual_seed(1)
    T = 300
    xi, theta = plant.sample_noise(2, T, g)
    t = plant.dt * torch.arange(1, T + 1, dtype=torch.float64)
    alpha = scenario_attack("step", t + 2.9)[None]  # the 0.4 step begins at k = 1
    load = torch.tensor([[0.01, 0.0]], dtype=torch.float64)
    plain = ClosedLoop(
        plant, K1, AttackObserver(plant.Ad, plant.Bd, plant.Q, plant.R), compensate=False
    )
    _, free = plain.run(plain.init(2), torch.zeros_like(alpha), xi, theta, load)
    _, attacked = plain.run(plain.init(2), alpha, xi, theta, load)
    # The attack drives the traditional loop away from the attack-free one ...
    assert (attacked.x - free.x)[..., 4].abs().max() > 0.05
    # ... and a secure loop fed the true attack reproduces the attack-free trajectory.
    secure = ClosedLoop(plant, K1, _OracleObserver(plant, alpha))
    _, oracle = secure.run(secure.init(2), alpha, xi, theta, load)
    assert torch.allclose(oracle.x, free.x, atol=1e-12)
    assert torch.allclose(oracle.mean, free.mean, atol=1e-12)


def test_closed_loop_shapes_and_online_learning(plant):
    K1, _ = lqr(plant.A, plant.B)
    net = NeuralFDIEstimator(init_scale=0.1, detection_head=False)
    for learning in ("ekf", "gradient"):
        obs = AttackObserver(
            plant.Ad,
            plant.Bd,
            plant.Q,
            plant.R,
            network=net,
            learning=learning,
            learning_kwargs={"lr": 0.01} if learning == "gradient" else {},
        )
        loop = ClosedLoop(plant, K1, obs)
        g = torch.Generator().manual_seed(2)
        xi, theta = plant.sample_noise(3, 20, g)
        alpha = torch.zeros(1, 20, 10, dtype=torch.float64)
        alpha[..., 2] = 0.5
        state, rec = loop.run(
            loop.init(3), alpha, xi, theta, torch.zeros(1, 2, dtype=torch.float64)
        )
        assert rec.attack_est.shape == (3, 20, 10) and rec.innovation_cov.shape == (20, 10, 10)
        assert bool(torch.isfinite(rec.attack_est).all())
        # Every run has its own weights, and learning moved them.
        W = state.observer.learner.params()["W"]
        assert W.shape == (3, 2, 5, 10)
        assert not torch.allclose(W[0], net.W)
        assert not torch.allclose(W[0], W[1])
    with pytest.raises(ValueError, match="learning"):
        AttackObserver(plant.Ad, plant.Bd, plant.Q, plant.R, learning="ekf")
    with pytest.raises(ValueError, match="gain"):
        AttackObserver(plant.Ad, plant.Bd, plant.Q, plant.R, kind="luenberger")
    with pytest.raises(ValueError, match="residual_lag"):
        AttackObserver(plant.Ad, plant.Bd, plant.Q, plant.R, residual_lag=2)


def test_residual_lag_zero_sees_the_current_measurement(plant):
    """With ℓ = 0 a frozen network reacts to an attack at the step it starts; with ℓ = 1 a step later."""
    K1, _ = lqr(plant.A, plant.B)
    net = NeuralFDIEstimator(init="symmetric", init_scale=0.3, seed=5, detection_head=False)
    xi = torch.zeros(1, 6, 10, dtype=torch.float64)
    alpha = torch.zeros(1, 6, 10, dtype=torch.float64)
    alpha[:, 3:, 2] = 1.0
    out = {}
    for lag in (0, 1):
        loop = ClosedLoop(
            plant,
            K1,
            AttackObserver(plant.Ad, plant.Bd, plant.Q, plant.R, network=net, residual_lag=lag),
        )
        _, rec = loop.run(loop.init(1), alpha, xi, xi, torch.zeros(1, 2, dtype=torch.float64))
        free_loop = ClosedLoop(
            plant,
            K1,
            AttackObserver(plant.Ad, plant.Bd, plant.Q, plant.R, network=net, residual_lag=lag),
        )
        _, free = free_loop.run(
            free_loop.init(1),
            torch.zeros_like(alpha),
            xi,
            xi,
            torch.zeros(1, 2, dtype=torch.float64),
        )
        out[lag] = (rec.attack_est - free.attack_est).abs().sum(-1)[0]
    assert out[0][3] > 1e-3 and out[1][3] == 0 and out[1][4] > 1e-3
