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

import torch
from torch import Tensor

from .._checks import check_filter_inputs
from .._steps import StepRecorder
from ..estimator import Detection, EstimatorOutput
from ..kalman import kalman_gain
from ..linalg import masked_measurement
from ..particle import (
    ModelLikelihood,
    ParticleState,
    particle_filter,
)
from ..resampling import Systematic
from .attack_estimation import BiasAttackEstimator
from .poa import (
    PoADetector,
    RunningAttackRate,
    literal_gaussian_density,
    literal_probability_of_attack,
    probability_of_attack,
)

__all__ = [
    "kalman_corrected_particles",
    "corrected_residuals",
    "FlatLikelihood",
    "AttackCompensatedLikelihood",
    "LiteralGaussianLikelihood",
    "reweight",
    "ModifiedPFWeighting",
    "modified_particle_filter",
    "particle_filter_poa",
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


def _linear_measurement(
    model, k: int, mask: Tensor | None, at: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """``(G, K)`` of eq. (35) at step ``k``, with the unreceived rows of ``G`` removed.

    ``G`` is the model's ``observation_matrix(k)``; a nonlinear measurement is linearised
    at ``at [..., dx]`` (the predictive particle mean), as an EKF would. Without a mask and
    linearisation ``G [dy, dx]`` and ``K [dx, dy]`` are shared by every run; otherwise both
    carry the batch dimensions (``K`` has zero columns for unreceived entries,
    :func:`~difffilter.linalg.masked_measurement`).
    """
    if hasattr(model, "observation_matrix"):
        G = model.observation_matrix(k)
    elif at is not None:
        G = model.observation_jacobian(at, k)
    else:
        raise ValueError("a nonlinear measurement needs a linearisation point (at=)")
    Q, R = model.process_cov(k - 1), model.measurement_cov(k)
    if mask is not None:
        G = G.expand(mask.shape[:-1] + G.shape[-2:])
        _, G, R, _ = masked_measurement(torch.zeros_like(mask, dtype=G.dtype), G, R, mask)
    K, _ = kalman_gain(Q @ G.transpose(-1, -2), G @ Q @ G.transpose(-1, -2) + R)
    return G, K


class ModifiedPFWeighting:
    """Table 2, steps 2–3 as the particle filter's likelihood: detect, then compensate.

    With the predictive particles ``x_k^i`` and weights ``w_{k−1}`` of the step
    (:class:`~difffilter.particle.Predictive`)::

        2-1/2-2  β̃_k = Σ_{‖(I − G K)(ỹ_k − h(x_k^i))‖ > η} w_{k−1}^i       (36), (58)
        2-3      l̂_k = [β̃_k > ζ_k]                                          (46), (53)
        3-0      γ̂_k: given ``[..., T, dy]``, or a BiasAttackEstimator fed the flagged innovation
        3-1      log p(ỹ_k − l̂_k γ̂_k | x_k^i)                                 (59)

    so ``particle_step(..., likelihood=ModifiedPFWeighting(...))`` is one step of the
    modified PF (eq. 60 is the step's weighted mean) and :func:`modified_particle_filter`
    is :func:`~difffilter.particle_filter` with it. ``G`` is the model's
    ``observation_matrix`` or, for a nonlinear measurement, its Jacobian at the predictive
    mean; unreceived entries (``mask``) enter neither the correction nor the norm. Each
    call appends ``beta``, ``alarm``, ``zeta`` and ``gamma_hat`` to :attr:`records` (and
    leaves them in :attr:`last`).

    Args:
        detector: :class:`PoADetector` (``η``; ``ζ`` unless ``attack_rate`` is given).
        gamma_hat: tensor ``[..., T, dy]`` (indexed by the step) or a
            :class:`BiasAttackEstimator`.
        attack_rate: :class:`RunningAttackRate` (Remark 6) or ``None``.
        gain: ``(G, K)`` shared by every step (``None``: computed at each step).
        base_likelihood: clean-measurement likelihood of eq. (59) (default the model's).
    """

    uses_predictive = True

    def __init__(self, detector, gamma_hat, *, attack_rate=None, gain=None, base_likelihood=None):
        self.detector, self.gamma_hat, self.attack_rate, self.gain = (
            detector,
            gamma_hat,
            attack_rate,
            gain,
        )
        self.base = base_likelihood
        self.estimator = gamma_hat if isinstance(gamma_hat, BiasAttackEstimator) else None
        self.est_state = self.rate_state = None
        self.records, self.last = StepRecorder(), {}

    def __call__(self, model, y, particles, k, mask, *, predictive) -> Tensor:
        batch = y.shape[:-1]
        if self.attack_rate is not None:
            if self.rate_state is None:
                self.rate_state = self.attack_rate.init(batch, dtype=y.dtype, device=y.device)
            zeta = self.attack_rate.zeta(self.rate_state)
        else:
            zeta = torch.full(batch, self.detector.zeta, dtype=y.dtype, device=y.device)
        G, K = (
            m.to(y.dtype)
            for m in (self.gain or _linear_measurement(model, k, mask, at=predictive.mean))
        )
        if hasattr(model, "observation_matrix"):
            residuals = corrected_residuals(
                particles, y if mask is None else y * mask.to(y.dtype), G, K
            )
        else:  # z̃⁺ = (I − G K)(ỹ − h(x^i)), G the Jacobian at the predictive mean
            innov = y.unsqueeze(-2) - model.observe(particles, k)
            if mask is not None:
                innov = innov * mask.unsqueeze(-2).to(innov.dtype)
            eye = torch.eye(G.shape[-2], dtype=G.dtype, device=G.device)
            residuals = innov @ (eye - G @ K).transpose(-1, -2)
        beta = probability_of_attack(residuals, self.detector.eta, predictive.log_weights)
        alarm = beta > zeta
        if self.attack_rate is not None:
            self.rate_state = self.attack_rate.update(self.rate_state, alarm)
        if self.estimator is not None:
            if self.est_state is None:
                self.est_state = self.estimator.init(batch)
            flag = alarm if mask is None else alarm.unsqueeze(-1) & mask
            self.est_state, g_hat, _ = self.estimator.step(
                self.est_state, predictive.innovation, predictive.innovation_cov, flag
            )
        else:
            g_hat = self.gamma_hat[..., k - 1, :]
        self.last = {"beta": beta, "alarm": alarm, "zeta": zeta, "gamma_hat": g_hat}
        self.records.add(**self.last)
        return AttackCompensatedLikelihood(alarm, g_hat, self.base)(model, y, particles, k, mask)


def driver_settings(
    num_particles, resampler, ess_threshold, generator, resample_generator, initial_state
) -> dict:
    """The particle-driver keywords the FDI filters share (default: systematic resampling)."""
    return {
        "num_particles": num_particles,
        "resampler": resampler if resampler is not None else Systematic(),
        "ess_threshold": ess_threshold,
        "generator": generator,
        "resample_generator": resample_generator,
        "initial_state": initial_state,
    }


# ------------------------------------------------------------------------------ filters


def modified_particle_filter(
    model,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    mask: Tensor | None = None,
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
    fused: bool = False,
) -> EstimatorOutput:
    """The modified PF of Table 2 over a sequence ``ys [..., T, dy]`` of received ``ỹ_k``.

    Args:
        model: a model with Gaussian process noise; a linear measurement
            (``observation_matrix``, as the four-tank plant has) gives the paper's exact
            eq. (35); a nonlinear one is linearised at the predictive particle mean.
        us: inputs ``[..., T, du]`` or ``None``; mask: received entries ``[..., T, dy]``.
        num_particles: ``N``.
        detector: :class:`PoADetector` with ``η`` (Theorem 1) and ``ζ`` (eqs 46, 53);
            :meth:`PoADetector.from_model` derives both.
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
        fused: run the low-overhead implementation of :mod:`difffilter.fdi.fused`
            (the same algorithm and random numbers, equal up to round-off; about 20
            kernels per step, for real-time use of small particle sets). It needs a
            tensor ``gamma_hat``, a time-invariant model, systematic resampling at every
            step and none of ``us``, ``mask``, ``attack_rate``, ``base_likelihood``; it
            records no gradient and returns no ``covs``.

    Returns an :class:`~difffilter.EstimatorOutput`: ``means`` ``x̂_k`` (eq. 60),
    ``covs``, ``attack = l̂_k γ̂_k`` ``[..., T, dy]`` (the compensation applied),
    ``detection`` (scores ``β̃_k``, eq. 58; alarms ``l̂_k``; threshold ``ζ_k [..., T]``)
    and ``extras``: ``gamma_hat [..., T, dy]``, ``pred_means [..., T, dx]``,
    ``ess [..., T]`` and, with ``attack_rate``, ``attack_rate`` (final ``p̂_l`` ``[...]``).
    """
    if not isinstance(detector, PoADetector):
        raise ValueError(f"detector must be a PoADetector; got {type(detector).__name__}")
    ys, us, mask = check_filter_inputs(
        model, ys, us, mask, resampler=resampler, ess_threshold=ess_threshold, gamma_hat=gamma_hat
    )
    batch, T = ys.shape[:-2], ys.shape[-2]
    if fused:
        return _run_fused(
            model, ys, us, mask, num_particles, detector, gamma_hat, attack_rate, resampler,
            ess_threshold, generator, resample_generator, initial_state, base_likelihood,
        )  # fmt: skip
    if not isinstance(gamma_hat, BiasAttackEstimator) and (
        not isinstance(gamma_hat, Tensor) or gamma_hat.shape[-2:] != ys.shape[-2:]
    ):
        raise ValueError(
            f"gamma_hat must be a BiasAttackEstimator or a tensor [..., {T}, {model.dim_y}]; "
            f"got {getattr(gamma_hat, 'shape', type(gamma_hat).__name__)}"
        )
    shared = (
        mask is None
        and hasattr(model, "observation_matrix")
        and not getattr(model, "time_varying", False)
    )
    gain = tuple(m.to(ys.dtype) for m in _linear_measurement(model, 1, None)) if shared else None
    weighting = ModifiedPFWeighting(
        detector, gamma_hat, attack_rate=attack_rate, gain=gain, base_likelihood=base_likelihood
    )
    settings = driver_settings(
        num_particles, resampler, ess_threshold, generator, resample_generator, initial_state
    )
    res = particle_filter(model, ys, us, mask=mask, likelihood=weighting, **settings)
    r = weighting.records.stack(len(batch))
    extras = {"gamma_hat": r["gamma_hat"], "pred_means": res.pred_means, "ess": res.ess}
    if attack_rate is not None:
        extras["attack_rate"] = attack_rate.estimate(weighting.rate_state)
    return EstimatorOutput(
        means=res.means,
        covs=res.covs,
        attack=r["alarm"].unsqueeze(-1).to(ys.dtype) * r["gamma_hat"],
        detection=Detection(r["beta"], r["alarm"], r["zeta"]),
        extras=extras,
    )


def _run_fused(
    model, ys, us, mask, num_particles, detector, gamma_hat, attack_rate, resampler,
    ess_threshold, generator, resample_generator, initial_state, base_likelihood,
) -> EstimatorOutput:  # fmt: skip
    from .fused import FusedModifiedPF

    unsupported = {
        "us": us is not None,
        "mask": mask is not None,
        "attack_rate": attack_rate is not None,
        "base_likelihood": base_likelihood is not None,
        "gamma_hat (an estimator)": not isinstance(gamma_hat, Tensor),
        "resampler (not Systematic)": resampler is not None and type(resampler) is not Systematic,
        "ess_threshold (not 1.0)": ess_threshold != 1.0,
    }
    bad = [name for name, flag in unsupported.items() if flag]
    if bad:
        raise ValueError(f"fused=True does not support {', '.join(bad)}; use fused=False")
    if ys.dim() != 3:
        raise ValueError(f"fused=True needs ys of shape [B, T, dy]; got {tuple(ys.shape)}")
    pf = FusedModifiedPF(
        model, num_particles=num_particles, eta=float(detector.eta), zeta=detector.zeta
    )
    return pf.run(
        ys,
        gamma_hat,
        generator=generator,
        resample_generator=resample_generator,
        initial_particles=None if initial_state is None else initial_state.particles,
    )


def particle_filter_poa(
    model,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    mask: Tensor | None = None,
    num_particles: int,
    detector: PoADetector,
    literal: bool = False,
    likelihood=None,
    resampler=None,
    ess_threshold: float = 1.0,
    generator: torch.Generator | None = None,
    resample_generator: torch.Generator | None = None,
    initial_state: ParticleState | None = None,
    return_particles: bool = False,
) -> EstimatorOutput:
    """The normal (bootstrap) PF on ``ys [..., T, dy]`` with the PoA detector of eqs (10)–(17).

    ``β_k = Σ_{‖y_k − h(x_k^i)‖ > η} w_k^i`` with the filter's posterior weights (eq. 17
    when it resamples every step); unreceived entries (``mask``) do not enter the norm.
    ``literal=True`` runs the diagnostic variant: weights from
    :class:`LiteralGaussianLikelihood` and the PoA of
    :func:`~difffilter.fdi.poa.literal_probability_of_attack` (NaN → no alarm when every
    density underflows). Other arguments as in :func:`modified_particle_filter`;
    ``likelihood`` overrides the weighting likelihood (log-space mode only).

    Returns an :class:`~difffilter.EstimatorOutput` (``attack`` is ``None``; detection
    scores ``β_k``, threshold ``ζ``) with ``extras``: ``ess [..., T]``,
    ``log_likelihood [...]`` and, with ``return_particles=True``, ``particles
    [..., T, N, dx]``, their normalised ``log_weights [..., T, N]`` and
    ``prior_log_weights [..., T, N]`` (the predictive weights ``log w_{k−1}`` of ``x_k``).
    β is computed by a step hook of the one particle driver, so no particle history is kept.
    """
    if not isinstance(detector, PoADetector):
        raise ValueError(f"detector must be a PoADetector; got {type(detector).__name__}")
    if literal and likelihood is not None:
        raise ValueError("pass either literal=True or a likelihood, not both")
    if literal and mask is not None:
        raise ValueError("literal=True does not support a measurement mask (mask must be None)")
    ys, us, mask = check_filter_inputs(
        model, ys, us, mask, resampler=resampler, ess_threshold=ess_threshold
    )
    R = model.measurement_cov(1)

    def poa(model, y, m, state, out):
        residuals = y.unsqueeze(-2) - model.observe(state.particles, state.k)
        if m is not None:
            residuals = residuals * m.unsqueeze(-2).to(residuals.dtype)
        if literal:
            prior = torch.exp(out.prior_log_weights)
            beta = literal_probability_of_attack(residuals, R, detector.eta, prior).to(y.dtype)
        else:
            beta = probability_of_attack(residuals, detector.eta, state.log_weights)
        return (
            {"beta": beta, "prior_log_weights": out.prior_log_weights}
            if return_particles
            else {"beta": beta}
        )

    settings = driver_settings(
        num_particles, resampler, ess_threshold, generator, resample_generator, initial_state
    )
    weigh = LiteralGaussianLikelihood() if literal else likelihood
    res = particle_filter(
        model, ys, us, mask=mask, likelihood=weigh, hooks=(poa,), return_particles=return_particles,
        **settings,
    )  # fmt: skip
    beta = res.records["beta"]
    extras = {"ess": res.ess, "log_likelihood": res.log_likelihood}
    if return_particles:
        extras.update(particles=res.particles, log_weights=res.log_weights,
                      prior_log_weights=res.records["prior_log_weights"])  # fmt: skip
    return EstimatorOutput(
        means=res.means,
        covs=res.covs,
        detection=Detection(beta, beta > detector.zeta, detector.zeta),
        extras=extras,
    )
