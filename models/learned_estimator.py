"""The neural FDI estimator in the evaluation and training: whole-sequence runs and the
registry entries of the trained checkpoints.

The wrapper itself, the network of eqs (8)–(9) inside any filter of the library, is
:class:`difffilter.fdi.neural.NeuralCompensation` (its module docstring has the
equations); the network is :class:`~difffilter.models.neural_estimator.NeuralFDIEstimator`
and its checkpoints carry an :class:`~difffilter.models.neural_estimator.EstimatorCard`.
:func:`neural_particle_filter` and :func:`neural_gaussian_filter` run it in the open loop
(what :mod:`difffilter.train.task` trains through); the registry entries ``pf_nn_grad``,
``gaussian_nn_grad``, ``pf_nn_ekf`` and ``gaussian_nn_ekf`` run a checkpoint as its card
says.
"""

from __future__ import annotations

import torch
from torch import Tensor

from difffilter.attack import Channel
from difffilter.estimator import EstimatorOutput, Generators
from difffilter.fdi.neural import (
    FEATURES,
    NeuralCompensation,
    OnlineLearning,
    Residual,
    build_delta,
    feature_dim,
)
from difffilter.kalman import GaussianFilter
from difffilter.loop import open_loop
from difffilter.models.estimators import SkipEstimator, register
from difffilter.models.generic_estimators import GAUSSIAN_FILTERS, deception_of
from difffilter.models.neural_estimator import NeuralFDIEstimator
from difffilter.particle import ParticleFilter, ParticleState

__all__ = [
    "FEATURES",
    "Residual",
    "OnlineLearning",
    "NeuralCompensation",
    "build_delta",
    "feature_dim",
    "neural_particle_filter",
    "neural_gaussian_filter",
]


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
    channel: Channel | str = Channel.SENSOR,
    deception=None,
    resampler=None,
    proposal=None,
    ess_threshold: float = 0.5,
    generator=None,
    resample_generator=None,
    initial_state: ParticleState | None = None,
) -> EstimatorOutput:
    """:class:`NeuralCompensation` around :class:`~difffilter.ParticleFilter` in the open loop.

    ``ys [..., T, dy]`` → means ``[..., T, dx]``, ``attack [..., T, dy]``, detection scores
    ``[..., T]``; ``extras``: ``attack_logit`` (with a head), ``log_likelihood [...]``,
    ``network_inputs [..., T, in]`` (when recorded). Other arguments as in
    :func:`~difffilter.particle_filter` and :class:`NeuralCompensation`.
    """
    pf = ParticleFilter(num_particles, resampler=resampler, proposal=proposal,
                        ess_threshold=ess_threshold)  # fmt: skip
    est = NeuralCompensation(
        network, pf, channel=channel, features=features, poa_eta=poa_eta, threshold=threshold,
        deception=deception, record_inputs=record_inputs,
    )  # fmt: skip
    gens = Generators.of(generator)
    if resample_generator is not None:
        gens = gens._replace(resample=resample_generator)
    carry = None if initial_state is None else est.attach(initial_state, model, gens)
    return open_loop(est, model, ys, us, mask=mask, generator=gens, carry=carry)


def neural_gaussian_filter(
    model,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    network: NeuralFDIEstimator,
    filter: GaussianFilter,
    mask: Tensor | None = None,
    threshold: float = 0.5,
    features=(),
    record_inputs: bool = False,
    channel: Channel | str = Channel.SENSOR,
) -> EstimatorOutput:
    """:class:`NeuralCompensation` around a Gaussian ``filter`` in the open loop: each step
    predicts once, updates with ``ỹ_k`` for ``ν_k, S_k, ℓ_k`` and again with ``ỹ_k − â_k``
    (``channel="sensor"``) or after predicting with the input ``u_{k−1} + â_k``
    (``"actuator"``: ``â [..., T, du]``). Shapes as in :func:`neural_particle_filter`."""
    if Channel(channel) is Channel.ACTUATOR and us is None:
        raise ValueError("channel='actuator' needs the inputs us [..., T, du]")
    est = NeuralCompensation(network, filter, channel=channel, features=features,
                             threshold=threshold, record_inputs=record_inputs)  # fmt: skip
    return open_loop(est, model, ys, us, mask=mask)


# ------------------------------------------------- registration with the estimator registry


def _trained_network(ctx, name: str, filters, trainer: str):
    """The checkpoint's network and card if it was trained for this scenario family with
    one of ``filters`` by ``trainer``; :class:`~difffilter.models.estimators.SkipEstimator`
    otherwise."""
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    if ctx.checkpoint is None:
        raise SkipEstimator("no --ckpt given and no shipped checkpoint")
    key = ("learned/ckpt", str(ctx.checkpoint))
    if key not in ctx.cache:
        ctx.cache[key] = load_estimator_checkpoint(ctx.checkpoint, dtype=ctx.dtype)
    net, card = ctx.cache[key]
    if (
        card.scenario_family != ctx.scenario.family
        or card.filter not in filters
        or (card.trainer != trainer)
    ):
        raise SkipEstimator(
            f"the checkpoint was trained with filter {card.filter!r} by {card.trainer} on "
            f"{card.scenario_family} scenarios; this one needs filter {'/'.join(filters)} by "
            f"{trainer} on {ctx.scenario.family}"
        )
    ctx.checkpoint_users.append(name)
    return net, card


def _learned(name: str, particles: bool, trainer: str):
    """A factory running the checkpoint's network in the open loop on the scenario's data
    (the particle filter with the study's common random numbers, or the card's Gaussian
    filter), without gradients."""

    def factory(ctx):
        filters = ("pf",) if particles else tuple(GAUSSIAN_FILTERS)
        net, card = _trained_network(ctx, name, filters, trainer)
        channel = Channel(card.channel)
        deception = None
        if channel is Channel.REPLACEMENT:
            deception = deception_of(ctx.scenario.attack_model(), ctx.dtype)[0]
        if particles:
            kw = ctx.particle_kwargs()
            inner = ParticleFilter(kw["num_particles"], resampler=kw["resampler"],
                                   ess_threshold=kw["ess_threshold"])  # fmt: skip
        else:
            inner = GAUSSIAN_FILTERS[card.filter]
        est = NeuralCompensation(
            net, inner, channel=channel, residual=Residual(card.residual),
            standardize=card.standardize, features=card.features, poa_eta=card.poa_eta,
            threshold=card.threshold, deception=deception,
        )  # fmt: skip

        def run(tr):
            with torch.no_grad():
                if not particles:
                    return open_loop(est, ctx.model, tr.y_recv, tr.us, mask=tr.mask)
                kw = ctx.particle_kwargs(len(tr.y_recv))
                gens = Generators(None, kw["generator"], kw["resample_generator"])
                carry = est.attach(kw["initial_state"], ctx.model, gens)
                return open_loop(est, ctx.model, tr.y_recv, tr.us, mask=tr.mask, carry=carry)

        return run

    return factory


_HOW = {
    "grad": "trained by gradient descent through the differentiable {}",
    "ekf": "trained by the EKF over its weights inside the {}",
}
for _trainer, _how in _HOW.items():
    for _particles in (True, False):
        _name = f"{'pf' if _particles else 'gaussian'}_nn_{_trainer}"
        register(
            _name,
            f"neural FDI estimator {_how.format('PF' if _particles else 'KF/EKF/UKF')} "
            "(checkpoint), compensating the filter's measurements; alarm at its "
            "validation-chosen threshold",
        )(_learned(_name, _particles, _trainer))
