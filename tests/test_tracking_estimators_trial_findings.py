"""Findings of a red-team trial of the tracking plant's likelihoods (2026-12-06), against
the generic density ``log p(y − h(x))``."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.models.tracking import PerSensorDeception, TrackingModel, communication_counts
from difffilter.ssm import StateSpaceModel


def _round_robin_case(model):
    x = model.sample_initial((2, 50), torch.Generator().manual_seed(0))
    mask = torch.zeros(2, 1, 8, dtype=torch.bool)
    mask[:, 0, 0:2] = True  # sensor 1's range and bearing
    return x, mask


def _generic(model, y, x, mask):
    return StateSpaceModel.measurement_log_prob(model, y, x, 1, mask)


def test_the_round_robin_shortcut_reads_the_sensor_where_it_is_now():
    # its position had been kept from construction: 42 nats off after a move in place
    model = TrackingModel()
    x, mask = _round_robin_case(model)
    with torch.no_grad():
        model.sensor_pos[0] = torch.tensor([12.0, 9.0], dtype=torch.float64)
    y = model.observe(x[:, :1], 1)
    fast = model.measurement_log_prob(y, x, 1, mask)
    assert torch.allclose(fast, _generic(model, y, x, mask), rtol=0, atol=1e-10)


class _RangeOffset(TrackingModel):
    def observe(self, x, k):
        y = super().observe(x, k).clone()
        y[..., 0::2] += 3.0
        return y


def test_a_plant_of_its_own_measurement_function_takes_the_generic_density():
    model = _RangeOffset()
    x, mask = _round_robin_case(model)
    y = model.observe(x[:, :1], 1)
    fast = model.measurement_log_prob(y, x, 1, mask)
    assert torch.equal(fast, _generic(model, y, x, mask))  # 1.8-2.3 nats apart before


def test_learnable_sensor_positions_get_their_gradient_on_the_shortcut():
    model = TrackingModel()
    x, mask = _round_robin_case(model)
    model.sensor_pos = model.sensor_pos.clone().requires_grad_(True)
    y = (model.observe(x[:, :1], 1) + 0.5).detach()
    (fast,) = torch.autograd.grad(model.measurement_log_prob(y, x, 1, mask).sum(), model.sensor_pos)
    (generic,) = torch.autograd.grad(_generic(model, y, x, mask).sum(), model.sensor_pos)
    assert torch.allclose(fast, generic, rtol=1e-9, atol=1e-9) and bool(fast.abs().sum() > 0)


LOW, HIGH = (-10.0, -math.pi / 2), (80.0, math.pi / 2)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((-0.1, LOW, HIGH, 4), r"rate .* must lie in \[0, 1\]"),
        ((1.5, LOW, HIGH, 4), r"rate .* must lie in \[0, 1\]"),
        ((float("nan"), LOW, HIGH, 4), "rate must be a finite"),
        ((0.2, HIGH, LOW, 4), "low below high"),
        ((0.2, LOW, (1.0, 2.0, 3.0), 4), "two finite"),
        ((0.2, LOW, HIGH, 0), "sensors must be an integer >= 1"),
    ],
)
def test_the_per_sensor_deception_checks_its_arguments(args, message):
    with pytest.raises(ValueError, match=message):
        PerSensorDeception(*args)


def test_communication_counts_are_per_run_of_the_sensors_given():
    shared = torch.ones(8, 8, dtype=torch.bool)  # [T, dy], every run the same
    assert communication_counts(shared, 3, 8).tolist() == [32, 32, 32]
    with pytest.raises(ValueError, match="mask holds 4 entries; 4 sensors send 8"):
        communication_counts(torch.ones(3, 8, 4, dtype=torch.bool), 3, 8)
    assert (
        communication_counts(torch.ones(3, 8, 4, dtype=torch.bool), 3, 8, sensors=2).tolist()
        == [16] * 3
    )


@pytest.mark.parametrize("gamma_ini", ["2", True, 2.0])
def test_the_first_sensor_is_an_integer(gamma_ini):
    import dataclasses

    from difffilter.models import registry

    with pytest.raises(ValueError, match="gamma_ini must be a sensor number"):
        dataclasses.replace(registry.get("tracking_rrp_deception"), gamma_ini=gamma_ini)
