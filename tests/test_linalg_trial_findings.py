"""Findings of a trial of difffilter.linalg and the result containers."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.estimator import output_of
from difffilter.gaussian import kalman_gain
from difffilter.linalg import safe_cholesky
from difffilter.noise import Gaussian, GaussianMixture

D = torch.float64


def test_a_jittered_factors_gradient_is_the_jittered_matrixs():
    """A member that needed jitter had its failed first factor merged by ``torch.where``,
    whose backward sent 0·∞ = NaN into the matrix's gradient; now the gradient of
    ``cholesky(M + εI)`` for the ε the ladder chose, and the other members' their own."""
    singular = torch.tensor([[1.0, 1.0], [1.0, 1.0]], dtype=D)
    regular = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=D)
    batch = torch.stack([singular, regular]).requires_grad_()
    factor = safe_cholesky(batch, name="M")
    (grad,) = torch.autograd.grad(factor.sum(), batch)
    assert bool(torch.isfinite(grad).all())
    for i, eps in ((0, 1e-14 * 1.0), (1, 0.0)):  # (the singular one's ε: the first rung)
        member = (batch[i].detach() + eps * torch.eye(2, dtype=D)).requires_grad_()
        (expected,) = torch.autograd.grad(torch.linalg.cholesky(member).sum(), member)
        torch.testing.assert_close(grad[i], expected, rtol=1e-6, atol=0)
    torch.testing.assert_close(factor[1], torch.linalg.cholesky(regular), rtol=0, atol=0)


def test_an_infinite_variance_is_a_breakdown_as_nan_is():
    """``cholesky_ex`` factorises diag(∞, 1, 2) without an error (√∞ on the diagonal): a
    covariance overflowed on its diagonal alone had passed, where NaN is refused."""
    with pytest.raises(
        df.NumericalBreakdown, match="P must be symmetric positive definite and finite"
    ):
        safe_cholesky(torch.diag(torch.tensor([float("inf"), 1.0, 2.0], dtype=D)), name="P")


@pytest.mark.parametrize("order", [(0, 1), (1, 0)])
def test_an_infinite_variance_beside_a_member_that_needs_jitter_is_a_breakdown(order):
    """The finiteness check ran only where every member factorised at once: beside a
    rank-one member (jitter needed) the overflowed member's jitter scale was ∞, 0·∞ = NaN,
    and torch's bare ``_LinAlgError`` (no ``NumericalBreakdown``, which the suites catch)
    came out of ``safe_cholesky`` and ``kalman_gain``."""
    overflowed = torch.diag(torch.tensor([float("inf"), 1.0], dtype=D))
    rank_one = torch.ones(2, 2, dtype=D)
    batch = torch.stack([(overflowed, rank_one)[i] for i in order])
    where = f"at batch index \\({order.index(0)},\\)"
    with pytest.raises(df.NumericalBreakdown, match=f"finite {where}: it holds NaN or inf"):
        safe_cholesky(batch, name="S")
    with pytest.raises(df.NumericalBreakdown, match="innovation covariance"):
        kalman_gain(torch.ones(2, 3, 2, dtype=D), batch)


def test_output_of_keeps_the_count_of_skipped_measurements():
    """``output_of`` (the EstimatorOutput ``open_loop`` would give) dropped
    ``nonfinite_skipped`` of a ``nonfinite="skip"`` run."""
    eye = torch.eye(2, dtype=D)
    model = df.LinearGaussianModel(eye, eye, 0.1 * eye, eye, torch.zeros(2, dtype=D), eye)
    _, ys, _ = model.simulate(4, (3,), generator=torch.Generator().manual_seed(0))
    ys[0, 1, 0] = float("nan")
    ys[2, 3, 1] = float("inf")
    result = df.kalman_filter(model, ys, nonfinite="skip")
    assert torch.equal(output_of(result).extras["nonfinite_skipped"], result.nonfinite_skipped)
    assert result.nonfinite_skipped.tolist() == [1, 0, 1]


def _scipy_logpdf(r, cov):
    from scipy.stats import multivariate_normal

    return float(multivariate_normal(mean=[0.0] * len(r), cov=cov).logpdf(r))


def test_a_masked_density_ignores_what_a_lost_entry_holds():
    """A second trial: ``residual · mask`` made a NaN or ∞ where nothing was received (as
    lost values are stored) a NaN density and gradient. Truth: scipy on the received entries."""
    cov = torch.tensor([[2.0, 0.3, 0.1], [0.3, 1.0, 0.2], [0.1, 0.2, 1.5]], dtype=D)
    mask = torch.tensor([True, False, True])
    want = _scipy_logpdf([0.4, -0.7], cov[[0, 2]][:, [0, 2]].numpy())
    for lost in (float("nan"), float("inf")):
        y = torch.tensor([0.4, lost, -0.7], dtype=D, requires_grad=True)
        for noise in (
            Gaussian(0, cov),
            GaussianMixture([1.0], torch.zeros(1, 3, dtype=D), cov[None]),
        ):
            got = noise.log_prob(y, mask)
            assert float(got.detach()) == pytest.approx(want, rel=1e-13)
            (grad,) = torch.autograd.grad(got, y)
            assert grad.isfinite().all() and float(grad[1]) == 0.0


def test_a_densitys_mask_and_value_are_checked():
    """A second trial: an all-True ``[N, 1]`` mask counted one received entry of three (the
    density (d − 1)/2 · log 2π off), an integer mask holding 2 weighed its entry twice, and a
    ``[N, 1]`` value broadcast to (v, v, v) against a non-zero mean."""
    g = Gaussian(torch.tensor([0.1, 0.2, 0.3], dtype=D), torch.eye(3, dtype=D))
    y = torch.zeros(4, 3, dtype=D)
    with pytest.raises(ValueError, match=r"mask must be bool \[\.\.\., 3\].*\(4, 1\)"):
        g.log_prob(y, torch.ones(4, 1, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"mask must be bool.*torch.int64"):
        g.log_prob(y, torch.tensor([1, 2, 0]).expand(4, 3))
    with pytest.raises(ValueError, match=r"value must be \[\.\.\., 3\]; got \(4, 1\)"):
        g.log_prob(torch.zeros(4, 1, dtype=D))
    assert g.log_prob(y, torch.ones(4, 3, dtype=torch.bool)).shape == (4,)


def test_a_correlation_written_in_one_triangle_is_refused():
    """A second trial: variances 1e6, 1e-2, 1e-2 and a correlation of 0.9 written below the
    diagonal only passed (9e-9 of the largest entry), and sampling (the lower triangle: 0.9)
    and the filters (symmetrised: 0.45) then used two noise models."""
    cov = torch.diag(torch.tensor([1e6, 1e-2, 1e-2], dtype=D))
    cov[2, 1] = 0.009
    with pytest.raises(ValueError, match=r"entries \(1, 2\) and \(2, 1\) differ by 0\.9 of"):
        Gaussian(0, cov)
    cov[1, 2] = 0.009 * (1 + 1e-9)  # round-off: taken
    Gaussian(0, cov)
    psd = torch.diag(torch.tensor([1.0, 0.0], dtype=D))  # a zero variance has no scale: taken
    Gaussian(0, psd + 1e-12 * torch.eye(2, dtype=D))


def _redundant_pairs(unit, dtype):
    """Two redundant pairs of precise sensors on a 2-state prior, in a measurement unit:
    ``S`` of a received pair is singular in float32 up to R = 1e-9·unit², so it is jittered."""
    P = unit**2 * torch.eye(2, dtype=dtype)
    H = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0]], dtype=dtype)
    R = unit**2 * 1e-9 * torch.eye(4, dtype=dtype)
    r = unit * torch.tensor([1.0, 1.0, 0.3, 0.3], dtype=dtype)
    return torch.zeros(2, dtype=dtype), P, r, H, R


def _closed_form(m0, P, r, H, R):
    """``m⁺ = m⁻ + K r``, ``P⁺ = P − K H P`` with ``K = P Hᵀ (H P Hᵀ + R)⁻¹`` in float64."""
    m0, P, r, H, R = (t.double() for t in (m0, P, r, H, R))
    S = H @ P @ H.T + R
    K = torch.linalg.solve(S, H @ P).T
    return m0 + K @ r, P - K @ H @ P


@pytest.mark.parametrize("unit", [1.0, 1e-3])
def test_a_masked_update_is_the_received_sub_models_in_any_unit(unit):
    """The jitter of a masked ``S`` was scaled by the mean diagonal over all entries, the
    lost entries' unit placeholders too: in units with variances near 1e-6 it was 5e5
    times the received sub-model's own (the mean 20 % off, P⁺ 8e7 times too large, 6.6
    nats). Now the masked update is the sub-model's (``H[:2]``, ``R[:2, :2]``) in both units,
    and its mean and P⁺ those of the float64 closed form."""
    m0, P, r, H, R = _redundant_pairs(unit, torch.float32)
    mask = torch.tensor([True, True, False, False])
    masked = df.gaussian.linear_update(m0, P, r, H, R, mask)
    sub = df.gaussian.linear_update(m0, P, r[:2], H[:2], R[:2, :2])
    for got, want in zip((masked[0], masked[1], masked[4]), (sub[0], sub[1], sub[4])):
        torch.testing.assert_close(got, want, rtol=1e-6, atol=0)
    mean, cov = _closed_form(m0, P, r[:2], H[:2], R[:2, :2])
    torch.testing.assert_close(masked[0].double() / unit, mean / unit, rtol=0, atol=1e-5)
    torch.testing.assert_close(masked[1].double() / unit**2, cov / unit**2, rtol=1e-2, atol=0)


def test_each_runs_mask_gets_its_own_received_entries_jitter():
    """A batch of runs, each with its own mask (one pair, the other, none, all): each run's
    update is its received sub-model's (float32, variances near 1e-6; its mean and P⁺ those
    of the float64 closed form), and a run that
    received nothing keeps its prior with a zero log-likelihood."""
    unit = 1e-3
    m0, P, r, H, R = _redundant_pairs(unit, torch.float32)
    masks = torch.tensor(
        [[True, True, False, False], [False, False, True, True], [False] * 4, [True] * 4]
    )
    mean, cov, _, _, log_lik = df.gaussian.linear_update(m0, P, r, H, R, masks)
    for i, keep in enumerate(masks):
        if not bool(keep.any()):
            torch.testing.assert_close(mean[i], m0, rtol=0, atol=0)
            torch.testing.assert_close(cov[i], P, rtol=0, atol=0)
            assert float(log_lik[i]) == 0.0
            continue
        idx = keep.nonzero().squeeze(-1)
        sub = df.gaussian.linear_update(m0, P, r[idx], H[idx], R[idx][:, idx])
        torch.testing.assert_close(mean[i], sub[0], rtol=1e-6, atol=0)
        # P⁺'s received direction has a variance 2e9 times below the prior's (5e-16 beside
        # 1e-6), under float32's round-off of P (ε·‖P‖ ≈ 1.2e-13): the kernels of one CPU
        # give 5.0e-16, of another 1.0e-15 or 1.5e-15, all float32's zero there. So P⁺ is
        # compared to within 0.1·ε·‖P‖ (the placeholders' jitter had made it 4e-8)
        tol = {"rtol": 1e-2, "atol": 1e-8 * unit**2}
        torch.testing.assert_close(cov[i], sub[1], **tol)
        want_mean, want_cov = _closed_form(m0, P, r[idx], H[idx], R[idx][:, idx])
        torch.testing.assert_close(mean[i].double() / unit, want_mean / unit, rtol=0, atol=1e-5)
        torch.testing.assert_close(cov[i].double(), want_cov, **tol)
        # The log-likelihood reads S's smallest pivot: 2e-15 exactly, under float32's
        # round-off of S (ε·‖S‖ ≈ 2.4e-13). Where a factorisation fails it is jittered to
        # about 2e-12 (1e-6 of the received diagonal); where round-off lets one pass (the
        # 4×4 of run 1 with MKL's AVX2 kernels: 1.46 nats above its 2×2) it keeps a pivot
        # between. So the two agree to ½·log(2e-12 / 2e-15) ≈ 3.5 nats; the placeholders'
        # jitter had made them 6.6 apart.
        torch.testing.assert_close(log_lik[i], sub[4], rtol=0, atol=3.5)


def test_one_jittered_matrix_shared_by_runs_with_masks_of_their_own():
    """``safe_cholesky(S [d, d], mask [B, d])`` where ``S`` needs jitter: one factor per run,
    each with its received entries' jitter, as ``S`` expanded to the runs by hand gives (a
    bare expand error before; the public ``kalman_gain`` and ``innovation_log_prob`` took
    the same path). Where ``S`` factorises it stays one shared factor."""
    from difffilter.gaussian import innovation_log_prob, kalman_gain
    from difffilter.linalg import masked_measurement

    u = 1e-3  # redundant precise pairs: S is singular on the received pair in float32
    H = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0]])
    P, R = u**2 * torch.eye(2), u**2 * 1e-9 * torch.eye(4)
    received = torch.tensor([True, True, False, False])
    masks = received.expand(3, 4)
    _, Hm, Rm, count = masked_measurement(None, H, R, received)
    S = Hm @ P @ Hm.T + Rm
    assert torch.linalg.cholesky_ex(S).info.item() != 0  # the jitter branch
    by_hand = safe_cholesky(S.expand(3, 4, 4), mask=masks)
    assert torch.equal(safe_cholesky(S, mask=masks), by_hand)
    assert safe_cholesky(S + torch.eye(4), mask=masks).shape == (4, 4)  # no jitter: shared
    cross = P @ Hm.T
    for shared, expanded in zip(kalman_gain(cross, S, masks),
                                kalman_gain(cross, S.expand(3, 4, 4), masks)):  # fmt: skip
        assert torch.equal(shared, expanded)
    r = torch.zeros(3, 4)
    assert torch.equal(innovation_log_prob(r, S, count, masks),
                       innovation_log_prob(r, S.expand(3, 4, 4), count, masks))  # fmt: skip


def test_a_lost_entry_holding_nan_leaves_the_kf_and_ekf_update_halves_alone():
    """``update`` and ``innovation`` called directly (the halves wrappers recombine) with a
    lost entry stored as NaN: the received sub-model's float64 update (``r · mask`` had kept
    the NaN: mean, innovation and log-likelihood NaN; the step API, which cleans ``y``, and
    the UKF's update were right)."""
    d = torch.float64
    H = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], dtype=d)
    Q, R, P0 = 0.1 * torch.eye(2, dtype=d), 0.5 * torch.eye(3, dtype=d), torch.eye(2, dtype=d)
    model = df.LinearGaussianModel(torch.eye(2, dtype=d), H, Q, R, torch.zeros(2, dtype=d), P0)
    y = torch.tensor([[0.3, float("nan"), 0.7]], dtype=d)
    mask = torch.tensor([[True, False, True]])
    keep = torch.tensor([0, 2])
    Pm, Hs, Rs, ys = P0 + Q, H[keep], R[keep][:, keep], y[0, keep]
    S = Hs @ Pm @ Hs.T + Rs
    mean = Pm @ Hs.T @ torch.linalg.solve(S, ys)
    ll = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=d), S).log_prob(ys)
    for est in (df.KalmanFilter(), df.ExtendedKalmanFilter(), df.UnscentedKalmanFilter()):
        carry = est.init(model, (1,))
        pred = est.predict(carry, None)
        _, out = est.update(carry, pred, y, mask)
        nu, _, ell = est.innovation(carry, pred, y, mask)
        torch.testing.assert_close(out.mean[0], mean, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(out.log_likelihood[0], ll, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(ell[0], ll, rtol=1e-12, atol=1e-12)
        assert bool(torch.isfinite(nu).all()) and nu[0, 1] == 0
