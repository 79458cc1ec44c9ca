"""Hand checks of the plant models and the core API beyond the paths the other tests take.

The LFC load's law and its absence from the observers' model, the tracking deception box,
the four-tank equilibrium, the robot at another sampling time, the measurement time index of
``simulate`` and of the open-loop feature, thresholds that change with the step, the lagged
residual under online learning, and the mixture PF's score with another proposal: each
against its docstring or paper equation, computed independently.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import difffilter as df

F64 = torch.float64


# ---------------------------------------------------------------- LFC


def test_lfc_load_is_uniform_around_zero_over_its_range():
    """``load_range``: a load per run and area ~ U[−range/2, range/2]."""
    from difffilter.models.lfc import LFCScenario

    scenario = LFCScenario(
        name="x", family="lfc", description="", attack="none", load_range=0.02, duration=0.05
    )
    load = scenario.exogenous(4000, {"plant": torch.Generator().manual_seed(0)})["load"]
    assert load.shape == (4000, 2)
    assert -0.01 <= float(load.min()) < -0.0099
    assert 0.0099 < float(load.max()) <= 0.01
    assert abs(float(load.mean())) < 4 * 0.02 / math.sqrt(12) / math.sqrt(8000)


def test_lfc_loop_hides_the_load_from_the_estimator():
    """The estimator runs on the observers' model: B = [B_d, 0] (the load an unknown input),
    B_d the zero-order hold of the continuous B (a Van Loan matrix exponential here)."""
    from difffilter.models.lfc import LFCPlant, continuous_model, lfc_loop

    seen = []

    class Spy(df.KalmanFilter):
        def _init(self, model, batch_shape, generators):
            seen.append(model)
            return super()._init(model, batch_shape, generators)

    plant = LFCPlant()
    xi, theta = plant.sample_noise(2, 5, torch.Generator().manual_seed(1))
    lfc_loop(plant, Spy(), xi, theta, torch.tensor([[0.01, 0.0]], dtype=F64))
    B = seen[0].B
    A, Bc, F = continuous_model()
    van_loan = torch.zeros(14, 14, dtype=F64)
    van_loan[:10, :10] = A
    van_loan[:10, 10:] = torch.cat([Bc, F], 1)
    discrete = torch.linalg.matrix_exp(van_loan * 0.01)
    torch.testing.assert_close(B[:, :2], discrete[:10, 10:12], rtol=0, atol=1e-12)
    assert float(B[:, 2:].abs().max()) == 0.0


# ---------------------------------------------------------------- tracking


def test_tracking_deception_box_needs_both_range_and_bearing_inside():
    """p_ξ uniform on the box of one sensor's (range, bearing): a packet with either entry
    outside has p_ξ = 0 (attacked term −∞); inside, log(η̄ / box area), in the filter's
    float64 (the box was float32: 1.7e-7 off)."""
    from difffilter.models.tracking import PerSensorDeception, TrackingModel

    low, high = (-10.0, -math.pi / 2), (80.0, math.pi / 2)
    deception = PerSensorDeception(0.2, low, high, 4)
    x = torch.tensor([[20.0, 0.3, 20.0, 0.3], [21.0, 0.3, 19.0, 0.3]], dtype=F64)
    # sensors: bearing outside; range outside; both inside; both outside
    y = torch.tensor([50.0, 3.0, 200.0, 0.5, 50.0, 0.5, 200.0, 3.0], dtype=F64)
    _, attacked, _ = deception.components(TrackingModel(), y, x, 1, None)
    assert attacked[0, 0] == -math.inf
    assert attacked[0, 1] == -math.inf
    assert attacked.dtype == F64  # the box's area in the filter's precision
    expected = math.log(0.2) - math.log(90.0 * math.pi)
    assert float(attacked[0, 2]) == pytest.approx(expected, abs=1e-12)
    assert attacked[0, 3] == -math.inf


# ---------------------------------------------------------------- four-tank, robot


def test_four_tank_fixed_point_is_an_equilibrium():
    """ḣ = 0 there (the continuous model written out in numpy), at the documented levels."""
    from difffilter.models.four_tank import FourTankParameters

    p = FourTankParameters()
    h = np.array(p.fixed_point())
    A, a = np.array(p.A), np.array(p.a)
    (k1, k2), (g1, g2), (v1, v2) = p.k, p.gamma, p.v
    s = np.sqrt(2 * p.g * h)
    rhs = np.array([
        -a[0] / A[0] * s[0] + a[2] / A[0] * s[2] + g1 * k1 / A[0] * v1,
        -a[1] / A[1] * s[1] + a[3] / A[1] * s[3] + g2 * k2 / A[1] * v2,
        -a[2] / A[2] * s[2] + (1 - g2) * k2 / A[2] * v2,
        -a[3] / A[3] * s[3] + (1 - g1) * k1 / A[3] * v1,
    ])  # fmt: skip
    assert np.abs(rhs).max() < 1e-12
    np.testing.assert_allclose(h, [12.263, 12.783, 1.634, 1.409], atol=1e-3)


@pytest.mark.parametrize("dt", [0.5, 2.0])
def test_robot_linearized_transition_at_another_sampling_time(dt):
    """f(x, u) = x + T [u_p cos θ, u_p sin θ, u_r] (B2) for T ≠ 1."""
    from difffilter.models.robot import RobotModel

    x = [torch.tensor(v, dtype=F64) for v in ([1.0, 3.0], [2.0, -1.0], [0.3, -2.0])]
    u = [torch.tensor([5.0], dtype=F64), torch.tensor([0.2], dtype=F64)]
    model = RobotModel(dt=dt)
    predicted = model.linearize_components(x, u, [torch.zeros(1, dtype=F64)] * model.dim_y, 1)[0]
    X = np.stack([t.numpy() for t in x], -1)
    want = X + dt * np.stack([5 * np.cos(X[:, 2]), 5 * np.sin(X[:, 2]), 0.2 * np.ones(2)], -1)
    np.testing.assert_allclose(np.stack([t.numpy() for t in predicted], -1), want, atol=1e-12)


# ---------------------------------------------------------------- time indices, thresholds


def test_simulate_measures_x_k_at_time_k():
    """ys[t] measures xs[t] = x_{t+1} with h(·, t + 1): h(x, k) = x + 100 k, noise ≈ 0."""
    eye = torch.eye(1, dtype=F64)
    model = df.NonlinearGaussianModel(
        lambda x: x, lambda x, k: x + 100.0 * k, 1e-12 * eye, 1e-12 * eye,
        torch.zeros(1, dtype=F64), eye,
    )  # fmt: skip
    xs, ys, _ = model.simulate(4, (2,), generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(
        (ys - xs)[0, :, 0], torch.tensor([100.0, 200.0, 300.0, 400.0], dtype=F64), rtol=0, atol=1e-3
    )


def test_open_loop_feature_evaluates_h_at_the_measurements_time():
    """(y_k − h(x̄_k, k)) / √R: with h(x, k) = x + 10 k, x̄_k = 0 and y_k = 10 k it is 0."""
    from difffilter.fdi.neural import NeuralCompensation
    from difffilter.models.neural_estimator import NeuralFDIEstimator

    eye = torch.eye(1, dtype=F64)
    model = df.NonlinearGaussianModel(
        lambda x: x, lambda x, k: x + 10.0 * k, 1e-3 * eye, 0.04 * eye,
        torch.zeros(1, dtype=F64), eye,
    )  # fmt: skip
    net = NeuralFDIEstimator(num_areas=1, area_dim=1, a=1, b=1, hidden=3, init="symmetric",
                             init_scale=0.5, extra_inputs=1, seed=1)  # fmt: skip
    estimator = NeuralCompensation(
        net, df.ExtendedKalmanFilter(), features=("open_loop_innovation",), record_inputs=True
    )
    carry = estimator.init(model, (2,))
    for k in range(1, 5):
        carry, out = estimator.step(carry, torch.full((2, 1), 10.0 * k, dtype=F64))
        assert float(out.extras["network_inputs"][..., -1].abs().max()) < 1e-12


def test_thresholds_that_change_with_the_step_are_stacked_per_step():
    from difffilter.estimator import stack_steps
    from difffilter.results import StepOutput

    def outputs(thresholds):
        return [StepOutput(mean=torch.zeros(2, 1), score=torch.zeros(2),
                           alarm=torch.zeros(2, dtype=torch.bool), threshold=t)
                for t in thresholds]  # fmt: skip

    varying = stack_steps(outputs([1.0, 2.0, 1.0]), torch.Size([2])).detection.threshold
    assert torch.is_tensor(varying) and varying.shape == (2, 3)
    assert varying[0].tolist() == [1.0, 2.0, 1.0]
    assert stack_steps(outputs([3.0, 3.0, 3.0]), torch.Size([2])).detection.threshold == 3.0


# ---------------------------------------------------------------- neural compensation


def test_lagged_residual_under_online_learning_uses_the_estimate_before_the_update():
    """e_k = ν_k − â_k with â_k the network's estimate before the step's weight update (its
    original weights at step 2, as step 1 updates nothing: δ₁ = 0), not the posterior's."""
    from difffilter.fdi.neural import NeuralCompensation, OnlineLearning, build_delta
    from difffilter.models.lfc import LFCPlant
    from difffilter.models.neural_estimator import NeuralFDIEstimator
    from difffilter.param_ekf import EKFRule

    model = LFCPlant().model(knows_load=False)
    net = NeuralFDIEstimator(init="symmetric", init_scale=0.3, seed=5, detection_head=False)
    estimator = NeuralCompensation(net, df.KalmanFilter(), residual="lagged", standardize=False,
                                   learning=OnlineLearning(EKFRule(), posterior=True))  # fmt: skip
    ys = 0.3 * torch.randn(2, 2, 10, generator=torch.Generator().manual_seed(6), dtype=F64)
    carry = estimator.init(model, (2,))
    kf = df.KalmanFilter()
    reference = kf.init(model, (2,))
    innovations = []
    for t in range(2):
        carry, out = estimator.step(carry, ys[:, t])
        pred = kf.predict(reference, None)
        innovations.append(ys[:, t] - pred.mean)
        reference, _ = kf.update(reference, pred, ys[:, t] - (0.0 if t == 0 else out.attack), None)
    history = torch.zeros(2, 3, 10, dtype=F64)
    history[:, 0] = innovations[0]
    with torch.no_grad():
        prior = net(build_delta(torch.zeros(2, 3, 10, dtype=F64), history, 2))[0].flatten(-2)
    assert float((out.attack - prior).abs().max()) > 1e-6  # the posterior moved: not void
    entry = carry.net.resid_hist[..., 0, :].flatten(-2)
    torch.testing.assert_close(entry, innovations[1] - prior, rtol=0, atol=1e-10)


# ---------------------------------------------------------------- mixture PF


def test_mixture_pf_score_with_a_kalman_proposal_is_the_attack_posterior():
    """P(l_k = 1 | y_1:k) = p p_ξ(y) Σᵢ wᵢ / mixᵢ over the posterior weights (w ∝ w̄ · mix),
    mix = (1 − p) N(y; x, R) + p p_ξ(y), in numpy."""
    from difffilter.fdi.mixture import (
        DeceptionMixtureLikelihood,
        MixtureParticleFilter,
        ReplacementDeception,
    )
    from difffilter.noise import UniformBox
    from difffilter.particle import KalmanProposal

    eye = torch.eye(1, dtype=F64)
    R, p = 0.5, 0.3
    model = df.LinearGaussianModel(eye, eye, 0.1 * eye, R * eye, torch.zeros(1, dtype=F64), eye)
    box = UniformBox(torch.tensor([-10.0], dtype=F64), torch.tensor([10.0], dtype=F64))
    pf = MixtureParticleFilter(
        200, DeceptionMixtureLikelihood(p, ReplacementDeception(box)), proposal=KalmanProposal()
    )
    carry = pf.init(model, (3,), torch.Generator().manual_seed(0))
    for value in (3.0, -1.0, 6.0, 0.5):
        carry, out = pf.step(carry, torch.full((3, 1), value, dtype=F64))
        x = carry.particles[..., 0].numpy()
        w = torch.softmax(carry.log_weights, -1).numpy()
        clean = np.exp(-0.5 * (value - x) ** 2 / R) / math.sqrt(2 * math.pi * R)
        mix = (1 - p) * clean + p / 20.0
        np.testing.assert_allclose(out.score.numpy(), p / 20.0 * (w / mix).sum(-1), atol=1e-9)
