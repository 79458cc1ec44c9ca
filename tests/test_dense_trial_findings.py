"""Findings of a red-team trial of the Gaussian filters against one dense joint Gaussian:
the adaptive Kalman filter's innovation covariance and evidence, and the matrices of a
time-varying model read at each step. Each test failed on the code before its fix."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter.fdi.adaptive_kf import adaptive_kalman_filter

DX, DY, DU, T, RUNS = 3, 2, 2, 7, 3


def _spd(rng, d, s):
    A = rng.standard_normal((d, d))
    return s * (A @ A.T / d + 0.3 * np.eye(d))


def _augmented_kf(F, H, Q, R, B, m0, P0, theta0, omega, ys, us):
    """The Kalman filter on ``s = [x; θ]`` with a constant ``θ ~ N(θ̂₀, ω I)`` (numpy):
    per step its innovation covariance, and per run log p(y_1:T)."""
    n = DX + DU
    FA = np.block([[F, B], [np.zeros((DU, DX)), np.eye(DU)]])
    BA = np.vstack([B, np.zeros((DU, DU))])
    HA = np.hstack([H, np.zeros((DY, DU))])
    QA = np.zeros((n, n))
    QA[:DX, :DX] = Q
    covs, evidence = np.zeros((RUNS, T, DY, DY)), np.zeros(RUNS)
    for r in range(RUNS):
        m = np.concatenate([m0, theta0])
        P = np.zeros((n, n))
        P[:DX, :DX], P[DX:, DX:] = P0, omega * np.eye(DU)
        for t in range(T):
            m, P = FA @ m + BA @ us[r, t], FA @ P @ FA.T + QA
            S, nu = HA @ P @ HA.T + R, ys[r, t] - HA @ m
            K = np.linalg.solve(S, HA @ P).T
            m, P = m + K @ nu, (np.eye(n) - K @ HA) @ P
            evidence[r] -= 0.5 * (nu @ np.linalg.solve(S, nu) + np.linalg.slogdet(S)[1]
                                  + DY * np.log(2 * np.pi))  # fmt: skip
            covs[r, t] = S
    return covs, evidence


def test_the_adaptive_kf_reports_the_innovation_covariance_and_evidence_of_the_augmented_kf():
    # with λ = 1 on a linear model it is the Kalman filter on [x; θ]: its means agreed, but
    # it reported Σ = C P⁻ Cᵀ + R ([[5.41, 1.51], …] for [[7.01, 2.91], …]) and a sum of
    # log N(ỹ; 0, Σ) (−46.98 for the evidence −43.92)
    rng = np.random.default_rng(30)
    F = 0.6 * rng.standard_normal((DX, DX)) + 0.5 * np.eye(DX)
    H, Q, R = rng.standard_normal((DY, DX)), _spd(rng, DX, 0.3), _spd(rng, DY, 0.5)
    B, m0, P0 = rng.standard_normal((DX, DU)), 2 * rng.standard_normal(DX), _spd(rng, DX, 1.5)
    ys, us = 2 * rng.standard_normal((RUNS, T, DY)), rng.standard_normal((RUNS, T, DU))
    omega, theta0 = 0.7, 0.5 * rng.standard_normal(DU)
    model = df.LinearGaussianModel(*(torch.tensor(a) for a in (F, H, Q, R, m0, P0, B)))
    out = adaptive_kalman_filter(model, torch.tensor(ys), torch.tensor(us), forgetting=1.0,
                                 attack_cov0=omega, attack0=torch.tensor(theta0))  # fmt: skip
    covs, evidence = _augmented_kf(F, H, Q, R, B, m0, P0, theta0, omega, ys, us)
    np.testing.assert_allclose(out.extras["innovation_covs"].numpy(), covs, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out.extras["log_likelihood"].numpy(), evidence, rtol=1e-10)


def test_the_mdpf_weight_keeps_the_papers_density_given_the_attack_estimate():
    # (A8) weighs by N(ỹ; 0, Σ), Σ = C P⁻ Cᵀ + R: unchanged by the fix above
    from difffilter.fdi.adaptive_kf import adaptive_update

    rng = np.random.default_rng(1)
    F = 0.5 * np.eye(DX)
    H, Q, R, B = (
        rng.standard_normal((DY, DX)),
        _spd(rng, DX, 0.3),
        _spd(rng, DY, 0.5),
        np.eye(DX, DU),
    )
    model = df.LinearGaussianModel(
        *(torch.tensor(a) for a in (F, H, Q, R, np.zeros(DX), np.eye(DX), B))
    )
    x, P = torch.tensor(rng.standard_normal(DX)), torch.tensor(_spd(rng, DX, 1.0))
    a, S = torch.zeros(DU, dtype=torch.float64), torch.eye(DU, dtype=torch.float64)
    ups, y, u = (
        torch.zeros(DX, DU, dtype=torch.float64),
        torch.tensor([0.3, -0.2]),
        torch.zeros(DU, dtype=torch.float64),
    )
    upd = adaptive_update(model, x, a, S, ups, y.double(), u, 0, forgetting=0.8, cov=P)
    Hm, Pp = torch.tensor(H), torch.tensor(F) @ P @ torch.tensor(F).T + torch.tensor(Q)
    sigma = Hm @ Pp @ Hm.T + torch.tensor(R)
    nu = y.double() - Hm @ (torch.tensor(F) @ x)
    torch.testing.assert_close(upd.residual_cov, sigma, rtol=1e-12, atol=1e-12)
    density = torch.distributions.MultivariateNormal(torch.zeros(DY, dtype=torch.float64), sigma)
    torch.testing.assert_close(upd.log_likelihood, density.log_prob(nu), rtol=1e-12, atol=1e-12)
    omega = Hm @ torch.tensor(B)  # C (A Υ₀ + Φ) with Υ₀ = 0
    torch.testing.assert_close(upd.predictive_cov, sigma + omega @ (S / 0.8) @ omega.T,
                               rtol=1e-12, atol=1e-12)  # fmt: skip


class _TimeVarying(df.LinearGaussianModel):
    """Tables of F_k, H_k and B_k (a recorded log's), one of them NaN at one step."""

    time_varying = True

    def __init__(self, bad: str, step: int):
        eye = torch.eye(2, dtype=torch.float64)
        super().__init__(0.9 * eye, eye[:1], 0.1 * eye, 0.2 * eye[:1, :1], torch.zeros(2, dtype=torch.float64),
                         eye, B=torch.ones(2, 1, dtype=torch.float64))  # fmt: skip
        for which in ("F", "H", "B"):
            table = getattr(self, which).expand(10, *getattr(self, which).shape).clone()
            if which == bad and step < 10:
                table[step] = float("nan")
            self.register_buffer(f"{which}s", table)

    def transition_matrix(self, k):
        return self.Fs[k]

    def observation_matrix(self, k):
        return self.Hs[k]

    def control_matrix(self, k):
        return self.Bs[k]


FILTERS = {
    "kf": lambda m, ys, us: df.kalman_filter(m, ys, us),
    "kf_parallel": lambda m, ys, us: df.kalman_filter(m, ys, us, method="parallel"),
    "ekf": lambda m, ys, us: df.extended_kalman_filter(m, ys, us),
    "smoother": lambda m, ys, us: df.kalman_smoother(m, ys, us),
}


@pytest.mark.parametrize("bad,method", [("F", "transition_matrix"), ("H", "observation_matrix"),
                                        ("B", "control_matrix")])  # fmt: skip
@pytest.mark.parametrize("run", sorted(FILTERS))
def test_a_nan_matrix_of_a_time_varying_model_is_named_with_its_step(bad, method, run):
    # a NaN B_2 had run to NaN means from step 2 on without an error; a NaN F_2 or H_2 was
    # blamed on "Q, R and P0"
    g = torch.Generator().manual_seed(0)
    ys, us = (
        torch.randn(3, 6, 1, generator=g, dtype=torch.float64),
        torch.ones(3, 6, 1, dtype=torch.float64),
    )
    with pytest.raises(ValueError, match=rf"_TimeVarying\.{method}\(\d\) contains NaN"):
        FILTERS[run](_TimeVarying(bad, 2), ys, us)
    clean = FILTERS[run](_TimeVarying(bad, 99), ys, us)  # never read: the same as a plain model
    assert torch.isfinite(clean.means).all()


@pytest.mark.parametrize("name", ["F", "H", "B"])
def test_a_matrix_written_nan_in_place_is_refused(name):
    eye = torch.eye(2, dtype=torch.float64)
    model = df.LinearGaussianModel(0.9 * eye, eye, 0.1 * eye, 0.1 * eye, torch.zeros(2, dtype=torch.float64),
                                   eye, B=torch.ones(2, 1, dtype=torch.float64))  # fmt: skip
    with torch.no_grad():
        getattr(model, name)[0, 0] = float("nan")
    ys = torch.zeros(2, 4, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match=f"model.{name} contains NaN"):
        df.kalman_filter(model, ys, torch.ones(2, 4, 1, dtype=torch.float64))
