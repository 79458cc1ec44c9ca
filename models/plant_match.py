"""Whether a trained network meets the plant it was trained on.

A checkpoint's card names the family it was trained for, and ``difffilter-eval`` refuses it
on another family's scenarios. Within a family the scenarios usually share one plant (the
LFC scenarios' attacks differ, their two areas do not), but a family of one's own may hold
several: a user trial's network, trained on a two-mass-spring system of family ``mine``, ran
on a pendulum of the same family without a word (its state error 6× the analytic ones'; only
the report's "trained on" line said where it came from). :func:`plant_difference` compares
the training scenario's plant with an evaluated scenario's where both can be built:

    dimensions (dx, dy, du),  f(x_j, u, k) and h(x_j, k) at x_j ∈ {m₀, m₀ + σ_i e_i, m₀ − σ},
    σ = √diag P₀, u = 0.1 · 1, and f(m₀, 0.1 · e_l, k) for each input l, at the steps
    k ∈ {0, 1, 2, 7} (h: {1, 2, 7}), each to rtol 1e-6, atol 1e-9 (16 ε of float32, scaled,
    where a model is float32), the same NaN in both reading as agreement

(one input at a time, as one state at a time: ``u = 0.1 · 1`` alone read input matrices of
the same row sums as one, actuators wired the other way round among them)

(the noise may differ: a study of the same plant under more noise is one of transfer, not
of another plant). :func:`training_plant_notes` turns that into the lines the command
prints, building the training scenario outside the registry and deciding "another plant" by
the plants, never by the names; and, where the checkpoint records the training plant's
fingerprint (:func:`plant_fingerprint`, on every card since), it says where that plant
reads otherwise now. The shipped checkpoints meet their families' scenarios except ``lfc_sine_1ms``,
whose plant is discretised at 1 ms (the network was trained at 10 ms).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import torch

__all__ = [
    "PLANT_FINGERPRINT",
    "plant_change",
    "plant_difference",
    "plant_fingerprint",
    "scenario_file_change",
    "training_scenario",
    "training_scenario_of",
    "training_plant_notes",
]


#: The step indices at which f(·, ·, k) and h(·, k) are probed: a plant that reads k (a
#: forcing sin(ωkΔt)) can agree at k = 0 and differ from k = 1 on (a trial's two
#: oscillators of ω = 1 and 5 read as one plant when f was probed at k = 0 alone)
PROBE_STEPS = (0, 1, 2, 7)


def plant_difference(trained, evaluated) -> str | None:
    """What differs between two models' plants (the module docstring's comparison), in
    words, or ``None`` where they agree. Each model is probed in its own dtype and device
    (a float32 model had been handed float64 points: "double != float"), and where either
    is coarser than float64 the tolerance is widened to its precision."""
    dims = [(m.dim_x, m.dim_y, int(getattr(m, "dim_u", 0) or 0)) for m in (trained, evaluated)]
    if dims[0] != dims[1]:
        return f"its dimensions (dx, dy, du) are {dims[0]} against {dims[1]}"
    mean = trained.initial.mean.detach().to(torch.float64)
    spread = torch.diagonal(trained.initial.cov.detach(), dim1=-2, dim2=-1).sqrt().to(mean.dtype)
    if mean.dim() != 1:  # a prior per run: its first
        mean, spread = mean.reshape(-1, mean.shape[-1])[0], spread.reshape(-1, mean.shape[-1])[0]
    # m₀, m₀ + σ_i e_i for each state (one coordinate at a time: points on the diagonal
    # alone confused h = x₁ with h = x₂ for m₀ = 1) and m₀ − σ
    points = torch.cat([mean[None], mean + torch.diag(spread), (mean - spread)[None]])
    du = dims[0][2]
    moved, u = points, None
    if du:  # u = 0.1 · 1 at every point, then 0.1 · e_l at m₀ for each input l
        u = torch.cat([torch.full((len(points), du), 0.1, dtype=mean.dtype),
                       0.1 * torch.eye(du, dtype=mean.dtype)])  # fmt: skip
        moved = torch.cat([points, mean.expand(du, -1)])
    tolerance = _tolerance(trained, evaluated)
    with torch.no_grad():
        for what, read, steps in (
            ("transition", lambda m, k: m.transition(_as(moved, m), _as(u, m), k), PROBE_STEPS),
            ("measurement function", lambda m, k: m.observe(_as(points, m), k), PROBE_STEPS[1:]),
        ):
            for k in steps:
                a, b = (read(m, k).to(torch.float64).cpu() for m in (trained, evaluated))
                # (the same NaN in both is agreement: a probe point outside both plants'
                # domain, √x at m₀ − σ < 0, had called a plant another than itself)
                if a.shape != b.shape or not torch.allclose(a, b, equal_nan=True, **tolerance):
                    return f"its {what} differs about the prior mean"
    return None


def _as(value, model):
    """``value`` (the probe points or inputs, float64) in ``model``'s dtype and device."""
    if value is None:
        return None
    prior = model.initial.mean
    return value.to(dtype=prior.dtype, device=prior.device)


def _tolerance(*models) -> dict[str, float]:
    """``rtol`` and ``atol`` of the comparison: 1e-6 and 1e-9, or 16 ε of the coarser dtype
    (ε of float32: 1.2e-7) where that is wider (the absolute one scaled by the prior mean's
    size, whose rounding the outputs carry)."""
    eps = max(torch.finfo(m.initial.mean.dtype).eps for m in models)
    if eps <= torch.finfo(torch.float64).eps:
        return {"rtol": 1e-6, "atol": 1e-9}
    scale = max(1.0, float(models[0].initial.mean.detach().abs().max()))
    return {"rtol": max(1e-6, 16 * eps), "atol": max(1e-9, 16 * eps * scale)}


def _card(path) -> dict:
    """The JSON card beside a checkpoint, or ``{}`` where there is none that reads."""
    try:
        card = json.loads(Path(path).with_suffix(".json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return card if isinstance(card, dict) else {}


def training_scenario_of(path) -> str | None:
    """The scenario a checkpoint's network was trained on, as its training was given it
    (the JSON card's ``model_config.scenario`` beside an export, or a Lightning
    checkpoint's ``hyper_parameters.scenario``: a registered name, ``module:object`` or a
    YAML path), else the name inside the checkpoint; ``None`` where none says. (A run's
    Lightning checkpoint has no card beside it: its YAML scenario's name alone could not be
    built by another process, and both notes of :func:`training_plant_notes` went unsaid.)"""
    from .neural_estimator import checkpoint_training_scenario

    config = _card(path).get("model_config")
    # (a card whose model_config is not a mapping says nothing: it had raised AttributeError)
    spec = config.get("scenario") if isinstance(config, dict) else None
    spec = spec or _lightning_scenario(path)
    return str(spec) if spec else checkpoint_training_scenario(path)


def _lightning_scenario(path) -> str | None:
    """The ``scenario`` hyperparameter a Lightning checkpoint records, else ``None``."""
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception:  # (not a zip-format torch file: the loaders name it themselves)
        return None
    hparams = blob.get("hyper_parameters") if isinstance(blob, dict) else None
    spec = hparams.get("scenario") if isinstance(hparams, dict) else None
    return spec if isinstance(spec, str) and spec else None


def _recorded_file_digest(path) -> str | None:
    """The sha256 of the YAML scenario file a checkpoint's network was trained on, as its
    training read it: the export card's ``scenario_file_sha256``, else a Lightning
    checkpoint's own record; ``None`` where neither holds one (a registered scenario, a
    card written before the field)."""
    from .yaml_scenario import SCENARIO_FILE_DIGEST

    return _recorded(path, "scenario_file_sha256", SCENARIO_FILE_DIGEST)


def _recorded(path, card_key: str, checkpoint_key: str) -> str | None:
    """What a checkpoint records under ``card_key`` on its export card, else under
    ``checkpoint_key`` in a Lightning checkpoint itself; ``None`` where neither does."""
    recorded = _card(path).get(card_key)
    if recorded:
        return str(recorded)
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception:  # (not a zip-format torch file: the loaders name it themselves)
        return None
    recorded = blob.get(checkpoint_key) if isinstance(blob, dict) else None
    return None if recorded is None else str(recorded)


def scenario_file_change(given: str, path, spec: str | None = None) -> str | None:
    """A note (naming the checkpoint as ``given``) where the YAML scenario file it was
    trained on (``spec``, default :func:`training_scenario_of`; read from this folder) now
    holds other bytes than training read: the plant comparison of
    :func:`training_plant_notes` builds the training plant from the file as it is now, so
    an edit after training went unseen (a trial edited F after export and evaluated and
    calibrated without a word). ``None`` where the file is unchanged, cannot be read here,
    or the checkpoint records no digest."""
    from .yaml_scenario import is_yaml_path, scenario_file_digest, scenario_file_matches

    spec = training_scenario_of(path) if spec is None else spec
    if spec is None or not is_yaml_path(spec):
        return None
    recorded, now = _recorded_file_digest(path), scenario_file_digest(spec)
    if recorded is None or now is None or scenario_file_matches(recorded, spec):
        return None
    return (
        f"note: {given} was trained on the scenario file {spec} as it was then "
        f"(digest {recorded[:12]}…); it, or the Python code it names, differs now "
        f"({now[:12]}…): the network never saw the plant as the file describes it today"
    )


#: The key of a training run's Lightning checkpoint (and, as ``scenario_plant_sha256``, of
#: an export's card) for the fingerprint of the plant it trained on (:func:`plant_fingerprint`).
PLANT_FINGERPRINT = "difffilter_scenario_plant_sha256"


def plant_fingerprint(scenario) -> str:
    """The fingerprint of ``scenario``'s plant (its float64 model) as the calibration cache
    reads one (:func:`~difffilter.models.calibration_cache.model_fingerprint`: its tensors,
    and the code, constants and closures of its functions), recorded on a checkpoint's
    card at training so that an edit of a ``module:object`` plant after training is seen
    (the YAML file's digest covers a file alone: a trial edited F in its module unseen)."""
    from .calibration_cache import model_fingerprint

    return model_fingerprint(scenario.system(torch.float64))


def _recorded_plant(path) -> str | None:
    """The plant fingerprint a checkpoint records (the card's ``scenario_plant_sha256``, else
    a Lightning checkpoint's own), ``None`` where none does (a card written before it)."""
    return _recorded(path, "scenario_plant_sha256", PLANT_FINGERPRINT)


def plant_change(given: str, path, spec: str, trained) -> str | None:
    """A note (naming the checkpoint as ``given``) where the plant of its training scenario
    ``spec``, as built here (``trained``), has another fingerprint than training recorded:
    a ``module:object`` plant edited since (:func:`scenario_file_change` reads YAML files
    only). ``None`` where they match or the checkpoint records none."""
    recorded = _recorded_plant(path)
    if recorded is None:
        return None
    now = plant_fingerprint(trained)
    if now == recorded:
        return None
    return (
        f"note: {given} was trained on the plant of {spec} as it was then (fingerprint "
        f"{recorded[:12]}…); that plant, or the code that builds it, reads otherwise now "
        f"({now[:12]}…): the network never saw the plant as it is today"
    )


def training_scenario(spec: str):
    """The scenario ``spec`` (a checkpoint's training scenario) names, read without the
    registry where it is a YAML file or ``module:object`` path: an evaluated copy of the
    file with its plant edited and its ``name`` kept is registered under that name, and
    registering the training file then raised the name clash (the plant comparison was
    dropped without a word, a trial)."""
    from . import registry
    from .scenario import Scenario
    from .yaml_scenario import import_object, is_yaml_path, scenario_from_yaml

    if is_yaml_path(spec):
        return scenario_from_yaml(spec)
    if ":" in spec:
        found = import_object(spec, f"scenario {spec!r}")
        if callable(found) and not isinstance(found, Scenario):
            found = found()
        if isinstance(found, Scenario):
            return found
    return registry.get(spec)


def training_plant_notes(
    checkpoints: Sequence[tuple[str, Path]], names: Sequence[str], *, flag: str = "--ckpt"
) -> list[str]:
    """One line for each checkpoint (``(how it was given, path)``, named as ``flag given``)
    and evaluated scenario of its family whose plant is not the one it was trained on
    (:func:`plant_difference`: the plants, not the names, decide: a copy of the training
    file with another plant and the same ``name`` is another plant), and one where its
    training scenario file, or plant, has changed since (:func:`scenario_file_change`,
    :func:`plant_change`). Nothing where the training scenario cannot be built here (a
    module not importable, a YAML file moved): a note, never an error."""
    from . import registry

    notes = []
    for given, path in checkpoints:
        spec = training_scenario_of(path)
        if spec is None:
            continue
        label = f"{flag} {given}" if flag else given
        changed = scenario_file_change(label, path, spec)
        if changed:
            notes.append(changed)
        try:
            trained = training_scenario(spec)
            model = trained.system(torch.float64)
        except Exception:  # (another machine's module or file: nothing to compare)
            continue
        if not changed:  # (a YAML file's edit is said above, in the file's words)
            try:
                changed = plant_change(label, path, spec, trained)
            except Exception:  # (a plant that cannot be fingerprinted: no claim)
                changed = None
            if changed:
                notes.append(changed)
        if changed:  # the plant built here is not the one trained on: no comparison with it
            continue
        for name in names:
            scenario = registry.get(name)
            if scenario.family != trained.family:
                continue
            try:
                why = plant_difference(model, scenario.system(torch.float64))
            except Exception:  # (a model that cannot be read so: no claim)
                continue
            if why:
                # (the same name on both: the training one named by its file or path)
                was = trained.name if trained.name != name else f"{spec} (named {name} too)"
                notes.append(
                    f"note: {label} was trained on {was}, whose plant is not {name}'s ({why}): "
                    f"its numbers on {name} say how it transfers to another plant"
                )
    return notes
