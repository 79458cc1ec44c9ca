"""Findings of a trial of the particle filter's plug-in protocols (each failed before its
fix): what a plug-in returns is checked, and a valid plug-in is taken."""

from __future__ import annotations

import math

import pytest
import torch

import difffilter as df
from difffilter import Generators, ParticleState
from difffilter.resampling import Resampled, Resampler, Systematic

F64 = dict(dtype=torch.float64)


def _model(d: int = 2):
    eye = torch.eye(d, **F64)
    return df.LinearGaussianModel(eye, eye, 0.01 * eye, 0.1 * eye, torch.zeros(d, **F64), eye)


def _ys(model, T=6, runs=3):
    return model.simulate(T, (runs,), generator=torch.Generator().manual_seed(1))[1]


def _run(model, ys, **kw):
    return df.particle_filter(
        model, ys, num_particles=50, generator=torch.Generator().manual_seed(0), **kw
    )


def _max_weight(name, steps=None):
    def hook(model, y, mask, carry, out):
        if steps is not None and carry.k not in steps:
            return {}
        return {name: carry.log_weights.exp().max(-1).values}

    hook.__qualname__ = f"hook_{name}"
    return hook


@pytest.mark.parametrize(
    ("hook", "match"),
    [
        (
            _max_weight("late", steps={3, 4, 5, 6}),
            r"extras\['late'\] must be a tensor at every step.*step 1 of 6 gave nothing",
        ),
        (
            _max_weight("early", steps={1}),
            r"extras\['early'\] must be a tensor at every step.*step 2 of 6 gave nothing",
        ),
        (lambda model, y, mask, carry, out: {"f": 1.0}, r"extras\['f'\].*step 1 of 6 gave float"),
    ],
)
def test_a_record_must_be_a_tensor_at_every_step(hook, match):
    """The records of the first step's keys alone were stacked: one a hook began at step 3
    was dropped without a word, one that stopped failed on a bare ``KeyError``, and a number
    in ``torch.stack``."""
    model = _model()
    with pytest.raises(ValueError, match=match):
        _run(model, _ys(model), hooks=[hook])
    assert sorted(_run(model, _ys(model), hooks=[_max_weight("always")]).records) == ["always"]


class _NisDetector:
    """A stateful likelihood recording its running NIS as ``"score"``."""

    def init(self, model, batch_shape, dtype, device):
        return torch.zeros(batch_shape, dtype=dtype, device=device)

    def weigh(self, state, model, y, particles, k, mask, predictive):
        nu, S = predictive.innovation, predictive.innovation_cov
        state = state + (nu.unsqueeze(-2) @ torch.linalg.solve(S, nu.unsqueeze(-1)))[..., 0, 0]
        return (
            state,
            model.measurement_log_prob(y.unsqueeze(-2), particles, k, None),
            {"score": state},
        )


def test_two_plugins_recording_one_name_are_refused():
    """The later of two plug-ins recording one name silently replaced the other: the
    detector's ``records["score"]`` read as a hook's."""
    model = _model()
    with pytest.raises(
        ValueError,
        match="the step hook hook_score recorded 'score' at step 1, which the likelihood _NisDetector records too",
    ):
        _run(model, _ys(model), likelihood=_NisDetector(), hooks=[_max_weight("score")])
    with pytest.raises(
        ValueError, match="recorded 'stat' at step 1, which the step hook hook_stat records too"
    ):
        _run(model, _ys(model), hooks=[_max_weight("stat"), _max_weight("stat")])


class _OutOfRange(Resampler):
    def _draw_given(self, log_w, weights, generator):
        ancestors = Systematic()._draw(log_w, generator)
        ancestors[0, -1] = log_w.shape[-1]  # index N: the next run's first particle
        return ancestors


class _OneShort(Resampler):
    def resample_normalized(self, particles, log_w, generator=None, rows=None, weights=None):
        return Resampled(particles[..., :-1, :], torch.log_softmax(log_w[..., :-1], -1), None)


@pytest.mark.parametrize(
    ("resampler", "match"),
    [
        (_OutOfRange(), r"_draw returned ancestors from \d+ to 10"),
        (_OneShort(), r"returned particles \(2, 9, 1\)"),
    ],
)
def test_a_resampler_through_its_other_hooks_is_checked(resampler, match):
    """A ``_draw_given`` or ``resample_normalized`` of one's own was accepted and never
    checked: an index N took run 1's particle into run 0 (mean 10.24 for about 0.2), and
    N − 1 particles shrank the carry."""
    model = _model(1)
    pf = df.ParticleFilter(10, resampler=resampler, ess_threshold=1.0)
    g = torch.Generator().manual_seed(0)
    start = torch.randn(2, 10, 1, generator=g, **F64)
    carry = pf.attach(
        ParticleState(start, torch.full((2, 10), -math.log(10), **F64)), model, Generators.of(g)
    )
    with pytest.raises(ValueError, match=match):
        for y in _ys(model, 3, 2).unbind(1):
            carry, _ = pf.step(carry, y)


def test_a_predictive_likelihood_may_require_its_predictive_argument():
    """The filter always passes ``predictive=`` to a ``uses_predictive`` likelihood, but one
    whose ``predictive`` had no default was refused against a call without it."""

    class Required:
        uses_predictive = True

        def __call__(self, model, y, particles, k, mask, predictive):
            return model.measurement_log_prob(y.unsqueeze(-2), particles, k, mask)

    class Defaulted(Required):
        def __call__(self, model, y, particles, k, mask, predictive=None):
            return super().__call__(model, y, particles, k, mask, predictive)

    model = _model()
    ys = _ys(model)
    runs = [_run(model, ys, likelihood=lik).log_likelihood for lik in (Required(), Defaulted())]
    torch.testing.assert_close(runs[0], runs[1], rtol=0, atol=0)
