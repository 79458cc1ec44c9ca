"""StateFeedback's gain and reference assigned after construction meet the constructor's
checks when a loop starts (an LQG trial: a reference [B, 1] set later had been broadcast
over every state entry, u₁ = −K(x̂₁ − [0.5, 0.5]))."""

import pytest
import torch

import difffilter as df
from difffilter.control import dlqr
from difffilter.loop import ReplayedNoise, StateFeedback, closed_loop

F64 = torch.float64
RUNS, T = 3, 6


def _loop(controller):
    F = torch.tensor([[1.02, 0.1], [0.0, 0.95]], dtype=F64)
    B = torch.tensor([[0.0], [0.1]], dtype=F64)
    plant = df.LinearGaussianModel(
        F, torch.tensor([[1.0, 0.0]], dtype=F64), 0.01 * torch.eye(2, dtype=F64),
        torch.tensor([[0.04]], dtype=F64), torch.zeros(2, dtype=F64),
        0.1 * torch.eye(2, dtype=F64), B=B,
    )  # fmt: skip
    g = torch.Generator().manual_seed(0)
    w = 0.1 * torch.randn(RUNS, T, 2, generator=g, dtype=F64)
    v = 0.2 * torch.randn(RUNS, T, 1, generator=g, dtype=F64)
    return closed_loop(plant, T, noise=ReplayedNoise(w, v), x0=torch.zeros(RUNS, 2, dtype=F64),
                       estimator=df.KalmanFilter(), controller=controller)  # fmt: skip


def _gain():
    F = torch.tensor([[1.02, 0.1], [0.0, 0.95]], dtype=F64)
    return dlqr(F, torch.tensor([[0.0], [0.1]], dtype=F64))[0]


@pytest.mark.parametrize("reference", [torch.full((RUNS, 1), 0.5, dtype=F64),
                                       torch.tensor(0.5, dtype=F64),
                                       torch.tensor([0.5, float("nan")], dtype=F64)])  # fmt: skip
def test_a_reference_set_later_is_checked_as_the_constructor_checks_it(reference):
    controller = StateFeedback(_gain())
    controller.reference = reference
    with pytest.raises(ValueError, match="reference"):
        _loop(controller)


def test_a_gain_set_later_is_checked_too():
    controller = StateFeedback(_gain())
    controller.gain = torch.zeros(1, 2, dtype=torch.int64)
    with pytest.raises(ValueError, match="gain must be a floating tensor"):
        _loop(controller)


def test_a_valid_reference_set_later_runs_as_one_given_to_the_constructor():
    reference = torch.tensor([0.5, -0.2], dtype=F64)
    later = StateFeedback(_gain())
    later.reference = reference
    given = _loop(StateFeedback(_gain(), reference))
    torch.testing.assert_close(_loop(later).trajectories.us, given.trajectories.us,
                               rtol=0, atol=0)  # fmt: skip
