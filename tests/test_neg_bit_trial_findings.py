"""Views of torch's negative bit (``z.conj().imag``: a real tensor whose values numpy cannot
view) through the host fast paths (a memory-layout trial: the one-run particle filter, a
Kalman step's checks and the control tools had failed in torch's "negative bit set"): the
numbers of the same values as a plain tensor, bit for bit."""

import pytest
import torch

import difffilter as df
from difffilter.control import dlqr

F64 = torch.float64


def _neg_view(t):
    """A tensor equal to ``t`` held as torch's negative-bit view."""
    view = torch.complex(torch.zeros_like(t), -t).conj().imag
    assert view.is_neg() and torch.equal(view, t)
    return view


def _model(R=None):
    eye = torch.eye(2, dtype=F64)
    return df.LinearGaussianModel(0.9 * eye, eye, 0.1 * eye, 0.2 * eye if R is None else R,
                                  torch.zeros(2, dtype=F64), eye)  # fmt: skip


def _pf_step(model, y, field=None):
    pf = df.ParticleFilter(num_particles=50)
    with torch.no_grad():
        carry = pf.init(model, (), generator=torch.Generator().manual_seed(0))
        if field is not None:
            carry = carry._replace(**{field: _neg_view(getattr(carry, field))})
        return pf.step(carry, y)[1].mean


@pytest.mark.parametrize("case", ["y", "log_weights", "R"])
def test_the_one_run_particle_step_reads_a_negative_bit_view(case):
    y = torch.tensor([0.3, -0.2], dtype=F64)
    plain = _pf_step(_model(), y)
    if case == "y":
        got = _pf_step(_model(), _neg_view(y))
    elif case == "log_weights":
        got = _pf_step(_model(), y, "log_weights")
    else:
        got = _pf_step(_model(R=_neg_view(0.2 * torch.eye(2, dtype=F64))), y)
    torch.testing.assert_close(got, plain, rtol=0, atol=0)


def test_the_whole_sequence_particle_filter_of_one_run_reads_one():
    ys = torch.randn(6, 2, dtype=F64, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        runs = [df.particle_filter(_model(), y, num_particles=40,
                                   generator=torch.Generator().manual_seed(2)).means
                for y in (ys, _neg_view(ys))]  # fmt: skip
    torch.testing.assert_close(runs[1], runs[0], rtol=0, atol=0)


def test_a_kalman_carry_and_the_control_tools_read_one():
    kf, y = df.KalmanFilter(), torch.ones(1, 2, dtype=F64)
    carry = kf.init(_model(), (1,))._replace(gains=None)
    plain = kf.step(carry, y)[1].mean
    got = kf.step(carry._replace(cov=_neg_view(carry.cov)), y)[1].mean
    torch.testing.assert_close(got, plain, rtol=0, atol=0)
    A = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=F64)
    B = torch.tensor([[0.0], [0.1]], dtype=F64)
    torch.testing.assert_close(dlqr(_neg_view(A), B)[0], dlqr(A, B)[0], rtol=0, atol=0)
