"""The modified particle filter of Table 2 and the normal PF with its PoA detector.

Sadeghzadeh-Nokhodberiz, Meskin & Hasanzadeh, IEEE Access 2022. Both are compositions
of the particle-filter parts of :mod:`difffilter.particle` (``particle_step``,
``particle_filter``, the bootstrap proposal, likelihood objects, resamplers) with the PoA
detector of :mod:`difffilter.fdi.poa`.

**Normal PF + PoA** (Sec. III): a bootstrap PF on the received ``ỹ``; at each step
``β_k = Σ_{‖ỹ − G x^i‖ > η} w^i`` (eqs 14, 17) and ``l̂_k = [β_k > ζ]``
(:func:`particle_filter_poa`).

**Modified PF** (Table 2), one step ``k − 1 → k``::

    1    x_k^i ~ p(x_k | x_{k−1}^i)                         (resample first if the ESS asks)
    2-1  x̃_k^{i+} = x_k^i + K (ỹ_k − G x_k^i),  K = Q Gᵀ (R + G Q Gᵀ)⁻¹          (35)–(36)
    2-2  β̃_k = Σ_{i: ‖ỹ_k − G x̃_k^{i+}‖ > η} w̃_k^{i+},  w̃_k^{i+} = w_{k−1}^i   (29), (58)
    2-3  l̂_k = [β̃_k > ζ]                                                          (46), (53)
    3-0  γ̂_k: the oracle γ_k (the paper's tables), a noisy oracle, or an estimator
    3-1  w_k^i ∝ p(ỹ_k − l̂_k γ̂_k | x_k^i) w_{k−1}^i                                 (59)
    3-2  x̂_k = Σ_i w_k^i x_k^i                                                     (60)

The corrected particles ``x̃^{i+}`` serve detection only; the uncorrected ``x_k^i`` are
propagated, so the estimate is unbiased given a correct ``l̂_k, γ̂_k`` (eqs 54–57). With
resampling at every step ``w_{k−1}^i = 1/N`` and step 2-2 is eq. (58) exactly.

Step 1 is :func:`~difffilter.particle.particle_step` with :class:`FlatLikelihood` (the
likelihood of "no measurement": it keeps the predictive weights ``w_{k−1}``), steps 3-1/3-2
are :func:`reweight` with :class:`AttackCompensatedLikelihood`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from .._checks import check_filter_inputs
from ..particle import (
    ModelLikelihood,
    ParticleState,
    particle_filter,
    particle_init,
    particle_step,
    weighted_moments,
)
from ..resampling import Systematic
from ..results import ParticleFilterResult
from .attack_estimation import BiasAttackEstimator
from .poa import (
    PoADetector,
    RunningAttackRate,
    literal_gaussian_density,
    literal_probability_of_attack,
    modified_pf_gain,
    probability_of_attack,
)

__all__ = [
    "kalman_corrected_particles",
    "corrected_residuals",
    "FlatLikelihood",
    "AttackCompensatedLikelihood",
    "LiteralGaussianLikelihood",
    "reweight",
    "modified_pf_detect",
    "modified_pf_estimate",
    "modified_particle_filter",
    "ModifiedPFResult",
    "particle_filter_poa",
    "PoAFilterResult",
    "prior_log_weights",
]


# ----------------------------------------------------------------------------- pieces


def kalman_corrected_particles(particles: Tensor, y: Tensor, G: Tensor, K: Tensor) -> Tensor:
    """Eq. (36): ``x̃^{i+} = x^i + K (ỹ − G x^i)``.

    Shapes: ``particles [..., N, dx]``, ``y [..., dy]``, ``G [dy, dx]``, ``K [dx, dy]`` →
    ``[..., N, dx]``.
    """
    innov = y.unsqueeze(-2) - particles @ G.transpose(-1, -2)
    return particles + innov @ K.transpose(-1, -2)


def corrected_residuals(particles: Tensor, y: Tensor, G: Tensor, K: Tensor) -> Tensor:
    """``z̃^{i+} = ỹ − G x̃^{i+} = (I − G K)(ỹ − G x^i)`` ``[..., N, dy]`` (eqs 36, 58)."""
    innov = y.unsqueeze(-2) - particles @ G.transpose(-1, -2)
    eye = torch.eye(G.shape[-2], dtype=G.dtype, device=G.device)
    return innov @ (eye - G @ K).transpose(-1, -2)


class FlatLikelihood:
    """``log p = 0`` for every particle: a step that only propagates (keeps ``w_{k−1}``)."""

    def __call__(self, model, y, particles, k, mask) -> Tensor:
        return particles.new_zeros(particles.shape[:-1])


class AttackCompensatedLikelihood:
    """Eq. (59): ``log p(ỹ_k − l̂_k γ̂_k | x_k^i)``, the measurement with the attack removed.

    Args:
        flags: ``l̂_k`` ``[...]`` (bool or 0/1).
        gamma_hat: ``γ̂_k`` ``[..., dy]``.
        base: the clean-measurement likelihood (default :class:`ModelLikelihood`).
    """

    def __init__(self, flags: Tensor, gamma_hat: Tensor, base=None):
        self.flags, self.gamma_hat = flags, gamma_hat
        self.base = base if base is not None else ModelLikelihood()

    def __call__(self, model, y, particles, k, mask) -> Tensor:
        shift = self.flags.to(y.dtype).unsqueeze(-1) * self.gamma_hat.to(y.dtype)
        return self.base(model, y - shift, particles, k, mask)


class LiteralGaussianLikelihood:
    """Diagnostic: the Gaussian density evaluated literally in float64, then its log.

    ``log[(2π)^{−m/2}|R|^{−1/2} exp(−½ rᵀR⁻¹r)]`` with the density formed first, so it is
    ``−inf`` wherever the density underflowed. A row in which *every* particle underflowed
    gets zeros instead (the guard a naive ``if sum(w) == 0`` implementation needs to keep
    running; the step then keeps its predictive weights). Its PoA must be computed with
    :func:`~difffilter.fdi.poa.literal_probability_of_attack`, which keeps the NaN.
    Requires a Gaussian measurement noise (``model.measurement_cov``) and no mask.
    """

    def __call__(self, model, y, particles, k, mask) -> Tensor:
        if mask is not None:
            raise ValueError(
                "LiteralGaussianLikelihood does not support a measurement mask (mask must be None)"
            )
        residuals = y.unsqueeze(-2) - model.observe(particles, k)
        dens = literal_gaussian_density(residuals, model.measurement_cov(k))
        log_dens = torch.log(dens)
        dead = (dens == 0).all(-1, keepdim=True)
        return torch.where(dead, torch.zeros_like(log_dens), log_dens).to(particles.dtype)


def reweight(log_weights: Tensor, log_likelihood: Tensor) -> tuple[Tensor, Tensor]:
    """Bayes' rule in log space: ``log w_k = log w_{k−1} + ℓ − log Σ_j exp(log w_{k−1}^j + ℓ^j)``.

    Shapes ``[..., N]`` → ``(normalised log-weights [..., N], log-evidence increment [...])``.
    """
    joint = log_weights + log_likelihood
    increment = torch.logsumexp(joint, dim=-1)
    return joint - increment.unsqueeze(-1), increment


def prior_log_weights(result: ParticleFilterResult, initial_log_weights: Tensor) -> Tensor:
    """Predictive weights ``log w_{k−1}`` of the particles ``x_k`` of a filter run ``[..., T, N]``.

    Uniform where the filter resampled before step ``t``; the previous posterior
    weights otherwise (``initial_log_weights [..., N]`` before the first step).
    Needs ``return_particles=True`` (the run's ``log_weights``).
    """
    if result.log_weights is None:
        raise ValueError("result must come from a filter run with return_particles=True")
    lw = result.log_weights
    prev = torch.cat(
        [initial_log_weights.unsqueeze(-2).expand(lw[..., :1, :].shape), lw[..., :-1, :]], dim=-2
    )
    uniform = torch.full_like(prev, -math.log(lw.shape[-1]))
    return torch.where(result.resampled.unsqueeze(-1), uniform, prev)


def _measurement_matrices(model, k: int) -> tuple[Tensor, Tensor, Tensor]:
    if not hasattr(model, "observation_matrix"):
        raise ValueError(
            "the modified PF needs a linear measurement y = G x + v: model must provide observation_matrix(k)"
        )
    G = model.observation_matrix(k)
    return G, model.process_cov(k - 1), model.measurement_cov(k)


def modified_pf_detect(
    model,
    state: ParticleState,
    y: Tensor,
    u: Tensor | None = None,
    *,
    detector: PoADetector,
    zeta: Tensor | float | None = None,
    gain: Tensor | None = None,
    resampler=None,
    ess_threshold: float = 1.0,
    generator: torch.Generator | None = None,
    resample_generator: torch.Generator | None = None,
):
    """Table 2, steps 1–2: propagate, correct the particles (eq. 36) and detect (eq. 58).

    Args:
        state: posterior particle set of ``x_{k−1}`` (particles ``[..., N, dx]``).
        y: received ``ỹ_k`` ``[..., dy]``; u: input ``u_{k−1}`` or ``None``.
        detector: :class:`PoADetector` (``η``, and ``ζ`` unless ``zeta`` is given).
        zeta: this step's ``ζ`` (number or ``[...]``; Remark 6), overriding the detector's.
        gain: ``K`` ``[dx, dy]`` of eq. (35) (computed from the model when ``None``).
        resampler, ess_threshold, generator, resample_generator: as in
            :func:`~difffilter.particle.particle_step` (default systematic resampling at
            every step; ``generator`` draws the propagation noise).

    Returns ``(pred_state, pred_out, beta [...], alarm [...])``: ``pred_state`` holds the
    uncorrected ``x_k^i`` with the predictive log-weights ``log w_{k−1}`` and
    ``pred_out`` the predictive moments (``pred_out.innovation`` ``ỹ − E[G x_k]`` and its
    covariance, used by γ̂ estimators).
    """
    pred_state, pred_out = particle_step(
        model,
        state,
        y,
        u,
        None,
        resampler=resampler if resampler is not None else Systematic(),
        likelihood=FlatLikelihood(),
        ess_threshold=ess_threshold,
        generator=generator,
        resample_generator=resample_generator,
    )
    G, Q, R = _measurement_matrices(model, pred_state.k)
    K = gain if gain is not None else modified_pf_gain(G, Q, R).to(y.dtype)
    residuals = corrected_residuals(pred_state.particles, y, G.to(y.dtype), K)
    beta = probability_of_attack(residuals, detector.eta, pred_state.log_weights)
    z = detector.zeta if zeta is None else zeta
    alarm = beta > (z if not isinstance(z, Tensor) else z.to(beta.dtype))
    return pred_state, pred_out, beta, alarm


def modified_pf_estimate(
    model,
    pred_state: ParticleState,
    y: Tensor,
    alarm: Tensor,
    gamma_hat: Tensor,
    *,
    base_likelihood=None,
) -> tuple[ParticleState, Tensor, Tensor, Tensor]:
    """Table 2, steps 3-1 and 3-2: weight the uncorrected particles by eq. (59), estimate by (60).

    Returns ``(state, mean [..., dx], cov [..., dx, dx], ess [...])``.
    """
    lik = AttackCompensatedLikelihood(alarm, gamma_hat, base_likelihood)
    log_lik = lik(model, y, pred_state.particles, pred_state.k, None)
    log_w, _ = reweight(pred_state.log_weights, log_lik)
    mean, cov = weighted_moments(pred_state.particles, log_w)
    ess = torch.exp(-torch.logsumexp(2.0 * log_w, dim=-1))
    return ParticleState(pred_state.particles, log_w, pred_state.k), mean, cov, ess


# ------------------------------------------------------------------------------ filters


@dataclass
class ModifiedPFResult:
    """Output of :func:`modified_particle_filter` (time index ``t`` ↔ ``k = t + 1``).

    Attributes:
        means: ``x̂_k`` (eq. 60) ``[..., T, dx]``; covs ``[..., T, dx, dx]``.
        pred_means: ``E[x_k | ỹ_{1:k−1}]`` ``[..., T, dx]``.
        beta: PoA ``β̃_k`` (eq. 58) ``[..., T]``; alarms: ``l̂_k`` ``[..., T]`` (bool).
        zeta: the threshold used at each step ``[..., T]``.
        gamma_hat: ``γ̂_k`` ``[..., T, dy]`` (used only where ``alarms``).
        ess: effective sample size after weighting ``[..., T]``.
        attack_rate: final ``p̂_l`` ``[...]`` (Remark 6) or ``None`` when ``p_l`` was known.
    """

    means: Tensor
    covs: Tensor
    pred_means: Tensor
    beta: Tensor
    alarms: Tensor
    zeta: Tensor
    gamma_hat: Tensor
    ess: Tensor
    attack_rate: Tensor | None = None

    def detach(self) -> ModifiedPFResult:
        return ModifiedPFResult(
            **{
                f.name: (v.detach() if isinstance(v := getattr(self, f.name), Tensor) else v)
                for f in fields(self)
            }
        )


def modified_particle_filter(
    model,
    ys: Tensor,
    *,
    num_particles: int,
    detector: PoADetector,
    gamma_hat: Tensor | BiasAttackEstimator,
    attack_rate: RunningAttackRate | None = None,
    resampler=None,
    ess_threshold: float = 1.0,
    generator: torch.Generator | None = None,
    resample_generator: torch.Generator | None = None,
    initial_state: ParticleState | None = None,
    base_likelihood=None,
) -> ModifiedPFResult:
    """The modified PF of Table 2 over a sequence ``ys [..., T, dy]`` of received ``ỹ_k``.

    Args:
        model: a model with a linear measurement (``observation_matrix``) and Gaussian
            process noise; the four-tank plant is one.
        num_particles: ``N``.
        detector: :class:`PoADetector` with ``η`` (Theorem 1) and ``ζ`` (eqs 46, 53).
        gamma_hat: ``γ̂`` as a tensor ``[..., T, dy]`` (the oracle ``γ_k`` or a noisy
            version), or a :class:`BiasAttackEstimator` fed with the flagged residuals.
        attack_rate: :class:`RunningAttackRate` for unknown ``p_l`` (Remark 6): ``ζ``
            then comes from it, not from ``detector``.
        resampler, ess_threshold: default systematic resampling at every step (1.0),
            which makes step 2-2 eq. (58) exactly.
        generator: initial particles (unless ``initial_state``) and propagation noise;
            resample_generator: resampling uniforms (separate streams keep common
            random numbers aligned across estimators).
        initial_state: start from this particle set instead of the prior.
        base_likelihood: clean-measurement likelihood of eq. (59) (default the model's).
    """
    check_filter_inputs(
        model, ys, resampler=resampler, ess_threshold=ess_threshold, gamma_hat=gamma_hat
    )
    if not isinstance(detector, PoADetector):
        raise ValueError(f"detector must be a PoADetector; got {type(detector).__name__}")
    if ys.dim() < 2 or ys.shape[-1] != model.dim_y:
        raise ValueError(f"ys must have shape [..., T, {model.dim_y}]; got {tuple(ys.shape)}")
    batch, T = ys.shape[:-2], ys.shape[-2]
    estimator = gamma_hat if isinstance(gamma_hat, BiasAttackEstimator) else None
    if estimator is None:
        if not isinstance(gamma_hat, Tensor) or gamma_hat.shape[-2:] != ys.shape[-2:]:
            raise ValueError(
                f"gamma_hat must be a BiasAttackEstimator or a tensor [..., {T}, {model.dim_y}]; "
                f"got {getattr(gamma_hat, 'shape', type(gamma_hat).__name__)}"
            )
    state = (
        initial_state
        if initial_state is not None
        else particle_init(model, num_particles, batch, generator)
    )
    G, Q, R = _measurement_matrices(model, 1)
    gain = None if getattr(model, "time_varying", False) else modified_pf_gain(G, Q, R).to(ys.dtype)
    est_state = estimator.init(batch) if estimator is not None else None
    rate_state = (
        attack_rate.init(batch, dtype=ys.dtype, device=ys.device)
        if attack_rate is not None
        else None
    )
    rec: dict[str, list[Tensor]] = {
        k: [] for k in ("mean", "cov", "pred", "beta", "alarm", "zeta", "ghat", "ess")
    }
    for t in range(T):
        y = ys[..., t, :]
        zeta = (
            attack_rate.zeta(rate_state)
            if attack_rate is not None
            else torch.full(batch, detector.zeta, dtype=ys.dtype, device=ys.device)
        )
        pred_state, pred_out, beta, alarm = modified_pf_detect(
            model,
            state,
            y,
            detector=detector,
            zeta=zeta,
            gain=gain,
            resampler=resampler,
            ess_threshold=ess_threshold,
            generator=generator,
            resample_generator=resample_generator,
        )
        if attack_rate is not None:
            rate_state = attack_rate.update(rate_state, alarm)
        if estimator is not None:
            est_state, g_hat, _ = estimator.step(
                est_state, pred_out.innovation, pred_out.innovation_cov, alarm
            )
        else:
            g_hat = gamma_hat[..., t, :]
        state, mean, cov, ess = modified_pf_estimate(
            model, pred_state, y, alarm, g_hat, base_likelihood=base_likelihood
        )
        for key, val in zip(rec, (mean, cov, pred_out.mean, beta, alarm, zeta, g_hat, ess)):
            rec[key].append(val)
    stack = {k: torch.stack(v, dim=len(batch)) for k, v in rec.items()}
    return ModifiedPFResult(
        means=stack["mean"],
        covs=stack["cov"],
        pred_means=stack["pred"],
        beta=stack["beta"],
        alarms=stack["alarm"],
        zeta=stack["zeta"],
        gamma_hat=stack["ghat"],
        ess=stack["ess"],
        attack_rate=attack_rate.estimate(rate_state) if attack_rate is not None else None,
    )


@dataclass
class PoAFilterResult:
    """Output of :func:`particle_filter_poa`: the filter run plus its PoA detector.

    Attributes:
        filter: the :class:`~difffilter.results.ParticleFilterResult` (with particles).
        beta: ``β_k`` ``[..., T]`` (NaN where a literal-density row underflowed).
        alarms: ``β_k > ζ`` ``[..., T]`` (false where ``β_k`` is NaN).
        prior_log_weights: predictive weights ``log w_{k−1}`` ``[..., T, N]``.
    """

    filter: ParticleFilterResult
    beta: Tensor
    alarms: Tensor
    prior_log_weights: Tensor


def particle_filter_poa(
    model,
    ys: Tensor,
    *,
    num_particles: int,
    detector: PoADetector,
    literal: bool = False,
    likelihood=None,
    resampler=None,
    ess_threshold: float = 1.0,
    generator: torch.Generator | None = None,
    resample_generator: torch.Generator | None = None,
    initial_state: ParticleState | None = None,
) -> PoAFilterResult:
    """The normal (bootstrap) PF on ``ys [..., T, dy]`` with the PoA detector of eqs (10)–(17).

    ``β_k = Σ_{‖y_k − G x_k^i‖ > η} w_k^i`` with the filter's posterior weights (eq. 17
    when it resamples every step). ``literal=True`` runs the diagnostic variant: weights
    from :class:`LiteralGaussianLikelihood` and the PoA of
    :func:`~difffilter.fdi.poa.literal_probability_of_attack` (NaN → no alarm when every
    density underflows). Other arguments as in :func:`modified_particle_filter`;
    ``likelihood`` overrides the weighting likelihood (log-space mode only).
    """
    check_filter_inputs(model, ys, resampler=resampler, ess_threshold=ess_threshold)
    if not isinstance(detector, PoADetector):
        raise ValueError(f"detector must be a PoADetector; got {type(detector).__name__}")
    if literal and likelihood is not None:
        raise ValueError("pass either literal=True or a likelihood, not both")
    batch = ys.shape[:-2]
    state = (
        initial_state
        if initial_state is not None
        else particle_init(model, num_particles, batch, generator)
    )
    res = particle_filter(
        model,
        ys,
        num_particles=num_particles,
        resampler=resampler if resampler is not None else Systematic(),
        likelihood=LiteralGaussianLikelihood() if literal else likelihood,
        ess_threshold=ess_threshold,
        generator=generator,
        resample_generator=resample_generator,
        return_particles=True,
        initial_state=state,
    )
    G = model.observation_matrix(1) if hasattr(model, "observation_matrix") else None
    obs = (
        res.particles @ G.transpose(-1, -2).to(ys.dtype)
        if G is not None
        else model.observe(res.particles, 1)
    )
    residuals = ys.unsqueeze(-2) - obs  # [..., T, N, dy]
    prior = prior_log_weights(res, state.log_weights)
    if literal:
        beta = literal_probability_of_attack(
            residuals, model.measurement_cov(1), detector.eta, torch.exp(prior)
        )
        beta = beta.to(ys.dtype)
    else:
        beta = probability_of_attack(residuals, detector.eta, res.log_weights)
    return PoAFilterResult(res, beta, beta > detector.zeta, prior)
