"""The neural FDI estimator inside difffilter's own filters: learned attack compensation.

At every step the filter that runs the scenario supplies the network's features and
uses its output (one configuration of :class:`~difffilter.models.neural_estimator.
NeuralFDIEstimator`, with one "area" of ``dy`` channels)::

    ν_k = ỹ_k − E[h(x_k) | ỹ_{1:k−1}],   S_k = Cov(ν_k)       the filter's innovation
    e_k = ν_k / √diag(S_k)                                    standardised, 0 where unreceived
    δ_k = [â_{k−1}, …, â_{k−a}, e_k, …, e_{k−b+1}, f_k]       eq. (9) with residual lag ℓ = 0
    â_k, logit_k = network(δ_k)                               eq. (8) and its detection head
    update with ỹ_k − â_k                                     the compensated measurement

An actuator attack (``channel="actuator"``, ``ũ = u + a``: the mobile robot) is estimated
in the input's ``du`` channels from the same ``dy`` residuals and compensated in the
input instead: the Kalman filters' update step predicts with ``u_{k−1} + â_k`` (the
innovation ``ν_k`` of the plain input ``u_{k−1}`` shows the attack of the last
transition). A replacement attack (``channel="replacement"``, ``ỹ = ξ ~ p_ξ``: the
tracking deception) has no additive signal to subtract: the particle filter weighs with
the mixture of eq. (15) of the RRP paper with the network's probability ``p_k`` in place
of the fixed rate η̄, ``log[(1 − p_k) p_v(ỹ_k − h(x^i)) + p_k p_ξ(ỹ_k)]``, and reports
``â_k = p_k ν_k`` (the injected ``ξ − y`` expected given the data).

``f_k`` holds the optional ``features`` (:data:`FEATURES`), in this order::

    "mask"            m_k ∈ {0, 1}^dy, the received entries
    "log_likelihood"  asinh(−2 ℓ_k / max(|m_k|, 1)),  ℓ_k = log p̂(ỹ_k | ỹ_{1:k−1}) of the
                      uncompensated measurement (the PF's log-sum-exp of its predictive
                      weights times the particles' likelihoods; the Kalman filters'
                      Gaussian density of ν_k): about 1 per entry without attack, growing
                      with it; asinh keeps the tanh units out of saturation
    "poa"             β_k = Σ_{i: ‖z^i‖ > η} w^i_{k−1},  z^i = ỹ_k − h(x^i_k) (received
                      entries; the model's ``measurement_residual``, angles wrapped): the
                      probability of attack of the modified-PF paper (eq. 14) with the
                      scenario's threshold η; particle filter only

``S_k`` is the particles' spread of ``h`` plus ``R`` for the particle filter (its
:class:`~difffilter.particle.Predictive`), ``H P⁻ Hᵀ + R`` for the Kalman filters. Every
operation is differentiable, so a loss on ``â``, ``logit`` or the state estimates
back-propagates through the filter (through the particle weights and, with a
differentiable resampler, through resampling): how :mod:`difffilter.train.task` trains
the network. Detection: ``p_k = sigmoid(logit_k)``, alarm where ``p_k > threshold``; a
network without a detection head (trained by the EKF over its weights, which fits the
attack estimate alone) scores ``s_k = Σ_c (â_{k,c} / √S_{k,cc})²``, the squared
standardised attack estimate, alarm where ``s_k > threshold``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from difffilter.estimator import Detection, EstimatorOutput
from difffilter.fdi.modified_pf import AttackCompensatedLikelihood
from difffilter.fdi.poa import probability_of_attack
from difffilter.models.estimators import SkipEstimator, register
from difffilter.models.generic_estimators import GAUSSIAN_FILTERS, deception_of
from difffilter.models.neural_estimator import NeuralFDIEstimator
from difffilter.particle import ModelLikelihood, particle_filter

__all__ = [
    "FEATURES",
    "feature_dim",
    "NeuralCompensation",
    "neural_particle_filter",
    "neural_gaussian_filter",
]

#: The optional per-step inputs (module docstring), in the order they enter ``δ_k``.
FEATURES = ("mask", "log_likelihood", "poa")


def feature_dim(features, dim_y: int) -> int:
    """Width of ``f_k`` for ``features`` (``ValueError`` naming an unknown or repeated one)."""
    features = tuple(features)
    unknown = [f for f in features if f not in FEATURES]
    if unknown or len(set(features)) != len(features):
        raise ValueError(f"features must be distinct names of {FEATURES}; got {list(features)}")
    return sum(dim_y if f == "mask" else 1 for f in features)


class NeuralCompensation:
    """The network's state over a sequence: its input histories and what it output.

    :meth:`step` maps one innovation ``ν [..., dy]`` with covariance ``S [..., dy, dy]``
    (and ``mask [..., dy]``, the step's ``log_likelihood [...]`` and ``poa [...]`` where
    ``features`` ask for them) to ``(â [..., dy], logit [...])``; :attr:`attack` and
    :attr:`logit` stack the outputs over the steps so far (``[..., T, dy]``, ``[..., T]``).
    As a particle-filter likelihood (``uses_predictive``) it reads the step's
    :class:`~difffilter.particle.Predictive`, computes the features from the proposed
    particles, and weighs them with the compensated measurement, ``log p(ỹ_k − â_k | x_k^i)``.

    Args:
        network: one area of ``dy`` channels, ``extra_inputs = feature_dim(features, dy)``.
        features: names of :data:`FEATURES` (module docstring).
        poa_eta: ``η`` of the ``"poa"`` feature (needed with it).
        record_inputs: keep every step's ``δ_k [..., in]`` (:attr:`inputs`: ``[..., T, in]``),
            the samples the EKF over the weights is trained on.
        channel: ``"sensor"`` (``â`` has the measurement's ``dy`` channels; unreceived ones
            are 0), ``"actuator"`` (``â`` has the network's ``area_dim = du`` channels,
            read from ``dy = network.resid_dim`` residuals) or ``"replacement"`` (the
            mixture likelihood with ``p_k``; needs a detection head and ``deception``).
        deception: ``log p_ξ`` as a likelihood ``(model, y, particles, k, mask) → [..., N]``
            (:class:`~difffilter.fdi.ReplacementDeception`), for ``"replacement"``.
    """

    uses_predictive = True

    def __init__(
        self,
        network: NeuralFDIEstimator,
        features=(),
        poa_eta: float | None = None,
        record_inputs: bool = False,
        channel: str = "sensor",
        deception=None,
    ):
        if not isinstance(network, NeuralFDIEstimator):
            raise TypeError(f"network must be a NeuralFDIEstimator; got {type(network).__name__}")
        if network.num_areas != 1:
            raise ValueError(
                f"network must have num_areas = 1 (one area of dy channels); got {network.num_areas}"
            )
        if channel not in ("sensor", "actuator", "replacement"):
            raise ValueError(
                f"channel must be 'sensor', 'actuator' or 'replacement'; got {channel!r}"
            )
        if channel != "actuator" and network.resid_dim != network.area_dim:
            raise ValueError("a sensor attack estimate needs network.resid_dim == area_dim (dy)")
        if channel == "replacement" and (deception is None or not network.detection_head):
            raise ValueError("channel='replacement' needs deception= and a network with a head")
        width = feature_dim(features, network.resid_dim)
        if network.extra_inputs != width:
            raise ValueError(
                f"network.extra_inputs is {network.extra_inputs} but features {list(features)} "
                f"need {width} inputs"
            )
        if "poa" in features and (poa_eta is None or not poa_eta >= 0):
            raise ValueError(
                f"the 'poa' feature needs poa_eta >= 0 (its threshold η); got {poa_eta!r}"
            )
        self.network, self.features, self.poa_eta = network, tuple(features), poa_eta
        self.channel, self.deception = channel, deception
        self.attack_hist = self.resid_hist = None
        self._attacks: list[Tensor] = []
        self._logits: list[Tensor] = []
        self._inputs: list[Tensor] | None = [] if record_inputs else None

    def _features(self, e: Tensor, mask: Tensor | None, log_likelihood, poa) -> list[Tensor]:
        received = torch.ones_like(e) if mask is None else mask.to(e.dtype)
        given = {"log_likelihood": log_likelihood, "poa": poa}
        out = []
        for name in self.features:
            if name == "mask":
                out.append(received)
                continue
            value = given[name]
            if value is None:
                raise ValueError(f"feature {name!r} needs the filter's {name} at every step")
            value = value.to(e.dtype)
            if name == "log_likelihood":
                value = torch.asinh(-2.0 * value / received.sum(-1).clamp_min(1.0))
            out.append(value.unsqueeze(-1))
        return out

    def step(
        self,
        innovation: Tensor,
        innovation_cov: Tensor,
        mask: Tensor | None = None,
        *,
        log_likelihood: Tensor | None = None,
        poa: Tensor | None = None,
    ):
        net, dy = self.network, innovation.shape[-1]
        if dy != net.resid_dim:
            raise ValueError(
                f"network.resid_dim is {net.resid_dim} but the measurement has dy = {dy}"
            )
        scale = torch.diagonal(innovation_cov, dim1=-2, dim2=-1).clamp_min(1e-30).sqrt()
        e = innovation / scale
        if mask is not None:
            e = e * mask.to(e.dtype)
        batch = e.shape[:-1]
        if self.attack_hist is None:
            self.attack_hist = e.new_zeros(*batch, net.a, net.area_dim)
            self.resid_hist = e.new_zeros(*batch, net.b, dy)
        resid = torch.cat([e.unsqueeze(-2), self.resid_hist[..., :-1, :]], -2)
        # eq. (9) for one area: [â_{k−1}, …, â_{k−a}, e_k, …, e_{k−b+1}] (most recent first)
        delta = torch.cat([self.attack_hist.flatten(-2), resid.flatten(-2)], -1)
        if self.features:
            extra = self._features(e, mask, log_likelihood, poa)
            delta = torch.cat([delta, *(f.expand(*batch, -1) for f in extra)], -1)
        if self._inputs is not None:
            self._inputs.append(delta.detach())
        attack, logit = net(delta.unsqueeze(-2).to(net.V.dtype))
        attack = attack[..., 0, :].to(e.dtype)
        sensor = self.channel != "actuator"
        if mask is not None and sensor:
            attack = attack * mask.to(attack.dtype)
        if logit is None:  # no detection head: the squared (standardised) attack estimate
            logit = (attack / scale if sensor else attack).square().sum(-1)
        else:
            logit = logit[..., 0].to(e.dtype)
        if self.channel == "replacement":  # the expected injected ξ − y, p_k ν_k
            attack = torch.sigmoid(logit).unsqueeze(-1) * innovation
        self.attack_hist = torch.cat([attack.unsqueeze(-2), self.attack_hist[..., :-1, :]], -2)
        self.resid_hist = resid
        self._attacks.append(attack)
        self._logits.append(logit)
        return attack, logit

    def __call__(self, model, y, particles, k, mask, *, predictive) -> Tensor:
        if self.channel == "actuator":
            raise ValueError(
                "the particle filter compensates sensor attacks; an actuator attack is "
                "compensated in the input of neural_gaussian_filter (filter kf/ekf/ukf)"
            )
        kw, clean = {}, None  # clean: log p_v(ỹ_k − h(x^i)) of every particle, once
        if "log_likelihood" in self.features or self.channel == "replacement":
            clean = ModelLikelihood()(model, y, particles, k, mask)
        if "log_likelihood" in self.features:
            kw["log_likelihood"] = torch.logsumexp(predictive.log_weights + clean, -1)
        if "poa" in self.features:
            z = model.measurement_residual(y.unsqueeze(-2), model.observe(particles, k))
            if mask is not None:
                z = z * mask.unsqueeze(-2).to(z.dtype)
            kw["poa"] = probability_of_attack(z, self.poa_eta, predictive.log_weights)
        attack, logit = self.step(predictive.innovation, predictive.innovation_cov, mask, **kw)
        if self.channel == "replacement":  # eq. (15) with the learned p_k for η̄
            replaced = self.deception(model, y, particles, k, mask)
            logit = logit.unsqueeze(-1)
            log_p, log_q = (
                torch.nn.functional.logsigmoid(logit),
                torch.nn.functional.logsigmoid(-logit),
            )
            return torch.logaddexp(clean + log_q, replaced + log_p)
        always = torch.ones(attack.shape[:-1], dtype=torch.bool, device=attack.device)
        return AttackCompensatedLikelihood(always, attack)(model, y, particles, k, mask)

    @property
    def attack(self) -> Tensor:
        return torch.stack(self._attacks, -2)

    @property
    def logit(self) -> Tensor:
        """Detection-head logits ``[..., T]`` (without a head: the statistic ``s_k``)."""
        return torch.stack(self._logits, -1)

    @property
    def inputs(self) -> Tensor:
        """The recorded ``δ_k`` ``[..., T, in]`` (``record_inputs=True``)."""
        if self._inputs is None:
            raise ValueError("inputs were not recorded (NeuralCompensation(record_inputs=True))")
        return torch.stack(self._inputs, -2)


def _output(means, covs, comp: NeuralCompensation, threshold: float, **extras) -> EstimatorOutput:
    if comp.network.detection_head:
        score, extras = torch.sigmoid(comp.logit), {"attack_logit": comp.logit, **extras}
    else:
        score = comp.logit  # s_k (module docstring)
    if comp._inputs is not None:
        extras["network_inputs"] = comp.inputs
    return EstimatorOutput(
        means,
        covs,
        attack=comp.attack,
        detection=Detection(score, score > threshold, float(threshold)),
        extras=extras,
    )


def neural_particle_filter(
    model,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    network: NeuralFDIEstimator,
    num_particles: int,
    mask: Tensor | None = None,
    threshold: float = 0.5,
    features=(),
    poa_eta: float | None = None,
    record_inputs: bool = False,
    channel: str = "sensor",
    deception=None,
    **driver,
) -> EstimatorOutput:
    """The particle filter of :func:`difffilter.particle_filter` (``driver``: resampler,
    proposal, generators, ``initial_state``, …) with the network's compensation as its
    likelihood (``features``, ``poa_eta``, ``record_inputs``, ``channel`` ``"sensor"`` or
    ``"replacement"``, ``deception``: :class:`NeuralCompensation`).
    ``ys [..., T, dy]`` → means ``[..., T, dx]``, ``attack [..., T, dy]``, detection scores
    ``[..., T]``; ``extras``: ``attack_logit`` (with a head), ``log_likelihood [...]``,
    ``network_inputs [..., T, in]`` (when recorded)."""
    comp = NeuralCompensation(network, features, poa_eta, record_inputs, channel, deception)
    res = particle_filter(
        model, ys, us, num_particles=num_particles, mask=mask, likelihood=comp, **driver
    )
    return _output(res.means, res.covs, comp, threshold, log_likelihood=res.log_likelihood)


def neural_gaussian_filter(
    model,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    network: NeuralFDIEstimator,
    kind: str = "kf",
    mask: Tensor | None = None,
    threshold: float = 0.5,
    features=(),
    record_inputs: bool = False,
    channel: str = "sensor",
) -> EstimatorOutput:
    """The KF, EKF or UKF (``kind``) with the network's compensation: each step runs the
    filter's step once for ``ν_k, S_k`` and ``ℓ_k`` and once with ``ỹ_k − â_k``
    (``channel="sensor"``) or with the input ``u_{k−1} + â_k`` (``"actuator"``: ``â``
    ``[..., T, du]``): the update that counts. ``features`` as in
    :class:`NeuralCompensation`, without ``"poa"`` (no particles). Shapes as in
    :func:`neural_particle_filter`."""
    if kind not in GAUSSIAN_FILTERS:
        raise ValueError(f"kind must be one of {sorted(GAUSSIAN_FILTERS)}; got {kind!r}")
    if "poa" in features or channel == "replacement":
        raise ValueError("'poa' and channel='replacement' need particles: neural_particle_filter")
    comp = NeuralCompensation(network, features, None, record_inputs, channel)
    filt, actuator = GAUSSIAN_FILTERS[kind], channel == "actuator"
    if actuator and us is None:
        raise ValueError("channel='actuator' needs the inputs us [..., T, du]")
    state = filt._init(model, ys.shape[:-2], None)
    means, covs = [], []
    for t in range(ys.shape[-2]):
        u = None if us is None else us[..., t, :]
        m = None if mask is None else mask[..., t, :]
        pred = filt.predict(state, u)
        _, probe = filt.update(state, pred, ys[..., t, :], m)
        attack, _ = comp.step(
            probe.innovation, probe.innovation_cov, m, log_likelihood=probe.log_likelihood
        )
        if actuator:
            state, _ = filt.update(state, filt.predict(state, u + attack), ys[..., t, :], m)
        else:
            state, _ = filt.update(state, pred, ys[..., t, :] - attack, m)
        means.append(state.mean)
        covs.append(state.cov)
    means = torch.stack(means, -2)
    covs = torch.stack(torch.broadcast_tensors(*covs), -3)  # data-independent: may be unbatched
    return _output(means, covs.expand(*means.shape, means.shape[-1]), comp, threshold)


# ------------------------------------------------- registration with the estimator registry


def _trained_network(ctx, name: str, kinds, trainer: str) -> tuple[NeuralFDIEstimator, dict]:
    """The checkpoint's network if it was trained for this scenario family with one of
    ``kinds`` of filter by ``trainer`` (``"grad"`` or ``"ekf"``);
    :class:`~difffilter.models.estimators.SkipEstimator` otherwise."""
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    if ctx.checkpoint is None:
        raise SkipEstimator("no --ckpt given and no shipped checkpoint")
    key = ("learned/ckpt", str(ctx.checkpoint))
    if key not in ctx.cache:
        ctx.cache[key] = load_estimator_checkpoint(ctx.checkpoint, dtype=ctx.dtype)
    net, obs = ctx.cache[key]
    family, kind, how = obs.get("scenario_family"), obs.get("kind"), obs.get("trainer", "grad")
    if family != ctx.scenario.family or kind not in kinds or how != trainer:
        trained = f"filter {kind!r}" + (f" by {how} on {family} scenarios" if family else "")
        raise SkipEstimator(
            f"the checkpoint was trained with {trained}; this one needs filter "
            f"{'/'.join(kinds)} by {trainer} on {ctx.scenario.family}"
        )
    ctx.checkpoint_users.append(name)
    return net, obs


def _run_pf(ctx, tr, obs, **kw):
    channel, deception = obs.get("channel", "sensor"), None
    if channel == "replacement":
        deception = deception_of(ctx.scenario.attack_model(), ctx.dtype)[0]
    return neural_particle_filter(
        ctx.model, tr.y_recv, tr.us, mask=tr.mask, poa_eta=obs.get("poa_eta"), channel=channel,
        deception=deception, **ctx.particle_kwargs(len(tr.y_recv)), **kw,
    )  # fmt: skip


def _run_gaussian(ctx, tr, obs, **kw):
    return neural_gaussian_filter(
        ctx.model, tr.y_recv, tr.us, mask=tr.mask, kind=obs["kind"],
        channel=obs.get("channel", "sensor"), **kw,
    )  # fmt: skip


def _learned(name: str, kinds, trainer: str, run_filter):
    """A factory running ``run_filter(ctx, traj, observer, network=, threshold=, features=)``
    with the checkpoint's network and input features, without gradients."""

    def factory(ctx):
        net, obs = _trained_network(ctx, name, kinds, trainer)
        kw = {"network": net, "threshold": float(obs.get("threshold", 0.5))}
        kw["features"] = tuple(obs.get("features", ()))

        def run(tr):
            with torch.no_grad():
                return run_filter(ctx, tr, obs, **kw)

        return run

    return factory


_HOW = {
    "grad": "trained by gradient descent through the differentiable {}",
    "ekf": "trained by the EKF over its weights inside the {}",
}
for _trainer, _how in _HOW.items():
    for _filter, _kinds, _run in (("pf", ("pf",), _run_pf),
                                  ("gaussian", tuple(GAUSSIAN_FILTERS), _run_gaussian)):  # fmt: skip
        _name = f"{_filter}_nn_{_trainer}"
        register(
            _name,
            f"neural FDI estimator {_how.format('PF' if _filter == 'pf' else 'KF/EKF/UKF')} "
            "(checkpoint), compensating the filter's measurements; alarm at its "
            "validation-chosen threshold",
        )(_learned(_name, _kinds, _trainer, _run))
