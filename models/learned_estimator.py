"""The neural FDI estimator in the evaluation: the registry entries of the trained
checkpoints.

The wrapper itself, the network of eqs (8)–(9) inside any filter of the library, is
:class:`difffilter.fdi.neural.NeuralCompensation` (its module docstring has the
equations); the network is :class:`~difffilter.models.neural_estimator.NeuralFDIEstimator`
and its checkpoints carry an :class:`~difffilter.models.neural_estimator.EstimatorCard`.
:mod:`difffilter.train.task` trains it through :func:`difffilter.loop.open_loop` or
:func:`~difffilter.loop.closed_loop`; the registry entries ``pf_nn_grad``,
``gaussian_nn_grad``, ``pf_nn_ekf`` and ``gaussian_nn_ekf`` run a checkpoint as its card
says.
"""

from __future__ import annotations

import torch

from difffilter.attack import Channel
from difffilter.estimator import Generators
from difffilter.fdi.neural import (
    FEATURES,
    NeuralCompensation,
    OnlineLearning,
    Residual,
    build_delta,
    feature_dim,
)
from difffilter.loop import open_loop
from difffilter.models.estimators import SkipEstimator, register
from difffilter.models.generic_estimators import GAUSSIAN_FILTERS, deception_of
from difffilter.particle import ParticleFilter

__all__ = [
    "FEATURES",
    "Residual",
    "OnlineLearning",
    "NeuralCompensation",
    "build_delta",
    "feature_dim",
    "LEARNED",
    "learned_step",
]


# ------------------------------------------------- registration with the estimator registry


def _trained_network(ctx, name: str, filters, trainer: str):
    """The checkpoint's network and card if it was trained for this scenario family with
    one of ``filters`` by ``trainer``; :class:`~difffilter.models.estimators.SkipEstimator`
    otherwise."""
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    path = ctx.checkpoint_for(name)
    if path is None:
        raise SkipEstimator("no --ckpt given and no shipped checkpoint")
    key = ("learned/ckpt", str(path))
    if key not in ctx.cache:
        ctx.cache[key] = load_estimator_checkpoint(path, dtype=ctx.dtype)
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


def _build(ctx, name: str, particles: bool, trainer: str) -> NeuralCompensation:
    """The checkpoint's network inside its filter as a step object (:func:`_trained_network`
    decides whether it fits the scenario)."""
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
    return NeuralCompensation(
        net, inner, channel=channel, residual=Residual(card.residual),
        standardize=card.standardize, features=card.features, poa_eta=card.poa_eta,
        threshold=card.threshold, deception=deception,
    )  # fmt: skip


def learned_step(ctx, name: str):
    """``(estimator, start)`` of the registered learned estimator ``name`` (``pf_nn_grad``,
    ``gaussian_nn_ekf``, …): its step object and ``start(runs) → carry`` (the study's
    common random numbers for a particle filter; ``None`` for a Gaussian filter, whose
    ``init`` draws nothing). What an attacker differentiates through
    (:mod:`difffilter.stealthy`); raises :class:`SkipEstimator` if the checkpoint does not
    fit the scenario."""
    if name not in LEARNED:
        raise ValueError(f"{name!r} is not a learned estimator; valid: {', '.join(LEARNED)}")
    particles, trainer = LEARNED[name]
    est = _build(ctx, name, particles, trainer)
    if not particles:
        return est, None

    def start(runs: int):
        kw = ctx.particle_kwargs(runs)
        gens = Generators(None, kw["generator"], kw["resample_generator"])
        return est.attach(kw["initial_state"], ctx.model, gens)

    return est, start


def _learned(name: str, particles: bool, trainer: str):
    """A factory running the checkpoint's network in the open loop on the scenario's data
    (the particle filter with the study's common random numbers, or the card's Gaussian
    filter), without gradients."""

    def factory(ctx):
        est, start = learned_step(ctx, name)

        def run(tr):
            with torch.no_grad():
                carry = None if start is None else start(len(tr.y_recv))
                return open_loop(est, ctx.model, tr.y_recv, tr.us, mask=tr.mask, carry=carry)

        return run

    return factory


_HOW = {
    "grad": "trained by gradient descent through the differentiable {}",
    "ekf": "trained by the EKF over its weights inside the {}",
}
#: The learned estimators by registry name: ``(particle filter?, trainer)``.
LEARNED = {
    f"{'pf' if particles else 'gaussian'}_nn_{trainer}": (particles, trainer)
    for trainer in _HOW
    for particles in (True, False)
}
for _name, (_particles, _trainer) in LEARNED.items():
    register(
        _name,
        f"neural FDI estimator {_HOW[_trainer].format('PF' if _particles else 'KF/EKF/UKF')} "
        "(checkpoint), compensating the filter's measurements; alarm at its "
        "validation-chosen threshold",
    )(_learned(_name, _particles, _trainer))
