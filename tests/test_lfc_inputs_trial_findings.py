"""Findings of a red-team trial of the LFC plant's attack tables (2026-12-06): inputs that
gave wrong or NaN tables, or raw errors, are refused by name."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from difffilter.models import registry
from difffilter.models.lfc import random_attacks, sawtooth_pulse_train, scenario_attack


def test_integer_sample_times_are_refused():
    # the table took their dtype: every value truncated (the step attack all zeros)
    with pytest.raises(ValueError, match="t must be a 1-D floating tensor"):
        scenario_attack("step", torch.arange(1, 11))
    assert scenario_attack("step", torch.arange(1, 11, dtype=torch.float64))[2, 2] == 0.4


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"amplitude": (0.1, math.inf)}, "amplitude must be"),
        ({"dt": math.nan}, "dt must be a finite"),
        ({"dt": 0.0}, "dt must be"),
        ({"channels": (2.0,)}, "channels must be integer indices"),
        ({"channels": (True,)}, "channels must be integer indices"),
    ],
)
def test_random_attacks_refuse_what_made_nan_or_raw_errors(kwargs, message):
    args = {"dt": 0.01, **kwargs}
    dt = args.pop("dt")
    with pytest.raises(ValueError, match=message):
        random_attacks(2, 100, dt, generator=torch.Generator().manual_seed(0), **args)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"width": math.inf}, "positive and finite"), ({"start": 5.0, "stop": 1.0}, "stop >= start")],
)
def test_the_sawtooth_refuses_what_made_nan_or_raw_errors(kwargs, message):
    with pytest.raises(ValueError, match=message):
        sawtooth_pulse_train(torch.linspace(0, 10, 11, dtype=torch.float64), **kwargs)


def test_an_infinite_duration_is_refused():
    with pytest.raises(ValueError, match="both finite"):
        dataclasses.replace(registry.get("lfc_step"), duration=math.inf)
