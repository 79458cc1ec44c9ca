"""A trial of time-varying linear models against a numpy Kalman filter: a model written
from ``StateSpaceModel`` with matrix methods (which the Kalman filter takes) and a
``LinearGaussianModel`` whose ``transition_matrix`` is assigned on the object changed ``F``
at every step with ``time_varying`` false and were filtered with the first step's ``F``
(16.5 nats off); an assigned ``measurement_cov`` was read by the Kalman filter and not by
``simulate`` or the particle filter."""

from __future__ import annotations

import math

import pytest
import torch

import difffilter as df
from difffilter.noise import Gaussian
from difffilter.ssm import StateSpaceModel

F64 = torch.float64
H = torch.tensor([[1.1, 0.0, 0.2], [0.0, 1.0, -0.1]], dtype=F64)
Q = torch.diag(torch.tensor([0.01, 0.02, 0.015], dtype=F64))
R = torch.tensor([[0.05, 0.005], [0.005, 0.15]], dtype=F64)
M0, P0 = (
    torch.tensor([0.5, -0.2, 1.0], dtype=F64),
    torch.diag(torch.tensor([0.5, 0.3, 0.2], dtype=F64)),
)


def rotating(k: int) -> torch.Tensor:
    c, s = math.cos(0.3 + 0.1 * k), math.sin(0.3 + 0.1 * k)
    return torch.tensor([[c, -s, 0.1 * k], [s, c, 0.0], [0.05 * k, 0.0, 0.9 - 0.02 * k]], dtype=F64)


class WrittenFromTheBase(StateSpaceModel):
    """A linear model of its own: the matrix methods on ``StateSpaceModel``."""

    def __init__(self):
        super().__init__()
        self.dim_x, self.dim_y, self.dim_u = 3, 2, 0
        self.initial = Gaussian(M0, P0)
        self.process_noise = Gaussian(torch.zeros(3, dtype=F64), Q)
        self.measurement_noise = Gaussian(torch.zeros(2, dtype=F64), R)

    def transition_matrix(self, k):
        return rotating(k)

    def observation_matrix(self, k):
        return H

    def control_matrix(self, k):
        return None

    def transition(self, x, u, k):
        return x @ rotating(k).mT

    def observe(self, x, k):
        return x @ H.mT


def assigned_on_the_object():
    model = df.LinearGaussianModel(rotating(0), H, Q, R, M0, P0)
    model.transition_matrix = rotating
    return model


def numpy_log_likelihood(ys: torch.Tensor) -> float:
    """log p(y_1..y_T) of the rotating model by a Kalman filter written out (the truth)."""
    m, P, total = M0.numpy(), P0.numpy(), 0.0
    h, q, r = H.numpy(), Q.numpy(), R.numpy()
    for k, y in enumerate(ys.numpy()):
        F = rotating(k).numpy()
        m, P = F @ m, F @ P @ F.T + q
        S = h @ P @ h.T + r
        res = y - h @ m
        total -= 0.5 * (res @ torch.linalg.solve(torch.tensor(S), torch.tensor(res)).numpy()
                        + math.log(float(torch.linalg.det(torch.tensor(S)))) + 2 * math.log(2 * math.pi))  # fmt: skip
        K = P @ h.T @ torch.linalg.inv(torch.tensor(S)).numpy()
        m, P = m + K @ res, P - K @ S @ K.T
    return total


@pytest.mark.parametrize("make", [WrittenFromTheBase, assigned_on_the_object])
def test_an_undeclared_time_varying_linear_model_is_refused_and_a_declared_one_filtered(make):
    model = make()
    _, ys, _ = model.simulate(8, (), generator=torch.Generator().manual_seed(4))
    for method in ("sequential", "parallel"):
        with pytest.raises(
            ValueError, match=r"transition_matrix\(k\) differs between k = 1 and k = 0"
        ):
            df.kalman_filter(model, ys, method=method)
    with pytest.raises(ValueError, match="time_varying is False"):
        df.KalmanFilter().init(model)
    model.time_varying = True  # (on the object: read as the class's would be)
    truth = numpy_log_likelihood(ys)
    for method in ("sequential", "parallel"):
        assert float(df.kalman_filter(model, ys, method=method).log_likelihood) == pytest.approx(
            truth, abs=1e-9
        )
    assert float(df.extended_kalman_filter(model, ys).log_likelihood) == pytest.approx(
        truth, abs=1e-9
    )


def test_a_constant_linear_model_written_from_the_base_is_filtered_as_before():
    class Constant(WrittenFromTheBase):
        def transition_matrix(self, k):
            return rotating(0)

        def transition(self, x, u, k):
            return x @ rotating(0).mT

    model = Constant()
    _, ys, _ = model.simulate(8, (), generator=torch.Generator().manual_seed(5))
    kf = df.KalmanFilter()
    assert kf.init(model).gains is not None  # the gain schedule of a constant model
    torch.testing.assert_close(df.kalman_filter(model, ys).log_likelihood,
                               df.extended_kalman_filter(model, ys).log_likelihood)  # fmt: skip


def test_an_assigned_measurement_cov_is_what_simulate_and_the_particle_filter_draw_and_weigh():
    model = df.LinearGaussianModel(rotating(0), H, Q, R, M0, P0)
    model.time_varying = True
    model.measurement_cov = lambda k: 100 * R
    torch.testing.assert_close(model.measurement_noise_at(1).cov, 100 * R)
    xs, ys, _ = model.simulate(1, (4000,), generator=torch.Generator().manual_seed(0))
    spread = (ys[:, 0] - xs[:, 0] @ H.mT).var(0)
    torch.testing.assert_close(spread, 100 * R.diagonal(), rtol=0.1, atol=0)  # (4,000 draws)
    one = ys[:8]
    pf = df.particle_filter(
        model, one, num_particles=4000, generator=torch.Generator().manual_seed(1)
    )
    torch.testing.assert_close(pf.log_likelihood, df.kalman_filter(model, one).log_likelihood,
                               atol=0.05, rtol=0)  # fmt: skip


def test_a_model_without_a_dict_is_probed_too():
    """A review: a duck type with ``__slots__`` failed in ``vars()`` (TypeError) once the
    check read methods assigned on the object."""
    from difffilter.kalman import _check_declared_time_varying

    class Slotted:
        __slots__ = ()
        time_varying = False

        def transition_matrix(self, k):
            return rotating(k)

    with pytest.raises(ValueError, match=r"Slotted.transition_matrix\(k\) differs"):
        _check_declared_time_varying(Slotted())


@pytest.mark.parametrize("how", ["subclass", "assigned"])
def test_the_fused_modified_pf_steps_where_the_model_has_a_process_cov_of_its_own(how):
    """A review: the fused modified PF drew the noise module's Q where the composed filter
    (since the assigned covariance is read) drew the model's ``process_cov``: means 4.19 apart
    with the same seeds (a subclass's override alike, before). Such a model steps."""
    from difffilter import fdi

    args = (torch.tensor([[0.9, 0.1], [0.0, 0.95]], dtype=F64), torch.eye(2, dtype=F64),
            0.01 * torch.eye(2, dtype=F64), 0.1 * torch.eye(2, dtype=F64),
            torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))  # fmt: skip
    big = torch.eye(2, dtype=F64)

    class OwnQ(df.LinearGaussianModel):
        def process_cov(self, k):
            return big

    if how == "subclass":
        model = OwnQ(*args)
    else:
        model = df.LinearGaussianModel(*args)
        model.process_cov = lambda k: big
    _, ys, _ = OwnQ(*args).simulate(15, (2,), generator=torch.Generator().manual_seed(1))
    means = [fdi.modified_particle_filter(model, ys, num_particles=400,
                                          detector=fdi.PoADetector(3.0, 0.5),
                                          gamma_hat=torch.zeros_like(ys), fused=fused,
                                          generator=torch.Generator().manual_seed(5),
                                          resample_generator=torch.Generator().manual_seed(6)).means
             for fused in (False, True)]  # fmt: skip
    torch.testing.assert_close(means[0], means[1], rtol=0, atol=1e-12)
