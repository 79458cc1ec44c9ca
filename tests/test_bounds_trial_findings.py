"""Findings of a red-team trial of the posterior Cramér–Rao bound (each failed before its
fix)."""

from __future__ import annotations

import warnings

import pytest
import torch

import difffilter as df
from difffilter.bounds import noise_information
from difffilter.noise import Gaussian, GaussianMixture, UniformBox

D = torch.float64
F = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=D)
H = torch.tensor([[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]], dtype=D)
Q, R = 0.1 * torch.eye(2, dtype=D), torch.eye(3, dtype=D)
M0, P0 = torch.zeros(2, dtype=D), torch.eye(2, dtype=D)


class _MixtureNoiseAR(df.StateSpaceModel):
    """x' = 0.9 x + w, w a zero-mean Gaussian mixture (its Fisher information 87, 1/cov 0.99)."""

    dim_x, dim_y, dim_u = 1, 1, 0

    def __init__(self):
        super().__init__()
        self.initial = Gaussian(torch.zeros(1, dtype=D), torch.eye(1, dtype=D))
        self.process_noise = GaussianMixture(torch.tensor([0.9, 0.1], dtype=D), torch.zeros(2, 1, dtype=D),
                                             torch.tensor([[[0.01]], [[10.0]]], dtype=D))  # fmt: skip
        self.measurement_noise = Gaussian(torch.zeros(1, dtype=D), 0.5 * torch.eye(1, dtype=D))

    def transition(self, x, u, k):
        return 0.9 * x

    def observe(self, x, k):
        return x.clone()


def test_a_process_noise_that_is_not_gaussian_is_refused():
    """Q⁻¹ stood for the noise's Fisher information: a mixture's is 87 where 1/cov is 0.99,
    and a particle filter beat the "bound" by 0.55×."""
    model = _MixtureNoiseAR()
    xs = torch.zeros(4, 3, 1, dtype=D)
    with pytest.raises(ValueError, match="needs a Gaussian process noise"):
        df.posterior_crb(model, xs, torch.zeros(4, 1, dtype=D))


def test_a_model_drawing_its_own_transitions_is_warned_unless_it_says_its_law():
    """The robot draws B(θ) n, not N(0, process_cov): its EKF came within 0.86 of the bound."""
    from difffilter.models.robot import RobotModel
    from difffilter.models.tracking import TrackingModel

    robot = RobotModel()
    us = torch.zeros(2, 3, 2, dtype=robot.initial.cov.dtype)
    xs = robot.initial.mean.expand(2, 3, 3).clone()
    with pytest.warns(UserWarning, match="draws its transitions its own way"):
        df.posterior_crb(robot, xs, xs[:, 0], us=us)
    tracking = TrackingModel()
    xs, _, x0 = tracking.simulate(3, (2,), generator=torch.Generator().manual_seed(0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # its draw has the process noise's law: no warning
        df.posterior_crb(
            tracking, xs, x0, num_samples=500, generator=torch.Generator().manual_seed(0)
        )


def test_the_fisher_information_of_a_mixture_under_inference_mode_and_a_uniform_refused():
    """enable_grad does not lift inference mode: the score had failed in torch's "element 0
    of tensors does not require grad"; a uniform noise failed the same way, unnamed."""
    mix = GaussianMixture(
        torch.tensor([0.5, 0.5]), torch.zeros(2, 1), torch.tensor([[[1.0]], [[4.0]]])
    )
    plain = noise_information(mix, num_samples=500, generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        inferred = noise_information(
            mix, num_samples=500, generator=torch.Generator().manual_seed(0)
        )
    torch.testing.assert_close(inferred.clone(), plain)
    box = UniformBox(-torch.ones(2, dtype=D), torch.ones(2, dtype=D))
    with pytest.raises(ValueError, match="UniformBox's has no gradient"):
        noise_information(box, num_samples=10)


@pytest.mark.parametrize("which", ["observation_jacobian", "transition_jacobian"])
def test_a_constant_jacobian_bounds_as_the_kalman_filter(which):
    """A constant Jacobian, [dy, dx] or [dx, dx], broadcasts in the EKF; the bound failed in
    einsum or on an index."""
    linear = df.LinearGaussianModel(F, H, Q, R, M0, P0)
    xs, ys, x0 = linear.simulate(6, (1,), generator=torch.Generator().manual_seed(0))
    constant = {"observation_jacobian": lambda x: H, "transition_jacobian": lambda x: F}[which]
    model = df.NonlinearGaussianModel(lambda x: x @ F.T, lambda x: x @ H.T, Q, R, M0, P0,
                                      **{which: constant})  # fmt: skip
    bound = df.posterior_crb(model, xs, x0).bound
    torch.testing.assert_close(bound, df.kalman_filter(linear, ys).covs[0])


def test_bad_arguments_are_named():
    linear = df.LinearGaussianModel(F, H, Q, R, M0, P0)
    xs, _, x0 = linear.simulate(4, (5,), generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="at least one path and one step"):
        df.posterior_crb(linear, xs[:, :0], x0)
    with pytest.raises(ValueError, match="at least one path and one step"):
        df.posterior_crb(linear, xs[:0], x0[:0])
    bad = -torch.eye(3, dtype=D).expand(4, 3, 3)
    with pytest.raises(ValueError, match="positive semi-definite"):
        df.posterior_crb(linear, xs, x0, information=bad)
    with pytest.raises(ValueError, match="positive semi-definite"):
        df.posterior_crb(linear, xs, x0, information=torch.full((4, 3, 3), float("nan"), dtype=D))
    with pytest.raises(ValueError, match="information must be a tensor"):
        df.posterior_crb(linear, xs, x0, information=[[0.0]])
    mask = torch.ones(3, 4, 3, dtype=torch.bool)
    with pytest.raises(
        ValueError, match=r"batch \(3,\) does not broadcast with the paths' batch \(2,\)"
    ):
        df.posterior_crb(linear, xs.expand(2, 5, 4, 2), x0.expand(2, 5, 2), mask=mask)


def test_h_is_read_from_step_1():
    """No measurement at k = 0: a model defining H_k for k ≥ 1 alone failed on H_0."""
    steps = 6
    rows = {k: torch.tensor([[1.0, 0.1 * k]], dtype=D) for k in range(1, steps + 1)}
    eye = torch.eye(2, dtype=D)

    class Varying(df.LinearGaussianModel):
        time_varying = True

        def observation_matrix(self, k):
            return rows[k]

    model = Varying(eye, rows[1], 0.1 * eye, torch.ones(1, 1, dtype=D), M0, eye)
    xs, ys, x0 = model.simulate(steps, (1,), generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(
        df.posterior_crb(model, xs, x0).bound, df.kalman_filter(model, ys).covs[0]
    )
