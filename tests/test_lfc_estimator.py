"""The LFC paper's neural FDI estimator, its observers and the secure closed loop, on the
shared path: NeuralCompensation around the library's filters in difffilter's closed loop."""

from __future__ import annotations

import pytest
import torch

import difffilter
from difffilter.estimator import Estimator, Generators
from difffilter.fdi.neural import build_delta
from difffilter.kalman import KalmanFilter
from difffilter.models.learned_estimator import NeuralCompensation, OnlineLearning, Residual
from difffilter.models.lfc import LFCPlant, lfc_loop, scenario_attack
from difffilter.models.lfc_estimators import LFCContext, lfc_estimator, paper_network
from difffilter.models.neural_estimator import (
    EstimatorCard,
    NeuralFDIEstimator,
    load_estimator_checkpoint,
    save_estimator_checkpoint,
)
from difffilter.observers import FixedGainFilter
from difffilter.param_ekf import EKFRule, GradientRule


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
    with pytest.raises(ValueError, match="WeightInit"):
        NeuralFDIEstimator(init="normal")
    with pytest.raises(ValueError, match="delta"):
        NeuralFDIEstimator()(torch.zeros(3, 2, 29, dtype=torch.float64))
    with pytest.raises(TypeError, match="inner"):
        NeuralCompensation(NeuralFDIEstimator(), "kf")
    with pytest.raises(TypeError, match="learning"):
        NeuralCompensation(NeuralFDIEstimator(), KalmanFilter(), learning="ekf")


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
    # any leading batch shape
    assert build_delta(
        attack_hist.expand(3, 4, a, 10), resid_hist.expand(3, 4, b, 10), 2
    ).shape == (3, 4, 2, 25)


def test_checkpoint_roundtrip_and_errors(tmp_path):
    net = NeuralFDIEstimator(hidden=6, resid_scale=0.1, seed=9, dtype=torch.float32)
    path = tmp_path / "est.ckpt"
    save_estimator_checkpoint(path, net, {"residual_lag": 0, "dt": 0.01, "kind": "kalman"})
    raw = torch.load(path, weights_only=True)  # never a pickled module
    assert set(raw) >= {"format", "estimator_config", "state_dict", "observer"}
    loaded, card = load_estimator_checkpoint(path)
    # the LFC module's older card layout reads as the typed card
    assert card.filter == "kf" and card.residual == "predicted" and not card.standardize
    assert card.scenario_family == "lfc" and card.dt == 0.01 and loaded.V.dtype == torch.float64
    assert torch.allclose(loaded.V.float(), net.V) and loaded.resid_scale == 0.1
    typed = EstimatorCard(scenario_family="four_tank", filter="pf", features=("mask",))
    save_estimator_checkpoint(path, net, typed)
    assert load_estimator_checkpoint(path)[1] == typed
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


def test_the_observers_kalman_filter_equals_kalman_step(plant):
    """The closed loop's Kalman filter (the shared gain schedule) is difffilter's
    kalman_step on every run."""
    model = plant.model(knows_load=False)
    g = torch.Generator().manual_seed(0)
    B, T = 3, 40
    zs = 0.05 * torch.randn(B, T, 10, generator=g, dtype=torch.float64)
    us = 0.05 * torch.randn(B, T, 4, generator=g, dtype=torch.float64)
    kf = KalmanFilter()
    carry = kf.init(model, (B,))
    assert carry.gains is not None  # an unbatched LTI model: gains shared by the runs
    ref = difffilter.GaussianState(
        torch.zeros(B, 10, dtype=torch.float64), 1e-2 * torch.eye(10, dtype=torch.float64)
    )
    for t in range(T):
        carry, out = kf.step(carry, zs[:, t], us[:, t])
        ref, ref_out = difffilter.kalman_step(model, ref, zs[:, t], u=us[:, t])
        assert torch.allclose(out.mean, ref.mean, atol=1e-12)
        assert torch.allclose(out.innovation, ref_out.innovation, atol=1e-12)
        assert torch.allclose(out.innovation_cov, ref_out.innovation_cov, atol=1e-14)
        assert torch.allclose(out.log_likelihood, ref_out.log_likelihood, atol=1e-9)


class _Oracle(Estimator):
    """A Kalman observer fed the measurement without the true attack, reporting it."""

    carry_type = difffilter.GaussianState

    def __init__(self, alpha):
        self.kf, self.alpha = KalmanFilter(), alpha

    def _init(self, model, batch_shape, generators):
        return self.kf._init(model, batch_shape, generators)

    def _step(self, carry, y, u, mask):
        a = self.alpha[:, carry.k]
        carry, out = self.kf._step(carry, y - a, u, mask)
        return carry, out._replace(attack=a.expand_as(y))


def test_secure_controller_with_a_perfect_estimate_undoes_the_attack(plant):
    g = torch.Generator().manual_seed(1)
    T = 300
    xi, theta = plant.sample_noise(2, T, g)
    t = plant.dt * torch.arange(1, T + 1, dtype=torch.float64)
    alpha = scenario_attack("step", t + 2.9)[None].expand(2, T, 10)  # begins at k = 10
    load = torch.tensor([[0.01, 0.0]], dtype=torch.float64)
    from difffilter.models.attacks import Signal

    free = lfc_loop(plant, KalmanFilter(), xi, theta, load, compensate=False)
    attacked = lfc_loop(plant, KalmanFilter(), xi, theta, load, attack=Signal(alpha),
                        compensate=False)  # fmt: skip
    dx = (attacked.trajectories.x - free.trajectories.x)[..., 4]
    assert dx.abs().max() > 0.05  # the attack drives the traditional loop away ...
    # ... and a secure loop fed the true attack reproduces the attack-free trajectory
    oracle = lfc_loop(plant, _Oracle(alpha), xi, theta, load, attack=Signal(alpha))
    assert torch.allclose(oracle.trajectories.x, free.trajectories.x, atol=1e-12)
    assert torch.allclose(oracle.output.means, free.output.means, atol=1e-12)
    # the loop's own record: the received measurement is the plant's output plus the attack
    tr = attacked.trajectories
    assert torch.allclose(tr.y_recv, tr.y_true + alpha) and bool(tr.flags[:, 10:190].all())


@pytest.mark.parametrize("rule", [EKFRule(), GradientRule(lr=0.01)], ids=["ekf", "gradient"])
def test_closed_loop_online_learning_keeps_one_learner_per_run(plant, rule):
    ctx = LFCContext()
    est = lfc_estimator(ctx, network=paper_network(0.1), rule=rule, init_scale=0.1)
    g = torch.Generator().manual_seed(2)
    xi, theta = plant.sample_noise(3, 20, g)
    alpha = torch.zeros(3, 20, 10, dtype=torch.float64)
    alpha[..., 2] = 0.5
    from difffilter.models.attacks import Signal

    gens = Generators(init=torch.Generator().manual_seed(4))
    loop = lfc_loop(plant, est, xi, theta, torch.zeros(1, 2, dtype=torch.float64),
                    attack=Signal(alpha), generator=gens)  # fmt: skip
    assert loop.output.attack.shape == (3, 20, 10) and bool(loop.output.attack.isfinite().all())
    learner = loop.state.carry.net.learner
    W = est.core.template.unflatten(learner.theta)["W"].reshape(3, 2, 5, 10)
    start = est.core.template.unflatten(
        est.core.init(torch.Size([3]), torch.float64, "cpu",
                      torch.Generator().manual_seed(4)).learner.theta)["W"].reshape(3, 2, 5, 10)  # fmt: skip
    assert not torch.allclose(W[0], start[0])  # learning moved the weights ...
    assert not torch.allclose(W[0], W[1])  # ... of every run on its own


def test_the_networks_step_by_hand(plant):
    """Eq. (9) with the predicted residual (ℓ = 0) and the lagged one (ℓ = 1), two steps."""
    model = plant.model(knows_load=False)
    net = NeuralFDIEstimator(init="symmetric", init_scale=0.3, seed=5, detection_head=False)
    g = torch.Generator().manual_seed(6)
    ys = 0.1 * torch.randn(2, 3, 10, generator=g, dtype=torch.float64)
    for residual in (Residual.PREDICTED, Residual.LAGGED):
        est = NeuralCompensation(net, KalmanFilter(), residual=residual, standardize=False)
        carry, kf = est.init(model, (2,)), KalmanFilter()
        ref = kf.init(model, (2,))
        a_hist = torch.zeros(2, 3, 10, dtype=torch.float64)
        r_hist = torch.zeros(2, 3, 10, dtype=torch.float64)
        for t in range(3):
            carry, out = est.step(carry, ys[:, t])
            pred = kf.predict(ref, None)
            nu = ys[:, t] - pred.mean
            if residual is Residual.PREDICTED:
                r = nu - a_hist[:, 0]
                resid_in = torch.cat([r[:, None], r_hist[:, :-1]], 1)
            else:
                resid_in = r_hist
            a, _ = net(build_delta(a_hist, resid_in, 2))
            a = a.flatten(-2)
            entry = r if residual is Residual.PREDICTED else nu - a
            ref, ref_out = kf.update(ref, pred, ys[:, t] - a, None)
            a_hist = torch.cat([a[:, None], a_hist[:, :-1]], 1)
            r_hist = torch.cat([entry[:, None], r_hist[:, :-1]], 1)
            torch.testing.assert_close(out.attack, a, rtol=0, atol=1e-12)
            torch.testing.assert_close(out.mean, ref.mean, rtol=0, atol=1e-12)


def test_residual_predicted_sees_the_current_measurement(plant):
    """With ℓ = 0 a frozen network reacts to an attack at the step it starts; with ℓ = 1 a step later."""
    net = NeuralFDIEstimator(init="symmetric", init_scale=0.3, seed=5, detection_head=False)
    xi = torch.zeros(1, 6, 10, dtype=torch.float64)
    alpha = torch.zeros(1, 6, 10, dtype=torch.float64)
    alpha[:, 3:, 2] = 1.0
    from difffilter.models.attacks import Signal

    out = {}
    zero = torch.zeros(1, 2, dtype=torch.float64)
    for residual in (Residual.PREDICTED, Residual.LAGGED):
        est = NeuralCompensation(net, KalmanFilter(), residual=residual, standardize=False)
        rec = lfc_loop(plant, est, xi, xi, zero, attack=Signal(alpha)).output.attack
        free = lfc_loop(plant, est, xi, xi, zero).output.attack
        out[residual] = (rec - free).abs().sum(-1)[0]
    p, lag = out[Residual.PREDICTED], out[Residual.LAGGED]
    assert p[3] > 1e-3 and lag[3] == 0 and lag[4] > 1e-3


def test_luenberger_observer_is_the_fixed_gain_filter(plant):
    ctx = LFCContext()
    L = ctx.luenberger("modal")
    model = plant.model(knows_load=False)
    obs = FixedGainFilter(L)
    carry = obs.init(model, (2,))
    y = torch.randn(2, 10, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    u = torch.zeros(2, 4, dtype=torch.float64)
    carry, out = obs.step(carry, y, u)
    pred = plant.Ad @ torch.zeros(10, dtype=torch.float64)
    assert torch.allclose(out.mean, pred + (y - pred) @ L.T)
    assert out.cov is None and out.innovation_cov is None
    with pytest.raises(ValueError, match="gain"):
        FixedGainFilter(torch.zeros(3, 3, dtype=torch.float64)).init(model, (1,))
    # the online learners are objects, not names
    with pytest.raises(TypeError, match="OnlineLearning"):
        NeuralCompensation(paper_network(), obs, learning="gradient")
    assert OnlineLearning(GradientRule()).posterior


@pytest.mark.parametrize("rule", [EKFRule(), GradientRule(lr=0.01)], ids=["ekf", "gradient"])
def test_the_online_learner_learns_nothing_from_steps_that_received_nothing(plant, rule):
    """A lossy-link trial: with every entry lost for 100 steps the per-run learner's weights
    had moved by 27 % of their size (towards the filter's placeholder innovation 0), and Υ
    with them. Steps that receive nothing leave the learner as it was (Q_ρ = 0)."""
    from difffilter.loop import ReplayedNoise, closed_loop
    from difffilter.models.attacks import Signal
    from difffilter.models.lfc import SecureController, lqr_gain

    ctx = LFCContext()
    est = lfc_estimator(ctx, network=paper_network(0.1), rule=rule, init_scale=0.1)
    g = torch.Generator().manual_seed(5)
    B, T = 2, 30
    xi, theta = plant.sample_noise(B, T, g)
    alpha = torch.zeros(B, T, 10, dtype=torch.float64)
    alpha[:, 5:, 2] = 0.5
    mask = torch.ones(B, T, 10, dtype=torch.bool)
    mask[:, 20:] = False  # steps 21–30: nothing arrives
    mask[0, 10:20, :5] = False  # run 0, steps 11–20: the first area's entries lost
    kw = dict(noise=ReplayedNoise(xi, theta), estimator=est, model=plant.model(knows_load=False),
              attack=Signal(alpha), mask=mask, horizon=T,
              controller=SecureController(lqr_gain(plant), torch.zeros(1, 2, dtype=torch.float64)))  # fmt: skip
    with torch.no_grad():
        head = closed_loop(plant.model(), 20, x0=torch.zeros(B, 10, dtype=torch.float64),
                           generator=Generators(init=torch.Generator().manual_seed(4)), **kw)  # fmt: skip
        before = head.state.carry.net.learner
        tail = closed_loop(plant.model(), 10, state=head.state.copy(), **kw)
    after = tail.state.carry.net.learner
    assert torch.equal(after.theta, before.theta)
    if isinstance(rule, EKFRule):
        assert torch.equal(after.upsilon, before.upsilon)
        assert torch.equal(EKFRule.covariance(after), EKFRule.covariance(before))
        # the learner of run 0's first area (row 0 of runs × areas): 10 fewer informed steps
        assert before.seen.tolist() == [10.0, 20.0, 20.0, 20.0]
    else:  # the gradient rule keeps no noise estimate
        assert before.upsilon is None and before.seen is None


def test_two_loops_resumed_from_one_state_run_the_same_and_to_the_end(plant):
    """A trial: resuming twice from one state (two what-ifs) gave attack estimates 0.107
    apart, the first loop having written the learners' donated covariance buffers in the
    state; and ``lfc_loop(state=…)`` without ``steps`` asked for draws past their end. A
    consumed state is refused; two loops from copies made before run the same."""
    from difffilter.models.attacks import Signal

    ctx = LFCContext()
    est = lfc_estimator(ctx, network=paper_network(0.1), rule=EKFRule(donate=True, fold_every=2),
                        init_scale=0.1)  # fmt: skip
    g = torch.Generator().manual_seed(6)
    xi, theta = plant.sample_noise(2, 24, g)
    alpha = torch.zeros(2, 24, 10, dtype=torch.float64)
    alpha[:, 8:, 2] = 0.5
    kw = dict(attack=Signal(alpha))
    load = torch.zeros(1, 2, dtype=torch.float64)
    gens = Generators(init=torch.Generator().manual_seed(4))
    whole = lfc_loop(plant, est, xi, theta, load, generator=gens, **kw)
    gens = Generators(init=torch.Generator().manual_seed(4))
    head = lfc_loop(plant, est, xi, theta, load, generator=gens, steps=10, **kw)
    spare = head.state.copy()
    first = lfc_loop(plant, est, xi, theta, load, state=head.state, **kw)  # steps 11–24
    with pytest.raises(ValueError, match="this learner state was consumed"):
        lfc_loop(plant, est, xi, theta, load, state=head.state, **kw)
    second = lfc_loop(plant, est, xi, theta, load, state=spare, **kw)
    assert first.output.attack.shape[1] == 14
    assert torch.equal(first.output.attack, second.output.attack)
    assert torch.equal(first.output.attack, whole.output.attack[:, 10:])


@pytest.mark.parametrize("rule", [EKFRule(), GradientRule(lr=0.01)], ids=["ekf", "gradient"])
def test_the_online_learners_run_on_float32_measurements(rule):
    """A trial: the registry's learners (``kf_nn_ekf``, ``traditional_ad``,
    ``kf_nn_grad_ekf``) failed on float32 draws with a raw matmul dtype error. The learners
    run in the network's dtype (float64 here), as the frozen network does, and hand out
    estimates in the measurements'; on the same draws they track the float64 loop."""
    from difffilter.models.attacks import Signal

    est = lfc_estimator(LFCContext(), network=paper_network(0.1), rule=rule, init_scale=0.1)
    g = torch.Generator().manual_seed(7)
    xi, theta = LFCPlant().sample_noise(2, 40, g)
    alpha = torch.zeros(2, 40, 10, dtype=torch.float64)
    alpha[:, 10:, 2] = 0.5
    out = {}
    for dtype in (torch.float64, torch.float32):
        gens = Generators(init=torch.Generator().manual_seed(4))
        loop = lfc_loop(LFCPlant(dtype=dtype), est, xi.to(dtype), theta.to(dtype),
                        torch.zeros(1, 2, dtype=dtype), attack=Signal(alpha.to(dtype)),
                        generator=gens)  # fmt: skip
        out[dtype] = loop.output.attack
    assert out[torch.float32].dtype == torch.float32
    torch.testing.assert_close(out[torch.float32].double(), out[torch.float64], rtol=0, atol=1e-3)


def test_a_load_of_other_runs_is_refused_by_name(plant):
    """A trial: a load drawn for 8 runs beside draws of 1 failed in a raw expand error."""
    xi, theta = plant.sample_noise(1, 5, torch.Generator().manual_seed(0))
    est = lfc_estimator(LFCContext(), network=paper_network(0.1))
    with pytest.raises(
        ValueError,
        match=r"load must be a tensor \[2\] or \[1, 2\] \(one for every run\) or \[1, 2\] \(one per run of xi\); got \(8, 2\)",
    ):
        lfc_loop(plant, est, xi, theta, torch.zeros(8, 2, dtype=torch.float64))
    for one_for_all in (
        torch.zeros(2, dtype=torch.float64),
        torch.zeros(1, 2, dtype=torch.float64),
    ):
        assert lfc_loop(plant, est, xi, theta, one_for_all).output.means.shape == (1, 5, 10)
