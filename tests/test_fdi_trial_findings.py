"""Findings of a trial of the analytic attack estimators (difffilter.fdi), each checked
against an independent computation."""

from __future__ import annotations

import pytest
import torch

from difffilter.fdi import _components as C
from difffilter.fdi import adaptive_particle_filter
from difffilter.ssm import LinearGaussianModel


def _model(dx: int, du: int) -> LinearGaussianModel:
    kw = {"dtype": torch.float64}
    B = torch.linspace(0.5, 1.5, dx * du, **kw).reshape(dx, du)
    return LinearGaussianModel(
        0.9 * torch.eye(dx, **kw), torch.eye(dx, **kw)[:2], 0.01 * torch.eye(dx, **kw),
        0.25 * torch.eye(2, **kw), torch.zeros(dx, **kw), torch.eye(dx, **kw), B=B,
    )  # fmt: skip


def _run(model, ys, us, form: str, reading: str):
    return adaptive_particle_filter(
        model, ys, us, num_particles=20, form=form, reading=reading,
        generator=torch.Generator().manual_seed(1),
        resample_generator=torch.Generator().manual_seed(2),
    )  # fmt: skip


@pytest.mark.parametrize("dx,du", [(4, 1), (5, 1), (5, 4)])
@pytest.mark.parametrize("reading", ["copy", "draw"])
def test_the_information_form_of_a_state_or_input_above_three_equals_the_covariance_form(
    dx, du, reading
):
    """The MDPF's information form inverts d > 3 matrices by a Cholesky factor of
    component products that fill only their upper triangle: it had read the lower one
    (``None``) and raised a bare TypeError for every state of 4 entries or more. One step
    with ``DRAW`` (the two forms are two samplers of one filter over a run, as the
    proposal's docstring says: a resampling's pick may move by round-off), three with
    ``COPY``."""
    model, steps = _model(dx, du), 1 if reading == "draw" else 3
    us = torch.randn(2, steps, du, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    _, ys, _ = model.simulate(steps, (2,), us, generator=torch.Generator().manual_seed(0))
    info = _run(model, ys, us, "information", reading)
    cov = _run(model, ys, us, "covariance", reading)
    torch.testing.assert_close(info.means, cov.means, rtol=0, atol=1e-9)


def test_the_component_inverse_reads_only_the_upper_triangle():
    """``sym_inverse`` of a d = 5 component matrix whose lower triangle is ``None`` equals
    ``torch.linalg.inv`` of the full matrix, and its log-determinant ``slogdet``'s."""
    gen = torch.Generator().manual_seed(0)
    m = torch.randn(3, 5, 5, generator=gen, dtype=torch.float64)
    a = m @ m.mT + 5 * torch.eye(5, dtype=torch.float64)
    comps = [[a[:, i, j] if j >= i else None for j in range(5)] for i in range(5)]
    inv, logdet = C.sym_inverse(comps, logdet=True)
    full = torch.stack([torch.stack(row, -1) for row in inv], -2)
    torch.testing.assert_close(full, torch.linalg.inv(a), rtol=0, atol=1e-12)
    torch.testing.assert_close(logdet, torch.linalg.slogdet(a)[1], rtol=0, atol=1e-12)


def test_fusion_of_ill_conditioned_or_far_scaled_locals_keeps_its_accuracy():
    """The 3 × 3 adjugate's error grows as cond²: two locals of cond 1e12 (float64) had
    fused to a mean 103 % off, and float32 locals of scale 1e13 to NaN (a trial). Such
    locals take the torch.linalg route; well-conditioned ones keep the by-hand one."""
    import mpmath
    import numpy as np

    from difffilter.fdi.fusion import _by_hand, covariance_intersection, information_fusion

    gen = torch.Generator().manual_seed(4)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    P1 = q @ torch.diag(torch.tensor([1.0, 1e-4, 1e-8], dtype=torch.float64)) @ q.T
    P2 = 1.5 * P1 + 1e-3 * torch.eye(3, dtype=torch.float64)
    covs = torch.stack([P1, P2])
    means = torch.randn(2, 3, generator=gen, dtype=torch.float64)
    mean, cov = information_fusion(means, covs)
    mpmath.mp.dps = 40  # the truth: the closed form in 40 digits on the same inputs
    i1, i2 = (mpmath.matrix(P.tolist()) ** -1 for P in (P1, P2))
    exact_cov = (i1 + i2) ** -1
    exact = exact_cov * (
        i1 * mpmath.matrix(means[0].tolist()) + i2 * mpmath.matrix(means[1].tolist())
    )
    ref_mean = np.array([float(v) for v in exact])
    ref_cov = np.array([[float(exact_cov[i, j]) for j in range(3)] for i in range(3)])
    # (the adjugate's: 1e-6 and worse; the LU route's 1e-10)
    assert np.abs(mean.numpy() - ref_mean).max() <= 1e-8 * np.abs(ref_mean).max()
    assert np.abs(cov.numpy() - ref_cov).max() <= 1e-8 * np.abs(ref_cov).max()
    assert not _by_hand(covs, 3) and _by_hand(torch.stack([torch.eye(3)] * 2), 3)
    for scale in (1e-14, 1e13):  # float32 determinants out of range: fused, not NaN
        eye = torch.eye(3)
        m = torch.stack([torch.ones(3), torch.zeros(3)])
        naive_mean, naive_cov = information_fusion(m, torch.stack([scale * eye, 2 * scale * eye]))
        torch.testing.assert_close(naive_mean, torch.full((3,), 2 / 3))
        torch.testing.assert_close(naive_cov / scale, 2 / 3 * eye)
        ci_mean, ci_cov, omega = covariance_intersection(m, torch.stack([scale * eye,
                                                                         2 * scale * eye]))  # fmt: skip
        torch.testing.assert_close(ci_mean, torch.ones(3), rtol=0, atol=1e-5)
