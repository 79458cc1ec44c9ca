"""Findings of a red-team trial of the public functions' documented shapes and dtypes:
batched or mixed inputs that had been taken with wrong numbers, or failed inside torch.
Each test failed on the code before its fix."""

from __future__ import annotations

import pytest
import torch

from difffilter import fdi
from difffilter.control import care_residual, dare_residual, lqr, observer_poles

D = torch.float64


def _plant():
    A = torch.tensor([[0.0, 1.0], [-2.0, -3.0]], dtype=D)
    B = torch.tensor([[0.0], [1.0]], dtype=D)
    return A, B, torch.eye(2, dtype=D), torch.eye(1, dtype=D)


def test_riccati_residuals_refuse_a_batch_instead_of_transposing_it_whole():
    # A.T of [b, n, n] had reversed every dimension: residuals 3.28 (CARE), 0.531 (DARE)
    A, B, Q, R = _plant()
    _, P = lqr(A, B, Q, R)
    assert care_residual(A, B, Q, R, P).abs().max() < 1e-8
    with pytest.raises(ValueError, match="A must be a two-dimensional floating tensor"):
        care_residual(torch.stack([A, A]), B, Q, R, P)
    with pytest.raises(ValueError, match="F must be a two-dimensional floating tensor"):
        dare_residual(torch.stack([A, A]), B, Q, R, P)
    with pytest.raises(ValueError, match="P must be a torch.float64 tensor of shape"):
        care_residual(A, B, Q, R, P.float())


def test_observer_poles_refuse_a_batch_of_closed_loops():
    # the whole batch's eigenvalues had decided where each member's zero modes went
    M1 = torch.diag(torch.tensor([-1.0, 0.0], dtype=D))
    M2 = torch.diag(torch.tensor([-0.5, -2.0], dtype=D))
    alone = observer_poles(M1, 0.1)
    torch.testing.assert_close(alone.real, torch.full((2,), 0.7408182206817179, dtype=D))
    with pytest.raises(ValueError, match=r"A_closed must be a square \[n, n\] floating tensor"):
        observer_poles(torch.stack([M1, M2]), 0.1)


def test_chi_square_equivalent_refuses_an_integer_statistic():
    # an int64 g had come back truncated: [1, 3, 4, 8] for [1.84, 3.16, 4.38, 8.93]
    g = torch.tensor([1.0, 2.0, 3.0, 7.0], dtype=D)
    got = fdi.chi_square_equivalent(g, 2, 3)
    torch.testing.assert_close(got, torch.tensor([1.8388, 3.1581, 4.3813, 8.9328], dtype=D),
                               rtol=0, atol=1e-4)  # fmt: skip
    with pytest.raises(ValueError, match="g must be a floating tensor"):
        fdi.chi_square_equivalent(g.long(), 2, 3)


@pytest.mark.parametrize("mask", [torch.full((2, 3), 0.5), torch.ones(3, 3, dtype=torch.bool)])
def test_missing_entries_counted_refuses_a_mask_that_is_no_mask_of_g(mask):
    # a float mask of 0.5s had counted half entries: g + 1.5
    with pytest.raises(ValueError, match="mask"):
        fdi.missing_entries_counted(torch.tensor([2.0, 3.0]), mask)
    mask = torch.tensor([[True, False, True], [True, True, True]])
    assert fdi.missing_entries_counted(torch.tensor([2.0, 3.0]), mask).tolist() == [3.0, 3.0]


def test_eq_36_takes_the_gain_in_the_particles_dtype():
    # modified_pf_gain had returned float64 K for float32 G, Q, R, which eq. (36) then
    # refused inside torch ("expected m1 and m2 to have the same dtype")
    G = torch.eye(2)
    Q, R = 0.1 * torch.eye(2), 0.2 * torch.eye(2)
    K = fdi.modified_pf_gain(G, Q, R)
    assert K.dtype == torch.float32
    torch.testing.assert_close(K, torch.full((2,), 1 / 3).diag())
    particles, y = torch.zeros(5, 2), torch.ones(2)
    moved = fdi.kalman_corrected_particles(particles, y, G, K.double())
    torch.testing.assert_close(moved, torch.full((5, 2), 1 / 3))
    residuals = fdi.corrected_residuals(particles, y, G, K)
    torch.testing.assert_close(residuals, torch.full((5, 2), 2 / 3))
    with pytest.raises(ValueError, match=r"y \[\.\.\., 2\]"):
        fdi.kalman_corrected_particles(particles, torch.ones(3), G, K)


@pytest.mark.parametrize("kwargs,match", [({"p0": (1.0, 1e-4, 1.0)}, "p0 must be 4 numbers"),
                                          ({"x0": (20.0, 0.3, 20.0)}, "x0 must be 4 numbers"),
                                          ({"sigma1": (4.0,)}, "sigma1 must be 2 numbers"),
                                          ({"sigma2": (25.0, 0.0)}, "sigma2 must be 2 numbers > 0")])  # fmt: skip
def test_the_tracking_plant_names_its_arguments(kwargs, match):
    # (a wrong-length p0 had been blamed on "loc", sigma1 of one entry failed in torch)
    from difffilter.models.tracking import TrackingModel

    with pytest.raises(ValueError, match=match):
        TrackingModel(**kwargs)
