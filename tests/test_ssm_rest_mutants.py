"""Independent truths for difffilter/ssm.py's wrapped_spread that a second mutation review
found unpinned (each check passes here and failed on its mutant): the weighted circular
mean of a cloud of angles against a brute-force grid minimiser of Σᵢ wᵢ wrap(pᵢ − c)²
(numpy float64), and the deviations against wrap(pᵢ − ŷ) by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter.noise import Gaussian, UniformBox
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


# -- batched noise models, dtype check, modules as f/h (a noise trial) ------------------


def _lg64(F=None, H=None):
    eye = torch.eye(2, dtype=F64)
    return LinearGaussianModel(eye * 0.0 if F is None else F, eye if H is None else H,
                               0.1 * eye, 0.2 * eye, torch.zeros(2, dtype=F64), eye)  # fmt: skip


def _halves():
    return torch.tensor([[1.0, 0.5], [2.0, 1.0], [3.0, 4.0]], dtype=F64)  # three runs' boxes


def _per_run_uniform(draws, half):
    """draws [N, 3, 2] of Uniform(−half_b, half_b) for run b: inside each run's own box, and
    the variance of each run's entries half²/3 (to 5%); the largest |draw| near half."""
    assert bool((draws.abs() <= half).all())
    var = draws.reshape(-1, 3, 2).square().mean(0)
    torch.testing.assert_close(var, half.square() / 3, rtol=0.05, atol=0)
    assert bool((draws.reshape(-1, 3, 2).abs().amax(0) > 0.98 * half).all())


def test_a_batched_uniform_box_is_drawn_one_box_per_run_as_a_batched_gaussian():
    """A UniformBox of bounds [3, d] as prior, process or measurement noise simulates 3 runs,
    as a batched Gaussian does (the prior had made 3 × 3 runs, the other two failed in a
    reshape): the shapes of the batched-Gaussian path, and per run the box's own bounds and
    variance half²/3. With F = 0 and H = I, x_k = w_{k−1} and y_k − x_k = v_k."""
    half = _halves()
    box = UniformBox(-half, half)
    runs, T = 2000, 3
    gauss = _lg64()
    gauss.initial = Gaussian(torch.zeros(3, 2, dtype=F64), torch.diag_embed(half.square() / 3))
    gx, gy, gx0 = gauss.simulate(T, (runs, 1), generator=torch.Generator().manual_seed(0))
    for role in ("initial", "process_noise", "measurement_noise"):
        model = _lg64()
        setattr(model, role, box)
        xs, ys, x0 = model.simulate(T, (runs, 1), generator=torch.Generator().manual_seed(1))
        assert (xs.shape, ys.shape, x0.shape) == (gx.shape, gy.shape, gx0.shape)
        assert x0.shape == (runs, 3, 2)
        drawn = {"initial": x0, "process_noise": xs.transpose(-2, -3),
                 "measurement_noise": (ys - xs).transpose(-2, -3)}[role]  # fmt: skip
        _per_run_uniform(drawn, half)
    torch.testing.assert_close(gx0.square().mean(0), half.square() / 3, rtol=0.1, atol=0)
    model = _lg64()
    model.initial = box
    assert model.simulate(T, generator=torch.Generator().manual_seed(2))[2].shape == (3, 2)


def test_a_box_of_one_set_broadcast_over_runs_draws_independently_per_run():
    """Bounds [1, d] over 3 runs (the prior's batch): one draw per run, not one copied to
    all; and a box whose batch does not fit the runs is refused by name."""
    model = _lg64()
    model.initial = Gaussian(torch.zeros(3, 2, dtype=F64), torch.eye(2, dtype=F64))
    model.process_noise = UniformBox(-torch.ones(1, 2, dtype=F64), torch.ones(1, 2, dtype=F64))
    xs, _, _ = model.simulate(400, generator=torch.Generator().manual_seed(0))
    assert xs.shape == (3, 400, 2)
    assert not torch.equal(xs[0], xs[1]) and not torch.equal(xs[1], xs[2])
    torch.testing.assert_close(xs.square().mean(1), torch.full((3, 2), 1 / 3, dtype=F64),
                               rtol=0.15, atol=0)  # fmt: skip
    model.process_noise = UniformBox(-torch.ones(4, 2, dtype=F64), torch.ones(4, 2, dtype=F64))
    with pytest.raises(ValueError, match=r"UniformBox has one set of parameters per run"):
        model.sample_transition(torch.zeros(3, 2, dtype=F64), None, 0)


def test_sample_initial_takes_an_int_for_a_batched_prior():
    """sample_initial(3) for a prior of one mean per run: what sample_initial((3,)) draws
    (the same generator state), as for an unbatched prior; it had raised "'int' object is
    not iterable"."""
    one = torch.eye(1, dtype=F64)
    m0 = torch.tensor([[-10.0], [0.0], [10.0]], dtype=F64)
    model = LinearGaussianModel(one, one, one, one, m0, one)
    a = model.sample_initial(3, torch.Generator().manual_seed(0))
    b = model.sample_initial((3,), torch.Generator().manual_seed(0))
    assert a.shape == (3, 1)
    torch.testing.assert_close(a, b)


@pytest.mark.parametrize("role", ["process_noise", "measurement_noise"])
def test_simulate_refuses_a_noise_of_another_dtype_by_name(role):
    """simulate checks the noise models' dtype as every filter does: a float64 noise on a
    float32 model had simulated float32 xs beside float64 ys, or failed in torch's words."""
    eye = torch.eye(2)
    model = LinearGaussianModel(0.9 * eye, eye, 0.1 * eye, 0.2 * eye, torch.zeros(2), eye)
    xs, ys, _ = model.simulate(3, 2, generator=torch.Generator().manual_seed(0))
    assert xs.dtype == ys.dtype == torch.float32
    setattr(model, role, UniformBox(-torch.ones(2, dtype=F64), torch.ones(2, dtype=F64)))
    with pytest.raises(ValueError, match=rf"model\.{role}\.low is torch\.float64 .*float32"):
        model.simulate(3, 2, generator=torch.Generator().manual_seed(0))


class _Net(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(2, 2, dtype=F64)

    def forward(self, x):
        return torch.tanh(self.lin(x))


class _NetXUK(torch.nn.Module):
    def forward(self, x, u, k):
        return x


def test_a_module_as_transition_is_called_with_its_forward_s_arguments():
    """An nn.Module as f is called as its forward takes it (x alone): the model's transition
    is the network's output, and a filter runs it as the same network wrapped in a lambda;
    a forward(x, u, k) takes all three. (It had been called with three arguments.)"""
    torch.manual_seed(0)
    net = _Net()
    assert _arity(net) == 1 and _arity(_NetXUK()) == 3
    assert _arity(torch.nn.Sequential(torch.nn.Tanh())) == 1
    eye = torch.eye(2, dtype=F64)
    model = NonlinearGaussianModel(
        net, lambda x: x, 0.1 * eye, 0.1 * eye, torch.zeros(2, dtype=F64), eye
    )
    x = torch.randn(5, 2, dtype=F64, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        torch.testing.assert_close(model.transition(x, None, 0), net(x))
    wrapped = NonlinearGaussianModel(lambda x: net(x), lambda x: x, 0.1 * eye, 0.1 * eye,
                                     torch.zeros(2, dtype=F64), eye)  # fmt: skip
    xs, ys, _ = model.simulate(4, 2, generator=torch.Generator().manual_seed(2))
    xs2, ys2, _ = wrapped.simulate(4, 2, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close((xs, ys), (xs2, ys2))
    from difffilter import extended_kalman_filter

    torch.testing.assert_close(extended_kalman_filter(model, ys).log_likelihood,
                               extended_kalman_filter(wrapped, ys).log_likelihood)  # fmt: skip
