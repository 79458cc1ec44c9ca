"""Findings of a second core-filter trial (smoothers and the PCRB against dense Gaussians):

* a smoother called without the ``us`` its filter ran on, on a model with inputs, had
  smoothed silently wrong (the particle smoother 5.3 smoothed sd off the RTS smoother; the
  extended RTS smoother 0.58 where ``u_0 = 0``) or met a check blaming the filter result:
  where the numbers read the inputs, ``us=None`` is refused, naming ``us``;
* ``posterior_crb`` read a subclass's ``measurement_cov`` override only on a time-varying
  model: a constant override bounded with the constructor's ``R`` (0.50 against the Kalman
  filter's 1.20, below the optimal filter).
"""

from __future__ import annotations

import pytest
import torch

import difffilter as df

D = torch.float64
T = 10
MISSING_US = r"us: the .* reads the inputs .*\(dim_u = 1\): pass the us \[\.\.\., T, 1\]"


def _linear_with_input(cls=df.LinearGaussianModel):
    F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=D)
    return cls(F, torch.tensor([[1.0, 0.0]], dtype=D), 0.01 * torch.eye(2, dtype=D),
               0.5 * torch.eye(1, dtype=D), torch.zeros(2, dtype=D), torch.eye(2, dtype=D),
               B=torch.tensor([[0.0], [1.0]], dtype=D))  # fmt: skip


def _nonlinear_with_input():
    def f(x, u):
        return torch.stack([x[..., 0] + 0.1 * x[..., 1] * (1 + u[..., 0]),
                            0.9 * x[..., 1] + 0.2 * torch.sin(x[..., 0]) * u[..., 0]], -1)  # fmt: skip

    return df.NonlinearGaussianModel(f, lambda x: x[..., :1], 0.05 * torch.eye(2, dtype=D),
                                     0.1 * torch.eye(1, dtype=D), torch.zeros(2, dtype=D),
                                     0.01 * torch.eye(2, dtype=D), dim_u=1)  # fmt: skip


@pytest.fixture(scope="module")
def linear_run():
    model = _linear_with_input()
    us = torch.ones(2, T, 1, dtype=D)
    _, ys, _ = model.simulate(T, (2,), us=us, generator=torch.Generator().manual_seed(24))
    return model, ys, us


def test_the_particle_smoother_refuses_a_forgotten_us_and_lands_on_rts_with_it(linear_run):
    model, ys, us = linear_run
    rts = df.kalman_smoother(model, ys, us)
    pf = df.particle_filter(model, ys, us, num_particles=1000, return_particles=True,
                            generator=torch.Generator().manual_seed(0))  # fmt: skip
    with pytest.raises(ValueError, match=MISSING_US):
        df.particle_smoother(model, pf)
    sd = rts.covs.diagonal(dim1=-2, dim2=-1).sqrt()
    off = ((df.particle_smoother(model, pf, us).means - rts.means) / sd).abs().max()
    assert float(off) < 0.5  # (5.3 without B u)


def test_zero_inputs_are_given_as_zeros(linear_run):
    """A filter run with ``us=None`` (zero inputs) is smoothed with zeros: the smoothers
    land where the zero-input smoothers do."""
    model = linear_run[0]
    zeros = torch.zeros(2, T, 1, dtype=D)
    _, ys, _ = model.simulate(T, (2,), us=zeros, generator=torch.Generator().manual_seed(5))
    pf = df.particle_filter(model, ys, num_particles=1000, return_particles=True,
                            generator=torch.Generator().manual_seed(0))  # fmt: skip
    rts = df.kalman_smoother(model, ys)  # zero inputs
    sd = rts.covs.diagonal(dim1=-2, dim2=-1).sqrt()
    assert (
        float(((df.particle_smoother(model, pf, zeros).means - rts.means) / sd).abs().max()) < 0.5
    )
    nonlinear = _nonlinear_with_input()
    ekf = df.extended_kalman_filter(nonlinear, ys)
    torch.testing.assert_close(df.rts_smoother(nonlinear, ekf, zeros).means,
                               df.extended_kalman_smoother(nonlinear, ys, zeros).means,
                               rtol=0, atol=0)  # fmt: skip


def test_the_linear_rts_smoother_and_bound_read_no_input_and_need_none(linear_run):
    model, ys, us = linear_run
    kf = df.kalman_filter(model, ys, us)
    torch.testing.assert_close(df.rts_smoother(model, kf).means,
                               df.rts_smoother(model, kf, us).means, rtol=0, atol=0)  # fmt: skip
    xs, _, x0 = model.simulate(T, (3,), us=us[:1], generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(df.posterior_crb(model, xs, x0).bound,
                               df.posterior_crb(model, xs, x0, us=us[:1].expand(3, T, 1)).bound,
                               rtol=0, atol=0)  # fmt: skip


@pytest.mark.parametrize("smoother", ["extended", "unscented"])
def test_a_nonlinear_smoother_refuses_a_forgotten_us_even_where_u0_is_zero(smoother):
    model = _nonlinear_with_input()
    us = torch.ones(2, T, 1, dtype=D)
    us[:, 0] = 0.0  # a controller starting at rest: the filter-result check saw nothing
    _, ys, _ = model.simulate(T, (2,), us=us, generator=torch.Generator().manual_seed(23))
    if smoother == "extended":
        filtered = df.extended_kalman_filter(model, ys, us)
        smooth = df.rts_smoother
    else:
        filtered = df.unscented_kalman_filter(model, ys, us)
        smooth = df.unscented_rts_smoother
    with pytest.raises(ValueError, match=MISSING_US):
        smooth(model, filtered)
    with_us = smooth(model, filtered, us)
    again = (df.extended_kalman_smoother if smoother == "extended"
             else df.unscented_kalman_smoother)(model, ys, us)  # fmt: skip
    torch.testing.assert_close(with_us.means, again.means, rtol=0, atol=0)


def test_a_nonlinear_bound_refuses_a_forgotten_us():
    model = _nonlinear_with_input()
    us = torch.ones(4, T, 1, dtype=D)
    xs, _, x0 = model.simulate(T, (4,), us=us, generator=torch.Generator().manual_seed(2))
    with pytest.raises(ValueError, match=r"us: posterior_crb reads the inputs"):
        df.posterior_crb(model, xs, x0)
    assert df.posterior_crb(model, xs, x0, us=us).bound.shape == (T, 2, 2)


class _ConstantOverride(df.LinearGaussianModel):
    """A parametrised, constant R and Q through the overrides (time_varying stays False)."""

    def measurement_cov(self, k):
        return 4.0 * torch.eye(2, dtype=D)

    def process_cov(self, k):
        return 0.5 * torch.eye(2, dtype=D)


@pytest.mark.parametrize("masked", [False, True])
def test_the_bound_reads_a_constant_measurement_cov_override(masked):
    F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=D)
    eye = torch.eye(2, dtype=D)
    model = _ConstantOverride(F, eye, eye, eye, torch.zeros(2, dtype=D), eye)
    xs, ys, x0 = model.simulate(5, (1,), generator=torch.Generator().manual_seed(11))
    mask = None
    if masked:
        mask = torch.tensor([[1, 1], [0, 1], [1, 0], [0, 0], [1, 1]], dtype=torch.bool)
    kf = df.kalman_filter(model, ys, mask=None if mask is None else mask[None])
    bound = df.posterior_crb(model, xs, x0, mask=mask).bound
    # on a linear-Gaussian model the bound is the Kalman filter's P_{k|k} (0.50 against
    # 1.20 with the constructor's R = I)
    torch.testing.assert_close(bound, kf.covs[0], rtol=1e-10, atol=1e-12)
