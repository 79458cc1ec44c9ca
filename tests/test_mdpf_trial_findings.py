"""The adaptive particle filter's choice of form (a red-team trial).

* ``form="auto"`` took the information form for a model whose ``R(k)`` varies without
  ``time_varying`` and filtered with ``R(0)`` throughout (6.5 off the covariance form's mean).
* It took the information form for a singular ``Q`` (which the form inverts) and failed in
  ``torch.linalg.inv``; a near-singular ``Q`` lost accuracy as ``cond(Q)``.
"""

import pytest
import torch

from difffilter.fdi.mdpf import adaptive_particle_filter, information_form_applies
from difffilter.ssm import LinearGaussianModel

d = torch.float64
F = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=d)
B = torch.tensor([[0.5], [1.0]], dtype=d)
EYE = torch.eye(2, dtype=d)


class _SensorDegrades(LinearGaussianModel):  # time_varying left False
    def measurement_cov(self, k):
        return EYE * (0.1 if k < 3 else 50.0)


class _VelocityNoiseOnly(LinearGaussianModel):
    def process_cov(self, k):
        return torch.tensor([[0.1, 0.0], [0.0, 0.0]], dtype=d)


def _run(model, ys, form):
    us = torch.zeros(ys.shape[0], 1, dtype=d)
    return adaptive_particle_filter(model, ys, us, num_particles=50, form=form, reading="copy",
                                    generator=torch.Generator().manual_seed(1))  # fmt: skip


def test_auto_reads_a_measurement_noise_that_varies_undeclared():
    model = _SensorDegrades(F, EYE, 0.1 * EYE, 0.1 * EYE, torch.zeros(2, dtype=d), EYE, B)
    ys = 3 * torch.randn(8, 2, generator=torch.Generator().manual_seed(0), dtype=d)
    assert not information_form_applies(model)
    torch.testing.assert_close(_run(model, ys, "auto").means, _run(model, ys, "covariance").means)


def test_auto_takes_the_covariance_form_for_a_singular_process_noise():
    H = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], dtype=d)
    model = _VelocityNoiseOnly(
        F, H, 0.1 * EYE, 0.2 * torch.eye(3, dtype=d), torch.zeros(2, dtype=d), EYE, B
    )
    ys = torch.randn(5, 3, generator=torch.Generator().manual_seed(0), dtype=d)
    assert not information_form_applies(model)
    torch.testing.assert_close(_run(model, ys, "auto").means, _run(model, ys, "covariance").means)
    with pytest.raises(ValueError, match="positive definite Q.*it inverts Q"):
        _run(model, ys, "information")
