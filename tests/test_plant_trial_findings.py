"""Findings of red-team trials of the four-tank and robot plants: models built under
inference mode, the linearised filter after a plant edit, gradients at an empty tank, and
the plants' input checks. Each test failed on the code before its fix."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.fdi.mdpf import adaptive_particle_filter
from difffilter.models.four_tank import FourTankModel, FourTankParameters
from difffilter.models.four_tank_estimators import linearised_four_tank
from difffilter.models.robot import RobotModel, RobotScenario
from difffilter.models.tracking import TrackingModel

D = torch.float64


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def test_a_four_tank_model_built_under_inference_mode_runs_as_one_built_outside():
    # its caches read tensor._version, which inference tensors lack: the EKF, transition on
    # 4096 entries or more and the PF had failed ("Inference tensors do not track version")
    ref = FourTankModel(dtype=D)
    _, ys, _ = ref.simulate(5, (2,), generator=_gen())
    with torch.inference_mode():
        want = df.extended_kalman_filter(ref, ys).means
        model = FourTankModel(dtype=D)
        got = df.extended_kalman_filter(model, ys).means
        x = model.initial.mean.expand(1024, 4).clone()
        big = model.transition(x, None, 0)
        pf = df.particle_filter(model, ys, num_particles=1000, generator=_gen(1)).means
        pf_ref = df.particle_filter(ref, ys, num_particles=1000, generator=_gen(1)).means
    assert torch.equal(got, want)
    assert torch.equal(big, ref.transition(x.clone(), None, 0))
    # (an inference model's noise factor is not cached: a triangular product for the
    # cached diagonal one, round-off apart)
    torch.testing.assert_close(pf, pf_ref, rtol=1e-12, atol=1e-12)


def test_other_models_built_under_inference_mode_run():
    # (the tracking model's sampler stamp and the adaptive PF's noise key failed alike)
    with torch.inference_mode():
        tracking = TrackingModel()
        _, ys, _ = tracking.simulate(6, (2,), generator=_gen())
        assert torch.isfinite(
            df.particle_filter(tracking, ys, num_particles=50, generator=_gen()).means
        ).all()
        eye = torch.eye(2, dtype=D)
        linear = df.LinearGaussianModel(
            0.9 * eye, eye, 0.1 * eye, 0.1 * eye, torch.zeros(2, dtype=D), eye, B=eye
        )
        us = torch.ones(2, 6, 2, dtype=D)
        _, ys, _ = linear.simulate(6, (2,), us, generator=_gen())
        out = adaptive_particle_filter(linear, ys, us, num_particles=20, generator=_gen())
        assert torch.isfinite(out.means).all()


def test_the_linearised_filter_follows_a_plant_edited_in_place():
    # x* had been the parameters' while the plant edited as transition's docstring says ran
    # elsewhere: 0.025 cm of drift a step, RMSE 0.096 against the EKF's 0.030
    new = FourTankModel(dtype=D, params=FourTankParameters(v=(3.3, 3.3)))
    model = FourTankModel(dtype=D)
    with torch.no_grad():
        model.step_offset.copy_(new.step_offset)
        model.inflow.copy_(new.inflow)
    lin, x_star = linearised_four_tank(model)
    assert (model.transition(x_star, None, 0) - x_star).abs().max() < 1e-12
    torch.testing.assert_close(
        x_star, torch.tensor(new.params.fixed_point(), dtype=D), rtol=1e-12, atol=0
    )
    xs, ys, _ = model.simulate(100, (10,), generator=_gen())
    kf = df.kalman_filter(lin, ys - x_star).means + x_star
    ekf = df.extended_kalman_filter(model, ys).means
    rmse = lambda a: ((a - xs) ** 2).sum(-1).mean().sqrt()  # noqa: E731
    assert rmse(kf) < 1.2 * rmse(ekf)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_an_unedited_plant_keeps_the_parameters_fixed_point_bit_for_bit(dtype):
    # (the demo's kf_linearised numbers are made from it)
    model = FourTankModel(dtype=dtype)
    assert torch.equal(model.fixed_point(), torch.tensor(model.params.fixed_point(), dtype=dtype))


def test_the_parameters_are_not_reassignable():
    model = FourTankModel(dtype=D)
    with pytest.raises(AttributeError, match="params are folded into the model's buffers"):
        model.params = FourTankParameters(v=(3.3, 3.3))


def test_the_gradient_from_empty_tanks_is_the_jacobians_convention():
    # autograd through sqrt(clamp(x)) had given inf at h = 0 and 0·inf = NaN: an EKF's
    # gradient from empty tanks [-inf, -inf, inf, inf]
    model = FourTankModel(dtype=D)
    x = torch.tensor([12.0, 12.0, 0.0, 1.4], dtype=D)
    jac = torch.autograd.functional.jacobian(lambda v: model.transition(v, None, 0), x)
    torch.testing.assert_close(jac, model.transition_jacobian(x, None, 0), rtol=1e-12, atol=1e-12)
    x0 = torch.zeros(4, dtype=D, requires_grad=True)
    empty = FourTankModel(dtype=D, x0=x0.detach())
    _, ys, _ = FourTankModel(dtype=D).simulate(10, (2,), generator=_gen())
    empty.initial.loc = x0  # (the prior mean the gradient is taken of)
    out = df.extended_kalman_filter(empty, ys)
    (grad,) = torch.autograd.grad(out.means.sum(), x0)
    assert torch.isfinite(grad).all()


def test_a_plants_values_are_unchanged_where_no_gradient_is_taken():
    model = FourTankModel(dtype=D)
    x = torch.tensor([[12.0, 12.0, 0.0, -1.0], [1.0, 2.0, 3.0, 4.0]], dtype=D)
    s = torch.sqrt(x.clamp_min(0.0))
    want = x + model.step_offset + s * model.step_diag + s[:, [2, 3, 2, 3]] * model.step_couple
    torch.testing.assert_close(
        model.transition(x.requires_grad_(), None, 0), want, rtol=0, atol=1e-15
    )


@pytest.mark.parametrize("kwargs,match", [
    ({"x0": [1.0, 2.0, 3.0]}, "x0 must be four tank levels"),
    ({"x0": [float("nan"), 12.0, 1.6, 1.4]}, "x0 contains NaN"),
    ({"dtype": torch.int64}, "dtype must be torch.float32 or torch.float64"),
    ({"dtype": torch.float16}, "dtype must be torch.float32 or torch.float64"),
])  # fmt: skip
def test_the_four_tank_arguments_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        FourTankModel(**kwargs)


@pytest.mark.parametrize("value", [-1.0, float("nan"), 0.0])
def test_robot_dt_assigned_later_is_checked(value):
    # dt = -1 had run the robot backwards and NaN simulated NaN states, without a word
    model = RobotModel()
    with pytest.raises(ValueError, match="dt must be a finite number > 0"):
        model.dt = value
    model.dt = 0.5
    x, u = torch.zeros(3, dtype=D), torch.tensor([2.0, 0.0], dtype=D)
    torch.testing.assert_close(model.transition(x, u, 0), torch.tensor([1.0, 0.0, 0.0], dtype=D))


def test_robot_sensor_positions_must_be_finite():
    sensors = [(float("nan"), 0.0), (10.0, 10.0)]
    with pytest.raises(ValueError, match="sensors contains NaN"):
        RobotModel(sensors=sensors)
    model = RobotModel()
    with torch.no_grad():
        model.sensor_pos[0, 0] = float("inf")
    with pytest.raises(ValueError, match="model.sensor_pos contains NaN or Inf"):
        model.simulate(5, (2,), torch.ones(2, 5, 2, dtype=D), generator=_gen())


@pytest.mark.parametrize("name,value,count", [("x0", (0.0, 0.0), 3), ("p0", (1.0,), 3),
                                              ("filter_q", (1.0, 1.0), 3), ("input_var", (1.0, 1.0, 1.0), 2)])  # fmt: skip
def test_robot_constructor_names_its_arguments(name, value, count):
    # (Gaussian had said "loc must have shape [..., 2]")
    with pytest.raises(ValueError, match=rf"{name} must be {count} numbers"):
        RobotModel(**{name: value})


@pytest.mark.parametrize("indices", [[True, False, True, False, False, False], [1, 1, 2]])
def test_robot_groups_of_a_mask_or_repeated_sensors_are_named(indices):
    # (a bool mask and a repeated index failed as "cov must be positive definite")
    with pytest.raises(ValueError, match="distinct ints"):
        RobotModel().group(indices)


@pytest.mark.parametrize("kwargs", [{"turn_rate_range_deg": (0.0, 15.0, 30.0)}, {"turn_rate_range_deg": 15.0},
                                    {"turn_rate_range_deg": (float("nan"), 1.0)}, {"attack_from": True}])  # fmt: skip
def test_robot_scenario_fields_are_checked_at_construction(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        RobotScenario(name="robot_probe", **kwargs)
