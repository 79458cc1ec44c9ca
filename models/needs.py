"""What an estimator needs of a scenario, declared where it is registered.

An estimator of the registry (:mod:`difffilter.models.estimators`) declares what it needs
to run and to mean something::

    @register("cusum_kf", "KF gated by CUSUM", needs=(LINEAR_MODEL,))

Before running an estimator the suite asks each of its needs whether the scenario meets it
(:meth:`Need.unmet`); one that is not met leaves the estimator out of the study, listed in
``SuiteResult.skipped`` (and the report) with the reason, instead of a crash or a number
that compares different things. Each need states one kind of fact:

- the model it runs on (:data:`LINEAR_MODEL`);
- the family whose parts it reads (:func:`scenario_of`: an LFC observer needs an
  :class:`~difffilter.models.lfc.LFCScenario`);
- what the data must be for its output to mean what its name says
  (:data:`SENSOR_ATTACK`: an oracle that subtracts the true attack from the measurements;
  :data:`ATTACK_FREE_MEASUREMENTS`: an attack-free reference run on the true ``y``), read
  from the attack the plant meets (:meth:`~difffilter.models.scenario.Scenario.simulated_attack`);
- what it assumes about the attack (:data:`ASSUMES_SENSOR_ATTACK`,
  :data:`ASSUMES_DECEPTION_DENSITY`), read from the scenario's own attack
  (:meth:`~difffilter.models.scenario.Scenario.attack_model`): in a threat study the
  defender keeps its assumptions while the attacker changes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from difffilter.attack import Channel
from difffilter.kalman import _check_linear
from difffilter.noise import Gaussian
from difffilter.particle import transition_law_unsaid

__all__ = [
    "Need",
    "LINEAR_MODEL",
    "SENSOR_ATTACK",
    "ATTACK_FREE_MEASUREMENTS",
    "ASSUMES_SENSOR_ATTACK",
    "ASSUMES_DECEPTION_DENSITY",
    "UNACKNOWLEDGED_INPUT_LOSS",
    "scenario_of",
    "model_of",
    "first_unmet",
]


@dataclass(frozen=True)
class Need:
    """One requirement: ``what`` (a line for the docs) and ``check(scenario, model)``, the
    reason it is not met or ``None``."""

    what: str
    check: Callable[[Any, Any], str | None]

    def unmet(self, scenario, model) -> str | None:
        """Why ``scenario`` (with its estimators' ``model``) does not meet this need, or
        ``None``. A check that returns anything else (a predicate's ``True`` where the need
        is met) is named: its ``True`` had been taken for a reason, the estimator left out
        of the study without a word (an estimator-API trial)."""
        reason = self.check(scenario, model)
        if reason is None or (isinstance(reason, str) and reason):
            return reason
        raise TypeError(
            f"the need {self.what!r}: its check(scenario, model) returns the reason it is not "
            f"met (a non-empty string) or None where it is met; got {reason!r}"
        )


def _channel(attack) -> Channel | None:
    return None if attack is None else Channel(getattr(attack, "channel", Channel.SENSOR))


def _linear(scenario, model) -> str | None:
    # the Kalman filter's own test (a transition matrix alone had passed the tracking
    # model, whose measurements are nonlinear: kf then died in the suite, not skipped)
    try:
        _check_linear(model)
    except TypeError:
        return f"needs a linear model (LinearGaussianModel); this one is a {type(model).__name__}"
    return None


#: A linear-Gaussian model (the Kalman filter's).
LINEAR_MODEL = Need("a linear model (LinearGaussianModel)", _linear)


def _transition_law(scenario, model) -> str | None:
    # what KalmanProposal checks before its first step: a need it passed and the proposal
    # refused (a UniformBox process noise) stopped the whole study instead of skipping it
    noise = getattr(model, "process_noise", None)
    if noise is not None and not isinstance(noise, Gaussian):
        return (f"weighs its particles by N(f, Q), and the process noise is a "
                f"{type(noise).__name__}, not Gaussian")  # fmt: skip
    why = transition_law_unsaid(model)
    return None if why is None else f"weighs its particles by N(f, Q), and {why}"


#: The model draws its transitions as ``f + w``, ``w`` its process noise, a Gaussian (the
#: Kalman proposal's weights take them so).
TRANSITION_IS_PROCESS_NOISE = Need("transitions drawn as f + its Gaussian process noise",
                                   _transition_law)  # fmt: skip


def _sensor_attack(scenario, model) -> str | None:
    channel = _channel(scenario.simulated_attack())
    if channel is not Channel.ACTUATOR:
        return None
    return ("reads the attack on the measurements (an oracle γ̂ subtracted from ỹ); this "
            "scenario's attack acts on the actuators")  # fmt: skip


#: The plant's attack, if any, acts on the measurements (sensor or replacement channel).
SENSOR_ATTACK = Need("the plant's attack acts on the measurements", _sensor_attack)


def _attack_free_y(scenario, model) -> str | None:
    attack = scenario.simulated_attack()
    if _channel(attack) is not Channel.ACTUATOR and not getattr(attack, "conceals", False):
        return None
    return (
        "an attack-free reference runs on the true measurements y, and here y carries "
        "the actuator attack through the plant: no attack-free reference on this scenario"
    )


#: The true measurements ``y`` are attack-free (no actuator attack drives the plant).
ATTACK_FREE_MEASUREMENTS = Need("attack-free true measurements (no actuator attack)",
                                _attack_free_y)  # fmt: skip


def _assumes_sensor(scenario, model) -> str | None:
    channel = _channel(scenario.attack_model())
    if channel is not Channel.ACTUATOR:
        return None
    return ("assumes an attack on the measurements (it estimates and removes a sensor "
            "bias); this scenario's attack acts on the actuators")  # fmt: skip


#: The scenario's attack model acts on the measurements.
ASSUMES_SENSOR_ATTACK = Need("assumes an attack on the measurements", _assumes_sensor)


def _assumes_deception(scenario, model) -> str | None:
    from .generic_estimators import deception_of

    attack = scenario.attack_model()
    if attack is None:
        return "assumes a known deception density, and the scenario has no attack"
    try:
        deception_of(attack, model.initial.mean.dtype)
    except ValueError:
        return (f"assumes a known deception density (a SensorBias's γ̄ or a Replacement's "
                f"box); the scenario's attack is a {type(attack).__name__}")  # fmt: skip
    return None


#: The scenario's attack has a density the mixture likelihood can use
#: (:func:`~difffilter.models.generic_estimators.deception_of`).
ASSUMES_DECEPTION_DENSITY = Need("assumes a known deception density", _assumes_deception)


def _unacknowledged_loss(scenario, model) -> str | None:
    from .generic_estimators import expected_input_filter

    try:
        expected_input_filter(scenario, model)
    except ValueError as error:
        return str(error)
    return None


#: The scenario loses input packets at random, unacknowledged (UDP-like): what the
#: expected-input Kalman filter of its arrival rate needs (with :data:`LINEAR_MODEL`;
#: :func:`~difffilter.models.generic_estimators.expected_input_filter`).
UNACKNOWLEDGED_INPUT_LOSS = Need(
    "random, independent, unacknowledged input loss (UDP-like)", _unacknowledged_loss
)


def _instance_of(cls: type, of_model: bool, what: str, why) -> Need:
    """A need met when the scenario (or, with ``of_model``, its model) is a ``cls``;
    ``why(scenario, model)`` is the reason otherwise."""

    def check(scenario, model) -> str | None:
        return None if isinstance(model if of_model else scenario, cls) else why(scenario, model)

    return Need(what, check)


def scenario_of(cls: type, family: str) -> Need:
    """The scenario is a ``cls`` (the ``family``'s scenario class, whose parts the
    estimator reads: its plant's matrices, its schedule, its paper's settings)."""
    return _instance_of(
        cls, False, f"the {family} family's scenario ({cls.__name__})",
        lambda sc, model: (f"an estimator of the {family} family: it reads the parts of a "
                           f"{cls.__name__}, and {sc.name!r} is a {type(sc).__name__}"),
    )  # fmt: skip


def model_of(cls: type) -> Need:
    """The estimators' model is a ``cls`` (e.g. the four-tank model, whose fixed point and
    input matrix an estimator reads), whatever the scenario around it."""
    return _instance_of(
        cls, True, f"a {cls.__name__} model",
        lambda sc, model: f"needs a {cls.__name__} model; this one is a {type(model).__name__}",
    )  # fmt: skip


def first_unmet(needs, scenario, model) -> str | None:
    """The reason of the first need of ``needs`` that ``scenario`` does not meet, or ``None``."""
    for need in needs:
        reason = need.unmet(scenario, model)
        if reason is not None:
            return reason
    return None
