"""Tests for difffilter.resampling: unbiasedness, low variance, shapes, reproducibility,
differentiable corrections (soft, stop-gradient) and entropy-regularised OT."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from difffilter.resampling import (
    Multinomial,
    OptimalTransport,
    Resampled,
    Residual,
    Soft,
    StopGradient,
    Stratified,
    Systematic,
    effective_sample_size,
    normalize_log_weights,
)

INDEX_RESAMPLERS = {
    "multinomial": Multinomial(),
    "systematic": Systematic(),
    "stratified": Stratified(),
    "residual": Residual(),
    "residual_systematic": Residual(Systematic()),
    "residual_stratified": Residual(Stratified()),
    "soft_alpha1": Soft(alpha=1.0),
    "soft": Soft(alpha=0.5),
    "soft_systematic": Soft(alpha=0.3, base=Systematic()),
    "stop_gradient": StopGradient(),
}
# Schemes whose offspring counts have mean N·w (Soft with α < 1 samples from q instead).
UNBIASED = [k for k in INDEX_RESAMPLERS if k not in ("soft", "soft_systematic")]
ALL_RESAMPLERS = {**INDEX_RESAMPLERS, "optimal_transport": OptimalTransport()}

# Uneven weights whose N·w_i are all at least 0.01 away from an integer, so that
# floor/ceil checks are not at the mercy of round-off.
RAW_WEIGHTS = [0.5, 3.0, 0.1, 1.7, 0.05, 2.2, 0.9, 4.1, 0.3, 1.0, 0.02, 0.6, 1.5]


def _weights() -> torch.Tensor:
    w = torch.tensor(RAW_WEIGHTS, dtype=torch.float64)
    w = w / w.sum()
    nw = len(RAW_WEIGHTS) * w
    assert bool(((nw - nw.round()).abs() > 0.01).all())
    return w


def _counts(ancestors: torch.Tensor, n: int) -> torch.Tensor:
    """Offspring counts ``[..., N]`` from ancestors ``[..., N]``."""
    counts = torch.zeros(*ancestors.shape[:-1], n, dtype=torch.float64)
    return counts.scatter_add_(-1, ancestors, torch.ones_like(counts))


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# ---------------------------------------------------------------- index-based schemes


@pytest.mark.parametrize("name", UNBIASED)
def test_expected_offspring_counts_equal_n_w(name):
    w = _weights()
    n, rows = w.numel(), 4000
    log_w = torch.log(w).expand(rows, n)
    counts = _counts(INDEX_RESAMPLERS[name].ancestors(log_w, _gen(1)), n)
    assert bool((counts.sum(-1) == n).all())
    mean = counts.mean(0)
    se = counts.std(0) / math.sqrt(rows)
    assert bool(((mean - n * w).abs() < 4 * se + 1e-9).all()), (mean, n * w)


@pytest.mark.parametrize("name", ["systematic", "residual_systematic", "stop_gradient"])
def test_systematic_counts_are_floor_or_ceil(name):
    w = _weights()
    n = w.numel()
    counts = _counts(INDEX_RESAMPLERS[name].ancestors(torch.log(w).expand(2000, n), _gen(2)), n)
    nw = n * w
    assert bool(((counts == nw.floor()) | (counts == nw.ceil())).all())


def test_stratified_counts_within_one_of_floor_ceil():
    w = _weights()
    n = w.numel()
    counts = _counts(Stratified().ancestors(torch.log(w).expand(2000, n), _gen(3)), n)
    nw = n * w
    assert bool(((counts >= nw.floor() - 1) & (counts <= nw.ceil() + 1)).all())


@pytest.mark.parametrize("name", ["residual", "residual_systematic", "residual_stratified"])
def test_residual_keeps_deterministic_copies(name):
    w = _weights()
    n = w.numel()
    counts = _counts(INDEX_RESAMPLERS[name].ancestors(torch.log(w).expand(2000, n), _gen(4)), n)
    assert bool((counts >= (n * w).floor()).all())


def test_residual_rows_with_different_remainders():
    # Row 0: N·w all integers (R = 0, fully deterministic); row 1: R = N (all residual).
    n = 4
    log_w = torch.log(torch.tensor([[0.5, 0.25, 0.25, 0.0], [0.24, 0.24, 0.26, 0.26]]))
    anc = Residual().ancestors(log_w, _gen(5))
    assert anc[0].tolist() == [0, 0, 1, 2]
    assert bool(((anc[1] >= 0) & (anc[1] < n)).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_residual_gives_equal_weights_one_copy_each_whatever_the_round_off(dtype):
    """⌊N w_i⌋ is of the weights, not of exp(−log N)·N an ulp under 1 (at N = 10 in float64,
    157 of the N ≤ 399: every copy went to the residual draws, 37 % of particles lost)."""
    for n in range(1, 400):
        log_w = torch.full((n,), -math.log(n), dtype=dtype)
        anc = Residual().ancestors(log_w, _gen(n))
        assert anc.tolist() == list(range(n)), n
    # an exact N w_i = 1 among others, in float32: 0.99999994 had no deterministic copy
    w = torch.tensor([0.3, 0.2, 0.1, 0.4] + [0.0] * 6, dtype=torch.float32)
    counts = _counts(Residual().ancestors(torch.log(w).expand(500, 10), _gen(9)), 10)
    assert bool((counts == torch.tensor([3.0, 2, 1, 4] + [0] * 6, dtype=counts.dtype)).all())


@pytest.mark.parametrize("name", list(INDEX_RESAMPLERS))
@pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ancestors_valid_and_shapes(name, batch, dtype):
    n, d = 7, 2
    g = _gen(6)
    log_w = torch.randn(*batch, n, generator=g, dtype=dtype)
    particles = torch.randn(*batch, n, d, generator=g, dtype=dtype)
    out = INDEX_RESAMPLERS[name](particles, log_w, _gen(7))
    assert isinstance(out, Resampled)
    assert out.ancestors.dtype == torch.int64
    assert out.ancestors.shape == (*batch, n)
    assert bool(((out.ancestors >= 0) & (out.ancestors < n)).all())
    assert out.particles.shape == (*batch, n, d) and out.particles.dtype == dtype
    assert out.log_weights.shape == (*batch, n) and out.log_weights.dtype == dtype
    torch.testing.assert_close(
        torch.logsumexp(out.log_weights, -1), torch.zeros(batch, dtype=dtype)
    )
    flat_p = particles.reshape(-1, n, d)
    flat_a = out.ancestors.reshape(-1, n)
    expected = flat_p[torch.arange(flat_p.shape[0])[:, None], flat_a]
    torch.testing.assert_close(out.particles.reshape(-1, n, d), expected)
    # ancestors() draws the same indices as __call__ for the same seed.
    assert torch.equal(INDEX_RESAMPLERS[name].ancestors(log_w, _gen(7)), out.ancestors)


@pytest.mark.parametrize("name", list(INDEX_RESAMPLERS))
def test_reproducible_with_generator(name):
    log_w = torch.randn(10, 50, generator=_gen(8))
    r = INDEX_RESAMPLERS[name]
    a1 = r.ancestors(log_w, _gen(11))
    a2 = r.ancestors(log_w, _gen(11))
    a3 = r.ancestors(log_w, _gen(12))
    assert torch.equal(a1, a2)
    assert not torch.equal(a1, a3)
    torch.manual_seed(3)
    b1 = r.ancestors(log_w)
    torch.manual_seed(3)
    assert torch.equal(b1, r.ancestors(log_w))


@pytest.mark.parametrize("name", list(INDEX_RESAMPLERS))
def test_zero_weight_particles_never_selected(name):
    n = 9
    log_w = torch.randn(500, n, generator=_gen(9), dtype=torch.float32)
    dead = torch.tensor([True, False, False, True, False, False, False, False, True])
    log_w = log_w.masked_fill(dead, -math.inf)
    anc = INDEX_RESAMPLERS[name].ancestors(log_w, _gen(10))
    assert not bool(dead[anc].any())


def test_unnormalised_log_weights_give_same_draws():
    log_w = torch.randn(4, 20, generator=_gen(13), dtype=torch.float64)
    for r in INDEX_RESAMPLERS.values():
        assert torch.equal(r.ancestors(log_w, _gen(1)), r.ancestors(log_w + 123.0, _gen(1)))


@pytest.mark.parametrize("name", list(INDEX_RESAMPLERS))
def test_given_weights_give_the_same_draws(name):
    # the particle filter passes exp(log_w) it already has: the same ancestors, rows kept
    log_w = torch.log_softmax(torch.randn(5, 40, generator=_gen(14), dtype=torch.float64), -1)
    x = torch.randn(5, 40, 3, generator=_gen(15), dtype=torch.float64)
    rows = torch.tensor([True, False, True, True, False])
    r = INDEX_RESAMPLERS[name]
    for keep in (None, rows):
        plain = r.resample_normalized(x, log_w, _gen(2), rows=keep)
        given = r.resample_normalized(x, log_w, _gen(2), rows=keep, weights=torch.exp(log_w))
        assert torch.equal(plain.ancestors, given.ancestors)
        assert torch.equal(plain.particles, given.particles)
        assert torch.equal(plain.log_weights, given.log_weights)


def test_particles_broadcast_against_log_weights():
    particles = torch.randn(6, 2)
    log_w = torch.randn(3, 6)
    out = Systematic()(particles, log_w, _gen(0))
    assert out.particles.shape == (3, 6, 2)
    torch.testing.assert_close(out.particles, particles[out.ancestors])


def test_gradient_flows_to_particles_through_gather():
    particles = torch.randn(2, 5, 3, requires_grad=True)
    out = Multinomial()(particles, torch.randn(2, 5), _gen(0))
    out.particles.sum().backward()
    counts = _counts(out.ancestors, 5).to(particles.dtype)
    torch.testing.assert_close(particles.grad, counts.unsqueeze(-1).expand(2, 5, 3))


# ------------------------------------------------------------------ soft resampling


def test_soft_weights_by_hand():
    alpha, n = 0.3, 4
    log_w = torch.log(torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=torch.float64)) + 2.0
    particles = torch.arange(4, dtype=torch.float64).reshape(4, 1)
    out = Soft(alpha=alpha)(particles, log_w, _gen(21))
    w = torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=torch.float64)
    q = alpha * w + (1 - alpha) / n
    # Ancestors come from the base scheme applied to q.
    assert torch.equal(out.ancestors, Multinomial().ancestors(torch.log(q), _gen(21)))
    ratio = (w / q)[out.ancestors]
    torch.testing.assert_close(out.log_weights.exp(), ratio / ratio.sum())
    torch.testing.assert_close(out.particles[:, 0], out.ancestors.to(torch.float64))


def test_soft_with_zero_weights_stays_finite():
    # Two particles, one of zero weight: the uniform part of q covers only the live one.
    log_w = torch.tensor([[0.0, -math.inf]] * 50, requires_grad=True)
    particles = torch.randn(50, 2, 1)
    out = Soft(alpha=0.5)(particles, log_w, _gen(26))
    assert bool((out.ancestors == 0).all())
    assert bool(torch.isfinite(out.log_weights).all())
    out.log_weights.exp().mul(out.particles[..., 0]).sum().backward()
    assert bool(torch.isfinite(log_w.grad).all())


def test_soft_alpha_one_is_plain_resampling():
    log_w = torch.randn(3, 8, generator=_gen(22))
    particles = torch.randn(3, 8, 2)
    soft = Soft(alpha=1.0)(particles, log_w, _gen(5))
    plain = Multinomial()(particles, log_w, _gen(5))
    assert torch.equal(soft.ancestors, plain.ancestors)
    torch.testing.assert_close(soft.log_weights, plain.log_weights)


def test_soft_gradient_reaches_log_weights():
    log_w = torch.randn(4, 10, generator=_gen(23), dtype=torch.float64).requires_grad_()
    particles = torch.randn(4, 10, 2, generator=_gen(24), dtype=torch.float64)
    out = Soft(alpha=0.5)(particles, log_w, _gen(25))
    estimate = (out.log_weights.exp().unsqueeze(-1) * out.particles).sum()
    estimate.backward()
    assert bool(torch.isfinite(log_w.grad).all())
    assert float(log_w.grad.abs().sum()) > 0


def test_soft_gradient_is_that_of_w_over_q_with_the_ancestors_held():
    """A mutation trial: with ``q`` detached in the correction ``w_a / q_a`` every test
    passed. With the draw held (one seeded generator per call, the ancestors piecewise
    constant in ``log w``), the new log-weights are a smooth function of ``log w``, and
    their gradient, through ``q = α w + (1 − α)/N`` as well as ``w``, is checked against
    finite differences in float64."""
    log_w = torch.randn(2, 6, generator=_gen(27), dtype=torch.float64).requires_grad_()
    particles = torch.randn(2, 6, 1, generator=_gen(28), dtype=torch.float64)
    ancestors = Soft(alpha=0.4)(particles, log_w, _gen(29)).ancestors

    def new_log_weights(lw):
        out = Soft(alpha=0.4)(particles, lw, _gen(29))
        assert torch.equal(out.ancestors, ancestors)  # (the draw held: no boundary crossed)
        return out.log_weights

    assert torch.autograd.gradcheck(new_log_weights, (log_w,), eps=1e-6, atol=1e-8)


# --------------------------------------------------------------- stop-gradient


def test_stop_gradient_values_uniform_and_score_gradient():
    n = 12
    log_w = torch.randn(3, n, generator=_gen(31), dtype=torch.float64).requires_grad_()
    particles = torch.randn(3, n, 1, generator=_gen(32), dtype=torch.float64)
    out = StopGradient()(particles, log_w, _gen(33))
    torch.testing.assert_close(
        out.log_weights.detach(), torch.full((3, n), -math.log(n), dtype=torch.float64)
    )
    h = out.particles[..., 0]
    (out.log_weights.exp() * h).sum().backward()
    # By hand: ∇_ℓk (1/N) Σ_j h_j log w_{a_j} with log w = ℓ − logsumexp ℓ
    #        = (1/N) [Σ_j h_j 1(a_j = k) − w_k Σ_j h_j].
    w = torch.softmax(log_w.detach(), -1)
    hits = torch.zeros(3, n, dtype=torch.float64).scatter_add_(-1, out.ancestors, h)
    expected = (hits - w * h.sum(-1, keepdim=True)) / n
    torch.testing.assert_close(log_w.grad, expected)


# ------------------------------------------------------------ optimal transport


def _ot_case(batch=(3,), n=40, d=2, dtype=torch.float64, seed=41):
    g = _gen(seed)
    particles = torch.randn(*batch, n, d, generator=g, dtype=dtype) * torch.tensor(
        [1.0, 3.0][:d] + [1.0] * max(d - 2, 0), dtype=dtype
    )
    log_w = 1.5 * torch.randn(*batch, n, generator=g, dtype=dtype)
    return particles, log_w


def test_ot_preserves_weighted_mean_and_marginals():
    # float32, default tolerance 1e-3 (max_iterations raised so that it is reached; this
    # uneven case needs ~150 iterations). Columns of the plan are normalised exactly and
    # rows to L1 error < tolerance, so |mean_new − Σ w x| <= 1e-3 · max_i |x_i − Σ w x|.
    particles, log_w = _ot_case(dtype=torch.float32)
    ot = OptimalTransport(max_iterations=1000)
    out = ot(particles, log_w)
    w = torch.softmax(log_w, -1)
    mean_in = (w.unsqueeze(-1) * particles).sum(-2)
    mean_out = out.particles.mean(-2)
    radius = (particles - mean_in.unsqueeze(-2)).norm(dim=-1).amax(-1)
    assert bool(((mean_out - mean_in).norm(dim=-1) <= ot.tolerance * radius + 1e-5).all())
    assert out.ancestors is None
    torch.testing.assert_close(out.log_weights, torch.full_like(log_w, -math.log(40)))

    plan = ot.transport_matrix(particles, log_w)
    assert plan.shape == (3, 40, 40)
    assert float((plan.sum(-1) - w).abs().sum(-1).max()) < ot.tolerance
    torch.testing.assert_close(plan.sum(-2), torch.full_like(w, 1 / 40))
    torch.testing.assert_close(40 * plan.mT @ particles, out.particles)


def test_ot_mean_error_bounded_by_marginal_error_at_defaults():
    # Whether or not Sinkhorn reached the tolerance within max_iterations, the mean error
    # is at most the plan's L1 row-marginal error times the cloud radius.
    particles, log_w = _ot_case(dtype=torch.float64)
    ot = OptimalTransport()
    w = torch.softmax(log_w, -1)
    row_error = (ot.transport_matrix(particles, log_w).sum(-1) - w).abs().sum(-1)
    mean_in = (w.unsqueeze(-1) * particles).sum(-2)
    radius = (particles - mean_in.unsqueeze(-2)).norm(dim=-1).amax(-1)
    error = (ot(particles, log_w).particles.mean(-2) - mean_in).norm(dim=-1)
    assert bool((error <= row_error * radius + 1e-10).all())
    assert float(row_error.max()) < 0.05


def test_ot_tight_tolerance_float64():
    particles, log_w = _ot_case()
    ot = OptimalTransport(tolerance=1e-9, max_iterations=5000)
    w = torch.softmax(log_w, -1)
    plan = ot.transport_matrix(particles, log_w)
    assert float((plan.sum(-1) - w).abs().sum(-1).max()) < 1e-9
    torch.testing.assert_close(plan.sum(-2), torch.full_like(w, 1 / 40), rtol=0, atol=1e-12)
    mean_in = (w.unsqueeze(-1) * particles).sum(-2)
    torch.testing.assert_close(ot(particles, log_w).particles.mean(-2), mean_in, rtol=0, atol=1e-7)


def test_ot_small_epsilon_preserves_weighted_covariance():
    particles, log_w = _ot_case(batch=(), n=30)
    w = torch.softmax(log_w, -1)
    m = w @ particles
    cov_in = ((particles - m).T * w) @ (particles - m)

    def cov_error(eps):
        out = OptimalTransport(epsilon=eps, max_iterations=5000, tolerance=1e-6)(particles, log_w)
        y = out.particles - out.particles.mean(0)
        return float((y.T @ y / 30 - cov_in).norm() / cov_in.norm())

    errors = [cov_error(eps) for eps in (1.0, 0.1, 0.01)]
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.1


def test_ot_uniform_weights_small_epsilon_is_near_identity():
    particles, _ = _ot_case(batch=(2,), n=20)
    out = OptimalTransport(epsilon=1e-3, max_iterations=5000, tolerance=1e-6)(
        particles, torch.zeros(2, 20, dtype=torch.float64)
    )
    assert float((out.particles - particles).abs().max()) < 0.05 * float(particles.std())


def test_ot_kernel_method_stays_finite_where_the_scaled_costs_are_huge():
    """float32 particles of spread 1e4 without standardising, ε = 0.1 (|C/ε| ~ 1e9): the
    kernel was made twice while absorbing the potentials, and the two products rounded
    88 apart: an infinite kernel, NaN particles. (Unconverged at this ε, as the log
    method is: each new particle a convex combination of the old.)"""
    g = torch.Generator().manual_seed(0)
    particles = 1e4 * torch.randn(2, 50, 3, generator=g)
    log_w = torch.log_softmax(torch.randn(2, 50, generator=g), -1)
    kernel = OptimalTransport(0.1, scale=False)(particles, log_w).particles
    log = OptimalTransport(0.1, scale=False, method="log")(particles, log_w).particles
    assert bool(torch.isfinite(kernel).all()) and bool(torch.isfinite(log).all())
    low, high = particles.amin(-2, keepdim=True), particles.amax(-2, keepdim=True)
    assert bool(((kernel >= low - 1e-2) & (kernel <= high + 1e-2)).all())


def test_ot_degenerate_weights_collapse_to_one_particle():
    particles, _ = _ot_case(batch=(2,), n=15)
    log_w = torch.full((2, 15), -math.inf, dtype=torch.float64)
    log_w[:, 4] = 0.0
    out = OptimalTransport()(particles, log_w)
    torch.testing.assert_close(out.particles, particles[:, 4:5].expand(2, 15, 2))


@pytest.mark.parametrize("method", ["kernel", "log"])
@pytest.mark.parametrize("wrt", ["log_weights", "particles"])
def test_ot_gradient_matches_finite_differences(wrt, method):
    # Tight forward tolerance and many differentiated iterations make the truncated
    # implicit gradient converge to the exact one (the default grad_iterations=5 is an
    # approximation of it, traded for speed).
    particles, log_w = _ot_case(batch=(1,), n=5, seed=42)
    ot = OptimalTransport(
        epsilon=0.5, tolerance=1e-13, max_iterations=20000, grad_iterations=300, method=method
    )
    coeff = torch.randn(1, 5, 2, generator=_gen(43), dtype=torch.float64)

    if wrt == "log_weights":

        def fn(lw):
            return (ot(particles, lw).particles * coeff).sum()

        arg = log_w
    else:

        def fn(x):
            return (ot(x, log_w).particles * coeff).sum()

        arg = particles
    assert torch.autograd.gradcheck(fn, (arg.clone().requires_grad_(),), eps=1e-6, atol=1e-6)


def test_ot_checkpoint_gives_same_gradients_and_finite():
    particles, log_w = _ot_case(batch=(2,), n=25)
    grads = []
    for ckpt in (True, False):
        x = particles.clone().requires_grad_()
        lw = log_w.clone().requires_grad_()
        out = OptimalTransport(checkpoint=ckpt)(x, lw)
        (out.particles.square().sum()).backward()
        grads.append((x.grad, lw.grad))
        assert bool(torch.isfinite(x.grad).all() and torch.isfinite(lw.grad).all())
        assert float(lw.grad.abs().sum()) > 0
    torch.testing.assert_close(grads[0], grads[1])


@pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
def test_ot_batch_shapes_match_rowwise(batch):
    particles, log_w = _ot_case(batch=batch, n=12)
    ot = OptimalTransport()
    out = ot(particles, log_w)
    assert out.particles.shape == (*batch, 12, 2)
    assert out.log_weights.shape == (*batch, 12)
    assert ot.transport_matrix(particles, log_w).shape == (*batch, 12, 12)
    flat_p, flat_w = particles.reshape(-1, 12, 2), log_w.reshape(-1, 12)
    rows = torch.stack([ot(flat_p[i], flat_w[i]).particles for i in range(flat_p.shape[0])])
    # Rows may stop at different iteration counts when batched; agree within tolerance.
    torch.testing.assert_close(out.particles.reshape(-1, 12, 2), rows, rtol=0, atol=5e-2)


def test_ot_memory_sanity_b4_n500():
    particles, log_w = _ot_case(batch=(4,), n=500, dtype=torch.float32)
    x = particles.requires_grad_()
    lw = log_w.requires_grad_()
    out = OptimalTransport()(x, lw)
    out.particles.mean().backward()
    assert out.particles.shape == (4, 500, 2)
    assert bool(torch.isfinite(out.particles).all())
    assert bool(torch.isfinite(x.grad).all() and torch.isfinite(lw.grad).all())


# ------------------------- kernel-domain Sinkhorn (default) against method="log" ----


@pytest.mark.parametrize("eps", [0.01, 0.1, 1.0])
def test_ot_kernel_marginals_within_tolerance(eps):
    # ε = 0.01 goes through stabilising absorptions and over-relaxation (ω up to 1.8);
    # ε = 1 converges in a few plain iterations. Columns are normalised exactly.
    particles, log_w = _ot_case(batch=(3,), n=40)
    ot = OptimalTransport(epsilon=eps, max_iterations=5000)
    w = torch.softmax(log_w, -1)
    plan = ot.transport_matrix(particles, log_w)
    assert float((plan.sum(-1) - w).abs().sum(-1).max()) < ot.tolerance
    torch.testing.assert_close(plan.sum(-2), torch.full_like(w, 1 / 40), rtol=0, atol=1e-12)
    torch.testing.assert_close(40 * plan.mT @ particles, ot(particles, log_w).particles)


def test_ot_kernel_float32_small_epsilon_stays_finite_and_within_tolerance():
    particles, log_w = _ot_case(dtype=torch.float32)
    ot = OptimalTransport(epsilon=0.01, max_iterations=5000)
    out = ot(particles, log_w)
    assert bool(torch.isfinite(out.particles).all())
    plan = ot.transport_matrix(particles, log_w)
    assert float((plan.sum(-1) - torch.softmax(log_w, -1)).abs().sum(-1).max()) < ot.tolerance


@pytest.mark.parametrize(
    ("settings", "bound"),
    [
        # converged: the two algorithms give the same particles up to the tolerance
        ({"epsilon": 0.05, "tolerance": 1e-10, "max_iterations": 20000}, 1e-8),
        # both at an L1 row-marginal error < 1e-3 (measured 0.008 standard deviations)
        ({"max_iterations": 1000}, 0.03),
    ],
)
def test_ot_kernel_agrees_with_log_domain(settings, bound):
    particles, log_w = _ot_case(batch=(3,), n=40)
    new = OptimalTransport(**settings)(particles, log_w).particles
    old = OptimalTransport(method="log", **settings)(particles, log_w).particles
    scale = particles.std(dim=-2, keepdim=True)
    assert float(((new - old) / scale).abs().max()) < bound


@pytest.mark.parametrize("grad_iterations", [0, 5])
def test_ot_kernel_gradient_matches_log_domain(grad_iterations):
    # From (nearly) the same converged potentials both differentiate the same truncated
    # fixed-point iteration, so their gradients agree however many iterations are unrolled.
    particles, log_w = _ot_case(batch=(2,), n=30)
    coeff = torch.randn(2, 30, 2, generator=_gen(5), dtype=torch.float64)
    grads = {}
    for method in ("kernel", "log"):
        x, lw = particles.clone().requires_grad_(), log_w.clone().requires_grad_()
        ot = OptimalTransport(
            tolerance=1e-11, max_iterations=20000, grad_iterations=grad_iterations, method=method
        )
        (ot(x, lw).particles * coeff).sum().backward()
        grads[method] = (x.grad, lw.grad)
    torch.testing.assert_close(grads["kernel"], grads["log"], rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("checkpoint", [True, False])
def test_ot_kernel_backward_matches_autograd_through_the_plan(checkpoint):
    # The hand-written backward of the kernel-domain iterations against autograd through
    # the same iterations (transport_matrix), at the defaults (not converged: the same
    # function either way).
    particles, log_w = _ot_case(batch=(2,), n=20, d=3)
    coeff = torch.randn(2, 20, 3, generator=_gen(7), dtype=torch.float64)
    ot = OptimalTransport(checkpoint=checkpoint)
    x1, l1 = particles.clone().requires_grad_(), log_w.clone().requires_grad_()
    (ot(x1, l1).particles * coeff).sum().backward()
    x2, l2 = particles.clone().requires_grad_(), log_w.clone().requires_grad_()
    ((20 * ot.transport_matrix(x2, l2).mT @ x2) * coeff).sum().backward()
    torch.testing.assert_close((x1.grad, l1.grad), (x2.grad, l2.grad), rtol=1e-9, atol=1e-11)


@pytest.mark.parametrize(("scaling", "max_relaxation"), [(0.0, 1.0), (0.3, 1.0), (0.0, 1.8)])
def test_ot_kernel_acceleration_cuts_iterations(scaling, max_relaxation):
    # ε-scaling and over-relaxation each reach the same tolerance in fewer iterations than
    # plain kernel-domain Sinkhorn, and both together in fewer still (counts, not times).
    from difffilter.resampling import _kernel_sinkhorn, _standardise

    particles, log_w = _ot_case(batch=(3,), n=40)
    log_a = normalize_log_weights(log_w)
    xs = _standardise(particles, log_a, True)

    def iterations(**kw):
        state = _kernel_sinkhorn(xs, log_a, 0.05, 1e-6, 5000, **kw)
        assert state.error < 1e-6
        return state.iterations

    both = iterations()
    variant = iterations(scaling=scaling, max_relaxation=max_relaxation)
    assert both < variant
    if (scaling, max_relaxation) != (0.0, 1.0):
        assert variant < iterations(scaling=0.0, max_relaxation=1.0)


def test_ot_has_no_ancestors():
    with pytest.raises(NotImplementedError):
        OptimalTransport().ancestors(torch.zeros(4))


def test_differentiable_flags():
    flags = {name: r.differentiable for name, r in ALL_RESAMPLERS.items()}
    assert flags["multinomial"] is False and flags["systematic"] is False
    assert flags["soft"] and flags["stop_gradient"] and flags["optimal_transport"]


# ------------------------------------------------------------------------- ESS


def test_effective_sample_size():
    assert float(effective_sample_size(torch.zeros(10))) == pytest.approx(10.0)
    one_hot = torch.full((2, 3, 5), -math.inf)
    one_hot[..., 2] = 0.0
    torch.testing.assert_close(effective_sample_size(one_hot), torch.ones(2, 3))
    log_w = torch.randn(4, 7, dtype=torch.float64)
    w = torch.softmax(log_w, -1)
    torch.testing.assert_close(effective_sample_size(log_w + 50.0), 1 / (w**2).sum(-1))
    torch.testing.assert_close(
        torch.logsumexp(normalize_log_weights(log_w), -1), torch.zeros(4, dtype=torch.float64)
    )


# ------------------------------------------------------------------ validation


@pytest.mark.parametrize("name", list(ALL_RESAMPLERS))
def test_bad_inputs_raise_value_error(name):
    r = ALL_RESAMPLERS[name]
    particles = torch.randn(2, 5, 3)
    with pytest.raises(ValueError, match="particles"):
        r(particles, torch.zeros(2, 6))
    with pytest.raises(ValueError, match="particles"):
        r(torch.randn(2, 5), torch.zeros(2, 5))
    with pytest.raises(ValueError, match="batch"):
        r(particles, torch.zeros(3, 5))
    with pytest.raises(ValueError, match="log_weights.*NaN"):
        r(particles, torch.tensor([[0.0, math.nan, 0, 0, 0]] * 2))
    with pytest.raises(ValueError, match="log_weights.*all -inf"):
        r(particles, torch.tensor([[0.0] * 5, [-math.inf] * 5]))
    with pytest.raises(ValueError, match="log_weights.*\\+inf"):
        r(particles, torch.tensor([[0.0, math.inf, 0, 0, 0]] * 2))
    bad = particles.clone()
    bad[0, 1, 2] = math.nan
    with pytest.raises(ValueError, match="particles.*NaN"):
        r(bad, torch.zeros(2, 5))
    with pytest.raises(ValueError, match="log_weights"):
        r(particles, [0.0] * 5)


def test_bad_log_weights_in_ancestors_and_ess():
    with pytest.raises(ValueError, match="log_weights"):
        Systematic().ancestors(torch.tensor([math.nan, 0.0]))
    with pytest.raises(ValueError, match="log_weights"):
        Multinomial().ancestors(torch.zeros(2, 0))
    with pytest.raises(ValueError, match="log_weights"):
        effective_sample_size(torch.tensor([-math.inf, -math.inf]))
    with pytest.raises(ValueError, match="log_weights.*floating"):
        Multinomial().ancestors(torch.zeros(3, dtype=torch.int64))


@pytest.mark.parametrize(
    ("factory", "argument"),
    [
        (lambda: Soft(alpha=0.0), "alpha"),
        (lambda: Soft(alpha=1.5), "alpha"),
        (lambda: Soft(alpha=True), "alpha"),
        (lambda: Soft(alpha="0.5"), "alpha"),
        (lambda: Soft(base=OptimalTransport()), "base"),
        (lambda: StopGradient(base="systematic"), "base"),
        (lambda: Residual(base=Soft()), "base"),
        (lambda: Residual(base=Residual()), "base"),
        (lambda: OptimalTransport(epsilon=0.0), "epsilon"),
        (lambda: OptimalTransport(epsilon=math.inf), "epsilon"),
        (lambda: OptimalTransport(max_iterations=0), "max_iterations"),
        (lambda: OptimalTransport(max_iterations=2.5), "max_iterations"),
        (lambda: OptimalTransport(tolerance=-1e-3), "tolerance"),
        (lambda: OptimalTransport(tolerance=2.0), "tolerance must be below 2"),
        (lambda: OptimalTransport(grad_iterations=-1), "grad_iterations"),
        (lambda: OptimalTransport(scale="yes"), "scale"),
        (lambda: OptimalTransport(checkpoint=1), "checkpoint"),
        (lambda: OptimalTransport(method="sinkhorn"), "method"),
    ],
)
def test_bad_constructor_arguments(factory, argument):
    with pytest.raises(ValueError, match=argument):
        factory()


def test_counts_from_numpy_are_integers():
    import numpy as np

    ot = OptimalTransport(max_iterations=np.int64(50), grad_iterations=np.int32(2))
    assert (ot.max_iterations, ot.grad_iterations) == (50, 2)
    assert type(ot.max_iterations) is int


@pytest.mark.parametrize("resampler", [Systematic(), StopGradient(), OptimalTransport()], ids=repr)
def test_resample_normalized_rows_keeps_the_unmarked_rows(resampler):
    gen = torch.Generator().manual_seed(0)
    particles = torch.randn(4, 32, 2, dtype=torch.float64, generator=gen)
    log_w = torch.log_softmax(2 * torch.randn(4, 32, dtype=torch.float64, generator=gen), -1)
    rows = torch.tensor([True, False, True, False])
    full = resampler.resample_normalized(particles, log_w, torch.Generator().manual_seed(1))
    part = resampler.resample_normalized(
        particles, log_w, torch.Generator().manual_seed(1), rows=rows
    )
    torch.testing.assert_close(part.particles[rows], full.particles[rows])
    torch.testing.assert_close(part.log_weights[rows], full.log_weights[rows])
    torch.testing.assert_close(part.particles[~rows], particles[~rows])
    torch.testing.assert_close(part.log_weights[~rows], log_w[~rows])


def test_gather_keeps_a_component_major_layout():
    from difffilter.resampling import _gather_particles

    g = torch.Generator().manual_seed(0)
    rows = torch.randn(3, 4, 50, generator=g)  # [B, d, N] in memory
    particles = rows.transpose(-1, -2)  # viewed [B, N, d]
    ancestors = torch.randint(0, 50, (3, 50), generator=g)
    out = _gather_particles(particles, ancestors)
    want = _gather_particles(particles.contiguous(), ancestors)
    assert torch.equal(out, want) and out.transpose(-1, -2).is_contiguous()
    assert torch.equal(out[1, 7], particles[1, ancestors[1, 7]])


def test_stratified_draws_each_stratum_apart_and_systematic_does_not():
    """w = (1/6, 2/3, 1/6), N = 3: with independent strata particle 1 gets 3 copies with
    probability 1/4; one shared offset (systematic) always gives it exactly 2. Both have
    the same mean counts, all the other tests compared."""
    lw = torch.tensor([1 / 6, 2 / 3, 1 / 6], dtype=torch.float64).log().expand(4000, 3)
    share = {}
    for name, r in (("stratified", Stratified()), ("systematic", Systematic())):
        ancestors = r.ancestors(lw, torch.Generator().manual_seed(2))
        share[name] = float(((ancestors == 1).sum(-1) == 3).double().mean())
    assert abs(share["stratified"] - 0.25) < 0.03 and share["systematic"] == 0.0


@pytest.mark.parametrize("method", ["kernel", "log"])
def test_optimal_transport_reports_how_sinkhorn_stopped(method):
    """A Sinkhorn cut at max_iterations above tolerance warns and says by how much (the
    transported mean is then off the weighted mean); a converged one is silent."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 50, 2, generator=g, dtype=torch.float64)
    lw = torch.randn(3, 50, generator=g, dtype=torch.float64)
    w = torch.softmax(lw, -1)
    cut = OptimalTransport(max_iterations=1, tolerance=1e-9, grad_iterations=0, method=method)
    with pytest.warns(RuntimeWarning, match="max_iterations"):
        out = cut(x, lw)
    assert cut.last_iterations == 1 and cut.last_error > 1e-9
    # the error it reports is the row-marginal error behind the mean's shift
    shift = (out.particles.mean(-2) - (w.unsqueeze(-1) * x).sum(-2)).abs().max()
    assert shift > 1e-6
    fine = OptimalTransport(max_iterations=1000, tolerance=1e-9, method=method)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = fine(x, lw)
    assert fine.last_error < 1e-9 and 1 < fine.last_iterations < 1000
    shift = (out.particles.mean(-2) - (w.unsqueeze(-1) * x).sum(-2)).abs().max()
    assert shift < 1e-7


def test_residual_reads_weights_of_large_log_magnitude_as_they_are():
    """A resampler trial: normalised float32 log-weights near −1e6 exponentiate to weights
    summing to 0.97–1.03 (their logsumexp rounds to the ulp of 1e6: three equal ones gave
    N w = 0.974 each, no deterministic copy, three multinomial draws); residual resampling
    renormalises them in float64, so equal weights keep one copy each."""
    for offset in (0.0, -1e5, -1e6):
        anc = Residual().ancestors(torch.full((200, 3), offset, dtype=torch.float32), _gen(3))
        assert anc.tolist() == [[0, 1, 2]] * 200, offset
