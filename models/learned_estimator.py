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

from pathlib import Path

import torch

from difffilter._checks import check_positive_int
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
from difffilter.models.estimators import SkipEstimator, loaded_checkpoint, register
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
    "compose",
    "TrainedEstimator",
    "load_estimator",
]


# ------------------------------------------------- registration with the estimator registry


def _trained_network(ctx, name: str, filters, trainer: str):
    """The checkpoint's network and card if it was trained for this scenario family with
    one of ``filters`` by ``trainer``; :class:`~difffilter.models.estimators.SkipEstimator`
    otherwise."""
    path = ctx.checkpoint_for(name)
    if path is None:
        raise SkipEstimator(
            "no checkpoint given (--ckpt; checkpoint= in Python) and no shipped one"
        )
    # the dtype too: the network is loaded in it (a float64 suite sharing the cache of a
    # float32 one had run the float32 network: a cache trial)
    net, card = loaded_checkpoint(ctx, path, ctx.dtype)
    if (
        card.scenario_family != ctx.scenario.family
        or card.filter not in filters
        or (card.trainer != trainer)
    ):
        fitting = _shipped_fitting(name, ctx.scenario.family)
        raise SkipEstimator(
            f"the checkpoint was trained with filter {card.filter!r} by {card.trainer} on "
            f"{card.scenario_family} scenarios; this one needs filter {'/'.join(filters)} by "
            f"{trainer} on {ctx.scenario.family}"
            + (f" (the shipped {fitting} is one: --ckpt {name}={fitting})" if fitting else "")
        )
    ctx.checkpoint_users.append(name)
    return net, card


def _shipped_fitting(name: str, family: str) -> str | None:
    """The shipped checkpoint (``checkpoints/*.ckpt``) whose card says it is estimator
    ``name``'s for ``family``, as a path from the current folder where it lies below it
    (else absolute), else ``None`` (a trial asked
    for ``pf_nn_ekf`` on the four-tank scenario and was told only that the default
    checkpoint did not fit, with ``four_tank_nn_ekf.ckpt`` beside it)."""
    import json

    root = Path(__file__).resolve().parents[1]
    for card_path in sorted((root / "checkpoints").glob("*.json")):
        try:
            card = json.loads(card_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        ckpt = card_path.with_suffix(".ckpt")
        if (isinstance(card, dict) and card.get("estimator") == name
                and card.get("scenario_family") == family and ckpt.is_file()):  # fmt: skip
            # as the user may give it: from the folder they run in where it lies below it
            here = Path.cwd().resolve()
            return str(ckpt.relative_to(here) if ckpt.is_relative_to(here) else ckpt)
    return None


def compose(
    net,
    card,
    *,
    num_particles: int | None = None,
    resampler=None,
    ess_threshold: float = 1.0,
    deception=None,
) -> NeuralCompensation:
    """The network ``net`` inside the filter its ``card`` names, as its card says
    (:class:`~difffilter.fdi.neural.NeuralCompensation`): a particle filter of
    ``num_particles`` (default the card's) with ``resampler`` (default systematic), or the
    card's Gaussian filter. ``deception``: the attacked-measurement density a
    replacement-channel network assumes (a scenario's, e.g. :func:`deception_of`)."""
    from difffilter.resampling import Systematic

    channel = Channel(card.channel)
    if channel is Channel.REPLACEMENT and deception is None:
        raise ValueError(
            "deception: this network compensates a replacement attack and needs the density "
            "it assumes (deception_of(scenario.attack_model(), dtype)[0])"
        )
    if channel is not Channel.REPLACEMENT and deception is not None:
        # (any value was taken and ignored, as a particle filter's settings on a Gaussian
        # card had been: a fuzzing trial)
        raise ValueError(
            f"deception: this checkpoint's network compensates the {channel.value} channel and "
            "reads no deception density (replacement-channel networks do); leave it out"
        )
    if card.filter == "pf":
        n = num_particles if num_particles is not None else card.num_particles
        if n is None:
            raise ValueError("num_particles: the card does not say how many the filter had")
        # (2.5 ran with 2 particles, True with 1 and "50" with 50, without a word)
        n = check_positive_int(n, "num_particles")
        inner = ParticleFilter(n, resampler=resampler or Systematic(),
                               ess_threshold=ess_threshold)  # fmt: skip
    elif card.filter in GAUSSIAN_FILTERS:
        # a particle filter's settings on a Gaussian card (a docs trial: num_particles=100 on
        # the robot's EKF checkpoint loaded without a word, as if it had been used)
        given = [name for name, value, unset in (("num_particles", num_particles, None),
                 ("resampler", resampler, None), ("ess_threshold", ess_threshold, 1.0))
                 if value != unset]  # fmt: skip
        if given:
            raise ValueError(
                f"{', '.join(given)}: set a particle filter, and this checkpoint's network runs "
                f"in the {card.filter} filter its card names (pf checkpoints take them)"
            )
        inner = GAUSSIAN_FILTERS[card.filter]
    else:
        raise ValueError(f"the card names filter {card.filter!r}; known: pf, "
                         f"{', '.join(GAUSSIAN_FILTERS)}")  # fmt: skip
    return NeuralCompensation(
        net, inner, channel=channel, residual=Residual(card.residual),
        standardize=card.standardize, features=card.features, poa_eta=card.poa_eta,
        threshold=card.threshold, deception=deception, gating=card.gating,
        compensation=card.compensation, restart=card.restart, confirm=card.confirm,
        reject=card.reject,
    )  # fmt: skip


def _build(ctx, name: str, particles: bool, trainer: str) -> NeuralCompensation:
    """The checkpoint's network inside its filter as a step object (:func:`_trained_network`
    decides whether it fits the scenario)."""
    filters = ("pf",) if particles else tuple(GAUSSIAN_FILTERS)
    net, card = _trained_network(ctx, name, filters, trainer)
    deception = None
    if Channel(card.channel) is Channel.REPLACEMENT:
        deception = deception_of(ctx.scenario.attack_model(), ctx.dtype)[0]
    # the suite's particle filter (ctx.particle_kwargs): N of the scenario, systematic
    # resampling at every step, compose's defaults
    n = ctx.scenario.num_particles if particles else None
    return compose(net, card, num_particles=n, deception=deception)


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
        "(checkpoint), compensating the channel its card names (the measurements, or the "
        "input under an actuator attack); alarm at its card's threshold (calibrated on "
        "attack-free runs where the card has a calibration, else its training's choice)",
        learned=True,
    )(_learned(_name, _particles, _trainer))


# ------------------------------------------------------------- a trained estimator in Python


class TrainedEstimator:
    """A trained neural FDI estimator from its checkpoint (:func:`load_estimator`): the
    same ``init``/``step`` as every estimator of the library, and ``run`` over whole
    sequences (:func:`difffilter.loop.open_loop`), in eval mode, outputs detached unless
    ``grad=True``.

    Attributes:
        estimator: the step object (:class:`~difffilter.fdi.neural.NeuralCompensation`).
        card: the checkpoint's :class:`~difffilter.models.neural_estimator.EstimatorCard`
            (filter, channel, threshold, the family it was trained for, …).
        path: the checkpoint file.
    """

    def __init__(self, estimator: NeuralCompensation, card, path):
        self.estimator, self.card, self.path = estimator, card, path

    def __repr__(self) -> str:
        c = self.card
        return (f"TrainedEstimator({str(self.path)!r}: {c.filter} filter, {c.channel} channel, "
                f"trained by {c.trainer} on {c.scenario_family}, threshold {c.threshold:g})")  # fmt: skip

    def init(self, model, batch_shape=(), generator=None):
        """The carry before step 1 (:meth:`difffilter.Estimator.init`)."""
        return self.estimator.init(model, batch_shape, generator)

    def step(self, carry, y, u=None, mask=None, *, grad: bool = False):
        """``(carry, StepOutput)`` of one measurement ``y [..., dy]``."""
        with torch.set_grad_enabled(grad):
            return self.estimator.step(carry, y, u, mask)

    def run(self, model, ys, us=None, *, mask=None, generator=None, carry=None,
            nonfinite="raise", grad: bool = False):  # fmt: skip
        """The estimator over ``ys [..., T, dy]`` (``us`` the known inputs, ``mask`` the
        received entries): an :class:`~difffilter.EstimatorOutput` with ``means``,
        ``attack`` estimates and ``detection`` (scores, alarms at the card's threshold).
        ``generator``/``carry``/``nonfinite`` as for :func:`~difffilter.loop.open_loop` (a
        particle filter's draws; ``"skip"``: a NaN or Inf entry of ``ys`` as unreceived)."""
        with torch.set_grad_enabled(grad):
            return open_loop(self.estimator, model, ys, us, mask=mask, generator=generator,
                             carry=carry, nonfinite=nonfinite)  # fmt: skip


def load_estimator(path, *, num_particles: int | None = None, resampler=None,
                   ess_threshold: float = 1.0, deception=None,
                   dtype: torch.dtype = torch.float64, device=None) -> TrainedEstimator:  # fmt: skip
    """A trained estimator from an exported checkpoint or a Lightning checkpoint of a
    training run, ready to run (:class:`TrainedEstimator`).

    The card in the checkpoint says which filter the network runs in and how it reads the
    filter; ``num_particles`` (default: the particles its threshold was calibrated with,
    :func:`calibrated_particles`), ``resampler`` and ``ess_threshold`` set a particle
    filter, ``deception`` the density a replacement-channel network assumes, ``device``
    where the network's weights go (default the CPU; run it on a model and measurements on
    that device, and give a particle filter a generator of that device).
    LFC checkpoints run inside the LFC closed loop (the secure controller and the online
    learners): evaluate them with ``difffilter-eval lfc``. Errors name the argument.
    """
    from difffilter.models.neural_estimator import _weights_dtype, load_estimator_checkpoint

    dtype = _weights_dtype(dtype)
    device = _device(device)
    net, card = load_estimator_checkpoint(path, dtype=dtype)
    if card.scenario_family == "lfc":
        raise ValueError(
            f"{path}: an LFC checkpoint runs inside the LFC closed loop (secure controller, "
            "online learners); evaluate it with difffilter-eval lfc --ckpt"
        )
    net.eval()
    if device is not None:
        net.to(device)
    if num_particles is None and card.filter == "pf":
        num_particles = calibrated_particles(card)
    return TrainedEstimator(
        compose(net, card, num_particles=num_particles, resampler=resampler,
                ess_threshold=ess_threshold, deception=deception), card, path,
    )  # fmt: skip


def calibrated_particles(card) -> int | None:
    """How many particles a ``pf`` card's threshold was calibrated with: what
    ``difffilter-train calibrate`` records (``card.extra["calibration"]["num_particles"]``),
    for a card it calibrated before it recorded them that of the calibration's scenario (it
    scores through the scenario's registered entry, with the scenario's particles), else the
    card's own (the training filter's, whose validation chose the threshold). The tracking
    card's threshold is for the scenario's 500 particles, the card's training filter had
    200: loaded with 200 it alarmed on 1.36 % of fresh attack-free steps, with 500 on 1.19 %
    (a trial, 600 runs × 120 steps)."""
    calibration = card.extra.get("calibration") or {}
    n = calibration.get("num_particles")
    if n is None and calibration.get("scenario"):
        from difffilter.models import registry

        try:
            n = registry.get(calibration["scenario"]).num_particles
        except ValueError:  # a scenario of one's own not registered here: the card's
            n = None
    return card.num_particles if n is None else int(n)


def _device(device):
    """``device`` of :func:`load_estimator` as a ``torch.device`` that this machine has, or
    ``None`` (a CUDA device without CUDA was torch's bare AssertionError)."""
    if device is None:
        return None
    try:
        device = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"device must name a torch device (e.g. 'cpu', 'cuda'); got {device!r}: "
                         f"{exc}") from None  # fmt: skip
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {str(device)!r}: this machine's torch has no CUDA device")
    return device
