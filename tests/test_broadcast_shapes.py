"""``difffilter._checks.broadcast_shapes``: the library's fast ``torch.broadcast_shapes``
gives torch's result (or torch's error) on every combination of a set of small shapes, and
the noise model's ``mean`` (its hot caller) keeps its broadcast."""

from __future__ import annotations

import itertools

import pytest
import torch

from difffilter._checks import broadcast_or_none, broadcast_shapes
from difffilter.noise import Gaussian

SHAPES = [(), (1,), (3,), (2, 3), (1, 3), (2, 1), (4, 2, 3), (4, 1, 1), (5,), (0,), (0, 3)]


def _torch(*shapes):
    try:
        return torch.broadcast_shapes(*shapes)
    except RuntimeError:
        return RuntimeError


def _ours(*shapes):
    try:
        return broadcast_shapes(*shapes)
    except RuntimeError:
        return RuntimeError


@pytest.mark.parametrize("count", [0, 1, 2, 3])
def test_every_combination_gives_torchs_shape_or_its_error(count):
    for combo in itertools.product(SHAPES, repeat=count):
        sizes = [torch.Size(s) for s in combo]
        expected = _torch(*sizes)
        for args in (sizes, list(combo)):  # sizes and plain tuples alike
            got = _ours(*args)
            assert got == expected, combo
            if got is not RuntimeError:
                assert type(got) is torch.Size, combo
        assert broadcast_or_none(*sizes) == (None if expected is RuntimeError else expected)


def test_the_noise_mean_broadcasts_its_location_over_the_covariance_batch():
    cov = torch.eye(2).expand(4, 2, 2)
    batched = Gaussian(torch.tensor([1.0, -2.0]), cov)
    assert batched.mean.shape == (4, 2)
    torch.testing.assert_close(batched.mean, torch.tensor([1.0, -2.0]).expand(4, 2))
    plain = Gaussian(torch.tensor([0.5, 0.25]), torch.eye(2))
    assert plain.mean.shape == (2,)
    per_run = Gaussian(torch.arange(6.0).reshape(3, 2), torch.eye(2))
    torch.testing.assert_close(per_run.mean, torch.arange(6.0).reshape(3, 2))
