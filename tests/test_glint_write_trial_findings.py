"""A glint noise written in place or assigned anew is read into new tables at its next
density (a model-write trial: ``cov`` and ``sample`` took the new variances while
``log_prob`` kept the constructor's tables, −2336.12 for −594.68, and a particle filter on
the tracking model 0.47 off); bad values written are named as the constructor names them."""

import pytest
import torch

from difffilter.models.tracking import GlintNoise

F64 = torch.float64


def _noise():
    weights = torch.tensor([0.9, 0.1], dtype=F64)
    variances = torch.tensor([[1.0, 0.01], [25.0, 0.3]], dtype=F64)
    return GlintNoise(weights, variances, sensors=2)


def _values():
    return torch.randn(7, 4, dtype=F64, generator=torch.Generator().manual_seed(0))


def test_variances_written_in_place_are_read_at_the_next_density():
    noise, v = _noise(), _values()
    before = noise.log_prob(v)
    with torch.no_grad():
        noise.variances.mul_(4.0)
    fresh = GlintNoise(noise.weights.clone(), noise.variances.clone(), sensors=2)
    torch.testing.assert_close(noise.log_prob(v), fresh.log_prob(v), rtol=0, atol=0)
    torch.testing.assert_close(noise.block_log_prob(v), fresh.block_log_prob(v), rtol=0, atol=0)
    mask = torch.tensor([True, False, True, True])
    torch.testing.assert_close(noise.log_prob(v, mask), fresh.log_prob(v, mask), rtol=0, atol=0)
    r, b = v[:, 0], v[:, 1]
    torch.testing.assert_close(noise.sensor_log_prob(r, b), fresh.sensor_log_prob(r, b),
                               rtol=0, atol=0)  # fmt: skip
    assert not torch.allclose(before, noise.log_prob(v))


def test_weights_assigned_anew_are_read_too():
    noise, v = _noise(), _values()
    noise.weights = torch.tensor([0.5, 0.5], dtype=F64)
    fresh = GlintNoise(torch.tensor([0.5, 0.5], dtype=F64), noise.variances.clone(), sensors=2)
    torch.testing.assert_close(noise.log_prob(v), fresh.log_prob(v), rtol=0, atol=0)


def test_values_written_wrong_are_named():
    noise = _noise()
    with torch.no_grad():
        noise.variances[0, 0] = -1.0
    with pytest.raises(ValueError, match="variances must be finite and positive"):
        noise.log_prob(_values())


def test_an_unchanged_noise_keeps_its_tables():
    noise = _noise()
    tables = noise._quad
    noise.log_prob(_values())
    assert noise._quad is tables


def test_tables_read_again_under_inference_mode_still_take_a_gradient_later():
    # the first density after a copy taken under inference mode had made inference tables,
    # and a later differentiated density failed "cannot be saved for backward" (a review)
    import copy

    x = torch.tensor([[0.3, -0.2, 1.0, 0.5]], dtype=F64)
    reference = x.clone().requires_grad_()
    _noise().log_prob(reference).sum().backward()
    for noise in (copy.deepcopy(_noise()), _noise().to(torch.float32).to(F64)):
        with torch.inference_mode():
            noise.log_prob(x)
        differentiated = x.clone().requires_grad_()
        noise.log_prob(differentiated).sum().backward()
        # (the float32 round trip rounds the weights: 4e-7)
        torch.testing.assert_close(differentiated.grad, reference.grad, rtol=0, atol=1e-6)
