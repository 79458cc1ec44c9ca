"""Findings of a trial of the resamplers: what they refuse, and where."""

from __future__ import annotations

import warnings

import pytest
import torch

import difffilter as df
from difffilter.resampling import (
    Multinomial,
    Resampler,
    Residual,
    Soft,
    StopGradient,
    Stratified,
    Systematic,
)  # fmt: skip


class _Misspelt(Resampler):
    def draw(self, log_w, generator):  # the hook is `_draw`
        return torch.arange(log_w.shape[-1]).expand(log_w.shape)


class _CallOnly(Resampler):
    def __call__(self, particles, log_weights, generator=None):
        return Systematic()(particles, log_weights, generator)


@pytest.mark.parametrize("wrapper", [Soft, StopGradient])
@pytest.mark.parametrize("base", [_Misspelt, _CallOnly])
def test_a_wrappers_base_that_cannot_draw_is_refused_when_it_is_made(wrapper, base):
    """Soft and StopGradient draw with their base's ``_draw``: a base without one had been
    accepted, and the filter failed at its first resampling (NotImplementedError naming
    neither the wrapper nor ``base``), or never where the ESS stayed high."""
    with pytest.raises(
        ValueError, match=rf"base must draw ancestors: {base.__name__} defines no _draw"
    ):
        wrapper(base=base())


def test_a_wrapper_of_a_base_of_ones_own_that_draws_still_runs():
    """The check reads the hook, not the class: a user's ``_draw`` is a base."""

    class Mine(Resampler):
        def _draw(self, log_w, generator):
            return Systematic()._draw(log_w, generator)

    model = df.LinearGaussianModel(
        torch.eye(1, dtype=torch.float64), torch.eye(1, dtype=torch.float64),
        torch.eye(1, dtype=torch.float64), 0.01 * torch.eye(1, dtype=torch.float64),
        torch.zeros(1, dtype=torch.float64), torch.eye(1, dtype=torch.float64),
    )  # fmt: skip
    _, ys, _ = model.simulate(5, (2,), generator=torch.Generator().manual_seed(0))
    ref = df.particle_filter(model, ys, num_particles=10, resampler=StopGradient(Systematic()),
                             generator=torch.Generator().manual_seed(0))  # fmt: skip
    mine = df.particle_filter(model, ys, num_particles=10, resampler=StopGradient(Mine()),
                              generator=torch.Generator().manual_seed(0))  # fmt: skip
    torch.testing.assert_close(mine.means, ref.means, rtol=0, atol=0)


@pytest.mark.parametrize(
    "resampler",
    [Multinomial(), Systematic(), Stratified(), Residual(), Soft(), StopGradient()],
    ids=repr,
)
def test_a_resamplers_generator_that_is_no_generator_is_named(resampler):
    """A seed where the generator goes had failed inside ``torch.rand`` ("rand() received
    an invalid combination of arguments"), naming neither the resampler nor the argument."""
    x, lw = torch.zeros(3, 1, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
    with pytest.raises(
        TypeError, match=r"generator of .* must be a torch.Generator or None.*got int"
    ):
        resampler(x, lw, 5)
    with pytest.raises(TypeError, match=r"must be a torch.Generator or None.*got int"):
        resampler.ancestors(lw, 5)
    resampler(x, lw, torch.Generator().manual_seed(0))  # a generator, and None, still go
    resampler(x, lw, None)


def test_large_float32_log_weights_are_normalised_to_weights_summing_to_one():
    """A second trial: ``ℓ − logsumexp ℓ`` rounded the logsumexp to the ulp of ℓ (0.0625 at
    1e6): float32 log-weights about 1e6 gave weights summing to 1.017, an ESS 3.4 % low, and
    an unbalanced transport that never met its tolerance. Truth: the same float32 numbers'
    softmax in float64."""
    from difffilter.resampling import OptimalTransport, effective_sample_size, normalize_log_weights

    g = torch.Generator().manual_seed(0)
    lw = (torch.randn(1, 1000, generator=g, dtype=torch.float64) + 1e6).float()
    w = torch.softmax(lw.double(), -1)
    assert abs(float(normalize_log_weights(lw).double().exp().sum()) - 1) < 1e-5
    assert float(effective_sample_size(lw)) == pytest.approx(float(1 / w.square().sum()), rel=1e-4)
    x = torch.randn(1, 1000, 2, generator=g)
    res = Systematic()(x, lw, torch.Generator().manual_seed(1))
    assert abs(float(res.log_weights.double().exp().sum()) - 1) < 1e-5
    ot = df.resampling.OptimalTransport()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # it had run every iteration and warned
        moved = ot(x, lw).particles
    shifted = OptimalTransport()(x, lw - 1e6).particles  # the same weights (exact shift)
    torch.testing.assert_close(moved, shifted, rtol=0, atol=1e-4)


@pytest.mark.parametrize("method", ["log", "kernel"])
def test_optimal_transport_of_no_runs_is_empty_and_its_generator_is_checked(method):
    """A second trial: a batch of no runs failed in torch's "max(): Expected reduction dim"
    (every other resampler returns an empty result), and ``generator=5`` was taken."""
    from difffilter.resampling import OptimalTransport

    ot = OptimalTransport(method=method)
    res = ot(torch.zeros(0, 5, 2), torch.zeros(0, 5))
    assert res.particles.shape == (0, 5, 2) and res.log_weights.shape == (0, 5)
    assert ot.transport_matrix(torch.zeros(0, 5, 2), torch.zeros(0, 5)).shape == (0, 5, 5)
    with pytest.raises(TypeError, match="generator of .* must be a torch.Generator"):
        ot(torch.zeros(5, 2), torch.zeros(5), 5)


@pytest.mark.parametrize("resampler", [Systematic(), Multinomial(), Soft(0.5)])
def test_particles_without_entries_are_refused_by_name(resampler):
    """``[2, 3, 0]`` failed in a raw "cannot reshape … [-1, 0]" (unbatched it passed)."""
    for shape in ((2, 3, 0), (3, 0)):
        with pytest.raises(ValueError, match=r"particles must have at least one entry each"):
            resampler(torch.ones(shape), torch.zeros(shape[:-1]), torch.Generator().manual_seed(0))


def _ot_cloud(n=20, dtype=torch.float64):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, n, 2, generator=g, dtype=dtype)
    log_w = torch.log_softmax(torch.randn(2, n, generator=g, dtype=dtype), -1)
    return x, log_w


@pytest.mark.parametrize("method", ["kernel", "log"])
def test_optimal_transport_refuses_a_second_derivative_it_cannot_give(method):
    """Its hand-written backward was marked once-differentiable: a double backward whose
    incoming gradient held no graph dropped the second-order terms without a word (1.3e-13
    where ``transport_matrix``, plain torch operations, gives 495)."""
    ot = df.resampling.OptimalTransport(method=method)
    x, log_w = _ot_cloud()
    log_w.requires_grad_()
    (grad,) = torch.autograd.grad(ot(x, log_w).particles.square().sum(), log_w, create_graph=False)
    assert bool(torch.isfinite(grad).all())
    with pytest.raises(RuntimeError, match="cannot be differentiated again"):
        torch.autograd.grad(ot(x, log_w).particles.square().sum(), log_w, create_graph=True)
    if method == "kernel":  # (its plan in plain torch operations: twice differentiable)
        plan = ot.transport_matrix(x, log_w)
        (g1,) = torch.autograd.grad(plan.square().sum(), log_w, create_graph=True)
        torch.autograd.grad(g1.sum(), log_w)


def test_optimal_transport_refuses_half_precision_and_torch_func():
    """float16 had been taken (its kernel floor swamped the kernel: particles 0.53 off, the
    run "converged"); under torch.func its autograd Functions failed deep in torch."""
    ot = df.resampling.OptimalTransport()
    x, log_w = _ot_cloud()
    with pytest.raises(ValueError, match="optimal transport needs float32 or float64"):
        ot(x.half(), log_w.half())
    with pytest.raises(ValueError, match="do not run under torch.func transforms"):
        torch.func.grad(lambda lw: ot(x, lw).particles.sum())(log_w)


def test_optimal_transport_scales_by_the_particles_that_have_weight():
    """The cost was scaled by the unweighted spread of every particle: one of zero weight
    far from the cloud set it, and the resampled cloud collapsed (std 0.35 for 0.98 with the
    outlier 100 away, 0.014 at 1e4)."""
    ot = df.resampling.OptimalTransport()
    x, log_w = _ot_cloud(200)
    far, near = x.clone(), x.clone()
    far[:, 0], near[:, 0] = 100.0, 0.0
    log_w = log_w.clone()
    log_w[:, 0] = -float("inf")
    log_w = torch.log_softmax(log_w, -1)
    spreads = [ot(cloud, log_w).particles[:, 1:].std(dim=-2) for cloud in (far, near)]
    assert float((spreads[0] / spreads[1]).min()) > 0.8
