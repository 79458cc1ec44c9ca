"""A float32 variance below the normal range is refused wherever it sits on the diagonal
(README, Numerical limits): the Cholesky factorisation alone had refused ``diag(1e-39, 1)``
and taken ``diag(1, 1e-39)``, the same matrix up to the order of the states (a docs trial)."""

import pytest
import torch

import difffilter as df


@pytest.mark.parametrize("where", [0, 1, 2])
@pytest.mark.parametrize("which", ["Q", "R", "P0"])
def test_a_subnormal_variance_is_refused_in_any_position(which, where):
    f32 = torch.float32
    eye = torch.eye(3, dtype=f32)
    small = torch.ones(3, dtype=f32)
    small[where] = 1e-39
    mats = {"Q": eye.clone(), "R": eye.clone(), "P0": eye.clone()}
    mats[which] = torch.diag(small)
    with pytest.raises(
        ValueError, match=rf"{which} has a variance of 1e-39 \(diagonal entry {where}\)"
    ):
        df.LinearGaussianModel(
            0.9 * eye, eye, mats["Q"], mats["R"], torch.zeros(3, dtype=f32), mats["P0"]
        )
