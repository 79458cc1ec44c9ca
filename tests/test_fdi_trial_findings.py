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
