"""Which of a study's threats a learned estimator met in training.

A network trained across threats (``data.init_args.threats``, a
:class:`~difffilter.threat_distribution.ThreatDistribution`) has seen some of a robustness
study's threats and not others; a verdict on a threat it was trained on says less than one
on a threat it never met. :func:`training_coverage` reads the card an export writes beside
its checkpoint (``<checkpoint>.json``: the training's data and model settings) and labels
every threat of the study (:meth:`~difffilter.threat_distribution.ThreatDistribution.covers`):

============  ================================================================================
within        a component of the training distribution could draw it (kind and every field);
              a component the weights never met in training (the card's ``threats_drawn``,
              runs per component until the weights were saved: a small weight, few epochs)
              counts for nothing
kind only     its kind was drawn, with other fields (another size, onset, share, …); a crafted
              attack when the network was trained adversarially (crafted against the network
              of the moment, fewer iterations) and its weights were saved after the first
              crafting (the card's ``adversarial_craftings``; weights chosen on an epoch
              before it met no crafted attack: held out)
held out      its kind was never drawn (for a network trained on its scenario's attack
              alone: every threat but those of that attack's kind, where it is a threat of
              the library)
not known     a threat of a class of your own (``module:object``) beside a network trained on
              its scenario's attack (alone, or as a distribution's ``own`` it drew) where that
              attack is not a threat of the library: nothing says whether it is the attack
              trained on (a user trial's network read "held out" on its own scaling attack,
              the one it was trained on)
============  ================================================================================
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from difffilter._checks import check_finite_number
from difffilter.threat_distribution import (
    HELD_OUT,
    KIND_ONLY,
    WITHIN,
    ThreatDistribution,
    threat_spec,
)
from difffilter.threats import THREATS, with_sampling_period

__all__ = ["training_coverage", "checkpoint_of", "NOT_KNOWN"]

#: The label of a threat the card cannot place (module docstring).
NOT_KNOWN = "not known"

#: What a card says the network was trained on, as the reports name it.
SCENARIO_ATTACK, DISTRIBUTION = "its scenario's attack", "a distribution over threats"


def _check_threats(threats) -> None:
    """``threats`` a mapping of threat name to a mapping with a ``kind`` of the library,
    ``stealthy`` or ``module:object``: a misspelt or missing kind had been labelled "held
    out", a list failed on ``.items`` (a coverage trial)."""
    if not isinstance(threats, Mapping):
        raise ValueError(f"threats must be a mapping {{name: {{'kind': …, …}}}}; got "
                         f"{type(threats).__name__}")  # fmt: skip
    for name, threat in threats.items():
        kind = threat.get("kind") if isinstance(threat, Mapping) else None
        if not isinstance(kind, str) or not (kind in THREATS or kind == "stealthy"
                                             or ":" in kind):  # fmt: skip
            raise ValueError(
                f"threats[{name!r}] must be a mapping whose kind is one of "
                f"{', '.join(sorted(THREATS))}, stealthy or module:object; got {threat!r}"
            )


#: ``_trained_scenario``'s answer where the card names a scenario file that is gone or
#: was edited since the training read it: the attack trained on is not known.
UNKNOWN_ATTACK = object()


def _trained_scenario(card: dict, own, dt):
    """``(own, dt)`` of the scenario the card says the weights were trained on
    (``data_config.scenario``: its attack and sampling period, which its training filled
    in): a registered name from the registry; a YAML file read as it is (not registered:
    a file of the study's name had collided, and the study's attack was read, a review)
    where its digest is the card's (``scenario_file_sha256``), else ``UNKNOWN_ATTACK`` (a
    file edited since: its new attack had been credited); the caller's (the study's) for
    a module's object or a name not registered here."""
    from difffilter.models import registry
    from difffilter.models.yaml_scenario import (
        is_yaml_path,
        scenario_file_matches,
        scenario_from_yaml,
    )

    name = (card.get("data_config") or {}).get("scenario")
    if not isinstance(name, str):
        return own, dt
    if is_yaml_path(name):
        recorded = card.get("scenario_file_sha256")
        # (scenario_file_matches: a card of before the digest covered the file's Python
        # code had read "not known" for an unchanged file, a review)
        if not Path(name).is_file() or (recorded and not scenario_file_matches(recorded, name)):
            return UNKNOWN_ATTACK, dt
        trained = scenario_from_yaml(name)
    else:
        try:
            trained = registry.get(name)
        except (KeyError, ValueError):  # (a module's object of a user's, not registered here)
            return own, dt
    return trained.attack_model(), getattr(trained, "dt", dt)


def checkpoint_of(name: str, suite) -> str | None:
    """The checkpoint file learned estimator ``name`` ran with in ``suite`` (a
    :class:`~difffilter.eval.suite.SuiteResult`): its own (``--ckpt name=path``), else the
    default one if it used it, else ``None``."""
    own = (suite.checkpoints or {}).get(name)
    if own:
        return own["path"]
    default = suite.checkpoint or {}
    return default.get("path") if name in default.get("used_by", ()) else None


def training_coverage(
    checkpoint, threats: dict[str, dict], model=None, own=None, dt: float | None = None
) -> dict[str, Any] | None:
    """``{"trained_on", "adversarial", "threats": {threat: label}}`` for the estimator of
    ``checkpoint`` against the study's ``threats`` (``{name: {"kind", **fields}}``), or
    ``None`` where no card beside the checkpoint says how it was trained (a Lightning
    checkpoint of a run, a file copied alone). ``model``: the scenario's, for threat kinds
    that read it (``ksigma_bias``, ``covert``). ``own``: the scenario's attack, what a
    network trained on it alone (or on a distribution's ``own``) met: where it is a threat
    of the library, a threat of its kind is "kind only" or "within", not "held out" (a
    user trial's ramp network read "held out" on a ramp that differed only in its share).
    ``dt``: the scenario's sampling period, a sinusoid's or chirp's where it sets none, on
    both sides, as training and the study fill it in (left out, the class's default had been
    compared: the very attack trained on read "kind only", and one at 20× another
    frequency "within")."""
    _check_threats(threats)
    if dt is not None:
        dt = check_finite_number(dt, "dt", positive=True)
    card_path = Path(checkpoint).with_suffix(".json") if checkpoint else None
    if card_path is None or not card_path.is_file():
        return None
    card = json.loads(card_path.read_text(encoding="utf-8"))
    # the attack and sampling period of the scenario the weights were trained on, where the
    # card names one that is registered: the study's had been credited (a network trained on
    # four_tank_bias read "within" on a library bias it never met, studied on another
    # scenario of the family whose attack that is: a coverage trial)
    own, trained_dt = _trained_scenario(card, own, dt)
    unknown = own is UNKNOWN_ATTACK
    if unknown:
        own = None
    spec = (card.get("data_config") or {}).get("threats")
    # adversarial only where the weights met a crafted attack: configured, they may predate
    # the first crafting (the card's count; a card written before it counted: configured)
    crafted = card.get("adversarial_craftings")
    adversarial = bool((card.get("model_config") or {}).get("adversarial_runs")) and crafted != 0
    drawn = card.get("threats_drawn")  # runs per component the weights met (a newer card)
    if spec and isinstance(drawn, dict):  # a component never drawn was not trained on
        spec = {name: entry for name, entry in spec.items() if drawn.get(name, 0) > 0}
        spec = spec or {"none": {"weight": 1.0}}  # (every draw of no component: no threat)
    if not spec:  # trained on the scenario's attack alone: a distribution of that one
        spec = {"own": {"weight": 1.0}} if threat_spec(own) is not None else None
        trained_on = SCENARIO_ATTACK
    else:
        trained_on = DISTRIBUTION
    if spec:
        spec = {name: with_sampling_period(entry, trained_dt) for name, entry in spec.items()}
    threats = {name: with_sampling_period(threat, dt) for name, threat in threats.items()}
    try:
        distribution = ThreatDistribution(spec, model=model, own=own) if spec else None
    except ValueError as error:
        # a card of another version whose distribution this one refuses (a share it now
        # names, a kind it lacks): its threats cannot be placed, and the study they label
        # had run to the end before failing here (a coverage trial)
        warnings.warn(f"{card_path}: its training distribution cannot be read by this "
                      f"version ({error}); its threats are labelled '{NOT_KNOWN}'",
                      stacklevel=2)  # fmt: skip
        return {"trained_on": trained_on, "adversarial": adversarial,
                "threats": dict.fromkeys(threats, NOT_KNOWN)}  # fmt: skip
    # a scenario attack of no library kind, met alone or as a distribution's drawn `own`: a
    # threat of a user's class may be that attack (the distribution's had read "held out")
    if trained_on == SCENARIO_ATTACK:
        unplaced = spec is None
    else:
        drawn_own = float((spec.get("own") or {}).get("weight", 0)) > 0
        unplaced = drawn_own and own is not None and threat_spec(own) is None
    # the scenario's attack trained on not known (its file gone or edited): whatever it
    # could have covered is not known, what a drawn component covers exactly still is
    own_met = trained_on == SCENARIO_ATTACK or float((spec.get("own") or {}).get("weight", 0)) > 0
    labels = {}
    for name, threat in threats.items():
        if threat.get("kind") == "stealthy":  # crafted when the study runs, not drawn
            labels[name] = KIND_ONLY if adversarial else HELD_OUT
        elif unplaced and ":" in str(threat.get("kind", "")):
            labels[name] = NOT_KNOWN
        else:
            labels[name] = HELD_OUT if distribution is None else distribution.covers(threat)
            if unknown and own_met and labels[name] != WITHIN:
                labels[name] = NOT_KNOWN
    return {"trained_on": trained_on, "adversarial": adversarial, "threats": labels}
