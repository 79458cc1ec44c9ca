"""Mutation-review checks of the four-tank and mobile-robot plants against the papers.

Four-tank: Johansson's quadruple tank (IEEE TCST 2000) as docs/scenarios.md section 1 writes it,
Euler-discretised; the modified-PF paper's thresholds (Theorem 1) and scenario numbers.
Robot: Tan, Weng, Chen & Yu, App. B, eqs (B2)-(B7). Every expected value is a literal numpy
(float64) evaluation of the equations, a central-difference derivative, or a number stated
in the papers / docs/scenarios.md, never the code under test.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch

from difffilter.models import registry
from difffilter.models.estimators import poa_detector_for_scenario
from difffilter.models.four_tank import (
    R_HIGH,
    R_NOMINAL,
    FourTankModel,
    FourTankParameters,
    FourTankScenario,
)
from difffilter.models.robot import GROUPS, SENSORS, RobotModel, RobotScenario

F64 = torch.float64
DEG = math.pi / 180.0

# A deliberately asymmetric tank: every area, outlet, pump gain, valve split and voltage
# differs, so a swapped index (A1 for A3, a2 for a4, ...) changes the numbers.
CUSTOM = FourTankParameters(
    A=(27.0, 31.0, 25.0, 35.0),
    a=(0.07, 0.05, 0.09, 0.04),
    g=981.0,
    k=(3.1, 3.6),
    gamma=(0.65, 0.55),
    v=(2.5, 3.5),
)


def _tank_rhs(h: np.ndarray, p: FourTankParameters) -> np.ndarray:
    """Johansson's four equations (docs/scenarios.md section 1), levels clamped at 0 in the roots."""
    A, a, g = np.array(p.A), np.array(p.a), p.g
    (k1, k2), (g1, g2), (v1, v2) = p.k, p.gamma, p.v
    s = np.sqrt(2 * g * np.maximum(h, 0.0))
    return np.array(
        [
            -a[0] / A[0] * s[0] + a[2] / A[0] * s[2] + g1 * k1 / A[0] * v1,
            -a[1] / A[1] * s[1] + a[3] / A[1] * s[3] + g2 * k2 / A[1] * v2,
            -a[2] / A[2] * s[2] + (1 - g2) * k2 / A[2] * v2,
            -a[3] / A[3] * s[3] + (1 - g1) * k1 / A[3] * v1,
        ]
    )


def _euler(h: np.ndarray, p: FourTankParameters, dt: float) -> np.ndarray:
    return h + dt * _tank_rhs(h, p)


def test_asymmetric_tank_step_rhs_fixed_point_and_jacobian_match_johansson():
    """With every parameter distinct, the Euler step, f_c, the √-affine form, the fixed
    point (f_c(x*) = 0, numpy) and the Jacobian (central differences) equal Johansson's
    equations evaluated in numpy."""
    dt = 0.8
    model = FourTankModel(dt=dt, params=CUSTOM, dtype=F64)
    xs = np.array([[10.0, 9.0, 2.0, 3.0], [5.0, 14.0, 4.5, 0.7], [-0.5, 4.0, -1.0, 2.0]])
    x_t = torch.tensor(xs, dtype=F64)
    want = np.stack([_euler(x, CUSTOM, dt) for x in xs])
    np.testing.assert_allclose(model.transition(x_t, None, 0).numpy(), want, rtol=0, atol=1e-12)
    rhs = np.stack([_tank_rhs(x, CUSTOM) for x in xs])
    np.testing.assert_allclose(model.continuous_rhs(x_t).numpy(), rhs, rtol=0, atol=1e-12)
    M, c = model.sqrt_affine_form()
    fused = xs + c.numpy() + np.sqrt(np.maximum(xs, 0.0)) @ M.numpy()
    np.testing.assert_allclose(fused, want, rtol=0, atol=1e-12)
    xstar = np.array(CUSTOM.fixed_point())
    assert (xstar > 0).all()
    np.testing.assert_allclose(_tank_rhs(xstar, CUSTOM), 0.0, atol=1e-12)
    # default prior mean = the exact fixed point
    np.testing.assert_allclose(model.initial.mean.numpy(), xstar, rtol=1e-12)
    eps = 1e-6
    for x0 in xs[:2]:
        fd = np.stack(
            [
                (_euler(x0 + eps * e, CUSTOM, dt) - _euler(x0 - eps * e, CUSTOM, dt)) / (2 * eps)
                for e in np.eye(4)
            ],
            axis=1,
        )
        jac = model.transition_jacobian(torch.tensor(x0, dtype=F64), None, 0).numpy()
        np.testing.assert_allclose(jac, fd, atol=1e-8)


def test_tank_jacobian_uses_zero_root_derivative_at_empty_and_negative_levels():
    """Docstring: ∂√h/∂h = 0 where h ≤ 0, so at x = (0, −1, 0, 4) only tank 4's outflow
    terms survive: J = I with J[3, 3] = 1 − dt (a4/A4) √(2g) / (2√4) and the coupling
    J[1, 3] = dt (a4/A2) √(2g) / (2√4) (numpy), all finite."""
    dt = 1.0
    model = FourTankModel(dt=dt, dtype=F64)
    p = FourTankParameters()
    x = torch.tensor([0.0, -1.0, 0.0, 4.0], dtype=F64)
    jac = model.transition_jacobian(x, None, 0).numpy()
    want = np.eye(4)
    want[3, 3] = 1.0 - dt * p.a[3] / p.A[3] * math.sqrt(2 * p.g) / (2 * math.sqrt(4.0))
    want[1, 3] = dt * p.a[3] / p.A[1] * math.sqrt(2 * p.g) / (2 * math.sqrt(4.0))
    assert np.isfinite(jac).all()
    np.testing.assert_allclose(jac, want, rtol=0, atol=1e-14)


def test_tank_jacobian_follows_coefficients_changed_in_place_and_their_gradients():
    """The Jacobian's ``(I, Mᵀ)`` are kept against the step coefficients' versions: a
    coefficient written in place (or replaced) is read at the next call, the Jacobian of
    a batch is each row's, and a coefficient that requires a gradient gets one through it."""
    dt = 0.5
    model = FourTankModel(dt=dt, dtype=F64)
    x = torch.tensor([[4.0, 9.0, 1.0, 16.0], [1.0, 1.0, 4.0, 0.25]], dtype=F64)
    d = 0.5 / x.sqrt()

    def want(diag, couple):
        j = torch.eye(4, dtype=F64).expand(2, 4, 4).clone()
        j[:, range(4), range(4)] += diag * d
        j[:, 0, 2], j[:, 1, 3] = couple[0] * d[:, 2], couple[1] * d[:, 3]
        return j

    torch.testing.assert_close(model.transition_jacobian(x, None, 0),
                               want(model.step_diag, model.step_couple), rtol=0, atol=0)  # fmt: skip
    torch.testing.assert_close(model.transition_jacobian(x[1], None, 0),
                               want(model.step_diag, model.step_couple)[1], rtol=0, atol=0)  # fmt: skip
    model.step_diag.mul_(2.0)  # in place: the cached terms are stale now
    model.step_couple.add_(0.125)
    torch.testing.assert_close(model.transition_jacobian(x, None, 0),
                               want(model.step_diag, model.step_couple), rtol=0, atol=0)  # fmt: skip
    model.step_couple = torch.tensor([0.3, -0.2, 0.0, 0.0], dtype=F64, requires_grad=True)
    jac = model.transition_jacobian(x, None, 0)
    torch.testing.assert_close(jac, want(model.step_diag, model.step_couple.detach()), rtol=0,
                               atol=0)  # fmt: skip
    (grad,) = torch.autograd.grad(jac[:, 0, 2].sum() + 2 * jac[:, 1, 3].sum(), model.step_couple)
    torch.testing.assert_close(grad, torch.stack([d[:, 2].sum(), 2 * d[:, 3].sum(),
                                                  torch.zeros((), dtype=F64),
                                                  torch.zeros((), dtype=F64)]))  # fmt: skip


def test_large_batches_of_different_shapes_and_changed_coefficients_step_correctly():
    """Inputs of ≥ 4096 entries go through cached full-size coefficients: two shapes in a
    row, and an in-place change of the step offset, must each give numpy's Euler step."""
    p = FourTankParameters()
    model = FourTankModel(dtype=F64)
    gen = torch.Generator().manual_seed(11)
    for shape in [(1100, 4), (1300, 4), (1100, 4), (5, 300, 4)]:
        x = 8.0 + 4.0 * torch.randn(*shape, generator=gen, dtype=F64)
        want = np.apply_along_axis(_euler, -1, x.numpy(), p, 1.0)
        got = model.transition(x, None, 0).numpy()
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    # doubling the inflow in place: the step must see it on the next same-shape call
    x = 8.0 + 4.0 * torch.randn(5, 300, 4, generator=gen, dtype=F64)
    with torch.no_grad():
        model.step_offset.mul_(2.0)
    (k1, k2), (g1, g2), (v1, v2) = p.k, p.gamma, p.v
    inflow = np.array(
        [
            g1 * k1 * v1 / p.A[0],
            g2 * k2 * v2 / p.A[1],
            (1 - g2) * k2 * v2 / p.A[2],
            (1 - g1) * k1 * v1 / p.A[3],
        ]
    )
    want = np.apply_along_axis(_euler, -1, x.numpy(), p, 1.0) + inflow
    np.testing.assert_allclose(model.transition(x, None, 0).numpy(), want, rtol=0, atol=1e-12)


def test_tank_observation_is_a_new_tensor_equal_to_x():
    """y = G x with G = I, returned as a new tensor (the comment's contract): writing into
    the measurement leaves the state untouched."""
    model = FourTankModel(dtype=F64)
    x = torch.tensor([[1.0, 2.0, 3.0, 4.0]], dtype=F64)
    y = model.observe(x, 0)
    np.testing.assert_array_equal(y.numpy(), [[1.0, 2.0, 3.0, 4.0]])
    y.add_(1.0)
    np.testing.assert_array_equal(x.numpy(), [[1.0, 2.0, 3.0, 4.0]])


def test_tank_covariances_and_their_validation():
    """p(x0) = N(x*, P0 I), Q = q I, R = diag(R) [docs/scenarios.md: 1e-2, 1e-4,
    1e-3 diag(1, 1, .5, .5)]; a custom P0 is the prior's; 3 diagonal entries are refused."""
    model = FourTankModel(dtype=F64)
    np.testing.assert_allclose(model.initial.cov.numpy(), 1e-2 * np.eye(4), rtol=1e-15)
    np.testing.assert_allclose(model.process_noise.cov.numpy(), 1e-4 * np.eye(4), rtol=1e-15)
    np.testing.assert_allclose(
        model.measurement_noise.cov.numpy(), 1e-3 * np.diag([1, 1, 0.5, 0.5]), rtol=1e-15
    )
    other = FourTankModel(Q=3e-4, P0=0.5, dtype=F64)
    np.testing.assert_allclose(other.initial.cov.numpy(), 0.5 * np.eye(4), rtol=1e-15)
    np.testing.assert_allclose(other.process_noise.cov.numpy(), 3e-4 * np.eye(4), rtol=1e-15)
    with pytest.raises(ValueError, match="4 diagonal entries"):
        FourTankModel(R=(1e-3, 1e-3, 1e-3), dtype=F64)
    with pytest.raises(ValueError, match="4 diagonal entries"):
        FourTankModel(P0=(1e-2,) * 5, dtype=F64)


def test_tank_scenarios_carry_the_papers_numbers_and_estimator_lists():
    """τ = 0.9, p_l = 0.5, ‖γ‖_min = 0.28, N = 100, R and R×5 (paper Sec. V); the scenario's
    P0 reaches its model; the Theorem-1 η estimator appears only where R differs from the
    design R, the noisy-γ̂ estimator only where γ̂ is not already noisy."""
    base = registry.get("four_tank_bias")
    assert (base.tau, base.p_l, base.gamma_min, base.num_particles) == (0.9, 0.5, 0.28, 100)
    assert base.R == (1e-3, 1e-3, 0.5e-3, 0.5e-3) and R_NOMINAL == base.R
    assert R_HIGH == (5e-3, 5e-3, 2.5e-3, 2.5e-3)
    assert abs(sum(R_NOMINAL) - 0.003) < 1e-15 and abs(sum(R_HIGH) - 0.015) < 1e-15
    assert (base.dt, base.P0, base.Q, base.steps) == (1.0, 1e-2, 1e-4, 100)
    high = registry.get("four_tank_bias_high_noise")
    noisy = registry.get("four_tank_bias_noisy_estimate")
    assert "modified_pf_eta_theorem1" not in base.estimators
    assert "modified_pf_eta_theorem1" in high.estimators
    assert "modified_pf_noisy_gamma" in base.estimators
    assert "modified_pf_noisy_gamma" not in noisy.estimators
    custom = FourTankScenario(name="p0_probe", P0=0.3, Q=2e-4, dt=0.5)
    m = custom.model()
    np.testing.assert_allclose(m.initial.cov.numpy(), 0.3 * np.eye(4), rtol=1e-15)
    np.testing.assert_allclose(m.process_noise.cov.numpy(), 2e-4 * np.eye(4), rtol=1e-15)
    assert m.dt == 0.5


def _eta_numpy(R_diag, q=1e-4, gamma_min=0.28):
    """η = ‖γ‖_min |σ − 1|, σ the singular value of G K nearest 1, K = Q(R + Q)⁻¹ (G = I)."""
    Q, R = q * np.eye(4), np.diag(R_diag)
    sv = np.linalg.svd(Q @ np.linalg.inv(R + Q), compute_uv=False)
    return gamma_min * abs(sv[np.argmin(abs(sv - 1))] - 1)


def test_high_noise_thresholds_keep_the_papers_eta_and_report_theorem1s():
    """High-noise case: the PoA η stays the paper's 0.233 = 0.28·5/6 (design R), while
    ``eta_theorem1`` is Theorem 1 for R×5: 0.28·25/26 = 0.2692 (numpy SVD)."""
    opts = registry.get("four_tank_bias_high_noise").estimator_options()
    assert opts["poa_eta"] == pytest.approx(0.28 * 5 / 6, rel=1e-12)
    assert opts["poa_eta"] == pytest.approx(_eta_numpy(R_NOMINAL), rel=1e-12)
    assert opts["eta_theorem1"] == pytest.approx(0.28 * 25 / 26, rel=1e-12)
    assert opts["eta_theorem1"] == pytest.approx(_eta_numpy(R_HIGH), rel=1e-12)
    assert opts["poa_zeta"] == pytest.approx(0.5)


# ----------------------------------------------------------------------------- robot


def test_robot_sensors_and_groups_are_the_papers_b7():
    """(B7) lidar positions in cm and the local groups {1, 2, 3}, {4, 5, 6} (App. B)."""
    b7 = [(-120, 0), (-60, -60), (60, -60), (-60, 60), (60, 60), (120, 0)]
    np.testing.assert_array_equal(np.array(SENSORS), np.array(b7, dtype=float))
    assert tuple(map(tuple, GROUPS)) == ((0, 1, 2), (3, 4, 5))
    np.testing.assert_array_equal(RobotModel().sensor_pos.numpy(), np.array(b7, dtype=float))


def _f(x, u, T):
    """(B2): x + T [u_p cos θ, u_p sin θ, u_r]."""
    return x + T * np.array([u[0] * np.cos(x[2]), u[0] * np.sin(x[2]), u[1]])


def _B(th, T):
    """(B4): T [[cos θ, 0], [sin θ, 0], [0, 1]]."""
    return T * np.array([[np.cos(th), 0.0], [np.sin(th), 0.0], [0.0, 1.0]])


def test_unicycle_at_a_non_unit_sampling_period():
    """T₀ = 0.5: f (B2), ∂f/∂x (central differences), B(k) (B4), and the fast path's
    (f, ∂f/∂x, ∂f/∂u) all equal numpy's evaluation of (B2)/(B4)."""
    T = 0.5
    model = RobotModel(dt=T)
    x, u = np.array([10.0, -5.0, 0.7]), np.array([6.0, 0.3])
    xt, ut = torch.tensor(x, dtype=F64), torch.tensor(u, dtype=F64)
    np.testing.assert_allclose(model.transition(xt, ut, 1).numpy(), _f(x, u, T), rtol=1e-14)
    eps = 1e-6
    fd = np.stack(
        [(_f(x + eps * e, u, T) - _f(x - eps * e, u, T)) / (2 * eps) for e in np.eye(3)], 1
    )
    np.testing.assert_allclose(model.transition_jacobian(xt, ut, 1).numpy(), fd, atol=1e-8)
    np.testing.assert_allclose(model.input_jacobian(xt, ut, 1).numpy(), _B(x[2], T), rtol=1e-14)
    xs = [torch.tensor([v], dtype=F64) for v in x]
    us = [torch.tensor([v], dtype=F64) for v in u]
    ys = [torch.zeros(1, dtype=F64)] * model.dim_y
    xp, F, B, _, _ = model.linearize_components(xs, us, ys, 1)
    as_np = np.vectorize(float)
    np.testing.assert_allclose(np.array([float(v) for v in xp]), _f(x, u, T), rtol=1e-14)
    np.testing.assert_allclose(as_np(np.array(F, dtype=object)), fd, atol=1e-8)
    np.testing.assert_allclose(as_np(np.array(B, dtype=object)), _B(x[2], T), rtol=1e-14)


def test_robot_group_keeps_every_setting_of_the_full_model():
    """``group(idx)`` is the same robot seen by the chosen lidars: dt, input noise, filter Q,
    per-sensor R, prior mean and covariance are those passed to the full model."""
    full = RobotModel(
        dt=0.5,
        input_var=(2.0, 3.0),
        filter_q=(4.0, 5.0, 6.0),
        meas_var=(7.0, 8.0),
        x0=(1.0, -2.0, 0.3),
        p0=(0.1, 0.2, 0.3),
    )
    sub = full.group([0, 2])
    assert sub.dt == 0.5 and sub.num_sensors == 2 and sub.dim_y == 4
    np.testing.assert_array_equal(sub.sensor_pos.numpy(), [[-120.0, 0.0], [60.0, -60.0]])
    np.testing.assert_allclose(sub.input_noise.cov.numpy(), np.diag([2.0, 3.0]))
    np.testing.assert_allclose(sub.process_noise.cov.numpy(), np.diag([4.0, 5.0, 6.0]))
    np.testing.assert_allclose(sub.measurement_noise.cov.numpy(), np.diag([7.0, 8.0, 7.0, 8.0]))
    np.testing.assert_allclose(sub.initial.mean.numpy(), [1.0, -2.0, 0.3])
    np.testing.assert_allclose(sub.initial.cov.numpy(), np.diag([0.1, 0.2, 0.3]))
    stacked = full.group(GROUPS)
    assert tuple(stacked.sensor_pos.shape) == (2, 3, 2) and stacked.dt == 0.5


def test_robot_default_covariances_are_the_papers():
    """R_i = diag(1 cm², 1 deg²) and the truth's input noise Q = diag(1 cm²/s², 1 deg²/s²)
    [P, App. B]; the filters' Q_x = diag(1, 1, 1 deg²) and P0 = diag(1 cm², 1 cm², 1 deg²)
    [DEF, docs/scenarios.md]; x(0) = 0 [P]."""
    m = RobotModel()
    np.testing.assert_allclose(
        m.measurement_noise.cov.numpy(), np.diag([1.0, DEG**2] * 6), rtol=1e-15
    )
    np.testing.assert_allclose(m.input_noise.cov.numpy(), np.diag([1.0, DEG**2]), rtol=1e-15)
    np.testing.assert_allclose(m.process_noise.cov.numpy(), np.diag([1, 1, DEG**2]), rtol=1e-15)
    np.testing.assert_allclose(m.initial.cov.numpy(), np.diag([1, 1, DEG**2]), rtol=1e-15)
    np.testing.assert_array_equal(m.initial.mean.numpy(), [0.0, 0.0, 0.0])


def test_robot_scenario_horizon_check_at_its_boundary_and_sensor_shape_check():
    """steps ≥ max(attack_from + 14, 41) (the docstring's rule) at both sides of each bound;
    sensors of shape [S, 3] are refused."""
    RobotScenario(name="h41", steps=41, attack_from=27)
    RobotScenario(name="h44", steps=44, attack_from=30)
    for steps, start in [(40, 20), (43, 30)]:
        with pytest.raises(ValueError, match="steps must be at least"):
            RobotScenario(name="short", steps=steps, attack_from=start)
    with pytest.raises(ValueError, match="sensors must have shape"):
        RobotModel(sensors=[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])


def test_tank_scenario_overrides_and_the_eq53_particle_condition():
    """``model(R=...)`` and ``attack(gamma_bar=...)`` use the override; the PoA threshold
    needs α = p_l N/(N − 1) < 1 (eq. 53) with the scenario's own N: p_l = 0.7, N = 3
    gives α = 1.05 (no PoA options: the PoA estimators are skipped), N = 4 gives
    α = 0.933 (ζ = p_l)."""
    base = registry.get("four_tank_bias")
    np.testing.assert_allclose(
        base.model(R=R_HIGH).measurement_noise.cov.numpy(), np.diag(R_HIGH), rtol=1e-15
    )
    assert base.attack((1.0, 2.0, 3.0, 4.0)).gamma_bar == (1.0, 2.0, 3.0, 4.0)
    assert base.attack().gamma_bar == (0.5,) * 4
    few = FourTankScenario(name="few", p_l=0.7, num_particles=3)
    assert not {"poa_eta", "poa_zeta", "eta_theorem1"} & set(few.estimator_options())
    with pytest.raises(ValueError, match="53"):
        poa_detector_for_scenario(few, few.system())
    opts = FourTankScenario(name="four", p_l=0.7, num_particles=4).estimator_options()
    assert opts["poa_zeta"] == pytest.approx(0.7, rel=1e-12)


@pytest.mark.parametrize("dt", [0.0, -1.0, math.inf, math.nan])
def test_tank_sampling_period_must_be_finite_and_positive(dt):
    """dt ≤ 0 or non-finite is refused at construction (the docstring: dt = inf would make
    every state NaN later)."""
    with pytest.raises(ValueError):
        FourTankModel(dt=dt, dtype=F64)


def test_robot_scenarios_carry_the_papers_and_the_documented_defaults():
    """docs/scenarios.md section 4: T₀ = 1 s, 100 MC runs, λ = 0.7, a = (20 cm/s, 20 deg/s) from
    k = 30 [P]; u = (5 cm/s, 5 deg/s), 100 steps, M = 100, S₀ = 10 I [DEF]; the 'draw'
    reading of eq. (5) [DEF, docs/scenarios.md]; the turning variant commands 10 deg/s and
    the training variant spreads u_r over 0-15 deg/s (their descriptions)."""
    from difffilter.fdi.mdpf import Reading

    s = registry.get("robot_actuator_attack")
    assert (s.dt, s.runs, s.steps, s.num_particles) == (1.0, 100, 100, 100)
    assert (s.forgetting, tuple(s.attack), s.attack_from) == (0.7, (20.0, 20.0), 30)
    assert (s.velocity, s.turn_rate_deg, s.attack_cov0) == (5.0, 5.0, 10.0)
    assert s.reading == Reading.DRAW
    turning = registry.get("robot_actuator_attack_turning")
    assert (turning.velocity, turning.turn_rate_deg) == (5.0, 10.0)
    u = turning.inputs(2, F64)
    np.testing.assert_allclose(u[..., 1].numpy(), np.full((2, 100), 10 * DEG), rtol=1e-15)
    assert tuple(registry.get("robot_actuator_attack_turn_rates").turn_rate_range_deg) == (0, 15)


@pytest.mark.parametrize("rows", [10, 2000])
def test_tank_step_of_a_float32_state_on_a_float64_model_promotes_at_every_batch_size(rows):
    """A float32 state through a float64 model takes torch's promotion (float64) whatever the
    batch: from 4,096 entries the cached coefficients had been cast to the state's dtype,
    so the result's dtype hung on the batch size (float64 for 10 rows, float32 for 2,000);
    every row's values are those of one row stepped alone, and within float32's rounding
    of the roots of the float64 step's."""
    m = FourTankModel(dtype=F64)
    x32 = torch.linspace(0.5, 20.0, rows * 4, dtype=torch.float32).reshape(rows, 4)
    out = m.transition(x32, None, 0)
    assert out.dtype == F64
    rows_alone = torch.cat([m.transition(x32[i : i + 1], None, 0) for i in (0, rows - 1)])
    torch.testing.assert_close(out[[0, rows - 1]], rows_alone, rtol=0, atol=0)
    torch.testing.assert_close(out, m.transition(x32.double(), None, 0), rtol=1e-7, atol=0)


@pytest.mark.parametrize(
    ("field", "value", "named"),
    [("gamma_bar", (1.0, 2.0), "gamma_bar must be 4 numbers"),
     ("tau", 5.0, "tau must lie in (0, 1)"), ("p_l", 2.0, "p_l must lie in [0, 1]"),
     ("false_alarm_rate", 1.5, "false_alarm_rate must lie in (0, 1)"),
     ("false_alarm_rate", 0.0, "false_alarm_rate must lie in (0, 1)"),
     ("gamma_hat_noise_var", -1.0, "gamma_hat_noise_var must be a finite number >= 0"),
     ("cusum_bias", 0.0, "cusum_bias must be a finite number > 0"),
     ("R", (0.1, 0.1, 0.1), "R must have 4 diagonal entries; got 3"),
     ("R", (-0.1, 0.1, 0.1, 0.1), "R must be positive definite"),
     ("Q", -1e-4, "Q must be positive definite"), ("P0", 0.0, "P0 must be positive definite"),
     ("dt", 0.0, "dt must be a finite number > 0")],
)  # fmt: skip
def test_four_tank_scenario_names_a_bad_attack_or_detector_field_at_build(field, value, named):
    """A four-tank scenario refuses, when built, an attack, detector or plant field its study
    would have failed on deep inside (or, for a two-entry γ̄, a rate of 1.5 or a negative γ̂
    noise variance, been accepted until then: a trial; a 3-entry R or P0 = 0 was refused at
    the study's first ``model()``)."""
    from difffilter.models.four_tank import FourTankScenario

    with pytest.raises(ValueError, match=re.escape(named)):
        FourTankScenario(name="bad", **{field: value})
    FourTankScenario(name="good")  # the defaults build
