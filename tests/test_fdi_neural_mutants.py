"""Hand checks of the neural compensation, the gated filter and the detectors, written to
kill mutants a mutation review found alive (g ↔ 1 − g at a gate ≠ 1/2, the mixture's
spread term, p·â vs â, rates and degrees of freedom of the χ² tests, the residual window,
CUSUM's drift and reset). Every expectation is the module docstring's equation evaluated
by hand in numpy on a 2-state linear model with a stub network of fixed outputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

import difffilter as df
from difffilter.fdi.detectors import ChiSquareDetector, CusumDetector, chi_square_upper_quantile
from difffilter.fdi.gated import GatedFilter
from difffilter.models.learned_estimator import NeuralCompensation

F = np.array([[1.0, 0.1], [0.0, 0.95]])
Q = 1e-3 * np.eye(2)
R = 1e-2 * np.eye(2)
P0 = np.eye(2)


def _model():
    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    return df.LinearGaussianModel(
        t(F), t(np.eye(2)), t(Q), t(R), torch.zeros(2, dtype=torch.float64), t(P0)
    )


class _Stub(nn.Module):
    """A :class:`~difffilter.fdi.neural.CompensationNetwork` of one area of 2 channels that
    returns, at its ``k``-th call, ``attacks[k]`` and ``logits[k]`` (the last ones after) and
    records every ``δ`` it is given."""

    num_areas, area_dim, resid_dim, extra_inputs = 1, 2, 2, 0
    detection_head = True

    def __init__(self, attacks, logits, a=2, b=3):
        super().__init__()
        self.a, self.b = a, b
        self.V = nn.Parameter(torch.zeros(1, 1, 2 * (a + b), dtype=torch.float64))
        self.attacks = [torch.as_tensor(x, dtype=torch.float64) for x in attacks]
        self.logits = [float(x) for x in logits]
        self.deltas: list[torch.Tensor] = []

    def forward(self, delta, W=None, V=None):
        k = len(self.deltas)
        self.deltas.append(delta.detach().clone())
        lead = delta.shape[:-2]
        att = self.attacks[min(k, len(self.attacks) - 1)]
        lg = self.logits[min(k, len(self.logits) - 1)]
        return att.expand(lead + (1, 2)).clone(), torch.full(lead + (1,), lg, dtype=torch.float64)

    def area_template(self):
        return nn.Linear(1, 1)

    def area_params(self):
        return {"W": self.V, "V": self.V}


def _sig(x):
    return 1.0 / (1.0 + math.exp(-x))


def _kf(m, P, y):
    """One predict + update of the 2-state model by hand: ``(m⁻, P⁻, ν, S, m_u, P_u)``."""
    mp, Pp = F @ m, F @ P @ F.T + Q
    S = Pp + R
    K = Pp @ np.linalg.inv(S)
    nu = y - mp
    return mp, Pp, nu, S, mp + K @ nu, (np.eye(2) - K) @ Pp


def _run(est, ys):
    model = _model()
    carry = est.init(model, ())
    outs = []
    for y in ys:
        carry, out = est.step(carry, torch.tensor(y, dtype=torch.float64))
        outs.append(out)
    return carry, outs


YS = [np.array([0.3, -0.2]), np.array([0.5, 0.4]), np.array([-0.1, 0.9]), np.array([0.2, 0.1])]


def test_gating_at_an_asymmetric_gate_gives_the_two_component_mixture_moments():
    """``m = (1−g) m_u + g m⁻``, ``P = (1−g)P_u + gP⁻ + g(1−g)(m_u−m⁻)(m_u−m⁻)ᵀ`` at
    ``g = sigmoid(1.3) ≈ 0.79`` (a gate of 1/2 cannot tell ``g`` from ``1 − g`` nor ``g(1−g)``
    from ``g²``), over 3 steps, against the mixture evaluated by hand."""
    a, lg = np.array([0.05, -0.1]), 1.3
    net = _Stub([a], [lg])
    _, outs = _run(NeuralCompensation(net, df.KalmanFilter(), gating=True), YS[:3])
    g = _sig(lg)
    m, P = np.zeros(2), P0
    for y, out in zip(YS[:3], outs):
        mp, Pp, _, _, mu, Pu = _kf(m, P, y - a)
        d = mu - mp
        m = (1 - g) * mu + g * mp
        P = (1 - g) * Pu + g * Pp + g * (1 - g) * np.outer(d, d)
        np.testing.assert_allclose(out.mean.numpy(), m, rtol=0, atol=1e-12)
        np.testing.assert_allclose(out.cov.numpy(), P, rtol=0, atol=1e-12)


@pytest.mark.parametrize("compensation", ["full", "detected"])
def test_full_subtracts_a_hat_and_detected_subtracts_p_times_a_hat(compensation):
    """``"full"``: update with ``ỹ − â``; ``"detected"``: with ``ỹ − p â``, ``p = sigmoid(logit)
    = sigmoid(−0.7)`` (neither 0, 1/2 nor 1), against the KF by hand."""
    a, lg = np.array([0.4, -0.25]), -0.7
    net = _Stub([a], [lg])
    _, outs = _run(NeuralCompensation(net, df.KalmanFilter(), compensation=compensation), YS)
    applied = a if compensation == "full" else _sig(lg) * a
    m, P = np.zeros(2), P0
    for y, out in zip(YS, outs):
        *_, m, P = _kf(m, P, y - applied)
        np.testing.assert_allclose(out.mean.numpy(), m, rtol=0, atol=1e-12)
        np.testing.assert_allclose(out.attack.numpy(), a, rtol=0, atol=0)


def test_the_residual_window_holds_the_last_b_innovations_and_a_estimates_most_recent_first():
    """``δ_k = [â_{k−1}, â_{k−2}, r_k, r_{k−1}, r_{k−2}]`` (a = 2, b = 3, ``standardize=False``,
    ``residual="innovation"``: ``r = ν`` the uncompensated innovation), zeros before step 1,
    against the innovations of the compensated KF by hand and the stub's estimates."""
    atts = [
        np.array([0.1, 0.2]),
        np.array([-0.3, 0.05]),
        np.array([0.7, -0.4]),
        np.array([0.0, 0.6]),
    ]
    net = _Stub(atts, [-2.0])
    _run(NeuralCompensation(net, df.KalmanFilter(), standardize=False), YS)
    m, P, nus = np.zeros(2), P0, []
    for k, y in enumerate(YS):
        mp, Pp, nu, *_ = _kf(m, P, y)
        nus.append(nu)
        *_, m, P = _kf(m, P, y - atts[k])
        past = lambda xs, n, j: [xs[j - i] if j - i >= 0 else np.zeros(2) for i in range(n)]  # noqa: E731
        want = np.concatenate(past(atts, 2, k - 1) + past(nus, 3, k))
        np.testing.assert_allclose(net.deltas[k][0].numpy(), want, rtol=0, atol=1e-12)


def test_the_predicted_residual_subtracts_the_most_recent_estimate():
    """``residual="predicted"``: ``r_k = ν_k − â_{k−1}`` (not an older estimate), against the
    KF by hand with estimates that change at every step."""
    atts = [
        np.array([0.1, 0.2]),
        np.array([-0.3, 0.05]),
        np.array([0.7, -0.4]),
        np.array([0.0, 0.6]),
    ]
    net = _Stub(atts, [-2.0], a=2, b=1)
    _run(NeuralCompensation(net, df.KalmanFilter(), standardize=False, residual="predicted"), YS)
    m, P = np.zeros(2), P0
    for k, y in enumerate(YS):
        _, _, nu, *_ = _kf(m, P, y)
        *_, m, P = _kf(m, P, y - atts[k])
        prev = atts[k - 1] if k else np.zeros(2)
        np.testing.assert_allclose(net.deltas[k][0, 4:].numpy(), nu - prev, rtol=0, atol=1e-12)


def _nis(nu, S):
    return float(nu @ np.linalg.solve(S, nu))


def test_reject_keeps_the_prediction_where_the_compensated_nis_exceeds_the_2_dof_quantile():
    """``reject=ρ``: prediction where ``(ν−â)ᵀS⁻¹(ν−â) > −2 ln ρ`` (χ²₂'s upper quantile in
    closed form), else the compensated update. The measurements put the NIS between χ²₁'s
    and χ²₂'s quantiles at one step (a test of the wrong degrees of freedom rejects it) and
    the raw innovation ν far above the quantile where ν − â is small (a test of ν rejects)."""
    rho = 0.05
    limit = -2 * math.log(rho)
    assert abs(limit - chi_square_upper_quantile(2, rho)) < 1e-9
    a = np.array([1.5, -1.2])
    ys = [a + np.array([0.02, 0.01]), a + np.array([0.35, 0.1]), a + np.array([0.1, -0.05]),
          a + np.array([0.2, 0.3])]  # fmt: skip
    _, outs = _run(NeuralCompensation(_Stub([a], [-3.0]), df.KalmanFilter(), reject=rho), ys)
    m, P, kinds = np.zeros(2), P0, []
    for y, out in zip(ys, outs):
        mp, Pp, nu, S, mu, Pu = _kf(m, P, y - a)
        q = _nis(nu, S)
        kinds.append(q)
        m, P = (mp, Pp) if q > limit else (mu, Pu)
        np.testing.assert_allclose(out.mean.numpy(), m, rtol=0, atol=1e-12)
        np.testing.assert_allclose(out.cov.numpy(), P, rtol=0, atol=1e-12)
    # the case this is about: one step between the quantiles of χ²₁ and χ²₂ (kept)
    q1 = chi_square_upper_quantile(1, rho)
    assert any(q1 < q <= limit for q in kinds), kinds


def _restart_by_hand(ys, a, lg, alpha, beta):
    """The restart and confirm of the module docstring by hand: the χ²-gated copy (update
    where its NIS ≤ −2 ln α, else prediction), the compensated filter restarted from it where
    quiet, and the score ``p · 1[q° > −2 ln β]``."""
    qa, qb = -2 * math.log(alpha), -2 * math.log(beta)
    m, P, mc, Pc, rows = np.zeros(2), P0, np.zeros(2), P0, []
    for y in ys:
        cp, cPp, cnu, cS, cu, cPu = _kf(mc, Pc, y)
        q = _nis(cnu, cS)
        quiet = q <= qa
        mc, Pc = (cu, cPu) if quiet else (cp, cPp)
        *_, m, P = _kf(m, P, y - a)
        if quiet:
            m, P = mc, Pc
        rows.append((m, P, _sig(lg) * (q > qb), q))
    return rows


def test_restart_takes_the_gated_copys_posterior_and_confirm_scores_beyond_beta():
    """Restart at ``α = 0.01`` (quiet: ``q° ≤ −2 ln α`` = 9.21) and confirm at ``β = 0.3``
    (alarm: ``q° > −2 ln β`` = 2.41): means, covariances and scores against the gated copy
    by hand; the measurements put ``q°`` below 2.41, between the two and above 9.21."""
    alpha, beta, a, lg = 0.01, 0.3, np.array([0.3, -0.2]), 0.4
    ys = [np.array([0.05, -0.02]), np.array([0.25, 0.3]), np.array([1.2, -1.0]), np.array([0.1, 0.0]),
          np.array([0.02, 0.04])]  # fmt: skip
    est = NeuralCompensation(_Stub([a], [lg]), df.KalmanFilter(), restart=alpha, confirm=beta)
    _, outs = _run(est, ys)
    rows = _restart_by_hand(ys, a, lg, alpha, beta)
    qs = [r[3] for r in rows]
    assert any(q <= -2 * math.log(beta) for q in qs), qs
    assert any(-2 * math.log(beta) < q <= -2 * math.log(alpha) for q in qs), qs
    assert any(q > -2 * math.log(alpha) for q in qs), qs
    for (m, P, score, _), out in zip(rows, outs):
        np.testing.assert_allclose(out.mean.numpy(), m, rtol=0, atol=1e-12)
        np.testing.assert_allclose(out.cov.numpy(), P, rtol=0, atol=1e-12)
        np.testing.assert_allclose(float(out.score), score, rtol=0, atol=1e-15)


def test_the_particle_filters_gate_tempers_the_log_likelihood_by_one_minus_g():
    """``log w_k = log w⁻ + (1−g) log p(ỹ − â | x)`` at ``g = sigmoid(1.1)``, normalised,
    without resampling: against the Gaussian log density of the carry's propagated
    particles by hand (the weights start uniform)."""
    a, lg = np.array([0.1, -0.05]), 1.1
    est = NeuralCompensation(
        _Stub([a], [lg]), df.ParticleFilter(50, ess_threshold=0.0), gating=True
    )
    model = _model()
    carry = est.init(model, (), generator=torch.Generator().manual_seed(3))
    y = np.array([0.3, -0.2])
    carry, _ = est.step(carry, torch.tensor(y))
    x = carry.particles.numpy()
    z = y - a - x
    loglik = -0.5 * np.einsum("ni,ij,nj->n", z, np.linalg.inv(R), z)
    lw = (1 - _sig(lg)) * loglik
    lw = lw - np.logaddexp.reduce(lw)
    np.testing.assert_allclose(carry.log_weights.numpy(), lw, rtol=0, atol=1e-10)


# -- detectors and the gated filter ---------------------------------------------------------


def _cusum_by_hand(g, b, tau):
    s, stats, alarms = 0.0, [], []
    for gk in g:
        s = max(0.0, s + gk - b)
        stats.append(s)
        alarms.append(s > tau)
        if s > tau:
            s = 0.0
    return np.array(stats), np.array(alarms)


@pytest.mark.parametrize("tau", [4.0, 0.0])
def test_cusum_step_and_run_follow_the_recursion_with_reset(tau):
    """``S_k = max(0, S_{k−1} + g_k − b)``, alarm ``S_k > τ`` (strictly: at ``τ = 0`` a
    statistic clamped at 0 does not alarm), then ``S_k ← 0``: online ``step`` and ``run``
    against the recursion written out (b = 3, τ = 4 and 0)."""
    g = [1.0, 5.0, 4.0, 6.5, 0.5, 9.0, 2.0, 7.0, 3.0]
    want_s, want_a = _cusum_by_hand(g, 3.0, tau)
    det = CusumDetector(3.0, threshold=tau)
    stats, alarms = det.run(torch.tensor(g, dtype=torch.float64))
    np.testing.assert_allclose(stats.numpy(), want_s, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(alarms.numpy(), want_a)
    state = det.init()
    for k, gk in enumerate(g):
        state, s, alarm = det.step(state, torch.tensor(gk, dtype=torch.float64))
        assert float(s) == pytest.approx(want_s[k], abs=1e-12) and bool(alarm) == want_a[k]


def test_chi_square_detector_online_window_thresholds_are_the_warming_quantiles():
    """Window ``W = 2`` of dim 2: step 1 against ``χ²₂`` (= −2 ln α), later steps the sum of
    two NIS against ``χ²₄`` (closed form ``x`` with ``e^{−x/2}(1 + x/2) = α``); a masked step
    receiving one entry against ``χ²_{1+2}`` over the window. Against scipy-free closed forms
    and scipy."""
    from scipy.stats import chi2

    alpha = 0.05
    q2 = -2 * math.log(alpha)
    x = 10.0
    for _ in range(60):  # Newton on e^{−x/2}(1 + x/2) = α
        f = math.exp(-x / 2) * (1 + x / 2) - alpha
        x -= f / (-math.exp(-x / 2) * x / 4)
    det = ChiSquareDetector(2, alpha, window=2)
    assert det.quantile(2) == pytest.approx(q2, rel=1e-12)
    assert det.threshold == pytest.approx(x, rel=1e-10)
    state = det.init(())
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    state, s, alarm = det.step(state, t(q2 - 0.1))  # below χ²₂ at step 1
    assert not bool(alarm) and float(s) == pytest.approx(q2 - 0.1)
    state, s, alarm = det.step(state, t(x - q2 + 0.2))  # the window's sum just above χ²₄
    assert bool(alarm) and float(s) == pytest.approx(x + 0.1)
    # one entry received: the window holds 2 + 1 dof; score the χ²₄ equivalent of χ²₃
    g3 = chi2.isf(alpha, 3) - (x - q2 + 0.2) + 0.05
    state, s, alarm = det.step(state, t(g3), mask=torch.tensor([True, False]))
    assert bool(alarm)
    total = (x - q2 + 0.2) + g3
    assert float(s) == pytest.approx(chi2.isf(chi2.sf(total, 3), 4), rel=1e-9)


def test_gated_filter_with_cusum_counts_missing_entries_and_skips_alarmed_updates():
    """GatedFilter + CUSUM under a mask: ``g_k + (m − m_k)`` enters the recursion, alarmed
    steps keep the prediction. Against the KF (unreceived entry: no update of it) and the
    recursion by hand."""
    model = _model()
    det = CusumDetector(2.5, threshold=1.5)
    gf = GatedFilter(det, df.KalmanFilter())
    ys = [np.array([0.1, 0.05]), np.array([0.9, 0.0]), np.array([0.2, 0.1]), np.array([0.3, 0.2])]
    masks = [np.array([True, True]), np.array([True, False]), np.array([True, False]),
             np.array([True, True])]  # fmt: skip
    carry = gf.init(model, ())
    m, P, s = np.zeros(2), P0, 0.0
    for y, mk in zip(ys, masks):
        carry, out = gf.step(carry, torch.tensor(y), mask=torch.tensor(mk))
        mp, Pp = F @ m, F @ P @ F.T + Q
        idx = np.flatnonzero(mk)
        Hs = np.eye(2)[idx]
        S = Hs @ Pp @ Hs.T + R[np.ix_(idx, idx)]
        nu = y[idx] - Hs @ mp
        g = _nis(nu, S) + (2 - len(idx))
        s = max(0.0, s + g - 2.5)
        alarm = s > 1.5
        assert float(out.score) == pytest.approx(s, abs=1e-10) and bool(out.alarm) == alarm
        if alarm:
            m, P, s = mp, Pp, 0.0
        else:
            K = Pp @ Hs.T @ np.linalg.inv(S)
            m, P = mp + K @ nu, (np.eye(2) - K @ Hs) @ Pp
        np.testing.assert_allclose(out.mean.numpy(), m, rtol=0, atol=1e-12)


def test_the_particle_filters_rejection_tests_the_compensated_not_the_raw_innovation():
    """``reject=ρ`` in the particle filter: the χ² test reads ``ν − â``. With ``â = (3, −3)``
    and ``ỹ = â + (0.1, −0.05)`` (prior covariance I: ``ν − â`` far inside ``−2 ln ρ``, ``ν``
    far outside) the update is kept: ``log w = log p(ỹ − â | x)`` normalised, by hand."""
    a = np.array([3.0, -3.0])
    est = NeuralCompensation(
        _Stub([a], [-3.0]), df.ParticleFilter(50, ess_threshold=0.0), reject=0.05
    )
    carry = est.init(_model(), (), generator=torch.Generator().manual_seed(5))
    y = a + np.array([0.1, -0.05])
    carry, _ = est.step(carry, torch.tensor(y))
    z = y - a - carry.particles.numpy()
    lw = -0.5 * np.einsum("ni,ij,nj->n", z, np.linalg.inv(R), z)
    np.testing.assert_allclose(
        carry.log_weights.numpy(), lw - np.logaddexp.reduce(lw), rtol=0, atol=1e-10
    )


def test_gated_filters_reported_chi_square_threshold_warms_up_with_the_window():
    """GatedFilter with ``ChiSquareDetector(2, α, window=3)``: the reported threshold of
    step ``k`` is ``F⁻¹_{χ²_{2·min(k, 3)}}(1 − α)``: −2 ln α at step 1 (closed form), then
    scipy's χ²₄ and χ²₆ quantiles."""
    from scipy.stats import chi2

    alpha = 0.02
    gf = GatedFilter(ChiSquareDetector(2, alpha, window=3), df.KalmanFilter())
    carry = gf.init(_model(), ())
    want = [-2 * math.log(alpha), chi2.isf(alpha, 4), chi2.isf(alpha, 6), chi2.isf(alpha, 6)]
    for y, w in zip(YS, want):
        carry, out = gf.step(carry, torch.tensor(y))
        assert float(out.threshold) == pytest.approx(w, rel=1e-10)


def test_the_gate_is_the_probability_of_the_most_likely_attacked_area():
    """``g_k = max over areas of sigmoid(logit_k)`` (the module docstring's gate): with two
    areas the larger probability, not their mean, by hand."""
    from difffilter.fdi.neural import gate_of

    logit = torch.tensor([[-2.0, 1.0], [0.5, -0.5]], dtype=torch.float64)
    expected = 1.0 / (1.0 + np.exp(-np.array([1.0, 0.5])))
    np.testing.assert_allclose(gate_of(logit).numpy(), expected, rtol=1e-15)
