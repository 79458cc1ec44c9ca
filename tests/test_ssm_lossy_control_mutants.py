"""Independent truths for lines of difffilter/ssm.py and difffilter/lossy_control.py that a
mutation review found unpinned (each check passes here and failed on its mutant): the
modified Riccati equations' closed forms where the problem's units are extreme, the
critical rate's upper end as a rate with a fixed point, and the value checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter.lossy_control import (
    _scale,
    critical_arrival_rate,
    intermittent_kalman_bounds,
)
from difffilter.ssm import LinearGaussianModel, NonlinearGaussianModel, batched_jacobian

F64 = torch.float64


def _t(*rows):
    return torch.tensor(rows, dtype=F64)


def _scalar_mare_root(a: float, h: float, q: float, r: float, lam: float) -> float:
    """The positive root of the scalar MARE v = a²v + q − λa²h²v²/(h²v + r), multiplied out:
    (1 − a² + λa²) h² v² + ((1 − a²) r − q h²) v − q r = 0 (float64 by hand)."""
    qa = (1.0 - a * a + lam * a * a) * h * h
    qb = (1.0 - a * a) * r - q * h * h
    qc = -q * r
    return (-qb + math.sqrt(qb * qb - 4.0 * qa * qc)) / (2.0 * qa)


def test_the_scale_is_its_docstrings_formula():
    """_scale against its docstring evaluated by hand in numpy: (tr Q + tr R ‖G⁺‖²) ·
    max(1, ρ(F)²) on an unstable F (ρ = 3) and a G of norm far from 1 (the ρ² and the
    pseudo-inverse's gain were unpinned: the divergence threshold and the restart's size)."""
    F = np.array([[3.0, 1.0], [0.0, 0.5]])
    G = np.array([[0.1, 0.0]])
    Q = np.diag([2.0, 1.0])
    R = np.array([[4.0]])
    want = (3.0 + 4.0 * (1.0 / 0.1) ** 2) * 9.0
    assert _scale(F, G, Q, R) == pytest.approx(want, rel=1e-12)


def test_a_weak_sensor_measures_the_noise_in_the_states_units():
    """Scalar a = 2, h = 1e-9, q = r = 1 at rate 1 and 0.9: V̄ ≈ 3e18 is the closed-form root
    of the scalar MARE, not 'diverged' (against tr Q + tr R alone, without ‖H⁺‖², the
    iterate passed 1e15 times the scale on its way to a legitimate fixed point)."""
    a, h = 2.0, 1e-9
    for lam in (1.0, 0.9):
        _, upper = intermittent_kalman_bounds(_t([a]), _t([h]), _t([1.0]), _t([1.0]), lam)
        assert upper.item() == pytest.approx(_scalar_mare_root(a, h, 1.0, 1.0, lam), rel=1e-9)


def test_a_slow_unmeasured_mode_is_large_but_not_divergent():
    """F = diag(0.9996, 0), H = [0, 1]: the unmeasured stable mode's variance is q/(1 − a²)
    = 1250.25, about 1,250 times the problem's scale (Lyapunov by hand); a divergence test
    a thousand times the scale called it divergent."""
    a = 0.9996
    F = _t([a, 0.0], [0.0, 0.0])
    H = _t([0.0, 1.0])
    Q = _t([1.0, 0.0], [0.0, 1e-3])
    _, upper = intermittent_kalman_bounds(F, H, Q, _t([1e-3]), 1.0)
    assert upper[0, 0].item() == pytest.approx(1.0 / (1.0 - a * a), rel=1e-6)
    assert upper[0, 1].item() == pytest.approx(0.0, abs=1e-9)


def test_the_critical_rates_upper_end_has_a_fixed_point():
    """critical_arrival_rate's upper end λ̄, found by bisection where H is not invertible, is
    a rate at which the MARE has a fixed point (docstring: 'to tol and a little high'):
    F = diag(1.2, 0.5) seen through H = [1, 0] (the unstable mode measured, the stable one
    not): λ_c = 1 − 1/1.2² < λ̄ ≤ λ_c + tol, the bounds exist at λ̄, and V̄ there is
    diagonal with the scalar closed-form root for the measured mode and q/(1 − 0.5²) for the
    other (an upper end of λ_c itself, where the quadratic's leading coefficient vanishes,
    has none)."""
    a = 1.2
    F, H = _t([a, 0.0], [0.0, 0.5]), _t([1.0, 0.0])
    rate = critical_arrival_rate(F, H)
    lam_c = 1.0 - 1.0 / a**2
    assert rate.lower == pytest.approx(lam_c, rel=1e-12)
    assert lam_c < rate.upper <= lam_c + 1e-3 + 1e-12
    _, upper = intermittent_kalman_bounds(F, H, torch.eye(2, dtype=F64), _t([1.0]), rate.upper)
    want = np.diag([_scalar_mare_root(a, 1.0, 1.0, 1.0, rate.upper), 1.0 / (1 - 0.25)])
    np.testing.assert_allclose(upper.numpy(), want, rtol=1e-6, atol=1e-9)


def test_the_bounds_are_exactly_symmetric():
    """S̄ and V̄ are covariances: exactly symmetric (bit for bit) on a random non-symmetric
    3×3 F (seeded), as the Cholesky factorisations downstream need."""
    g = torch.Generator().manual_seed(0)
    F = 0.5 * torch.randn(3, 3, generator=g, dtype=F64)
    H = torch.randn(1, 3, generator=g, dtype=F64)
    lower, upper = intermittent_kalman_bounds(F, H, torch.eye(3, dtype=F64), _t([1.0]), 0.9)
    assert torch.equal(lower, lower.mT)
    assert torch.equal(upper, upper.mT)


def test_a_slightly_asymmetric_q_and_a_singular_r_are_refused():
    """Q off symmetric by 1e-3 (relative) and R = 0 are not covariances of the docstring's
    kind (Q symmetric PSD, R symmetric positive definite): ValueError naming them."""
    F, H = _t([0.5, 0.0], [0.0, 0.5]), _t([1.0, 0.0])
    with pytest.raises(ValueError, match="Q must be symmetric"):
        intermittent_kalman_bounds(F, H, _t([1.0, 1e-3], [0.0, 1.0]), _t([1.0]), 0.9)
    with pytest.raises(ValueError, match="R must be positive definite"):
        intermittent_kalman_bounds(F, H, torch.eye(2, dtype=F64), _t([0.0]), 0.9)


def test_the_bounds_keep_the_models_dtype():
    """A float32 (F, H, Q, R) gets float32 bounds (the docstring's 'like F'; a float64 pair
    handed to a float32 filter promoted it)."""
    f32 = torch.float32
    F, H = torch.tensor([[0.5]], dtype=f32), torch.tensor([[1.0]], dtype=f32)
    one = torch.ones(1, 1, dtype=f32)
    lower, upper = intermittent_kalman_bounds(F, H, one, one, 0.9)
    assert lower.dtype == f32 and upper.dtype == f32


# -- ssm.py ------------------------------------------------------------------------------


class _Ramp(LinearGaussianModel):
    """Scalar x_{k+1} = (1 + k/4) x_k + 2 u_k + w_k, y_k = (1 + k) x_k + v_k: every step
    index shows in the numbers."""

    time_varying = True

    def transition_matrix(self, k):
        return self.F * (1.0 + k / 4.0)

    def observation_matrix(self, k):
        return self.H * (1.0 + k)


def test_simulate_follows_the_modules_time_convention():
    """Noise 1e-14 (variance): xs[t] = x_{t+1} = (1 + t/4) x_t + 2 u_t, ys[t] = y_{t+1} =
    (2 + t) x_{t+1}, from the returned x0, u_t = us[t] (module docstring), recomputed by hand
    in float64 (a step index off by one, us read a step late and x_T returned as x0 were
    unpinned)."""
    tiny = 1e-14
    model = _Ramp(_t([1.0]), _t([1.0]), _t([tiny]), _t([tiny]), _t(0.5), _t([1.0]), B=_t([2.0]))
    us = torch.tensor([[0.3], [-0.2], [0.1], [0.4], [-0.5]], dtype=F64)
    g = torch.Generator().manual_seed(3)
    xs, ys, x0 = model.simulate(5, us=us, generator=g)
    x = float(x0[0])
    for t in range(5):
        x = (1.0 + t / 4.0) * x + 2.0 * float(us[t, 0])
        assert float(xs[t, 0]) == pytest.approx(x, abs=1e-5)
        assert float(ys[t, 0]) == pytest.approx((2.0 + t) * x, abs=1e-5)


def test_the_linear_models_jacobians_are_central_differences():
    """LinearGaussianModel's closed-form ∂f/∂x and ∂h/∂x against central differences of its
    own transition/observe on a non-symmetric F, and a batched H ([2, 1, 2] for x [2])
    expanded to one Jacobian per run; batched_jacobian of a nonlinear f(x, u) with u of a
    larger batch than x against central differences (the transpose, the parameter batch,
    and the argument's batch were unpinned)."""
    F = _t([0.9, 0.4], [-0.3, 0.7])
    H = _t([[1.0, 2.0]], [[-1.0, 0.5]])
    eye = torch.eye(2, dtype=F64)
    model = LinearGaussianModel(F, H, eye, torch.eye(1, dtype=F64), torch.zeros(2, dtype=F64), eye)
    x = _t(0.3, -1.2)
    eps = 1e-6

    def central(fn):
        cols = [(fn(x + eps * eye[j]) - fn(x - eps * eye[j])) / (2 * eps) for j in range(2)]
        return torch.stack(cols, -1)

    torch.testing.assert_close(
        model.transition_jacobian(x, None, 0), central(lambda z: model.transition(z, None, 0))
    )
    jh = model.observation_jacobian(x, 1)
    assert jh.shape == (2, 1, 2)
    torch.testing.assert_close(jh, central(lambda z: model.observe(z, 1)))

    def f(z, u):
        return torch.stack([torch.sin(z[..., 0]) * u[..., 0], z[..., 0] * z[..., 1] ** 2], -1)

    u = _t([1.5], [-2.0], [0.5])  # three runs of u for one x
    jac = batched_jacobian(f, x, u)
    assert jac.shape == (3, 2, 2)
    for i in range(3):
        torch.testing.assert_close(jac[i], central(lambda z, i=i: f(z, u[i])))


def test_batched_jacobian_returns_the_dtype_of_x():
    """A function that promotes a float32 x with a float64 constant: its Jacobian 2·I comes
    back in x's float32 (docstring's comment: a float64 Jacobian reached a float32 filter)."""
    x = torch.tensor([[1.0, -2.0]], dtype=torch.float32)
    jac = batched_jacobian(lambda z: z * torch.full((2,), 2.0, dtype=F64), x)
    assert jac.dtype == torch.float32
    torch.testing.assert_close(jac[0], 2.0 * torch.eye(2))


def test_a_prior_per_run_draws_one_state_per_run():
    """m0 [3, 1] = −10, 0, 10 with P0 = 1e-12: sample_initial((3,)) and simulate's x0 are
    [3, 1], run i at m0[i] (sample_initial's docstring: broadcast, not 9 draws)."""
    m0 = _t([-10.0], [0.0], [10.0])
    P0 = 1e-12 * torch.ones(3, 1, 1, dtype=F64)
    one = torch.ones(1, 1, dtype=F64)
    model = LinearGaussianModel(_t([0.5]), one, one, one, m0, P0)
    g = torch.Generator().manual_seed(1)
    x0 = model.sample_initial((3,), generator=g)
    assert x0.shape == (3, 1)
    torch.testing.assert_close(x0, m0, atol=1e-4, rtol=0)
    _, _, x0 = model.simulate(2, generator=g)
    torch.testing.assert_close(x0, m0, atol=1e-4, rtol=0)


def test_the_masked_measurement_density_is_the_received_entrys_marginal():
    """measurement_log_prob with mask [True, False] on R = [[2, 0.5], [0.5, 1]]: the
    received entry's marginal log N(r₀; 0, R₀₀) by hand; all received: the full bivariate
    density by hand (numpy float64)."""
    R = np.array([[2.0, 0.5], [0.5, 1.0]])
    eye = torch.eye(2, dtype=F64)
    model = LinearGaussianModel(eye, eye, eye, torch.tensor(R), torch.zeros(2, dtype=F64), eye)
    x, y = _t(0.2, -0.1), _t(1.0, 3.0)
    r = np.array([0.8, 3.1])
    got = model.measurement_log_prob(y, x, 1, mask=torch.tensor([True, False]))
    assert got.item() == pytest.approx(-0.5 * (math.log(2 * math.pi * 2.0) + r[0] ** 2 / 2.0))
    full = -0.5 * (
        2 * math.log(2 * math.pi) + math.log(np.linalg.det(R)) + r @ np.linalg.solve(R, r)
    )
    assert model.measurement_log_prob(y, x, 1).item() == pytest.approx(full)


def test_the_models_refuse_misshapen_or_indefinite_parameters():
    """The docstring's shapes and covariances: P0 with a negative eigenvalue, H [1, 3] for a
    2-state F, B [3, 1] for 2 states, dim_u = −1: ValueError each."""
    eye, one, m0 = torch.eye(2, dtype=F64), torch.ones(1, 1, dtype=F64), torch.zeros(2, dtype=F64)
    H = _t([1.0, 0.0])
    with pytest.raises(ValueError, match="P0"):
        LinearGaussianModel(eye, H, eye, one, m0, _t([1.0, 0.0], [0.0, -1.0]))
    with pytest.raises(ValueError, match="H must have shape"):
        LinearGaussianModel(eye, _t([1.0, 0.0, 0.0]), eye, one, m0, eye)
    with pytest.raises(ValueError, match="B must have shape"):
        LinearGaussianModel(eye, H, eye, one, m0, eye, B=_t([1.0], [0.0], [0.0]))
    with pytest.raises(ValueError, match="dim_u"):
        NonlinearGaussianModel(lambda x, u: x, lambda x: x[..., :1], eye, one, m0, eye, dim_u=-1)
