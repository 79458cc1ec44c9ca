"""Particle filter with pluggable proposal, likelihood and resampler.

One step ``k−1 → k`` (weights in log space throughout)::

    resample   if ESS_{k−1} < ess_threshold · N: (x, log w) ← resampler(x, log w)
    propose    x_k^i ~ q(· | x_{k−1}^i, y_k),      c^i = log p(x_k^i | x_{k−1}^i) − log q(x_k^i | ·)
    weight     log α^i = log p(y_k | x_k^i) + c^i
    evidence   log p̂(y_k | y_{1:k−1}) = logsumexp_i(log w^i + log α^i)        (log w normalised)
    normalise  log w_k^i = log w^i + log α^i − log p̂(y_k | y_{1:k−1})

**Degenerate steps.** When every ``log w^i + log α^i`` of a run is ``−inf`` (a measurement
so far from every particle that its log-likelihood overflows, e.g. one reading of 1e20
on a float32 model with noise of order one; at 1e19 it is still a finite −5e37 and the
step is not flagged), the normalisation is ``−inf − (−inf) = NaN`` and would poison the run
forever. Policy: that run's weights are reset to the predictive weights (``w^i`` times
the proposal correction, normalised; uniform after resampling), the particles are kept,
the step is flagged in ``degenerate`` (step output and filter result), its evidence
increment stays ``−inf`` (the measurement had numerically zero likelihood: the
log-likelihood says so rather than hiding it), and filtering continues. A collapse
without underflow (one particle holding nearly all the weight at every step, under a
likelihood much narrower than the cloud) is not flagged: the ``ess`` output shows it.

The bootstrap proposal is the transition (``c = 0``). ``log p̂(y_{1:T})`` is the sum of
the increments; it is unbiased for ``p(y_{1:T})`` with resampling that keeps every
offspring count's mean ``N w_i`` and uniform new weights (multinomial, systematic,
stratified, residual, stop-gradient), not with ``Soft``, whose new weights are
self-normalised (a resampler trial: E[p̂/p] = 1.015 ± 0.002 with ``Soft(0.5)``, N = 4,
T = 5).
Gradients flow through reparameterised proposals and the weights; whether they flow
through resampling depends on the resampler (``Soft``, ``StopGradient``,
``OptimalTransport`` are differentiable). Everything is vectorised over runs and
particles; the time loop is the only Python loop.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple, Protocol

import torch
from torch import Tensor

from ._assignments import note_assignment
from ._checks import (
    NonFinite,
    broadcast_shapes,
    check_batch_shape,
    check_callable_as,
    check_carry_fits_model,
    check_carry_tensor,
    check_ess_threshold,
    check_fraction,
    check_model,
    check_one_model,
    check_positive_int,
    check_strategy,
    first_index,
)
from .estimator import Estimator, Generators
from .gaussian import gaussian_update
from .linalg import (
    gaussian_log_prob_chol,
    masked_measurement,
    matvec,
    rowwise,
    safe_cholesky,
    symmetrize,
)
from .loop import open_loop
from .noise import Gaussian
from .resampling import (
    Resampler,
    Systematic,
    _AncestorError,
    check_resampler_hooks,
    defined_outside,
    effective_sample_size,
    keep_unmarked_rows,
)
from .results import ParticleFilterResult, StepOutput
from .ssm import StateSpaceModel, inputs_per_point, plain_residual, wrapped_spread

# the resampler base class's hook: uniform log-weights −log N after resampling
_UNIFORM = Resampler._new_log_weights

__all__ = [
    "ParticleState",
    "ParticleFilter",
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
    """Online state (the carry): particles ``[..., N, dx]`` and normalised log-weights
    ``[..., N]`` of ``x_k``.

    ``ess [...]`` caches the effective sample size of ``log_weights`` and ``weights [..., N]``
    their exponential ``w = exp(log_weights)`` (``None``: compute them when needed).
    ``model`` is the model being filtered, ``aux`` the state of a stateful likelihood
    (:class:`StepLikelihood`: a detector's running statistics, a network's histories),
    ``generators`` the :class:`~difffilter.estimator.Generators` the steps draw from.
    """

    particles: Tensor
    log_weights: Tensor
    k: int = 0
    ess: Tensor | None = None
    weights: Tensor | None = None
    model: Any = None
    aux: Any = None
    generators: Any = None


#: The particle filter's step output: the one :class:`~difffilter.results.StepOutput`
#: (``innovation``/``innovation_cov`` ``None`` for a step asked for no ``innovations``),
#: with ``extras`` ``"ess" [...]`` after weighting, ``"resampled" [...]`` (bool),
#: ``"degenerate" [...]`` (bool: every weight of the run underflowed and was reset to the
#: predictive weights, see the module docstring), ``"prior_log_weights" [..., N]`` (the
#: normalised predictive log-weights ``log w_{k−1}`` of the proposed particles; with
#: ``record_prior=True``) and what the likelihood and hooks recorded.
ParticleStepOutput = StepOutput


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
    [..., dy] | None) → log p(y_k | x_k^i)`` ``[..., N]``, one per run and particle (summed
    over the received entries), in the particles' dtype, finite or ``−inf`` (a zero
    density); ``k`` is the index of the measurement (the proposal's ``k`` plus one). The
    step checks the shape and dtype at every step, and names the likelihood where a NaN or
    ``+inf`` makes a step degenerate (it was taken for an underflow, the measurement
    dropped).

    A likelihood with ``uses_predictive = True`` is also passed ``predictive=``, the step's
    :class:`Predictive` (predictive weights and moments): the hook through which the
    attack-aware filters (the modified PF's detection and compensation) decide how to
    weigh the particles.
    """

    def __call__(self, model, y, particles, k, mask) -> Tensor: ...


class StepLikelihood(Protocol):
    """A likelihood with state (in the carry's ``aux``) that reads the step's predictive view.

    ``init(model, batch_shape, dtype, device) -> state`` and ``weigh(state, model, y [...,
    dy], particles [..., N, dx], k, mask, predictive) -> (state, log p [..., N], record)``
    with ``record`` a ``{name: tensor [...]}`` that the step reports in its ``extras``.
    The attack-aware filters decide with it, step by step, whether and how to discount a
    measurement (the modified PF's detection and compensation, the learned estimator).
    """

    def init(self, model, batch_shape, dtype, device) -> Any: ...

    def weigh(
        self, state, model, y, particles, k, mask, predictive
    ) -> tuple[Any, Tensor, dict]: ...


StepHook = Callable[..., dict]


class BootstrapProposal:
    """``q = p(x_k | x_{k−1})``: propagate through the model; zero correction (``None``)."""

    def __call__(self, model, particles, u, y, k, mask, generator):
        return model.sample_transition(
            particles, inputs_per_point(u, particles), k, generator
        ), None


class KalmanProposal:
    """Locally linearised optimal proposal (FastSLAM 2.0; eqs 35–36 of the modified-PF paper).

    With ``f = f(x_{k−1}, u)``, ``H = ∂h/∂x(f)``, ``S = H Q Hᵀ + R``, ``K = Q Hᵀ S⁻¹``::

        q = N(μ, Σ),   μ = f + K (y − h(f)),   Σ = (I − KH) Q (I − KH)ᵀ + K R Kᵀ

    (the moments are :func:`kalman_proposal_moments`, one :func:`~difffilter.kalman.
    gaussian_update` per particle) and ``log_correction = log N(x; f, Q) − log q(x)``, so
    the weights target the same posterior as the bootstrap filter. On a linear-Gaussian
    measurement this is the exact optimal proposal (incremental weights ``N(y; H f, S)``).
    Requires a Gaussian process noise (``model.process_cov``; another is refused), whose
    mean joins ``f``, and a model that draws its transitions so: one that overrides
    ``sample_transition`` is refused unless it declares ``samples_process_noise = True``
    (the robot draws ``f + B(θ) n`` from its inputs' noise: the weights had targeted
    ``N(f, Q)``'s posterior, 4 nats from the bootstrap filter's).

    The filter's predictive outputs (``pred_means``, ``innovations``, ``innovation_covs``)
    weigh particles drawn near the measurement by ``p/q``: consistent, but with
    heavy-tailed weights, so they converge far more slowly than the bootstrap filter's (a
    user trial, 2-D linear model: ``pred_means`` RMS error 0.105 / 0.074 / 0.084 against
    the Kalman filter at N = 10³ / 10⁴ / 10⁵, the bootstrap's 0.024 / 0.0073 / 0.0022; the
    posterior means converge as the bootstrap's). A χ² test on a particle filter's
    innovations wants the bootstrap proposal.

    Args:
        defensive: weight ``ρ ∈ [0, 1)`` of the prior in a defensive mixture
            ``q = (1 − ρ) N(μ, Σ) + ρ N(f, Q)`` (default 0: the plain Kalman proposal).
            With ``ρ > 0`` a measurement that the likelihood will discount (a replaced
            packet) cannot drag every particle; each particle draws one extra uniform to
            pick its component.
    """

    def __init__(self, defensive: float = 0.0):
        self.rho = defensive

    def __setattr__(self, name, value):
        # checked whenever set: ρ = 1 assigned later had stopped the first step on a bare
        # "math domain error" (a red-team trial)
        if name == "rho":
            value = check_fraction(value, "defensive (rho)")
        super().__setattr__(name, value)

    def __call__(self, model, particles, u, y, k, mask, generator):
        noise = getattr(model, "process_noise", None)
        if noise is not None and not isinstance(noise, Gaussian):
            # its weights p/q take p = N(f, Q): with another noise they target another model
            raise ValueError(
                f"KalmanProposal needs a Gaussian process noise; model.process_noise is a "
                f"{type(noise).__name__}: use the bootstrap proposal (the default)"
            )
        why = transition_law_unsaid(model)
        if why:
            raise ValueError(f"KalmanProposal: {why}: use the bootstrap proposal (the default)")
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

    ``f = f(x_{k−1}, u) + E[w_k] [..., N, dx]`` (the prior mean: a process noise of nonzero
    mean had been left out, 32 nats off the Kalman filter) and ``Q [dx, dx]`` (the
    transition), ``μ [..., N, dx]`` and ``Σ`` (``[..., N, dx, dx]``, or broadcastable to
    it: one ``[dx, dx]`` for a linear model): one :func:`~difffilter.kalman.gaussian_update` of the prior
    ``N(f, Q)`` with ``y [..., dy]`` on the received entries (``mask [..., dy]``), ``H`` the
    model's ``observation_matrix`` when it has one (one gain for every particle) and its
    Jacobian at ``f`` otherwise; the residual is the model's (a wrapped bearing stays
    wrapped). ``u [..., du]`` or ``None``.
    """
    f = model.transition(particles, inputs_per_point(u, particles), k)
    noise = model.process_noise_at(k)
    if isinstance(noise, Gaussian) and not noise._zero_loc():
        f = f + noise.mean.unsqueeze(-2)
    Q = model.process_cov(k)
    if hasattr(model, "observation_matrix"):
        H = model.observation_matrix(k + 1)
    else:
        H = model.observation_jacobian(f, k + 1)
    residual = model.measurement_residual(y.unsqueeze(-2), model.observe(f, k + 1))
    R = model.measurement_cov(k + 1)
    keep, m = _shared_received(mask), None
    if keep is not None:  # every run receives the same entries: update on those alone
        if keep.numel() == 0:
            return f, Q, f, Q.expand(f.shape + f.shape[-1:])
        residual, H = residual.index_select(-1, keep), H.index_select(-2, keep)
        R, observed = R.index_select(-1, keep).index_select(-2, keep), keep.numel()
    else:
        m = None if mask is None else mask.unsqueeze(-2)
        residual, H, R, observed = masked_measurement(residual, H, R, m)
    cross = Q @ H.transpose(-1, -2)
    mu, sigma, _, _ = gaussian_update(f, Q, residual, cross, H @ cross, H, R, observed,
                                      evidence=False, mask=m)  # fmt: skip
    return f, Q, mu, sigma


def transition_law_unsaid(model) -> str | None:
    """Why ``model``'s transition draws may not be ``f + w``, ``w`` its process noise (it
    overrides ``sample_transition`` and does not declare ``samples_process_noise = True``),
    or ``None``: what a proposal or a bound that weighs by ``N(f, Q)`` needs."""
    if type(model).sample_transition is StateSpaceModel.sample_transition or getattr(
        model, "samples_process_noise", False
    ):
        return None
    return (f"{type(model).__name__} draws its transitions its own way (sample_transition), "
            "and the weights take them as f + w, w ~ its process_noise (a class whose draw "
            "has that law says so with samples_process_noise = True)")  # fmt: skip


def _shared_received(mask: Tensor | None) -> Tensor | None:
    """The indices of the received entries when every run of ``mask [..., dy]`` receives
    the same ones (a Round-Robin schedule, no loss), else ``None``: the Kalman proposal's
    update then runs on ``[..., d_received, d_received]`` matrices instead of masking
    ``[..., dy, dy]`` ones (the same numbers: a masked entry's gain column is zero)."""
    if mask is None:
        return None
    rows = mask.reshape(-1, mask.shape[-1])
    if not bool((rows == rows[:1]).all()):
        return None
    return rows[0].nonzero().squeeze(-1)


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


#: What to do with a sweep of parameter sets where one model for all runs is needed.
PER_SET = ("run a filter per parameter set, or use the Kalman filter or the EKF, which take "
           "them")  # fmt: skip


def particle_init(
    model: StateSpaceModel,
    num_particles: int,
    batch_shape=(),
    generator: torch.Generator | None = None,
) -> ParticleState:
    """Draw ``N`` particles from the prior: ``[*batch_shape, N, dx]``, log-weights ``−log N``."""
    check_positive_int(num_particles, "num_particles")
    check_one_model(model, "the particle filter", PER_SET)
    batch_shape = check_batch_shape(batch_shape, least=0)  # (an int too, as init takes it)
    particles = model.sample_initial(batch_shape + (num_particles,), generator)
    log_w = particles.new_full(batch_shape + (num_particles,), -math.log(num_particles))
    return ParticleState(particles, log_w, 0, model=model)


class ParticleFilter(Estimator):
    """The particle filter as an estimator object (module docstring for one step).

    Args:
        num_particles: ``N ≥ 1``.
        resampler: a :mod:`difffilter.resampling` object (default ``Systematic()``).
        proposal: default :class:`BootstrapProposal`; :class:`KalmanProposal` is the
            locally linearised optimal proposal.
        likelihood: default :class:`ModelLikelihood`; any callable ``(model, y, particles,
            k, mask) → [..., N]`` (``uses_predictive = True``: also passed ``predictive=``),
            or a :class:`StepLikelihood` whose state lives in the carry's ``aux``.
        ess_threshold: resample when ``ESS < ess_threshold · N`` (``1.0`` resamples at
            every step with non-uniform weights, and with equal weights where their ESS
            rounds below ``N``, as it does for some ``N`` and batch layouts: one run
            unbatched and as a batch of one, 200.00000000000003 against 199.9999999999999
            at N = 200, resample at different steps and then draw different numbers;
            ``0`` never: plain SIS).
        hooks: callables ``hook(model, y, mask, carry, out) → {name: tensor [...]}`` run
            after every step (``carry``: the new carry, ``out``: its step output); what
            they return goes into the step's ``extras`` (what a detector needs, without
            keeping every particle).
        innovations: compute the predictive measurement moments (``innovation``,
            ``innovation_cov``); ``False`` skips them unless the likelihood reads them.
        cov_dims: ``cov`` of the first ``cov_dims`` particle components only (default
            all ``dx``): for particles that carry more than the state (the per-particle
            Kalman statistics of :mod:`difffilter.fdi.mdpf`).
        record_prior: also report the predictive log-weights ``"prior_log_weights"``.

    Carry: :class:`ParticleState` with the generators (``init`` draws the prior particles
    from ``generators.init``, the steps propagate with ``generators.propagate`` and
    resample with ``generators.resample``).
    """

    carry_type = ParticleState

    def __init__(
        self,
        num_particles: int,
        *,
        resampler: Resampler | None = None,
        proposal: Proposal | None = None,
        likelihood: Likelihood | None = None,
        ess_threshold: float = 0.5,
        hooks: Sequence[StepHook] = (),
        innovations: bool = True,
        cov_dims: int | None = None,
        record_prior: bool = False,
    ):
        self.num_particles = check_positive_int(num_particles, "num_particles")
        # (the same checks as a replacement's: _checked_strategy)
        self.resampler = _checked_strategy("resampler", resampler)
        self.proposal = _checked_strategy("proposal", proposal)
        _check_likelihood(likelihood)
        self.ess_threshold = check_ess_threshold(ess_threshold)
        self.likelihood = likelihood if likelihood is not None else ModelLikelihood()
        self.stateful = hasattr(self.likelihood, "weigh")
        self.hooks = _check_hooks(hooks)
        self.innovations, self.cov_dims = bool(innovations), _check_cov_dims(cov_dims, None)
        self.record_prior = bool(record_prior)

    def _init(self, model, batch_shape, generators):
        state = particle_init(model, self.num_particles, batch_shape, generators.init)
        return self.attach(state, model, generators)

    def attach(self, state: ParticleState, model, generators: Generators) -> ParticleState:
        """``state`` (e.g. particles drawn elsewhere) as this filter's carry on ``model``:
        the model, the generators and, for a stateful likelihood, its initial state."""
        n = state.log_weights.shape[-1] if isinstance(state, ParticleState) else None
        if n != self.num_particles:
            raise ValueError(
                f"state must be a ParticleState of {self.num_particles} particles (num_particles); "
                f"got {'a ' + type(state).__name__ if n is None else f'{n} particles'}"
            )
        _check_cov_dims(self.cov_dims, model.dim_x)
        aux, lead = state.aux, state.log_weights.shape[:-1]
        if self.stateful and aux is None:
            aux = self.likelihood.init(model, lead, state.particles.dtype, state.particles.device)
        elif self.stateful and hasattr(self.likelihood, "resume"):  # a carry's own, for model
            aux = self.likelihood.resume(aux, model, lead, state.particles.dtype,
                                         state.particles.device)  # fmt: skip
        return state._replace(model=model, aux=aux, generators=generators)

    def batch_of(self, carry):
        return carry.log_weights.shape[:-1]

    def _model_of(self, carry):
        return carry.model

    def _check_carry(self, carry):
        n, dx = self.num_particles, carry.model.dim_x
        _check_cov_dims(self.cov_dims, dx)
        check_carry_tensor(carry.particles, "particles", dim=None)
        # the weights and their caches as tensors of the carry's dtype first (numpy ones, or
        # a float32 ess cache, had failed in torch's words: an apishapes trial)
        for name in ("log_weights", "weights", "ess"):
            value = getattr(carry, name)
            if (value is not None or name == "log_weights") and not (
                isinstance(value, torch.Tensor) and value.dtype == carry.particles.dtype
            ):
                got = value.dtype if isinstance(value, torch.Tensor) else type(value).__name__
                raise ValueError(
                    f"carry.{name} must be a {carry.particles.dtype} tensor (the particles' "
                    f"dtype{'' if name == 'log_weights' else ', or None'}); got {got}"
                )
        check_carry_fits_model(carry.model, particles=carry.particles,
                               log_weights=carry.log_weights)  # fmt: skip
        if carry.particles.dim() < 2 or carry.particles.shape[-2:] != (n, dx):
            raise ValueError(
                f"carry.particles must have shape [..., {n}, {dx}] (num_particles = {n}); got "
                f"{tuple(carry.particles.shape)}"
            )
        if carry.log_weights.shape != carry.particles.shape[:-1]:
            raise ValueError(
                f"carry.log_weights must have shape {tuple(carry.particles.shape[:-1])}; got "
                f"{tuple(carry.log_weights.shape)}"
            )
        if bool(torch.isnan(carry.log_weights).any()):
            raise ValueError("carry.log_weights contains NaN values")
        if carry.aux is None and self.stateful:  # (it failed on None's attributes: a trial)
            raise ValueError(
                f"carry.aux is None, and this particle filter's likelihood "
                f"({type(self.likelihood).__name__}) keeps a state there: start the carry from "
                "this estimator's init"
            )
        if carry.aux is not None and not self.stateful:  # (it was stepped, the state ignored)
            raise ValueError(
                "carry.aux holds a stateful likelihood's state (another estimator's carry, e.g. "
                "a learned particle filter's), and this particle filter's likelihood keeps "
                "none: start the carry from this estimator's init"
            )
        log_w = carry.log_weights.detach()
        # normalised as the steps leave them (round-off of a sum over N aside): the steps
        # add to them, so unnormalised ones scale every mean and shift the evidence
        tol = 1e4 * torch.finfo(log_w.dtype).eps
        if not bool((torch.logsumexp(log_w, dim=-1).abs() <= tol).all()):
            raise ValueError(
                "carry.log_weights must be normalised (logsumexp over the N particles = 0; "
                "e.g. torch.log_softmax(…, dim=-1))"
            )
        # The caches against log_weights to half the dtype's digits: a step computes
        # log w = joint − log p̂ with round-off ε·|joint|, which grows with the size of the
        # log-likelihoods (2.2e-13 relative on the tracking plant's range-bearing steps, where
        # 1e3 ε had refused the step's own carry: a serialisation trial); a cache left stale by
        # new log_weights differs by far more
        rtol = torch.finfo(log_w.dtype).eps ** 0.5
        if carry.weights is not None:
            info = torch.finfo(log_w.dtype)  # (a subnormal weight keeps fewer digits)
            if carry.weights.shape != log_w.shape or not torch.allclose(
                carry.weights.detach(), log_w.exp(), rtol=rtol, atol=info.tiny
            ):
                raise ValueError(
                    "carry.weights is not exp(carry.log_weights) (a cache of the step that "
                    "made the carry): give new log_weights with weights=None, ess=None"
                )
        if carry.ess is not None:
            ess = effective_sample_size(log_w)
            if carry.ess.shape != ess.shape or not torch.allclose(
                carry.ess.detach(), ess, rtol=rtol, atol=0
            ):
                raise ValueError(
                    "carry.ess is not the effective sample size of carry.log_weights (a cache "
                    "of the step that made the carry): give new log_weights with ess=None, "
                    "weights=None"
                )

    #: Settings a carry is made for: one replaced after ``init`` is checked as ``__init__``
    #: checks it, and the next step validates its carry against it in full (a lean step had
    #: gone on with 50 particles for ``num_particles = 20`` and returned a 0 × 0 covariance
    #: for ``cov_dims = 0``: a red-team trial); a new likelihood's statefulness is read again.
    _CARRY_SETTINGS = frozenset({"num_particles", "cov_dims", "likelihood"})
    #: Settings read at each step, checked when replaced as ``__init__`` checks them.
    _STRATEGY_SETTINGS = frozenset({"ess_threshold", "resampler", "proposal", "hooks"})

    def __setattr__(self, name, value):
        if name in self._STRATEGY_SETTINGS and name in self.__dict__:
            # checked as __init__ checks them (a NaN or negative ess_threshold assigned later
            # turned resampling off for good, 2.0 resampled at every step; a None resampler
            # failed at the step as "'NoneType' object is not callable": a trial)
            super().__setattr__(name, _checked_strategy(name, value))
            return
        if name not in self._CARRY_SETTINGS or name not in self.__dict__:
            super().__setattr__(name, value)
            return
        if name == "num_particles":
            value = check_positive_int(value, "num_particles")
        elif name == "cov_dims":
            value = _check_cov_dims(value, None)
        elif name == "likelihood":  # (None had failed at the step, "'NoneType' object is
            _check_likelihood(value)  # not callable": the constructor's default here too)
            value = ModelLikelihood() if value is None else value
        super().__setattr__(name, value)
        if name == "likelihood":
            super().__setattr__("stateful", hasattr(value, "weigh"))
        note_assignment()

    def _step(self, carry, y, u, mask):
        if _single_run.on_defaults(self, carry):  # one run on the defaults: a leaner step
            density = _host_step.density(carry, y, u)
            if density is not None:  # ... on host arrays where nothing is recorded (a mask too)
                return _host_step.host_step(self, carry, y, u, density, mask)
            if mask is None:
                return _single_run.single_run_step(self, carry, y, u)
        elif _single_run.one_of_a_batch(self, carry, y, u, mask):  # init(model, (1,)): its run
            # ParticleFilter's own step, not a subclass's override: a subclass adjusting
            # super()._step's output had it applied twice at batch (1,) (a red-team trial)
            new, out = ParticleFilter._step(self, _single_run.run_of(carry), y[0],
                                            None if u is None else u[0],
                                            None if mask is None else mask[0])  # fmt: skip
            return _single_run.as_batch_of_one(new, out)
        return _particle_step(self, carry, y, u, mask)


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
) -> tuple[ParticleState, StepOutput]:
    """One particle-filter step ``x_{k−1} → x_k`` with measurement ``y_k [..., dy]``.

    Args as in :func:`particle_filter`; ``u [..., du]``, ``mask [..., dy]``. The inputs
    are validated as in :func:`difffilter.kalman_step` (a NaN or Inf in a received entry
    of ``y`` raises). Returns the new :class:`ParticleState` and the step's
    :class:`~difffilter.results.StepOutput` (``extras``: ``ess``, ``resampled``,
    ``degenerate``, ``prior_log_weights``).
    """
    check_model(model)
    if not isinstance(state, ParticleState):
        raise TypeError(
            f"state must be a ParticleState (particle_init); got {type(state).__name__}"
        )
    pf = ParticleFilter(
        state.log_weights.shape[-1], resampler=resampler, proposal=proposal,
        likelihood=likelihood, ess_threshold=ess_threshold, innovations=innovations,
        cov_dims=_check_cov_dims(cov_dims, state.particles.shape[-1]), record_prior=True,
    )  # fmt: skip
    gens = Generators(None, generator, resample_generator if resample_generator else generator)
    return pf.step(pf.attach(state, model, gens), y, u, mask)


def _check_cov_dims(cov_dims, dim: int | None) -> int | None:
    """``cov_dims`` as the steps take it (``None`` for every state), or a ``ValueError``;
    ``dim = None``: the state's dimension is not known yet (a filter object is made before
    its model: its ``init`` checks it against ``dx``, and keeps what was given). The object
    had taken ``-1`` (the first ``dx − 1`` states, unsaid) and ``0``."""
    if cov_dims is None:
        return None
    top = "dx" if dim is None else dim
    if (isinstance(cov_dims, bool) or not isinstance(cov_dims, int) or cov_dims < 1
            or (dim is not None and cov_dims > dim)):  # fmt: skip
        raise ValueError(f"cov_dims must be None or an integer in [1, {top}]; got {cov_dims!r}")
    return None if cov_dims == dim else cov_dims


#: How the filter calls a hook (:class:`ParticleFilter`'s ``hooks``).
_HOOK_ARGS = ("model", "y", "mask", "carry", "out")


def _check_hooks(hooks) -> tuple:
    """``hooks`` as a tuple of callables that take ``hook(model, y, mask, carry, out)``,
    checked when the filter is made (a bare function had failed as "not iterable", a
    ``None`` at the first step as "not callable")."""
    if callable(hooks) or isinstance(hooks, (str, bytes)) or not hasattr(hooks, "__iter__"):
        raise TypeError(
            f"hooks must be a sequence of callables hook({', '.join(_HOOK_ARGS)}) → {{name: "
            f"tensor}}; got {type(hooks).__name__} (one hook: hooks=[hook])"
        )
    hooks = tuple(hooks)
    for i, hook in enumerate(hooks):
        if not callable(hook):
            raise TypeError(f"hooks[{i}] must be callable as hook({', '.join(_HOOK_ARGS)}); "
                            f"got {type(hook).__name__}")  # fmt: skip
        check_callable_as(hook, f"hooks[{i}]", "hook", _HOOK_ARGS)
    return hooks


def _checked_strategy(name: str, value):
    """A ``ess_threshold``, ``resampler``, ``proposal`` or ``hooks`` of a
    :class:`ParticleFilter`, given to ``__init__`` or assigned later: checked, ``None`` read
    as the default strategy."""
    if name == "ess_threshold":
        return check_ess_threshold(value)
    if name == "hooks":
        return _check_hooks(value)
    if name == "resampler":
        value = Systematic() if value is None else value
        check_strategy(value, "resampler", "difffilter.resampling.Systematic()",
                       ("particles", "log_weights", "generator"))  # fmt: skip
        check_resampler_hooks(value)
        return value
    value = BootstrapProposal() if value is None else value
    check_strategy(value, "proposal", "difffilter.BootstrapProposal()",
                   ("model", "particles", "u", "y", "k", "mask", "generator"))  # fmt: skip
    return value


def _check_likelihood(likelihood) -> None:
    # an init without a __call__ is a stateful likelihood whose weigh is missing (a
    # misspelt weigh had been told "must be a callable object": a gradients trial)
    if hasattr(likelihood, "weigh") or (hasattr(likelihood, "init") and not callable(likelihood)):
        _check_step_likelihood(likelihood)
    elif getattr(likelihood, "uses_predictive", False):  # (it failed at the first step)
        # called with predictive= always: a required predictive had been refused against
        # a call without it that the filter never makes (a trial of the plug-ins)
        check_strategy(likelihood, "likelihood", "difffilter.ModelLikelihood()")
        check_callable_as(likelihood, f"the likelihood {type(likelihood).__name__} "
                          "(uses_predictive = True)", "likelihood",
                          ("model", "y", "particles", "k", "mask"), ("predictive",))  # fmt: skip
    else:
        check_strategy(likelihood, "likelihood", "difffilter.ModelLikelihood()",
                       ("model", "y", "particles", "k", "mask"))  # fmt: skip


#: What a stateful likelihood implements (:class:`StepLikelihood`), named in its errors.
_STEP_CONTRACT = (
    "init(model, batch_shape, dtype, device) → state and weigh(state, model, y, particles, "
    "k, mask, predictive) → (state, log p [..., N], record {name: tensor [...]}) "
    "(difffilter.particle.StepLikelihood; docs/plugins.md)"
)


def _check_step_likelihood(likelihood) -> None:
    """A likelihood with ``weigh`` (or ``init`` and no ``__call__``) is a stateful one
    (:class:`StepLikelihood`): an instance
    whose ``init`` and ``weigh`` can be called as the filter calls them, checked when the
    filter is made, as the other plug-ins are (one without ``init`` failed at the
    filter's init on a bare AttributeError; a class passed for an instance, on a missing
    argument)."""
    if isinstance(likelihood, type):
        raise TypeError(
            f"likelihood must be an instance, not the class {likelihood.__name__}: pass "
            f"likelihood={likelihood.__name__}(...)"
        )
    name = type(likelihood).__name__
    for method, params in (("init", ("model", "batch_shape", "dtype", "device")),
                           ("weigh", ("state", "model", "y", "particles", "k", "mask",
                                      "predictive"))):  # fmt: skip
        fn = getattr(likelihood, method, None)
        if not callable(fn):
            has = "an init" if method == "weigh" else "a weigh"
            raise TypeError(
                f"the likelihood {name} has {has}, so it is a stateful likelihood, and it "
                f"has no {method} method: it implements {_STEP_CONTRACT}"
            )
        check_callable_as(fn, f"the likelihood {name}'s {method}", method, params)


def _resample(pf: ParticleFilter, particles, log_w, ess, w, generator, k: int):
    """Resample the rows whose ESS fell below the threshold: ``(particles, log_w, w,
    need [...], uniform)`` (``uniform``: the weights are now exactly −log N in every row);
    ``k`` the measurement step it precedes (named in a user resampler's errors)."""
    n = particles.shape[-2]
    need = (_ess(log_w) if ess is None else ess) < pf.ess_threshold * n
    count = int(need.item()) if need.dim() == 0 else int(need.sum())  # one run: one read
    if not count:
        return particles, log_w, w, need, False
    resampler, uniform = pf.resampler, False
    rows = None if count == need.numel() else need
    # weights here are normalised and finite by construction: skip re-validation
    kind = type(resampler)
    # a user's __call__, or resample_normalized (one returning N − 1 particles had shrunk
    # the carry unchecked: a trial of the plug-ins), checked
    if (not isinstance(resampler, Resampler) or defined_outside(kind, "__call__")
            or defined_outside(kind, "resample_normalized")):  # fmt: skip
        res = _checked_resampled(resampler(particles, log_w, generator), particles, log_w,
                                 resampler, k)  # fmt: skip
        if rows is not None:
            res = keep_unmarked_rows(res, particles, log_w, rows)
        return res.particles, res.log_weights, None, need, uniform
    fast = resampler.resample_normalized
    try:
        if kind.resample_normalized is Resampler.resample_normalized:
            # the library's index resamplers also take the weights this step has (no exp)
            res = fast(particles, log_w, generator, rows=rows, weights=w)
            uniform = rows is None and kind._new_log_weights is _UNIFORM
        else:
            res = fast(particles, log_w, generator, rows=rows)
    except _AncestorError as error:  # a user's `_draw`: name the step too
        raise ValueError(f"{error} (before step {k})") from None
    if defined_outside(kind, "_new_log_weights"):  # a user's: checked to be normalised
        res = _checked_resampled(res, particles, log_w, resampler, k)
    return res.particles, res.log_weights, None, need, uniform


def _checked_resampled(res, particles: Tensor, log_w: Tensor, resampler=None,
                       k: int | None = None):  # fmt: skip
    """A user resampler's result, checked: a :class:`~difffilter.resampling.Resampled`
    (``.particles``, ``.log_weights``) of the particles' shape and dtype, its log-weights
    normalised (``logsumexp = 0`` per run). One returning N − 1 particles shrank the
    online carry a particle a step; unnormalised log-weights shifted the evidence by their
    sum at every resampling, all without a word. One reduction per resampling. Its errors
    name the resampler, and its NaN (a plug-in trial: blamed on the likelihood, a step
    later)."""
    name = type(res).__name__
    who = "the resampler" if resampler is None else f"the resampler {type(resampler).__name__}"
    if k is not None:
        who += f" (before step {k})"
    got = getattr(res, "particles", None), getattr(res, "log_weights", None)
    if not all(isinstance(t, Tensor) for t in got):
        raise TypeError(f"{who} returned a {name}; it returns a Resampled(particles, "
                        "log_weights, ancestors) (difffilter.resampling.Resampled)")  # fmt: skip
    new, new_lw = got
    if (new.shape != particles.shape or new_lw.shape != log_w.shape
            or new.dtype != particles.dtype or new_lw.dtype != log_w.dtype):  # fmt: skip
        raise ValueError(
            f"{who} returned particles {tuple(new.shape)} {new.dtype} and log-weights "
            f"{tuple(new_lw.shape)} {new_lw.dtype}; it was given {tuple(particles.shape)} "
            f"{particles.dtype} and {tuple(log_w.shape)} {log_w.dtype}: the same number of "
            "particles, of the same dtype"
        )
    total = torch.logsumexp(new_lw.detach(), dim=-1)
    if bool(total.isnan().any()) or not bool(torch.isfinite(new).all()):
        raise ValueError(f"{who} returned NaN or inf particles or NaN log-weights")
    if not bool((total.abs() <= 1e-4 if new_lw.dtype != torch.float64 else
                 total.abs() <= 1e-9).all()):  # fmt: skip
        raise ValueError(
            f"{who} returned log-weights whose logsumexp per run is up to "
            f"{float(total.abs().max()):.3g} from 0: return normalised log-weights (e.g. "
            "log_w - logsumexp(log_w)); unnormalised ones shift the evidence at each resampling"
        )
    return res


def _particle_step(pf: ParticleFilter, carry: ParticleState, y, u, mask):
    """One step of ``pf`` from ``carry`` (inputs validated): resample, propose, weigh."""
    model, gens, k = carry.model, carry.generators or Generators(), carry.k
    resample_gen = gens.resample if gens.resample is not None else gens.propagate
    particles, log_w, w, need, uniform = _resample(
        pf, carry.particles, carry.log_weights, carry.ess, carry.weights, resample_gen, k + 1
    )
    proposed = pf.proposal(model, particles, u, y, k, mask, gens.propagate)
    if type(proposed) is not tuple or len(proposed) != 2:
        _check_proposal_pair(proposed, pf.proposal, k + 1)
    new, correction = proposed
    _check_proposed(new, correction, particles, log_w, pf.proposal, k)

    # Predictive weights of the proposed particles: w_{k−1}·p/q (just w_{k−1} for the
    # bootstrap proposal, whose correction is None), and the predictive moments.
    prior_lw = log_w if correction is None else _corrected(log_w, correction)
    uses_predictive = pf.stateful or getattr(pf.likelihood, "uses_predictive", False)
    obs = predictive = pred_w = None
    if correction is None and uniform:
        # equal weights: the predicted mean is the particles' average (no exp, no product)
        pred_mean = new.mean(-2)
    else:
        pred_w = (w if correction is None and w is not None else torch.exp(prior_lw)).unsqueeze(-2)
        pred_mean = _weighted_mean(pred_w, new)
    if pf.innovations or uses_predictive:
        pred_w = torch.exp(prior_lw).unsqueeze(-2) if pred_w is None else pred_w
        obs = model.observe(new, k + 1)
        predictive = _predictive(model, y, mask, k, obs, pred_w, prior_lw, pred_mean)

    aux, log_lik, record = _weigh(pf, carry.aux, model, y, new, k + 1, mask, obs, predictive,
                                  uses_predictive)  # fmt: skip
    _check_log_density(log_lik, log_w, pf.likelihood, "likelihood", k + 1)
    log_alpha = log_lik if correction is None else log_lik + correction

    def blame() -> None:
        _blame_degenerate(pf, new, log_lik, correction, log_w, k + 1)

    increment, log_w_new, w_new, degenerate = _normalise(log_w + log_alpha, prior_lw, blame)
    ess_new = torch.linalg.vecdot(w_new, w_new).reciprocal()
    mean, cov = _moments(new, w_new, pf.cov_dims)
    extras = {"ess": ess_new, "resampled": need, "degenerate": degenerate, **record}
    if pf.record_prior or pf.hooks:
        extras["prior_log_weights"] = prior_lw
    shown = predictive if pf.innovations else None
    out = StepOutput(
        mean, cov, pred_mean=pred_mean, log_likelihood=increment, extras=extras,
        innovation=None if shown is None else shown.innovation,
        innovation_cov=None if shown is None else shown.innovation_cov,
    )  # fmt: skip
    new_carry = ParticleState(new, log_w_new, k + 1, ess_new, w_new, model, aux, carry.generators)
    if pf.hooks:
        taken = {key: f"the likelihood {type(pf.likelihood).__name__}" for key in record}
        for hook in pf.hooks:
            recorded = hook(model, y, mask, new_carry, out)
            name = getattr(hook, "__qualname__", type(hook).__name__)
            if type(recorded) is not dict or not _RESERVED_KEYS.isdisjoint(recorded):
                recorded = _checked_record(recorded, f"the step hook {name}", "record", k + 1)
            if not taken.keys().isdisjoint(recorded):
                # (one plug-in's record had silently replaced another's of the same name:
                # a detector's "score" read as a hook's; a trial of the plug-ins)
                key = next(key for key in recorded if key in taken)
                raise ValueError(
                    f"the step hook {name} recorded {key!r} at step {k + 1}, which "
                    f"{taken[key]} records too (one would replace the other): name them apart"
                )
            taken.update(dict.fromkeys(recorded, f"the step hook {name}"))
            extras.update(recorded)
        if not pf.record_prior:
            del extras["prior_log_weights"]
    return new_carry, out


def _weigh(pf, aux, model, y, particles, k, mask, obs, predictive, uses_predictive):
    """``(aux, log α [..., N], record)``: the likelihood of the proposed particles at step ``k``
    (the model's own density reuses the predicted measurements ``obs`` when it has them)."""
    likelihood = pf.likelihood
    if type(likelihood) is ModelLikelihood and _default_measurement_density(model):
        obs = model.observe(particles, k) if obs is None else obs
        m = None if mask is None else mask.unsqueeze(-2)
        residual = model.measurement_residual(y.unsqueeze(-2), obs)
        return aux, model.measurement_noise.log_prob(residual, mask=m), {}
    if pf.stateful:
        weighed = likelihood.weigh(aux, model, y, particles, k, mask, predictive)
        # (the usual step: three comparisons and a lookup per recorded key)
        if (type(weighed) is not tuple or len(weighed) != 3 or type(weighed[2]) is not dict
                or not _RESERVED_KEYS.isdisjoint(weighed[2])):  # fmt: skip
            weighed = _checked_weighed(weighed, likelihood, k)
        return weighed
    if uses_predictive:
        return aux, likelihood(model, y, particles, k, mask, predictive=predictive), {}
    return aux, likelihood(model, y, particles, k, mask), {}


def _checked_weighed(weighed, likelihood, k: int) -> tuple:
    """A stateful likelihood's ``weigh`` result that the step's quick test did not pass,
    checked: a triple ``(state, log p, record)``, its record as :func:`_checked_record`
    checks it. A pair failed as "not enough values to unpack", naming neither the
    likelihood nor the step. Returns the triple with a ``dict`` record."""
    name = type(likelihood).__name__
    if not isinstance(weighed, Sequence) or isinstance(weighed, Tensor) or len(weighed) != 3:
        got = (f"a tensor {tuple(weighed.shape)}" if isinstance(weighed, Tensor)
               else f"a {type(weighed).__name__} of {len(weighed)}"
               if isinstance(weighed, Sequence) else f"a {type(weighed).__name__}")  # fmt: skip
        raise TypeError(
            f"the likelihood {name}'s weigh returned {got} at step {k}; it returns a triple "
            "(state, log p [..., N], record {name: tensor [...]}, {} for none)"
        )
    state, log_p, record = weighed
    return state, log_p, _checked_record(record, f"the likelihood {name}", "weigh's record", k)


def _checked_record(record, who: str, what: str, k: int) -> dict:
    """A record a plug-in reports in a step's extras (a stateful likelihood's, ``who`` "the
    likelihood X"; a step hook's, "the step hook f"), checked where it is not a plain
    ``dict`` of the plug-in's own keys: a mapping, none of whose keys is one the filter
    reports itself (:data:`_RESERVED_KEYS`). A record ``"ess"`` had silently replaced the
    filter's own ESS in ``extras`` and the result, and a list failed in ``dict.update`` or
    unpacking, naming neither the plug-in nor the step."""
    if not isinstance(record, Mapping):
        raise TypeError(
            f"{who}'s {what} is a {type(record).__name__} at step {k}; it is a dict "
            "{name: tensor [...]} ({} for none), reported in the step's extras"
        )
    clash = sorted(_RESERVED_KEYS.intersection(record))
    if clash:
        raise ValueError(
            f"{who} recorded {', '.join(map(repr, clash))} at step {k}: the particle filter "
            "reports such keys itself in extras (one would replace the other); name the "
            f"entries otherwise, none of the filter's {', '.join(sorted(_RESERVED_KEYS))}"
        )
    return dict(record)


def _check_log_density(value, log_w: Tensor, plugin, what: str, k: int) -> None:
    """A plug-in's log-densities are a floating tensor of the particles' shape and dtype,
    ``[..., N]`` as ``log_w``: a likelihood that forgot the runs (``[N]``) gave every run
    the first run's likelihood, an integer one was truncated, all without a word. Shape
    and dtype only (a few comparisons a step); values are read only on a degenerate step
    (:func:`_blame_nonfinite`)."""
    if type(value) is Tensor and value.shape == log_w.shape and value.dtype == log_w.dtype:
        return
    name = f"{what} {type(plugin).__name__}"
    if not isinstance(value, Tensor):
        raise TypeError(f"the {name} returned a {type(value).__name__} at step {k}; it returns "
                        f"log p(y_k | x_k^i), a tensor {list(log_w.shape)}")  # fmt: skip
    raise ValueError(
        f"the {name} returned log-densities of shape {tuple(value.shape)} and dtype "
        f"{value.dtype} at step {k}; the particles' weights are {tuple(log_w.shape)} "
        f"{log_w.dtype} ([..., N]: one per run and particle, summed over the measurement)"
    )


def _corrected(log_w: Tensor, correction: Tensor) -> Tensor:
    """The predictive log-weights ``log_softmax(log w + log p/q)`` ``[..., N]``; a run whose
    every proposed particle has zero transition density (``correction`` all −inf) keeps
    ``log w`` (a normalised softmax of all −inf is NaN: those NaNs became the run's reset
    weights and failed the next resampling, blamed on the resampler), and its step is then
    degenerate, its evidence −inf, as for a likelihood that is zero everywhere. Selected
    before the softmax, so that no NaN enters the graph (other runs' gradients stay
    finite). Elementwise: no host sync."""
    joint = log_w + correction
    void = (joint == -math.inf).all(-1, keepdim=True)
    safe = torch.where(void, log_w, joint)
    return torch.where(void, log_w, torch.log_softmax(safe, dim=-1))


def _check_proposal_pair(proposed, proposal, k: int) -> None:
    """A proposal returns ``(particles, log_correction or None)``; a bare tensor failed as
    'too many values to unpack', naming neither the proposal nor what it returns."""
    if isinstance(proposed, Sequence) and not isinstance(proposed, Tensor) and len(proposed) == 2:
        return
    got = (f"a tensor {tuple(proposed.shape)}" if isinstance(proposed, Tensor)
           else f"a {type(proposed).__name__} of {len(proposed)}" if isinstance(proposed, Sequence)
           else f"a {type(proposed).__name__}")  # fmt: skip
    raise TypeError(
        f"the proposal {type(proposal).__name__} returned {got} at step {k}; it returns a "
        "pair (particles [..., N, dx], log_correction [..., N] or None: log p(x_k | x_{k−1})"
        " − log q(x_k | x_{k−1}, y_k), None for the bootstrap proposal)"
    )


def _check_proposed(new, correction, particles: Tensor, log_w: Tensor, proposal, k: int) -> None:
    """A proposal returns particles of the shape and dtype it was given and a correction
    ``None`` or of the weights' (:func:`_check_log_density`): one run's particles ``[N, dx]``
    for a batch broadcast into every run (the means came out ``[3, 3, T, dx]``), a
    correction of the first run alone (``[N]``) gave every run its evidence (15 nats off),
    float32 particles failed inside torch (a plug-in trial). Shapes and dtypes only."""
    if type(new) is Tensor and new.shape == particles.shape and new.dtype == particles.dtype:
        pass  # (the usual step: three comparisons)
    elif not (isinstance(new, Tensor) and new.dtype == particles.dtype
              and new.shape[-2:] == particles.shape[-2:]
              and _broadcasts_into(particles.shape[:-2], new.shape[:-2])):  # fmt: skip
        # (a carry of one set of runs on a model of several grows to the model's sets)
        got = (f"{tuple(new.shape)} {new.dtype}" if isinstance(new, Tensor)
               else type(new).__name__)  # fmt: skip
        raise ValueError(
            f"the proposal {type(proposal).__name__} returned particles {got} at step {k + 1}; "
            f"it was given {tuple(particles.shape)} {particles.dtype}: the same shape ([..., N, "
            "dx], every run) and dtype"
        )
    if correction is not None:  # one per run (the proposed runs) and particle
        weights = log_w if log_w.shape == new.shape[:-1] else log_w.expand(new.shape[:-1])
        _check_log_density(correction, weights, proposal, "proposal's correction", k + 1)


def _broadcasts_into(small, big) -> bool:
    """Whether batch shape ``small`` broadcasts to exactly ``big``."""
    try:
        return broadcast_shapes(small, big) == big
    except RuntimeError:
        return False


def _blame_degenerate(pf, particles, log_lik, correction, log_w, k: int) -> None:
    """Raise the ``ValueError`` that names the plug-in behind a degenerate step of measurement
    ``k`` (every run's joint weight −inf or NaN) where one is: proposed ``particles`` that
    hold NaN or inf, a NaN or +inf in the likelihood's ``log_lik``, the proposal's
    ``correction`` (or ``None``) or the resampler's ``log_w``; else return (an underflow: the
    step resets to the predictive weights). Called by every step that can degenerate, the
    one-run paths included (:mod:`difffilter._pf_single_run`,
    :mod:`difffilter._pf_host_step`), so that all of them raise where the general one does."""
    bad = ~torch.isfinite(particles)
    if bool(bad.any()):  # (the likelihood of a NaN particle is NaN: not its fault)
        hint = getattr(pf.proposal, "nonfinite_hint", None)  # (what the proposal knows)
        raise ValueError(
            f"the particles proposed by {type(pf.proposal).__name__} hold NaN or inf at step "
            f"{k} (first at index {first_index(bad)})" + (f": {hint}" if hint else "")
        )
    _blame_nonfinite(log_lik, pf.likelihood, "likelihood", k)
    if correction is not None:
        _blame_nonfinite(correction, pf.proposal, "proposal's correction", k)
    _blame_nonfinite(log_w, pf.resampler, "resampler's log-weights", k)


def _blame_nonfinite(value: Tensor, plugin, what: str, k: int) -> None:
    """``ValueError`` naming ``plugin`` where ``value`` holds NaN or +inf: a density is
    finite or −inf (zero). Such a step was taken for an underflow, its run's weights reset
    to the predictive ones, and the measurement silently ignored."""
    bad = torch.isnan(value) | (value == math.inf)
    if bool(bad.any()):
        where = [int(i) for i in bad.nonzero()[0]]
        raise ValueError(
            f"the {what} of {type(plugin).__name__} holds NaN or +inf at step {k} (first at "
            f"index {tuple(where)}): log-densities and log-weights are finite or -inf"
        )


def _normalise(joint: Tensor, prior_lw: Tensor, blame=None):
    """``(increment [...], log w [..., N], w [..., N], degenerate [...])`` from the joint log
    weights: logsumexp by hand, keeping its exponentials (``e = exp(joint − max)`` gives the
    weights ``e / Σe`` and the increment ``log Σe + max`` without a second exp pass).
    Degenerate runs (every joint weight −inf, or NaN) reset to the predictive weights
    ``prior_lw`` (module docstring): one host sync per step, the reset only when needed.
    The reset keeps the other runs' gradients finite: its graph holds no NaN of the
    degenerate runs (a ``torch.where`` over a NaN branch passes ``0 · NaN`` back)."""
    increment, log_w, w = _normalised(joint)
    degenerate = ~torch.isfinite(increment)
    if bool(degenerate if degenerate.dim() == 0 else degenerate.any()):
        if blame is not None:  # ``blame()`` raises where a plug-in, not underflow, is why
            blame()
        reset = degenerate.unsqueeze(-1)
        # −inf (not NaN) where all are −inf; no gradient through a degenerate run's
        increment = torch.logsumexp(torch.where(reset, joint.detach(), joint), dim=-1)
        # the other runs' weights as a batch without the degenerate ones gives them,
        # recomputed beside finite stand-ins
        _, kept_log_w, kept_w = _normalised(torch.where(reset, prior_lw.detach(), joint))
        log_w = torch.where(reset, prior_lw, kept_log_w)
        w = torch.where(reset, torch.exp(prior_lw), kept_w)
    return increment, log_w, w, degenerate


def _normalised(joint: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(log Σ exp joint [...], log w [..., N], w [..., N])`` by hand (:func:`_normalise`)."""
    if joint.dim() == 1:  # one run: the same numbers without the keepdim reshapes
        top = joint.detach().amax(-1)
        e = torch.exp(joint - top)
        total = e.sum(-1)
        increment = torch.log(total) + top
        return increment, joint - increment, e / total
    top = joint.detach().amax(-1, keepdim=True)
    e = torch.exp(joint - top)
    total = e.sum(-1, keepdim=True)
    increment = (torch.log(total) + top).squeeze(-1)
    return increment, joint - increment.unsqueeze(-1), e / total


def _predictive(model, y, mask, k, obs, pred_w, prior_lw, pred_mean) -> Predictive:
    """The step's :class:`Predictive` from the predicted measurements ``obs [..., N, dy]``."""
    if plain_residual(model):
        y_hat = (pred_w @ obs).squeeze(-2)
        obs_dev = rowwise(torch.sub, obs, y_hat.unsqueeze(-2))
    else:  # angles: averaged as residuals about one particle's, not as raw numbers
        y_hat, obs_dev = wrapped_spread(model, obs, pred_w.squeeze(-2))
    y_cov = (obs_dev * pred_w.transpose(-1, -2)).transpose(-1, -2) @ obs_dev
    innovation = model.measurement_residual(y, y_hat)
    try:
        R = model.measurement_cov(k + 1)
    except NotImplementedError as error:  # a noise without a covariance (Cauchy)
        raise NotImplementedError(
            f"{error}; the particle filter's innovation covariance adds the measurement "
            "noise's: pass innovations=False to filter without it"
        ) from error
    if mask is not None:
        eye = torch.eye(R.shape[-1], dtype=R.dtype, device=R.device)
        innovation, _, R, _ = masked_measurement(innovation, eye, R, mask)
        mf = mask.to(y_cov.dtype)
        y_cov = y_cov * (mf.unsqueeze(-1) * mf.unsqueeze(-2))
    return Predictive(prior_lw, pred_mean, innovation, symmetrize(y_cov + R))


def _default_measurement_density(model: StateSpaceModel) -> bool:
    """Whether ``model.measurement_log_prob`` is the base class's ``log p(y − h(x))`` with
    the noise module at every step (no ``measurement_cov`` of a subclass to follow)."""
    return (type(model).measurement_log_prob is StateSpaceModel.measurement_log_prob
            and not model._varying_noise("measurement_cov"))  # fmt: skip


def _moments(
    particles: Tensor, weights: Tensor, cov_dims: int | None = None
) -> tuple[Tensor, Tensor]:
    """Mean ``[..., d]`` and covariance ``[..., c, c]`` of ``particles [..., N, d]`` under
    normalised ``weights [..., N]``; the covariance of the first ``c = cov_dims``
    components (default all ``d``)."""
    w = weights.unsqueeze(-2)
    mean = _weighted_mean(w, particles)
    # deviations laid out [..., c, N]: the subtraction and the weighting then broadcast
    # along the long particle axis (a short last axis runs ~2x slower on CPU); no copy
    # for component-major particles ([..., d, N] in memory)
    rows, centre = particles.transpose(-1, -2), mean.unsqueeze(-1)
    if cov_dims is not None:
        rows, centre = rows[..., :cov_dims, :], centre[..., :cov_dims, :]
    dev = rows.contiguous() - centre
    cov = (dev * w) @ dev.transpose(-1, -2)
    return mean, symmetrize(cov)


def _weighted_mean(w: Tensor, particles: Tensor) -> Tensor:
    """``Σᵢ wᵢ xᵢ`` ``[..., d]`` for row weights ``w [..., 1, N]`` and ``particles [..., N, d]``:
    one batched product (one run: a vector-matrix product, the same numbers without the
    two reshapes)."""
    if particles.dim() == 2:
        return w.squeeze(0) @ particles
    return (w @ particles).squeeze(-2)  # [..., 1, N] @ [..., N, dx]


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
    generator: torch.Generator | Generators | None = None,
    resample_generator: torch.Generator | None = None,
    return_particles: bool = False,
    initial_state: ParticleState | None = None,
    hooks: Sequence[StepHook] = (),
    nonfinite: NonFinite | str = NonFinite.RAISE,
    innovations: bool = True,
    cov_dims: int | None = None,
) -> ParticleFilterResult:
    """Particle filter over a whole sequence: :class:`ParticleFilter` in the open loop.

    Args:
        model: any :class:`~difffilter.StateSpaceModel`.
        ys: measurements ``[..., T, dy]``; us: inputs ``[..., T, du]`` or ``None``.
        num_particles, resampler, proposal, likelihood, ess_threshold, hooks,
            innovations, cov_dims: as in :class:`ParticleFilter`.
        mask: received measurement entries ``[..., T, dy]`` or ``None``.
        generator: source of every random draw (prior, proposal; resampling too unless
            ``resample_generator`` is given — separate streams keep common random numbers
            aligned across estimators), or :class:`~difffilter.estimator.Generators`.
        return_particles: also return particles ``[..., T, N, dx]`` and log-weights
            ``[..., T, N]`` (memory ``O(T N)``).
        initial_state: start from this :class:`ParticleState` instead of the prior.
        nonfinite: :class:`~difffilter.NonFinite` (``RAISE`` default, or ``SKIP``), as in
            :func:`difffilter.kalman_filter` (skipped entries are counted in
            ``nonfinite_skipped``).

    Inputs are validated first (:func:`difffilter._checks.check_sequence_inputs`);
    ``resampler``, ``proposal`` and ``likelihood`` must be objects, not strings. A step
    at which every weight of a run underflows is recovered and flagged in
    ``degenerate`` (module docstring).

    Returns:
        :class:`~difffilter.results.ParticleFilterResult`: weighted means ``[..., T, dx]``,
        covariances, innovations and their covariances, ``log_likelihood [...]`` (the
        particle estimate), ``ess [..., T]``, ``resampled [..., T]``, ``degenerate [..., T]``,
        and in ``records`` what the hooks (and a stateful likelihood) recorded.
    """
    check_positive_int(num_particles, "num_particles")
    dx = model.dim_x if initial_state is None else initial_state.particles.shape[-1]
    pf = ParticleFilter(
        num_particles, resampler=resampler, proposal=proposal, likelihood=likelihood,
        ess_threshold=ess_threshold, hooks=hooks, innovations=innovations,
        cov_dims=_check_cov_dims(cov_dims, dx),
    )  # fmt: skip
    gens = Generators.of(generator)
    if resample_generator is not None:
        gens = gens._replace(resample=resample_generator)
    carry = None if initial_state is None else pf.attach(initial_state, model, gens)
    collect = None
    if return_particles:

        def collect(carry, out):
            return {"particles": carry.particles, "log_weights": carry.log_weights}

    out = open_loop(pf, model, ys, us, mask=mask, generator=gens, carry=carry,
                    nonfinite=nonfinite, collect=collect)  # fmt: skip
    result = particle_result(out)
    result.start = 0 if initial_state is None else int(initial_state.k)  # (the smoother's)
    return result


#: The keys of a particle filter's stacked extras that are fields of its result.
_PF_FIELDS = ("ess", "resampled", "degenerate", "particles", "log_weights")
_FILTER_KEYS = (
    "pred_means", "pred_covs", "innovations", "innovation_covs",
    "log_likelihood_increments", "log_likelihood", "nonfinite_skipped",
)  # fmt: skip
#: The extras a particle filter writes itself: a stateful likelihood's or a step hook's
#: record of one of these names would replace the filter's own (``extras = {"ess": …,
#: **record}``) or be replaced by it, and is refused (:func:`_checked_record`).
_RESERVED_KEYS = frozenset(_PF_FIELDS + _FILTER_KEYS + ("prior_log_weights",))


def particle_result(out) -> ParticleFilterResult:
    """The :class:`~difffilter.results.ParticleFilterResult` of a particle filter's
    :class:`~difffilter.EstimatorOutput` (what :func:`~difffilter.loop.open_loop` stacks)."""
    x = out.extras
    records = {k: v for k, v in x.items() if k not in _PF_FIELDS + _FILTER_KEYS}
    return ParticleFilterResult.from_output(
        out, **{k: x.get(k) for k in _PF_FIELDS}, records=records
    )


# The one-run step (below the classes it builds on: it imports them from this module).
from . import _pf_host_step as _host_step  # noqa: E402
from . import _pf_single_run as _single_run  # noqa: E402
