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


# -- a second trial (2026-12-07) ------------------------------------------------------------


def _log_normal(v, var):
    return -0.5 * v * v / var - 0.5 * math.log(2 * math.pi * var)


def test_a_sensor_whose_range_alone_arrived_is_weighed_by_the_ranges_marginal():
    """Only sensor 1's range received: the clean term read the missing bearing as data and
    the box its 2-D density (−7.25 for both particles); the truth is the range's marginal
    ``log((1 − η̄) Σ_c π_c N(r; 0, var_c) + η̄ / 90)``."""
    from difffilter.models.tracking import PerSensorDeception, TrackingModel

    model, eta = TrackingModel(), 0.2
    likelihood = PerSensorDeception(eta, (-10, -math.pi / 2), (80, math.pi / 2), 4)
    x = torch.tensor([[20.0, 0.3, 20.0, 0.3], [21.0, 0.3, 19.0, 0.3]], dtype=torch.float64)
    y = torch.tensor([14.0, 0.0, 0, 0, 0, 0, 0, 0], dtype=torch.float64)
    mask = torch.tensor([True, False] + [False] * 6)
    got = likelihood(model, y, x, 1, mask)
    for i in range(2):
        r = 14.0 - math.hypot(x[i, 0].item() - 10, x[i, 2].item() - 10)
        clean = 0.8 * math.exp(_log_normal(r, 4.0)) + 0.2 * math.exp(_log_normal(r, 25.0))
        assert float(got[i]) == pytest.approx(math.log((1 - eta) * clean + eta / 90.0), abs=1e-12)
    # a range outside the box has no attacked term; a sensor received whole is as before
    outside = likelihood(model, torch.tensor([95.0] + [0.0] * 7, dtype=torch.float64), x, 1, mask)
    r = 95.0 - math.hypot(x[0, 0].item() - 10, x[0, 2].item() - 10)
    clean = 0.8 * math.exp(_log_normal(r, 4.0)) + 0.2 * math.exp(_log_normal(r, 25.0))
    assert float(outside[0]) == pytest.approx(math.log((1 - eta) * clean), rel=1e-12)
    whole = torch.tensor([True, True] + [False] * 6)
    y2 = torch.tensor([14.0, 0.2] + [0.0] * 6, dtype=torch.float64)
    unmasked = likelihood(model, y2, x, 1, None)
    others = torch.tensor([False, False] + [True] * 6)  # sensors 2–4
    sensor_one = unmasked - likelihood(model, y2, x, 1, others)
    torch.testing.assert_close(likelihood(model, y2, x, 1, whole), sensor_one, rtol=0, atol=1e-12)


def test_the_glint_density_ignores_what_an_unreceived_entry_holds():
    """NaN, inf or 1e200 in an entry not received made its sensor's term NaN (0 · inf)."""
    from difffilter.models.tracking import TrackingModel

    model = TrackingModel()
    noise = model.measurement_noise
    mask = torch.tensor([True, True] + [False] * 6)
    clean = torch.tensor([1.0, 0.01] + [0.0] * 6, dtype=torch.float64)
    for junk in (math.nan, math.inf, 1e200):
        value = clean.clone()
        value[2:] = junk
        assert float(noise.log_prob(value, mask)) == float(noise.log_prob(clean, mask))
    x = torch.tensor([[20.0, 0.3, 20.0, 0.3], [21.0, 0.3, 19.0, 0.3]], dtype=torch.float64)
    y = torch.tensor([[30.0, 0.5] + [math.nan] * 6], dtype=torch.float64)
    per_particle = model.measurement_log_prob(y, x, 1, mask.expand(2, 8))
    one_row = model.measurement_log_prob(y, x, 1, mask[None])  # the Round-Robin fast path
    assert bool(torch.isfinite(per_particle).all())
    torch.testing.assert_close(
        per_particle, one_row.reshape(per_particle.shape), rtol=0, atol=1e-12
    )
