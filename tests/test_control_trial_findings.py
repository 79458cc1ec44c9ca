"""Findings of a red-team trial of the control and consistency tools (each failed before
its fix)."""

from __future__ import annotations

import math
from functools import partial

import numpy as np
import pytest
import scipy.linalg as sla
import torch

from difffilter.consistency import ensemble_test, whiteness
from difffilter.control import (
    controllability_rank,
    dlqr,
    kalman_steady_state,
    lqr,
    luenberger_gain,
    observer_poles,
    uncontrollable_direction,
    zoh_discretize,
)
from difffilter.lossy_control import intermittent_kalman_bounds


def _t(a) -> torch.Tensor:
    return torch.tensor(a, dtype=torch.float64)


@pytest.mark.parametrize("poles, dt", [(-2.0, 0.1), (-1.0, 0.05)])
def test_the_modal_observer_of_a_defective_closed_loop_has_its_poles(poles, dt):
    """A critically damped closed loop (a double, defective eigenvalue) made V singular:
    the modal Φ = V diag(p) V⁻¹ put the poles at 0.29 and 0.49 for 0.55 twice, or made the
    observer unstable; it is expm(factor·A_closed·dt), as the docstring says."""
    A_closed = _t([[0.0, 1.0], [-(poles**2), 2.0 * poles]])  # (s − poles)²
    Ad = _t(sla.expm(np.array([[0.0, 1.0], [0.0, -0.5]]) * dt))
    L = luenberger_gain(Ad, A_closed, dt).numpy()
    Phi = Ad.numpy() @ (np.eye(2) - L)
    np.testing.assert_allclose(Phi, sla.expm(3.0 * A_closed.numpy() * dt), atol=1e-12)
    np.testing.assert_allclose(np.linalg.eigvals(Phi), np.exp(3.0 * poles * dt), rtol=1e-6)


def test_the_modal_observer_moves_a_zero_pole_beside_a_defective_pair():
    """The zero eigenvalue's pole moved to the slowest other (as the LFC's) where the rest
    of the closed loop is defective: the spectral projector onto its null space."""
    A_closed = _t([[0.0, 1.0, 0.0], [0.0, -2.0, 1.0], [0.0, 0.0, -2.0]])
    dt = 0.1
    L = luenberger_gain(torch.eye(3, dtype=torch.float64), A_closed, dt).numpy()
    Phi = np.eye(3) - L
    want = np.full(3, np.exp(-6.0 * dt))  # the zero pole at the slowest other, 3 × (−2)
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(Phi).real), want, rtol=1e-6)
    # a defective zero eigenvalue cannot be moved by the modal design: said so
    with pytest.raises(ValueError, match="defective zero eigenvalue"):
        luenberger_gain(torch.eye(3, dtype=torch.float64),
                        _t([[0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, -1.0]]), dt)  # fmt: skip


def test_lqr_of_a_small_scale_controllable_plant_is_the_plain_care():
    """A floor of 1 in the tolerance called a controllable plant of entries 1e-9
    uncontrollable, and lqr solved a sub-problem (K = [−0.08, 0.68] for [0.24, 0.81])."""
    A, B = _t([[0.0, 1.0], [-2.0, -0.5]]), _t([[0.0], [1.0]])
    want = lqr(A, B)[0]
    for scale in (1e-9, 1e-10):
        assert uncontrollable_direction(scale * A, scale * B) is None
        torch.testing.assert_close(lqr(scale * A, scale * B)[0], want, rtol=1e-6, atol=0)


def test_controllability_rank_in_float32_does_not_overflow():
    """A chain of ten integrators of gain 2e4: Aⁿ⁻¹B overflowed float32 before the columns
    were scaled, and the SVD failed on non-finite values."""
    n = 10
    A = torch.diag(torch.full((n - 1,), 2e4), -1)
    B = torch.zeros(n, 1)
    B[0, 0] = 1.0
    assert controllability_rank(A, B) == n and controllability_rank(A.double(), B.double()) == n
    with pytest.raises(ValueError, match=r"A must have shape \[10, 10\]"):
        controllability_rank(A[:, :9], B)


def test_edge_inputs_get_errors_that_say_what_is_wrong():
    eye = torch.eye(2, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"\(F, H\) detectable"):
        kalman_steady_state(_t([[2.0, 0], [0, 1]]), _t([[0.0, 1.0]]), eye, _t([[1.0]]))
    for solve in (lqr, dlqr):
        with pytest.raises(ValueError, match="stabilisable"):
            solve(_t([[1.0, 0], [0, 2]]), _t([[0.0], [1.0]]))
    with pytest.raises(ValueError, match="every eigenvalue of A_closed is zero"):
        observer_poles(torch.zeros(2, 2, dtype=torch.float64), 0.1)
    with pytest.raises(ValueError, match=r"Ad must be a square \[n, n\] floating tensor"):
        luenberger_gain(np.eye(2), -eye, 0.1)
    with pytest.raises(TypeError, match="dt"):
        zoh_discretize(eye, _t([[0.0], [1.0]]), True)  # (taken for 1 s)
    Ad, _ = zoh_discretize(eye, _t([[0.0], [1.0]]), np.float32(0.5))  # (refused)
    torch.testing.assert_close(
        Ad, torch.eye(2, dtype=torch.float64) * float(np.exp(np.float32(0.5)))
    )
    with pytest.raises(ValueError, match="Q and R"):
        intermittent_kalman_bounds(0.5 * eye, _t([[1.0, 0.0]]), None, None, 0.5)
    with pytest.raises(ValueError, match=r"A must have shape \[2, 2\]"):
        uncontrollable_direction(torch.ones(2, 3, dtype=torch.float64), _t([[0.0], [1.0]]))
    # numpy's integers and a one-number tensor as the numbers they are
    nu = torch.randn(3, 10, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    S = eye.expand(3, 10, 2, 2)
    torch.testing.assert_close(whiteness(nu, S, np.int64(2))[0], whiteness(nu, S, 2)[0])
    stat = torch.rand(4, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    one, plain = ensemble_test(stat, torch.tensor(2)), ensemble_test(stat, 2)
    assert (one.low, one.high, one.outside) == (plain.low, plain.high, plain.outside)


def test_observer_poles_do_not_depend_on_the_plants_time_units():
    """The zero mode had been any eigenvalue below an absolute 1e-8: a plant in slow units
    (every number × 1e-9, dt / 1e-9: the same discrete poles) had every pole moved to
    ``zero_pole`` (0.82 where 0.49 is designed), or refused as all zero (a trial)."""
    import numpy as np

    from difffilter.control import lqr, luenberger_gain, observer_poles, zoh_discretize

    A0 = torch.tensor([[-1, 1.0, 0.5], [1, -1.0, -0.5], [0.3, 0.2, -2]], dtype=torch.float64)
    B0 = torch.tensor([[1.0], [-1.0], [1.0]], dtype=torch.float64)  # w = (1, 1, 0): a zero mode
    poles, errors = [], []
    for s in (1.0, 1e-9, 1e10):
        A, B, dt = s * A0, s * B0, 0.1 / s
        K, _ = lqr(A, B)
        closed = A - B @ K
        poles.append(np.sort(np.abs(observer_poles(closed, dt, zero_pole=-2.0 * s).numpy())))
        Ad, _ = zoh_discretize(A, B, dt)
        L = luenberger_gain(Ad, closed, dt, zero_pole=-2.0 * s).numpy()
        errors.append(np.sort(np.abs(np.linalg.eigvals(Ad.numpy() @ (np.eye(3) - L)))))
        observer_poles(closed, dt)  # one zero eigenvalue: the others give its pole
    assert poles[0] == pytest.approx([0.49087053, 0.49087053, math.exp(-0.2)], abs=1e-7)
    for p, e in zip(poles, errors):
        assert p == pytest.approx(poles[0], abs=1e-6) and e == pytest.approx(poles[0], abs=1e-6)


def test_the_steady_kalman_filter_refuses_a_marginal_mode_no_measurement_sees():
    """A constant state that nothing measures, with Q = 0 on it, had been given P⁻ = 0 and
    the gain 0 by scipy, where the filter keeps its prior variance on it for ever (the
    steady state depends on the prior: none; a trial). A marginal mode that is measured
    but not excited has the limit the filter's decaying variance reaches: gain 0."""
    from difffilter.control import kalman_steady_state

    t = partial(torch.tensor, dtype=torch.float64)
    F, Q, R = t([[1.0, 0.0], [0.0, 0.5]]), t([[0.0, 0.0], [0.0, 1.0]]), t([[1.0]])
    with pytest.raises(ValueError, match=r"\(F, H\) detectable: the mode of F at eigenvalue 1"):
        kalman_steady_state(F, t([[0.0, 1.0]]), Q, R)
    # measured, the same constant state has a steady state (its variance goes to 0)
    c, s = math.cos(0.3), math.sin(0.3)
    gain, pred, _ = kalman_steady_state(t([[c, -s], [s, c]]), t([[1.0, 0.0]]),
                                        torch.zeros(2, 2, dtype=torch.float64), R)  # fmt: skip
    assert float(gain.abs().max()) < 1e-6 and float(pred.abs().max()) < 1e-6


_S = torch.tensor([[1.0, 0.3], [0.2, 1.0]], dtype=torch.float64)  # a change of coordinates


def _in_other_coordinates(A, *more):
    """``S A S⁻¹`` (and ``S M`` for the others): the same system, not triangular."""
    Si = torch.linalg.inv(_S)
    return (_S @ A @ Si, *(_S @ m for m in more))


def test_an_unmeasured_position_is_undetectable_in_any_coordinates():
    """A double integrator with its velocity alone measured: numpy gives the Jordan block's
    eigenvalues √ε apart (1 ± 1e-8), where the PBH test passed, and the steady state came
    back with P⁻ 2.8e8 and a residual of 1 (refused in triangular coordinates)."""
    D = torch.float64
    J = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=D)
    (F,) = _in_other_coordinates(J)
    H = torch.tensor([[0.0, 1.0]], dtype=D) @ torch.linalg.inv(_S)
    for q in (torch.diag(torch.tensor([0.0, 1e-6], dtype=D)), torch.zeros(2, 2, dtype=D)):
        Q = _S @ q @ _S.T
        with pytest.raises(
            ValueError, match="needs \\(F, H\\) detectable: the mode of F at eigenvalue 1"
        ):
            kalman_steady_state(F, H, Q, torch.eye(1, dtype=D))
    seen = torch.eye(2, dtype=D)  # both measured: a steady state
    kalman_steady_state(F, seen, _S @ _S.T * 1e-6, torch.eye(2, dtype=D))


def test_a_gain_for_a_pair_that_cannot_be_stabilised_is_refused():
    """scipy returned a 'solution' for these pairs in coordinates not triangular: dlqr's
    closed loop kept its pole at 1.2 (DARE residual 0.44 of its terms), lqr(direct) a CARE
    residual of 2.09."""
    D = torch.float64
    e1 = torch.tensor([[1.0], [0.0]], dtype=D)
    F, B = _in_other_coordinates(torch.tensor([[1.2, 1.0], [0.0, 1.2]], dtype=D), e1)
    with pytest.raises(ValueError, match="no stabilising solution here.*residual is"):
        dlqr(F, B)
    A, Bc = _in_other_coordinates(torch.tensor([[0.0, 1.0], [0.0, 0.0]], dtype=D), e1)
    with pytest.raises(ValueError, match="no stabilising solution here.*residual is"):
        lqr(A, Bc, method="direct")
    K, _ = dlqr(*_in_other_coordinates(torch.tensor([[1.2, 1.0], [0.0, 1.2]], dtype=D),
                                        torch.tensor([[0.0], [1.0]], dtype=D)))  # fmt: skip
    assert float(torch.linalg.eigvals(F - B @ K).abs().max()) > 0  # (controllable: solved)


def test_a_round_off_column_does_not_count_in_the_controllability_rank():
    """A column of A M that is zero up to round-off (-2.8e-17) was scaled to unit length and
    counted: an uncontrollable pair had rank 2; a NaN tol gave 0, a negative one was taken."""
    D = torch.float64
    A, B = _in_other_coordinates(torch.tensor([[1.0, 0.0], [0.0, 2.0]], dtype=D),
                                 torch.tensor([[1.0], [0.0]], dtype=D))  # fmt: skip
    assert controllability_rank(A, B) == 1
    assert controllability_rank(A, _S @ torch.ones(2, 1, dtype=D)) == 2
    for tol in (float("nan"), -1.0):
        with pytest.raises(ValueError, match="tol must be a finite number >= 0"):
            controllability_rank(A, B, tol=tol)


def test_a_plant_matrix_holding_nan_is_refused_by_name():
    """NaN had come out of the discretisation and the observer gain without a word, and
    numpy's "SVD did not converge" out of the others; lqr with no input failed in scipy."""
    D = torch.float64
    bad = torch.tensor([[float("nan"), 1.0], [0.0, -1.0]], dtype=D)
    B = torch.ones(2, 1, dtype=D)
    calls = {
        "A": [lambda: zoh_discretize(bad, B, 0.1), lambda: lqr(bad, B),
              lambda: uncontrollable_direction(bad, B), lambda: controllability_rank(bad, B)],
        "F": [lambda: dlqr(bad, B)],
        "Ad": [lambda: luenberger_gain(bad, -torch.eye(2, dtype=D), 0.1)],
        "A_closed": [lambda: observer_poles(bad, 0.1)],
    }  # fmt: skip
    for name, fns in calls.items():
        for fn in fns:
            with pytest.raises(ValueError, match=f"^{name} contains NaN or Inf values"):
                fn()
    with pytest.raises(ValueError, match="B must have at least one column"):
        lqr(-torch.eye(2, dtype=D), torch.zeros(2, 0, dtype=D))
