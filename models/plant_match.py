"""Whether a trained network meets the plant it was trained on.

A checkpoint's card names the family it was trained for, and ``difffilter-eval`` refuses it
on another family's scenarios. Within a family the scenarios usually share one plant (the
LFC scenarios' attacks differ, their two areas do not), but a family of one's own may hold
several: a user trial's network, trained on a two-mass-spring system of family ``mine``, ran
on a pendulum of the same family without a word (its state error 6× the analytic ones'; only
the report's "trained on" line said where it came from). :func:`plant_difference` compares
the training scenario's plant with an evaluated scenario's where both can be built:

    dimensions (dx, dy, du),  f(x_j, u, 0) and h(x_j, 1) at x_j ∈ {m₀, m₀ + σ_i e_i, m₀ − σ},
    σ = √diag P₀, u = 0.1 · 1, and f(m₀, 0.1 · e_l, 0) for each input l (each to rtol 1e-6,
    atol 1e-9)

(one input at a time, as one state at a time: ``u = 0.1 · 1`` alone read input matrices of
the same row sums as one, actuators wired the other way round among them)

(the noise may differ: a study of the same plant under more noise is one of transfer, not
of another plant). :func:`training_plant_notes` turns that into the lines the command
prints. The shipped checkpoints meet their families' scenarios except ``lfc_sine_1ms``,
whose plant is discretised at 1 ms (the network was trained at 10 ms).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import torch

__all__ = [
    "plant_difference",
    "scenario_file_change",
    "training_scenario_of",
    "training_plant_notes",
]


def plant_difference(trained, evaluated) -> str | None:
    """What differs between two models' plants (the module docstring's comparison), in
    words, or ``None`` where they agree."""
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
    with torch.no_grad():
        for what, read in (("transition", lambda m: m.transition(moved, u, 0)),
                           ("measurement function", lambda m: m.observe(points, 1))):  # fmt: skip
            a, b = (read(m).to(torch.float64) for m in (trained, evaluated))
            if a.shape != b.shape or not torch.allclose(a, b, rtol=1e-6, atol=1e-9):
                return f"its {what} differs about the prior mean"
    return None


def _card(path) -> dict:
    """The JSON card beside a checkpoint, or ``{}`` where there is none that reads."""
    try:
        card = json.loads(Path(path).with_suffix(".json").read_text())
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

    recorded = _card(path).get("scenario_file_sha256")
    if recorded:
        return str(recorded)
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception:  # (not a zip-format torch file: the loaders name it themselves)
        return None
    recorded = blob.get(SCENARIO_FILE_DIGEST) if isinstance(blob, dict) else None
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


def training_plant_notes(
    checkpoints: Sequence[tuple[str, Path]], names: Sequence[str]
) -> list[str]:
    """One line for each checkpoint (``(how it was given, path)``) and evaluated scenario
    of its family whose plant is not the one it was trained on (:func:`plant_difference`),
    and one where its training scenario file has changed since (:func:`scenario_file_change`).
    Nothing where the training scenario cannot be built here (a module not importable, a
    YAML file moved): a note, never an error."""
    from . import registry

    notes = []
    for given, path in checkpoints:
        spec = training_scenario_of(path)
        if spec is None:
            continue
        changed = scenario_file_change(f"--ckpt {given}", path, spec)
        if changed:
            notes.append(changed)
        try:
            trained = registry.get(spec)
            model = trained.system(torch.float64)
        except Exception:  # (another machine's module or file: nothing to compare)
            continue
        for name in names:
            scenario = registry.get(name)
            if scenario.family != trained.family or name == trained.name:
                continue
            try:
                why = plant_difference(model, scenario.system(torch.float64))
            except Exception:  # (a model that cannot be read so: no claim)
                continue
            if why:
                notes.append(
                    f"note: --ckpt {given} was trained on {trained.name}, whose plant is not "
                    f"{name}'s ({why}): its numbers on {name} say how it transfers to another "
                    "plant"
                )
    return notes
