"""Bad input raises ValueError naming the argument and the expectation."""

from __future__ import annotations

import pytest
import torch
from conftest import constant_velocity

import difffilter as df
from difffilter.particle import particle_filter

FILTERS = [
    df.kalman_filter,
    df.extended_kalman_filter,
    df.unscented_kalman_filter,
    lambda m, ys, us=None, **kw: particle_filter(m, ys, us, num_particles=10, **kw),
]
IDS = ["kf", "ekf", "ukf", "pf"]


@pytest.mark.parametrize("run", FILTERS, ids=IDS)
def test_wrong_measurement_dimension(run):
    with pytest.raises(ValueError, match=r"ys must have shape \[\.\.\., T, 2\]"):
        run(constant_velocity(), torch.zeros(5, 3, dtype=torch.float64))


@pytest.mark.parametrize("run", FILTERS, ids=IDS)
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_nan_or_inf_measurements(run, bad):
    ys = torch.zeros(5, 2, dtype=torch.float64)
    ys[2, 1] = bad
    with pytest.raises(ValueError, match="ys contains NaN or Inf"):
        run(constant_velocity(), ys)


@pytest.mark.parametrize("run", FILTERS, ids=IDS)
def test_nan_allowed_where_masked(run):
    ys = torch.zeros(5, 2, dtype=torch.float64)
    ys[2, 1] = float("nan")
    mask = torch.ones(5, 2, dtype=torch.bool)
    mask[2, 1] = False
    res = run(constant_velocity(), ys, mask=mask)
    assert torch.isfinite(res.means).all()


@pytest.mark.parametrize("run", FILTERS, ids=IDS)
def test_inputs_with_wrong_length(run):
    model = constant_velocity(with_input=True)
    with pytest.raises(ValueError, match="us must have T = 5"):
        run(model, torch.zeros(5, 2, dtype=torch.float64), torch.zeros(4, 1, dtype=torch.float64))


@pytest.mark.parametrize("shape", [(4, 2), (1, 2), (3, 5, 2)], ids=str)
def test_mask_must_have_the_shape_of_ys(shape):
    # (1, 2) and (3, 5, 2) broadcast with ys (5, 2) but are not its shape
    with pytest.raises(ValueError, match=r"mask must have the shape of ys \(5, 2\)"):
        df.kalman_filter(
            constant_velocity(),
            torch.zeros(5, 2, dtype=torch.float64),
            mask=torch.ones(shape, dtype=torch.bool),
        )


@pytest.mark.parametrize("name", ["Q", "R", "P0"])
def test_covariance_not_positive_definite(name):
    base = constant_velocity()
    args = dict(
        F=base.F,
        H=base.H,
        Q=base.process_noise.cov,
        R=base.measurement_noise.cov,
        m0=base.initial.mean,
        P0=base.initial.cov,
    )
    bad = -torch.eye(args[name].shape[-1], dtype=torch.float64)
    args[name] = bad
    with pytest.raises(ValueError, match=f"{name} must be positive definite"):
        df.LinearGaussianModel(**args)


def test_covariance_not_symmetric():
    base = constant_velocity()
    R = torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match="R must be symmetric"):
        df.LinearGaussianModel(
            base.F, base.H, base.process_noise.cov, R, base.initial.mean, base.initial.cov
        )


def test_matrix_shapes():
    base = constant_velocity()
    with pytest.raises(ValueError, match=r"H must have shape \[\.\.\., dy, 4\]"):
        df.LinearGaussianModel(
            base.F,
            torch.zeros(2, 3),
            base.process_noise.cov,
            base.measurement_noise.cov,
            base.initial.mean,
            base.initial.cov,
        )
    with pytest.raises(ValueError, match=r"m0 must have shape \[\.\.\., 4\]"):
        df.LinearGaussianModel(
            base.F,
            base.H,
            base.process_noise.cov,
            base.measurement_noise.cov,
            torch.zeros(3),
            base.initial.cov,
        )


@pytest.mark.parametrize("n", [0, -3, 2.5, True])
def test_num_particles_must_be_positive_int(n):
    with pytest.raises(ValueError, match="num_particles must be a positive integer"):
        particle_filter(
            constant_velocity(), torch.zeros(5, 2, dtype=torch.float64), num_particles=n
        )


def test_particle_filter_dtype_mismatch():
    with pytest.raises(ValueError, match="ys must have the model's dtype"):
        particle_filter(
            constant_velocity(), torch.zeros(5, 2, dtype=torch.float32), num_particles=4
        )


def test_ess_threshold_range():
    with pytest.raises(ValueError, match="ess_threshold must lie in"):
        particle_filter(
            constant_velocity(),
            torch.zeros(5, 2, dtype=torch.float64),
            num_particles=4,
            ess_threshold=2.0,
        )


def test_noise_model_errors():
    with pytest.raises(ValueError, match="cov must be positive definite"):
        df.noise.Gaussian(torch.zeros(2), -torch.eye(2))
    with pytest.raises(ValueError, match="weights must be finite, non-negative and sum to 1"):
        df.noise.GaussianMixture([0.5, 0.6], torch.zeros(2, 1), torch.ones(2, 1, 1))
    with pytest.raises(ValueError, match="high must be strictly greater"):
        df.noise.UniformBox([0.0, 1.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="loc contains NaN"):
        df.noise.Gaussian(torch.tensor([float("nan"), 0.0]), torch.eye(2))


def test_the_textbook_rank_one_noise_is_refused_with_its_eigenvalue_and_the_fix():
    """A course trial: the white-noise-acceleration Q = q g gᵀ (rank 1) was refused with
    "must be positive definite" alone; the remedy was in the README only."""
    # (dt a power of two: g gᵀ's second Cholesky pivot is exactly 0 on every CPU; at dt =
    # 0.1 round-off left it positive on an AVX-512 one, and the matrix passed)
    dt = 0.5
    g = torch.tensor([[dt**2 / 2], [dt]], dtype=torch.float64)
    rank_one = g @ g.T
    smallest = float(torch.linalg.eigvalsh(rank_one).min())
    with pytest.raises(ValueError, match=r"Q must be positive definite") as error:
        df.LinearGaussianModel(torch.eye(2, dtype=torch.float64), torch.tensor([[1.0, 0.0]],
                               dtype=torch.float64), rank_one, torch.eye(1, dtype=torch.float64),
                               torch.zeros(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64))  # fmt: skip
    message = str(error.value)
    assert f"its smallest is {smallest:.3g}" in message
    assert "Q + 1e-12 · max(diag) · I" in message and "Numerical limits" in message


def test_a_definite_covariance_too_ill_conditioned_for_float32_says_so():
    """From a numerics trial: a float32 Q with eigenvalues 1.5e-6 and 125 was refused as "must
    be positive definite (all eigenvalues > 0)", which it is."""
    g = torch.tensor([[0.5], [1.0]], dtype=torch.float64)
    Q = (1e2 * g @ g.T + 1e-6 * torch.eye(2, dtype=torch.float64)).float()
    with pytest.raises(ValueError, match=r"Q is positive definite in exact arithmetic \(its correlation "
                       r"matrix's smallest eigenvalue \S+; variances from \S+ to \S+\) but too near "
                       r"singular for float32 .*build the model in float64"):  # fmt: skip
        df.LinearGaussianModel(torch.eye(2), torch.eye(2)[:1], Q, torch.eye(1), torch.zeros(2),
                               torch.eye(2))  # fmt: skip
    # the variance the message suggests in float32 is one float32 resolves (1e-12 of the
    # largest was below its spacing: the same matrix, refused again)
    rank_one = (g @ g.T).float()
    with pytest.raises(ValueError, match=r"Q \+ 1e-04 · max\(diag\) · I") as error:
        df.LinearGaussianModel(torch.eye(2), torch.eye(2)[:1], rank_one, torch.eye(1),
                               torch.zeros(2), torch.eye(2))  # fmt: skip
    del error
    fixed = rank_one + 1e-4 * rank_one.diagonal().max() * torch.eye(2)
    df.LinearGaussianModel(torch.eye(2), torch.eye(2)[:1], fixed, torch.eye(1), torch.zeros(2),
                           torch.eye(2))  # fmt: skip
