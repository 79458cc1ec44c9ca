"""Findings of a plug-in author's trial: a resampler's own ``_draw`` whose
ancestors are out of range, and a ``Residual`` whose base has a ``_draw`` of its own."""

import pytest
import torch

import difffilter as df
from difffilter.resampling import Multinomial, Resampler, Residual

D = torch.float64


class _OffByOne(Resampler):
    """Identity ancestors, but run 0's first slot is N: an inverse CDF by ``searchsorted``
    without the clamp at the top (what round-off at u → 1 gives)."""

    def _draw(self, log_w, generator):
        n = log_w.shape[-1]
        a = torch.arange(n).expand(log_w.shape).clone()
        a[0, 0] = n
        return a


def test_out_of_range_ancestors_of_an_own_draw_are_refused_not_taken_from_another_run():
    """Index N of run 0 was read, through the gather on the flattened rows, as particle 0
    of run 1: run 0 went on with another run's particle, without a word."""
    particles = torch.stack([torch.zeros(5, 1, dtype=D), torch.full((5, 1), 7.0, dtype=D)])
    log_w = torch.zeros(2, 5, dtype=D)
    with pytest.raises(ValueError, match=r"_OffByOne.*\[0, N\)"):
        _OffByOne()(particles, log_w)
    with pytest.raises(ValueError, match=r"_OffByOne.*\[0, N\)"):
        _OffByOne().ancestors(log_w)


def test_the_filter_names_a_resampler_whose_draw_is_out_of_range_and_the_step():
    model = df.LinearGaussianModel(
        torch.eye(2, dtype=D), torch.eye(1, 2, dtype=D), 0.1 * torch.eye(2, dtype=D),
        0.1 * torch.eye(1, dtype=D), torch.zeros(2, dtype=D), torch.eye(2, dtype=D),
    )  # fmt: skip
    _, ys, _ = model.simulate(4, (3,), generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=r"_OffByOne.*\[0, N\).*before step \d"):
        df.particle_filter(model, ys, num_particles=5, resampler=_OffByOne(), ess_threshold=1.0,
                           generator=torch.Generator().manual_seed(0))  # fmt: skip


def test_float_or_short_ancestors_of_an_own_draw_are_named():
    """A float or a short ancestor tensor failed inside torch (index_select's dtype, an
    expand), naming neither the resampler nor what _draw returns."""

    class Floats(Resampler):
        def _draw(self, log_w, generator):
            return torch.zeros(log_w.shape, dtype=log_w.dtype)

    class Short(Resampler):
        def _draw(self, log_w, generator):
            return torch.zeros(log_w.shape[:-1] + (log_w.shape[-1] - 1,), dtype=torch.long)

    x, log_w = torch.zeros(2, 4, 1, dtype=D), torch.zeros(2, 4, dtype=D)
    for kind in (Floats, Short):
        with pytest.raises(ValueError, match=kind.__name__ + r"'s _draw returned"):
            kind()(x, log_w)


def test_residual_refuses_a_base_whose_own_draw_it_would_ignore():
    """Residual draws its R < N residual slots with the base's inverse CDF
    (``_draw_from``): a base's own ``_draw`` was ignored, silently (a scheme that picks
    particle 0 at every draw picked it in 60 % of the residual slots, the weights' share)."""

    class Everyone0(Multinomial):
        def _draw(self, log_w, generator):
            return torch.zeros(log_w.shape, dtype=torch.long)

    with pytest.raises(ValueError, match=r"base.*_draw"):
        Residual(base=Everyone0())

    class Spaced(Multinomial):  # own uniforms: honoured by the residual draws, accepted
        def _uniforms(self, weights, count, generator):
            return (torch.arange(weights.shape[-1], dtype=weights.dtype) + 0.5) / count

    Residual(base=Spaced())


def test_a_plugin_whose_call_misses_an_argument_is_named_at_construction():
    """A resampler's ``__call__`` written without ``generator`` failed at the first
    resampling with Python's bare "__call__() takes 3 positional arguments but 4 were
    given", naming neither the plug-in's role nor the contract."""

    class NoGenerator:
        def __call__(self, particles, log_weights):
            raise AssertionError("never called")

    class ShortProposal:
        def __call__(self, model, particles, u, y, k, mask):
            raise AssertionError("never called")

    def short_likelihood(model, y, particles, k):
        raise AssertionError("never called")

    cases = [
        (dict(resampler=NoGenerator()), r"resampler NoGenerator is called as resampler\("
         r"particles, log_weights, generator\); its call takes \(particles, log_weights\)"),
        (dict(proposal=ShortProposal()), r"proposal ShortProposal is called as proposal\("
         r"model, particles, u, y, k, mask, generator\)"),
        (dict(likelihood=short_likelihood), r"likelihood function is called as likelihood\("
         r"model, y, particles, k, mask\)"),
    ]  # fmt: skip
    for kwargs, message in cases:
        with pytest.raises(TypeError, match=message):
            df.ParticleFilter(8, **kwargs)

    class Flexible:  # extra keyword-only or defaulted parameters still bind: accepted
        def __call__(self, particles, log_weights, generator=None, *, scale=1.0):
            return Multinomial()(particles, log_weights, generator)

    df.ParticleFilter(8, resampler=Flexible())


def test_a_resampler_subclass_without_a_hook_is_refused_when_the_filter_is_made():
    """A fuzzing trial: a subclass whose ``_draw`` was misspelt ``draw`` passed the filter's
    construction and failed at its first resampling (many steps in, or never) with a bare
    NotImplementedError naming neither the argument nor the hook."""
    from difffilter.fdi import PoADetector, particle_filter_poa
    from difffilter.resampling import Systematic, missing_hook

    class Misspelt(Resampler):
        def draw(self, log_w, generator):
            return torch.zeros_like(log_w, dtype=torch.long)

    with pytest.raises(TypeError, match="resampler Misspelt subclasses Resampler but defines "
                                        "none of its hooks: give it _draw"):  # fmt: skip
        df.ParticleFilter(50, resampler=Misspelt())
    model = df.LinearGaussianModel(torch.eye(1), torch.eye(1), torch.eye(1), torch.eye(1),
                                   torch.zeros(1), torch.eye(1))  # fmt: skip
    with pytest.raises(TypeError, match="defines none of its hooks"):  # the FDI filters too
        particle_filter_poa(model, torch.zeros(2, 3, 1), num_particles=10,
                            detector=PoADetector(0.1, 0.5), resampler=Misspelt())  # fmt: skip
    assert missing_hook(Systematic()) is None and missing_hook(df.resampling.Soft()) is None


def test_optimal_transport_names_particles_and_weights_of_two_dtypes():
    from difffilter.resampling import OptimalTransport

    x = torch.randn(2, 8, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    log_w = torch.zeros(2, 8)
    for particles, weights in ((x, log_w), (x.float(), log_w.double())):
        with pytest.raises(ValueError, match="particles are torch.float(64|32) and log_weights "
                                             "torch.float(32|64): optimal transport"):  # fmt: skip
            OptimalTransport()(particles, weights)
    assert OptimalTransport()(x, log_w.double()).particles.shape == (2, 8, 2)
