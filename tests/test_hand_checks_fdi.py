"""Independent truths for lines of the attack-aware filters a second mutation review found
unpinned (each check passes here and failed on its mutant): the gated filters under a mask,
Zhang's Wald test, the bias attack estimator, the MDPF's draw and mixture moments, and the
neural compensation's log-likelihood feature."""

from __future__ import annotations

import numpy as np
import torch
from scipy.stats import chi2

import difffilter as df
from difffilter import fdi


def _two_states():
    """``(F, Q, R, m0, P0)`` as numpy arrays and the linear model of them (H = I)."""
    F, Q, R = np.array([[1.0, 0.1], [0.0, 0.95]]), np.diag([0.01, 0.02]), np.diag([0.05, 0.08])
    m0, P0 = np.zeros(2), np.eye(2)
    model = df.LinearGaussianModel(*(torch.tensor(a) for a in (F, np.eye(2), Q, R, m0, P0)))
    return F, Q, R, m0, P0, model


def test_gated_filters_under_a_mask_equal_a_numpy_gated_kf():
    """The χ² gate's quantile has the received count's degrees of freedom (its score the
    statistic's full-measurement equivalent), CUSUM adds the
    missing entries' (m − m_k) to g_k, and cusum_detector_for calibrates on the same: against
    a numpy gated Kalman filter (a mutation review found none of the three pinned)."""

    F, Q, R, m0, P0, model = _two_states()
    T = 12
    rng = np.random.default_rng(0)
    mask = np.array([[1, 0], [0, 1], [1, 1]] * 4, dtype=bool)[:T]
    target_nis = {
        2: 8.0,
        4: 8.0,
        7: 8.0,
    }  # one-entry steps: chi2_1 99% = 6.63 < 8 < chi2_2 99% = 9.21

    def truth(kind, b=3.0, tau=5.0):
        m, P, S_c = m0.copy(), P0.copy(), 0.0
        ys, alarms, scores, means = [], [], [], []
        for k in range(T):
            m, P = F @ m, F @ P @ F.T + Q
            idx = np.flatnonzero(mask[k])
            H = np.eye(2)[idx]
            S = H @ P @ H.T + R[np.ix_(idx, idx)]
            y = np.zeros(2)
            y[idx] = H @ m + rng.normal(size=len(idx)) * np.sqrt(np.diag(S)) * 0.5
            if k in target_nis and len(idx) == 1:
                y[idx] = H @ m + np.sqrt(target_nis[k] * S[0, 0])
            y[~mask[k]] = 0.0
            r = y[idx] - H @ m
            g = float(r @ np.linalg.solve(S, r))
            if kind == "chi2":
                alarm = g > chi2.ppf(0.99, len(idx))
                # the score: χ²_2's value of g's tail probability (one threshold, one rate)
                score = g if len(idx) == 2 else float(chi2.isf(chi2.sf(g, len(idx)), 2))
            else:
                S_c = max(0.0, S_c + g + (2 - len(idx)) - b)
                score = S_c
                alarm = S_c > tau
                if alarm:
                    S_c = 0.0
            if not alarm:
                K = P @ H.T @ np.linalg.inv(S)
                m, P = m + K @ r, P - K @ S @ K.T
            ys.append(y)
            alarms.append(alarm)
            scores.append(score)
            means.append(m.copy())
        return np.array(ys), np.array(alarms), np.array(scores), np.array(means)

    for kind in ("chi2", "cusum"):
        ys, alarms, scores, means = truth(kind)
        det = (
            fdi.ChiSquareDetector(2, 0.01)
            if kind == "chi2"
            else fdi.CusumDetector(3.0, threshold=5.0)
        )
        out = fdi.gated_gaussian_filter(
            model, torch.tensor(ys), mask=torch.tensor(mask), detector=det, filter=df.KalmanFilter()
        )
        a = out.detection.alarms.numpy()
        s = out.detection.scores.numpy()
        assert (a == alarms).all(), f"{kind}: alarms differ at {np.argwhere(a != alarms)}"
        assert abs(s - scores).max() < 1e-8, f"{kind}: scores differ"
        assert abs(out.means.numpy() - means).max() < 1e-8, f"{kind}: means differ"

    # cusum_detector_for on masked attack-free data: tau calibrated on g + (m - m_k)
    rng2 = np.random.default_rng(1)
    B, T2 = 40, 30
    _, ysim, _ = model.simulate(T2, (B,), generator=torch.Generator().manual_seed(3))
    mk = torch.tensor(rng2.random((B, T2, 2)) < 0.5)
    mk[..., 0] |= ~mk[..., 1]  # >= 1 received
    g = []
    for bb in range(B):
        m, P = m0.copy(), P0.copy()
        gb = []
        for k in range(T2):
            m, P = F @ m, F @ P @ F.T + Q
            idx = np.flatnonzero(mk[bb, k].numpy())
            H = np.eye(2)[idx]
            S = H @ P @ H.T + R[np.ix_(idx, idx)]
            r = ysim[bb, k].numpy()[idx] - H @ m
            gb.append(r @ np.linalg.solve(S, r) + (2 - len(idx)))
            K = P @ H.T @ np.linalg.inv(S)
            m, P = m + K @ r, P - K @ S @ K.T
        g.append(gb)
    ref = fdi.CusumDetector(4.0)
    ref.calibrate(torch.tensor(g), 0.05)
    got = fdi.cusum_detector_for(
        model, false_alarm_rate=0.05, filter=df.KalmanFilter(), ys=ysim, mask=mk
    )

    assert abs(got.threshold - ref.threshold) < 1e-6 * max(1, ref.threshold), (
        got.threshold, ref.threshold,
    )  # fmt: skip


def test_zhangs_wald_test_has_the_attacks_degrees_of_freedom():
    """The adaptive KF's Wald statistic on θ̂ (du = 2) alarms above the χ²_du quantile, not
    χ²_dy's: scipy's quantile and the statistic recomputed from the returned estimate."""

    from difffilter.models.robot import RobotModel

    model = RobotModel()  # du = 2, dy = 12
    T = 40
    us = torch.tensor([5.0, 5 * np.pi / 180], dtype=torch.float64).expand(1, T, 2).clone()
    _, ys, _ = model.simulate(T, (1,), us, generator=torch.Generator().manual_seed(0))
    out = fdi.adaptive_kalman_filter(model, ys, us, false_alarm_rate=0.01)
    thr = np.asarray(out.detection.threshold, dtype=float)
    ref = chi2.ppf(0.99, 2)
    a = out.attack[0].numpy()
    S = out.extras["attack_covs"][0].numpy()
    score = np.array([a[t] @ np.linalg.solve(S[t], a[t]) for t in range(T)])
    assert np.allclose(thr, ref), (thr, ref)
    assert np.allclose(out.detection.scores[0].numpy(), score, rtol=1e-6)
    assert (out.detection.alarms[0].numpy() == (score > ref)).all()


def test_the_bias_attack_estimator_is_a_kalman_filter_on_gamma_and_gamma_bar():
    """θ = [γ; γ̄], F = [[τI, (1−τ)I], [0, I]], γ_0 = 0 known (eq. 4), γ̄ ~ N(0, vI), updated
    on flagged steps only: against a numpy Kalman filter."""

    from difffilter.fdi import BiasAttackEstimator

    d, tau, v, q = 2, 0.9, 1.0, 1e-6
    I, Z = np.eye(d), np.zeros((d, d))
    F = np.block([[tau * I, (1 - tau) * I], [Z, I]])
    H = np.hstack([I, Z])
    Q = np.diag([q] * (2 * d))
    P = np.diag([0.0] * d + [v] * d)
    m = np.zeros(2 * d)
    rng = np.random.default_rng(0)
    T = 6
    res = rng.normal(size=(T, d)) + np.array([0.5, -0.3])
    Sk = np.stack([np.diag([0.2, 0.3]) + 0.05 * k * np.eye(d) for k in range(T)])
    flags = np.array([1, 1, 0, 1, 1, 1], dtype=bool)
    est = BiasAttackEstimator(d, tau)
    st = est.init(())
    for k in range(T):
        m, P = F @ m, F @ P @ F.T + Q
        if flags[k]:
            S = H @ P @ H.T + Sk[k]
            K = P @ H.T @ np.linalg.inv(S)
            m = m + K @ (res[k] - H @ m)
            P = P - K @ S @ K.T
        st, g, gc = est.step(st, torch.tensor(res[k]), torch.tensor(Sk[k]), torch.tensor(flags[k]))
        assert abs(g.numpy() - m[:d]).max() < 1e-6, f"gamma differs at step {k}"
        assert abs(gc.numpy() - P[:d, :d]).max() < 1e-6, f"its covariance differs at step {k}"


def test_the_mdpf_draw_reading_draws_from_the_particles_gaussian():
    """A DRAW step from identical particles equals a COPY step from particles moved to
    x̄ + L ε, L Lᵀ = P, with the same ε (drawing with Lᵀ has covariance LᵀL ≠ P)."""

    from difffilter.fdi.mdpf import ParticleLayout, adaptive_particle_step
    from difffilter.models.robot import RobotModel
    from difffilter.particle import ParticleState

    model = RobotModel()
    B, N = 4, 1  # N = 1: resampling is the identity
    lay = ParticleLayout(3, 2)
    P = np.array([[2.0, 0.9, 0.05], [0.9, 1.5, -0.03], [0.05, -0.03, 0.01]])
    L = np.linalg.cholesky(P)
    x0 = torch.tensor([1.0, -2.0, 0.3], dtype=torch.float64)

    def packed(x):
        sh = x.shape[:-1]
        return lay.pack(
            x,
            x.new_zeros(sh + (2,)),
            x.new_zeros(sh + (3, 2)),
            (10 * torch.eye(2, dtype=x.dtype)).expand(sh + (2, 2)),
            torch.tensor(P).expand(sh + (3, 3)),
        )

    y = model.observe(x0 + torch.tensor([5.0, 0.0, 0.1], dtype=torch.float64), 1).expand(B, -1)
    u = torch.tensor([5.0, 0.1], dtype=torch.float64).expand(B, 2)
    lw = torch.full((B, N), -np.log(N), dtype=torch.float64)
    for form in ("covariance", "information"):

        def step(particles, reading, seed, form=form):
            return adaptive_particle_step(
                model, ParticleState(packed(particles), lw, 0), y, u, reading=reading, form=form,
                generator=torch.Generator().manual_seed(seed),
                resample_generator=torch.Generator().manual_seed(1),
            )[1]  # fmt: skip

        out_d = step(x0.expand(B, N, 3), "draw", 7)
        if form == "covariance":
            eps = torch.randn(
                (B, N, 3), generator=torch.Generator().manual_seed(7), dtype=torch.float64
            ).numpy()
        else:  # component-major draw [dx, B, N]
            eps = np.moveaxis(
                torch.randn(
                    (3, B, N), generator=torch.Generator().manual_seed(7), dtype=torch.float64
                ).numpy(),
                0,
                -1,
            )
        xs = torch.tensor(x0.numpy() + eps @ L.T)
        out_c = step(xs, "copy", 99)

        assert abs(out_d.mean - out_c.mean).max().item() < 1e-8, form


def test_the_mdpf_local_estimate_is_the_mixture_of_its_particles_gaussians():
    """x = Σ w x_j, P = Σ w (P_j + (x_j − x)(x_j − x)ᵀ), likewise a and S, recomputed in
    numpy from the step's particles and weights (the spread term was unpinned)."""

    from difffilter.fdi.mdpf import ParticleLayout, adaptive_particle_init, adaptive_particle_step
    from difffilter.models.robot import RobotModel

    model = RobotModel()
    g = torch.Generator().manual_seed(0)
    T = 4
    us = torch.tensor([5.0, 5 * np.pi / 180], dtype=torch.float64).expand(2, T, 2).clone()
    _, ys, _ = model.simulate(T, (2,), us, generator=torch.Generator().manual_seed(1))
    state = adaptive_particle_init(model, 50, (2,), g)
    lay = ParticleLayout(3, 2)
    for form in ("covariance", "information"):
        st = state
        for t in range(T):
            st, out = adaptive_particle_step(model, st, ys[:, t], us[:, t], form=form, generator=g)
        x, a, _, S, P = (v.numpy() for v in lay.unpack(st.particles.contiguous()))
        w = torch.softmax(st.log_weights, -1).numpy()
        xm = np.einsum("bn,bni->bi", w, x)
        am = np.einsum("bn,bni->bi", w, a)
        dxx = x - xm[:, None]
        daa = a - am[:, None]
        Pm = np.einsum("bn,bnij->bij", w, P + dxx[..., :, None] * dxx[..., None, :])
        Sm = np.einsum("bn,bnij->bij", w, S + daa[..., :, None] * daa[..., None, :])
        assert abs(out.mean.numpy() - xm).max() < 1e-8, f"{form}: mean"
        assert abs(out.cov.numpy() - Pm).max() < 1e-8, f"{form}: cov"
        assert abs(out.attack.numpy() - am).max() < 1e-8, f"{form}: attack"
        assert abs(out.extras["attack_covs"].numpy() - Sm).max() < 1e-8, f"{form}: attack cov"


def test_the_log_likelihood_feature_divides_by_the_received_count():
    """asinh(−2 l_k / max(|m_k|, 1)) with l_k of the received entries (a numpy masked KF), read
    from the network's recorded inputs with every weight zero."""

    from difffilter.loop import open_loop
    from difffilter.models.learned_estimator import NeuralCompensation
    from difffilter.models.neural_estimator import NeuralFDIEstimator

    F, Q, R, m0, P0, model = _two_states()
    T = 6
    _, ys, _ = model.simulate(T, (1,), generator=torch.Generator().manual_seed(0))
    mask = torch.tensor([[1, 0], [1, 1], [0, 1], [1, 0], [1, 1], [0, 1]], dtype=torch.bool)[None]
    net = NeuralFDIEstimator(
        num_areas=1, area_dim=2, a=1, b=1, hidden=3, extra_inputs=1, dtype=torch.float64
    )
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()
    est = NeuralCompensation(
        net, df.KalmanFilter(), features=("log_likelihood",), record_inputs=True
    )
    out = open_loop(est, model, ys, mask=mask)
    feat = out.extras["network_inputs"][0, :, -1].numpy()
    m, P, ref = m0.copy(), P0.copy(), []
    for k in range(T):
        m, P = F @ m, F @ P @ F.T + Q
        idx = np.flatnonzero(mask[0, k].numpy())
        H = np.eye(2)[idx]
        S = H @ P @ H.T + R[np.ix_(idx, idx)]
        r = ys[0, k].numpy()[idx] - H @ m
        ll = -0.5 * (r @ np.linalg.solve(S, r) + np.log(np.linalg.det(2 * np.pi * S)))
        ref.append(np.arcsinh(-2 * ll / max(len(idx), 1)))
        K = P @ H.T @ np.linalg.inv(S)
        m, P = m + K @ r, P - K @ S @ K.T

    assert np.allclose(feat, ref, atol=1e-9)
