"""Noise models: densities against torch.distributions, moments against samples."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.noise import Gaussian, GaussianMixture, UniformBox

D = torch.float64


def test_gaussian_log_prob_and_sampling_moments():
    cov = torch.tensor([[2.0, 0.6, 0.0], [0.6, 1.0, -0.3], [0.0, -0.3, 0.5]], dtype=D)
    loc = torch.tensor([1.0, -2.0, 0.5], dtype=D)
    g = Gaussian(loc, cov)
    x = torch.randn(50, 3, dtype=D, generator=torch.Generator().manual_seed(0))
    ref = torch.distributions.MultivariateNormal(loc, cov)
    torch.testing.assert_close(g.log_prob(x), ref.log_prob(x))
    s = g.sample((40000,), generator=torch.Generator().manual_seed(1))
    assert s.shape == (40000, 3)
    torch.testing.assert_close(s.mean(0), loc, atol=0.03, rtol=0)
    torch.testing.assert_close(torch.cov(s.T), cov, atol=0.05, rtol=0)


def test_gaussian_diagonal_fast_path_equals_general_path():
    cov = torch.diag(torch.tensor([0.5, 2.0], dtype=D))
    g = Gaussian(torch.zeros(2, dtype=D), cov.clone())
    x = torch.randn(10, 2, dtype=D, generator=torch.Generator().manual_seed(2))
    ref = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=D), cov)
    torch.testing.assert_close(g.log_prob(x), ref.log_prob(x))
    # the cached factor follows in-place edits of the covariance
    g._cov.mul_(4.0)
    ref = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=D), 4.0 * cov)
    torch.testing.assert_close(g.log_prob(x), ref.log_prob(x))


def test_gaussian_masked_log_prob_is_the_marginal():
    cov = torch.tensor([[2.0, 0.6, 0.2], [0.6, 1.0, -0.3], [0.2, -0.3, 0.5]], dtype=D)
    g = Gaussian(torch.zeros(3, dtype=D), cov)
    x = torch.randn(7, 3, dtype=D, generator=torch.Generator().manual_seed(3))
    mask = torch.tensor([True, False, True])
    keep = mask.nonzero().squeeze(-1)
    ref = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=D), cov[keep][:, keep])
    torch.testing.assert_close(g.log_prob(x, mask), ref.log_prob(x[:, keep]))


def test_gaussian_scale_tril_and_gradient():
    L = torch.tensor([[1.0, 0.0], [0.5, 2.0]], dtype=D, requires_grad=True)
    g = Gaussian(torch.zeros(2, dtype=D), scale_tril=L)
    x = torch.tensor([[0.3, -1.0]], dtype=D)
    lp = g.log_prob(x).sum()
    lp.backward()
    ref = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=D), scale_tril=L.detach())
    assert math.isclose(lp.item(), ref.log_prob(x).item(), rel_tol=1e-12)
    assert torch.isfinite(L.grad).all()


def test_a_scale_tril_whose_diagonal_training_made_negative_is_the_same_covariance():
    """A user trial: an optimiser step took a scale_tril Parameter's diagonal to -0.7; the
    Kalman filters (reading cov = L Lᵀ) ran on, the particle filter's densities were NaN
    (log of a negative diagonal) and it ignored every measurement without a word."""
    import difffilter as df

    L = torch.nn.Parameter(torch.tensor([[0.7, 0.0], [0.2, 0.4]], dtype=D))
    g = Gaussian(torch.zeros(2, dtype=D), scale_tril=L)
    x = torch.randn(5, 2, dtype=D, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        L[0, 0] = -0.7
    after = g.log_prob(x)  # the density of cov = L Lᵀ, as the Kalman filters read it
    cov = (L @ L.T).detach()
    ref = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=D), cov).log_prob(x)
    torch.testing.assert_close(after, ref, rtol=1e-13, atol=0)
    torch.testing.assert_close(g.cov, L @ L.T)
    after.sum().backward()  # the gradient of the same density, with the sign
    flipped = L.detach().clone()
    flipped[:, 0] *= -1
    ref = torch.nn.Parameter(flipped)
    Gaussian(torch.zeros(2, dtype=D), scale_tril=ref).log_prob(x).sum().backward()
    torch.testing.assert_close(L.grad[:, 1], ref.grad[:, 1])
    torch.testing.assert_close(L.grad[:, 0], -ref.grad[:, 0])
    # a particle filter's likelihood is then the one of the positive factor
    F, H = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=D), torch.eye(2, dtype=D)
    model = df.LinearGaussianModel(F, H, 1e-2 * torch.eye(2, dtype=D), torch.eye(2, dtype=D),
                                   torch.zeros(2, dtype=D), torch.eye(2, dtype=D))  # fmt: skip
    model.measurement_noise = g  # (how a noise model of one's own is given)
    ys = torch.randn(2, 10, 2, dtype=D, generator=torch.Generator().manual_seed(6))
    lls = []
    for sign in (-1.0, 1.0):  # column 0 negated: the same cov, a negative diagonal
        with torch.no_grad():
            L[:, 0] = sign * torch.tensor([0.7, 0.2], dtype=D)
            run = df.particle_filter(model, ys, num_particles=64,
                                     generator=torch.Generator().manual_seed(7))  # fmt: skip
            lls.append(run.log_likelihood)
    assert bool(torch.isfinite(lls[0]).all())
    torch.testing.assert_close(lls[0], lls[1], rtol=1e-12, atol=0)
    with torch.no_grad():
        L[1, 1] = 0.0
    with pytest.raises(ValueError, match="scale_tril has a zero on its diagonal"):
        g.log_prob(x)


def test_mixture_log_prob_moments_and_sampling():
    weights = torch.tensor([0.8, 0.2], dtype=D)
    locs = torch.zeros(2, 2, dtype=D)
    covs = torch.stack(
        [
            torch.diag(torch.tensor([4.0, 1e-2], dtype=D)),
            torch.diag(torch.tensor([25.0, 4e-2], dtype=D)),
        ]
    )
    mix = GaussianMixture(weights, locs, covs)
    x = torch.randn(9, 2, dtype=D, generator=torch.Generator().manual_seed(4))
    comps = torch.stack(
        [torch.distributions.MultivariateNormal(locs[c], covs[c]).log_prob(x) for c in range(2)], -1
    )
    torch.testing.assert_close(mix.log_prob(x), torch.logsumexp(comps + weights.log(), -1))
    torch.testing.assert_close(mix.cov, 0.8 * covs[0] + 0.2 * covs[1])
    s = mix.sample((100000,), generator=torch.Generator().manual_seed(5))
    torch.testing.assert_close(s.var(0), mix.cov.diagonal(), rtol=0.03, atol=0)
    # masked: mixture of the marginals
    mask = torch.tensor([True, False])
    marg = torch.stack(
        [torch.distributions.Normal(0.0, covs[c, 0, 0].sqrt()).log_prob(x[:, 0]) for c in range(2)],
        -1,
    )
    torch.testing.assert_close(mix.log_prob(x, mask), torch.logsumexp(marg + weights.log(), -1))


def test_uniform_box():
    box = UniformBox(
        torch.tensor([-10.0, -math.pi / 2], dtype=D), torch.tensor([80.0, math.pi / 2], dtype=D)
    )
    inside = torch.tensor([[0.0, 0.0], [79.0, 1.5]], dtype=D)
    outside = torch.tensor([[81.0, 0.0]], dtype=D)
    torch.testing.assert_close(
        box.log_prob(inside), torch.full((2,), -math.log(90 * math.pi), dtype=D)
    )
    assert box.log_prob(outside).item() == -math.inf
    s = box.sample((50000,), generator=torch.Generator().manual_seed(6))
    assert (s[:, 0] >= -10).all() and (s[:, 0] <= 80).all()
    torch.testing.assert_close(s.mean(0), box.mean, atol=0.5, rtol=0)
    torch.testing.assert_close(s.var(0), box.cov.diagonal(), rtol=0.03, atol=0)
    assert box.log_prob(outside, torch.tensor([False, True])).item() == pytest.approx(
        -math.log(math.pi)
    )


def test_sampling_is_reproducible():
    g = Gaussian(torch.zeros(2), torch.eye(2))
    a = g.sample((5,), generator=torch.Generator().manual_seed(9))
    b = g.sample((5,), generator=torch.Generator().manual_seed(9))
    assert torch.equal(a, b)


@pytest.mark.parametrize(
    "cov, loc",
    [
        (torch.diag(torch.tensor([0.5, 2.0, 1e-4, 3.0], dtype=D)), torch.zeros(4, dtype=D)),
        (torch.diag(torch.tensor([0.5, 2.0, 1e-4, 3.0], dtype=D)), torch.ones(4, dtype=D)),
        (torch.eye(4, dtype=D) + 0.5, torch.zeros(4, dtype=D)),
    ],
    ids=["diagonal-zero-mean-fused", "diagonal-with-mean", "full"],
)
def test_perturb_equals_value_plus_a_sample_with_the_same_draws(cov, loc):
    g = Gaussian(loc, cov)
    value = torch.randn(3, 64, 4, dtype=D, generator=torch.Generator().manual_seed(0))
    got = g.perturb(value, torch.Generator().manual_seed(1))
    want = value + g.sample((3, 64), torch.Generator().manual_seed(1))
    torch.testing.assert_close(got, want, rtol=0, atol=1e-14)


def test_noise_models_work_on_inference_mode_tensors():
    """Lightning's validate/test run under torch.inference_mode, whose tensors have no
    version counter: the cached factors must not ask for one."""
    from difffilter.noise import Gaussian, UniformBox

    with torch.inference_mode():
        g = Gaussian(torch.zeros(2), torch.eye(2))
        box = UniformBox(torch.zeros(2), torch.ones(2))
        x = g.sample((3,), torch.Generator().manual_seed(0))
        assert torch.isfinite(g.log_prob(x)).all()
        assert torch.allclose(box.log_prob(torch.full((2,), 0.5)), torch.tensor(0.0))


def test_a_diagonal_density_follows_its_covariance_changed_in_place():
    """The density's cached 1/σ² and normaliser follow the covariance's version counter."""
    f64 = torch.float64
    g = Gaussian(torch.zeros(3, dtype=f64), torch.diag(torch.tensor([1.0, 2.0, 3.0], dtype=f64)))
    x = torch.randn(5, 3, dtype=f64, generator=torch.Generator().manual_seed(0))
    before = g.log_prob(x)
    with torch.no_grad():
        g._cov.mul_(4.0)
    fresh = Gaussian(
        torch.zeros(3, dtype=f64), torch.diag(torch.tensor([4.0, 8.0, 12.0], dtype=f64))
    )
    torch.testing.assert_close(g.log_prob(x), fresh.log_prob(x), rtol=0, atol=1e-12)
    assert not torch.allclose(before, fresh.log_prob(x))


def test_a_density_first_evaluated_in_inference_mode_still_takes_gradients():
    g = Gaussian(torch.zeros(3), torch.diag(torch.tensor([1.0, 2.0, 3.0])))
    with torch.inference_mode():
        g.log_prob(torch.randn(4, 3))
    x = torch.randn(4, 3, requires_grad=True)
    g.log_prob(x).sum().backward()
    torch.testing.assert_close(x.grad, -x.detach() / torch.tensor([1.0, 2.0, 3.0]))


def test_a_factor_cached_under_inference_mode_does_not_break_autograd_later():
    """A full covariance's factor first made under ``torch.inference_mode()`` is an inference
    tensor, which autograd cannot save: once reused from the cache, it failed a later
    gradient through the density."""
    R = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=torch.float64)
    g = Gaussian(torch.zeros(2, dtype=torch.float64), R)
    v = torch.tensor([[0.3, -0.2]], dtype=torch.float64)
    with torch.inference_mode():
        g.log_prob(v)
    x = v.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(g.log_prob(x).sum(), x)
    torch.testing.assert_close(grad, -(torch.linalg.solve(R, v.T)).T)


def test_safe_cholesky_jitters_only_the_members_that_need_it():
    """One failing matrix of a batch once jittered every member (by the largest ε any
    needed): the others keep their own factors."""
    from difffilter.linalg import safe_cholesky

    good = torch.tensor([[1.0, 0.0], [0.0, 1e-3]])
    bad = torch.tensor([[1.0, 0.0], [0.0, -1e-3]])  # needs ε·mean(diag) > 1e-3: ε = 1e-2
    L = safe_cholesky(torch.stack([good, bad]))
    assert torch.equal(L[0], torch.linalg.cholesky(good))
    assert torch.isfinite(L[1]).all() and (L[1] @ L[1].T)[1, 1] > 0
    with pytest.raises(ValueError, match="factor must be symmetric positive definite"):
        safe_cholesky(torch.stack([good, -torch.eye(2)]), name="factor")


def test_safe_cholesky_error_names_the_failing_member_and_its_eigenvalues():
    """Which member of a batch fails, its eigenvalues, and in float32 (not float64) that
    round-off may be the cause; a NaN member is named as such."""
    from difffilter.linalg import safe_cholesky

    for dtype in (torch.float64, torch.float32):
        batch = torch.stack([torch.eye(2), torch.tensor([[1.0, 2.0], [2.0, 1.0]])]).to(dtype)
        with pytest.raises(ValueError) as err:
            safe_cholesky(batch.expand(3, 2, 2, 2), name="S")
        assert "at batch index (0, 1) (eigenvalues from -1 to 3)" in str(err.value)
        assert ("float64 may hold it" in str(err.value)) == (dtype == torch.float32)
    nan = torch.tensor([[1.0, float("nan")], [float("nan"), 1.0]], dtype=torch.float64)
    with pytest.raises(
        ValueError, match=r"jitter: it holds NaN or inf \(a covariance that overflowed"
    ):
        safe_cholesky(nan, name="S")


def test_rowwise_takes_a_scalar_operand_as_broadcasting_does():
    from difffilter.linalg import rowwise

    a = torch.randn(4096, 2, generator=torch.Generator().manual_seed(0))
    assert torch.equal(rowwise(torch.mul, a, torch.tensor(2.0)), a * 2.0)


def test_safe_cholesky_jitters_from_round_off_up():
    """From a numerics trial: the ladder began at 1e-10 of the mean variance in float64,
    2e6 times the smallest variance of a mixed-scale state covariance (a UKF 4.25 nats off,
    its gradient 5 % off). A matrix that fails by round-off alone (rank 3 of 4) now gets a
    jitter of round-off's size: L Lᵀ within 2e-14 of it, relative to its mean variance."""
    from difffilter.linalg import safe_cholesky

    B = torch.randn(4, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    A = B @ B.T
    assert int(torch.linalg.cholesky_ex(A).info) != 0  # (the plain factorisation fails)
    L = safe_cholesky(A)
    gap = float((L @ L.T - A).abs().max() / A.diagonal().mean())
    assert 0 < gap < 2e-14
    f32 = safe_cholesky(A.float())  # float32: the ladder as before, from 1e-6
    assert float((f32 @ f32.T - A.float()).abs().max() / A.diagonal().mean()) < 2e-6


def test_gaussian_refuses_a_loc_and_cov_whose_batches_do_not_broadcast():
    """loc [2, d] beside cov [4, d, d] (or scale_tril) is refused by name, as
    torch.distributions.MultivariateNormal refuses it; batches that broadcast ([1, d] or
    [4, d] beside [4, d, d]) build, with the densities of MultivariateNormal."""
    cov = (
        torch.eye(3, dtype=D).expand(4, 3, 3)
        * torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=D)[:, None, None]
    )
    with pytest.raises(ValueError, match=r"loc and cov .*loc \(2,\), cov \(4,\)"):
        Gaussian(torch.zeros(2, 3, dtype=D), cov)
    with pytest.raises(ValueError, match=r"loc and scale_tril .*loc \(2,\), scale_tril \(4,\)"):
        Gaussian(torch.ones(2, 3, dtype=D), scale_tril=cov.sqrt())
    with pytest.raises((ValueError, RuntimeError)):  # torch's own rule, which it follows
        torch.distributions.MultivariateNormal(torch.zeros(2, 3, dtype=D), cov)
    x = torch.randn(5, 4, 3, dtype=D, generator=torch.Generator().manual_seed(0))
    for loc in (torch.tensor([[1.0, -1.0, 0.5]], dtype=D), torch.randn(4, 3, dtype=D)):
        ref = torch.distributions.MultivariateNormal(loc, cov)
        torch.testing.assert_close(Gaussian(loc, cov).log_prob(x), ref.log_prob(x))


@pytest.mark.parametrize("mask", [torch.tensor([2, 0]), torch.tensor([1, 0]),
                                  torch.tensor([0.5, 0.0]), torch.tensor([True])])  # fmt: skip
def test_uniform_box_refuses_a_mask_that_is_not_bool_of_its_dimension(mask):
    """A mask is bool [..., d], as Gaussian's and the mixture's masked densities require:
    an integer 2 had counted an entry's log-length twice and, through `outside & 2 == 0`,
    given a value outside the box a finite density."""
    box = UniformBox(torch.zeros(2, dtype=D), torch.tensor([2.0, 3.0], dtype=D))
    with pytest.raises(ValueError, match=r"mask must be bool \[\.\.\., 2\]"):
        box.log_prob(torch.tensor([5.0, 1.0], dtype=D), mask)


def test_uniform_box_bool_mask_is_the_marginal_box():
    """With a bool mask the density is the marginal box's: −log 2 on entry 0 of [0, 2]×[0, 3]
    inside, −inf outside it on that entry, and an entry outside the box but unreceived
    does not count."""
    box = UniformBox(torch.zeros(2, dtype=D), torch.tensor([2.0, 3.0], dtype=D))
    first = torch.tensor([True, False])
    v = torch.tensor([[1.0, 1.0], [5.0, 1.0], [1.0, 7.0]], dtype=D)
    out = box.log_prob(v, first)
    torch.testing.assert_close(
        out, torch.tensor([-math.log(2.0), -math.inf, -math.log(2.0)], dtype=D)
    )


def test_has_batch_of_the_noise_models():
    """has_batch: a box with bounds [B, d] has one per run, one of [d] none; a mixture none;
    a noise of one's own reads it from its mean's batch."""
    assert UniformBox(-torch.ones(3, 2, dtype=D), torch.ones(3, 2, dtype=D)).has_batch()
    assert not UniformBox(-torch.ones(2, dtype=D), torch.ones(2, dtype=D)).has_batch()
    mix = GaussianMixture(torch.tensor([0.5, 0.5], dtype=D), torch.zeros(2, 1, dtype=D),
                          torch.ones(2, 1, 1, dtype=D))  # fmt: skip
    assert not mix.has_batch()
    assert Gaussian(torch.zeros(3, 2, dtype=D), torch.eye(2, dtype=D)).has_batch()
