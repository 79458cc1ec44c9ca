"""Findings of a trial of the resamplers: what they refuse, and where."""

from __future__ import annotations

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
