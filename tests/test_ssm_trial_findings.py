"""Findings of a trial of the models and their simulation (difffilter/ssm.py, noise.py): a
nonlinear model converted to float32 whose functions promote to float64, a noise mean
written NaN, ``simulate``'s ``batch_shape``, a ``scale_tril`` with entries above its
diagonal, and a prior of another dimension assigned since built."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter.noise import Gaussian, GaussianMixture
from difffilter.ssm import LinearGaussianModel, NonlinearGaussianModel

F64 = torch.float64


def _linear():
    eye = torch.eye(2, dtype=F64)
    return LinearGaussianModel(0.9 * eye, torch.ones(1, 2, dtype=F64), eye,
                               torch.eye(1, dtype=F64), torch.zeros(2, dtype=F64), eye)  # fmt: skip


def _nonlinear(transition, dtype=F64):
    eye = torch.eye(2, dtype=dtype)
    return NonlinearGaussianModel(transition, lambda x: x[..., :1], 0.1 * eye,
                                  torch.eye(1, dtype=dtype), torch.zeros(2, dtype=dtype), eye)  # fmt: skip


def test_a_nonlinear_model_converted_to_a_dtype_its_transition_does_not_keep_is_refused():
    gain = torch.tensor([0.9, 0.5], dtype=F64)  # a float64 constant inside f

    def promoting(x):
        return x * gain

    with pytest.raises(ValueError, match="transition returns torch.float64"):
        _nonlinear(promoting, torch.float32)  # built in float32: refused, as before
    model = _nonlinear(promoting)
    with pytest.raises(ValueError, match="transition returns torch.float64") as caught:
        model.to(torch.float32)  # had been taken: float64 xs beside a float32 x0
    assert "the model was not converted: it stays torch.float64" in caught.value.__notes__[0]
    assert model.initial.mean.dtype == model.process_noise.cov.dtype == F64
    xs, ys, x0 = model.simulate(3, (2,), generator=torch.Generator().manual_seed(0))
    assert xs.dtype == ys.dtype == x0.dtype == F64
    kept = _nonlinear(lambda x: 0.5 * x).float()  # a transition that keeps x's dtype converts
    xs, ys, x0 = kept.simulate(3, (2,), generator=torch.Generator().manual_seed(0))
    assert xs.dtype == ys.dtype == x0.dtype == torch.float32


@pytest.mark.parametrize("noise", ["process_noise", "measurement_noise"])
def test_a_noise_mean_written_non_finite_is_named_by_simulate_and_the_filters(noise):
    model = _linear()
    _, ys, _ = model.simulate(3, (2,), generator=torch.Generator().manual_seed(0))
    state = model.state_dict()
    state[f"{noise}.loc"] = torch.full_like(state[f"{noise}.loc"], float("nan"))
    model.load_state_dict(state)
    for run in (lambda: model.simulate(3, (2,)), lambda: df.kalman_filter(model, ys),
                lambda: df.particle_filter(model, ys, num_particles=16,
                                           generator=torch.Generator().manual_seed(0))):  # fmt: skip
        with pytest.raises(ValueError, match=f"model.{noise}'s mean \\(loc\\) contains NaN"):
            run()
    with torch.no_grad():  # written back in place: followed
        getattr(model, noise).loc.zero_()
    torch.testing.assert_close(df.kalman_filter(model, ys).means,
                               df.kalman_filter(_linear(), ys).means)  # fmt: skip


def test_a_mixture_noise_written_since_built_is_checked():
    model = _linear()
    mixture = GaussianMixture(torch.tensor([0.5, 0.5], dtype=F64), torch.zeros(2, 1, dtype=F64),
                              torch.stack([torch.eye(1, dtype=F64)] * 2))  # fmt: skip
    model.measurement_noise = mixture
    _, ys, _ = model.simulate(4, (2,), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        mixture.locs[0, 0] = float("inf")
    with pytest.raises(ValueError, match="model.measurement_noise's locs contains NaN or Inf"):
        df.particle_filter(model, ys, num_particles=16)
    with torch.no_grad():
        mixture.locs[0, 0] = 0.0
    df.particle_filter(model, ys, num_particles=16, generator=torch.Generator().manual_seed(0))


def test_simulates_batch_shape_is_checked_as_num_steps_is():
    model = _linear()
    for bad in (True, False, (-1,), (2, True), "3", 2.5, (2.0,)):
        with pytest.raises(ValueError, match="batch_shape must be a tuple of integers >= 0"):
            model.simulate(2, bad)
    for good, runs in ((np.int64(4), (4,)), ((np.int64(2), 3), (2, 3)), (torch.Size([2]), (2,)),
                       (3, (3,)), ((), ()), ((0,), (0,))):  # fmt: skip
        assert model.simulate(2, good)[2].shape == (*runs, 2)
    with pytest.raises(ValueError, match="batch_shape must be a tuple of integers >= 1"):
        df.KalmanFilter().init(model, True)


def test_a_scale_tril_with_entries_above_its_diagonal_is_refused():
    upper = torch.tensor([[1.0, 0.8], [0.0, 0.5]], dtype=F64)  # scipy's default factor form
    with pytest.raises(ValueError, match="scale_tril must be lower triangular"):
        Gaussian(torch.zeros(2, dtype=F64), scale_tril=upper)
    lower = Gaussian(torch.zeros(2, dtype=F64), scale_tril=upper.T)
    torch.testing.assert_close(lower.cov, upper.T @ upper)
    model = _linear()
    model.process_noise = lower
    model.simulate(2, (2,))
    with torch.no_grad():  # written since: refused where the model is used
        lower._scale_tril.copy_(upper.clone())
    with pytest.raises(ValueError, match="model.process_noise's scale_tril must be lower"):
        model.simulate(2, (2,))


@pytest.mark.parametrize("kind", ["linear", "nonlinear"])
def test_a_prior_of_another_dimension_assigned_since_built_is_named(kind):
    model = _linear() if kind == "linear" else _nonlinear(lambda x: 0.9 * x)
    model.initial = Gaussian(torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    # (the nonlinear model had broadcast it over both states: x0 [B, 1], both states equal)
    with pytest.raises(ValueError, match="model.initial has dimension 1 and the model 2 states"):
        model.simulate(3, (4,))
    with pytest.raises(ValueError, match="model.initial has dimension 1"):
        df.unscented_kalman_filter(model, torch.zeros(3, 1, dtype=F64))
    model.initial = Gaussian(torch.ones(2, dtype=F64), torch.eye(2, dtype=F64))
    assert model.simulate(3, (4,))[2].shape == (4, 2)


def test_simulates_inputs_of_other_runs_are_named_against_the_runs_not_ys():
    eye = torch.eye(2, dtype=F64)
    model = LinearGaussianModel(0.9 * eye, eye, eye, eye, torch.zeros(2, dtype=F64), eye, B=eye)
    with pytest.raises(ValueError, match=r"does not broadcast with the runs' \(4,\)"):
        model.simulate(3, (4,), us=torch.zeros(3, 3, 2, dtype=F64))


def test_a_mixture_prior_still_runs_and_batch_shapes_of_arrays_and_tensors():
    """A review: a GaussianMixture prior (any noise model may be one) had failed every use
    on the new written-since check; an integer tensor batch_shape had been refused."""
    eye = torch.eye(2, dtype=F64)
    model = _linear()
    model.initial = GaussianMixture(torch.tensor([0.5, 0.5], dtype=F64),
                                    torch.tensor([[1.0, 0.0], [-1.0, 0.0]], dtype=F64),
                                    torch.stack([0.1 * eye, 0.1 * eye]))  # fmt: skip
    _, ys, _ = model.simulate(5, (3,), generator=torch.Generator().manual_seed(0))
    df.particle_filter(model, ys, num_particles=32, generator=torch.Generator().manual_seed(1))
    model = _linear()
    for shape, runs in ((torch.tensor([2, 3]), (2, 3)), (np.array([2, 3]), (2, 3)),
                        (np.array(3), (3,)), (torch.tensor(4), (4,))):  # fmt: skip
        assert model.simulate(2, shape)[2].shape == (*runs, 2)
    with pytest.raises(ValueError, match="batch_shape must be a tuple of integers"):
        model.simulate(2, torch.tensor([2.5]))
