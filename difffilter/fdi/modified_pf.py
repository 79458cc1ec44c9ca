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

The modified PF is :class:`~difffilter.ParticleFilter` whose likelihood is
:class:`ModifiedPFWeighting` (steps 2–3: it reads the step's predictive view, decides and
weighs with the compensated measurement; its running statistics live in the carry):
:class:`ModifiedParticleFilter`. The normal PF with PoA is the bootstrap PF with a step
hook computing ``β_k``: :class:`PoAParticleFilter`. Both report their decisions in the
step output (``score``, ``alarm``, ``threshold``, ``attack``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch
from torch import Tensor

from .._assignments import note_assignment
from .._checks import broadcast_or_none, check_filter_inputs, check_flag
from ..estimator import EstimatorOutput, Generators
from ..gaussian import kalman_gain
from ..linalg import masked_measurement
from ..loop import open_loop
from ..noise import Gaussian
from ..particle import ModelLikelihood, ParticleFilter, ParticleState, _default_measurement_density
from ..resampling import Systematic
from ..ssm import StateSpaceModel
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
    "ModifiedParticleFilter",
    "PoAParticleFilter",
    "modified_particle_filter",
    "particle_filter_poa",
]


# ----------------------------------------------------------------------------- pieces


def kalman_corrected_particles(particles: Tensor, y: Tensor, G: Tensor, K: Tensor) -> Tensor:
    """Eq. (36): ``x̃^{i+} = x^i + K (ỹ − G x^i)``.

    Shapes: ``particles [..., N, dx]``, ``y [..., dy]``, ``G [..., dy, dx]``, ``K [..., dx,
    dy]`` (one per run, or shared) → ``[..., N, dx]``. ``G`` and ``K`` are taken in the particles' dtype
    (:func:`~difffilter.fdi.modified_pf_gain` computes ``K`` in float64).
    """
    G, K = _correction_terms(particles, y, G, K)
    innov = y.unsqueeze(-2) - particles @ G.transpose(-1, -2)
    return particles + innov @ K.transpose(-1, -2)


def corrected_residuals(particles: Tensor, y: Tensor, G: Tensor, K: Tensor) -> Tensor:
    """``z̃^{i+} = ỹ − G x̃^{i+} = (I − G K)(ỹ − G x^i)`` ``[..., N, dy]`` (eqs 36, 58);
    arguments as :func:`kalman_corrected_particles` takes them."""
    G, K = _correction_terms(particles, y, G, K)
    innov = y.unsqueeze(-2) - particles @ G.transpose(-1, -2)
    eye = torch.eye(G.shape[-2], dtype=G.dtype, device=G.device)
    return innov @ (eye - G @ K).transpose(-1, -2)


def _correction_terms(particles, y, G, K) -> tuple[Tensor, Tensor]:
    """``(G, K)`` in the particles' dtype, every shape checked by name (float64 ``K`` with
    float32 particles, a wrong-length ``y`` or a numpy argument had failed inside torch:
    an apishapes trial)."""
    for name, t in (("particles", particles), ("y", y), ("G", G), ("K", K)):
        if not isinstance(t, Tensor) or not t.is_floating_point():
            got = t.dtype if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"{name} must be a floating tensor; got {got}")
    if particles.dim() < 2 or G.dim() < 2 or K.dim() < 2:
        raise ValueError(f"particles must be [..., N, dx], G [..., dy, dx] and K [..., dx, dy]; "
                         f"got {tuple(particles.shape)}, {tuple(G.shape)} and {tuple(K.shape)}")  # fmt: skip
    dy, dx = G.shape[-2:]
    if particles.shape[-1] != dx or y.shape[-1:] != (dy,) or tuple(K.shape[-2:]) != (dx, dy):
        raise ValueError(
            f"G [..., {dy}, {dx}] needs particles [..., N, {dx}], y [..., {dy}] and K "
            f"[..., {dx}, {dy}]; got {tuple(particles.shape)}, {tuple(y.shape)} and "
            f"{tuple(K.shape)}"
        )
    return G.to(particles.dtype), K.to(particles.dtype)


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
        residuals = model.measurement_residual(y.unsqueeze(-2), model.observe(particles, k))
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
    K, _ = kalman_gain(Q @ G.transpose(-1, -2), G @ Q @ G.transpose(-1, -2) + R, mask)
    return G, K


class WeightingState(NamedTuple):
    """The running state of :class:`ModifiedPFWeighting` (in the particle carry's ``aux``):
    Remark 6's ``rate`` (:class:`~difffilter.fdi.poa.AttackRateState` or ``None``), the
    attack estimator's ``estimator`` state (or ``None``) and the ``gain`` ``(G, K)`` given
    to the weighting (``None``: computed from the model at each step)."""

    rate: Any
    estimator: Any
    gain: Any


class ModifiedPFWeighting:
    """Table 2, steps 2–3 as the particle filter's likelihood: detect, then compensate.

    With the predictive particles ``x_k^i`` and weights ``w_{k−1}`` of the step
    (:class:`~difffilter.particle.Predictive`)::

        2-1/2-2  β̃_k = Σ_{‖(I − G K)(ỹ_k − h(x_k^i))‖ > η} w_{k−1}^i       (36), (58)
        2-3      l̂_k = [β̃_k > ζ_k]                                          (46), (53)
        3-0      γ̂_k: given ``[..., T, dy]``, or a BiasAttackEstimator fed the flagged innovation
        3-1      log p(ỹ_k − l̂_k γ̂_k | x_k^i)                                 (59)

    a :class:`~difffilter.particle.StepLikelihood` (its :class:`WeightingState` lives in
    the carry), so ``ParticleFilter(N, likelihood=ModifiedPFWeighting(...))`` steps the
    modified PF (eq. 60 is the step's weighted mean). ``G`` is the model's
    ``observation_matrix`` or, for a nonlinear measurement, its Jacobian at the predictive
    mean; unreceived entries (``mask``) enter neither the correction nor the norm. Each
    step records ``beta``, ``alarm``, ``zeta``, ``gamma_hat`` (and, with ``attack_rate``,
    the running ``attack_rate`` ``p̂_l``).

    Args:
        detector: :class:`PoADetector` (``η``; ``ζ`` unless ``attack_rate`` is given).
        gamma_hat: tensor ``[..., T, dy]`` (indexed by the step) or a
            :class:`BiasAttackEstimator`.
        attack_rate: :class:`RunningAttackRate` (Remark 6) or ``None``.
        gain: ``(G, K)`` shared by every step (``None``: computed from the model at each
            step, so that a model written in place mid-run is followed: a pair computed at
            ``init`` had met the new ``H`` with the old ``K``, β 0.11 off, an aliasing
            trial; a small linear solve against the step's ``N`` particles).
        base_likelihood: clean-measurement likelihood of eq. (59) (default the model's).
    """

    def __init__(self, detector, gamma_hat, *, attack_rate=None, gain=None, base_likelihood=None):
        self.detector, self.gamma_hat, self.attack_rate = detector, gamma_hat, attack_rate
        self.gain, self.base = gain, base_likelihood

    def __setattr__(self, name, value):
        # detector and gamma_hat checked whenever set, and a replacement counted: the next
        # step validates its carry against them in full (a table assigned after __init__
        # had never been read through ModifiedParticleFilter.gamma_hat: a red-team trial)
        if name == "detector":
            if not isinstance(value, PoADetector):
                raise ValueError(f"detector must be a PoADetector; got {type(value).__name__}")
        elif name == "gamma_hat":
            _check_gamma_hat(value)
            super().__setattr__(
                "estimator", value if isinstance(value, BiasAttackEstimator) else None
            )
        elif name == "estimator":  # (derived from gamma_hat: one source of truth)
            raise AttributeError("estimator follows gamma_hat: assign gamma_hat instead")
        replacing = (
            name in ("detector", "gamma_hat", "attack_rate", "base") and name in self.__dict__
        )
        super().__setattr__(name, value)
        if replacing:
            note_assignment()

    def check_fits(self, model, batch_shape) -> None:
        """The detector's ``η`` against ``batch_shape`` runs of ``model``, and the bias
        estimator's dimension against ``model.dim_y``."""
        self.detector.check_runs(batch_shape, model)
        if self.estimator is not None and self.estimator.dim != model.dim_y:
            raise ValueError(
                f"gamma_hat is a BiasAttackEstimator of dim {self.estimator.dim}; the model "
                f"measures {model.dim_y} entries (dim must be model.dim_y)"
            )

    def check_state(self, state: WeightingState, what: str) -> None:
        """``state`` must hold the running state this weighting keeps (``what`` names it)."""
        for kept, have, name in ((self.attack_rate, state.rate, "attack_rate"),
                                 (self.estimator, state.estimator, "a BiasAttackEstimator")):  # fmt: skip
            if kept is not None and have is None:
                start = ("its own initial state (initial_state=None)" if what == "initial_state"
                         else "its init (a detector or gamma_hat assigned since?)")  # fmt: skip
                raise ValueError(
                    f"{what}: the carry comes from a run without {name}, which this "
                    f"filter keeps: start this filter from {start}"
                )

    def init(self, model, batch_shape, dtype, device) -> WeightingState:
        self.check_fits(model, batch_shape)
        rate = None
        if self.attack_rate is not None:
            rate = self.attack_rate.init(batch_shape, dtype=dtype, device=device)
        est = None if self.estimator is None else self.estimator.init(batch_shape)
        return WeightingState(rate, est, self._gain_for(model, dtype))

    def _gain_for(self, model, dtype):
        """The given ``(G, K)`` of eq. (35) in ``dtype``, or ``None`` (from the model, per
        step)."""
        gain = self.gain
        return None if gain is None else tuple(m.to(dtype) for m in gain)

    def resume(self, state: WeightingState, model, batch_shape, dtype, device) -> WeightingState:
        """``state`` of a carry given as ``initial_state`` for ``model``: its gain that
        model's (the gain of the model the carry came from had tested another model's
        particles: β 0.72 for 0.66), and refused where it lacks the state this weighting
        keeps (a carry of a run without ``attack_rate`` or the bias estimator failed with an
        AttributeError: a red-team trial)."""
        self.check_state(state, "initial_state")
        return state._replace(gain=self._gain_for(model, dtype))

    def weigh(self, state: WeightingState, model, y, particles, k, mask, predictive):
        batch = y.shape[:-1]
        if self.attack_rate is not None:
            zeta = self.attack_rate.zeta(state.rate).to(y.dtype)  # (counted in float64)
        else:
            zeta = torch.full(batch, self.detector.zeta, dtype=y.dtype, device=y.device)
        gain = state.gain if mask is None else None
        G, K = (
            m.to(y.dtype) for m in (gain or _linear_measurement(model, k, mask, at=predictive.mean))
        )
        if hasattr(model, "observation_matrix"):
            residuals = corrected_residuals(
                particles, y if mask is None else y * mask.to(y.dtype), G, K
            )
        else:  # z̃⁺ = (I − G K)(ỹ − h(x^i)), G the Jacobian at the predictive mean
            innov = model.measurement_residual(y.unsqueeze(-2), model.observe(particles, k))
            if mask is not None:
                innov = innov * mask.unsqueeze(-2).to(innov.dtype)
            eye = torch.eye(G.shape[-2], dtype=G.dtype, device=G.device)
            residuals = innov @ (eye - G @ K).transpose(-1, -2)
        beta = probability_of_attack(residuals, self.detector.eta, predictive.log_weights)
        alarm = beta > zeta
        rate, est = state.rate, state.estimator
        record = {"beta": beta, "alarm": alarm, "zeta": zeta}
        if self.attack_rate is not None:
            rate = self.attack_rate.update(rate, alarm)
            record["attack_rate"] = self.attack_rate.estimate(rate).to(y.dtype)
        if self.estimator is not None:
            flag = alarm if mask is None else alarm.unsqueeze(-1) & mask
            innovation = predictive.innovation  # (the filter's own: no check needed)
            # the estimator's Kalman filter runs in its own dtype (float64 by default) and
            # γ̂ comes back in the measurements': a float32 model had recorded float64
            # attacks, and an estimator of float32 on a float64 model failed in a raw matmul
            own = self.estimator.model.H.dtype
            est, g_hat, _ = self.estimator._update(
                est,
                innovation.to(own),
                predictive.innovation_cov.to(own),
                self.estimator._flagged(flag, innovation),
            )
            g_hat = g_hat.to(y.dtype)
        else:
            # a shared γ̂ [T, dy] is recorded per run, so the records stack after the batch
            if k > self.gamma_hat.shape[-2]:  # (a bare IndexError at step T + 1)
                raise ValueError(
                    f"gamma_hat has {self.gamma_hat.shape[-2]} rows (steps) and step {k} needs "
                    "row k: give a row for every step the filter runs"
                )
            g_hat = self.gamma_hat[..., k - 1, :].to(y.dtype)
            g_hat = g_hat.expand(torch.broadcast_shapes(g_hat.shape, zeta.shape + y.shape[-1:]))
        record["gamma_hat"] = g_hat
        log_p = AttackCompensatedLikelihood(alarm, g_hat, self.base)(model, y, particles, k, mask)
        return WeightingState(rate, est, state.gain), log_p, record


def _check_gamma_hat(gamma_hat) -> None:
    if not isinstance(gamma_hat, (BiasAttackEstimator, Tensor)):
        raise ValueError(
            "gamma_hat must be a BiasAttackEstimator or a tensor [..., T, dy]; got "
            f"{type(gamma_hat).__name__}"
        )
    if isinstance(gamma_hat, Tensor) and gamma_hat.dim() < 2:  # a bare IndexError at step 1
        raise ValueError(
            "gamma_hat must be a tensor [..., T, dy] (one row per step); got shape "
            f"{tuple(gamma_hat.shape)}: for one γ̂ for every step, expand it to [T, dy]"
        )


class ModifiedParticleFilter(ParticleFilter):
    """The modified PF of Table 2 as an estimator object.

    Args:
        num_particles: ``N``.
        detector: :class:`PoADetector` with ``η`` (Theorem 1) and ``ζ`` (eqs 46, 53).
        gamma_hat: ``γ̂`` as a tensor ``[..., T, dy]`` (the oracle ``γ_k`` or a noisy
            version), or a :class:`BiasAttackEstimator` fed with the flagged residuals.
        attack_rate: :class:`RunningAttackRate` for unknown ``p_l`` (Remark 6).
        resampler, ess_threshold: default systematic resampling at every step (1.0),
            which makes step 2-2 eq. (58) exactly.
        base_likelihood: clean-measurement likelihood of eq. (59) (default the model's).
        fused: run whole sequences through the low-overhead implementation of
            :mod:`difffilter.fdi.fused` (the same algorithm and random numbers, equal up to
            round-off); it needs a tensor ``gamma_hat``, a time-invariant model, systematic
            resampling at every step and none of ``us``, ``mask``, ``attack_rate``,
            ``base_likelihood``. Where its other assumptions fail (runs not ``[B, T,
            dy]``, one ``η`` per run, a measurement noise other than ``N(0, R)``, or one
            random stream for the propagation and the resampling: give a
            ``resample_generator``, as the evaluation does, for the fast path) the run
            steps instead. It returns ``means``, ``attack``, ``detection`` (a float
            threshold ``ζ``) and ``extras["gamma_hat"]`` only, without gradients
            (``covs`` ``None``; none of the steps' other extras).

    Step output: the weighted mean (eq. 60), ``attack = l̂_k γ̂_k`` (the compensation
    applied), ``score`` ``β̃_k`` (eq. 58), ``alarm`` ``l̂_k``, ``threshold`` ``ζ_k [...]``,
    ``extras`` ``gamma_hat`` (and the particle filter's records).
    """

    def __init__(
        self,
        num_particles: int,
        detector: PoADetector,
        gamma_hat,
        *,
        attack_rate: RunningAttackRate | None = None,
        resampler=None,
        ess_threshold: float = 1.0,
        base_likelihood=None,
        fused: bool = False,
    ):
        _check_attack_rate_particles(attack_rate, num_particles)
        weighting = ModifiedPFWeighting(
            detector, gamma_hat, attack_rate=attack_rate, base_likelihood=base_likelihood
        )
        resampler = resampler if resampler is not None else Systematic()
        super().__init__(
            num_particles, resampler=resampler, likelihood=weighting, ess_threshold=ess_threshold
        )
        self.fused = fused  # (detector and gamma_hat: the weighting's, below)

    @property
    def fused(self) -> bool:
        """Whether whole sequences take :mod:`difffilter.fdi.fused`'s path. Assigned, it is
        checked against the filter's settings as the constructor checks it; the settings are
        checked again at every fused run (one assigned later, ``fused = True`` beside an
        ``attack_rate`` or a resampler other than systematic, had run the fused path without
        it: a fixed ζ for the running one, 0.045 off, and systematic draws for multinomial
        ones, means 0.023 off: a red-team trial)."""
        return self._fused

    @fused.setter
    def fused(self, fused) -> None:
        fused = check_flag(fused, "fused")
        if fused:
            self._check_fused_settings()
        self._fused = fused

    def _check_fused_settings(self, **assigned) -> None:
        """The fused path's assumptions, with the weighting's settings as they are or as
        ``assigned`` (``gamma_hat``, ``attack_rate``, ``base``) is about to make them."""
        w = self.likelihood
        now = {"gamma_hat": w.gamma_hat, "attack_rate": w.attack_rate, "base": w.base, **assigned}
        _check_fused(now["gamma_hat"], now["attack_rate"], now["base"], self.resampler,
                     self.ess_threshold)  # fmt: skip

    # The detector and γ̂ are the weighting's (the likelihood's) alone, read and assigned
    # through it: a copy kept here as well had been assigned and never read by the steps,
    # which weigh with the weighting's (a red-team trial).
    @property
    def detector(self) -> PoADetector:
        """The weighting's :class:`PoADetector` (``η``, ``ζ``)."""
        return self.likelihood.detector

    @detector.setter
    def detector(self, detector: PoADetector) -> None:
        self.likelihood.detector = detector  # (checked there, and the carries validated again)

    @property
    def gamma_hat(self):
        """The weighting's ``γ̂``: a tensor ``[..., T, dy]`` or a :class:`BiasAttackEstimator`."""
        return self.likelihood.gamma_hat

    @gamma_hat.setter
    def gamma_hat(self, gamma_hat) -> None:
        if self.fused:
            _check_gamma_hat(gamma_hat)
            self._check_fused_settings(gamma_hat=gamma_hat)
        self.likelihood.gamma_hat = gamma_hat

    # Remark 6's running rate and eq. (59)'s clean likelihood are the weighting's too: an
    # assignment here had made a new attribute the steps never read (the first threshold
    # 0.2 where a filter built with the rate gives 0.882: an options trial).
    @property
    def attack_rate(self):
        """The weighting's :class:`RunningAttackRate` (Remark 6), or ``None``."""
        return self.likelihood.attack_rate

    @attack_rate.setter
    def attack_rate(self, attack_rate) -> None:
        if attack_rate is not None and not isinstance(attack_rate, RunningAttackRate):
            raise ValueError(
                f"attack_rate must be a RunningAttackRate or None; got {type(attack_rate).__name__}"
            )
        _check_attack_rate_particles(attack_rate, self.num_particles)
        if self.fused:
            self._check_fused_settings(attack_rate=attack_rate)
        self.likelihood.attack_rate = attack_rate

    @property
    def base_likelihood(self):
        """The weighting's clean-measurement likelihood of eq. (59) (``None``: the model's)."""
        return self.likelihood.base

    @base_likelihood.setter
    def base_likelihood(self, base) -> None:
        if self.fused:
            self._check_fused_settings(base=base)
        self.likelihood.base = base

    def attach(self, state: ParticleState, model, generators: Generators) -> ParticleState:
        # (init's road too: an attack_rate of another N assigned before the first run)
        _check_attack_rate_particles(self.likelihood.attack_rate, self.num_particles)
        return super().attach(state, model, generators)

    def _check_carry(self, carry):
        super()._check_carry(carry)
        # (an attack_rate assigned to the weighting since, of another N, is met here: the
        # assignment has the next step validate its carry in full)
        _check_attack_rate_particles(self.likelihood.attack_rate, self.num_particles)
        if isinstance(carry.aux, WeightingState):  # (a detector or γ̂ assigned since its init)
            self.likelihood.check_fits(carry.model, carry.log_weights.shape[:-1])
            self.likelihood.check_state(carry.aux, "carry.aux")

    def _step(self, carry, y, u, mask):
        carry, out = super()._step(carry, y, u, mask)
        x = dict(out.extras)
        beta, alarm, zeta = x.pop("beta"), x.pop("alarm"), x.pop("zeta")
        attack = alarm.unsqueeze(-1).to(y.dtype) * x["gamma_hat"]
        return carry, out._replace(attack=attack, score=beta, alarm=alarm, threshold=zeta, extras=x)

    def _run(self, carry, ys, us, mask):
        gamma_hat = self.gamma_hat
        # one table for all runs, or one per run
        if isinstance(gamma_hat, Tensor) and broadcast_or_none(gamma_hat.shape[:-2],
                                                               ys.shape[:-2]) is None:  # fmt: skip
            raise ValueError(
                f"gamma_hat's runs {tuple(gamma_hat.shape[:-2])} do not broadcast with ys' "
                f"{tuple(ys.shape[:-2])}: give gamma_hat [T, dy] for all runs or one per run"
            )
        if not self.fused:
            return None
        self._check_fused_settings()  # (any of them assigned since)
        if us is not None or mask is not None:
            bad = "us" if us is not None else "mask"
            raise ValueError(f"fused=True does not support {bad}; use fused=False")
        if not _fusable(carry.model, ys, self.detector, self.gamma_hat):
            return None  # step by step: the same numbers, without the fused path's assumptions
        log_w = carry.log_weights
        if carry.k != 0 or not bool((log_w == log_w[..., :1]).all()):
            # the fused path starts from equally weighted particles at k = 0: a weighted set
            # (a state carried over) had been filtered as if its weights were equal, 0.27
            # off the steps' numbers (a time-index trial)
            return None
        gens = carry.generators or Generators()
        if gens.resample is gens.propagate:
            # one stream for both (one generator given, or torch's global one): the fused
            # path draws the whole horizon's noise before any resampling uniform, the steps
            # alternate them, and the two had drawn other numbers (0.27 apart in the mean
            # at N = 4: a paper-equations check); its numbers are the steps' only with
            # streams of their own
            return None
        from .fused import FusedModifiedPF

        pf = FusedModifiedPF(
            carry.model, num_particles=self.num_particles, eta=float(self.detector.eta),
            zeta=self.detector.zeta,
        )  # fmt: skip
        return pf.run(
            ys, self.gamma_hat.expand(ys.shape), generator=gens.propagate,
            resample_generator=gens.resample, initial_particles=carry.particles,
        )  # fmt: skip


def _fusable(model, ys: Tensor, detector, gamma_hat: Tensor) -> bool:
    """Whether the fused path computes what the steps do: runs ``[B, T, dy]``, one ``η`` for
    every run, ``γ̂`` broadcasting to ``ys``, and the measurement density ``N(y − h(x); 0,
    R)`` of eq. (59) (a zero-mean Gaussian noise, the model's own density and residual: the
    fused weights are written for it; another noise, a glint mixture or an offset, gave
    other weights)."""
    noise = model.measurement_noise
    plain = (
        type(noise) is Gaussian
        and noise._zero_loc()
        and _default_measurement_density(model)
        and type(model).measurement_residual is StateSpaceModel.measurement_residual
    )
    try:
        fits = torch.broadcast_shapes(gamma_hat.shape, ys.shape) == ys.shape
    except RuntimeError:
        fits = False
    # the fused path draws the noise module's Q and reads the first step's matrices: a
    # declared time-varying model, or a process_cov of the model's own (a subclass's, or one
    # assigned on the object), steps instead (an assigned Q had put the paths 4.19 apart: a
    # review)
    constant = not getattr(model, "time_varying", False) and not model._varying_noise("process_cov")
    return (plain and constant and fits and ys.dim() == 3
            and torch.as_tensor(detector.eta).numel() == 1)  # fmt: skip


def _check_attack_rate_particles(attack_rate, num_particles: int) -> None:
    if attack_rate is not None and getattr(attack_rate, "n", num_particles) != num_particles:
        # (its warm-up ζ is eq. 46's for its own N: 0.25 for 0.49 in a trial)
        raise ValueError(
            f"attack_rate is a RunningAttackRate of {attack_rate.n} particles; this filter "
            f"has num_particles = {num_particles}: make it RunningAttackRate({num_particles})"
        )


def _check_fused(gamma_hat, attack_rate, base_likelihood, resampler, ess_threshold) -> None:
    unsupported = {
        "attack_rate": attack_rate is not None,
        "base_likelihood": base_likelihood is not None,
        "gamma_hat (an estimator)": not isinstance(gamma_hat, Tensor),
        "resampler (not Systematic)": type(resampler) is not Systematic,
        "ess_threshold (not 1.0)": ess_threshold != 1.0,
    }
    bad = [name for name, flag in unsupported.items() if flag]
    if bad:
        raise ValueError(f"fused=True does not support {', '.join(bad)}; use fused=False")


def _generators(generator, resample_generator) -> Generators:
    gens = Generators.of(generator)
    return gens if resample_generator is None else gens._replace(resample=resample_generator)


def _attach(pf: ParticleFilter, model, initial_state, generators):
    return None if initial_state is None else pf.attach(initial_state, model, generators)


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
    """The modified PF of Table 2 over a sequence ``ys [..., T, dy]`` of received ``ỹ_k``:
    :class:`ModifiedParticleFilter` in the open loop.

    Args:
        model: a model with Gaussian process noise; a linear measurement
            (``observation_matrix``, as the four-tank plant has) gives the paper's exact
            eq. (35); a nonlinear one is linearised at the predictive particle mean.
        us: inputs ``[..., T, du]`` or ``None``; mask: received entries ``[..., T, dy]``.
        num_particles, detector, gamma_hat, attack_rate, resampler, ess_threshold,
            base_likelihood, fused: as in :class:`ModifiedParticleFilter`.
        generator: initial particles (unless ``initial_state``) and propagation noise;
            resample_generator: resampling uniforms (separate streams keep common
            random numbers aligned across estimators).
        initial_state: start from this particle set instead of the prior.

    Returns an :class:`~difffilter.EstimatorOutput`: ``means`` ``x̂_k`` (eq. 60),
    ``covs``, ``attack = l̂_k γ̂_k`` ``[..., T, dy]`` (the compensation applied),
    ``detection`` (scores ``β̃_k``, eq. 58; alarms ``l̂_k``; threshold ``ζ_k [..., T]``)
    and ``extras``: ``gamma_hat [..., T, dy]``, ``pred_means [..., T, dx]``,
    ``ess [..., T]`` and, with ``attack_rate``, ``attack_rate`` (final ``p̂_l`` ``[...]``);
    with ``fused=True`` what :class:`ModifiedParticleFilter` says of it.
    """
    ys, us, mask = check_filter_inputs(
        model, ys, us, mask, resampler=resampler, ess_threshold=ess_threshold, gamma_hat=gamma_hat
    )
    if isinstance(gamma_hat, Tensor) and gamma_hat.shape[-2:] != ys.shape[-2:]:
        raise ValueError(
            f"gamma_hat must be a BiasAttackEstimator or a tensor [..., {ys.shape[-2]}, "
            f"{model.dim_y}]; got {tuple(gamma_hat.shape)}"
        )
    start = 0 if initial_state is None else int(initial_state.k)
    if isinstance(gamma_hat, Tensor) and start > 0:
        # a table aligned with ys, read by each step at its absolute index k − 1: from a
        # state at k0 its rows start at k0 (rows before it are never read). A γ̂ of T rows
        # had been read k0 rows late and ran out at step T − k0 + 1 (a time-index trial)
        skipped = gamma_hat.new_zeros(gamma_hat.shape[:-2] + (start, gamma_hat.shape[-1]))
        gamma_hat = torch.cat([skipped, gamma_hat], dim=-2)
    pf = ModifiedParticleFilter(
        num_particles, detector, gamma_hat, attack_rate=attack_rate, resampler=resampler,
        ess_threshold=ess_threshold, base_likelihood=base_likelihood, fused=fused,
    )  # fmt: skip
    gens = _generators(generator, resample_generator)
    carry = _attach(pf, model, initial_state, gens)
    out = None
    if fused and carry is not None:  # open_loop takes the fast path only from the prior
        out = pf._run(carry, ys, us, mask)  # None where the fused path declines the run
    if out is None:
        out = open_loop(pf, model, ys, us, mask=mask, generator=gens, carry=carry)
    if attack_rate is not None:
        out.extras["attack_rate"] = out.extras["attack_rate"][..., -1]
    return out


class PoAParticleFilter(ParticleFilter):
    """The normal (bootstrap) PF with the PoA detector of eqs (10)–(17), as an estimator.

    ``β_k = Σ_{‖y_k − h(x_k^i)‖ > η} w_k^i`` with the filter's posterior weights (eq. 17
    when it resamples every step); unreceived entries (``mask``) do not enter the norm.
    ``literal=True`` runs the diagnostic variant: weights from
    :class:`LiteralGaussianLikelihood` and the PoA of
    :func:`~difffilter.fdi.poa.literal_probability_of_attack` (NaN → no alarm when every
    density underflows). ``likelihood`` overrides the weighting likelihood (log-space mode
    only). Step output: ``score`` ``β_k``, ``alarm`` ``β_k > ζ``, ``threshold`` ``ζ``.
    """

    def __init__(
        self,
        num_particles: int,
        detector: PoADetector,
        *,
        literal: bool = False,
        likelihood=None,
        resampler=None,
        ess_threshold: float = 1.0,
        record_prior: bool = False,
    ):
        if not isinstance(detector, PoADetector):
            raise ValueError(f"detector must be a PoADetector; got {type(detector).__name__}")
        if literal and likelihood is not None:
            raise ValueError("pass either literal=True or a likelihood, not both")
        self.detector, self.literal = detector, check_flag(literal, "literal")
        super().__init__(
            num_particles,
            resampler=resampler if resampler is not None else Systematic(),
            likelihood=LiteralGaussianLikelihood() if literal else likelihood,
            ess_threshold=ess_threshold,
            hooks=(self._poa,),
            record_prior=record_prior,
        )

    def __setattr__(self, name, value):
        # (a detector assigned since built had been taken unchecked, failing at the next step
        # on a bare AttributeError; literal assigned since had switched the score's density
        # and not the weights': means 0.42 off a filter built so; an options trial)
        if name == "detector" and not isinstance(value, PoADetector):
            raise ValueError(f"detector must be a PoADetector; got {type(value).__name__}")
        if name == "literal" and name in self.__dict__:
            raise AttributeError(
                "literal is built into the filter's likelihood by its constructor: it cannot "
                "be assigned later (build a new PoAParticleFilter(..., literal=...))"
            )
        replacing = name == "detector" and name in self.__dict__
        super().__setattr__(name, value)
        if replacing:
            note_assignment()

    def attach(self, state: ParticleState, model, generators: Generators) -> ParticleState:
        self.detector.check_runs(state.log_weights.shape[:-1], model)
        return super().attach(state, model, generators)

    def _poa(self, model, y, m, state, out):
        # through the model's residual: a bearing near ±π is wrapped (else ~2π: a false PoA)
        residuals = model.measurement_residual(
            y.unsqueeze(-2), model.observe(state.particles, state.k)
        )
        if m is not None:
            residuals = residuals * m.unsqueeze(-2).to(residuals.dtype)
        if self.literal:
            if m is not None:
                raise ValueError(
                    "literal=True does not support a measurement mask (mask must be None)"
                )
            prior = torch.exp(out.extras["prior_log_weights"])
            R = model.measurement_cov(state.k)
            beta = literal_probability_of_attack(residuals, R, self.detector.eta, prior)
            return {"beta": beta.to(y.dtype)}
        return {"beta": probability_of_attack(residuals, self.detector.eta, state.log_weights)}

    def _step(self, carry, y, u, mask):
        carry, out = super()._step(carry, y, u, mask)
        x = dict(out.extras)
        beta = x.pop("beta")
        zeta = self.detector.zeta
        return carry, out._replace(score=beta, alarm=beta > zeta, threshold=zeta, extras=x)


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
    """The normal (bootstrap) PF on ``ys [..., T, dy]`` with the PoA detector:
    :class:`PoAParticleFilter` in the open loop.

    Other arguments as in :func:`modified_particle_filter`. Returns an
    :class:`~difffilter.EstimatorOutput` (``attack`` is ``None``; detection scores
    ``β_k``, threshold ``ζ``) with ``extras``: ``ess [..., T]``, ``log_likelihood [...]``
    and, with ``return_particles=True``, ``particles [..., T, N, dx]``, their normalised
    ``log_weights [..., T, N]`` and ``prior_log_weights [..., T, N]`` (the predictive
    weights ``log w_{k−1}`` of ``x_k``). β is computed by a step hook, so no particle
    history is kept unless asked for.
    """
    if literal and mask is not None:
        raise ValueError("literal=True does not support a measurement mask (mask must be None)")
    ys, us, mask = check_filter_inputs(
        model, ys, us, mask, resampler=resampler, ess_threshold=ess_threshold
    )
    pf = PoAParticleFilter(
        num_particles, detector, literal=literal, likelihood=likelihood, resampler=resampler,
        ess_threshold=ess_threshold, record_prior=return_particles,
    )  # fmt: skip
    gens = _generators(generator, resample_generator)
    collect = None
    if return_particles:

        def collect(carry, out):
            return {"particles": carry.particles, "log_weights": carry.log_weights}

    carry = _attach(pf, model, initial_state, gens)
    return open_loop(pf, model, ys, us, mask=mask, generator=gens, carry=carry, collect=collect)
