"""Models of one parameter set per run (a red-team trial, 2026-12-07; each test failed
before its fix).

* A time-varying linear model whose ``transition_matrix(k)`` gives one ``F`` per run (its
  ``F`` attribute one matrix) was taken by the particle filter: where ``N = B`` the runs'
  matrices met the particle axis (each particle moved by another run's ``F``: 0.50 off a
  deterministic truth the Kalman filter follows to 1e-10), else a raw shape error. The
  UKF refused it already; the particle filters now do too.
* The EKF on one shared ``ys [T, dy]`` with a model of per-run sets whose ``f`` holds
  per-run values met one prior mean ``[dx]``: its Jacobian call failed naming sigma
  points. The prior mean now has the runs' shape.
"""

from __future__ import annotations

import pytest
import torch

import difffilter as df

DT = torch.float64
EYE = torch.eye(2, dtype=DT)
F_PER_RUN = torch.tensor(
    [[[0.9, 0.2], [0.0, 0.8]], [[0.5, -0.3], [0.3, 0.5]], [[1.0, 0.0], [0.4, 0.7]]], dtype=DT
)
M0 = torch.tensor([1.0, 1.0], dtype=DT)


class _PerRunTransition(df.LinearGaussianModel):
    time_varying = True

    def transition_matrix(self, k):
        return F_PER_RUN


def test_the_particle_filters_refuse_a_matrix_per_run_from_a_method():
    model = _PerRunTransition(EYE, EYE, 1e-10 * EYE, EYE, M0, 1e-10 * EYE)
    T = 4
    truth = torch.stack([
        torch.stack([torch.linalg.matrix_power(F_PER_RUN[b], k + 1) @ M0 for k in range(T)])
        for b in range(3)
    ])  # fmt: skip
    ys = truth + 0.1 * torch.randn(3, T, 2, generator=torch.Generator().manual_seed(0), dtype=DT)
    # the Kalman filter takes it, each run with its own F: the deterministic truth
    torch.testing.assert_close(df.kalman_filter(model, ys).means, truth, rtol=0, atol=1e-8)
    for N in (3, 5):  # N = B had mixed the runs silently
        with pytest.raises(ValueError, match=r"batch shape \(3,\) \(one set per run\)"):
            df.particle_filter(
                model, ys, num_particles=N, generator=torch.Generator().manual_seed(1)
            )
    with pytest.raises(ValueError, match=r"batch shape \(3,\) \(one set per run\)"):
        df.ParticleFilter(3).init(model, (3,), generator=torch.Generator().manual_seed(1))

    class OneTransition(df.LinearGaussianModel):  # [1, n, n] from the method is one set
        time_varying = True

        def transition_matrix(self, k):
            return F_PER_RUN[:1]

    one = OneTransition(EYE, EYE, 1e-10 * EYE, EYE, M0, 1e-10 * EYE)
    out = df.particle_filter(
        one, ys[:1], num_particles=4, generator=torch.Generator().manual_seed(1)
    )
    torch.testing.assert_close(out.means, truth[:1], rtol=0, atol=1e-4)


def test_the_ekf_runs_a_per_run_model_with_per_run_values_in_f_on_one_shared_ys():
    gains = torch.tensor([[0.5], [0.9], [1.3]], dtype=DT)  # one per run
    Q = torch.stack([0.1 * EYE, 0.2 * EYE, 0.4 * EYE])

    def model_of(a, q):
        return df.NonlinearGaussianModel(
            lambda x: torch.sin(x) * a, lambda x: x + 0.1 * x**2, q, 0.2 * EYE,
            torch.zeros(2, dtype=DT), EYE,
            transition_jacobian=lambda x: torch.diag_embed(torch.cos(x) * a),
            observation_jacobian=lambda x: torch.diag_embed(1 + 0.2 * x),
        )  # fmt: skip

    ys = torch.randn(6, 2, generator=torch.Generator().manual_seed(0), dtype=DT)
    per_set = torch.stack([
        df.extended_kalman_filter(model_of(gains[b], Q[b]), ys).means for b in range(3)
    ])  # fmt: skip
    shared = df.extended_kalman_filter(model_of(gains, Q), ys)
    torch.testing.assert_close(shared.means, per_set, rtol=0, atol=1e-14)
    assert df.gaussian_init(model_of(gains, Q)).mean.shape == (3, 2)
