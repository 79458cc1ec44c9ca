"""Hand checks of the filters' steps on cases the wider tests do not build.

One UKF and one EKF step on a 2-D nonlinear model with non-diagonal covariances against
numpy; the Kalman proposal against the importance-sampling identity; the particle filter's
masked innovation covariance; the MDPF's information form against its covariance form
under a mask; the CUSUM's default drift; and the learned PF estimator's resampling rule.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from reference import scaled_sigma_points, scaled_sigma_weights

from difffilter.ssm import LinearGaussianModel, NonlinearGaussianModel

F64 = torch.float64
CHECKPOINTS = Path(__file__).resolve().parent.parent / "checkpoints"


# ---------------------------------------------------------------- UKF and EKF by hand


def _f(x):
    return torch.stack(
        [x[..., 0] + 0.3 * torch.sin(x[..., 1]), 0.9 * x[..., 1] + 0.2 * x[..., 0] ** 2], -1
    )


def _h(x):
    return torch.stack([x[..., 0] ** 2 + x[..., 1], torch.atan(x[..., 1])], -1)


_Q = [[0.2, 0.05], [0.05, 0.1]]
_R = [[0.3, 0.0], [0.0, 0.05]]
_M0, _P0, _Y = [0.5, -0.4], [[0.5, 0.2], [0.2, 0.3]], [1.1, -0.2]


def _one_step_state():
    from difffilter.results import GaussianState

    t = lambda v: torch.tensor(v, dtype=F64)  # noqa: E731
    model = NonlinearGaussianModel(_f, _h, t(_Q), t(_R), t(_M0), t(_P0))
    return GaussianState(t(_M0), t(_P0), 0, model), t(_Y)


def _numpy(g):
    return lambda x: g(torch.as_tensor(x)).numpy()


def _ukf_by_hand(alpha, beta, kappa):
    """Scaled sigma points, their weights, the predicted moments, then K = P_xy S⁻¹ and
    P = P⁻ − K S Kᵀ (the textbook posterior)."""
    f, h, n = _numpy(_f), _numpy(_h), 2
    lam, wm, wc = scaled_sigma_weights(n, alpha, beta, kappa)

    def points(m, P):
        return scaled_sigma_points(m, P, lam)

    def cov(A, a, B, b):
        return sum(wc[i] * np.outer(A[i] - a, B[i] - b) for i in range(2 * n + 1))

    FX = np.array([f(x) for x in points(np.array(_M0), np.array(_P0))])
    mp = wm @ FX
    Pp = cov(FX, mp, FX, mp) + np.array(_Q)
    Xp = points(mp, Pp)
    Y = np.array([h(x) for x in Xp])
    yh = wm @ Y
    S = cov(Y, yh, Y, yh) + np.array(_R)
    K = cov(Xp, mp, Y, yh) @ np.linalg.inv(S)
    return mp + K @ (np.array(_Y) - yh), Pp - K @ S @ K.T


def _ekf_by_hand():
    """F = ∂f/∂x at the current mean, H = ∂h/∂x at the predicted mean (central differences)."""
    f, h = _numpy(_f), _numpy(_h)

    def jacobian(g, x, e=1e-6):
        return np.stack(
            [(g(x + e * np.eye(2)[i]) - g(x - e * np.eye(2)[i])) / (2 * e) for i in range(2)], -1
        )

    m0 = np.array(_M0)
    F = jacobian(f, m0)
    mp = f(m0)
    Pp = F @ np.array(_P0) @ F.T + np.array(_Q)
    H = jacobian(h, mp)
    S = H @ Pp @ H.T + np.array(_R)
    K = Pp @ H.T @ np.linalg.inv(S)
    return mp + K @ (np.array(_Y) - h(mp)), Pp - K @ S @ K.T


@pytest.mark.parametrize("alpha, beta, kappa", [(1.0, 2.0, 0.0), (0.5, 2.0, 1.0)])
def test_one_ukf_step_by_hand(alpha, beta, kappa):
    from difffilter.extended import SigmaPoints, UnscentedKalmanFilter

    state, y = _one_step_state()
    _, out = UnscentedKalmanFilter(SigmaPoints(alpha, beta, kappa)).step(state, y)
    mean, cov = _ukf_by_hand(alpha, beta, kappa)
    np.testing.assert_allclose(out.mean.numpy(), mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.cov.numpy(), cov, rtol=0, atol=1e-9)


def test_one_ekf_step_by_hand():
    from difffilter.extended import ExtendedKalmanFilter

    state, y = _one_step_state()
    _, out = ExtendedKalmanFilter().step(state, y)
    mean, cov = _ekf_by_hand()
    np.testing.assert_allclose(out.mean.numpy(), mean, rtol=0, atol=1e-7)
    np.testing.assert_allclose(out.cov.numpy(), cov, rtol=0, atol=1e-7)


# ---------------------------------------------------------------- particle filter


def _scalar_model():
    one = torch.eye(1, dtype=F64)
    return LinearGaussianModel(one, one, one, 0.1 * one, torch.zeros(1, dtype=F64), one)


@pytest.mark.parametrize("defensive", [0.3, 0.6])
def test_kalman_proposal_weights_are_importance_weights_of_the_prior(defensive):
    """E_q[(p/q) g] = E_p[g] for the prior p = N(f(x), Q) = N(0, 1) and g = 1, x, x²: the
    drawn mixture and the density in the correction must agree (400k draws)."""
    from difffilter.particle import KalmanProposal

    x_prev = torch.zeros(400_000, 1, dtype=F64)
    y = torch.tensor([3.0], dtype=F64)
    proposal = KalmanProposal(defensive=defensive)
    new, correction = proposal(
        _scalar_model(), x_prev, None, y, 0, None, torch.Generator().manual_seed(1)
    )
    w, x = correction.exp(), new[:, 0]
    assert float(w.mean()) == pytest.approx(1.0, abs=0.03)
    assert float((w * x).mean()) == pytest.approx(0.0, abs=0.03)
    assert float((w * x**2).mean()) == pytest.approx(1.0, abs=0.06)


def test_kalman_proposal_with_nothing_received_is_the_prior():
    from difffilter.particle import KalmanProposal

    x_prev = torch.zeros(400_000, 1, dtype=F64)
    mask = torch.zeros(400_000, 1, dtype=torch.bool)
    y = torch.tensor([3.0], dtype=F64)
    new, correction = KalmanProposal()(
        _scalar_model(), x_prev, None, y, 0, mask, torch.Generator().manual_seed(1)
    )
    assert float(new[:, 0].var()) == pytest.approx(1.0, abs=0.02)
    assert float(correction.abs().max()) < 1e-9


def test_masked_innovation_covariance_keeps_the_received_block_and_no_cross_terms():
    """The received block equals the unmasked covariance on the same draws; a received and an
    unreceived entry are uncorrelated (the unreceived one is no measurement)."""
    from difffilter.particle import particle_init, particle_step

    H = torch.tensor([[1.0, 0.5, 0.0], [0.3, 1.0, 0.2], [0.0, 0.4, 1.0]], dtype=F64)
    Q = torch.tensor([[1.0, 0.6, 0.2], [0.6, 1.0, 0.5], [0.2, 0.5, 1.0]], dtype=F64)
    eye = torch.eye(3, dtype=F64)
    model = LinearGaussianModel(eye, H, Q, 0.1 * eye, torch.zeros(3, dtype=F64), eye)
    state = particle_init(model, 500, (2,), torch.Generator().manual_seed(0))
    y = torch.tensor([[0.3, -0.2, 0.5], [1.0, 0.1, -0.4]], dtype=F64)
    mask = torch.tensor([[True, False, True], [False, True, True]])
    full, masked = (
        particle_step(model, state, y, mask=m, generator=torch.Generator().manual_seed(1))[1].innovation_cov
        for m in (None, mask)
    )  # fmt: skip
    for b in range(2):
        received = mask[b]
        both = received[:, None] & received[None, :]
        cross = received[:, None] ^ received[None, :]
        torch.testing.assert_close(masked[b][both], full[b][both], rtol=0, atol=1e-12)
        assert float(masked[b][cross].abs().max()) < 1e-12


# ---------------------------------------------------------------- MDPF, CUSUM, learned PF


def test_mdpf_information_form_equals_the_covariance_form_under_a_mask():
    """log N(ε; 0, Σ) over the received entries (A8): the same number in both forms."""
    from difffilter.fdi.mdpf import (
        AdaptiveKalmanProposal,
        adaptive_particle_init,
        adaptive_particle_step,
    )
    from difffilter.models.registry import get
    from difffilter.models.robot import GROUPS, RobotModel
    from difffilter.models.robot_estimators import group_measurements

    gens = {"plant": torch.Generator().manual_seed(0), "attack": None}
    traj = get("robot_actuator_attack").simulate(2, gens)
    model = RobotModel().group(GROUPS)
    ys, us = group_measurements(traj.y_recv), traj.us.expand(2, -1, -1, -1)
    g = torch.Generator().manual_seed(2)
    state = adaptive_particle_init(model, 6, (2, 2), g)
    for t in range(4):
        state, _ = adaptive_particle_step(model, state, ys[:, :, t], us[:, :, t], generator=g)
    k = state.k
    y, u = ys[:, :, k], us[:, :, k]
    mask = torch.ones(y.shape, dtype=torch.bool)
    mask[0, 0, 0] = mask[0, 1, -1] = mask[0, 1, 0] = False  # one and two entries missing
    info, covariance = (
        AdaptiveKalmanProposal(model, 0.7, "copy", form)(model, state.particles, u, y, k, mask, None)[1]
        for form in ("information", "covariance")
    )  # fmt: skip
    torch.testing.assert_close(info, covariance, rtol=0, atol=1e-8)


@pytest.mark.parametrize("dy", [1, 2])
def test_cusum_default_drift_is_dy_plus_two(dy):
    from difffilter.fdi.gated import cusum_detector_for

    eye = torch.eye(2, dtype=F64)
    model = LinearGaussianModel(0.9 * eye, eye[:dy], 0.1 * eye, 0.2 * torch.eye(dy, dtype=F64),
                                torch.zeros(2, dtype=F64), eye)  # fmt: skip
    detector = cusum_detector_for(model, false_alarm_rate=0.05, runs=20, steps=30,
                                  generator=torch.Generator().manual_seed(0))  # fmt: skip
    assert detector.bias == dy + 2.0


def test_learned_pf_estimators_resample_at_every_step():
    """``compose``'s default, as ``load_estimator``'s: ``ess_threshold = 1``."""
    from difffilter.attack import Channel
    from difffilter.models.learned_estimator import compose, load_estimator
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    seen = 0
    for path in sorted(CHECKPOINTS.glob("*.ckpt")):
        net, card = load_estimator_checkpoint(path, dtype=F64)
        if card.filter != "pf" or Channel(card.channel) is Channel.REPLACEMENT:
            continue
        seen += 1
        for estimator in (compose(net, card), load_estimator(path).estimator):
            assert getattr(estimator, "inner", estimator).ess_threshold == 1.0, path.name
    assert seen > 0


@pytest.mark.parametrize(
    "entry, checkpoint",
    [("pf_nn_ekf", "four_tank_nn_grad.ckpt"), ("pf_nn_grad", "four_tank_nn_ekf.ckpt")],
)
def test_a_checkpoint_runs_only_as_the_entry_of_its_trainer(entry, checkpoint):
    """Same family and filter, another trainer: skipped with the reason, not run as the other."""
    from difffilter.models import estimators, registry
    from difffilter.models.estimators import SkipEstimator, SuiteContext
    from difffilter.models.streams import Streams

    scenario = registry.get("four_tank_bias")
    ctx = SuiteContext(
        scenario, scenario.system(), 2, Streams(0), checkpoint=CHECKPOINTS / checkpoint
    )
    with pytest.raises(SkipEstimator, match="by (grad|ekf)"):
        estimators.get(entry).factory(ctx)
    assert ctx.checkpoint_users == []
