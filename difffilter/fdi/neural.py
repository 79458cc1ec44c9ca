"""The learned attack compensation of the LFC paper around any filter: one wrapper.

Sargolzaei et al. (TII 2020, eqs 5–9): an observer runs on the measurement with the
estimated attack removed, and a network estimates the attack from the observer's
residuals. :class:`NeuralCompensation` wraps a filter of the library (a Kalman, extended
or unscented Kalman filter, the fixed-gain Luenberger observer of the paper's baseline,
or a particle filter) with any network of the eq. (8)–(9) interface
(:class:`CompensationNetwork`; the project's is
:class:`difffilter.models.neural_estimator.NeuralFDIEstimator`, ``J`` areas of ``d``
channels). One step ``k`` with the inner filter's prediction::

    ν_k = ỹ_k − E[h(x_k) | ỹ_{1:k−1}],   S_k = Cov(ν_k)        the inner filter's innovation
    r_k = ν_k (or ν_k / √diag S_k, standardise=True; 0 where unreceived)
    δ_k = [â_{k−1}, …, â_{k−a}, r-history, f_k]                 eq. (9), per area
    â_k, logit_k = network(δ_k)                                 eq. (8) and its detection head
    update with ỹ_k − â_k                                       the compensated measurement

The residual history (``residual``, :class:`Residual`):

* ``INNOVATION``: ``r_k, r_{k−1}, …, r_{k−b+1}`` of the innovations (ours; eq. 9 with lag 0);
* ``PREDICTED``: the same of ``ν_k − â_{k−1}`` (the residual if the attack kept its last
  estimate: the LFC paper's network with lag 0, ``kf_nn_grad``);
* ``LAGGED``: ``e_{k−1} … e_{k−b}``, ``e = ν − â`` after compensation (lag 1, as the
  definition of δ and eq. 13 read it; eq. 9 as printed has lags a+1 … a+b: the paper's
  online-learned network; with online learning ``â`` is the estimate
  before the step's weight update, the learner's own error of eq. 11, whatever
  ``posterior`` reports and subtracts).

Online learning (``learning``, :class:`OnlineLearning`): before estimating, the weights of
each run and area take one step of a rule of :mod:`difffilter.param_ekf` (the EKF over the
weights of eqs 10–14, or plain gradient steps) towards ``ν_k`` (the attack plus noise the
observer sees, eq. 5), and ``â_k`` is the re-evaluated (``posterior``) or the prior
estimate. The learners' state lives in the carry, one weight vector per run.

Channels (:class:`~difffilter.attack.Channel`): a sensor attack estimate is subtracted
from the measurement; an actuator attack estimate (``â`` in the input's channels, from
the ``dy`` residuals) is added to the input of the Gaussian filters' prediction; against
a replacement (the tracking deception, ``ỹ = ξ ~ p_ξ``) the particle filter weighs with
the mixture of eq. (15) of the RRP paper with the network's probability ``p_k`` in place
of the fixed rate, ``log[(1 − p_k) p_v(ỹ_k − h(x^i)) + p_k p_ξ(ỹ_k)]``, and reports ``â_k =
p_k ν_k``.

``f_k`` holds the optional ``features`` (:data:`FEATURES`), in this order::

    "mask"              m_k ∈ {0, 1}^dy, the received entries (one area only)
    "log_likelihood"    asinh(−2 ℓ_k / max(|m_k|, 1)), ℓ_k = log p̂(ỹ_k | ỹ_{1:k−1}) of the
                        uncompensated measurement (about 1 per entry without attack; one
                        area only)
    "poa"               β_k = Σ_{i: ‖z^i‖ > η} w^i_{k−1},  z^i = ỹ_k − h(x^i_k): the
                        probability of attack of the modified-PF paper in the form of its
                        modified PF, eq. (58) over the predictive weights of eq. (29) (not
                        eq. 14's likelihood weights), on the raw residuals; particle filter
                        only
    "plain_innovation"  ν°_k / √diag S°_k (0 where unreceived): the standardised innovation
                        of a second copy of the filter that reads ỹ_k uncompensated, each
                        area its own channels; Gaussian filters only
    "open_loop_innovation"
                        (ỹ_k − h(x̄°_k)) / √diag R_k (0 where unreceived), x̄°_k = f(x̄°_{k−1},
                        u_{k−1}, k−1), x̄°_0 = E[x_0]: the measurement against the noise-free
                        open-loop trajectory of the prior mean (what a filter that reads no
                        measurement predicts), each area its own channels; any filter

The plain copy's state never depends on the network: when an attack ends it returns to
the attack-free innovation at its own rate, whereas the compensated filter's state
carries whatever part of the attack the estimate missed, and the innovation of that state
error looks like an attack to a network that reads it alone. The open-loop trajectory
depends on no measurement at all: a persistent attack that a filter absorbs (a slow ramp,
a random walk) leaves its innovation small and the open-loop one as large as the attack.

Gating (``gating=True``, sensor attacks, a network with a detection head): beside
subtracting its estimate, the network may drop the measurement. With ``g_k = p_k`` (below)
the update keeps the compensated measurement with probability ``1 − g_k``::

    Gaussian filters:  m_k = (1 − g) m_u + g m⁻,
                       P_k = (1 − g) P_u + g P⁻ + g (1 − g)(m_u − m⁻)(m_u − m⁻)ᵀ
                       (the moments of that two-component mixture; u: updated, ⁻: predicted)
    particle filter:   log w_k += (1 − g) log p(ỹ_k − â_k | x_k)      (a tempered update)

so ``g = 0`` is plain compensation and ``g = 1`` skips the update, as a χ²-gated filter
does on an alarm; ``g`` is differentiable, so training decides when to drop.

Compensation (``compensation``, :class:`Compensation`; sensor and actuator attacks, a
network with a detection head for ``"detected"``)::

    "full"       ỹ_k − â_k                (the paper's: every step compensated)
    "detected"   ỹ_k − pⁱ_k âⁱ_k           (each area's estimate times its probability)

With ``"full"`` the network's estimate on an attack-free step, noise of the size of the
innovation, is subtracted too: it takes part of the innovation for an attack, so the
filter corrects its state less, and a state error (the one an attack leaves behind among
them) decays slowly. With ``"detected"`` an attack-free step (``p ≈ 0``) updates with the
measurement as the filter alone would. The reported ``attack`` is ``â_k`` either way.

Restart (``restart=α``, sensor attacks, Gaussian filters): a copy of the filter that
never reads the estimate runs beside, gated by the χ² test of its innovation at the
false-alarm rate ``α`` (the ``chi_square_kf`` of the LFC evaluation: an alarmed
measurement is not used), and on every step where that test is quiet the compensated
filter takes the copy's posterior::

    q_k = ν°_kᵀ (S°_k)⁻¹ ν°_k ≤ F⁻¹_{χ²_dy}(1 − α)     (the copy's test is quiet)
    m°_k, P°_k = its update with ỹ_k where q_k, else its prediction
    m_k, P_k ← m°_k, P°_k   where q_k                   (else the compensated update)

A compensated filter carries whatever part of an attack its estimate missed, and a
network that reads its residuals takes that state error for an attack, whose
compensation in turn keeps the filter from correcting it: after an attack the alarms
outlast it by seconds. The gated copy leaves the attack with the state its predictions
kept (it used no alarmed measurement), so the compensated filter restarts from a state
that has not absorbed the attack as soon as the copy's test is quiet again, and an
attack-free step updates as the filter alone would. The switch is a hard choice;
gradients flow through the branch taken. With ``"plain_innovation"`` as well, that
feature is the gated copy's innovation.

Rejection (``reject=ρ``, sensor attacks, every entry received): where the compensated
innovation fails its χ² test at the false-alarm rate ``ρ``, the compensated filter keeps
its prediction instead of its update (after the gating; before the restart)::

    q_k = (ν_k − â_k)ᵀ S_k⁻¹ (ν_k − â_k) > F⁻¹_{χ²_dy}(1 − ρ)  ⇒
        Gaussian filters:  m_k, P_k ← m⁻_k, P⁻_k
        particle filter:   log w_k ← log w⁻_k   (the propagated particles keep their weights)

(``ν_k`` the innovation, ``S_k`` its covariance: the filter's, or for the particle filter
its predictive moments with ``R``; ``â_k`` what it subtracts). An attack the network
follows (a bias) leaves a quiet compensated innovation and is compensated; one it cannot
follow (a replay, the first steps of a ramp) leaves it loud, and the filter predicts over
it as a χ²-gated filter does, rather than absorb the part the estimate missed.

Detection: ``p_k = sigmoid(logit_k)`` (the largest over areas), alarm where ``p_k >
threshold``; a network without a detection head (trained by the EKF over its weights,
which fits the attack estimate alone) scores ``s_k = Σ_c (â_{k,c} / √S_{k,cc})²`` against a
sensor attack and ``s_k = Σ_c â_{k,c}²`` against an actuator attack (the input's channels
have no innovation variance to divide by: the robot's card calibrates this raw score), or
against a sensor attack behind a filter that reports no ``S_k`` (a fixed-gain observer). Every
operation is differentiable, so a loss on ``â``, ``logit`` or the state estimates
back-propagates through the filter (through the particle weights and, with a
differentiable resampler, through resampling): how :mod:`difffilter.train.task` trains
the network.

Confirmed alarms (``confirm=β``, with ``restart``): the score counts only where the gated
copy's χ² test at the rate ``β`` alarms as well::

    s_k = p_k · 1[q°_k > F⁻¹_{χ²_dy}(1 − β)]

so an alarm needs the network and the uncompensated innovation. Aimed at the steps just
after an attack: the network reads residuals of a few past steps, so its probability
outlasts the attack, while the copy, which used no alarmed measurement, is quiet again
as soon as the injected signal ends. The threshold is then chosen for this score.
"""

from __future__ import annotations

import math
from functools import partial
from typing import Any, NamedTuple, Protocol

import torch
from torch import Tensor, nn

from .._checks import (
    Choice,
    broadcast_or_none,
    check_flag,
    check_rate,
    check_strategy,
    model_batch_shape,
    real_number,
    values_known,
)
from ..attack import Channel
from ..estimator import Estimator, Generators
from ..kalman import GaussianFilter
from ..param_ekf import EKFRule, GradientRule, LearnerState, WeightTemplate
from ..particle import ModelLikelihood, ParticleFilter, ParticleState
from ..results import StepOutput
from .detectors import _nis, chi_square_upper_quantile
from .modified_pf import AttackCompensatedLikelihood
from .poa import probability_of_attack

__all__ = [
    "FEATURES",
    "CompensationNetwork",
    "Residual",
    "Compensation",
    "OnlineLearning",
    "NeuralState",
    "NeuralCarry",
    "NeuralCompensation",
    "build_delta",
    "feature_dim",
    "restart_applies",
]

#: The optional per-step inputs (module docstring), in the order they enter ``δ_k``.
FEATURES = ("mask", "log_likelihood", "poa", "plain_innovation", "open_loop_innovation")
#: Features with one entry per measured channel that each area reads on its own channels.
PER_AREA_FEATURES = ("plain_innovation", "open_loop_innovation")


class CompensationNetwork(Protocol):
    """What :class:`NeuralCompensation` needs of its network: eq. (8) per area.

    Sizes: ``num_areas`` ``J``, ``area_dim`` ``d`` (attack channels per area),
    ``resid_dim`` (residual channels per area), ``a``, ``b`` (estimates and residuals in
    ``δ``), ``extra_inputs`` (the features' width); ``detection_head`` (whether it returns
    a logit); ``V`` (its first-layer weights: their dtype is the network's).
    ``__call__(δ [..., J, in], W=None, V=None) → (â [..., J, d], logit [..., J] or
    None)`` with optional per-run weights; ``area_template()`` one area as an
    ``nn.Module`` of parameters ``W, V`` (the online learners' template) and
    ``area_params() → {"W": [J, d, h], "V": [J, h, in]}``.
    """

    num_areas: int
    area_dim: int
    resid_dim: int
    a: int
    b: int
    extra_inputs: int
    detection_head: bool
    V: Tensor

    def __call__(self, delta: Tensor, W: Tensor | None = None, V: Tensor | None = None): ...

    def area_template(self) -> nn.Module: ...

    def area_params(self) -> dict[str, Tensor]: ...


def build_delta(attack_hist: Tensor, resid_hist: Tensor, num_areas: int) -> Tensor:
    """Per-area network inputs ``δ [..., J, a·d + b·r]`` from the histories (eq. 9).

    ``attack_hist [..., a, J·d]`` holds ``M̂_{k−1} … M̂_{k−a}`` (most recent first),
    ``resid_hist [..., b, J·r]`` the residuals, most recent first. Area ``i`` takes its own
    channels: ``δⁱ = [M̂ⁱ_{k−1}, …, M̂ⁱ_{k−a}, eⁱ_…]``.
    """
    J = num_areas

    def per_area(hist: Tensor) -> Tensor:  # [..., n, J·d] → [..., J, n·d]
        lead, n, width = hist.shape[:-2], hist.shape[-2], hist.shape[-1]
        split = hist.reshape(lead + (n, J, width // J)).transpose(-3, -2)
        return split.reshape(lead + (J, n * (width // J)))

    return torch.cat([per_area(attack_hist), per_area(resid_hist)], dim=-1)


class Residual(Choice):
    """Which residuals the network reads (module docstring)."""

    INNOVATION = "innovation"
    PREDICTED = "predicted"
    LAGGED = "lagged"


class Compensation(Choice):
    """What the filter subtracts (module docstring): ``â_k``, or each area's ``pⁱ_k âⁱ_k``."""

    FULL = "full"
    DETECTED = "detected"


class OnlineLearning(NamedTuple):
    """Online learning of the weights, one learner per run and area: ``rule`` an
    :class:`~difffilter.param_ekf.EKFRule` or :class:`~difffilter.param_ekf.GradientRule`;
    ``posterior``: estimate with the weights after this step's update (Algorithm 1's final
    "estimate the FDI attack from (8)") or before it; ``init_scale``: each run starts from
    its own ``s·U[0, 1]`` weights (Algorithm 1, drawn from the carry's init generator) or,
    ``None``, from the network's."""

    rule: EKFRule | GradientRule
    posterior: bool = True
    init_scale: float | None = None


def _check_inner_carry(inner) -> None:
    """``inner``'s carry is the state alone: the learned estimator compensates and reports
    the carry's moments (its steps report the carry's mean)."""
    if not getattr(inner, "carry_is_state", True):
        raise ValueError(
            f"inner: {type(inner).__name__}'s carry holds more than the state (on held "
            "inputs, [x; z]), and the learned estimator compensates and reports the "
            "carry's moments: give it a KalmanFilter, or the filter with on_loss='zero'"
        )


def _check_learning(learning: OnlineLearning) -> None:
    """An :class:`OnlineLearning`'s fields, when the estimator is built: a ``rule="ekf"``
    had failed in the loop's first step (``'str' object has no attribute 'init'``), a NaN
    ``init_scale`` as a Cholesky breakdown naming nothing, a negative one was taken (where
    ``paper_network`` refuses it)."""
    if not isinstance(learning.rule, (EKFRule, GradientRule)):
        raise TypeError(
            "learning.rule must be an EKFRule or a GradientRule (difffilter.param_ekf); got "
            f"{learning.rule!r}"
        )
    scale = learning.init_scale
    number = None if isinstance(scale, Tensor) else real_number(scale)  # (numpy's too)
    if scale is not None and (number is None or not math.isfinite(number) or number <= 0):
        raise ValueError(
            "learning.init_scale must be a finite number > 0 (each run starts from s·U[0, 1] "
            f"weights) or None (the network's own); got {scale!r}"
        )
    check_flag(learning.posterior, "learning.posterior")


class NeuralState(NamedTuple):
    """The network's part of a carry: ``attack_hist [..., J, a, d]`` (``â_{k−1} … â_{k−a}``
    of each area), ``resid_hist [..., J, b, r]`` (most recent first), the online ``learner``
    (:class:`~difffilter.param_ekf.LearnerState` of ``[... · J]`` learners, or ``None``) and,
    with the ``"open_loop_innovation"`` feature, the open-loop mean ``x̄°_k [..., dx]`` of the
    carry's step ``k`` (else ``None``)."""

    attack_hist: Tensor
    resid_hist: Tensor
    learner: LearnerState | None = None
    open_loop: Tensor | None = None


class NeuralCarry(NamedTuple):
    """Carry of a :class:`NeuralCompensation` around a Gaussian filter: the filter's carry
    ``inner``, the network's :class:`NeuralState`, the model and, with the
    ``"plain_innovation"`` feature or ``restart``, the carry of the copy that never reads
    the estimate, ``plain`` (χ²-gated with ``restart``)."""

    inner: Any
    net: NeuralState
    model: Any
    plain: Any = None


def _check_net_state(network, state, dtype: torch.dtype, runs: torch.Size) -> None:
    """A carry's :class:`NeuralState` histories: tensors of the carry's dtype, finite, of the
    network's layout ``[..., J, a, d]`` and ``[..., J, b, r]`` (a NaN estimate in a hand-built
    history had run to NaN means, another layout failed in torch's cat: an apishapes trial)."""
    if not isinstance(state, NeuralState):
        raise ValueError(
            f"the carry's network state must be a NeuralState; got {type(state).__name__}"
        )
    J = network.num_areas
    for name, t, tail in (("attack_hist", state.attack_hist, (J, network.a, network.area_dim)),
                          ("resid_hist", state.resid_hist, (J, network.b, network.resid_dim))):  # fmt: skip
        want = tuple(runs) + tail
        if not isinstance(t, Tensor) or t.dtype != dtype or tuple(t.shape) != want:
            got = f"{t.dtype} {tuple(t.shape)}" if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"carry's NeuralState.{name} must be a {dtype} tensor of shape "
                             f"{list(want)} (its runs, then the network's layout); got {got}")  # fmt: skip
        if values_known(t) and not bool(torch.isfinite(t).all()):
            raise ValueError(f"carry's NeuralState.{name} contains NaN or Inf values")


def feature_dim(features, dim_y: int) -> int:
    """Width of ``f_k`` for ``features`` (``ValueError`` naming an unknown or repeated one)."""
    features = tuple(features)
    unknown = [f for f in features if f not in FEATURES]
    if unknown or len(set(features)) != len(features):
        raise ValueError(f"features must be distinct names of {FEATURES}; got {list(features)}")
    return sum(dim_y if f in ("mask", *PER_AREA_FEATURES) else 1 for f in features)


def _push(hist: Tensor, value: Tensor, areas: int) -> Tensor:
    """``value [..., J·c]`` in front of ``hist [..., J, n, c]``, the oldest entry dropped (an
    empty history, ``n = 0``, stays empty)."""
    if hist.shape[-2] == 0:
        return hist
    return torch.cat([value.unflatten(-1, (areas, -1)).unsqueeze(-2), hist[..., :-1, :]], -2)


class _Core:
    """The network's step (eqs 8–9) on one innovation, shared by both adapters."""

    def __init__(self, network, channel, residual, standardize, features, poa_eta, learning,
                 record_inputs):  # fmt: skip
        self.network, self.channel, self.residual = network, channel, residual
        self.standardize, self.features, self.poa_eta = standardize, features, poa_eta
        self.learning, self.record_inputs = learning, record_inputs
        self.template = None if learning is None else WeightTemplate(network.area_template())

    def init(self, batch: torch.Size, dtype, device, generator, model=None) -> NeuralState:
        """The histories at zero, the learners at their start and, with the
        ``"open_loop_innovation"`` feature, ``x̄°_0 = E[x_0]`` of ``model`` for every run
        (``model`` is read only then)."""
        net = self.network
        J = net.num_areas
        # per-area layout: δⁱ is the two histories of area i flattened (no transposes per step)
        attack_hist = torch.zeros(batch + (J, net.a, net.area_dim), dtype=dtype, device=device)
        resid_hist = torch.zeros(batch + (J, net.b, net.resid_dim), dtype=dtype, device=device)
        learner = None
        if self.learning is not None:
            # the learners in the network's dtype, whatever the measurements' (as the frozen
            # network runs): float32 data had met the float64 network's scales and head in
            # a raw matmul error
            areas, wdtype = batch + (J,), net.V.dtype
            start = {k: v.detach() for k, v in net.area_params().items()}
            if self.learning.init_scale is not None:  # Algorithm 1: every run its own draw
                s = self.learning.init_scale
                start = {
                    k: s * torch.rand(batch + v.shape, generator=generator, dtype=wdtype)
                    for k, v in start.items()
                }
            theta = self.template.flatten(start, areas).to(device)
            learner = self.learning.rule.init(theta)
        open_loop = None
        if "open_loop_innovation" in self.features:
            mean = model.initial.mean.detach().to(dtype=dtype, device=device)
            open_loop = mean.expand(batch + mean.shape[-1:]).clone()
        return NeuralState(attack_hist, resid_hist, learner, open_loop)

    def advance_open_loop(self, state: NeuralState, model, u, k: int) -> NeuralState:
        """``state`` with ``x̄°_{k+1} = f(x̄°_k, u_k, k)`` (unchanged without the feature)."""
        if state.open_loop is None:
            return state
        with torch.no_grad():  # the model's trajectory: nothing to learn through it
            return state._replace(open_loop=model.transition(state.open_loop, u, k))

    @staticmethod
    def open_loop_feature(state: NeuralState, model, y: Tensor, k: int) -> Tensor | None:
        """``(ỹ_k − h(x̄°_k)) / √diag R_k`` ``[..., dy]`` (``None`` without the feature)."""
        if state.open_loop is None:
            return None
        residual = model.measurement_residual(y, model.observe(state.open_loop, k))
        return residual / _std(model.measurement_cov(k)).to(residual.dtype)

    def _features(self, e, mask, log_likelihood, poa, plain, open_loop=None) -> list[Tensor]:
        """The features as ``[..., J, width]`` each (every area reads the run's, or its own
        channels of a per-area one)."""
        J = self.network.num_areas
        received = torch.ones_like(e) if mask is None else mask.to(e.dtype)
        given = {"log_likelihood": log_likelihood, "poa": poa, "plain_innovation": plain,
                 "open_loop_innovation": open_loop}  # fmt: skip
        out = []
        for name in self.features:
            if name == "mask":
                out.append(received.unsqueeze(-2))
                continue
            value = given[name]
            if value is None:
                raise ValueError(f"feature {name!r} needs the filter's {name} at every step")
            value = value.to(e.dtype)
            if name in PER_AREA_FEATURES:  # each area its own channels; 0 where unreceived
                # (where, not a product: an unreceived entry of ỹ may hold NaN)
                value = value if mask is None else torch.where(mask, value, 0.0)
                out.append(value.unflatten(-1, (J, -1)))
                continue
            if name == "log_likelihood":
                value = torch.asinh(-2.0 * value / received.sum(-1).clamp_min(1.0))
            out.append(value.unsqueeze(-1).unsqueeze(-2))
        return out

    def step(self, state: NeuralState, innovation, innovation_cov, mask, log_likelihood=None,
             poa=None, plain=None, open_loop=None):  # fmt: skip
        """``(state, â [..., J·d], logit [..., J] or None, scale [..., dy], δ [..., J, in])``;
        ``plain [..., dy]``: the plain copy's standardised innovation, ``open_loop [..., dy]``
        the open-loop one (their features)."""
        net, J = self.network, self.network.num_areas
        if innovation.shape[-1] != J * net.resid_dim:
            raise ValueError(
                f"network.resid_dim is {net.resid_dim} (× {J} areas) but the measurement has "
                f"dy = {innovation.shape[-1]}"
            )
        scale, e = None, innovation
        # √diag S: read by the standardisation and, without a head, by the score
        if innovation_cov is not None and (self.standardize or not net.detection_head):
            scale = _std(innovation_cov)
        if self.residual is Residual.PREDICTED:  # ν_k − â_{k−1}, then standardised and masked
            e = e - state.attack_hist[..., 0, :].flatten(-2)
        if self.standardize:
            e = e / scale
        if mask is not None:
            e = e * mask.to(e.dtype)
        if self.residual is Residual.LAGGED:
            resid_in = state.resid_hist
        else:
            resid_in = _push(state.resid_hist, e, J)
        # δ [..., J, in]: each area's histories, most recent first (build_delta's layout)
        delta = torch.cat([state.attack_hist.flatten(-2), resid_in.flatten(-2)], -1)
        if self.features:
            extra = self._features(e, mask, log_likelihood, poa, plain, open_loop)
            areas = e.shape[:-1] + (J,)
            delta = torch.cat([delta, *(f.expand(*areas, -1) for f in extra)], -1)
        learner = state.learner
        if learner is None:
            attack, logit = net(delta if delta.dtype == net.V.dtype else delta.to(net.V.dtype))
            attack = attack if attack.dtype == e.dtype else attack.to(e.dtype)
        else:
            attack, logit, learner, prior = self._learn(learner, delta, innovation, mask)
        attack = attack.flatten(-2)  # [..., J·d]
        if self.residual is Residual.LAGGED:  # e = ν − â, standardised and masked as r is
            # (a trial: a lost entry's −â had entered the history, and standardize did nothing)
            entry = innovation - (attack if learner is None else prior)
            if self.standardize:
                entry = entry / scale
            if mask is not None:
                entry = entry * mask.to(entry.dtype)
        else:
            entry = e
        sensor = self.channel is not Channel.ACTUATOR
        if mask is not None and sensor:
            attack = attack * mask.to(attack.dtype)
        if logit is not None and logit.dtype != e.dtype:
            logit = logit.to(e.dtype)
        if self.channel is Channel.REPLACEMENT:  # the expected injected ξ − y, p_k ν_k
            attack = torch.sigmoid(logit) * innovation
        hist = NeuralState(
            _push(state.attack_hist, attack, J),
            _push(state.resid_hist, entry, J),
            learner,
            state.open_loop,
        )
        return hist, attack, logit, scale, delta

    def _learn(self, learner: LearnerState, delta: Tensor, innovation: Tensor,
               mask: Tensor | None = None):  # fmt: skip
        """One step of every run's learner towards ``ν`` (eq. 5's ``e = z − ẑ``), then the
        estimate: ``(â [..., J, d], logit, learner, prior â [..., J·d])``. An entry not
        received (``mask [..., dy]`` False) is no target: its innovation is the filter's
        placeholder 0, towards which the weights had been pulled (a lossy-link trial: 27 %
        of their size over 100 steps without a packet)."""
        net, J, d = self.network, self.network.num_areas, self.network.area_dim
        lead = delta.shape[:-2]
        x = delta.reshape(-1, delta.shape[-1]).to(learner.theta.dtype)  # the network's dtype
        pred, H = self.template.jacobian(learner.theta, x)
        target = innovation.reshape(-1, d).to(pred.dtype)
        received = None if mask is None else mask.expand(innovation.shape).reshape(-1, d).bool()
        learner = self.learning.rule.step(learner, H, target - pred, received)
        prior = pred.reshape(lead + (J * d,)).to(innovation.dtype)
        if self.learning.posterior:
            attack = self.template.forward(learner.theta, x).reshape(lead + (J, d))
        else:
            attack = pred.reshape(lead + (J, d))
        attack = attack.to(innovation.dtype)
        logit = None
        if net.detection_head:
            params = {k: v.reshape(lead + (J,) + v.shape[1:])
                      for k, v in self.template.unflatten(learner.theta).items()}  # fmt: skip
            _, logit = net(delta.to(learner.theta.dtype), W=params["W"], V=params["V"])
        return attack, logit, learner, prior

    def detect(self, attack, logit, scale, innovation) -> tuple[Tensor, dict]:
        """``(score [...], extras)``: ``sigmoid`` of the largest area logit, or without a
        head the squared estimate, standardised by ``√diag S`` against a sensor attack
        where the filter reports ``S`` (module docstring)."""
        if logit is not None:
            top = logit.amax(-1)
            extras = {"attack_logit": top}
            if logit.shape[-1] > 1:  # one per area (the training loss reads them)
                extras["area_logits"] = logit
            return torch.sigmoid(top), extras
        sensor = self.channel is not Channel.ACTUATOR
        s = attack / scale if (sensor and scale is not None) else attack
        return s.square().sum(-1), {}


class _NeuralLikelihood:
    """The network inside the particle filter: a :class:`~difffilter.particle.StepLikelihood`
    that estimates from the step's predictive view and weighs with the compensated
    measurement (or, against a replacement, with the learned mixture)."""

    def __init__(self, core: _Core, deception, gating: bool = False,
                 compensation: Compensation = Compensation.FULL, reject_limit=None):  # fmt: skip
        self.core, self.deception, self.gating = core, deception, gating
        self.compensation = compensation
        self.reject_limit = reject_limit  # dof ↦ F⁻¹_{χ²_dof}(1 − ρ), or None

    def init(self, model, batch_shape, dtype, device):
        return self.core.init(batch_shape, dtype, device, None, model)

    def weigh(self, state, model, y, particles, k, mask, predictive):
        core, kw, clean = self.core, {}, None
        if "log_likelihood" in core.features or core.channel is Channel.REPLACEMENT:
            clean = ModelLikelihood()(model, y, particles, k, mask)
        if "log_likelihood" in core.features:
            kw["log_likelihood"] = torch.logsumexp(predictive.log_weights + clean, -1)
        if "poa" in core.features:
            z = model.measurement_residual(y.unsqueeze(-2), model.observe(particles, k))
            if mask is not None:
                z = z * mask.unsqueeze(-2).to(z.dtype)
            kw["poa"] = probability_of_attack(z, core.poa_eta, predictive.log_weights)
        kw["open_loop"] = core.open_loop_feature(state, model, y, k)
        nu, S = predictive.innovation, predictive.innovation_cov
        state, attack, logit, scale, delta = core.step(state, nu, S, mask, **kw)
        record = {"attack": attack, "scale": scale}
        if logit is not None:
            record["logit"] = logit
        if core.record_inputs:
            record["network_inputs"] = delta[..., 0, :].detach()
        if core.channel is Channel.REPLACEMENT:  # eq. (15) with the learned p_k for η̄
            top = logit.amax(-1, keepdim=True)
            log_p = torch.nn.functional.logsigmoid(top)
            log_q = torch.nn.functional.logsigmoid(-top)
            replaced = self.deception(model, y, particles, k, mask)
            return state, torch.logaddexp(clean + log_q, replaced + log_p), record
        always = torch.ones(attack.shape[:-1], dtype=torch.bool, device=attack.device)
        applied = applied_estimate(attack, logit, self.compensation)
        log_lik = AttackCompensatedLikelihood(always, applied)(model, y, particles, k, mask)
        if self.gating:  # a tempered update: kept with probability 1 − g
            log_lik = log_lik * (1.0 - gate_of(logit)).unsqueeze(-1)
        if self.reject_limit is not None:  # no update where ν − â fails its χ² test
            if _partial(mask):
                raise ValueError(_REJECT_MASK)
            kept = _nis(nu - applied, S) <= self.reject_limit(nu.shape[-1])
            log_lik = torch.where(kept.unsqueeze(-1), log_lik, torch.zeros_like(log_lik))
        return state, log_lik, record


class NeuralCompensation(Estimator):
    """The neural FDI estimator around a filter of the library (module docstring).

    Args:
        network: a :class:`CompensationNetwork` (e.g.
            :class:`~difffilter.models.neural_estimator.NeuralFDIEstimator`: ``J`` areas of
            ``area_dim`` channels; ``extra_inputs = feature_dim(features, dy)``).
        inner: the filter: a :class:`~difffilter.kalman.GaussianFilter` (KF, EKF, UKF,
            :class:`~difffilter.observers.FixedGainFilter`) or a
            :class:`~difffilter.ParticleFilter` (its resampler, proposal and ESS threshold
            are used; its likelihood is the network's).
        channel: :class:`~difffilter.attack.Channel` of the attack it compensates.
        residual: :class:`Residual`; standardize: divide the innovations by ``√diag S``.
        features: names of :data:`FEATURES` (one area only, but the per-area
            ``"plain_innovation"`` and ``"open_loop_innovation"``).
        poa_eta: ``η`` of the ``"poa"`` feature.
        learning: :class:`OnlineLearning` or ``None`` (frozen weights).
        threshold: alarm threshold of the score.
        deception: ``log p_ξ`` (:class:`~difffilter.fdi.ReplacementDeception`) for the
            replacement channel.
        record_inputs: report every step's ``δ_k [..., in]`` (``extras["network_inputs"]``;
            one area): the samples the EKF over the weights is trained on.
        gating: drop the measurement with the network's probability of attack (module
            docstring; sensor attacks, a network with a detection head).
        compensation: :class:`Compensation`: subtract ``â_k`` (``"full"``, the paper's) or
            each area's estimate times its probability of attack (``"detected"``).
        restart: ``α`` in (0, 1): restart the compensated filter from a χ²-gated copy that
            never reads the estimate, on every step where the copy's test at false-alarm
            rate ``α`` is quiet (module docstring; sensor attacks, Gaussian filters, every
            entry received); ``None`` (default): never.
        evidence: report the density ``log p(y_k − â_k | …)`` of the compensated update
            (``StepOutput.log_likelihood``, Gaussian filters); ``False`` leaves it ``None``
            and saves its operations (training reads none).
        confirm: ``β`` in (0, 1): the score only where the χ²-gated copy's test at rate
            ``β`` alarms too, ``0`` elsewhere (module docstring; needs ``restart``);
            ``None`` (default): the network's score alone.
        reject: ``ρ`` in (0, 1): where the compensated innovation ``ν_k − â_k`` fails its
            χ² test at rate ``ρ``, keep the prediction (module docstring; sensor attacks,
            every entry received); ``None`` (default): never.

    Step output: the filter's moments after compensation, ``attack`` ``â_k``, ``score``,
    ``alarm``, ``threshold`` and ``extras`` (``"attack_logit"`` with a head, the recorded
    inputs, ``"confirmed"`` with ``confirm``: where the copy's test at ``β`` alarmed).
    Carry: :class:`NeuralCarry` (Gaussian inner filter) or the particle filter's
    :class:`~difffilter.ParticleState` with the :class:`NeuralState` in ``aux``.
    """

    def __init__(
        self,
        network: CompensationNetwork,
        inner: GaussianFilter | ParticleFilter,
        *,
        channel: Channel | str = Channel.SENSOR,
        residual: Residual | str = Residual.INNOVATION,
        standardize: bool = True,
        features=(),
        poa_eta: float | None = None,
        learning: OnlineLearning | None = None,
        threshold: float = 0.5,
        deception=None,
        record_inputs: bool = False,
        gating: bool = False,
        compensation: Compensation | str = Compensation.FULL,
        restart: float | None = None,
        evidence: bool = True,
        confirm: float | None = None,
        reject: float | None = None,
    ):
        channel, residual, features = Channel(channel), Residual(residual), tuple(features)
        compensation = Compensation(compensation)
        # (read with bool() before: gating="false" gated, standardize="no" standardised, the
        # means 0.18 and 1.4 off: an LFC options trial)
        gating, standardize = check_flag(gating, "gating"), check_flag(standardize, "standardize")
        evidence, record_inputs = (
            check_flag(evidence, "evidence"),
            check_flag(record_inputs, "record_inputs"),
        )
        _check_options(network, inner, channel, features, poa_eta, learning, deception)
        _check_step_options(network, channel, residual, gating, compensation)
        _check_restart(restart, inner, channel)
        _check_confirm(confirm, restart)
        _check_reject(reject, channel)
        _check_needs_innovation_cov(
            inner, standardize=standardize, restart=restart, reject=reject,
            plain_innovation="plain_innovation" in features,
            log_likelihood="log_likelihood" in features,
        )  # fmt: skip
        _check_inner_carry(inner)
        self.gating, self.compensation, self.evidence = gating, compensation, evidence
        self.restart = None if restart is None else float(restart)
        self.confirm = None if confirm is None else float(confirm)
        self.reject = None if reject is None else float(reject)
        self._chi2_quantiles: dict[tuple, float] = {}  # χ² quantile by (dof, rate)
        self.network, self.inner, self.channel = network, inner, channel
        self.attack_channel = channel  # what its attack estimate â_k is on
        self.threshold = threshold  # (checked by __setattr__)
        self.core = _Core(network, channel, residual, standardize, features, poa_eta,
                          learning, record_inputs)  # fmt: skip
        self.particles = isinstance(inner, ParticleFilter)
        # the uncompensated copy runs beside for its innovation or its χ² test
        self.plain = "plain_innovation" in features or self.restart is not None
        if self.particles:
            self.pf = ParticleFilter(
                inner.num_particles, resampler=inner.resampler, proposal=inner.proposal,
                likelihood=_NeuralLikelihood(
                    self.core, deception, self.gating, compensation,
                    None if self.reject is None else partial(self._chi2_threshold, rate=self.reject),
                ),
                ess_threshold=inner.ess_threshold, innovations=True,
            )  # fmt: skip
            self.carry_type = ParticleState
        else:
            self.carry_type = NeuralCarry

    #: What the constructor checks together and builds into the estimator (the core, the
    #: uncompensated copy, the particle filter's likelihood): assigned later, ``restart``
    #: had been ignored (its copy is made by the constructor's choice) and an ``inner``
    #: observer reached ``S_k = None`` inside torch (an observers trial). Not reassignable.
    _BUILT = frozenset({
        "network", "inner", "channel", "gating", "compensation", "restart", "confirm",
        "reject", "evidence", "core", "particles", "plain", "pf", "carry_type",
    })  # fmt: skip

    def __setattr__(self, name, value):
        if name in self._BUILT and name in self.__dict__:
            raise AttributeError(
                f"{name} is checked with the other options and built into the estimator by "
                f"its constructor: it cannot be assigned later (build a new "
                f"{type(self).__name__})"
            )
        # checked whenever set, as the card checks it: a NaN threshold never alarmed, True read
        # as 1.0 (a probability score then never alarms) and "0.5" as 0.5 (a trial); the LFC
        # entries set it after construction
        if name == "threshold":
            number = real_number(value)
            if number is None or math.isnan(number):
                raise ValueError(f"threshold must be a number (±inf allowed); got {value!r}")
            value = number
        super().__setattr__(name, value)

    def batch_of(self, carry):
        return self.pf.batch_of(carry) if self.particles else self.inner.batch_of(carry.inner)

    def _init(self, model, batch_shape, generators):
        net = self.network
        if model.dim_y != net.num_areas * net.resid_dim:  # (it was said at the first step)
            raise ValueError(
                f"network.resid_dim is {net.resid_dim} (× {net.num_areas} areas) but the model "
                f"has dim_y = {model.dim_y}: the network was made for another plant"
            )
        attack_width = net.num_areas * net.area_dim
        if self.channel is Channel.ACTUATOR and model.dim_u != attack_width:
            # its estimate is added to the input: ``u + â`` had broadcast a 1-wide input to
            # 2 without a word, or failed in torch's raw matmul error (a checkpoint trial)
            raise ValueError(
                f"network.area_dim is {net.area_dim} (× {net.num_areas} areas): an actuator "
                f"attack estimate {attack_width} wide, but the model has dim_u = "
                f"{model.dim_u}: the network was made for another plant"
            )
        # the network's histories (and learners) per run a step makes: the carry's batch
        # broadcast with the model's parameter sets, as every estimator's step runs (a
        # carry of init(model, ()) on a model of 3 sets had failed in a raw cat error)
        runs = broadcast_or_none(batch_shape, model_batch_shape(model)) or batch_shape
        if self.particles:
            self._follow_inner()
            carry = self.pf._init(model, batch_shape, generators)
            net = self.core.init(runs, carry.particles.dtype, carry.particles.device,
                                 generators.init, model)  # fmt: skip
            return carry._replace(aux=net)
        _check_inner_carry(self.inner)  # (its on_loss may have been assigned since: a review)
        inner = self.inner._init(model, batch_shape, generators)
        net = self.core.init(runs, inner.mean.dtype, inner.mean.device, generators.init,
                             model)  # fmt: skip
        plain = self.inner._init(model, batch_shape, generators) if self.plain else None
        return NeuralCarry(inner, net, model, plain)

    def attach(self, state: ParticleState, model, generators: Generators) -> ParticleState:
        """Particles drawn elsewhere as this estimator's carry (particle filter only)."""
        if not self.particles:  # (a bare AttributeError: 'pf')
            raise TypeError(
                f"attach takes particles for an estimator over a ParticleFilter; this one's "
                f"inner is a {type(self.inner).__name__}: start its carry from init"
            )
        if state.k and "open_loop_innovation" in self.core.features:
            raise ValueError(
                "the open_loop_innovation feature starts its trajectory at E[x_0]: attach "
                f"particles of step k = 0 (got k = {state.k}), or run from init"
            )
        self._follow_inner()  # (as init: a count assigned to inner since, a review)
        carry = self.pf.attach(state._replace(aux=None), model, generators)
        lead = state.log_weights.shape[:-1]
        net = self.core.init(lead, state.particles.dtype, state.particles.device, generators.init,
                             model)  # fmt: skip
        return carry._replace(aux=net)

    def _model_of(self, carry):
        return carry.model

    def _check_carry(self, carry):
        if self.particles:
            if carry.aux is None:  # (a plain particle filter's: it failed inside the step)
                raise ValueError(
                    "carry is a particle filter's without this estimator's network state "
                    "(carry.aux is None): start the carry from this estimator's init"
                )
            self._follow_inner()
            self.pf._check_carry(carry)
            net_state, dtype = carry.aux, carry.particles.dtype
        else:
            self.inner._check_carry(carry.inner)
            net_state, dtype = carry.net, carry.inner.mean.dtype
        _check_net_state(self.network, net_state, dtype, self._runs_of(carry))

    def _follow_inner(self) -> None:
        """The particle filter's settings as ``inner`` has them now: its own filter (of the
        network's likelihood) was built from ``inner``'s, and ``inner.num_particles = 20`` or
        its ``ess_threshold`` assigned since had been ignored (means 0.47 and 0.13 off one
        built so: an options trial). A count other than the carry's is then refused by the
        carry's check, as a plain particle filter's."""
        inner, pf = self.inner, self.pf
        for name in ("num_particles", "ess_threshold"):
            if getattr(pf, name) != getattr(inner, name):
                setattr(pf, name, getattr(inner, name))
        for name in ("resampler", "proposal"):
            if getattr(pf, name) is not getattr(inner, name):
                setattr(pf, name, getattr(inner, name))

    def _step(self, carry, y, u, mask):
        if self.particles:  # the open-loop mean to step k + 1 first: the likelihood reads it
            self._follow_inner()
            carry = carry._replace(aux=self.core.advance_open_loop(carry.aux, carry.model, u,
                                                                   carry.k))  # fmt: skip
            carry, out = self.pf._step(carry, y, u, mask)
            x = dict(out.extras)
            attack, logit, scale = x.pop("attack"), x.pop("logit", None), x.pop("scale")
            return carry, self._report(out, attack, logit, scale, out.innovation, x)
        inner, core = self.inner, self.core
        pred = inner.predict(carry.inner, u)
        # what the innovation and the compensated update share (S, C, H: they do not read y)
        moments = inner.moments(carry.inner, pred, mask)
        evidence = "log_likelihood" in core.features
        nu, S, ell = inner.innovation(carry.inner, pred, y, mask, evidence=evidence,
                                      moments=moments)  # fmt: skip
        plain, plain_feature, quiet, confirmed = carry.plain, None, None, None
        if plain is not None:  # the copy that never reads the estimate (nor its density)
            plain_pred = inner.predict(plain, u)
            plain, plain_out = inner.update(plain, plain_pred, y, mask, evidence=False)
            plain_nu, plain_S = plain_out.innovation, plain_out.innovation_cov
            if "plain_innovation" in core.features:
                plain_feature = plain_nu / _std(plain_S)
            if self.restart is not None:
                if _partial(mask):
                    raise ValueError("restart tests every channel of the uncompensated copy: "
                                     "it needs every entry received (mask=None)")  # fmt: skip
                nis, dof = _nis(plain_nu, plain_S), plain_nu.shape[-1]
                quiet = nis <= self._chi2_threshold(dof, self.restart)
                if self.confirm is not None:
                    confirmed = nis > self._chi2_threshold(dof, self.confirm)
                plain = _gated_copy(plain, plain_pred, quiet)
        net = core.advance_open_loop(carry.net, carry.model, u, carry.inner.k)
        net, attack, logit, scale, delta = core.step(
            net, nu, S, mask, log_likelihood=ell, plain=plain_feature,
            open_loop=core.open_loop_feature(net, carry.model, y, carry.inner.k + 1),
        )  # fmt: skip
        applied = applied_estimate(attack, logit, self.compensation)
        if self.channel is Channel.ACTUATOR:
            if u is None:
                raise ValueError("channel ACTUATOR compensates the input: step needs u_k [..., du] "
                                 "(a whole sequence, us [..., T, du])")  # fmt: skip
            compensated = inner.predict(carry.inner, u + applied)
            new, out = inner.update(carry.inner, compensated, y, mask, evidence=self.evidence)
        else:
            new, out = inner.update(carry.inner, pred, y - applied, mask, evidence=self.evidence,
                                    moments=moments)  # fmt: skip
            if self.gating:
                new, out = _gated(new, out, pred, gate_of(logit))
            if self.reject is not None:
                new, out = self._rejected(new, out, pred, nu - applied, S, mask)
            if quiet is not None:
                new, out = _restarted(new, out, plain, quiet)
        extras = {"network_inputs": delta[..., 0, :].detach()} if core.record_inputs else {}
        report = self._report(out, attack, logit, scale, nu, extras, confirmed)
        return NeuralCarry(new, net, carry.model, plain), report

    def _rejected(self, new, out: StepOutput, pred, compensated_nu: Tensor, S: Tensor, mask):
        """``new`` where the compensated innovation ``ν_k − â_k [..., dy]`` passes its χ²
        test at the rate ``reject`` (``S [..., dy, dy]``), the prediction ``pred`` where it
        fails (module docstring, rejection), and the step's output to match."""
        if _partial(mask):
            raise ValueError(_REJECT_MASK)
        dof = compensated_nu.shape[-1]
        kept = _nis(compensated_nu, S) <= self._chi2_threshold(dof, self.reject)
        state = _chosen(new, kept, new, pred)
        return state, out._replace(mean=state.mean, cov=state.cov)

    def _chi2_threshold(self, dof: int, rate: float) -> float:
        """``F⁻¹_{χ²_dof}(1 − rate)``: the copy's test at ``rate`` alarms above it (the
        restart's is quiet at or below it)."""
        key = (dof, rate)
        if key not in self._chi2_quantiles:
            self._chi2_quantiles[key] = chi_square_upper_quantile(dof, rate)
        return self._chi2_quantiles[key]

    def _report(self, out: StepOutput, attack, logit, scale, innovation, extras,
                confirmed: Tensor | None = None) -> StepOutput:  # fmt: skip
        score, more = self.core.detect(attack, logit, scale, innovation)
        if confirmed is not None:  # the network's score only where the copy's test alarms
            score = torch.where(confirmed, score, torch.zeros_like(score))
            more = {**more, "confirmed": confirmed}
        return out._replace(
            attack=attack, score=score, alarm=score > self.threshold, threshold=self.threshold,
            extras={**extras, **more},
        )  # fmt: skip


def _std(cov: Tensor) -> Tensor:
    """``√diag S [..., dy]`` of ``S [..., dy, dy]`` (floored at 1e-15: never a division by 0)."""
    return torch.diagonal(cov, dim1=-2, dim2=-1).clamp_min(1e-30).sqrt()


def _chosen(base, quiet: Tensor, where_quiet, elsewhere):
    """``base`` (a Gaussian filter's carry) with the mean and covariance of ``where_quiet``
    where ``quiet [...]`` and of ``elsewhere`` otherwise. A covariance both share (the
    shared gain schedule) stays shared; else each run gets its own (the schedule dropped)."""
    mean = torch.where(quiet.unsqueeze(-1), where_quiet.mean, elsewhere.mean)
    if where_quiet.cov is elsewhere.cov:
        return base._replace(mean=mean)
    cov = torch.where(quiet[..., None, None], where_quiet.cov, elsewhere.cov)
    state = base._replace(mean=mean, cov=cov)
    return state._replace(gains=None) if hasattr(state, "gains") else state


def _gated_copy(updated, pred, quiet: Tensor):
    """The χ²-gated copy: its update ``updated`` where ``quiet [...]``, its prediction
    ``pred`` (no update: the measurement is not used) where the test alarms."""
    return _chosen(updated, quiet, updated, pred)


def _restarted(new, out: StepOutput, plain, quiet: Tensor):
    """The compensated posterior ``new`` where ``quiet [...]`` is false, the gated copy's
    ``plain`` where it is true (module docstring, restart), and the step's output to match."""
    state = _chosen(new, quiet, plain, new)
    return state, out._replace(mean=state.mean, cov=state.cov)


def applied_estimate(attack: Tensor, logit: Tensor | None, compensation) -> Tensor:
    """What the filter subtracts (:class:`Compensation`): ``â [..., J·d]`` itself, or each
    area's ``sigmoid(logitⁱ) âⁱ`` (``logit [..., J]``)."""
    if compensation is Compensation.FULL:
        return attack
    p = torch.sigmoid(logit)
    return attack * p.repeat_interleave(attack.shape[-1] // p.shape[-1], -1)


def gate_of(logit: Tensor) -> Tensor:
    """``g_k = max over areas of sigmoid(logit_k)`` ``[...]``: the probability of attack."""
    return torch.sigmoid(logit).amax(-1)


def _gated(new, out: StepOutput, pred, g: Tensor):
    """The Gaussian update kept with probability ``1 − g``: the moments of the mixture of
    the updated and the predicted posteriors (module docstring). The covariance becomes
    one per run (no shared gain schedule)."""
    keep = (1.0 - g).unsqueeze(-1)
    jump = new.mean - pred.mean
    mean = pred.mean + keep * jump
    w = keep.unsqueeze(-1)
    cov = (
        w * new.cov
        + (1.0 - w) * pred.cov
        + (w * (1.0 - w)) * (jump.unsqueeze(-1) * jump.unsqueeze(-2))
    )
    state = new._replace(mean=mean, cov=cov)
    if hasattr(state, "gains"):
        state = state._replace(gains=None)
    return state, out._replace(mean=mean, cov=cov)


def _check_step_options(network, channel, residual, gating, compensation) -> None:
    """``ValueError`` for a residual, gating or compensation the network cannot serve."""
    if channel is Channel.ACTUATOR and residual is not Residual.INNOVATION:
        raise ValueError(
            f"residual={residual.value!r} subtracts the attack estimate from the innovation: it "
            "needs a sensor attack (an actuator estimate lives in the input's channels); use "
            "residual='innovation'"
        )
    if residual is Residual.PREDICTED and network.a < 1:
        raise ValueError(
            "residual='predicted' subtracts the last attack estimate: it needs a network "
            f"that keeps one (a >= 1); got a = {network.a}"
        )
    # the options that read the head's probability of attack: (on, what, channels, which)
    heads = (
        (gating, "gating drops a measurement with the network's probability of attack",
         (Channel.SENSOR,), "a sensor attack"),
        (compensation is Compensation.DETECTED,
         "compensation='detected' weighs each area's estimate with its probability of attack",
         (Channel.SENSOR, Channel.ACTUATOR), "a sensor or actuator attack"),
    )  # fmt: skip
    for on, what, channels, which in heads:
        if on and (channel not in channels or not network.detection_head):
            raise ValueError(
                f"{what}: it needs {which} and a network with a detection head (channel "
                f"{channel.value}, detection_head {bool(network.detection_head)})"
            )


def restart_applies(particle_filter: bool, channel) -> bool:
    """Whether a network's filter can restart from a χ²-gated uncompensated copy: a
    Gaussian filter (not a particle filter) against sensor attacks (``channel``)."""
    return not particle_filter and Channel(channel) is Channel.SENSOR


def _check_restart(restart, inner, channel) -> None:
    """``ValueError`` for a ``restart`` rate out of (0, 1) or one the filter cannot serve."""
    if restart is None:
        return
    check_rate(restart, "restart", unset="None")
    if not restart_applies(isinstance(inner, ParticleFilter), channel):
        raise ValueError(
            "restart runs an uncompensated copy of a Gaussian filter against sensor attacks: "
            f"inner must be a Gaussian filter and channel 'sensor' (got {type(inner).__name__}, "
            f"channel {channel.value!r})"
        )


def _partial(mask: Tensor | None) -> bool:
    """Whether ``mask`` leaves some entry unreceived (an all-True mask is ``mask=None``,
    as every other estimator reads it: restart and reject had refused it)."""
    return mask is not None and not bool(mask.all())


_REJECT_MASK = ("reject tests every channel of the compensated innovation: it needs every "
                "entry received (mask=None)")  # fmt: skip


def _check_needs_innovation_cov(inner, **options) -> None:
    """``ValueError`` naming the options that read the innovation covariance ``S_k`` where
    ``inner`` reports none (a fixed-gain observer: they had failed at the first step inside
    torch, "must be Tensor, not NoneType"; a red-team trial)."""
    if getattr(inner, "reports_innovation_cov", True):  # (a particle filter reads none)
        return
    used = [name for name, value in options.items() if value not in (None, False)]
    if used:
        raise ValueError(
            f"{', '.join(used)}: {'these read' if len(used) > 1 else 'it reads'} the innovation "
            f"covariance S_k, which a {type(inner).__name__} (a Luenberger observer) does not "
            "report (nor a log-likelihood): "
            "give a KalmanFilter (or leave them out: standardize=False, restart=None, "
            "reject=None, no 'plain_innovation' or 'log_likelihood' feature)"
        )


def _check_reject(reject, channel) -> None:
    """``ValueError`` for a ``reject`` rate out of (0, 1) or one without a sensor attack."""
    if reject is None:
        return
    check_rate(reject, "reject", unset="None")
    if channel is not Channel.SENSOR:
        raise ValueError(
            "reject tests the compensated innovation of a sensor attack: channel must be "
            f"'sensor' (got {channel.value!r})"
        )


def _check_confirm(confirm, restart) -> None:
    """``ValueError`` for a ``confirm`` rate out of (0, 1) or one without the gated copy."""
    if confirm is None:
        return
    check_rate(confirm, "confirm", unset="None")
    if restart is None:
        raise ValueError(
            "confirm reads the χ² test of the χ²-gated uncompensated copy, which runs only "
            f"with restart=α: give restart too (got confirm={confirm!r}, restart=None)"
        )


def _check_options(network, inner, channel, features, poa_eta, learning, deception) -> None:
    needed = ("num_areas", "area_dim", "resid_dim", "a", "b", "extra_inputs", "area_template")
    missing = [name for name in needed if not hasattr(network, name)]
    if not isinstance(network, nn.Module) or missing:
        raise TypeError(
            "network must be an eq. (8)-(9) network (e.g. difffilter.models.neural_estimator."
            f"NeuralFDIEstimator); {type(network).__name__} lacks {', '.join(missing) or 'nn.Module'}"
        )
    if not isinstance(inner, (GaussianFilter, ParticleFilter)):
        raise TypeError(
            "inner must be a filter object (difffilter.KalmanFilter(), ExtendedKalmanFilter(), "
            f"UnscentedKalmanFilter(), ParticleFilter(N), ...); got {type(inner).__name__}"
        )
    particles = isinstance(inner, ParticleFilter)
    if channel is not Channel.ACTUATOR and network.resid_dim != network.area_dim:
        raise ValueError("a sensor attack estimate needs network.resid_dim == area_dim (dy)")
    if channel is Channel.ACTUATOR and particles:
        raise ValueError(
            "the particle filter compensates sensor attacks; an actuator attack is "
            "compensated in the input of a Gaussian filter (filter kf/ekf/ukf)"
        )
    if channel is Channel.REPLACEMENT and (
        deception is None or not network.detection_head or not particles
    ):
        raise ValueError(
            "channel='replacement' needs a particle filter, deception= and a network with a head"
        )
    if isinstance(deception, tuple):  # (taken, it failed at the first step: a user's trial)
        raise TypeError(
            "deception must be the attacked-measurement density, not a tuple: "
            "deception_of(...) returns (density, rate), give its [0]"
        )
    # an instance, callable as the particle filter calls a likelihood (a class, or a function
    # of too few arguments, failed at the first step on Python's bare "takes 2 positional")
    check_strategy(deception, "deception", "difffilter.fdi.ReplacementDeception(density)",
                   ("model", "y", "particles", "k", "mask"))  # fmt: skip
    whole_run = [f for f in features if f not in PER_AREA_FEATURES]
    if whole_run and network.num_areas != 1:
        raise ValueError(
            f"features {whole_run} are read by a network of one area (num_areas = 1); "
            f"with several areas only {list(PER_AREA_FEATURES)}"
        )
    width = feature_dim(features, network.resid_dim)
    if network.extra_inputs != width:
        raise ValueError(
            f"network.extra_inputs is {network.extra_inputs} but features {list(features)} "
            f"need {width} inputs"
        )
    if "plain_innovation" in features and particles:
        raise ValueError(
            "'plain_innovation' runs an uncompensated copy of a Gaussian filter: inner must be "
            "a KalmanFilter, ExtendedKalmanFilter or UnscentedKalmanFilter"
        )
    if "poa" in features and not particles:
        raise ValueError("'poa' needs particles: inner must be a ParticleFilter")
    if "poa" in features and (poa_eta is None or not poa_eta >= 0):
        raise ValueError(f"the 'poa' feature needs poa_eta >= 0 (its threshold η); got {poa_eta!r}")
    if learning is not None and not isinstance(learning, OnlineLearning):
        raise TypeError(
            f"learning must be an OnlineLearning(rule=...) or None; got {type(learning).__name__}"
        )
    if learning is not None:
        _check_learning(learning)
    if learning is not None and channel is not Channel.SENSOR:
        raise ValueError(
            "online learning fits the estimate to the innovation (eq. 5): it needs a sensor "
            f"attack; got channel {channel.value!r}"
        )
