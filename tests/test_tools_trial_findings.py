"""Findings of a trial of the analysis tools (control design, consistency):

* ``dlqr`` and ``kalman_steady_state`` accepted an indefinite ``Q`` (a "covariance" with
  eigenvalue -0.11 came back) and ``R = -1``, which ``lossy_dlqr`` refused by name;
* mixed dtypes of ``F`` and ``B`` (or ``H``) failed in torch's matmul, naming neither;
* ``nees`` raised torch's LinAlgError for the whole batch on one exactly singular
  covariance, where its docstring promised the huge NEES a collapsed cloud deserves.
"""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.consistency import nees
from difffilter.control import dlqr, kalman_steady_state
from difffilter.lossy_control import lossy_dlqr

D = torch.float64
F = torch.tensor([[1.1, 0.2], [0.0, 0.9]], dtype=D)
B = torch.tensor([[0.0], [1.0]], dtype=D)
H = torch.tensor([[1.0, 0.0]], dtype=D)
EYE = torch.eye(2, dtype=D)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: dlqr(F, B, torch.diag(torch.tensor([1.0, -0.5], dtype=D))),
         "Q must be positive semidefinite; its least eigenvalue is -0.5"),
        (lambda: dlqr(F, B, R=-torch.ones(1, 1, dtype=D)), "R must be positive definite"),
        (lambda: dlqr(F, B, torch.tensor([[1.0, 2.0], [0.0, 1.0]], dtype=D)),
         "Q must be symmetric"),
        (lambda: kalman_steady_state(F, H, torch.diag(torch.tensor([1.0, -0.01], dtype=D)),
                                     torch.ones(1, 1, dtype=D)),
         "Q must be positive semidefinite"),
        (lambda: kalman_steady_state(F, H, EYE, torch.full((1, 1), math.nan, dtype=D)),
         "R contains NaN or Inf values"),
        (lambda: dlqr(F, B.float()), "F is torch.float64 and B torch.float32: give them one"),
        (lambda: kalman_steady_state(F, H.float(), EYE, torch.ones(1, 1, dtype=D)),
         "F is torch.float64 and Hᵀ torch.float32"),
        (lambda: lossy_dlqr(F, B.float(), arrival_rate=0.9), "F is torch.float64 and B"),
    ],
)  # fmt: skip
def test_the_riccati_designs_name_bad_weights_and_mixed_dtypes(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_good_weights_still_design_as_scipy_does():
    K, P = dlqr(F, B, torch.diag(torch.tensor([1.0, 0.0], dtype=D)))  # semidefinite Q
    closed = F - B @ K
    assert float(torch.linalg.eigvals(closed).abs().max()) < 1.0
    K2, _ = lossy_dlqr(F, B, torch.diag(torch.tensor([1.0, 0.0], dtype=D)), arrival_rate=1.0)
    torch.testing.assert_close(K, K2, rtol=0, atol=1e-8)


def test_nees_of_an_exactly_singular_covariance_is_infinite_for_its_run_alone():
    covs = torch.stack(
        [1e-26 * EYE, torch.zeros(2, 2, dtype=D), 2.0 * EYE, torch.zeros(2, 2, dtype=D)]
    )
    errors = torch.tensor([[1.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 0.0]], dtype=D)
    got = nees(errors, covs)
    torch.testing.assert_close(got, torch.tensor([1e26, math.inf, 1.0, 0.0], dtype=D))
    one = nees(errors[:1], covs[1:2].expand(1, 2, 2))  # a shared singular covariance
    assert one.tolist() == [math.inf]


def test_an_ensemble_tests_dof_of_fractions_is_refused():
    """Per-value degrees of freedom are counts of entries received: 2.5 had been taken
    (the scalar dof is refused so already); whole numbers in a float tensor still go."""
    from difffilter.consistency import ensemble_test

    stat = torch.ones(4, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"dof must be whole numbers.*got 2.5"):
        ensemble_test(stat, torch.full((4, 3), 2.5, dtype=torch.float64))
    whole = ensemble_test(stat, torch.full((4, 3), 2.0, dtype=torch.float64))
    counted = ensemble_test(stat, torch.full((4, 3), 2, dtype=torch.int64))
    assert whole.outside == counted.outside and torch.equal(whole.low, counted.low)
