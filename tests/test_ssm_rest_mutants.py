"""Independent truths for difffilter/ssm.py's wrapped_spread that a second mutation review
found unpinned (each check passes here and failed on its mutant): the weighted circular
mean of a cloud of angles against a brute-force grid minimiser of Σᵢ wᵢ wrap(pᵢ − c)²
(numpy float64), and the deviations against wrap(pᵢ − ŷ) by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter.ssm import LinearGaussianModel, NonlinearGaussianModel, _arity, wrapped_spread

F64 = torch.float64


def _wrap_np(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


class _Bearing(LinearGaussianModel):
    """A scalar model whose measurement residual wraps at ±π."""

    def measurement_residual(self, y, y_hat):
        return torch.remainder(y - y_hat + math.pi, 2 * math.pi) - math.pi


def _bearing_model():
    one = torch.ones(1, 1, dtype=F64)
    return _Bearing(one, one, one, one, torch.zeros(1, dtype=F64), one)


def _grid_circular_mean(p, w):
    """argmin over c of Σᵢ wᵢ wrap(pᵢ − c)² on a grid of 400,001 points over [−π, π]
    (step 1.6e-5 rad), numpy float64."""
    c = np.linspace(-np.pi, np.pi, 400_001)
    spread = (w[None, :] * _wrap_np(p[None, :] - c[:, None]) ** 2).sum(1)
    return c[spread.argmin()]


# Clouds on which the documented starts (plain mean and point of largest weight, each
# re-centred twice, the smaller spread kept) reach the global minimum; each is one on which
# a mutant did not: a single pass from the largest weight, the larger spread kept, the
# plain mean's start alone, the smallest weight's start, Σ wᵢ |rᵢ| as the spread.
CLOUDS = [
    ([2.677, 1.397, -1.984], [0.171, 0.173, 0.655]),
    ([-2.616, 2.272, 0.063, -2.649, -2.047, 1.738], [0.218, 0.074, 0.166, 0.158, 0.208, 0.175]),
    ([2.632, -1.986, 1.226, -1.522, -1.534], [0.244, 0.261, 0.043, 0.353, 0.099]),
    ([-2.606, -0.416, 2.244, 1.507, 2.743, 3.139], [0.322, 0.017, 0.237, 0.23, 0.016, 0.177]),
    ([3.0, -3.0, 3.1, 0.3], [0.3, 0.3, 0.3, 0.1]),
    # even on both sides of ±π: the plain mean 0.01 wraps no deviation, and was returned
    # (spread 9.30 rad² where 0.0108 is right: the review's bug)
    ([3.0, -3.0, 3.1, -3.1], [0.2, 0.3, 0.3, 0.2]),
]


@pytest.mark.parametrize("points, weights", CLOUDS)
def test_the_wrapped_mean_minimises_the_weighted_circular_spread(points, weights):
    """wrapped_spread's ŷ of angles straddling ±π (or spread wide) is, modulo 2π, the grid
    minimiser of Σᵢ wᵢ wrap(pᵢ − c)² to 1e-4 rad (the grid's step is 1.6e-5), and its
    deviations are wrap(pᵢ − ŷ) by hand (numpy float64)."""
    p = np.array(points)
    w = np.array(weights) / np.sum(weights)
    mean, dev = wrapped_spread(_bearing_model(), torch.tensor(p)[:, None], torch.tensor(w))
    assert mean.shape == (1,) and dev.shape == (len(p), 1)
    want = _grid_circular_mean(p, w)
    assert abs(_wrap_np(mean.item() - want)) < 1e-4
    np.testing.assert_allclose(dev[:, 0].numpy(), _wrap_np(p - mean.item()), atol=1e-12)


def test_a_user_observation_jacobian_gets_the_step():
    """h(x, k) = (1 + k) x² with its closed-form Jacobian given: observation_jacobian at
    x = 1.5, k = 3 is 2 (1 + 3) 1.5 = 12 by hand (the step was unpinned: read at 0 it is 3),
    and the autodiff default of the same h agrees."""
    eye = torch.eye(1, dtype=F64)

    def h(x, k):
        return (1.0 + k) * x**2

    def jh(x, k):
        return (2.0 * (1.0 + k) * x).unsqueeze(-1)

    x = torch.tensor([1.5], dtype=F64)
    given = NonlinearGaussianModel(lambda x: x, h, eye, eye, x, eye, observation_jacobian=jh)
    assert given.observation_jacobian(x, 3).item() == pytest.approx(12.0, rel=1e-12)
    auto = NonlinearGaussianModel(lambda x: x, h, eye, eye, x, eye)
    assert auto.observation_jacobian(x, 3).item() == pytest.approx(12.0, rel=1e-12)


def _pendulum_jacobian(x, u=None, k=0):
    one = torch.ones_like(x[..., 0])
    return torch.stack([torch.stack([one, 0.05 * one], -1),
                        torch.stack([-0.05 * 9.81 * torch.cos(x[..., 0]), 0.975 * one], -1)], -2)  # fmt: skip


@pytest.mark.parametrize(
    ("jacobian", "message"),
    [
        (lambda x, u=None, k=0: _pendulum_jacobian(x).mT, "is not the derivative of transition"),
        # one state's (x[0]: a row, not an entry, of a batch)
        (
            lambda x, u=None, k=0: _pendulum_jacobian(x[0] if x.dim() > 1 else x),
            "is not the derivative of transition",
        ),
        (
            lambda x, u=None, k=0: torch.zeros(*x.shape[:-1], 2, 3, dtype=x.dtype),
            r"transition_jacobian returns \(3, 2, 3\) for x \[3, 2\]; it must return \[\.\.\., 2, 2\]",
        ),
    ],
)
def test_a_closed_form_jacobian_must_be_the_derivative_it_stands_for(jacobian, message):
    """A trial's pendulum: a transposed closed-form Jacobian, or one of run 0's state, had
    filtered silently (means 0.028 off, 1.5 posterior standard deviations), one of the wrong
    shape failed mid-filter as a raw matmul error. The model compares them with torch.func's
    at states about the prior when it is built; the right one is taken."""

    def f(x):
        return torch.stack([x[..., 0] + 0.05 * x[..., 1],
                            x[..., 1] - 0.05 * (9.81 * torch.sin(x[..., 0]) + 0.5 * x[..., 1])], -1)  # fmt: skip

    eye = torch.eye(2, dtype=F64)
    args = (f, lambda x: torch.sin(x), 1e-4 * eye, 1e-3 * eye, torch.tensor([0.5, 0.0], dtype=F64),
            1e-2 * eye)  # fmt: skip
    NonlinearGaussianModel(*args, transition_jacobian=_pendulum_jacobian)
    with pytest.raises(ValueError, match=message):
        NonlinearGaussianModel(*args, transition_jacobian=jacobian)
    with pytest.raises(ValueError, match="observation_jacobian is not the derivative of observe"):
        NonlinearGaussianModel(*args, observation_jacobian=lambda x: torch.diag_embed(x))


def _x_u_default(x, u=None):
    return x


def _x_dt(x, dt=0.1):
    return x


def _star(*args):
    return args[0]


def _x_u_k(x, u, k):
    return x


def _z_v(z, v):
    return z


def _x_k_default(x, k=0):
    return x


def test_the_arity_counts_the_arguments_the_docstring_names():
    """_arity's docstring: f(x, u=None) takes u (2), f(x, dt=0.1) takes x alone (1),
    f(*args) all three, f(z, v) two (no defaults: all positional), f(x, u, k)
    three, h(x, k=0) of names (x, k) two, a callable without a signature all;
    and a model of f(x, u=None) with dim_u = 1 gets its input: x + u by hand."""
    assert _arity(_x_u_default) == 2
    assert _arity(_x_dt) == 1
    assert _arity(_star) == 3
    assert _arity(_x_u_k) == 3
    assert _arity(_x_k_default, ("x", "k")) == 2
    assert _arity(torch.sin) == 3
    assert _arity(_z_v) == 2

    def f(x, u=None):
        return x + u

    eye = torch.eye(1, dtype=F64)
    model = NonlinearGaussianModel(f, lambda x: x, eye, eye, eye[0], eye, dim_u=1)
    out = model.transition(torch.tensor([[1.0]], dtype=F64), torch.tensor([[2.5]], dtype=F64), 0)
    assert out.item() == 3.5


def test_noise_covariances_per_run_draw_each_run_with_its_own():
    """Q per run = 0.04, 1, 25 and R per run = 0.01, 1, 100 with F = 0 (x_{k+1} = w_k) and
    H = 1, P0 = 1e-12: over 400 steps run i's xs have sample variance Q_i and its
    ys − xs sample variance R_i, each within 35 % (the estimates' relative standard
    deviation is √(2/400) ≈ 7 %), seeded."""
    Q = torch.tensor([0.04, 1.0, 25.0], dtype=F64).reshape(3, 1, 1)
    R = torch.tensor([0.01, 1.0, 100.0], dtype=F64).reshape(3, 1, 1)
    zero, one = torch.zeros(1, 1, dtype=F64), torch.ones(1, 1, dtype=F64)
    model = LinearGaussianModel(zero, one, Q, R, torch.zeros(1, dtype=F64), 1e-12 * one)
    xs, ys, _ = model.simulate(400, generator=torch.Generator().manual_seed(5))
    assert xs.shape == ys.shape == (3, 400, 1)
    for draws, cov in ((xs, Q), (ys - xs, R)):
        ratio = draws[..., 0].square().mean(-1) / cov.reshape(3)
        assert bool(((ratio > 0.65) & (ratio < 1.35)).all()), ratio


def test_the_nonlinear_model_names_an_indefinite_q_or_r():
    """Q = −1 or R = [[1, 2], [2, 1]] (eigenvalue −1) are not covariances (class docstring:
    Q, R as in LinearGaussianModel): ValueError naming the argument, not the noise module's
    anonymous 'cov'."""
    eye1 = torch.eye(1, dtype=F64)
    m0 = torch.zeros(1, dtype=F64)
    with pytest.raises(ValueError, match="^Q must be positive definite"):
        NonlinearGaussianModel(lambda x: x, lambda x: x, -eye1, eye1, m0, eye1)
    bad_r = torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=F64)
    with pytest.raises(ValueError, match="^R must be positive definite"):
        NonlinearGaussianModel(
            lambda x: x, lambda x: x.expand(*x.shape[:-1], 2), eye1, bad_r, m0, eye1
        )


def test_simulate_refuses_inputs_that_do_not_fit_the_model():
    """simulate's us is [..., T, du] (module docstring: u_0 … u_{T−1}): us for a model without
    input (du = 0), us of T − 1 = 2 steps for T = 3, and us of du = 2 for B [1, 1] each raise
    ValueError before anything is drawn."""
    one = torch.ones(1, 1, dtype=F64)
    m0 = torch.zeros(1, dtype=F64)
    no_input = LinearGaussianModel(one, one, one, one, m0, one)
    with pytest.raises(ValueError, match="dim_u = 0"):
        no_input.simulate(3, us=torch.zeros(3, 1, dtype=F64))
    model = LinearGaussianModel(one, one, one, one, m0, one, B=one)
    with pytest.raises(ValueError, match="T = 3"):
        model.simulate(3, us=torch.zeros(2, 1, dtype=F64))
    with pytest.raises(ValueError, match="us must have shape"):
        model.simulate(3, us=torch.zeros(3, 2, dtype=F64))


def test_batch_shapes_and_dtypes_that_do_not_fit_are_refused():
    """A model of 3 parameter sets simulated for batch_shape (4,), a B of 3 sets beside a P0
    of 4 (class docstring: one batch for all arguments), and a transition returning float32
    for a float64 model each raise ValueError naming the misfit."""
    one = torch.ones(1, 1, dtype=F64)
    m0 = torch.zeros(1, dtype=F64)
    three = torch.ones(3, 1, 1, dtype=F64)
    model = LinearGaussianModel(one, one, one, three, m0, one)
    with pytest.raises(ValueError, match="does not broadcast"):
        model.simulate(2, batch_shape=(4,))
    with pytest.raises(ValueError, match=r"P0 \(4,\), B \(3,\)"):
        LinearGaussianModel(one, one, one, one, m0, torch.ones(4, 1, 1, dtype=F64), B=three)
    with pytest.raises(ValueError, match="float32"):
        NonlinearGaussianModel(lambda x: x.float(), lambda x: x, one, one, m0, one)
