"""The particle filter's marginal smoother: ``p(x_k | y_{1:T})`` on the filter's own particles.

Forward filtering, backward smoothing (FFBSm; Doucet, Godsill & Andrieu 2000; Doucet &
Johansen 2009, §5.1): the filter's particles ``x_k^i`` and normalised weights ``w_k^i``
(after step ``k``'s update) are reweighted from the last step back,

    w_{T|T}^i = w_T^i
    w_{k|T}^i = w_k^i Σ_j w_{k+1|T}^j f(x_{k+1}^j | x_k^i) / Σ_l w_k^l f(x_{k+1}^j | x_k^l)

with ``f`` the transition density, ``x_{k+1} = f(x_k, u_k, k) + w`` under the model's
process noise (``model.process_noise_at(k).log_prob``). Computed in the log domain (two
log-sum-exps a step); ``O(N² T)`` per run, the ``[runs, N, N, dx]`` differences a step in
chunks of runs that keep them under :data:`CHUNK_ELEMENTS` entries. Whatever proposal,
likelihood and resampler the filter used: the smoother reads only its filtering
approximations. As every particle smoother on the filter's particles, it cannot put weight
where the filter had no particle (a filter that resampled down to few distinct particles
gives a smoother of few distinct points).
"""

from __future__ import annotations

import math
import numbers
from typing import NamedTuple

import torch
from torch import Tensor

from ._checks import (
    _check_us,
    check_filtered_dtype,
    check_finite_at,
    check_inputs_given,
    check_one_model,
    check_same_result,
    model_dtype_device,
    values_known,
)
from .noise import Gaussian
from .results import ParticleFilterResult
from .ssm import StateSpaceModel, inputs_per_point

__all__ = ["ParticleSmootherResult", "particle_smoother"]

#: The most entries of the ``[runs, N, N, dx]`` transition differences computed at once.
CHUNK_ELEMENTS = 1 << 24


class ParticleSmootherResult(NamedTuple):
    """The smoothed marginals, with the runs' batch shape: ``means [..., T, dx]``
    ``E[x_k | y_{1:T}]`` and ``covs [..., T, dx, dx]`` (the weighted moments of the filter's
    particles under the smoothing weights), ``log_weights [..., T, N]`` the normalised
    smoothing log-weights ``log w_{k|T}^i`` of ``filtered.particles``, and ``filtered``."""

    means: Tensor
    covs: Tensor
    log_weights: Tensor
    filtered: ParticleFilterResult


def _start_of(filtered: ParticleFilterResult, start) -> int:
    """The step the filter started from: ``start`` where given, checked against what the
    filter recorded (``filtered.start``), else the recorded one (0 where none was)."""
    if start is None:
        return 0 if filtered.start is None else filtered.start
    if isinstance(start, bool) or not isinstance(start, numbers.Integral) or start < 0:
        raise ValueError(f"start must be an integer >= 0 (the filter's first k); got {start!r}")
    if filtered.start is not None and start != filtered.start:
        raise ValueError(
            f"start={start} but the particle filter started from k = {filtered.start} "
            "(filtered.start): leave start out to smooth from the filter's own first step "
            "(a result cut in time starts later: dataclasses.replace(filtered, start=k))"
        )
    return int(start)


def particle_smoother(
    model: StateSpaceModel, filtered: ParticleFilterResult, us: Tensor | None = None, *,
    start: int | None = None,
) -> ParticleSmootherResult:  # fmt: skip
    """FFBSm (module docstring) of ``filtered``, the result of
    :func:`difffilter.particle_filter` on ``model`` with ``return_particles=True`` and the same
    inputs ``us [..., T, du]`` (``u_k`` drives ``x_k → x_{k+1}``: the filter's own pairing;
    required on a model with inputs, ``ValueError`` without: zero inputs are given as zeros).
    ``start``: the step ``k`` the filter started from (its ``initial_state``'s; 0 from the
    prior), so that a time-varying model's step ``k`` is read at its own ``k``; by default
    ``filtered.start`` (what :func:`difffilter.particle_filter` recorded; 0 for a result
    made elsewhere), and a ``start`` that contradicts it is refused (left at 0 for a
    filter started at k = 3 it had smoothed 2.7 sd off: a trial). Zero
    filtering weights (``−inf`` log-weights, a particle a bounded noise cannot reach) weigh
    nothing, and their derivatives are 0. Differentiable in the particles, weights and the
    model's parameters. Under nearly deterministic dynamics (``Q`` tiny against the
    particles' spread) the transition density weighs one filtering particle per successor
    and the smoothed weights collapse without a warning (an analyst's trial: ``Q = 1e-12 I``,
    N = 200, 66 off the RTS smoother): compare with the filter, or smooth such a model with
    a Gaussian smoother."""
    if not isinstance(filtered, ParticleFilterResult):
        raise TypeError(
            "filtered must be the ParticleFilterResult of difffilter.particle_filter(model, "
            f"ys, …, return_particles=True); got {type(filtered).__name__}"
        )
    if filtered.particles is None or filtered.log_weights is None:
        raise ValueError(
            "filtered holds no particles: run the particle filter with return_particles=True"
        )
    custom = isinstance(model, StateSpaceModel) and (
        type(model).sample_transition is not StateSpaceModel.sample_transition
    )
    if not isinstance(model, StateSpaceModel) or custom:
        raise TypeError(
            "the particle smoother needs the transition density of x_{k+1} = f(x_k, u_k, k) + w "
            "(a StateSpaceModel with the default sample_transition, its process noise's "
            f"log_prob); {type(model).__name__} "
            + ("draws its transition its own way" if custom else "is no StateSpaceModel")
        )
    start = _start_of(filtered, start)
    # as the particle filter refuses it: its runs' parameter sets lined up with the particles
    # (0.75 off where N = runs; torch's "size of tensor a" otherwise: a trial)
    check_one_model(model, "the particle smoother", "smooth each parameter set's filter result "
                    "with its own model")  # fmt: skip
    particles, log_w = filtered.particles, filtered.log_weights
    _check_particles_weights(particles, log_w)
    steps = particles.shape[-3]
    if particles.shape[-1] != model.dim_x:  # (torch's "Expected size for first two …")
        raise ValueError(
            f"model's states have {model.dim_x} entries and the filter's particles "
            f"{particles.shape[-1]}: smooth with the model the filter ran on"
        )
    check_filtered_dtype(model, particles, "particles")
    check_inputs_given(model, us, "the particle smoother", "its transition density's f(x_k, u_k)")
    if us is not None:  # the filter's inputs, checked as the filters check them
        dtype, device = model_dtype_device(model)
        _check_us(model, us, particles.shape[:-3], steps, dtype, device,
                  against="the particles'")  # fmt: skip
        runs = particles.shape[:-3]
        if torch.broadcast_shapes(us.shape[:-2], runs) != runs:  # (torch's expand had failed)
            raise ValueError(
                f"us's batch shape {tuple(us.shape[:-2])} has runs the filter's particles "
                f"{tuple(runs)} do not: give the inputs the filter ran on"
            )
    smoothed = [log_w[..., -1, :]]
    for t in range(steps - 2, -1, -1):  # index t holds x_{t+1}; its successor x_{t+2}
        u = None if us is None else us[..., t + 1, :]
        smoothed.append(_backward_step(model, particles[..., t, :, :], log_w[..., t, :],
                                       particles[..., t + 1, :, :], smoothed[-1], u,
                                       start + t + 1))  # fmt: skip
    smoothed.reverse()
    log_ws = torch.stack(smoothed, -2)  # [..., T, N]
    w = log_ws.exp()
    means = (w.unsqueeze(-1) * particles).sum(-2)
    dev = particles - means.unsqueeze(-2)
    covs = (w[..., None, None] * dev.unsqueeze(-1) * dev.unsqueeze(-2)).sum(-3)
    return ParticleSmootherResult(means, 0.5 * (covs + covs.mT), log_ws, filtered)


def _check_particles_weights(particles: Tensor, log_w: Tensor) -> None:
    """``filtered.particles [..., T, N, dx]`` (T ≥ 1, finite) and ``filtered.log_weights
    [..., T, N]`` of the same shape, dtype and device (no NaN or +inf; −inf: a zero weight):
    log-weights one step short had been read a step shifted (0.9 posterior sd off), others
    had failed in torch or given NaN means (a particle smoother trial)."""
    for t, name in ((particles, "particles"), (log_w, "log_weights")):
        if not isinstance(t, Tensor) or not t.is_floating_point():
            got = t.dtype if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"filtered.{name} must be a floating tensor; got {got}")
    if particles.dim() < 3 or particles.shape[-3] == 0:
        raise ValueError(
            "filtered.particles must have shape [..., T, N, dx] with T >= 1 (a particle "
            f"filter's result with return_particles=True); got {tuple(particles.shape)}"
        )
    if log_w.shape != particles.shape[:-1]:
        raise ValueError(
            f"filtered.log_weights must have shape {tuple(particles.shape[:-1])} ([..., T, N], "
            f"one per particle of filtered.particles); got {tuple(log_w.shape)}"
        )
    check_same_result(log_w, "filtered.log_weights", particles, "the particles")
    check_finite_at(particles, "filtered.particles")
    if values_known(log_w) and bool((torch.isnan(log_w) | (log_w == float("inf"))).any()):
        raise ValueError(
            "filtered.log_weights contains NaN or +inf values (−inf, a zero weight, is allowed)"
        )


def _backward_step(model, now: Tensor, log_w: Tensor, later: Tensor, later_smoothed: Tensor,
                   u: Tensor | None, k: int) -> Tensor:  # fmt: skip
    """``log w_{k|T} [..., N]`` from the filter's ``now [..., N, dx]`` and ``log_w [..., N]``
    at step ``k``, the particles ``later [..., N, dx]`` of step ``k + 1`` and their smoothing
    log-weights ``later_smoothed [..., N]``, by chunks of runs (module docstring)."""
    batch, (n, dx) = now.shape[:-2], now.shape[-2:]
    runs = math.prod(batch)
    if runs == 0:  # no run: nothing to weigh
        return log_w.new_empty(batch + (n,))
    now_r, later_r = _runs(now, batch, 2), _runs(later, batch, 2)
    log_w_r, smooth_r = _runs(log_w, batch, 1), _runs(later_smoothed, batch, 1)
    u_r = None if u is None else _runs(u, batch, 1)
    noise = model.process_noise_at(k)
    gaussian = type(noise) is Gaussian
    chunk = max(1, CHUNK_ELEMENTS // max(1, n * n * dx))
    out = []
    for start in range(0, runs, chunk):
        rows = slice(start, min(runs, start + chunk))
        u_c = None if u_r is None else inputs_per_point(u_r[rows], now_r[rows])  # (as the PF)
        ahead = model.transition(now_r[rows], u_c, k)  # [c, N_i, dx]: f(x_k^i, u_k)
        # log f(x_{k+1}^j | x_k^i) [c, N_i, N_j]
        log_f = noise.log_prob(later_r[rows].unsqueeze(-3) - ahead.unsqueeze(-2))
        joint = log_w_r[rows].unsqueeze(-1) + log_f  # log w_k^i f(x_{k+1}^j | x_k^i)
        # no −inf term: finite weights and a Gaussian density (finite everywhere)
        exact = (
            gaussian
            and bool(torch.isfinite(log_w_r[rows]).all())
            and bool(torch.isfinite(smooth_r[rows]).all())
        )
        # Σ_j w_{k+1|T}^j f_ij / Σ_l w_k^l f_lj: a log-sum-exp over l, then over j
        reach = _logsumexp(joint, -2, exact)  # −inf: no weighted particle reaches x_{k+1}^j
        if exact:
            per_j = smooth_r[rows].unsqueeze(-2) - reach
        else:
            unreached = reach == float("-inf")
            per_j = smooth_r[rows].unsqueeze(-2) - reach.masked_fill(unreached, 0.0)
            per_j = per_j.masked_fill(unreached, float("-inf"))
        log_new = _logsumexp(joint + per_j, -1, exact).squeeze(-1)
        out.append(log_new - _logsumexp(log_new, -1, exact))
    return torch.cat(out).reshape(batch + (n,))


def _runs(t: Tensor, batch: torch.Size, tail: int) -> Tensor:
    """``t [..., *tail dims]`` broadcast to the runs ``batch`` and flattened: ``[runs, ...]``."""
    return t.expand(batch + t.shape[t.dim() - tail :]).reshape((-1, *t.shape[t.dim() - tail :]))


def _logsumexp(x: Tensor, dim: int, exact: bool = False) -> Tensor:
    """``log Σ exp x`` over ``dim`` (kept), ``−inf`` where every term is ``−inf`` (a particle
    that no weighted particle reaches, one of zero weight), with a derivative of 0 there:
    torch's is NaN on an all-``−inf`` slice (its ``exp(x − lse)`` is ``exp(−inf + inf)``).
    ``exact``: no term is ``−inf`` (finite weights, a Gaussian noise): torch's alone (the
    masking cost 1.9× on the ``[N, N]`` terms)."""
    if exact:
        return torch.logsumexp(x, dim, keepdim=True)
    some = (x != float("-inf")).any(dim, keepdim=True)
    safe = torch.logsumexp(x.masked_fill(~some, 0.0), dim, keepdim=True)
    return safe.masked_fill(~some, float("-inf"))
