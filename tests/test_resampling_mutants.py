"""Mutation review of difffilter/resampling.py: checks that the existing suite let through.

Each test compares the library against an independent truth: a dense numpy evaluation of
a docstring's equation, a float64 log-domain Sinkhorn written out in numpy, a finite
difference-free identity (translation equivariance), or the documented contract on a
hand-made case. Mutants these tests kill (all passed the rest of the resampling tests):
the last-positive clamp of ``_inverse_cdf`` counting zero weights, ``Systematic._uniforms``
ignoring ``U`` or ``count``, ``Residual`` without its dummy weights on ``R = 0`` rows or
without clamping negative residuals, Soft counting live particles over the batch, a
StopGradient accepted as a base, and the optimal-transport details named on each test
(standardisation, stopping error, ε-scaling warm start, NaN warning).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter import resampling as rs

D = torch.float64


def _dense_inverse_cdf(w, u):
    """``a_j = min{i : u_j W < cdf_i}``, clamped to the last positive weight (numpy float64)."""
    w = np.asarray(w, dtype=np.float64)
    cdf = np.cumsum(w)
    last = int(np.nonzero(w > 0)[0].max())
    out = []
    for uj in np.asarray(u, dtype=np.float64):
        hit = np.nonzero(uj * cdf[-1] < cdf)[0]
        out.append(min(int(hit[0]) if hit.size else last, last))
    return np.array(out)


class _FixedRand:
    """``torch.rand`` returning ``value`` everywhere (in the requested dtype)."""

    def __init__(self, value):
        self.value = value

    def __call__(self, *shape, generator=None, dtype=None, device=None):
        size = shape[0] if len(shape) == 1 else shape
        return torch.full(size, self.value, dtype=dtype)


# ------------------------------------------------------------------ index-based schemes


def test_stratified_float32_top_uniform_rounding_to_one_never_draws_a_trailing_zero(monkeypatch):
    """float32 stratum ``(N − 1 + U)/N`` with ``U`` the largest float below 1 rounds to
    exactly 1, so the target equals the total and ``searchsorted`` runs past the last
    positive weight. Against the documented contract (a zero-weight particle is never
    drawn; indices past the last positive weight are clamped to it) and the dense numpy
    inverse CDF of the same uniforms. Kills ``weights >= 0`` in the clamp."""
    u_top = float(np.nextafter(np.float32(1.0), np.float32(0.0)))
    w = torch.tensor([0.25, 0.5, 0.25, 0.0, 0.0], dtype=torch.float32)
    u = (torch.arange(5, dtype=torch.float32) + u_top) / 5
    assert float(u[-1]) == 1.0  # the round-off this test is about
    want = _dense_inverse_cdf(w.numpy(), u.numpy())
    assert want.tolist() == [0, 1, 1, 2, 2]
    monkeypatch.setattr(torch, "rand", _FixedRand(u_top))
    got = rs.Stratified()._draw_from(w, None)
    assert got.tolist() == want.tolist()


@pytest.mark.parametrize("count", [None, 3.0])
def test_systematic_uniforms_hook_is_j_plus_u_over_count(count):
    """``Systematic._uniforms`` (the documented hook a subclass may call) against the
    docstring ``u_j = (j + U)/M`` in numpy, ``U`` the generator's one uniform per row and
    ``M = count`` (default ``N``). Kills ``j + 0.5`` and a dropped ``count``."""
    n = 6
    w = torch.rand(2, n, generator=torch.Generator().manual_seed(3), dtype=D)
    cnt = None if count is None else torch.full((2, 1), count, dtype=D)
    got = rs.Systematic()._uniforms(w, cnt, torch.Generator().manual_seed(17))
    big_u = torch.rand((2, 1), generator=torch.Generator().manual_seed(17), dtype=D).numpy()
    m = n if count is None else count
    want = (np.arange(n)[None, :] + big_u) / m
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-15)


@pytest.mark.parametrize("base", ["Systematic", "Stratified", "Multinomial"])
def test_residual_rows_without_remainder_are_the_floor_copies(base):
    """Rows whose ``N w_i`` are all whole (``R = 0``) are the deterministic copies alone:
    ``[0.5, 0.25, 0.25, 0]`` at ``N = 4`` gives ``[0, 0, 1, 2]`` and equal weights the
    identity, for every base (by hand from ``c_i = ⌊N w_i⌋``). Kills dropping the dummy
    residual weights of ``R = 0`` rows (the systematic base then divides 0 by 0)."""
    res = rs.Residual(getattr(rs, base)())
    lw = torch.log(torch.tensor([[0.5, 0.25, 0.25, 0.0], [0.25, 0.25, 0.25, 0.25]], dtype=D))
    got = res._draw(rs.normalize_log_weights(lw), torch.Generator().manual_seed(0))
    assert got.tolist() == [[0, 0, 1, 2], [0, 1, 2, 3]]
    got1 = res._draw(torch.zeros(8, dtype=D), torch.Generator().manual_seed(1))
    assert got1.tolist() == list(range(8))


# ------------------------------------------------------------------- optimal transport


def _lse(z, axis):
    m = z.max(axis=axis, keepdims=True)
    return (m + np.log(np.exp(z - m).sum(axis=axis, keepdims=True))).squeeze(axis)


def _numpy_ot(x, log_w, eps, iterations=5000):
    """The class docstring's algorithm in numpy float64, written out: standardise (weighted
    mean, unweighted population std per coordinate), ``C_ij = ‖x̃_i − x̃_j‖²``, log-domain
    Sinkhorn with ``a = w``, ``b = 1/N``, plan ``P`` and projection ``y = N Pᵀ x``."""
    x = np.asarray(x, dtype=np.float64)
    log_a = np.asarray(log_w, dtype=np.float64)
    log_a = log_a - _lse(log_a, 0)
    n = x.shape[0]
    mu = np.exp(log_a) @ x
    sd = x.std(axis=0)
    sd = np.where(sd > 0, sd, 1.0)
    xs = (x - mu) / sd
    c = ((xs[:, None, :] - xs[None, :, :]) ** 2).sum(-1)
    log_b = -math.log(n)
    f = np.zeros(n)
    g = np.zeros(n)
    for _ in range(iterations):
        f = -eps * _lse(log_b + (g[None, :] - c) / eps, 1)
        g = -eps * _lse(log_a[:, None] + (f[:, None] - c) / eps, 0)
    plan = np.exp((f[:, None] + g[None, :] - c) / eps + log_a[:, None] + log_b)
    return plan, n * plan.T @ x


def _ot_cloud(seed, n=7, d=2):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, d, generator=g, dtype=D) * torch.tensor([1.0, 4.0][:d], dtype=D)
    lw = 1.2 * torch.randn(n, generator=g, dtype=D)
    return x, lw


@pytest.mark.parametrize("method", ["kernel", "log"])
def test_ot_particles_and_plan_match_a_numpy_sinkhorn(method):
    """Transported particles and plan of both methods at a tight tolerance against the
    numpy Sinkhorn above (small ``N``, so that the unweighted std's ``1/N`` matters):
    kills an unbiased variance in ``_standardise``, a variance for a std, a wrong
    cross term of the cost, a wrong normalisation axis of the plan."""
    x, lw = _ot_cloud(4)
    eps = 0.3
    ot = rs.OptimalTransport(epsilon=eps, tolerance=1e-11, max_iterations=20000, method=method)
    plan_np, y_np = _numpy_ot(x.numpy(), (lw + 3.0).numpy(), eps)
    y = ot(x, lw + 3.0).particles  # unnormalised log-weights are normalised inside
    np.testing.assert_allclose(y.numpy(), y_np, rtol=0, atol=1e-8)
    plan = ot.transport_matrix(x, lw + 3.0)
    np.testing.assert_allclose(plan.numpy(), plan_np, rtol=0, atol=1e-10)


def test_ot_log_first_error_is_the_row_marginal_error_of_the_zero_potentials():
    """After one log-domain iteration, ``last_error`` is the L1 row-marginal error of the
    plan before the update, i.e. of ``f = g = 0``: ``Σ_i w_i |Σ_j e^{−C_ij/ε}/N − 1|``
    (numpy, from the standardised cloud written out). Kills the error taken as
    ``Σ w_i |e^{(f′ − f)/ε} − 1|`` (the reciprocal row sums)."""
    x, lw = _ot_cloud(6, n=9)
    eps = 2.0
    ot = rs.OptimalTransport(epsilon=eps, max_iterations=1, tolerance=1e-12, method="log")
    with pytest.warns(RuntimeWarning, match="max_iterations"):
        ot(x, lw)
    xn, w = x.numpy(), torch.softmax(lw, -1).numpy()
    sd = xn.std(axis=0)
    xs = (xn - w @ xn) / sd
    c = ((xs[:, None, :] - xs[None, :, :]) ** 2).sum(-1)
    want = float((w * np.abs(np.exp(-c / eps).mean(1) - 1.0)).sum())
    assert ot.last_iterations == 1
    assert want > 0.1  # far from converged: the two error forms differ here
    assert ot.last_error == pytest.approx(want, rel=1e-10)


def test_ot_kernel_first_error_follows_the_documented_epsilon_scaling():
    """Kernel method, ``max_iterations=1``: ``last_error`` is the row-marginal error after
    one iteration at ``ε`` warm-started by the ε-scaling stages. Against the
    ``_kernel_sinkhorn`` docstring written out in numpy, log domain: one Sinkhorn iteration
    (``f`` then ``g``, ``a = w``, ``b = 1/N``) at each ``ε_k = ε/0.3^k ≤ 2 Σ_k Var(x̃_k)``
    from the largest down, potentials carried in cost units, then one at ``ε`` and the
    L1 row error of its plan. Kills a stage's column update without the weights ``a``."""
    x, lw = _ot_cloud(8, n=10)
    eps = 0.05
    ot = rs.OptimalTransport(epsilon=eps, max_iterations=1, tolerance=1e-14)
    with pytest.warns(RuntimeWarning, match="max_iterations"):
        ot(x, lw)
    xn = x.numpy()
    log_a = torch.log_softmax(lw, -1).numpy()
    xs = (xn - np.exp(log_a) @ xn) / xn.std(axis=0)
    c = ((xs[:, None, :] - xs[None, :, :]) ** 2).sum(-1)
    log_b = -math.log(10)
    start = 2.0 * xs.var(axis=0).sum()  # = 2 d = 4 for a standardised cloud
    stages, e = [], eps
    while e / 0.3 <= start:
        e /= 0.3
        stages.append(e)
    assert len(stages) == 3  # 0.05/0.3^k for k = 1, 2, 3 (k = 4 gives 6.2 > 4)
    f = np.zeros(10)
    g = np.zeros(10)
    for e in [*reversed(stages), eps]:  # f, g in cost units
        f = -e * _lse(log_b + (g[None, :] - c) / e, 1)
        g = -e * _lse(log_a[:, None] + (f[:, None] - c) / e, 0)
    rows = np.exp((f[:, None] + g[None, :] - c) / eps + log_a[:, None] + log_b).sum(1)
    want = float(np.abs(rows - np.exp(log_a)).sum())
    assert ot.last_iterations == 1
    assert ot.last_error == pytest.approx(want, rel=1e-8)


def test_residual_never_draws_a_particle_whose_residual_rounds_below_zero(monkeypatch):
    """``w_1 = 1/5`` exactly in intent; float64 gives ``N w_1`` an ulp under 1, so it is
    counted as one copy and its residual ``N w_1 − 1`` is ``−1e-16``. The residual weight
    must be 0 (the docstring: extra draws only where ``N w_i − ⌊N w_i⌋ > 0``): with
    ``N w ≈ [0.49, 1, 1.50, 0.83, 1.17]`` the copies are particles ``1, 2, 4`` and both
    ``R = 2`` residual draws, at a uniform whose target ``u·R`` falls in the ``1e-16`` dip
    a negative residual would leave in the cumulative sum, go to particle 0 (inverse CDF
    of ``[0.49, 0, 0.50, 0.83, 0.17]``, by hand). Kills dropping ``clamp_min(0)``."""
    lw = torch.tensor(
        [
            -2.326680366262343,
            -1.6094379124341003,
            -1.2009342948834354,
            -1.7923840950031582,
            -1.4485732675977057,
        ],
        dtype=D,
    )
    assert float(torch.logsumexp(lw, -1)) == pytest.approx(0.0, abs=1e-15)
    assert lw[1] == pytest.approx(-math.log(5), abs=1e-15)
    np.testing.assert_allclose(5 * np.exp(lw.numpy()), [0.488, 1, 1.505, 0.833, 1.175], atol=1e-3)
    monkeypatch.setattr(torch, "rand", _FixedRand(0.2440481750645695))
    got = rs.Residual()._draw(lw, None)
    assert got.tolist() == [1, 2, 4, 0, 0]


def test_ot_warns_when_the_stopping_error_is_nan():
    """``_record``'s contract: warn whenever the error is not below ``tolerance``, NaN
    included (a float32 kernel run on an unstandardised cloud of spread 1e6 stops at
    ``max_iterations=5`` with a NaN error, its particles still finite). Against that
    contract directly and on such a run. Kills ``error > tolerance`` (False for NaN)."""
    ot = rs.OptimalTransport()
    with pytest.warns(RuntimeWarning, match="max_iterations"):
        ot._record(3, math.nan)
    assert ot.last_iterations == 3 and math.isnan(ot.last_error)
    g = torch.Generator().manual_seed(0)
    torch.randn(2, 50 * 4, generator=g)  # skip to a cloud found to give a NaN error
    x = 1e6 * torch.randn(2, 50, 3, generator=g)
    lw = torch.log_softmax(torch.randn(2, 50, generator=g), -1)
    ot = rs.OptimalTransport(0.1, scale=False, max_iterations=5)
    with pytest.warns(RuntimeWarning, match="max_iterations"):
        out = ot(x, lw)
    assert bool(torch.isfinite(out.particles).all())
    assert not ot.last_error < ot.tolerance  # NaN on this cloud (CPU; not asserted)


@pytest.mark.parametrize("wrapper", ["Soft", "StopGradient"])
@pytest.mark.parametrize("inner", ["Soft", "StopGradient"])
def test_gradient_corrected_schemes_refuse_each_other_as_base(wrapper, inner):
    """``base`` must be index-based (Multinomial, Systematic, Stratified or Residual, as the
    error says): a Soft or StopGradient base would draw from its own ``q`` or ignore the
    correction of the outer scheme. Kills dropping StopGradient from the refused types."""
    with pytest.raises(ValueError, match="index-based"):
        getattr(rs, wrapper)(base=getattr(rs, inner)())


@pytest.mark.parametrize("method", ["kernel", "log"])
def test_ot_float32_is_translation_equivariant_far_from_the_origin(method):
    """The cost ``‖x̃_i − x̃_j‖²`` is translation invariant, so moving the cloud by
    ``c = (3e3, −5e3)`` must move the transported particles by ``c`` (the exact OT
    identity); in float32 that holds only because ``_standardise`` centres before the
    expanded square (``‖x̃‖²`` ~ 1e7 would otherwise cancel away the cost). Tolerance
    0.02 (the float32 ulp of 5e3 is 5e-4; spread ~1). Kills dropping the centring."""
    g = torch.Generator().manual_seed(5)
    x = torch.randn(30, 2, generator=g) * torch.tensor([1.0, 2.0])
    lw = torch.randn(30, generator=g)
    c = torch.tensor([3e3, -5e3])
    ot = rs.OptimalTransport(epsilon=0.1, tolerance=1e-4, max_iterations=2000, method=method)
    y0 = ot(x, lw).particles
    y1 = ot(x + c, lw).particles - c
    assert float((y0 - y1).abs().max()) < 0.02


def test_soft_mixture_counts_the_live_particles_of_each_row():
    """Batched ``q_i = α w_i + (1 − α)/N_alive`` with ``N_alive`` per row (the docstring:
    the uniform part spread over the particles of positive weight), by hand in numpy for
    two rows with 5 and 3 live particles; ``q`` sums to 1 in each row. Kills counting
    the live particles over the whole batch."""
    alpha = 0.4
    raw = np.array([[0.1, -1.0, 0.7, 2.0, -0.3], [0.5, -np.inf, 1.2, -np.inf, 0.0]])
    lw = torch.log_softmax(torch.tensor(raw, dtype=D), -1)
    q = rs.Soft(alpha)._log_q(lw).exp().numpy()
    w = np.exp(raw - raw.max(-1, keepdims=True))
    w = w / w.sum(-1, keepdims=True)
    alive = np.isfinite(raw)
    want = np.where(alive, alpha * w + (1 - alpha) / alive.sum(-1, keepdims=True), 0.0)
    np.testing.assert_allclose(q, want, rtol=1e-12, atol=0)
    np.testing.assert_allclose(q.sum(-1), [1.0, 1.0], rtol=1e-12)
