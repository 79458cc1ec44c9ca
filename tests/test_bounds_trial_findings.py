"""Findings of a red-team trial of the posterior Cramér–Rao bound (each failed before its
fix)."""

from __future__ import annotations

import warnings

import pytest
import torch

import difffilter as df
from difffilter.bounds import gaussian_information, noise_information
from difffilter.noise import Gaussian, GaussianMixture, NoiseModel, UniformBox

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


# -- a second red-team trial ----------------------------------------------------------


def test_a_float32_model_is_bounded_as_in_float64():
    """J = D22 − D21 (J + D11)⁻¹ D12 subtracts two matrices of size ‖Q⁻¹‖ (here ~1e5) to
    get one of size ~1: in float32 the "bound" was 0.79×–1.78× the Kalman filter's
    covariance, above the optimal filter's MSE at step 1 (1.000 against 0.909)."""
    dt = 0.01
    F64 = torch.tensor([[1.0, dt], [0.0, 1.0]], dtype=D)
    Q64 = torch.tensor([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]], dtype=D)
    args = (F64, torch.tensor([[1.0, 0.0]], dtype=D), Q64, torch.eye(1, dtype=D),
            torch.zeros(2, dtype=D), 10 * torch.eye(2, dtype=D))  # fmt: skip
    m32 = df.LinearGaussianModel(*(a.float() for a in args))
    # the float64 truth on the float32 model's own (rounded) numbers: the Riccati recursion
    m64 = df.LinearGaussianModel(*(a.float().double() for a in args))
    xs, ys, x0 = m32.simulate(60, (1,), generator=torch.Generator().manual_seed(0))
    bound = df.posterior_crb(m32, xs, x0).bound
    assert bound.dtype == torch.float32
    exact = df.kalman_filter(m64, ys.double()).covs[0]
    torch.testing.assert_close(bound, exact.float(), rtol=1e-5, atol=0.0)


class _LaplaceMeasured(df.LinearGaussianModel):
    """y = x + v, v ~ Laplace of variance R (scale b = √(R/2)), drawn and weighed so."""

    def _b(self):
        return (self.measurement_noise.cov.diagonal() / 2).sqrt()

    def sample_measurement(self, x, k, generator=None):
        mean = self.observe(x, k)
        u = torch.rand(mean.shape, generator=generator, dtype=mean.dtype) - 0.5
        return mean - self._b() * u.sign() * torch.log1p(-2 * u.abs())

    def measurement_log_prob(self, y, x, k, mask=None):
        r = self.measurement_residual(y, self.observe(x, k))
        lp = -r.abs() / self._b() - torch.log(2 * self._b())
        return (lp if mask is None else lp * mask).sum(-1)


def test_a_model_drawing_its_own_measurements_is_warned_unless_it_says_its_law():
    """Laplace noise of variance R has J_v = 2/R, the Gaussian of that variance 1/R: the
    bound from measurement_noise was beaten by a particle filter (0.84×), unsaid."""
    eye = torch.eye(1, dtype=D)
    model = _LaplaceMeasured(eye, eye, 0.05 * eye, eye, torch.zeros(1, dtype=D), eye)
    xs, _, x0 = model.simulate(8, (3,), generator=torch.Generator().manual_seed(0))
    with pytest.warns(UserWarning, match=r"its own way \(sample_measurement"):
        df.posterior_crb(model, xs, x0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # information= is the law's: no warning
        bound = df.posterior_crb(model, xs, x0, information=torch.full((8, 1, 1), 2.0, dtype=D))
    J, floor = 1.0, []  # scalar recursion J' = (Q + 1/J)⁻¹ + 2/R (F = H = 1, R = 1)
    for _ in range(8):
        J = 1 / (0.05 + 1 / J) + 2.0
        floor.append(1 / J)
    torch.testing.assert_close(bound.bound[:, 0, 0], torch.tensor(floor, dtype=D))


def test_a_time_varying_q_or_r_is_checked_and_a_singular_q_named():
    """Q_k and R_k were read unchecked (an indefinite R_3 gave a "bound" with eigenvalue
    15.3 where the Kalman filter refuses the model), and a singular Q_k died in torch's
    "linalg.inv: The diagonal element 1 is zero"."""
    eye = torch.eye(2, dtype=D)
    bad = torch.diag(torch.tensor([1.0, -0.5], dtype=D))

    class BadR(df.LinearGaussianModel):
        time_varying = True

        def measurement_cov(self, k):
            return bad if k == 3 else self.measurement_noise.cov

    class BadQ(df.LinearGaussianModel):
        time_varying = True

        def process_cov(self, k):
            return 0.1 * bad if k == 2 else self.process_noise.cov

    class SingularQ(df.LinearGaussianModel):
        time_varying = True

        def process_cov(self, k):  # white acceleration on the velocity alone from step 1
            return torch.tensor([[0.0, 0.0], [0.0, 0.1]], dtype=D) if k >= 1 else eye

    xs, x0 = torch.zeros(1, 5, 2, dtype=D), torch.zeros(1, 2, dtype=D)
    for cls, name in ((BadR, r"BadR\.measurement_cov\(3\)"), (BadQ, r"BadQ\.process_cov\(2\)")):
        model = cls(eye, eye, 0.1 * eye, eye, torch.zeros(2, dtype=D), eye)
        with pytest.raises(ValueError, match=name + ".*positive semi-definite"):
            df.kalman_filter(model, xs)  # the filters' contract, which the bound now shares
        with pytest.raises(ValueError, match=name + ".*positive semi-definite"):
            df.posterior_crb(model, xs, x0)
    model = SingularQ(F, eye, 0.1 * eye, eye, torch.zeros(2, dtype=D), eye)
    df.kalman_filter(model, xs)  # a singular Q runs in the Kalman filter
    with pytest.raises(ValueError, match=r"SingularQ\.process_cov\(1\) is singular.*Q_k⁻¹"):
        df.posterior_crb(model, xs, x0)


class _GaussTimesUniform(NoiseModel):
    """v = (N(0, 1), U(−½, ½)), independent."""

    dim = 2

    def __init__(self):
        super().__init__()
        self.g = Gaussian(torch.zeros(1, dtype=D), torch.eye(1, dtype=D))
        self.u = UniformBox(torch.tensor([-0.5], dtype=D), torch.tensor([0.5], dtype=D))

    def sample(self, sample_shape=(), generator=None):
        return torch.cat([self.g.sample(sample_shape, generator),
                          self.u.sample(sample_shape, generator)], -1)  # fmt: skip

    def log_prob(self, v, mask=None):
        lg, lu = self.g.log_prob(v[..., :1]), self.u.log_prob(v[..., 1:])
        if mask is not None:
            lg, lu = torch.where(mask[..., 0], lg, 0.0), torch.where(mask[..., 1], lu, 0.0)
        return lg + lu


def test_a_noise_uniform_in_one_received_entry_is_refused_by_name():
    """The regularity check looked at the summed log-density alone: the Gaussian entry gave
    it a gradient, the uniform entry got zero information, and a particle filter reached
    0.13× the "bound"."""
    noise = _GaussTimesUniform()
    with pytest.raises(ValueError, match=r"_GaussTimesUniform's score in entry 1 is zero"):
        noise_information(noise, num_samples=2000, generator=torch.Generator().manual_seed(0))
    # the uniform entry unreceived: the Gaussian entry's information, 1 (Monte Carlo sd 0.01)
    mask = torch.tensor([[True, False], [False, True]])
    with pytest.raises(ValueError, match="entry 1"):
        noise_information(noise, mask, num_samples=2000, generator=torch.Generator().manual_seed(0))
    info = noise_information(
        noise, mask[:1], num_samples=20_000, generator=torch.Generator().manual_seed(0)
    )
    torch.testing.assert_close(info[0], torch.tensor([[1.0, 0.0], [0.0, 0.0]], dtype=D),
                               atol=0.05, rtol=0.0)  # fmt: skip


def test_a_float32_fisher_information_is_accepted():
    """The symmetry check's tolerance was 1e-8 whatever the dtype: float32 round-off of the
    library's own gaussian_information (relative asymmetry ~3e-8) was refused."""
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        A = torch.randn(3, 3, generator=g)
        model = df.LinearGaussianModel(torch.eye(2), torch.randn(3, 2, generator=g),
                                       0.1 * torch.eye(2), A @ A.T + 0.01 * torch.eye(3),
                                       torch.zeros(2), torch.eye(2))  # fmt: skip
        xs, _, x0 = model.simulate(4, (1,), generator=g)
        mask = torch.rand(4, 3, generator=g) > 0.3
        R = model.measurement_noise.cov
        # a user's R⁻¹ (float32 round-off leaves it asymmetric) and the library's own J_v
        for info, m in ((torch.linalg.inv(R).expand(4, 3, 3), None),
                        (gaussian_information(R, mask), mask)):  # fmt: skip
            given = df.posterior_crb(model, xs, x0, information=info)
            torch.testing.assert_close(given.bound, df.posterior_crb(model, xs, x0, mask=m).bound)
        info = gaussian_information(R, mask)
        assert torch.equal(info, info.mT)  # symmetric to the bit, as a Fisher information is


def test_a_mask_beside_the_information_is_refused():
    """``information`` is ``J_v`` already: a ``mask`` given beside it had been ignored (an
    all-false mask bounded as if everything arrived; noted in an earlier session)."""
    model = df.LinearGaussianModel(F, H, Q, R, M0, P0)
    xs, x0 = torch.zeros(1, 3, 2, dtype=D), torch.zeros(1, 2, dtype=D)
    info = torch.eye(3, dtype=D).expand(3, 3, 3)
    lost = torch.zeros(3, 3, dtype=torch.bool)
    with pytest.raises(ValueError, match="give mask or information, not both"):
        df.posterior_crb(model, xs, x0, mask=lost, information=info)
    # the documented way: the rows and columns of what was lost zeroed
    zeroed = df.posterior_crb(model, xs, x0, information=torch.zeros(3, 3, 3, dtype=D))
    masked = df.posterior_crb(model, xs, x0, mask=lost)
    torch.testing.assert_close(zeroed.bound, masked.bound)
