"""Findings of a red-team trial of the noise distributions (each failed before its fix)."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.models.tracking import GlintNoise
from difffilter.noise import GaussianMixture

VARS = [[1.0, 0.01], [100.0, 1.0]]


def test_a_glint_noise_is_constant_and_says_so():
    """Learnable weights or variances kept the tables of construction (3.2 nats off after
    an edit) and a second backward failed on their graph: refused by name."""
    with pytest.raises(ValueError, match="GlintNoise's weights and variances are constants"):
        GlintNoise(torch.tensor([0.9, 0.1]), torch.nn.Parameter(torch.tensor(VARS)), 2)


def test_a_glint_noise_takes_float32_weights_integers_and_empty_draws():
    """float32 weights of 0.1 × 10 (sum 1 + 1.2e-7) were refused against 1e-9; integer
    tables failed in multinomial; an empty draw failed in its reshape; sensors = 0 was
    taken."""
    ten = GlintNoise(torch.full((10,), 0.1, dtype=torch.float32), torch.ones(10, 2), 2)
    assert ten.sample((0,)).shape == (0, 4) and ten.sample((3, 0)).shape == (3, 0, 4)
    ints = GlintNoise([1, 0], [[1, 1], [2, 2]], 1)
    assert ints.sample((5,), torch.Generator().manual_seed(0)).dtype.is_floating_point
    with pytest.raises(ValueError, match="sensors must be an integer >= 1"):
        GlintNoise([1.0], [[1.0, 1.0]], 0)


def test_a_mixture_refuses_nonfinite_parameters_and_values_of_another_width():
    """NaN weights passed both comparisons and NaN locs no check (log_prob NaN); a value
    [..., 1] of a 3-dimensional mixture broadcast to (v, v, v) without a word."""
    covs = torch.eye(3).expand(2, 3, 3)
    with pytest.raises(ValueError, match="weights must be finite"):
        GaussianMixture(torch.tensor([math.nan, 1.0]), torch.zeros(2, 3), covs)
    with pytest.raises(ValueError, match="locs must be finite"):
        GaussianMixture(torch.tensor([0.5, 0.5]), torch.full((2, 3), math.inf), covs)
    mix = GaussianMixture(torch.tensor([0.5, 0.5]), torch.zeros(2, 3), covs)
    with pytest.raises(ValueError, match=r"value must be \[\.\.\., 3\]"):
        mix.log_prob(torch.zeros(2, 1))
