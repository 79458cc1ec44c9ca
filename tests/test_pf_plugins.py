"""A particle-filter plug-in author's findings: a likelihood, a proposal or a resampler of
one's own that misbehaves is named at the step it misbehaves, where it gave wrong numbers
without a word (a forgotten batch axis, a NaN read as an underflow, unnormalised
log-weights, a particle lost at each resampling)."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import constant_velocity

import difffilter as df
from difffilter.particle import ModelLikelihood
from difffilter.resampling import Resampled, Resampler, Systematic


def _data(B=3, T=6):
    model = constant_velocity()
    _, ys, _ = model.simulate(T, (B,), generator=torch.Generator().manual_seed(2))
    return model, ys


def _run(model, ys, **kw):
    return df.particle_filter(model, ys, num_particles=16,
                              generator=torch.Generator().manual_seed(0), **kw)  # fmt: skip


class _Lik:
    """The model's likelihood, then ``spoil(log p, k)``."""

    def __init__(self, spoil):
        self.spoil = spoil

    def __call__(self, model, y, particles, k, mask):
        return self.spoil(ModelLikelihood()(model, y, particles, k, mask), k)


def test_a_likelihood_of_the_wrong_shape_or_dtype_is_named():
    """``[N]`` gave every run the first run's likelihood; an integer one was truncated."""
    model, ys = _data()
    for spoil, match in (
        (lambda lp, k: lp[0], r"likelihood _Lik returned log-densities of shape \(16,\)"),
        (lambda lp, k: lp.sum(), r"shape \(\)"),
        (lambda lp, k: lp.long(), "dtype torch.int64"),
        (lambda lp, k: lp.float(), "dtype torch.float32"),
    ):
        with pytest.raises(ValueError, match=match):
            _run(model, ys, likelihood=_Lik(spoil))
    with pytest.raises(TypeError, match="likelihood _Lik returned a tuple at step 1"):
        _run(model, ys, likelihood=_Lik(lambda lp, k: (lp,)))


def test_a_nan_or_plus_inf_from_a_plug_in_is_named_not_taken_for_an_underflow():
    """One NaN on one particle made the step degenerate: the run's weights reset to the
    predictive ones and the measurement was ignored, with finite, plausible means."""
    model, ys = _data()

    def spoil_at(step, value):
        def spoil(lp, k):
            if k == step:
                lp = lp.clone()
                lp[1, 5] = value
            return lp

        return spoil

    for value in (math.nan, math.inf):
        with pytest.raises(ValueError, match=r"likelihood of _Lik holds NaN or \+inf at step 3 "
                                             r"\(first at index \(1, 5\)\)"):  # fmt: skip
            _run(model, ys, likelihood=_Lik(spoil_at(3, value)))
    # an underflow (every particle −inf) still resets the run, as documented
    res = _run(model, ys, likelihood=_Lik(lambda lp, k: torch.where(
        torch.tensor(k == 3), torch.full_like(lp, -math.inf), lp)))  # fmt: skip
    assert res.degenerate[:, 2].all() and torch.isfinite(res.means).all()

    class NanProposal(df.BootstrapProposal):
        def __call__(self, model, particles, u, y, k, mask, generator):
            new, _ = super().__call__(model, particles, u, y, k, mask, generator)
            correction = torch.zeros(new.shape[:-1], dtype=new.dtype)
            correction[0, 0] = math.nan if k == 2 else 0.0
            return new, correction

    with pytest.raises(ValueError, match="proposal's correction of NanProposal holds NaN"):
        _run(model, ys, proposal=NanProposal())


class _Unnormalised:
    def __init__(self, shift=0.0, drop=0):
        self.shift, self.drop = shift, drop

    def __call__(self, particles, log_weights, generator=None):
        res = Systematic()(particles, log_weights, generator)
        n = particles.shape[-2] - self.drop
        return Resampled(res.particles[..., :n, :], res.log_weights[..., :n] + self.shift,
                         res.ancestors[..., :n])  # fmt: skip


def test_a_resampler_of_ones_own_is_checked_and_a_call_only_subclass_is_called():
    """Unnormalised log-weights shifted the evidence by their sum at each resampling; N − 1
    particles shrank the online carry a particle a step; a Resampler subclass overriding
    ``__call__`` alone was never called (the base asked for ``_draw``)."""
    model, ys = _data()
    with pytest.raises(ValueError, match="logsumexp per run is up to 5 from 0"):
        _run(model, ys, resampler=_Unnormalised(shift=5.0), ess_threshold=1.0)
    with pytest.raises(ValueError, match=r"returned particles \(3, 15, 4\).*given \(3, 16, 4\)"):
        _run(model, ys, resampler=_Unnormalised(drop=1), ess_threshold=1.0)
    pf = df.ParticleFilter(8, resampler=_Unnormalised(drop=1), ess_threshold=1.0)
    carry = pf.init(model, (), torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="the same number of particles"):
        for t in range(2):  # (the carry shrank 8 → 7 → 6 … before)
            carry, _ = pf.step(carry, ys[0, t])

    class CallOnly(Resampler):
        calls = 0

        def __call__(self, particles, log_weights, generator=None):
            CallOnly.calls += 1
            return Systematic()(particles, log_weights, generator)

    mine = _run(model, ys, resampler=CallOnly(), ess_threshold=1.0)
    assert CallOnly.calls == ys.shape[1]  # at ess_threshold 1 every step resamples
    plain = _run(model, ys, resampler=Systematic(), ess_threshold=1.0)
    torch.testing.assert_close(mine.means, plain.means)  # the same draws, the same filter
