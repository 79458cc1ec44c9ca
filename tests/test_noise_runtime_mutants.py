"""Mutation review of difffilter/noise.py, difffilter/_assignments.py and difffilter/runtime.py:
checks that the existing suite let through.

Each test compares the library against an independent truth: scipy.stats densities, a
literal numpy float64 evaluation of a docstring's equation (the mixture's moments
``Σ π_c μ_c`` and ``Σ π_c (Σ_c + μ_c μ_cᵀ) − mean meanᵀ``, the box's ``−Σ log(high − low)``),
the closed-form gradient of a Gaussian log density, Monte Carlo moments of ``sample`` with a
stated tolerance, the documented generator contract, glibc's ``<malloc.h>`` parameter
numbers, or the documented counting rule of :mod:`difffilter._assignments`. The mutant(s)
each test kills are named in its docstring (ids of the review's table).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from difffilter import runtime
from difffilter._assignments import CountsAssignments, assignments
from difffilter.noise import Gaussian, GaussianMixture, UniformBox

D = torch.float64


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _spd(d: int, seed: int) -> np.ndarray:
    a = np.random.default_rng(seed).standard_normal((d, d))
    return a @ a.T + d * np.eye(d)


# ------------------------------------------------------------------------------ Gaussian


def test_gaussian_log_prob_matches_scipy_for_batched_diagonal_covariances():
    """A per-run diagonal covariance ``[B, d, d]`` with its loc: ``log_prob`` of values
    ``[N, B, d]`` against scipy's logpdf run by run (N06: a batched diagonal factor taken for
    the shared-diagonal fast path)."""
    variances = np.array([[0.5, 2.0, 1.5], [3.0, 0.2, 1.0]])
    loc = np.array([[1.0, -1.0, 0.5], [0.0, 2.0, -0.5]])
    g = Gaussian(torch.tensor(loc), torch.diag_embed(torch.tensor(variances)))
    x = torch.randn(5, 2, 3, dtype=D, generator=_gen(0))
    got = g.log_prob(x).numpy()
    assert got.shape == (5, 2)
    for b in range(2):
        want = stats.multivariate_normal(loc[b], np.diag(variances[b])).logpdf(x[:, b].numpy())
        np.testing.assert_allclose(got[:, b], want, rtol=1e-12)


def test_a_scale_tril_is_the_lower_factor_and_entries_above_its_diagonal_are_refused():
    """``scale_tril`` is the lower factor: ``cov``, ``log_prob`` and ``sample`` take ``L Lᵀ``
    (numpy, scipy; 40,000 draws: covariance entries within 0.06, their sd about 0.01).
    Entries above its diagonal had been dropped without a word (an upper factor, scipy's
    default, gave another covariance: an ssm trial): refused when built, and when written
    since, at the next use."""
    full = np.array([[1.2, 0.7, -0.4], [0.3, 0.9, 0.5], [-0.2, 0.4, 1.1]])
    lower = np.tril(full)
    cov = lower @ lower.T
    loc = np.array([0.5, -1.0, 2.0])
    with pytest.raises(ValueError, match="scale_tril must be lower triangular"):
        Gaussian(torch.tensor(loc), scale_tril=torch.tensor(full))
    g = Gaussian(torch.tensor(loc), scale_tril=torch.tensor(lower))
    np.testing.assert_allclose(g.cov.numpy(), cov, rtol=1e-14)
    x = torch.randn(6, 3, dtype=D, generator=_gen(1))
    want = stats.multivariate_normal(loc, cov).logpdf(x.numpy())
    np.testing.assert_allclose(g.log_prob(x).numpy(), want, rtol=1e-12)
    s = g.sample((40000,), generator=_gen(20)).numpy()
    np.testing.assert_allclose(np.cov(s.T), cov, atol=0.06)
    np.testing.assert_allclose(s.mean(0), loc, atol=0.04)
    with torch.no_grad():
        g._scale_tril.copy_(torch.tensor(full))
    for use in (lambda: g.cov, lambda: g.log_prob(x), lambda: g.sample((2,))):
        with pytest.raises(ValueError, match="scale_tril must be lower triangular"):
            use()


def test_a_gaussian_mean_takes_the_batch_of_its_covariance():
    """``mean → [*batch, d]``: one loc ``[d]`` with covariances ``[3, d, d]`` has a mean
    ``[3, d]``, each row the loc, and batch shape ``(3,)`` (N11: the loc returned as given)."""
    loc = torch.tensor([1.0, -2.0], dtype=D)
    scales = torch.tensor([1.0, 2.0, 3.0], dtype=D).view(3, 1, 1)
    g = Gaussian(loc, torch.eye(2, dtype=D) * scales)
    assert g.mean.shape == (3, 2) and g.batch_shape == (3,)
    np.testing.assert_array_equal(g.mean.numpy(), np.tile([1.0, -2.0], (3, 1)))


def test_a_scalar_loc_fills_every_entry():
    """``loc`` as a scalar with ``cov``: every entry takes it (``0`` means zeros; ``1.5``
    means ``1.5·1``), so the density is scipy's at that mean (N03: the scalar's value lost)."""
    cov = _spd(2, 2)
    g = Gaussian(1.5, torch.tensor(cov))
    np.testing.assert_array_equal(g.mean.numpy(), [1.5, 1.5])
    x = torch.randn(4, 2, dtype=D, generator=_gen(2))
    want = stats.multivariate_normal([1.5, 1.5], cov).logpdf(x.numpy())
    np.testing.assert_allclose(g.log_prob(x).numpy(), want, rtol=1e-12)


def test_a_gaussian_needs_exactly_one_covariance_and_a_positive_factor_diagonal():
    """The constructor's contract: ``cov=`` and ``scale_tril=`` together are refused, and a
    ``scale_tril`` with a zero on its diagonal (a singular ``cov``) too (N02, N01)."""
    with pytest.raises(ValueError, match="exactly one of cov= or scale_tril="):
        Gaussian(torch.zeros(2), torch.eye(2), scale_tril=torch.eye(2))
    with pytest.raises(ValueError, match="positive diagonal"):
        Gaussian(torch.zeros(2), scale_tril=torch.tensor([[1.0, 0.0], [0.3, 0.0]]))


def test_diagonal_sampling_moments_with_a_mean():
    """``sample = μ + L ε`` for a diagonal covariance with a non-zero loc: 40,000 draws have
    the loc's mean (sd of the mean ≤ 2/200 = 0.01, tolerance 0.05) and the covariance's
    variances (relative sd √(2/40000) = 0.7 %, tolerance 4 %) (N14: σ² as the factor; N15:
    the loc subtracted)."""
    loc = torch.tensor([1.0, -2.0, 3.0], dtype=D)
    var = torch.tensor([0.25, 4.0, 1.0], dtype=D)
    s = Gaussian(loc, torch.diag(var)).sample((40000,), generator=_gen(3))
    torch.testing.assert_close(s.mean(0), loc, atol=0.05, rtol=0)
    torch.testing.assert_close(s.var(0), var, rtol=0.04, atol=0)


@pytest.mark.parametrize("diagonal", [True, False], ids=["diagonal", "full"])
def test_a_per_run_loc_gets_independent_draws_per_run(diagonal):
    """A loc ``[B, d]`` with one shared covariance: ``sample((n,))`` is ``[n, B, d]``, each run
    at its own mean, the runs' draws independent (sample correlation of runs 0 and 1 below
    0.05, its sd 1/√20000 = 0.007) and of the covariance's variance (N13: the batch taken from
    the factor alone, one ε shared by all runs or a shape error)."""
    loc = torch.tensor([[1.0, 0.0], [-1.0, 2.0], [0.0, 5.0]], dtype=D)
    cov = torch.diag(torch.tensor([0.5, 2.0], dtype=D)) if diagonal else torch.tensor(_spd(2, 4))
    s = Gaussian(loc, cov).sample((20000,), generator=_gen(4))
    assert s.shape == (20000, 3, 2)
    torch.testing.assert_close(s.mean(0), loc, atol=0.06, rtol=0)
    r = (s - loc).numpy()
    assert abs(np.corrcoef(r[:, 0, 0], r[:, 1, 0])[0, 1]) < 0.05
    np.testing.assert_allclose(np.cov(r[:, 2].T), cov.numpy(), rtol=0.05, atol=0.05)


def test_a_loc_edited_in_place_is_followed():
    """A zero loc, once used, then set to ones in place under ``no_grad``: the density and
    the draws follow it (scipy; the draws' mean within 0.05) (N08: the zero-loc cache keyed
    without the version counter)."""
    cov = _spd(2, 5)
    g = Gaussian(torch.zeros(2, dtype=D), torch.tensor(cov))
    x = torch.randn(4, 2, dtype=D, generator=_gen(5))
    g.log_prob(x)
    with torch.no_grad():
        g.loc.add_(1.0)
    want = stats.multivariate_normal([1.0, 1.0], cov).logpdf(x.numpy())
    np.testing.assert_allclose(g.log_prob(x).numpy(), want, rtol=1e-12)
    assert np.abs(g.sample((20000,), generator=_gen(6)).mean(0).numpy() - 1.0).max() < 0.05


def test_a_non_zero_loc_made_in_inference_mode_is_used():
    """Under ``torch.inference_mode`` (Lightning's validation) a loc ``[1, 2]`` is no zero
    loc: the density is scipy's at that mean (N07: the inference-mode zero test inverted)."""
    cov = np.diag([0.5, 2.0])
    x = np.array([[0.3, 1.0], [1.2, 2.5]])
    with torch.inference_mode():
        g = Gaussian(torch.tensor([1.0, 2.0], dtype=D), torch.tensor(cov))
        got = g.log_prob(torch.tensor(x)).numpy()
    np.testing.assert_allclose(got, stats.multivariate_normal([1.0, 2.0], cov).logpdf(x))


def test_a_diagonal_density_first_weighed_in_inference_mode_after_a_draw_takes_gradients():
    """A diagonal Gaussian's factor made by a draw, its first density evaluated under
    ``torch.inference_mode`` (Lightning's validation), then a density with gradients: the
    gradient in the value is ``−Σ⁻¹ x`` (closed form) (N25: the inference-mode ``1/σ²`` kept
    with the factor, which autograd cannot save)."""
    var = torch.tensor([1.0, 2.0, 4.0], dtype=D)
    g = Gaussian(torch.zeros(3, dtype=D), torch.diag(var))
    g.sample((2,), generator=_gen(19))
    with torch.inference_mode():
        g.log_prob(torch.ones(1, 3, dtype=D))
    x = torch.tensor([[0.5, -1.0, 2.0]], dtype=D, requires_grad=True)
    (grad,) = torch.autograd.grad(g.log_prob(x).sum(), x)
    np.testing.assert_allclose(grad.numpy(), [[-0.5, 0.5, -0.5]], rtol=1e-15)


def _log_prob_grads(x, mu, cov):
    """Closed-form gradients of ``log N(x; μ, Σ)`` summed over rows (numpy float64):
    ``∂/∂μ = Σ⁻¹ Σ_n r_n`` and ``∂/∂Σ = ½ Σ_n (Σ⁻¹ r_n r_nᵀ Σ⁻¹ − Σ⁻¹)``."""
    inv = np.linalg.inv(cov)
    r = x - mu
    g_mu = inv @ r.sum(0)
    g_cov = 0.5 * sum(inv @ np.outer(v, v) @ inv - inv for v in r)
    return g_mu, g_cov


@pytest.mark.parametrize("diagonal", [True, False], ids=["diagonal", "full"])
def test_gradients_through_log_prob_match_the_closed_form_on_every_call(diagonal):
    """A learnable loc (zero at first) and covariance: the gradients of ``Σ log_prob`` match
    the closed form (``Σ⁻¹ r`` and ``½(Σ⁻¹ r rᵀ Σ⁻¹ − Σ⁻¹)``, symmetric in Σ) on two
    successive evaluations of the same module (N52: a zero loc requiring gradients taken as a
    constant, no gradient; N53: the factor of a covariance requiring gradients cached, the
    second backward through a freed graph)."""
    cov0 = np.diag([0.5, 2.0]) if diagonal else _spd(2, 7)
    loc = torch.nn.Parameter(torch.zeros(2, dtype=D))
    cov = torch.nn.Parameter(torch.tensor(cov0))
    g = Gaussian(loc, cov)
    x = torch.randn(5, 2, dtype=D, generator=_gen(7))
    g_mu, g_cov = _log_prob_grads(x.numpy(), np.zeros(2), cov0)
    for _ in range(2):
        loc.grad = cov.grad = None
        g.log_prob(x).sum().backward()
        assert loc.grad is not None
        np.testing.assert_allclose(loc.grad.numpy(), g_mu, rtol=1e-10)
        sym = 0.5 * (cov.grad + cov.grad.T).numpy()  # only the symmetric part is defined
        np.testing.assert_allclose(sym, g_cov, rtol=1e-10, atol=1e-12)


def test_gradcheck_through_log_prob_in_the_covariance_and_its_factor():
    """``torch.autograd.gradcheck`` (float64 finite differences) of ``log_prob`` through a
    covariance ``A Aᵀ + I`` and through a ``scale_tril`` (the module docstring: a covariance
    with autograd history keeps it)."""
    x = torch.randn(3, 2, dtype=D, generator=_gen(8))
    a = torch.tensor([[0.8, 0.2], [-0.3, 0.6]], dtype=D, requires_grad=True)

    def via_cov(a):
        return Gaussian(torch.zeros(2, dtype=D), a @ a.T + torch.eye(2, dtype=D)).log_prob(x)

    def via_tril(a):
        return Gaussian(
            torch.ones(2, dtype=D), scale_tril=a.tril() + torch.eye(2, dtype=D)
        ).log_prob(x)

    assert torch.autograd.gradcheck(via_cov, (a,))
    assert torch.autograd.gradcheck(via_tril, (a,))


def test_draw_like_and_perturb_with_a_loc_and_covariance_per_run():
    """``draw_like([n, B, d])`` with a loc and covariance per run: run ``b``'s draws have
    mean ``μ_b`` (tolerance 0.06) and covariance ``Σ_b`` (tolerance 6 %); ``perturb`` of a
    per-run loc alone adds such draws; a shape that does not fit the batch is a ValueError
    (N20: the loc subtracted; N18: a per-run loc not seen as a batch; N19: the shape check)."""
    loc = torch.tensor([[1.0, -1.0], [3.0, 0.5]], dtype=D)
    covs = np.stack([_spd(2, 9), 0.5 * _spd(2, 10)])
    g = Gaussian(loc, torch.tensor(covs))
    s = g.draw_like((20000, 2, 2), generator=_gen(9))
    torch.testing.assert_close(s.mean(0), loc, atol=0.06, rtol=0)
    for b in range(2):
        np.testing.assert_allclose(np.cov(s[:, b].numpy().T), covs[b], rtol=0.06, atol=0.06)
    with pytest.raises(ValueError, match="does not fit draws of shape"):
        g.draw_like((10, 3, 2))
    shared = Gaussian(loc, torch.tensor(covs[0]))
    value = torch.zeros(20000, 2, 2, dtype=D)
    p = shared.perturb(value, _gen(10))
    assert p.shape == value.shape
    torch.testing.assert_close(p.mean(0), loc, atol=0.06, rtol=0)


# ---------------------------------------------------------------------- Gaussian mixture


def _mixture():
    weights = np.array([0.5, 0.3, 0.2])
    locs = np.array([[1.0, -2.0], [-3.0, 0.5], [0.0, 4.0]])
    covs = np.stack([_spd(2, 11), 0.3 * _spd(2, 12), np.diag([0.2, 1.5])])
    mix = GaussianMixture(torch.tensor(weights), torch.tensor(locs), torch.tensor(covs))
    return mix, weights, locs, covs


def test_mixture_moments_are_the_exact_ones_by_hand():
    """``mean = Σ π_c μ_c`` and ``cov = Σ π_c (Σ_c + μ_c μ_cᵀ) − mean meanᵀ`` written out in
    numpy, with components of non-zero means (N27: a mean over components; N28: the
    ``μ_c μ_cᵀ`` term dropped; N29: ``mean meanᵀ`` not subtracted)."""
    mix, w, locs, covs = _mixture()
    mean = sum(w[c] * locs[c] for c in range(3))
    second = sum(w[c] * (covs[c] + np.outer(locs[c], locs[c])) for c in range(3))
    np.testing.assert_allclose(mix.mean.numpy(), mean, rtol=1e-14)
    np.testing.assert_allclose(mix.cov.numpy(), second - np.outer(mean, mean), rtol=1e-13)


def test_mixture_log_prob_with_means_against_scipy_and_per_sample_masks():
    """``log_prob = log Σ_c π_c N(v; μ_c, Σ_c)`` with scipy's component densities; with a
    mask per sample ``[N, d]`` each sample's density is the mixture of its received entries'
    marginals (N34: the residual ``v + μ_c``; N35: a per-sample mask broadcast against the
    components instead of the samples)."""
    mix, w, locs, covs = _mixture()
    x = np.random.default_rng(13).normal(size=(4, 2)) * 2
    want = np.log(sum(w[c] * stats.multivariate_normal(locs[c], covs[c]).pdf(x) for c in range(3)))
    np.testing.assert_allclose(mix.log_prob(torch.tensor(x)).numpy(), want, rtol=1e-12)
    mask = np.array([[True, False], [False, True], [True, True], [True, False]])
    got = mix.log_prob(torch.tensor(x), torch.tensor(mask)).numpy()
    for n in range(4):
        k = np.flatnonzero(mask[n])
        dens = sum(
            w[c] * stats.multivariate_normal(locs[c][k], covs[c][np.ix_(k, k)]).pdf(x[n, k])
            for c in range(3)
        )
        assert got[n] == pytest.approx(math.log(dens), rel=1e-12)


def test_mixture_samples_have_the_exact_moments():
    """60,000 draws of the mixture: sample mean within 0.06 of ``Σ π_c μ_c`` (its sd ≤
    √(13/60000) = 0.015) and sample covariance within 0.2 of the exact one (entries up to 8)
    (N33: the components' means left out of the draws)."""
    mix, w, locs, covs = _mixture()
    mean = sum(w[c] * locs[c] for c in range(3))
    second = sum(w[c] * (covs[c] + np.outer(locs[c], locs[c])) for c in range(3))
    s = mix.sample((60000,), generator=_gen(14)).numpy()
    np.testing.assert_allclose(s.mean(0), mean, atol=0.06)
    np.testing.assert_allclose(np.cov(s.T), second - np.outer(mean, mean), atol=0.2)


def test_a_mixture_component_of_weight_zero_is_legal():
    """Weights are "non-negative, summing to one": ``[1, 0]`` is accepted, and the density is
    the first component's (scipy) (N26: zero weights refused)."""
    cov = _spd(2, 15)
    weights = torch.tensor([1.0, 0.0], dtype=D)
    locs = torch.tensor([[1.0, 2.0], [0.0, 0.0]], dtype=D)
    mix = GaussianMixture(weights, locs, torch.tensor(np.stack([cov, np.eye(2)])))
    x = np.array([[0.0, 1.0], [2.0, 2.5]])
    want = stats.multivariate_normal([1.0, 2.0], cov).logpdf(x)
    np.testing.assert_allclose(mix.log_prob(torch.tensor(x)).numpy(), want, rtol=1e-12)


# ---------------------------------------------------------------------------- uniform box


def test_box_density_on_its_closed_faces_outside_and_at_nan():
    """``[low, high]`` is closed: points on either face have ``−Σ log(high − low)`` (numpy);
    NaN is outside (``−inf``); a value of the wrong width is refused (N41: ``< high``; N42:
    NaN taken as inside; N47: the width check)."""
    low, high = np.array([-1.0, 2.0]), np.array([3.0, 2.5])
    box = UniformBox(torch.tensor(low), torch.tensor(high))
    inside = -np.log(high - low).sum()
    faces = torch.tensor([[-1.0, 2.0], [3.0, 2.5], [3.0, 2.0]], dtype=D)
    np.testing.assert_allclose(box.log_prob(faces).numpy(), [inside] * 3, rtol=1e-15)
    assert box.log_prob(torch.tensor([[float("nan"), 2.2]], dtype=D)).item() == -math.inf
    with pytest.raises(ValueError, match="the box's dimension"):
        box.log_prob(torch.zeros(3, 1, dtype=D))


def test_a_batched_box_samples_per_run_and_its_log_volume():
    """Boxes ``[B, d]``: ``sample((n,))`` is ``[n, B, d]`` with scipy.stats.uniform's mean and
    variance per run (40,000 draws: tolerance 2 % of each side), ``log_volume`` ``[B]`` is
    ``Σ log(high − low)`` per run (N50: the batch dropped from the draws; N49: the log volume
    summed over runs)."""
    low = np.array([[0.0, -1.0], [10.0, 5.0]])
    high = np.array([[1.0, 3.0], [14.0, 5.5]])
    box = UniformBox(torch.tensor(low), torch.tensor(high))
    np.testing.assert_allclose(box.log_volume.numpy(), np.log(high - low).sum(-1), rtol=1e-15)
    s = box.sample((40000,), generator=_gen(16)).numpy()
    assert s.shape == (40000, 2, 2)
    ref = stats.uniform(loc=low, scale=high - low)
    np.testing.assert_allclose(s.mean(0), ref.mean(), atol=0.02 * (high - low).max())
    np.testing.assert_allclose(s.var(0), ref.var(), rtol=0.04)
    assert (s >= low).all() and (s <= high).all()


def test_a_learnable_box_gives_its_gradient_on_every_call_and_follows_in_place_edits():
    """``∂/∂high (−Σ log(high − low)) = −1/(high − low)`` for a ``high`` Parameter, on two
    successive evaluations (N45: log lengths of a learnable ``high`` cached, the second
    backward through a freed graph); a plain ``high`` edited in place is followed
    (N46: the cache keyed without ``high``'s version)."""
    low = torch.tensor([0.0, -1.0], dtype=D)
    high = torch.nn.Parameter(torch.tensor([2.0, 3.0], dtype=D))
    box = UniformBox(low, high)
    v = torch.tensor([[1.0, 0.0]], dtype=D)
    for _ in range(2):
        high.grad = None
        box.log_prob(v).sum().backward()
        np.testing.assert_allclose(high.grad.numpy(), [-1 / 2.0, -1 / 4.0], rtol=1e-15)
    plain = UniformBox(low.clone(), torch.tensor([2.0, 3.0], dtype=D))
    plain.log_prob(v)
    with torch.no_grad():
        plain.high.mul_(2.0)
    assert plain.log_prob(v).item() == pytest.approx(-math.log(4.0 * 7.0), rel=1e-15)


# ------------------------------------------------------------- generators and parameters


@pytest.mark.parametrize("kind", ["gaussian", "mixture", "box"])
def test_a_given_generator_alone_is_drawn_from(kind):
    """The module docstring: every draw comes from the given generator. The same seed gives
    the same draws, and the global generator's state is untouched (N31, N32: the mixture's
    component index or ε from the global generator; N40: the box's)."""
    noise = {
        "gaussian": Gaussian(torch.zeros(2, dtype=D), torch.tensor(_spd(2, 17))),
        "mixture": _mixture()[0],
        "box": UniformBox(torch.zeros(2, dtype=D), torch.ones(2, dtype=D)),
    }[kind]
    state = torch.get_rng_state()
    a = noise.sample((7, 3), generator=_gen(18))
    after = torch.get_rng_state()
    b = noise.sample((7, 3), generator=_gen(18))
    torch.set_rng_state(state)
    assert torch.equal(after, state)
    assert torch.equal(a, b) and a.shape == (7, 3, 2)


def test_parameters_are_registered_as_parameters_and_tensors_as_buffers():
    """The module docstring: ``nn.Parameter`` arguments are parameters, plain tensors buffers
    (N48: every tensor registered as a buffer; an optimiser of ``parameters()`` trains none)."""
    cov = torch.nn.Parameter(torch.eye(2, dtype=D))
    g = Gaussian(torch.zeros(2, dtype=D), cov)
    assert dict(g.named_parameters()) == {"_cov": cov}
    assert set(dict(g.named_buffers())) == {"loc"}
    high = torch.nn.Parameter(torch.ones(2, dtype=D))
    box = UniformBox(torch.zeros(2, dtype=D), high)
    assert list(box.parameters()) == [high] and set(dict(box.named_buffers())) == {"low"}

    # a 0-d parameter as loc became a [d] buffer copied once: SGD moved the parameter
    # (0.5 → 3.5 → 6.5) and the model's mean stayed 0.5 (the review's bug); refused, while a
    # 0-d tensor with autograd history (the output of a computation) is still taken
    with pytest.raises(ValueError, match=r"loc: a 0-d nn.Parameter .*torch.full\(\(2,\)"):
        Gaussian(torch.nn.Parameter(torch.tensor(0.5, dtype=D)), torch.eye(2, dtype=D))
    w = torch.tensor(0.5, dtype=D, requires_grad=True)
    Gaussian(w * 2.0, torch.eye(2, dtype=D)).mean.sum().backward()
    assert float(w.grad) == 4.0  # d(2w + 2w)/dw


# -------------------------------------------------------------------------- assignments


class _Holder(CountsAssignments):
    def __init__(self):
        super().__init__()
        self.register_buffer("buf", torch.zeros(2))
        self.weight = torch.nn.Parameter(torch.ones(2))
        self.sub = torch.nn.Linear(1, 1)
        self.plain = torch.zeros(1)  # a tensor attribute that is neither (in __dict__)


def test_the_assignment_count_follows_its_documented_rule():
    """The module docstring of ``_assignments``: replacing a tensor or module the model holds
    (buffer, parameter, submodule or plain attribute), a deletion and every ``_apply`` add
    one; a first assignment and a non-tensor value add none (A01: modules not counted; A02:
    deletions; A03: ``_apply``; A04, A06: submodules or parameters not looked up; A05: plain
    attributes; A07: the lookup after the assignment, counting first assignments)."""
    start = assignments()
    h = _Holder()
    assert assignments() == start  # building counts nothing
    h.extra = torch.zeros(1)  # a first assignment
    h.note = "text"
    assert assignments() == start
    steps = [
        lambda: setattr(h, "buf", torch.ones(2)),
        lambda: setattr(h, "weight", torch.nn.Parameter(torch.zeros(2))),
        lambda: setattr(h, "sub", torch.nn.Linear(1, 1)),
        lambda: setattr(h, "plain", torch.ones(1)),
        lambda: delattr(h, "extra"),
        lambda: h.double(),
    ]
    for i, step in enumerate(steps, 1):
        step()
        assert assignments() == start + i, i


# ------------------------------------------------------------------------------ runtime


class _FakeLibc:
    def __init__(self, answer: int):
        self.calls, self.answer = [], answer

        def mallopt(param, value):
            self.calls.append((param, value))
            return self.answer

        self.mallopt = mallopt


@pytest.mark.parametrize("answer", [1, 0])
def test_tune_cpu_allocator_sets_glibcs_three_parameters(monkeypatch, answer):
    """With a recording stand-in for libc: ``mallopt`` is called with glibc's ``<malloc.h>``
    numbers (``M_TRIM_THRESHOLD = −1``, ``M_TOP_PAD = −2``, ``M_MMAP_THRESHOLD = −3``), the mmap
    and trim thresholds at ``mmap_threshold`` and the top pad at ``top_pad``; the result is
    whether every call succeeded (glibc returns 1) (R01, R02, R09: numbers or values wrong;
    R03: failure reported as success; R08: Linux taken for another platform)."""
    fake = _FakeLibc(answer)
    monkeypatch.setattr(runtime.sys, "platform", "linux")
    monkeypatch.setattr(runtime.ctypes.util, "find_library", lambda name: "libc.so.6")
    monkeypatch.setattr(runtime.ctypes, "CDLL", lambda name: fake)
    assert runtime.tune_cpu_allocator(1000, 77) is bool(answer)
    assert sorted(fake.calls) == [(-3, 1000), (-2, 77), (-1, 1000)]
    monkeypatch.setattr(runtime.sys, "platform", "darwin")
    fake.calls.clear()
    assert runtime.tune_cpu_allocator() is False and fake.calls == []


def test_command_threads_default_and_a_zero_and_one_thread_after_an_exception(monkeypatch):
    """``command_threads(default)`` uses ``default`` without ``DIFFFILTER_THREADS``, refuses
    ``0`` (not a positive integer) with the variable's name, and ``one_thread`` restores the
    thread count when its block raises (R05: the default ignored; R04: zero accepted; R06:
    the count restored on a normal exit only)."""
    before = torch.get_num_threads()
    try:
        monkeypatch.delenv("DIFFFILTER_THREADS", raising=False)
        assert runtime.command_threads(default=2) == 2 and torch.get_num_threads() == 2
        monkeypatch.setenv("DIFFFILTER_THREADS", "0")
        with pytest.raises(ValueError, match="DIFFFILTER_THREADS must be a positive integer"):
            runtime.command_threads()
        torch.set_num_threads(2)
        with pytest.raises(RuntimeError, match="inside"), runtime.one_thread():
            assert torch.get_num_threads() == 1
            raise RuntimeError("inside")
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"mmap_threshold": 2**32}, r"mmap_threshold must be an integer <= 2\*\*31 - 1"),
        ({"top_pad": -1}, "top_pad must be an integer >= 0"),
        ({"mmap_threshold": 1.5e9}, "mmap_threshold must be an integer >= 0"),
    ],
)
def test_the_allocator_tuning_refuses_what_a_c_int_cannot_hold(kwargs, match):
    """mallopt takes a C int: 2**32 had wrapped to 0 (every block mmapped) and returned True."""
    with pytest.raises(ValueError, match=match):
        runtime.tune_cpu_allocator(**kwargs)
