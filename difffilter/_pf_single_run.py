"""The particle filter's step for one run on its default strategies, in few tensor operations.

An estimator deployed on one plant calls ``ParticleFilter(N).step`` with batch shape ``()``
at every measurement. At ``N = 100`` each tensor operation costs a few microseconds of
dispatch and almost no arithmetic, so a step costs what its operations and its Python
cost; the general step (:func:`difffilter.particle._particle_step`) spends most of its time
in its dispatch over proposals, likelihoods, resamplers, masks and batch layouts.

For the default configuration (the bootstrap proposal, the model's own measurement
density, systematic resampling; no mask, hooks, ``cov_dims`` or ``record_prior``) on one run,
:func:`single_run_step` computes the same step written out::

    resample   if ESS_{k−1} < ess_threshold · N:
                   a_j = F⁻¹((j + U)/N)  (U ~ U[0, 1), F the cumulative weights),
                   x ← x[a],  log w ← −log N
    propose    x_k^i = f(x^i, u) + ε^i                    (the model's sample_transition)
    weight     log α^i = log p(y_k | x_k^i)               (the model's measurement noise)
    normalise  log p̂(y_k | y_{1:k−1}) = logsumexp_i(log w^i + log α^i),
               log w_k^i = log w^i + log α^i − log p̂

with the same draws from the same generators in the same order, so the same numbers up to
round-off (tests: the general step against this one, values and gradients, in float64).
Two rewrites of the general step's numbers, both exact in exact arithmetic:

* the Gaussian log-density ``−½ rᵀΣ⁻¹r − c`` of a diagonal zero-mean measurement noise
  enters the normalisation as ``−½ rᵀΣ⁻¹r`` and ``c`` is subtracted from the evidence
  afterwards (one pass over the particles fewer);
* the systematic ancestors are one binary search of the targets ``(j + U)·W/N`` in the
  cumulative weights (``W`` their total); the general step counts offspring instead
  (:func:`~difffilter.resampling.systematic_ancestors`), which equals it up to round-off at
  exact ties and is faster on many rows, slower on one.

A degenerate step (every weight −inf or NaN) resets to the predictive weights or names
the NaN particle or density in the general step's error, as the general step does.

Gradients flow as through the general step (the same detached maximum in the
normalisation, ancestors drawn from detached weights, uniform weights after resampling).
"""

from __future__ import annotations

import math
import weakref

import torch
from torch import Tensor

from ._assignments import assignments
from ._checks import model_batch_shape
from .estimator import Generators
from .noise import Gaussian
from .particle import (
    BootstrapProposal,
    ModelLikelihood,
    ParticleState,
    _blame_degenerate,
    _default_measurement_density,
    _ess,
    _predictive,
)
from .resampling import Systematic
from .results import StepOutput
from .ssm import StateSpaceModel, inputs_per_point

__all__ = [
    "applies",
    "as_batch_of_one",
    "on_defaults",
    "one_of_a_batch",
    "run_of",
    "single_run_step",
]

_NO_GENERATORS = Generators()


def applies(pf, carry, mask) -> bool:
    """Whether :func:`single_run_step` computes ``pf``'s step from ``carry``: no mask, and
    :func:`on_defaults`."""
    return mask is None and on_defaults(pf, carry)


def on_defaults(pf, carry, lead: int = 0) -> bool:
    """Whether ``carry`` is one run (particles ``[N, dx]``; with ``lead = 1``, ``[1, N, dx]``)
    of ``pf`` on the default strategies with no hooks, and its model keeps the base class's
    measurement density: the one-run steps' condition (:func:`single_run_step` also needs
    no mask; the host-array step of :mod:`difffilter._pf_host_step` takes one)."""
    return (
        carry.particles.dim() == 2 + lead
        and type(pf.proposal) is BootstrapProposal
        and type(pf.likelihood) is ModelLikelihood
        and type(pf.resampler) is Systematic
        and not pf.hooks
        and not pf.record_prior
        and pf.cov_dims is None
        and _default_measurement_density(carry.model)
    )


def one_of_a_batch(pf, carry, y: Tensor, u: Tensor | None, mask: Tensor | None) -> bool:
    """Whether ``carry`` is a batch of one run (particles ``[1, N, dx]``, from ``init(model,
    (1,))``) on the defaults (:func:`on_defaults`), stepped with inputs of that batch (``y
    [1, dy]``, ``u [1, du]``, ``mask [1, dy]``): its run takes the one-run steps
    (:func:`run_of`, :func:`as_batch_of_one`), the same numbers as the batched general step
    up to round-off, about 1.7 times as fast. (``init`` refuses a model with parameter sets; one
    given a batch of one set since, ``F [1, dx, dx]``, keeps the batched step.)"""
    p = carry.particles
    return (
        p.dim() == 3
        and p.shape[0] == 1
        and y.shape[:-1] == (1,)
        and (u is None or u.shape[:-1] == (1,))
        and (mask is None or mask.shape[:-1] == (1,))
        and on_defaults(pf, carry, lead=1)
        and _unbatched(carry.model)
    )


def _unbatched(model) -> bool:
    """Whether ``model`` has no parameter sets (:func:`~difffilter._checks.model_batch_shape`
    ``()``), read again only after a tensor was assigned to a model (a set's batch can
    change in no other way)."""
    global _LAST_UNBATCHED
    count, last = assignments(), _LAST_UNBATCHED
    if last is not None and last[0]() is model and last[1] == count:
        return last[2]
    answer = not model_batch_shape(model)
    _LAST_UNBATCHED = (weakref.ref(model), count, answer)
    return answer


#: ``(weak reference to the model, assignments() then, unbatched)`` of the last model read.
_LAST_UNBATCHED: tuple | None = None


def run_of(carry):
    """The run of a batch-of-one carry: its ``[1, …]`` tensors without the batch dimension
    (views)."""
    return carry._replace(
        particles=carry.particles[0], log_weights=carry.log_weights[0],
        ess=None if carry.ess is None else carry.ess[0],
        weights=None if carry.weights is None else carry.weights[0],
    )  # fmt: skip


def as_batch_of_one(carry, out: StepOutput):
    """A one-run step's ``(carry, output)`` with every tensor given its batch of one back
    (views): what the batched step returns for a batch of one run."""
    carry = carry._replace(
        particles=carry.particles.unsqueeze(0), log_weights=carry.log_weights.unsqueeze(0),
        ess=carry.ess.unsqueeze(0), weights=carry.weights.unsqueeze(0),
    )  # fmt: skip
    fields = {name: value.unsqueeze(0) for name, value in zip(out._fields, out)
              if isinstance(value, Tensor)}  # fmt: skip
    extras = {name: value.unsqueeze(0) for name, value in out.extras.items()}
    return carry, out._replace(**fields, extras=extras)


def single_run_step(pf, carry, y: Tensor, u: Tensor | None):
    """One step of ``pf`` from ``carry`` (one run, validated inputs; module docstring):
    ``(ParticleState, StepOutput)`` as the general step returns them.

    Shapes: particles ``[N, dx]``, log-weights ``[N]``, ``y [dy]``, ``u [du]`` or ``None``.
    """
    model, gens, k = carry.model, carry.generators or _NO_GENERATORS, carry.k
    particles, log_w, w = carry.particles, carry.log_weights, carry.weights
    n = particles.shape[0]
    ess = carry.ess if carry.ess is not None else _ess(log_w)
    need = ess < pf.ess_threshold * n  # the step's "resampled" flag, on its device
    resampled = bool(need)
    if resampled:
        gen = gens.resample if gens.resample is not None else gens.propagate
        weights = (w if w is not None else torch.exp(log_w)).detach()
        particles = particles.index_select(0, _systematic_ancestors(weights, gen))
        log_w = torch.full_like(log_w, 0.0 - math.log(n)).detach()
        w = None

    new = _propagate(model, particles, inputs_per_point(u, particles), k, gens.propagate)
    obs = model.observe(new, k + 1)
    if resampled:
        pred_mean = new.mean(0)  # equal weights: the average (no exp, no product)
    else:
        w = w if w is not None else torch.exp(log_w)
        pred_mean = torch.mv(new.mT, w)
    predictive = None
    if pf.innovations:
        pred_w = (torch.exp(log_w) if w is None else w).unsqueeze(0)
        predictive = _predictive(model, y, None, k, obs, pred_w, log_w, pred_mean)

    residual = model.measurement_residual(y, obs)
    increment, log_w_new, w_new, degenerate = _weigh_and_normalise(
        model.measurement_noise, residual, log_w
    )
    if degenerate:  # a NaN particle or density is named, as the general step names it
        log_lik = model.measurement_noise.log_prob(residual)
        _blame_degenerate(pf, new, log_lik, None, log_w, k + 1)
    ess_new = torch.dot(w_new, w_new).reciprocal()
    mean = torch.mv(new.mT, w_new)
    dev = new - mean
    cov = torch.mm(dev.mT * w_new, dev)
    cov = (cov + cov.mT).mul_(0.5)
    extras = {"ess": ess_new, "resampled": need, "degenerate": degenerate}
    out = StepOutput(
        mean, cov, pred_mean, None,
        None if predictive is None else predictive.innovation,
        None if predictive is None else predictive.innovation_cov,
        increment, extras=extras,
    )  # fmt: skip
    new_carry = ParticleState(new, log_w_new, k + 1, ess_new, w_new, model, carry.aux,
                              carry.generators)  # fmt: skip
    return new_carry, out


def _propagate(model, particles: Tensor, u: Tensor | None, k: int, generator) -> Tensor:
    """``f(x, u) + ε`` ``[N, dx]``: the model's :meth:`sample_transition`, its noise drawn in
    line where it is the base class's with a diagonal zero-mean Gaussian (the same draw:
    ``f + σ ⊙ randn``, as :meth:`~difffilter.noise.Gaussian.perturb`)."""
    noise = model.process_noise
    if (
        type(model).sample_transition is StateSpaceModel.sample_transition
        and type(noise) is Gaussian
        and not model._varying_noise("process_cov")
    ):
        _, diag = noise._factor()
        if diag is not None and diag.dim() == 1 and noise._zero_loc():
            mean = model.transition(particles, u, k)
            eps = torch.randn(mean.shape, generator=generator, dtype=diag.dtype, device=diag.device)
            return torch.addcmul(mean, eps, diag)
    return model.sample_transition(particles, u, k, generator)


def _systematic_ancestors(weights: Tensor, generator) -> Tensor:
    """``a_j = F⁻¹((j + U)/N)`` ``[N]`` (int64) for non-negative ``weights [N]``: the targets
    ``(j + U)·W/N`` searched in the cumulative weights (right side, as the general
    resampler's offspring count), clamped to the last particle of positive weight."""
    n = weights.shape[0]
    offset = torch.rand((1,), generator=generator, dtype=weights.dtype, device=weights.device)
    cdf = torch.cumsum(weights, 0)
    total = cdf[-1:]
    targets = torch.arange(n, dtype=weights.dtype, device=weights.device).add_(offset)
    ancestors = torch.searchsorted(cdf, targets.mul_(total.div(n)), right=True)
    # the last particle of positive weight is the number of cdf entries below the total
    return torch.minimum(ancestors, torch.searchsorted(cdf, total))


def _weigh_and_normalise(noise, residual: Tensor, log_w: Tensor):
    """``(increment [], log w_k [N], w_k [N], degenerate [])`` from the residuals ``[N, dy]``
    of the proposed particles and the predictive log-weights ``log_w [N]``.

    The general step's :func:`~difffilter.particle._normalise` of ``log w + log α``; for a
    diagonal zero-mean Gaussian noise the density's constant joins the evidence at the end.
    A degenerate step (every weight underflowed) resets to ``log_w`` as there.
    """
    constant = None
    if type(noise) is Gaussian:
        _, diag = noise._factor()
        if diag is not None and diag.dim() == 1 and noise._zero_loc():
            inv_var, constant = noise._diagonal_terms(diag)
            joint = torch.addmv(log_w, residual.square(), inv_var, alpha=-0.5)
    if constant is None:
        joint = log_w + noise.log_prob(residual)
    top = joint.detach().amax()
    e = torch.exp(joint - top)
    total = e.sum()
    increment = torch.log(total).add_(top)
    log_w_new, w_new = joint - increment, e / total
    if constant is not None:
        increment = increment - constant
    finite = math.isfinite(increment.item())
    if not finite:
        increment = torch.logsumexp(joint, dim=-1)
        if constant is not None:
            increment = increment - constant
        log_w_new, w_new = log_w, torch.exp(log_w)
    return increment, log_w_new, w_new, torch.tensor(not finite, device=increment.device)
