"""LQR on the LFC model (uncontrollable zero mode) and Luenberger observer designs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difffilter.control import (
    LuenbergerDesign,
    care_residual,
    lqr,
    luenberger_gain,
    observer_poles,
    uncontrollable_direction,
)
from difffilter.models.lfc import LFCPlant


@pytest.fixture(scope="module")
def plant():
    return LFCPlant(dt=0.01)


def _controllable_basis(w: torch.Tensor) -> torch.Tensor:
    """Orthonormal basis [n, n-1] of w⊥."""
    q, _ = torch.linalg.qr(torch.cat([w[:, None], torch.eye(w.numel(), dtype=w.dtype)], 1))
    return q[:, 1 : w.numel()]


def test_uncontrollable_direction_is_tie_line_sum(plant):
    w = uncontrollable_direction(plant.A, plant.B)
    expected = torch.zeros(10, dtype=torch.float64)
    expected[3] = expected[8] = 2**-0.5
    assert torch.allclose(w, expected, atol=1e-10)
    # A controllable pair has none.
    assert uncontrollable_direction(plant.A[:3, :3], plant.B[:3]) is None


def test_direct_care_fails_on_lfc(plant):
    with pytest.raises((np.linalg.LinAlgError, ValueError)):
        lqr(plant.A, plant.B, method="direct")


def test_reduced_lqr_is_optimal_on_the_controllable_subspace(plant):
    A, B = plant.A, plant.B
    K, P = lqr(A, B)
    w = uncontrollable_direction(A, B)
    V = _controllable_basis(w)
    # The gain ignores the uncontrollable direction...
    assert torch.allclose(K @ w, torch.zeros(2, dtype=torch.float64), atol=1e-10)
    # ... and P solves the CARE restricted to the controllable subspace.
    Q, R = torch.eye(10, dtype=torch.float64), torch.eye(2, dtype=torch.float64)
    res = V.T @ care_residual(A, B, Q, R, P) @ V
    assert res.abs().max() < 1e-8 * max(1.0, P.abs().max().item())
    assert torch.linalg.eigvalsh(V.T @ P @ V).min() > 0


def test_closed_loop_is_stable_except_the_conserved_mode(plant):
    K, _ = lqr(plant.A, plant.B)
    eig = torch.linalg.eigvals(plant.A - plant.B @ K)
    re = eig.real.sort().values
    assert re[-1].abs() < 1e-9  # the tie-line sum: eigenvalue 0, untouched by any feedback
    assert re[-2] < -0.05  # every controllable mode strictly stable
    eig_d = torch.linalg.eigvals(plant.Ad - plant.Bd @ K).abs().sort().values
    assert eig_d[-2] < 1 - 1e-4 and abs(eig_d[-1].item() - 1) < 1e-9


def test_shift_method_agrees_on_the_controllable_subspace(plant):
    K, _ = lqr(plant.A, plant.B)
    K_shift, _ = lqr(plant.A, plant.B, method="shift", shift=1e-7)
    V = _controllable_basis(uncontrollable_direction(plant.A, plant.B))
    assert torch.allclose(K @ V, K_shift @ V, atol=1e-4)
    # ...but the shifted design feeds the conserved tie-line sum back.
    w = uncontrollable_direction(plant.A, plant.B)
    assert (K_shift @ w).abs().max() > 0.1


def test_lqr_bad_arguments(plant):
    with pytest.raises(ValueError, match="LQRMethod"):
        lqr(plant.A, plant.B, method="magic")
    with pytest.raises(ValueError, match="A must have shape"):
        lqr(plant.A[:3, :3], plant.B)


@pytest.mark.parametrize("design", LuenbergerDesign)
def test_luenberger_designs_place_the_same_poles(plant, design):
    K, _ = lqr(plant.A, plant.B)
    Acl = plant.A - plant.B @ K
    L = luenberger_gain(plant.Ad, Acl, plant.dt, design=design)
    err = plant.Ad @ (torch.eye(10, dtype=torch.float64) - L)
    got = np.sort_complex(torch.linalg.eigvals(err).numpy())
    want = np.sort_complex(observer_poles(Acl, plant.dt).numpy())
    assert np.allclose(got, want, atol=1e-7)
    assert np.abs(want).max() < 1.0  # the zero mode was moved inside the unit circle


def test_luenberger_designs_differ(plant):
    K, _ = lqr(plant.A, plant.B)
    Acl = plant.A - plant.B @ K
    gains = [luenberger_gain(plant.Ad, Acl, plant.dt, design=d) for d in LuenbergerDesign]
    assert (gains[0] - gains[1]).abs().max() > 0.05
    with pytest.raises(ValueError, match="LuenbergerDesign"):
        luenberger_gain(plant.Ad, Acl, plant.dt, design="nope")  # names LuenbergerDesign
