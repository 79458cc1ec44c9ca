"""Independent truths for model lines a second mutation review found unpinned (each check
passes here and failed on its mutant): the models' Jacobians, the tracking Q and glint
noise, the deception density and the robot's truth noise."""

from __future__ import annotations

import math

import numpy as np
import torch


def test_every_models_closed_form_jacobians_equal_autodiff_of_its_own_functions():
    """The tracking (eq. 18), four-tank and robot models' hand-written Jacobians against
    autodiff of their own transition and observation (a bearing row's sign, the four-tank's
    ∂√h/∂h and a coupling entry's place were unpinned)."""
    from difffilter.models.four_tank import FourTankModel
    from difffilter.models.robot import RobotModel
    from difffilter.models.tracking import TrackingModel
    from difffilter.ssm import batched_jacobian

    f64 = torch.float64
    cases = [
        (TrackingModel(), torch.tensor([[30.0, 0.3, 25.0, -0.2], [-40.0, 1.0, 60.0, 0.5]], dtype=f64), None),
        (FourTankModel(dtype=f64), torch.tensor([[12.0, 13.0, 1.5, 1.4], [8.0, 9.0, 3.0, 2.0]], dtype=f64), None),
        (RobotModel(), torch.tensor([[10.0, -20.0, 0.7], [-30.0, 40.0, -2.0]], dtype=f64),
         torch.tensor([[5.0, 0.3], [4.0, -0.1]], dtype=f64)),
    ]  # fmt: skip
    for model, x, u in cases:
        name = type(model).__name__
        auto_f = batched_jacobian(lambda xi, ui, m=model: m.transition(xi, ui, 0), x, u)
        auto_h = batched_jacobian(lambda xi, m=model: m.observe(xi, 1), x)
        torch.testing.assert_close(
            model.transition_jacobian(x, u, 0), auto_f, rtol=1e-9, atol=1e-12, msg=name
        )
        torch.testing.assert_close(
            model.observation_jacobian(x, 1), auto_h, rtol=1e-9, atol=1e-12, msg=name
        )


def test_the_tracking_process_noise_is_the_papers_q():
    """σ²[[T³/3, T²/2], [T²/2, T]] per axis (below eq. 17), in process_cov and in the draws of
    both sampling paths."""
    from difffilter.models.tracking import TrackingModel

    for T in (1.0, 0.5):
        m = TrackingModel(dt=T)
        s2 = 0.055**2
        blk = s2 * np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]])
        ref = np.block([[blk, np.zeros((2, 2))], [np.zeros((2, 2)), blk]])
        e = abs(m.process_cov(0).numpy() - ref).max()
        x = torch.zeros(4, 20000, 4, dtype=torch.float64)  # particle path [B, N, 4]
        emp = np.cov(
            m.sample_transition(x, None, 0, torch.Generator().manual_seed(0))
            .reshape(-1, 4)
            .numpy()
            .T
        )
        x1 = torch.zeros(80000, 4, dtype=torch.float64)  # one-particle path [..., 4]
        emp1 = np.cov(m.sample_transition(x1, None, 0, torch.Generator().manual_seed(1)).numpy().T)
        r1 = abs(emp - ref).max() / abs(ref).max()
        r2 = abs(emp1 - ref).max() / abs(ref).max()
        assert e < 1e-15, f"process_cov at dt={T}"
        assert r1 < 0.05, f"particle-path draws at dt={T}: {r1:.3f}"
        assert r2 < 0.05, f"one-particle draws at dt={T}: {r2:.3f}"


def test_glint_noise_wrapping_and_the_deception_density():
    """The glint mixture's covariance (1 − κ)Σ₁ + κΣ₂ (eq. 19; the filters' R), angles wrapped
    to (−π, π], and the deception term log(η̄ · 1/volume)."""
    from difffilter.models.tracking import PerSensorDeception, TrackingModel, wrap_angle

    m = TrackingModel()
    s1 = np.array([4.0, (math.pi / 180) ** 2])
    s2 = np.array([25.0, (math.pi / 90) ** 2])
    kap = 0.2
    ref = (1 - kap) * s1 + kap * s2
    x = m.measurement_noise.sample((100000,), torch.Generator().manual_seed(0)).numpy()
    emp = x.reshape(-1, 4, 2).var(axis=(0, 1))
    cov = np.diag(m.measurement_noise.cov.numpy())[:2]
    assert np.allclose(emp, ref, rtol=0.03), (emp, ref)
    assert np.allclose(cov, ref, rtol=1e-12), (cov, ref)
    w = wrap_angle(torch.tensor([math.pi, -math.pi, 3 * math.pi, 0.5], dtype=torch.float64)).numpy()
    assert np.allclose(w, [math.pi, math.pi, math.pi, 0.5]), w
    low, high = (-10.0, -math.pi / 2), (80.0, math.pi / 2)
    d = PerSensorDeception(0.1, low, high, 4)
    y = m.observe(torch.tensor([30.0, 0.3, 25.0, 0.3], dtype=torch.float64), 1)
    _, att, _ = d.components(m, y, torch.zeros(1, 5, 4, dtype=torch.float64), 1, None)
    refa = math.log(0.1) - math.log(90.0 * math.pi)
    # the box is stored in float32 (1.7e-7 off)
    assert abs(float(att[0, 0, 0]) - refa) < 1e-6, (float(att[0, 0, 0]), refa)


def test_the_robot_truth_noise_is_b_n():
    """w = B(θ) n, n ~ N(0, diag(1, deg²)) (B4): the empirical covariance of the draws."""
    from difffilter.models.robot import RobotModel

    m = RobotModel(dt=0.5)
    th = 1.0
    x = torch.tensor([3.0, -4.0, th], dtype=torch.float64).expand(100000, 3)
    u = torch.tensor([5.0, 0.1], dtype=torch.float64).expand(100000, 2)
    w = (
        m.sample_transition(x, u, 0, torch.Generator().manual_seed(0)) - m.transition(x, u, 0)
    ).numpy()
    B = 0.5 * np.array([[math.cos(th), 0], [math.sin(th), 0], [0, 1]])
    ref = B @ np.diag([1.0, (math.pi / 180) ** 2]) @ B.T
    emp = np.cov(w.T)
    err = abs(emp - ref).max() / abs(ref).max()
    assert err < 0.03
