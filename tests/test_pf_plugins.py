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


class _OneRunCorrection(df.KalmanProposal):
    def __call__(self, *args):
        new, correction = super().__call__(*args)
        return new, correction[0]  # the first run's alone


class _OneRunParticles:
    def __call__(self, model, particles, u, y, k, mask, generator):
        return model.sample_transition(particles[0], None, k, generator), None


class _Float32Particles:
    def __call__(self, model, particles, u, y, k, mask, generator):
        return model.sample_transition(particles, None, k, generator).float(), None


class _NaNParticles:
    def __call__(self, model, particles, u, y, k, mask, generator):
        new = model.sample_transition(particles, None, k, generator).clone()
        new[0, 0, 0] = float("nan")
        return new, None


@pytest.mark.parametrize(
    "proposal, match",
    [
        (_OneRunCorrection(), r"the proposal's correction _OneRunCorrection returned log-densities of shape"),
        (_OneRunParticles(), r"the proposal _OneRunParticles returned particles \(16, 4\)"),
        (_Float32Particles(), r"the proposal _Float32Particles returned particles .* torch.float32"),
        (_NaNParticles(), r"the particles proposed by _NaNParticles hold NaN or inf at step 1"),
    ],
)  # fmt: skip
def test_a_proposal_that_breaks_its_contract_is_named(proposal, match):
    """From a plug-in trial: a proposal's output was never checked: one run's correction for
    a batch gave every run its evidence (15 nats off), one run's particles came out as means
    [3, 3, T, dx], float32 particles failed inside torch, NaN particles were blamed on the
    likelihood."""
    model, ys = _data()
    with pytest.raises(ValueError, match=match):
        _run(model, ys, proposal=proposal)


def test_a_resampler_subclass_draws_with_its_own_draw():
    """From the same trial: the documented hook ``_draw`` of a Multinomial (Systematic,
    Stratified) subclass was used by ``ancestors`` alone; calling the resampler, and the
    filter, drew from the parent's inverse CDF (12 of 20 particles distinct for 1)."""
    from difffilter.resampling import Multinomial

    class Heaviest(Multinomial):
        def _draw(self, log_w, generator):
            return log_w.argmax(-1, keepdim=True).expand(log_w.shape).clone()

    class Spaced(Systematic):  # a subclass's own uniforms are honoured too
        def _uniforms(self, weights, count, generator):
            n = weights.shape[-1]
            return (torch.arange(n, dtype=weights.dtype) + 0.5) / n

    log_w = torch.log(torch.tensor([0.1, 0.6, 0.3], dtype=torch.float64))
    x = torch.arange(3, dtype=torch.float64).reshape(3, 1)
    assert Heaviest()(x, log_w).ancestors.tolist() == [1, 1, 1]
    assert Spaced()(x, log_w).ancestors.tolist() == [1, 1, 2]  # targets 1/6, 1/2, 5/6
    model, ys = _data()

    def keep(model, particles, u, y, k, mask, generator):  # shows the resampled cloud
        return particles.clone(), None

    out = _run(model, ys, resampler=Heaviest(), proposal=keep, return_particles=True,
               ess_threshold=1.0)  # fmt: skip
    # (the first step resamples at ess_threshold = 1): every run down to one particle
    assert bool(out.resampled[:, 0].all())
    assert all(len(torch.unique(p, dim=0)) == 1 for p in out.particles[:, 0])


def test_a_resampler_that_breaks_its_contract_is_named():
    """From the plug-in trial: float32 log-weights failed inside torch, NaN particles were
    blamed on the likelihood a step later, and no resampler error named the resampler."""

    class Spoiled:
        def __init__(self, spoil):
            self.spoil = spoil

        def __call__(self, particles, log_weights, generator=None):
            res = Systematic()(particles, log_weights, generator)
            return Resampled(*self.spoil(res.particles, res.log_weights), res.ancestors)

    model, ys = _data()
    cases = {
        "float32 log-weights": (lambda p, lw: (p, lw.float()), r"the resampler Spoiled \(before step 1\) returned "
                                r"particles .* and log-weights \(3, 16\) torch.float32"),
        "NaN particles": (lambda p, lw: (p * float("nan"), lw),
                          r"the resampler Spoiled \(before step 1\) returned NaN or inf particles"),
    }  # fmt: skip
    for spoil, match in cases.values():
        with pytest.raises(ValueError, match=match):
            _run(model, ys, resampler=Spoiled(spoil), ess_threshold=1.0)


def test_a_draw_override_that_goes_through_draw_given_does_not_recurse():
    """From a review: the parent's own ``_draw`` had gone through ``_draw_given``; an override
    written the same way recursed forever once ``_draw_given`` honoured overrides."""
    from difffilter.resampling import Multinomial

    class Through(Multinomial):
        def _draw(self, log_w, generator):
            return self._draw_given(log_w, None, generator)  # the parent's draw

    log_w = torch.log(torch.tensor([0.2, 0.5, 0.3], dtype=torch.float64))
    x = torch.arange(3, dtype=torch.float64).reshape(3, 1)
    got = Through()(x, log_w, torch.Generator().manual_seed(0)).ancestors
    want = Multinomial()(x, log_w, torch.Generator().manual_seed(0)).ancestors
    assert torch.equal(got, want)


class _VoidAt(df.KalmanProposal):
    """The Kalman proposal, its correction −inf on every particle of run 0 at step ``at``
    (every proposed particle of zero transition density)."""

    def __init__(self, at: int):
        super().__init__()
        self.at = at

    def __call__(self, model, particles, u, y, k, mask, generator):
        new, correction = super().__call__(model, particles, u, y, k, mask, generator)
        if k + 1 == self.at:  # (one run: its N corrections; a batch: run 0's row)
            correction = correction.clone()
            correction[(0,) * (correction.dim() - 1)] = -math.inf
        return new, correction


def test_a_run_whose_every_correction_is_minus_inf_is_degenerate_not_nan():
    """From a plug-in trial: the predictive weights log_softmax(log w − inf) were NaN, the
    run's reset weights with them; the next resampling failed on an index of −2^63 (two
    runs) or blamed the resampler (one run). Such a step is degenerate, as a likelihood
    zero everywhere: evidence −inf, the weights kept, the filter goes on."""
    model, ys = _data(B=2, T=6)
    res = _run(model, ys, proposal=_VoidAt(3), ess_threshold=1.0)
    assert res.degenerate.nonzero().tolist() == [[0, 2]]
    assert res.log_likelihood[0] == -math.inf and torch.isfinite(res.log_likelihood[1])
    assert torch.isfinite(res.means).all()
    fine = _run(model, ys, proposal=df.KalmanProposal(), ess_threshold=1.0)
    torch.testing.assert_close(res.means[1], fine.means[1], rtol=0, atol=0)  # run 1 untouched
    one = _run(model, ys[0], proposal=_VoidAt(3), ess_threshold=1.0)
    assert one.degenerate.nonzero().tolist() == [[2]] and torch.isfinite(one.means).all()
    # no NaN enters the graph: the other run's gradient stays finite
    q = torch.tensor(0.1, dtype=ys.dtype, requires_grad=True)
    out = _run(constant_velocity(q=q), ys, proposal=_VoidAt(3), ess_threshold=1.0)
    out.log_likelihood[1].backward()
    assert torch.isfinite(q.grad)


def test_a_library_schemes_subclass_with_its_own_call_is_called():
    """A Systematic subclass overriding ``__call__`` (to gate on its own ESS rule) inherits
    a ``_draw``, so the filter took the fast path and never called it, bit for bit plain
    Systematic, though the docs say the filter calls an own ``__call__``."""
    model, ys = _data(B=2, T=6)

    class Keeps(Systematic):
        calls = 0

        def __call__(self, particles, log_weights, generator=None):
            Keeps.calls += 1
            log_w = log_weights - torch.logsumexp(log_weights, -1, keepdim=True)
            return Resampled(particles, log_w, None)  # never resamples

    mine = _run(model, ys, resampler=Keeps(), ess_threshold=1.0)
    assert Keeps.calls == ys.shape[1]
    kept = _run(model, ys, resampler=Keeps(), ess_threshold=0.0)  # never called: nothing due
    torch.testing.assert_close(mine.means, kept.means)  # its choice, not Systematic's draw
    plain = _run(model, ys, resampler=Systematic(), ess_threshold=1.0)
    assert not torch.equal(mine.means, plain.means)


def test_an_own_new_log_weights_hook_is_checked_for_normalisation():
    """A Systematic subclass whose ``_new_log_weights`` returned zeros for −log N moved the
    evidence by log N at every resampling (75.3 for −30.7 over 20 steps), without a word."""
    model, ys = _data()

    class Zeros(Systematic):
        def _new_log_weights(self, log_w, ancestors):
            return torch.zeros_like(log_w)

    with pytest.raises(
        ValueError, match=r"resampler Zeros \(before step 1\) returned log-weights whose"
    ):
        _run(model, ys, resampler=Zeros(), ess_threshold=1.0)

    class Uniform(Systematic):  # normalised: runs, the same as the base
        def _new_log_weights(self, log_w, ancestors):
            return torch.full_like(log_w, -math.log(log_w.shape[-1]))

    torch.testing.assert_close(_run(model, ys, resampler=Uniform(), ess_threshold=1.0).means,
                               _run(model, ys, resampler=Systematic(), ess_threshold=1.0).means)  # fmt: skip


def test_a_plug_ins_step_is_the_measurements_and_a_bare_tensor_is_named():
    """A +inf correction at the first step was reported 'at step 0' (its shape error 'at step
    1'); a proposal returning its particles alone failed as 'too many values to unpack'."""
    model, ys = _data()

    class PlusInf(df.KalmanProposal):
        def __call__(self, *args):
            new, correction = super().__call__(*args)
            return new, torch.full_like(correction, math.inf)

    with pytest.raises(ValueError, match="correction of PlusInf holds NaN or \\+inf at step 1 "):
        _run(model, ys, proposal=PlusInf())

    class Bare:
        def __call__(self, model, particles, u, y, k, mask, generator):
            return model.sample_transition(particles, u, k, generator)

    with pytest.raises(TypeError, match=r"proposal Bare returned a tensor \(3, 16, 4\) at step 1;"
                                        r" it returns a pair"):  # fmt: skip
        _run(model, ys, proposal=Bare())


class _KeepMixin:
    """A ``__call__`` of one's own that never resamples (kept particles, normalised weights)."""

    calls = 0

    def __call__(self, particles, log_weights, generator=None):
        type(self).calls += 1
        return Resampled(particles, log_weights - torch.logsumexp(log_weights, -1, keepdim=True),
                         None)  # fmt: skip


@pytest.mark.parametrize("layout", ["mixin", "beside_draw", "inherited", "plain_object"])
def test_a_call_of_ones_own_is_called_wherever_python_finds_it(layout):
    """From a review: a ``__call__`` beside an own ``_draw``, from a mixin, or inherited by a
    subclass that overrides ``_draw`` was skipped (the filter drew with the scheme); a
    wrapper that delegates attributes failed on ``resample_normalized``."""
    model, ys = _data(B=2, T=6)

    class Inherits(_KeepMixin, Systematic):
        pass

    kinds = {
        "mixin": Inherits,
        "beside_draw": type("Beside", (Systematic,), {"__call__": _KeepMixin.__call__,
                                                       "_draw": Systematic._draw, "calls": 0}),
        "inherited": type("Sub", (Inherits,), {"_draw": Systematic._draw, "calls": 0}),
        "plain_object": type("Delegates", (_KeepMixin,), {
            "calls": 0, "__getattr__": lambda self, name: getattr(Systematic(), name)}),
    }  # fmt: skip
    kind = kinds[layout]
    mine = _run(model, ys, resampler=kind(), ess_threshold=1.0)
    assert kind.calls == ys.shape[1]
    never = _run(model, ys, resampler=Systematic(), ess_threshold=0.0)  # nothing resampled
    torch.testing.assert_close(mine.means, never.means, rtol=0, atol=0)


def test_a_class_changed_after_a_run_is_read_as_it_is_now():
    model, ys = _data(B=2, T=6)

    class Later(Systematic):
        calls = 0

    _run(model, ys, resampler=Later(), ess_threshold=1.0)
    Later.__call__ = _KeepMixin.__call__
    _run(model, ys, resampler=Later(), ess_threshold=1.0)
    assert Later.calls == ys.shape[1]


def test_a_resamplers_error_names_the_step_and_a_wrong_tuple_is_named():
    model, ys = _data()
    with pytest.raises(ValueError, match=r"the resampler _Unnormalised \(before step 1\) returned"):
        _run(model, ys, resampler=_Unnormalised(shift=5.0), ess_threshold=1.0)

    class Three(df.KalmanProposal):
        def __call__(self, *args):
            return (*super().__call__(*args), None)

    with pytest.raises(TypeError, match="proposal Three returned a tuple of 3 at step 1"):
        _run(model, ys, proposal=Three())
