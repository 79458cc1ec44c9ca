"""difffilter.consistency (a consistency trial found none): NEES against its formula, the
χ² bounds against scipy, and the tests' verdicts against theory: a matched Kalman filter
is consistent and white, one whose Q is 10× too small is overconfident (its NEES above
the bounds) and one whose F is wrong has correlated innovations."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.stats import chi2

import difffilter as df
from difffilter.consistency import chi_square_bounds, ensemble_test, nees, whiteness
from difffilter.fdi import normalized_innovation_squared

F64 = torch.float64
F = torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=F64)
H = torch.tensor([[1.0, 0.0]], dtype=F64)
Q = torch.tensor([[1e-3, 0.0], [0.0, 4e-3]], dtype=F64)
R = torch.tensor([[2e-2]], dtype=F64)


def _model(F=F, Q=Q):
    return df.LinearGaussianModel(F, H, Q, R, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))


def _runs(runs=300, steps=60):
    xs, ys, _ = _model().simulate(steps, (runs,), generator=torch.Generator().manual_seed(2))
    return xs, ys


def test_nees_and_the_bounds_are_their_formulas():
    g = torch.Generator().manual_seed(0)
    A = torch.randn(5, 3, 3, generator=g, dtype=F64)
    P = A @ A.mT + 0.1 * torch.eye(3, dtype=F64)
    e = torch.randn(5, 3, generator=g, dtype=F64)
    want = torch.stack([e[i] @ torch.linalg.inv(P[i]) @ e[i] for i in range(5)])
    torch.testing.assert_close(nees(e, P), want, rtol=1e-12, atol=0)
    low, high = chi_square_bounds(2, 50, 0.95)
    assert (low, high) == pytest.approx(tuple(chi2.ppf([0.025, 0.975], 100) / 50), rel=1e-12)
    with pytest.raises(ValueError, match=r"covs must be \[..., 3, 3\]"):
        nees(e, P[..., :2, :2])
    with pytest.raises(ValueError, match="runs must be an integer >= 1"):
        chi_square_bounds(2, 0)
    with pytest.raises(ValueError, match=r"statistic must be \[R, T\]"):
        ensemble_test(torch.ones(5), 2)


def test_a_matched_kalman_filter_is_consistent_and_white():
    xs, ys = _runs()
    out = df.kalman_filter(_model(), ys)
    test = ensemble_test(nees(xs - out.means, out.covs), dof=2)
    assert test.outside <= 0.15 and float(test.mean.mean()) == pytest.approx(2.0, rel=0.05)
    nis = normalized_innovation_squared(out.innovations, out.innovation_covs)
    assert ensemble_test(nis, dof=1).outside <= 0.15
    rho, bound = whiteness(out.innovations, out.innovation_covs)
    assert bound == pytest.approx(1.96 / 300**0.5, rel=1e-3)
    assert float((rho.abs() > bound).double().mean()) <= 0.15


def test_mismatched_filters_fail_the_tests_theory_says_they_fail():
    xs, ys = _runs()
    small_q = df.kalman_filter(_model(Q=Q / 10), ys)
    test = ensemble_test(nees(xs - small_q.means, small_q.covs), dof=2)
    assert test.outside >= 0.8 and bool((test.mean[10:] > test.high).all())
    wrong_f = df.kalman_filter(_model(F=torch.tensor([[1.0, 0.0], [0.0, 0.6]], dtype=F64)), ys)
    rho, bound = whiteness(wrong_f.innovations, wrong_f.innovation_covs)
    assert float((rho[10:] > bound).double().mean()) >= 0.8  # positively correlated


def test_the_review_cases_a_diverged_run_lost_entries_and_few_runs():
    """From the review: a NaN run average counted as inside the bounds (outside 0.0 for a
    filter that diverged), the NIS under packet loss was judged against dof m (a matched
    filter "inconsistent" at 98 % of the steps), and 1.96/√(Rm) never rejected at Rm ≤ 3."""
    stat = torch.full((4, 10), 2.0, dtype=F64)
    stat[1] = float("nan")
    assert ensemble_test(stat, dof=2).outside == 1.0
    from difffilter.models.schedules import PacketLoss

    xs, ys = _runs()
    mask = PacketLoss(0.5).mask(ys.shape[0], ys.shape[1], 1, torch.Generator().manual_seed(3))
    out = df.kalman_filter(_model(), ys, mask=mask)
    nis = normalized_innovation_squared(out.innovations, out.innovation_covs)
    assert ensemble_test(nis, dof=1).outside >= 0.8  # lost entries add 0: below m's bounds
    received = ensemble_test(nis, dof=mask.sum(-1))
    assert received.outside <= 0.15 and received.low.shape == (ys.shape[1],)
    with pytest.raises(ValueError, match=r"dof must be a number or \[R, T\]"):
        ensemble_test(nis, dof=mask.sum(-1)[:2])
    # three scalar runs: |ρ̄| ≤ 1 always; the exact bound rejects 5 % of white steps
    white = torch.randn(3, 4001, 1, dtype=F64, generator=torch.Generator().manual_seed(4))
    rho, bound = whiteness(white, torch.ones(1, 1, dtype=F64), lag=1)
    assert bound < 1 and float((rho.abs() > bound).double().mean()) == pytest.approx(
        0.05, abs=0.012
    )
    assert whiteness(white[:1], torch.ones(1, 1, dtype=F64))[1] == 1.0  # one scalar run: no test


def test_steps_where_nothing_arrived_are_not_judged_outside():
    """From the review: one run under loss, a step without any entry had bounds NaN and
    counted as outside (33.7 % of a matched filter's steps)."""
    nis = torch.tensor([[0.5, 0.0, 1.2, 0.0]], dtype=F64)
    dof = torch.tensor([[1, 0, 1, 0]])
    test = ensemble_test(nis, dof=dof)
    assert test.low[1] == 0 and test.high[1] == 0 and test.outside == 0.0


def test_numpy_integers_and_negative_degrees_of_freedom():
    import numpy as np

    stat = torch.full((3, 4), 2.0, dtype=F64)
    assert ensemble_test(stat, dof=np.int64(2)).low == pytest.approx(chi_square_bounds(2, 3)[0])
    with pytest.raises(ValueError, match=r"dof must be a number or \[R, T\] like statistic"):
        ensemble_test(stat, dof=torch.full((3, 4), -1))


def test_degrees_of_freedom_as_a_numpy_array():
    import numpy as np

    stat = torch.full((3, 4), 1.0, dtype=F64)
    dof = np.ones((3, 4), dtype=np.int64)
    assert ensemble_test(stat, dof=dof).outside == ensemble_test(stat, dof=torch.ones(3, 4)).outside


def test_whiteness_under_packet_loss_counts_the_pairs_that_arrived():
    """Under loss the lost entries' zero innovations diluted ρ̄ below the bound of R m
    entries (a matched filter with 4 runs, 2 entries, half lost: 7.8 % of the steps
    rejected for 5 %). With the mask, ρ̄ sums the pairs whose both entries arrived and the
    bound is the exact one for their count, per step: 5 % again, and a wrong F still fails.
    A step with one pair is not tested (bound 1): ρ̄ is ±1 there and never beyond it (a
    review: 1 + 1 ulp had been rejected at 10 % of those steps)."""
    import numpy as np
    from scipy.stats import beta

    from difffilter.models.schedules import PacketLoss

    gen = torch.Generator().manual_seed(5)
    two = df.LinearGaussianModel(F, torch.eye(2, dtype=F64), Q, torch.diag(R[0].repeat(2)),
                                 torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))  # fmt: skip
    xs, ys, _ = two.simulate(6001, (4,), generator=gen)
    mask = PacketLoss(0.5).mask(4, 6001, 2, gen)
    out = df.kalman_filter(two, ys, mask=mask)
    rho, bound = whiteness(out.innovations, out.innovation_covs, mask=mask)
    assert bound.shape == (6000,) and rho.shape == (6000,)
    rejected = rho.abs() > bound
    assert not bool(rejected[bound == 1].any())  # the untested steps: never rejected
    assert float(rejected.double().sum() / (bound < 1).sum()) == pytest.approx(0.05, abs=0.01)
    old_rho, old_bound = whiteness(out.innovations, out.innovation_covs)
    assert float((old_rho.abs() > old_bound).double().mean()) > 0.065  # (7.8 % here)
    # by hand at one step: the products and squares of the pairs received at k and k + 1
    chol = torch.linalg.cholesky(out.innovation_covs)
    w = torch.linalg.solve_triangular(chol, out.innovations.unsqueeze(-1), upper=False)[..., 0]
    k = 17
    both = (mask[:, k] & mask[:, k + 1]).numpy()
    a, b = w[:, k].numpy()[both], w[:, k + 1].numpy()[both]
    assert float(rho[k]) == pytest.approx(a @ b / np.sqrt((a @ a) * (b @ b)), rel=1e-12)
    n = int(both.sum())
    assert float(bound[k]) == pytest.approx(
        np.sqrt(beta.ppf(0.95, 0.5, (n - 1) / 2)) if n > 1 else 1.0, rel=1e-12
    )
    wrong = df.LinearGaussianModel(torch.tensor([[1.0, 0.0], [0.0, 0.6]], dtype=F64),
                                   two.H, Q, two.measurement_noise.cov, torch.zeros(2, dtype=F64),
                                   torch.eye(2, dtype=F64))  # fmt: skip
    bad = df.kalman_filter(wrong, ys, mask=mask)
    assert abs(float(rho.nanmean())) < 0.02  # the matched filter's
    rho, bound = whiteness(bad.innovations, bad.innovation_covs, mask=mask)
    assert float(rho.nanmean()) > 0.2  # positively correlated (0.33; few pairs a step: a
    # step's own test has little power at n_k ≤ 8, 8 % rejected, so judge the average)
    with pytest.raises(ValueError, match=r"mask must be a bool tensor of the innovations' shape"):
        whiteness(out.innovations, out.innovation_covs, mask=mask[:, :, :1])


def test_whiteness_names_covariances_of_another_dtype():
    """A fuzzing trial: float32 covariances whitened float64 innovations without a word
    (``nees`` refuses the same mix)."""
    nu = torch.randn(3, 5, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    S = torch.eye(2, dtype=torch.float64).expand(3, 5, 2, 2)
    whiteness(nu, S)
    with pytest.raises(ValueError, match="innovation_covs are torch.float32 on cpu and innovations "
                                         "torch.float64 on cpu: give them one dtype"):  # fmt: skip
        whiteness(nu, S.float())


def test_the_share_outside_is_of_the_steps_with_data():
    """A sensor read every 10th step (``dof = mask.sum(-1)``, 0 in between): ``outside`` is
    the share of the tested steps outside the bounds, counted by hand from the returned
    average and bounds, not diluted by the 90 % of steps that test nothing (counted as
    inside, a filter whose S was 25 % too small had read 3–5 %, as a consistent one); NaN
    where no step has data."""
    R, T = 50, 600
    recv = torch.zeros(R, T, 2, dtype=torch.bool)
    recv[:, ::10] = True
    dof = recv.sum(-1)
    z = torch.randn(R, T, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    nis = 1.25 * (z.square() * recv).sum(-1)
    r = ensemble_test(nis, dof)
    tested = dof.sum(0) > 0
    inside = (r.mean >= r.low) & (r.mean <= r.high)
    assert r.outside == pytest.approx(float((~inside[tested]).double().mean()))
    assert r.outside > 0.2  # the miscalibrated S shows (0.3-0.5 on the tested steps)
    assert math.isnan(ensemble_test(torch.zeros(3, 5), torch.zeros(3, 5, dtype=torch.long)).outside)
