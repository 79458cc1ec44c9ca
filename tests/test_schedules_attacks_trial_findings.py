"""The papers' attacks and a custom scenario's schedule (a red-team trial).

* ``Signal`` flagged a step when any entry was non-zero, so under a Round-Robin a step that
  received only the clean entries was labelled attacked (the labels of TPR, FPR and delay).
* ``ActuatorInjection("20")`` was the attack (2, 0): a string split into its characters.
* ``CustomScenario(protocol="round_robin")`` was built and failed at its first simulate.
"""

import numpy as np
import pytest
import torch

from difffilter.models.attacks import ActuatorInjection, Signal
from difffilter.models.scenario import CustomScenario
from difffilter.models.schedules import RoundRobin
from difffilter.models.streams import Streams
from difffilter.ssm import LinearGaussianModel
from difffilter.threats import Bias


def _plant(dtype):
    eye = torch.eye(2, dtype=dtype)
    return LinearGaussianModel(
        0.9 * eye, eye, 0.01 * eye, 0.01 * eye, torch.zeros(2, dtype=dtype), eye
    )


def _flags(attack, steps=6):
    scenario = CustomScenario(name="x", family="x", description="", model_fn=_plant, attack=attack,
                              protocol=RoundRobin(((0,), (1,))), steps=steps, runs=1)  # fmt: skip
    return scenario.simulate(1, Streams(0).simulation()).flags[0].tolist()


def test_a_signal_flags_only_the_steps_whose_attacked_entries_arrived():
    signal = Signal(torch.tensor([[0.5, 0.0]] * 6, dtype=torch.float64))
    truth = _flags(Bias(value=0.5, entries=[0]))
    assert truth == [True, False] * 3
    assert _flags(signal) == truth  # was every step


def test_a_signal_without_a_schedule_flags_its_non_zero_steps():
    values = torch.zeros(5, 2, dtype=torch.float64)
    values[2, 1] = 1.0
    _, flags = Signal(values).sample((3,), 5, 2, dtype=torch.float64)
    assert flags.shape == (3, 5, 2)
    assert flags.any(-1).tolist() == [[False, False, True, False, False]] * 3


@pytest.mark.parametrize("value", ["20", True, (True, False), b"12"])
def test_an_actuator_injection_of_no_numbers_is_refused(value):
    with pytest.raises(ValueError, match="value must be a non-empty sequence of finite numbers"):
        ActuatorInjection(value)


@pytest.mark.parametrize("value", [(1, 2), [1.0, 2.0], torch.tensor([1.0, 2.0]), np.array([1, 2])])
def test_an_actuator_injection_takes_any_sequence_of_numbers(value):
    assert ActuatorInjection(value).value == (1.0, 2.0)


@pytest.mark.parametrize(
    "protocol", ["round_robin", ((0,), (1,)), {"kind": "round_robin"}, RoundRobin]
)
def test_a_custom_scenario_protocol_that_is_no_schedule_is_refused(protocol):
    with pytest.raises(TypeError, match="protocol must be a schedule object"):
        CustomScenario(name="x", family="x", description="", model_fn=_plant, protocol=protocol)
