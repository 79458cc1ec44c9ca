"""Particle filter with pluggable proposal, likelihood and resampler.

One step ``k−1 → k`` (weights in log space throughout)::

    resample   if ESS_{k−1} < ess_threshold · N: (x, log w) ← resampler(x, log w)
    propose    x_k^i ~ q(· | x_{k−1}^i, y_k),      c^i = log p(x_k^i | x_{k−1}^i) − log q(x_k^i | ·)
    weight     log α^i = log p(y_k | x_k^i) + c^i
    evidence   log p̂(y_k | y_{1:k−1}) = logsumexp_i(log w^i + log α^i)        (log w normalised)
    normalise  log w_k^i = log w^i + log α^i − log p̂(y_k | y_{1:k−1})

**Degenerate steps.** When every ``log w^i + log α^i`` of a run is ``−inf`` (a measurement
so far from every particle that its likelihood underflows, e.g. one reading of 1e19 on
a float32 model), the normalisation is ``−inf − (−inf) = NaN`` and would poison the run
forever. Policy: that run's weights are reset to the predictive weights (``w^i`` times
the proposal correction, normalised; uniform after resampling), the particles are kept,
the step is flagged in ``degenerate`` (step output and filter result), its evidence
increment stays ``−inf`` (the measurement had numerically zero likelihood: the
log-likelihood says so rather than hiding it), and filtering continues.

The bootstrap proposal is the transition (``c = 0``). ``log p̂(y_{1:T})`` is the sum of
the increments; it is unbiased for ``p(y_{1:T})`` with multinomial-type resampling.
Gradients flow through reparameterised proposals and the weights; whether they flow
through resampling depends on the resampler (``Soft``, ``StopGradient``,
``OptimalTransport`` are differentiable). Everything is vectorised over runs and
particles; the time loop is the only Python loop.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple, Protocol

import torch
from torch import Tensor

from ._checks import (
    check_ess_threshold,
    check_positive_int,
    check_step_inputs,
    check_strategy,
)
from ._steps import StepRecorder
from .kalman import _validate_inputs, gaussian_update
from .linalg import (
    gaussian_log_prob_chol,
    masked_measurement,
    matvec,
    rowwise,
    safe_cholesky,
    symmetrize,
)
from .resampling import Resampler, Systematic, keep_unmarked_rows
from .results import ParticleFilterResult
from .ssm import StateSpaceModel

# the resampler base class's hook: uniform log-weights −log N after resampling
_UNIFORM = Resampler._new_log_weights

__all__ = [
    "ParticleState",
    "ParticleStepOutput",
    "Predictive",
    "Proposal",
    "Likelihood",
    "BootstrapProposal",
    "KalmanProposal",
    "kalman_proposal_moments",
    "ModelLikelihood",
    "particle_init",
    "particle_step",
    "particle_filter",
    "weighted_moments",
]


class ParticleState(NamedTuple):
    """Online state: particles ``[..., N, dx]`` and normalised log-weights ``[..., N]`` of ``x_k``.

    ``ess [...]`` caches the effective sample size of ``log_weights`` and ``weights [..., N]``
    their exponential ``w = exp(log_weights)`` (``None``: compute them when needed).
    """

    particles: Tensor
    log_weights: Tensor
    k: int = 0
    ess: Tensor | None = None
    weights: Tensor | None = None


class ParticleStepOutput(NamedTuple):
    """Per-step report: ``mean [..., dx]``, ``cov [..., dx, dx]``, the predicted state mean
    ``pred_mean = E[x_k | y_{1:k−1}]`` ``[..., dx]``, ``innovation = y − E[h(x_k) | y_{1:k−1}]``
    ``[..., dy]`` and its covariance (particle covariance of ``h`` plus ``R``) ``[..., dy, dy]``
    (both ``None`` for a step asked for no ``innovations``), ``log_likelihood`` increment
    ``[...]``, ``ess [...]`` after weighting, ``resampled [...]`` (bool), the normalised
    predictive log-weights ``log w_{k−1}`` of the proposed particles ``[..., N]`` and
    ``degenerate [...]`` (bool: every weight of the run underflowed and was reset to the
    predictive weights, see the module docstring)."""

    mean: Tensor
    cov: Tensor
    pred_mean: Tensor
    innovation: Tensor
    innovation_cov: Tensor
    log_likelihood: Tensor
    ess: Tensor
    resampled: Tensor
    prior_log_weights: Tensor
    degenerate: Tensor | None = None


class Predictive(NamedTuple):
    """The predictive view of a step, before weighting (what attack-aware likelihoods read).

    ``log_weights`` ``log w_{k−1}`` of the proposed particles ``[..., N]`` (normalised),
    ``mean`` ``E[x_k | y_{1:k−1}]`` ``[..., dx]``, ``innovation`` ``y_k − E[h(x_k) | y_{1:k−1}]``
    ``[..., dy]`` (zero where unreceived) and its covariance ``[..., dy, dy]``.
    """

    log_weights: Tensor
    mean: Tensor
    innovation: Tensor
    innovation_cov: Tensor


class Proposal(Protocol):
    """A proposal ``q(x_k | x_{k−1}, y_k)``.

    ``__call__(model, particles [..., N, dx], u [..., du] | None, y [..., dy], k, mask,
    generator)`` returns ``(new_particles [..., N, dx], log_correction [..., N])`` with
    ``log_correction = log p(x_k | x_{k−1}) − log q(x_k | x_{k−1}, y_k)`` (``None`` means
    zero: the bootstrap proposal); ``k`` is the index of the state being propagated
    (``x_k → x_{k+1}``).
    """

    def __call__(self, model, particles, u, y, k, mask, generator) -> tuple[Tensor, Tensor]: ...


class Likelihood(Protocol):
    """A measurement log-likelihood: ``(model, y [..., dy], particles [..., N, dx], k, mask
    [..., dy] | None) → log p(y_k | x_k^i)`` ``[..., N]``.

    A likelihood with ``uses_predictive = True`` is also passed ``predictive=``, the step's
    :class:`Predictive` (predictive weights and moments): the hook through which the
    attack-aware filters (the modified PF's detection and compensation) decide how to
    weigh the particles.
    """

    def __call__(self, model, y, particles, k, mask) -> Tensor: ...


StepHook = Callable[..., dict]


class BootstrapProposal:
    """``q = p(x_k | x_{k−1})``: propagate through the model; zero correction (``None``)."""

    def __call__(self, model, particles, u, y, k, mask, generator):
        u = None if u is None else u.unsqueeze(-2)
        return model.sample_transition(particles, u, k, generator), None


class KalmanProposal:
    """Locally linearised optimal proposal (FastSLAM 2.0; eqs 35–36 of the modified-PF paper).

    With ``f = f(x_{k−1}, u)``, ``H = ∂h/∂x(f)``, ``S = H Q Hᵀ + R``, ``K = Q Hᵀ S⁻¹``::

        q = N(μ, Σ),   μ = f + K (y − h(f)),   Σ = (I − KH) Q (I − KH)ᵀ + K R Kᵀ

    (the moments are :func:`kalman_proposal_moments`, one :func:`~difffilter.kalman.
    gaussian_update` per particle) and ``log_correction = log N(x; f, Q) − log q(x)``, so
    the weights target the same posterior as the bootstrap filter. On a linear-Gaussian
    measurement this is the exact optimal proposal (incremental weights ``N(y; H f, S)``).
    Requires a Gaussian process noise (``model.process_cov``).

    Args:
        defensive: weight ``ρ ∈ [0, 1)`` of the prior in a defensive mixture
            ``q = (1 − ρ) N(μ, Σ) + ρ N(f, Q)`` (default 0: the plain Kalman proposal).
            With ``ρ > 0`` a measurement that the likelihood will discount (a replaced
            packet) cannot drag every particle; each particle draws one extra uniform to
            pick its component.
    """

    def __init__(self, defensive: float = 0.0):
        rho = float(defensive)
        if not 0.0 <= rho < 1.0:
            raise ValueError(f"defensive must lie in [0, 1); got {defensive!r}")
        self.rho = rho

    def __call__(self, model, particles, u, y, k, mask, generator):
        f, Q, mu, sigma = kalman_proposal_moments(model, particles, u, y, k, mask)
        chol_sigma = safe_cholesky(sigma, name="proposal covariance")
        chol_q = safe_cholesky(Q, name="Q")
        eps = torch.randn(mu.shape, generator=generator, dtype=mu.dtype, device=mu.device)
        if self.rho == 0:
            new = mu + matvec(chol_sigma, eps)
            log_q = gaussian_log_prob_chol(new - mu, chol_sigma)
            return new, gaussian_log_prob_chol(new - f, chol_q) - log_q
        u_pick = torch.rand(mu.shape[:-1], generator=generator, dtype=mu.dtype, device=mu.device)
        prior = (u_pick < self.rho).unsqueeze(-1)
        new = torch.where(prior, f + matvec(chol_q, eps), mu + matvec(chol_sigma, eps))
        log_p = gaussian_log_prob_chol(new - f, chol_q)
        log_kalman = gaussian_log_prob_chol(new - mu, chol_sigma)
        log_q = torch.logaddexp(log_kalman + math.log1p(-self.rho), log_p + math.log(self.rho))
        return new, log_p - log_q


def kalman_proposal_moments(
    model, particles: Tensor, u: Tensor | None, y: Tensor, k: int, mask: Tensor | None
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Moments of the Kalman proposal of every particle: ``(f, Q, μ, Σ)``.

    ``f = f(x_{k−1}, u) [..., N, dx]`` and ``Q [dx, dx]`` (the transition), ``μ [..., N, dx]``
    and ``Σ [..., N, dx, dx]``: one :func:`~difffilter.kalman.gaussian_update` of the prior
    ``N(f, Q)`` with ``y [..., dy]`` on the received entries (``mask [..., dy]``), ``H`` the
    model's ``observation_matrix`` when it has one (one gain for every particle) and its
    Jacobian at ``f`` otherwise; the residual is the model's (a wrapped bearing stays
    wrapped). ``u [..., du]`` or ``None``.
    """
    u = None if u is None else u.unsqueeze(-2)
    f = model.transition(particles, u, k)
    Q = model.process_cov(k)
    if hasattr(model, "observation_matrix"):
        H = model.observation_matrix(k + 1)
    else:
        H = model.observation_jacobian(f, k + 1)
    residual = model.measurement_residual(y.unsqueeze(-2), model.observe(f, k + 1))
    m = None if mask is None else mask.unsqueeze(-2)
    residual, H, R, observed = masked_measurement(residual, H, model.measurement_cov(k + 1), m)
    cross = Q @ H.transpose(-1, -2)
    mu, sigma, _, _ = gaussian_update(f, Q, residual, cross, H @ cross, H, R, observed)
    return f, Q, mu, sigma


class ModelLikelihood:
    """The model's own measurement density ``log p(y | x)`` (``model.measurement_log_prob``)."""

    def __call__(self, model, y, particles, k, mask):
        m = None if mask is None else mask.unsqueeze(-2)
        return model.measurement_log_prob(y.unsqueeze(-2), particles, k, m)


def weighted_moments(particles: Tensor, log_weights: Tensor) -> tuple[Tensor, Tensor]:
    """Weighted mean ``[..., d]`` and covariance ``[..., d, d]`` of ``particles [..., N, d]``.

    ``mean = Σ wᵢ xᵢ``, ``cov = Σ wᵢ (xᵢ − mean)(xᵢ − mean)ᵀ`` with ``w = softmax(log_weights)``.
    """
    return _moments(particles, torch.softmax(log_weights, dim=-1))


def _ess(log_weights: Tensor) -> Tensor:
    return torch.exp(-torch.logsumexp(2.0 * log_weights, dim=-1))


def particle_init(
    model: StateSpaceModel,
    num_particles: int,
    batch_shape=(),
    generator: torch.Generator | None = None,
) -> ParticleState:
    """Draw ``N`` particles from the prior: ``[*batch_shape, N, dx]``, log-weights ``−log N``."""
    check_positive_int(num_particles, "num_particles")
    batch_shape = torch.Size(batch_shape)
    particles = model.sample_initial(batch_shape + (num_particles,), generator)
    log_w = particles.new_full(batch_shape + (num_particles,), -math.log(num_particles))
    return ParticleState(particles, log_w, 0)


def particle_step(
    model: StateSpaceModel,
    state: ParticleState,
    y: Tensor,
    u: Tensor | None = None,
    mask: Tensor | None = None,
    *,
    resampler: Resampler | None = None,
    proposal: Proposal | None = None,
    likelihood: Likelihood | None = None,
    ess_threshold: float = 0.5,
    generator: torch.Generator | None = None,
    resample_generator: torch.Generator | None = None,
    innovations: bool = True,
    cov_dims: int | None = None,
) -> tuple[ParticleState, ParticleStepOutput]:
    """One particle-filter step ``x_{k−1} → x_k`` with measurement ``y_k [..., dy]``.

    Args as in :func:`particle_filter`; ``u [..., du]``, ``mask [..., dy]``. The inputs
    are validated as in :func:`difffilter.kalman_step` (a NaN or Inf in a received entry
    of ``y`` raises). Returns the new :class:`ParticleState` and a
    :class:`ParticleStepOutput`.
    """
    y, u, mask = check_step_inputs(model, state.particles, y, u, mask)
    ess_threshold = _check_strategies(resampler, proposal, likelihood, ess_threshold)
    return _particle_step(
        model,
        state,
        y,
        u,
        mask,
        resampler=resampler,
        proposal=proposal,
        likelihood=likelihood,
        ess_threshold=ess_threshold,
        generator=generator,
        resample_generator=resample_generator,
        innovations=innovations,
        cov_dims=_check_cov_dims(cov_dims, state.particles.shape[-1]),
    )


def _check_cov_dims(cov_dims, dim: int) -> int | None:
    if cov_dims is None:
        return None
    if isinstance(cov_dims, bool) or not isinstance(cov_dims, int) or not 1 <= cov_dims <= dim:
        raise ValueError(f"cov_dims must be None or an integer in [1, {dim}]; got {cov_dims!r}")
    return None if cov_dims == dim else cov_dims


def _check_strategies(resampler, proposal, likelihood, ess_threshold) -> float:
    check_strategy(resampler, "resampler", "difffilter.resampling.Systematic()")
    check_strategy(proposal, "proposal", "difffilter.BootstrapProposal()")
    check_strategy(likelihood, "likelihood", "difffilter.ModelLikelihood()")
    return check_ess_threshold(ess_threshold)


def _particle_step(
    model,
    state,
    y,
    u=None,
    mask=None,
    *,
    resampler=None,
    proposal=None,
    likelihood=None,
    ess_threshold=0.5,
    generator=None,
    resample_generator=None,
    innovations=True,
    cov_dims=None,
):
    """:func:`particle_step` without input validation (the filter validates whole sequences)."""
    resampler = resampler if resampler is not None else Systematic()
    proposal = proposal if proposal is not None else BootstrapProposal()
    likelihood = likelihood if likelihood is not None else ModelLikelihood()
    particles, log_w, k, ess, w = state
    n = particles.shape[-2]

    # Resample the rows whose ESS fell below the threshold.
    need = (_ess(log_w) if ess is None else ess) < ess_threshold * n
    count = int(need.sum())
    uniform = False  # whether the weights are now exactly −log N in every row
    if count:
        gen = resample_generator if resample_generator is not None else generator
        rows = None if count == need.numel() else need
        # weights here are normalised and finite by construction: skip re-validation
        fast = getattr(resampler, "resample_normalized", None)
        if fast is None:  # a user resampler with only __call__
            res = resampler(particles, log_w, gen)
            if rows is not None:
                res = keep_unmarked_rows(res, particles, log_w, rows)
        elif type(resampler).resample_normalized is Resampler.resample_normalized:
            # the library's index resamplers also take the weights this step has (no exp)
            res = fast(particles, log_w, gen, rows=rows, weights=w)
            uniform = rows is None and type(resampler)._new_log_weights is _UNIFORM
        else:
            res = fast(particles, log_w, gen, rows=rows)
        particles, log_w, w = res.particles, res.log_weights, None

    new, correction = proposal(model, particles, u, y, k, mask, generator)

    # Predictive weights of the proposed particles: w_{k−1}·p/q (just w_{k−1} for the
    # bootstrap proposal, whose correction is None), and the predictive moments.
    prior_lw = log_w if correction is None else torch.log_softmax(log_w + correction, dim=-1)
    uses_predictive = getattr(likelihood, "uses_predictive", False)
    obs = predictive = None
    pred_w = None
    if correction is None and uniform:
        # equal weights: the predicted mean is the particles' average (no exp, no product)
        pred_mean = new.mean(-2)
    else:
        pred_w = (w if correction is None and w is not None else torch.exp(prior_lw)).unsqueeze(-2)
        pred_mean = (pred_w @ new).squeeze(-2)  # [..., 1, N] @ [..., N, dx]
    if innovations or uses_predictive:
        pred_w = torch.exp(prior_lw).unsqueeze(-2) if pred_w is None else pred_w
        obs = model.observe(new, k + 1)
        predictive = _predictive(model, y, mask, k, obs, pred_w, prior_lw, pred_mean)

    if type(likelihood) is ModelLikelihood and _default_measurement_density(model):
        # the model's own density: reuse the predicted measurements computed above
        obs = model.observe(new, k + 1) if obs is None else obs
        m = None if mask is None else mask.unsqueeze(-2)
        log_alpha = model.measurement_noise.log_prob(
            model.measurement_residual(y.unsqueeze(-2), obs), mask=m
        )
    elif uses_predictive:
        log_alpha = likelihood(model, y, new, k + 1, mask, predictive=predictive)
    else:
        log_alpha = likelihood(model, y, new, k + 1, mask)
    if correction is not None:
        log_alpha = log_alpha + correction
    joint = log_w + log_alpha
    # logsumexp by hand, keeping its exponentials: e = exp(joint − max) gives the new weights
    # e / Σe and the increment log Σe + max without a second exp pass
    top = joint.detach().amax(-1, keepdim=True)
    e = torch.exp(joint - top)
    total = e.sum(-1, keepdim=True)
    increment = (torch.log(total) + top).squeeze(-1)
    log_w_new = joint - increment.unsqueeze(-1)
    w_new = e / total
    # Degenerate runs (every joint weight −inf, or NaN): reset to the predictive weights
    # (module docstring). One host sync per step; the reset itself only when needed.
    degenerate = ~torch.isfinite(increment)
    if bool(degenerate.any()):
        increment = torch.logsumexp(joint, dim=-1)  # −inf (not NaN) where all are −inf
        log_w_new = torch.where(degenerate.unsqueeze(-1), prior_lw, log_w_new)
        w_new = torch.exp(log_w_new)
    ess_new = torch.linalg.vecdot(w_new, w_new).reciprocal()
    mean, cov = _moments(new, w_new, cov_dims)
    out = ParticleStepOutput(
        mean=mean,
        cov=cov,
        pred_mean=pred_mean,
        innovation=None if predictive is None else predictive.innovation,
        innovation_cov=None if predictive is None else predictive.innovation_cov,
        log_likelihood=increment,
        ess=ess_new,
        resampled=need,
        prior_log_weights=prior_lw,
        degenerate=degenerate,
    )
    return ParticleState(new, log_w_new, k + 1, ess_new, w_new), out


def _predictive(model, y, mask, k, obs, pred_w, prior_lw, pred_mean) -> Predictive:
    """The step's :class:`Predictive` from the predicted measurements ``obs [..., N, dy]``."""
    y_hat = (pred_w @ obs).squeeze(-2)
    obs_dev = rowwise(torch.sub, obs, y_hat.unsqueeze(-2))
    y_cov = (obs_dev * pred_w.transpose(-1, -2)).transpose(-1, -2) @ obs_dev
    innovation = model.measurement_residual(y, y_hat)
    R = model.measurement_cov(k + 1)
    if mask is not None:
        eye = torch.eye(R.shape[-1], dtype=R.dtype, device=R.device)
        innovation, _, R, _ = masked_measurement(innovation, eye, R, mask)
        mf = mask.to(y_cov.dtype)
        y_cov = y_cov * (mf.unsqueeze(-1) * mf.unsqueeze(-2))
    return Predictive(prior_lw, pred_mean, innovation, symmetrize(y_cov + R))


def _default_measurement_density(model: StateSpaceModel) -> bool:
    """Whether ``model.measurement_log_prob`` is the base class's ``log p(y − h(x))``."""
    return type(model).measurement_log_prob is StateSpaceModel.measurement_log_prob


def _moments(
    particles: Tensor, weights: Tensor, cov_dims: int | None = None
) -> tuple[Tensor, Tensor]:
    """Mean ``[..., d]`` and covariance ``[..., c, c]`` of ``particles [..., N, d]`` under
    normalised ``weights [..., N]``; the covariance of the first ``c = cov_dims``
    components (default all ``d``)."""
    w = weights.unsqueeze(-2)
    mean = (w @ particles).squeeze(-2)
    # deviations laid out [..., c, N]: the subtraction and the weighting then broadcast
    # along the long particle axis (a short last axis runs ~2x slower on CPU); no copy
    # for component-major particles ([..., d, N] in memory)
    rows, centre = particles.transpose(-1, -2), mean.unsqueeze(-1)
    if cov_dims is not None:
        rows, centre = rows[..., :cov_dims, :], centre[..., :cov_dims, :]
    dev = rows.contiguous() - centre
    cov = (dev * w) @ dev.transpose(-1, -2)
    return mean, symmetrize(cov)


def particle_filter(
    model: StateSpaceModel,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    num_particles: int,
    resampler: Resampler | None = None,
    proposal: Proposal | None = None,
    likelihood: Likelihood | None = None,
    mask: Tensor | None = None,
    ess_threshold: float = 0.5,
    generator: torch.Generator | None = None,
    resample_generator: torch.Generator | None = None,
    return_particles: bool = False,
    initial_state: ParticleState | None = None,
    hooks: Sequence[StepHook] = (),
    nonfinite: str = "raise",
    innovations: bool = True,
    cov_dims: int | None = None,
) -> ParticleFilterResult:
    """Particle filter over a whole sequence.

    Args:
        model: any :class:`~difffilter.StateSpaceModel`.
        ys: measurements ``[..., T, dy]``; us: inputs ``[..., T, du]`` or ``None``.
        num_particles: ``N ≥ 1``.
        resampler: a :mod:`difffilter.resampling` object (default ``Systematic()``).
        proposal: default :class:`BootstrapProposal`; :class:`KalmanProposal` is the
            locally linearised optimal proposal.
        likelihood: default :class:`ModelLikelihood`; any callable
            ``(model, y, particles, k, mask) → [..., N]``.
        mask: received measurement entries ``[..., T, dy]`` or ``None``.
        ess_threshold: resample when ``ESS < ess_threshold · N`` (``1.0`` resamples
            at every step with non-uniform weights, ``0`` never: plain SIS).
        generator: source of every random draw (prior, proposal; resampling too unless
            ``resample_generator`` is given — separate streams keep common random numbers
            aligned across estimators).
        return_particles: also return particles ``[..., T, N, dx]`` and log-weights
            ``[..., T, N]`` (memory ``O(T N)``).
        initial_state: start from this :class:`ParticleState` instead of the prior.
        hooks: callables ``hook(model, y, mask, state, out) → {name: tensor [...]}`` run
            after every step (``state``: the new :class:`ParticleState`, ``out``: its
            :class:`ParticleStepOutput`); their values are stacked over time into
            ``result.records[name]`` ``[..., T, ...]`` — what a detector needs, without
            keeping every particle (``return_particles``).
        nonfinite: ``"raise"`` (default) or ``"skip"``, as in
            :func:`difffilter.kalman_filter` (skipped entries are counted in
            ``nonfinite_skipped``).
        innovations: compute the predictive measurement moments (``innovations``,
            ``innovation_covs``); ``False`` skips them (both ``None`` in the result and
            the step outputs) unless the likelihood reads them (``uses_predictive``): a
            filter whose caller needs only the state estimates saves ``h`` of every
            particle on every measurement entry per step.
        cov_dims: ``covs`` (and each step's ``cov``) of the first ``cov_dims`` particle
            components only, ``[..., T, c, c]`` (default ``None``: all ``dx``); the means
            keep every component. For particles that carry more than the state (the
            per-particle Kalman statistics of :mod:`difffilter.fdi.mdpf`), whose
            covariance nobody reads: a ``dx × dx`` covariance costs ``O(N dx²)`` per run.

    Inputs are validated first (:func:`difffilter._checks.check_sequence_inputs`);
    ``resampler``, ``proposal`` and ``likelihood`` must be objects, not strings. A step
    at which every weight of a run underflows is recovered and flagged in
    ``degenerate`` (module docstring).

    Returns:
        :class:`~difffilter.results.ParticleFilterResult`: weighted means ``[..., T, dx]``,
        covariances, innovations and their covariances, ``log_likelihood [...]`` (the
        particle estimate), ``ess [..., T]``, ``resampled [..., T]``, ``degenerate [..., T]``.
    """
    check_positive_int(num_particles, "num_particles")
    ess_threshold = _check_strategies(resampler, proposal, likelihood, ess_threshold)
    ys, us, mask, skipped = _validate_inputs(model, ys, us, mask, nonfinite)
    batch = ys.shape[:-2]
    if us is not None:
        batch = torch.broadcast_shapes(batch, us.shape[:-2])
    state = (
        initial_state
        if initial_state is not None
        else particle_init(model, num_particles, batch, generator)
    )
    step_options = {
        "resampler": resampler,
        "proposal": proposal,
        "likelihood": likelihood,
        "ess_threshold": ess_threshold,
        "generator": generator,
        "resample_generator": resample_generator,
        "innovations": innovations,
        "cov_dims": _check_cov_dims(cov_dims, state.particles.shape[-1]),
    }
    outs, parts, logws, records = [], [], [], StepRecorder()
    for t in range(ys.shape[-2]):
        u = None if us is None else us[..., t, :]
        m = None if mask is None else mask[..., t, :]
        y = ys[..., t, :]  # one view: the step and its hooks see the same tensor
        state, out = _particle_step(model, state, y, u, m, **step_options)
        outs.append(out)
        for hook in hooks:
            records.add(**hook(model, y, m, state, out))
        if return_particles:
            parts.append(state.particles)
            logws.append(state.log_weights)

    def stack(name, dims):
        return torch.stack([getattr(o, name) for o in outs], dim=-1 - dims)

    increments = stack("log_likelihood", 0)
    return ParticleFilterResult(
        means=stack("mean", 1),
        covs=stack("cov", 2),
        pred_means=stack("pred_mean", 1),
        pred_covs=None,
        innovations=stack("innovation", 1) if innovations else None,
        innovation_covs=stack("innovation_cov", 2) if innovations else None,
        log_likelihood_increments=increments,
        log_likelihood=increments.sum(-1),
        ess=stack("ess", 0),
        resampled=stack("resampled", 0),
        degenerate=stack("degenerate", 0),
        nonfinite_skipped=skipped,
        particles=torch.stack(parts, dim=-3) if return_particles else None,
        log_weights=torch.stack(logws, dim=-2) if return_particles else None,
        records=records.stack(len(batch)),
    )
