"""Bad LFC inputs named where torch had failed without a word (an LFC trial): a gain K₁ of
another shape, sample times of no single axis, counts of random attacks that are no
integers (a scenario built with one had failed only at its simulation)."""

import pytest
import torch

from difffilter.kalman import KalmanFilter
from difffilter.models.lfc import (
    LFCPlant,
    LFCScenario,
    SecureController,
    lfc_loop,
    lqr_gain,
    random_attacks,
    sawtooth_pulse_train,
)

F64 = torch.float64


@pytest.mark.parametrize("K1", [torch.zeros(3, 10, dtype=F64), torch.zeros(2, 9, dtype=F64),
                                torch.zeros(2, 10, dtype=torch.int64), [[0.0] * 10] * 2])  # fmt: skip
def test_a_gain_of_another_shape_or_dtype_is_named(K1):
    plant = LFCPlant()
    xi = torch.zeros(2, 5, 10, dtype=F64)
    load = torch.tensor([0.01, 0.0], dtype=F64)
    with pytest.raises(ValueError, match=r"K1 must be a floating tensor \[2, 10\]"):
        lfc_loop(plant, KalmanFilter(), xi, xi, load, K1=K1)


def test_the_lqr_gain_given_explicitly_runs_as_the_default():
    plant = LFCPlant()
    gen = torch.Generator().manual_seed(3)
    xi = 1e-3 * torch.randn(2, 6, 10, dtype=F64, generator=gen)
    theta = 1e-3 * torch.randn(2, 6, 10, dtype=F64, generator=gen)
    load = torch.tensor([0.01, 0.0], dtype=F64)
    default = lfc_loop(plant, KalmanFilter(), xi, theta, load)
    given = lfc_loop(plant, KalmanFilter(), xi, theta, load, K1=lqr_gain(plant))
    torch.testing.assert_close(given.trajectories.x, default.trajectories.x, rtol=0, atol=0)
    assert SecureController(lqr_gain(plant), load).K1.shape == (2, 10)


@pytest.mark.parametrize("t", [torch.zeros(3, 4, dtype=F64), torch.tensor(0.5, dtype=F64)])
def test_sample_times_of_no_single_axis_are_named(t):
    with pytest.raises(ValueError, match=r"t must be a 1-D tensor of sample times \[T\]"):
        sawtooth_pulse_train(t)


def test_the_sawtooth_of_1d_times_is_unchanged():
    t = torch.tensor([0.0, 0.05, 0.1, 0.15, 0.5], dtype=F64)
    # pulses of width 0.2 centred at 0, 0.5, …: the ramp (τ + 0.1)/0.2 up to each delay
    expected = torch.tensor([0.5, 0.75, 0.0, 0.0, 0.5], dtype=F64)
    torch.testing.assert_close(sawtooth_pulse_train(t), expected)


@pytest.mark.parametrize("arg", ["num_runs", "steps", "min_events", "max_events"])
def test_counts_of_random_attacks_that_are_no_integers_are_named(arg):
    args = dict(num_runs=2, steps=5, dt=0.01, generator=torch.Generator().manual_seed(0),
                min_events=0, max_events=2)  # fmt: skip
    args[arg] = 1.5
    with pytest.raises(ValueError, match=f"{arg} must be an integer"):
        random_attacks(**args)


def test_a_random_scenario_of_a_fractional_count_is_refused_when_built():
    with pytest.raises(ValueError, match="max_events must be an integer"):
        LFCScenario(name="t", family="lfc", description="", attack="random", duration=0.1,
                    max_events=1.5)  # fmt: skip
