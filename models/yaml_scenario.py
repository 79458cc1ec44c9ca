"""Scenarios written in YAML: a linear plant as matrices, or a plant given by Python paths.

Wherever a scenario name is taken (both command lines, ``run_suite``, a training config),
a path ending in ``.yaml`` or ``.yml`` names a file such as::

    name: motor_actuator                 # required: the report folder, the card's scenario
    family: user_plants                  # default "custom"
    description: DC motor, known input, bias on the actuator
    dt: 0.01                             # sampling period in s (default 1)
    runs: 50                             # default Monte Carlo runs (default 100)
    steps: 150                           # horizon (default 100)
    num_particles: 200                   # of the particle filters (default 100)
    false_alarm_rate: 0.01               # of the residual detectors (default 0.005)
    gamma_min: 0.1                       # PoA's smallest attack norm (optional)
    units: {state: rad/s, attack: V}     # what reports call state and attack units
    plant:                               # a linear plant ...
      F: [[0.95, 0.04], [-0.02, 0.8]]    #   x_{k+1} = F x_k + B u_k + w_k
      B: [[0.0], [0.2]]
      H: [[1.0, 0.0]]                    #   y_k = H x_k + v_k
      Q: 1.0e-4                          #   a number (× I), a list (diagonal) or a matrix
      R: 1.0e-3
      m0: [0.0, 0.0]                     #   prior mean (default zeros) and covariance
      P0: 1.0e-2                         #   (default I)
    random_initial: false                # true: each run starts at x_0 ~ N(m0, P0);
                                         #    false (default): every run at m0
    inputs: {kind: sinusoid, amplitude: 1.0, frequency: 0.5}   # known inputs (optional)
    attack: {kind: bias, channel: actuator, value: 0.5, onset: 50, share: 0.5}
                                         #    (a sinusoid's or chirp's dt: the file's
                                         #    unless set: frequencies in its time unit)
    schedule: all                        # or {kind: round_robin, groups: [[0], [1]]},
                                         #    {kind: packet_loss, rate: 0.1} (packets:
                                         #    [[0, 1], [2]]: entries lost together),
                                         #    {kind: burst_loss, to_bad: 0.05, to_good:
                                         #    0.25} (Gilbert–Elliott: losses in bursts;
                                         #    loss_good, loss_bad, packets optional)
    input_loss: {kind: packet_loss, rate: 0.1, on_loss: hold, acknowledged: true}
                                         # optional: the inputs' packets lost on the way
                                         #    to the actuators (any schedule kind above,
                                         #    over the inputs; on_loss hold or zero;
                                         #    acknowledged true: TCP-like, false: UDP-like)
    estimators: [chi_square_kf, cusum_kf]   # optional; default: the generic suite
    options: {cusum_bias: 2.0}           # settings the estimators read (optional; the
                                         #    CUSUM's drift b above E[g] = dy)

A nonlinear plant names its functions by ``package.module:function`` paths, with the
noise as above::

    plant:
      transition: my_plants:vdp_step     # f(x), f(x, u) or f(x, u, k): [..., dx] → [..., dx]
      observe: my_plants:vdp_measure     # h(x) or h(x, k); or H: [[...]] for a linear one
      dim_u: 0
      angles: [1]                        # optional: measurement entries that are angles
                                         #    (bearings): residuals wrapped to (−π, π]
      Q: 1.0e-4
      R: 1.0e-2
      m0: [2.0, 0.0]
      P0: 1.0e-2

or the whole model by one path, ``plant: {model: my_plants:vdp}`` (a function ``dtype →
StateSpaceModel``). ``inputs`` is ``{kind: sinusoid, amplitude, frequency (Hz), phase
(rad)}`` (each a number, or a list with one per input for several), ``{kind: constant,
value}`` (a number or one per input), ``{values: [[...], ...]}`` (``[T, du]``) or
``{function: module:function}`` (of the step index tensor ``k``, as
:class:`~difffilter.models.scenario.CustomScenario`'s ``known_inputs``). ``attack`` is
any threat of :data:`difffilter.threats.THREATS` (``kind`` and its fields), an attack of
one's own (``kind: package.module:object`` and its arguments, as a threat set names one:
:func:`~difffilter.threats.threat_from_dict`), or one of the papers' attacks:
``sensor_bias`` (``gamma_bar``, ``tau``, ``p_l``; eqs 3–4 of the modified-PF paper),
``actuator_injection`` (``value``, ``start``) and ``replacement`` (``rate``, ``low``,
``high``). Every error names the file and the field.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from difffilter._imports import import_object
from difffilter.attack import Channel
from difffilter.input_loss import InputLossSchedule
from difffilter.ssm import LinearGaussianModel, NonlinearGaussianModel, StateSpaceModel, _arity
from difffilter.threats import THREATS, check_attack_fits, threat_from_dict, with_sampling_period

from .attacks import ActuatorInjection, Replacement, SensorBias
from .scenario import CustomScenario
from .schedules import AllSensors, BurstLoss, PacketLoss, RoundRobin

__all__ = [
    "check_unique_keys",
    "is_yaml_path",
    "scenario_from_yaml",
    "scenario_from_dict",
    "import_object",
    "PAPER_ATTACKS",
]

#: The papers' attacks by the names a YAML scenario uses (beside the threat library's).
PAPER_ATTACKS = {
    "sensor_bias": SensorBias,
    "actuator_injection": ActuatorInjection,
    "replacement": Replacement,
}
_TOP = {"name", "family", "description", "dt", "runs", "steps", "num_particles",
        "false_alarm_rate", "gamma_min", "units", "plant", "inputs", "attack", "schedule",
        "input_loss", "estimators", "options", "paper", "notes", "random_initial"}  # fmt: skip
_PLANT = {"F", "B", "H", "Q", "R", "m0", "P0", "transition", "observe", "dim_u", "model",
          "angles"}  # fmt: skip


def is_yaml_path(name: str) -> bool:
    """Whether a scenario name is a YAML file's path (it ends in ``.yaml`` or ``.yml``)."""
    return str(name).lower().endswith((".yaml", ".yml"))


#: The key of a training run's Lightning checkpoint (and, as ``scenario_file_sha256``, of
#: an export's card) for the sha256 of the YAML scenario file it trained on.
SCENARIO_FILE_DIGEST = "difffilter_scenario_file_sha256"


def scenario_file_digest(name) -> str | None:
    """The sha256 of a YAML scenario file's bytes (what its plant, attack and schedule are)
    and, where it names Python objects (``module:function``: a nonlinear plant's functions,
    its inputs' function, an attack of one's own), of their code as the calibration cache
    fingerprints it (:func:`~difffilter.models.calibration_cache.model_fingerprint`: code,
    constants, defaults and the module-level values the functions read); ``None`` for a name
    that is no YAML file's path or a file that cannot be read. What a run trained or a
    study computed on a scenario file is reused only for the same digest (a training trial:
    a sweep judged a plant whose R was edited against the old plant's baselines, and resumed
    runs across the edit; another's edited the pendulum's gravity in its module, and the
    sweep re-scored the old network against the old plant's baselines). A file that names no
    Python object has the digest of its bytes alone, as before."""
    import hashlib

    if not is_yaml_path(str(name)):
        return None
    try:
        data = Path(name).read_bytes()
    except OSError:
        return None
    digest = hashlib.sha256(data)
    named = _python_objects(data)
    if not named:
        return digest.hexdigest()
    from .calibration_cache import _class_code, model_fingerprint

    for path in named:
        try:
            obj = import_object(path, "")
        except Exception:  # noqa: BLE001 (one that cannot be imported: its name alone)
            digest.update(f"{path}: not importable".encode())
            continue
        code = _class_code(obj).hex() if isinstance(obj, type) else model_fingerprint(obj)
        digest.update(f"{path}: {code}".encode())
    return digest.hexdigest()


def scenario_file_matches(recorded: str | None, name) -> bool:
    """Whether a digest recorded for scenario file ``name`` (a checkpoint's, a sweep's)
    is its digest now: :func:`scenario_file_digest`, or the digest of its bytes alone where
    the record was made before the digest covered the Python code the file names (such a
    record cannot tell an edit of that code; read as unchanged, as it was then: a review
    found every run recorded before the change refused as "changed")."""
    import hashlib

    if recorded is None:
        return True
    if recorded == scenario_file_digest(name):
        return True
    try:
        return recorded == hashlib.sha256(Path(name).read_bytes()).hexdigest()
    except OSError:
        return False


def _python_objects(data: bytes) -> list[str]:
    """The ``module:object`` paths a YAML scenario file's text names (sorted, each once):
    every string value of that form; none for a file that is not readable YAML."""
    import re

    try:
        doc = load_yaml_text(data.decode("utf-8"))
    except Exception:  # noqa: BLE001 (read, and refused, where the scenario is built)
        return []
    found, stack = set(), [doc]
    while stack:
        item = stack.pop()
        if isinstance(item, dict):
            for key, value in item.items():
                if (key in _CODE_FIELDS and isinstance(value, str)
                        and re.fullmatch(r"[A-Za-z_][\w.]*:[A-Za-z_][\w.]*", value)):  # fmt: skip
                    found.add(value)
                else:
                    stack.append(value)
        elif isinstance(item, list):
            stack.extend(item)
    return sorted(found)


#: The fields of a scenario file that name Python objects (``module:object``): a plant's
#: functions or model, its inputs' function, an attack of one's own (its ``kind``). Other
#: text (a description with a colon) is not imported to digest it (a review).
_CODE_FIELDS = frozenset({"transition", "observe", "model", "function", "kind",
                          "transition_jacobian", "observation_jacobian"})  # fmt: skip


def scenario_from_yaml(path: str | Path) -> CustomScenario:
    """The :class:`~difffilter.models.scenario.CustomScenario` a YAML file describes
    (module docstring); ``ValueError`` naming the file and the field otherwise."""
    path = Path(path)
    doc = read_yaml(path, f"scenario file {str(path)!r}")
    return scenario_from_dict(doc, where=str(path))


def number_loader():
    """The PyYAML loader of the scenario files, threat sets and ``--option`` values:
    SafeLoader, but ``1e-5`` (an exponent without a decimal point) is a number, as YAML 1.2
    and the training configs' loader read it (PyYAML's YAML 1.1 took it for text: a noise
    ``Q: 1e-4`` was refused, and ``-o watermark_std=1e-2`` and a threat's ``value: 5e-1``
    were "not a number", with a hint in the first place alone: a CLI trial). Not the
    training's :func:`difffilter.train.common.jsonargparse_yaml_loader`: the models sit
    below the training in the imports, and that loader is jsonargparse's private one, with
    SafeLoader (text again) where its name has moved."""
    global _NUMBER_LOADER
    if _NUMBER_LOADER is None:
        import re

        import yaml

        class NumberLoader(yaml.SafeLoader):
            pass

        NumberLoader.add_implicit_resolver(
            "tag:yaml.org,2002:float",
            re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
            list("-+.0123456789"),
        )
        _NUMBER_LOADER = NumberLoader
    return _NUMBER_LOADER


_NUMBER_LOADER = None


def load_yaml_text(text: str) -> Any:
    """``text`` read by :func:`number_loader` (``yaml.YAMLError`` where it is not YAML)."""
    import yaml

    return yaml.load(text, Loader=number_loader())  # noqa: S506 (a SafeLoader)


def read_yaml(path: Path, named: str) -> Any:
    """The YAML document in ``path`` (``None`` for an empty file), or a ``ValueError`` that
    begins with ``named``: the file does not exist, or is not valid YAML (the parser's
    message says where)."""
    import yaml

    if not Path(path).is_file():
        raise ValueError(f"{named} does not exist")
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as error:  # (it had named neither the file nor the encoding)
        raise ValueError(f"{named} is not UTF-8 text ({error}): save it as UTF-8") from None
    try:
        check_unique_keys(text, named, number_loader())
        return load_yaml_text(text)
    except yaml.YAMLError as error:
        raise ValueError(f"{named} is not valid YAML: {error}") from None


def check_unique_keys(text: str, named: str, loader=None) -> None:
    """``ValueError`` beginning with ``named`` where a mapping of the YAML ``text`` holds a
    key twice: PyYAML keeps the last one without a word (a trial's threat set with two
    threats named ``r`` lost its ramp, and a training config's did the same). Keys compare
    as the dict PyYAML builds compares them (``1``, ``0x1`` and ``1.0`` are one key, ``1``
    and ``'1'`` two); merge keys (``<<``) are left to YAML, which merges each. ``loader``:
    the PyYAML loader class to compose with (SafeLoader). Invalid YAML raises the parser's
    ``yaml.YAMLError``."""
    import yaml

    construct = yaml.constructor.SafeConstructor().construct_object
    pending, visited = [yaml.compose(text, Loader=loader or yaml.SafeLoader)], set()
    while pending:
        node = pending.pop()
        if id(node) in visited:  # an alias: the node it names, read once
            continue
        visited.add(id(node))
        if isinstance(node, yaml.MappingNode):
            seen: dict = {}
            for key, value in node.value:
                pending += [key, value]
                if not isinstance(key, yaml.ScalarNode) or key.tag == "tag:yaml.org,2002:merge":
                    continue
                try:
                    as_built = construct(key)
                    hash(as_built)
                except (yaml.YAMLError, TypeError, ValueError):
                    as_built = (key.tag, key.value)
                if as_built in seen:
                    line, first = seen[as_built]
                    what = (f"the key {key.value!r} appears twice" if first == key.value
                            else f"the keys {first!r} and {key.value!r} are one key")  # fmt: skip
                    raise ValueError(
                        f"{named}: {what} in one mapping (lines {line} and "
                        f"{key.start_mark.line + 1}); YAML would keep the last alone: rename one"
                    )
                seen[as_built] = (key.start_mark.line + 1, key.value)
        elif isinstance(node, yaml.SequenceNode):
            pending += node.value


def scenario_from_dict(doc: Mapping[str, Any], where: str = "scenario") -> CustomScenario:
    """The scenario of a mapping with the fields of a YAML scenario (module docstring)."""
    if not isinstance(doc, Mapping):
        raise ValueError(f"{where}: a scenario is a mapping of fields; got {type(doc).__name__}")
    _check_fields(doc, _TOP, where)
    for key in ("name", "plant"):
        if key not in doc:
            raise ValueError(f"{where}: the field {key!r} is required")
    for key in ("name", "family"):  # (a blank name: None, read as the scenario 'None')
        if key in doc and not isinstance(doc[key], str):
            raise ValueError(f"{where}: {key} must be a name (text); got {doc[key]!r}")
    options = doc.get("options") or {}
    if not isinstance(options, Mapping):
        raise ValueError(f"{where}: options must be a mapping of option: value (e.g. "
                         f"{{cusum_bias: 2.0}}); got {options!r}")  # fmt: skip
    from .estimators import check_options  # (its values too, now, not mid-study)

    check_options(options, f"{where}: options")
    plant = _plant(doc["plant"], f"{where}: plant")
    try:  # built once now: its shapes and functions checked (_probe) before any run
        probe = plant(torch.float64)
    except (ValueError, TypeError, KeyError, IndexError, RuntimeError) as error:
        message = str(error)  # (a message that names the file and the field already: as is)
        raise ValueError(
            message if message.startswith(where) else f"{where}: plant: {message}"
        ) from error.__cause__  # (a user's function's own error, where it was kept: its traceback)
    units = doc.get("units") or {}
    if not isinstance(units, Mapping) or set(units) - {"state", "attack"}:
        raise ValueError(f"{where}: units must be {{state: ..., attack: ...}}; got {units!r}")
    settings = {k: doc[k] for k in ("runs", "steps", "num_particles") if k in doc}
    for key in ("runs", "steps", "num_particles"):
        value = settings.get(key)
        if value is not None and (
            isinstance(value, bool) or not isinstance(value, int) or value < 1
        ):
            raise ValueError(f"{where}: {key} must be an integer >= 1; got {value!r}")
    for key in ("dt", "false_alarm_rate", "gamma_min"):
        if doc.get(key) is not None:
            settings[key] = _number(doc[key], f"{where}: {key}")
    if not settings.get("dt", 1.0) > 0:
        raise ValueError(f"{where}: dt must be a sampling period > 0 (s); got {doc['dt']!r}")
    # checked here, by the file, not when a detector is first built from them
    if not 0 < settings.get("false_alarm_rate", 0.01) < 1:
        raise ValueError(
            f"{where}: false_alarm_rate must be a rate in (0, 1); got {doc['false_alarm_rate']!r}"
        )
    if not settings.get("gamma_min", 1.0) > 0:
        raise ValueError(f"{where}: gamma_min must be a number > 0; got {doc['gamma_min']!r}")
    drawn = doc.get("random_initial", False)
    if not isinstance(drawn, bool):
        raise ValueError(f"{where}: random_initial must be true or false; got {drawn!r}")
    steps = settings.get("steps", CustomScenario.steps)
    attack = _attack(doc.get("attack"), probe, steps, f"{where}: attack", settings.get("dt"))
    known = _inputs(doc.get("inputs"), settings.get("dt", 1.0), f"{where}: inputs")
    loss = _input_loss(doc.get("input_loss"), f"{where}: input_loss")
    _check_inputs_to_lose(loss, known, attack, probe, where)  # (in the file's words)
    try:
        scenario = CustomScenario(
            name=str(doc["name"]),
            family=str(doc.get("family", "custom")),
            description=str(doc.get("description", f"a scenario from {where}")),
            paper=str(doc.get("paper", "")),
            notes=_names(doc.get("notes"), f"{where}: notes"),
            model_fn=plant,
            attack=attack,
            protocol=_schedule(doc.get("schedule"), f"{where}: schedule"),
            known_inputs=known,
            input_loss=loss,
            estimators=_estimators(doc.get("estimators"), f"{where}: estimators"),
            options=dict(options),
            state_unit=str(units.get("state", "state units")),
            attack_unit=str(units.get("attack", "attack units")),
            random_initial=drawn,
            **settings,
        )
    except (ValueError, TypeError) as error:
        message = str(error)
        raise ValueError(message if message.startswith(where) else f"{where}: {message}") from None
    _check_against_plant(scenario, probe, where)
    return scenario


def _check_inputs_to_lose(loss, known, attack, probe, where: str) -> None:
    """An ``input_loss`` needs inputs to lose: the plant's, and given ones (``inputs:``) or
    an actuator attack riding in them (a trial's report announced a loss that changed
    nothing); said in the file's words before :class:`CustomScenario` says it in Python's."""
    if loss is None:
        return
    if probe.dim_u == 0:
        raise ValueError(f"{where}: input_loss: the plant has no input to lose (dim_u = 0)")
    actuated = attack is not None and Channel(attack.channel) is Channel.ACTUATOR
    if known is None and not actuated:
        raise ValueError(
            f"{where}: input_loss: the plant has no inputs: (it runs on zero inputs, which "
            "a lost packet leaves as they are, and no actuator attack rides in them): give "
            "it inputs: (for a threat study of actuator attacks, {kind: constant, value: "
            "0.0}), or drop input_loss"
        )


def _inputs_field(model) -> str:
    """Where a plant's number of inputs is set: a linear plant's ``B`` or ``plant.dim_u``."""
    linear = isinstance(getattr(model, "F", None), torch.Tensor)
    return "dim_u: plant.B's columns" if linear else "plant.dim_u"


def _check_against_plant(scenario: CustomScenario, probe, where: str) -> None:
    """The schedule's groups and the known inputs against the plant's widths, now: they
    failed at the first run, with messages that named neither the file nor the field."""
    try:
        scenario.schedule().mask((1,), 1, probe.dim_y, torch.Generator().manual_seed(0))
    except (ValueError, TypeError, IndexError) as error:
        raise ValueError(f"{where}: schedule: {error}") from None
    if scenario.input_loss is not None:
        try:
            scenario.input_loss.draw(1, 1, probe.dim_u, torch.Generator().manual_seed(0))
        except (ValueError, TypeError, IndexError) as error:
            raise ValueError(f"{where}: {error}") from None  # (draw names input_loss, du)
    known = scenario.known_inputs
    runs = known.shape[0] if isinstance(known, torch.Tensor) and known.dim() == 3 else 1
    width = _input_width(known)
    if width is not None and width != probe.dim_u:  # (it said known_inputs [1, 100, 2])
        raise ValueError(
            f"{where}: inputs: they give {width} value(s) per step and the plant has "
            f"{probe.dim_u} input(s) ({_inputs_field(probe)}): give one per input "
            "(amplitude, frequency, phase or value: a list of dim_u numbers, or a number on a "
            "one-input plant; values: [T, dim_u])"
        )
    try:
        scenario.inputs(runs, torch.float64)
    except (ValueError, TypeError, IndexError, RuntimeError) as error:
        raise ValueError(f"{where}: inputs: {error}") from None


def _input_width(known) -> int | None:
    """The values per step of YAML ``inputs:`` (a table ``[.., T, du]`` or a sinusoid's or
    constant's function of the step, this module's), or ``None`` for a function of the
    user's (called once for a step, one that squeezed its output read as one input: the
    scenario's own check, at the study's length, names such a function's misfit)."""
    if isinstance(known, torch.Tensor):
        return int(known.shape[-1])
    if not callable(known) or getattr(known, "__module__", None) != __name__:
        return None
    try:
        value = known(torch.arange(1, dtype=torch.float64))
    except Exception:  # (the scenario's own check below names it)
        return None
    if not isinstance(value, torch.Tensor):
        return None
    return 1 if value.dim() < 2 else int(value.shape[-1])


def _number(value: Any, where: str) -> float:
    """A finite number of the YAML file (``ValueError`` starting with ``where`` otherwise)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(
            f"{where} must be a finite number; got {value!r}{_string_number_hint(value)}"
        )
    return float(value)


def _string_number_hint(value: Any) -> str:
    """Why a number may have been read as a string: it was quoted (``Q: '1e-5'``), or it is
    a number to Python that YAML reads as text (``inf``, ``nan``: YAML's are ``.inf``,
    ``.nan``)."""
    text = value if isinstance(value, str) else None
    if isinstance(value, list):  # the first string of a (nested) list
        stack = list(value)
        while stack and text is None:
            item = stack.pop(0)
            text = item if isinstance(item, str) else None
            stack = (item if isinstance(item, list) else []) + stack
    try:
        float(text)
    except (TypeError, ValueError):
        return ""
    if isinstance(load_yaml_text(text), str):  # text to YAML even unquoted
        return f" (YAML reads {text!r} as text: write a number such as 1.5, 1e-5, .inf or .nan)"
    return f" ({text!r} is text here, in quotes: write the number without them)"


def _names(value: Any, where: str) -> tuple:
    """A list of strings of the YAML file as a tuple; one string is a list of one (never its
    characters)."""
    if value is None:
        return ()
    if isinstance(value, str):
        return (value,)
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
        raise ValueError(f"{where} must be a list of strings; got {value!r}")
    return tuple(value)


def _estimators(value: Any, where: str) -> tuple:
    """The scenario's estimator names (:func:`_names`); an empty list is refused: it ran
    the default suite, where ``--estimators ""`` is refused for that reason."""
    names = _names(value, where)
    if value is not None and not names:
        raise ValueError(f"{where}: an empty list names no estimator; leave estimators out "
                         "for the defaults")  # fmt: skip
    return names


def _check_fields(mapping: Mapping, valid: set[str], where: str) -> None:
    """``ValueError`` naming the fields of ``mapping`` outside ``valid`` (and the valid ones)."""
    unknown = sorted(set(mapping) - valid)
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {', '.join(unknown)}; valid: "
                         f"{', '.join(sorted(valid))}")  # fmt: skip


def _import(path: Any, where: str):
    """The function of a ``package.module:function`` path."""
    if not isinstance(path, str) or ":" not in path:
        raise ValueError(f"{where} must be a 'package.module:object' path; got {path!r}")
    obj = import_object(path, where)
    if not callable(obj):
        raise ValueError(f"{where}: {path} is not a function")
    return obj


def _refuse_booleans(value: Any, where: str) -> None:
    """No entry of ``value`` (a number or nested lists) is a boolean: YAML reads ``yes``,
    ``no``, ``on``, ``off``, ``true`` and ``false`` as ones, and ``torch.tensor`` had taken
    them for 1 and 0 (``Q: yes`` an identity; a YAML trial), where a scalar field refuses
    them by name."""
    if isinstance(value, bool):
        raise ValueError(
            f"{where}: {value!r} is a boolean (YAML reads yes/no/on/off/true/false so), not a "
            "number: write the number"
        )
    if isinstance(value, list):
        for entry in value:
            _refuse_booleans(entry, where)


def _matrix(value: Any, n: int | None, where: str, dtype) -> torch.Tensor:
    """A covariance or matrix from YAML: a number (× I of size ``n``), a list (its diagonal,
    when ``n`` is given) or a nested list (the matrix)."""
    _refuse_booleans(value, where)
    try:
        t = torch.tensor(value, dtype=dtype)
    except (TypeError, ValueError, RuntimeError):
        rows = (
            [len(r) for r in value]
            if isinstance(value, list) and value and all(isinstance(r, list) for r in value)
            else None
        )
        if rows is not None and len(set(rows)) > 1:  # (it said only "(nested) lists of numbers")
            raise ValueError(f"{where}: its rows have {rows} entries: every row of a matrix "
                             f"needs the same number; got {value!r}") from None  # fmt: skip
        raise ValueError(
            f"{where} must be a number or (nested) lists of numbers; got {value!r}"
            f"{_string_number_hint(value)}"
        ) from None
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{where} must be finite; got {value!r}")
    if n is not None and t.dim() == 0:
        return t * torch.eye(n, dtype=dtype)
    if n is not None and t.dim() == 1:
        return torch.diag(t)
    if t.dim() != 2:
        raise ValueError(f"{where} must be a matrix (a list of rows); got shape {list(t.shape)}")
    return t


def _plant(spec: Any, where: str):
    """``dtype → StateSpaceModel`` of the plant mapping."""
    if not isinstance(spec, Mapping):
        raise ValueError(f"{where} must be a mapping (module docstring); got {spec!r}")
    _check_fields(spec, _PLANT, where)
    if "model" in spec:
        ignored = sorted(set(spec) - {"model"})
        if ignored:  # the function makes the whole model: these would not be read
            raise ValueError(f"{where}: model gives the whole plant; remove {', '.join(ignored)} "
                             "(set them in the model's function)")  # fmt: skip
        return _ModelFunction(_import(spec["model"], f"{where}.model"), spec["model"], where)
    for given, ignored in (("transition", ("F", "B")), ("observe", ("H",))):
        clash = [k for k in ignored if given in spec and k in spec]
        if clash:
            raise ValueError(f"{where}: {given} replaces {' and '.join(clash)}; give one or the "
                             "other")  # fmt: skip
    if "angles" in spec and ("transition" not in spec or "model" in spec):
        raise ValueError(
            f"{where}.angles wraps the residuals of a nonlinear plant's measurements (with "
            "transition:); a linear plant's Kalman filter subtracts plainly, and a model: "
            "of one's own overrides measurement_residual itself"
        )
    if "dim_u" in spec and "transition" not in spec:
        raise ValueError(f"{where}.dim_u is for a transition function (a linear plant's inputs "
                         "are B's columns)")  # fmt: skip
    transition = (
        _import(spec["transition"], f"{where}.transition") if "transition" in spec else None
    )
    observe = _import(spec["observe"], f"{where}.observe") if "observe" in spec else None
    if transition is None and "F" not in spec:
        raise ValueError(f"{where} needs F (a linear plant), transition (a function path) or "
                         "model (a function dtype -> StateSpaceModel)")  # fmt: skip
    if observe is None and "H" not in spec:
        raise ValueError(f"{where} needs H (a linear observation) or observe (a function path)")
    for key in ("Q", "R"):
        if key not in spec:
            raise ValueError(f"{where}.{key} is required (a number × I, a diagonal or a matrix)")

    def build(dtype):
        H = None if observe is not None else _matrix(spec["H"], None, f"{where}.H", dtype)
        F = None if transition is not None else _matrix(spec["F"], None, f"{where}.F", dtype)
        m0 = _vector(spec["m0"], f"{where}.m0", dtype) if spec.get("m0") is not None else None
        dx = F.shape[0] if F is not None else (0 if m0 is None else m0.shape[0])
        if dx == 0:
            raise ValueError(f"{where}.m0 is required with a transition function (it sets dx)")
        m0 = torch.zeros(dx, dtype=dtype) if m0 is None else m0
        if F is not None and F.shape != (dx, dx):
            raise ValueError(f"{where}.F must be square (dx × dx); got {list(F.shape)}")
        if m0.shape[0] != dx:
            raise ValueError(f"{where}.m0 has {m0.shape[0]} entries; the state has {dx} (F is "
                             f"{dx} × {dx})")  # fmt: skip
        if H is not None and H.shape[1] != dx:
            raise ValueError(f"{where}.H must have dx = {dx} columns; got {list(H.shape)}")
        # the state's size comes from F, else m0: say which (a user trial gave m0 three
        # entries and read "Q must be 3 × 3")
        states = (f"the state has {dx} entries, as F is {dx} × {dx}" if F is not None
                  else f"the state has {dx} entries, as m0 has")  # fmt: skip
        Q = _shaped(_matrix(spec["Q"], dx, f"{where}.Q", dtype), dx, f"{where}.Q", states)
        P0 = _shaped(_matrix(spec.get("P0", 1.0), dx, f"{where}.P0", dtype), dx, f"{where}.P0",
                     states)  # fmt: skip
        if H is not None:
            dy = H.shape[0]
        else:  # h(x) or h(x, k)
            args = (m0,) if _arity(observe) <= 1 else (m0, 1)
            out = _call(observe, args, f"{where}.observe")
            if not isinstance(out, torch.Tensor) or out.dim() != 1:
                raise ValueError(f"{where}.observe must map m0 [{dx}] to a vector [dy]; got "
                                 f"{getattr(out, 'shape', type(out).__name__)}")  # fmt: skip
            dy = out.shape[-1]
        outputs = (f"there are {dy} outputs, as H has {dy} rows" if H is not None
                   else f"there are {dy} outputs, as observe returns at m0")  # fmt: skip
        R = _shaped(_matrix(spec["R"], dy, f"{where}.R", dtype), dy, f"{where}.R", outputs)
        if transition is None and observe is None:
            B = _matrix(spec["B"], None, f"{where}.B", dtype) if "B" in spec else None
            if B is not None and B.shape[0] != dx:
                raise ValueError(f"{where}.B must have dx = {dx} rows; got {list(B.shape)}")
            return LinearGaussianModel(F, H, Q, R, m0, P0, B=B)
        if transition is None:
            raise ValueError(f"{where}: a nonlinear observation needs a transition function too")
        h = observe if observe is not None else (lambda x: x @ H.transpose(-1, -2))
        dim_u = spec.get("dim_u", 0)
        if isinstance(dim_u, bool) or not isinstance(dim_u, int) or dim_u < 0:
            raise ValueError(f"{where}.dim_u must be an integer >= 0; got {dim_u!r}")
        angles = _angles(spec.get("angles"), dy, f"{where}.angles")
        kind = NonlinearGaussianModel if not angles else _AngleMeasured
        extra = {} if not angles else {"angles": angles}
        model = kind(transition, h, Q, R, m0, P0, dim_u=dim_u, **extra)
        if dim_u and model._f_arity < 2:
            raise ValueError(f"{where}: dim_u = {dim_u} but transition takes x alone: f(x, u) "
                             "(or f(x, u, k)) reads the input")  # fmt: skip
        _probe(model, where)
        return model

    return build


class _ModelFunction:
    """A YAML ``plant: {model: path}``: ``dtype → StateSpaceModel`` by the user's function,
    its failures and a result that is no model named with the file and the field (a trial:
    "'torch.dtype' object is not subscriptable" alone). A class, not a closure: it pickles
    as the function it wraps does."""

    def __init__(self, function, path: str, where: str):
        self.function, self.path, self.where = function, path, where

    def __call__(self, dtype):
        try:
            model = self.function(dtype)
        except Exception as error:  # a user's function may raise anything
            raise ValueError(
                f"{self.where}.model: {self.path}(dtype) raised {type(error).__name__}: {error} "
                "(model: names a function dtype → StateSpaceModel)"
            ) from error
        if not isinstance(model, StateSpaceModel):
            raise ValueError(
                f"{self.where}.model: {self.path}(dtype) returned a {type(model).__name__}; it "
                "must return a StateSpaceModel (e.g. difffilter.NonlinearGaussianModel)"
            )
        from difffilter._checks import model_dtype_device

        built, _ = model_dtype_device(model)
        if built is not None and built != dtype:  # (blamed on inputs:, or a later error)
            raise ValueError(
                f"{self.where}.model: {self.path}({dtype}) returned a model of {built}: build "
                "its tensors in the dtype it is given (the suite and the training ask for "
                "float64 and float32)"
            )
        return model


def _angles(value: Any, dy: int, where: str) -> tuple[int, ...]:
    """The measurement entries of YAML ``angles:`` (distinct, in ``[0, dy)``), or ``()``."""
    if value is None:
        return ()
    ok = (
        isinstance(value, list)
        and value
        and all(isinstance(i, int) and not isinstance(i, bool) and 0 <= i < dy for i in value)
    )
    if not ok or len(set(value)) != len(value):
        raise ValueError(f"{where} must be a list of distinct measurement entries in [0, {dy}) "
                         f"(there are {dy} outputs); got {value!r}")  # fmt: skip
    return tuple(value)


class _AngleMeasured(NonlinearGaussianModel):
    """A nonlinear plant whose measurement entries ``angles`` are angles: the residual
    ``y − ŷ`` wrapped to ``(−π, π]`` there (YAML ``angles:``), which the EKF, UKF, the Kalman
    proposal and the particle filters' likelihood all read (a trial's bearings near ±π: a
    χ² threshold of 22,958 and no detection with plain residuals)."""

    def __init__(self, *args, angles: tuple[int, ...], **kwargs):
        super().__init__(*args, **kwargs)
        self.angles = angles

    def measurement_residual(self, y, y_hat):
        d = y - y_hat
        index = torch.tensor(self.angles, device=d.device)
        # π − ((π − d) mod 2π) ∈ (−π, π]: +π stays +π, as the tracking model's wrap_angle
        wrapped = math.pi - torch.remainder(math.pi - d.index_select(-1, index), 2 * math.pi)
        return d.index_copy(-1, index, wrapped)


def _vector(value: Any, where: str, dtype) -> torch.Tensor:
    """A finite vector of the YAML file."""
    _refuse_booleans(value, where)
    try:
        t = torch.tensor(value, dtype=dtype)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"{where} must be a list of numbers; got {value!r}") from None
    if t.dim() != 1 or not bool(torch.isfinite(t).all()):
        raise ValueError(f"{where} must be a list of finite numbers; got {value!r}")
    return t


def _shaped(matrix: torch.Tensor, n: int, where: str, because: str) -> torch.Tensor:
    if matrix.shape != (n, n):
        raise ValueError(f"{where} must be {n} × {n} ({because}; a number × I, a diagonal of "
                         f"{n} or the matrix); got {list(matrix.shape)}")  # fmt: skip
    return matrix


def _call(fn, args: tuple, where: str):
    """``fn(*args)``, its error named (a user's function failing on the prior mean)."""
    try:
        return fn(*args)
    except Exception as error:  # a user's function may raise anything
        raise ValueError(f"{where} failed on m0: {type(error).__name__}: {error}") from None


def _probe(model, where: str) -> None:
    """``f(m0, 0_u, 0)`` of width ``dx`` and ``h(m0)`` of ``dy``: the plant's functions run
    on its prior mean, their errors and widths named now, not deep inside a run."""
    m0 = model.initial.mean
    u = torch.zeros(model.dim_u, dtype=m0.dtype) if model.dim_u else None
    # (f(x, u) reading an input the plant does not have, dim_u 0, is named by the model
    # itself: NonlinearGaussianModel's probe, "give dim_u=", under this file's plant:)
    moved = _call(model.transition, (m0, u, 0), f"{where}.transition")
    for name, out, width in (("transition", moved, model.dim_x),
                             ("observe", _call(model.observe, (m0, 1), f"{where}.observe"),
                              model.dim_y)):  # fmt: skip
        if not isinstance(out, torch.Tensor) or out.shape[-1:] != (width,) or out.dim() != 1:
            shape = list(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
            raise ValueError(
                f"{where}.{name} must map m0 [{model.dim_x}] to [{width}]; got {shape}"
            )


def _attack(spec: Any, model, steps: int, where: str, dt: float | None = None):
    attack = _attack_object(spec, model, where, dt)
    if attack is None:
        return None
    try:  # its first step, its width against the channel's, a model with inputs: now
        check_attack_fits(attack, model, steps)
    except (ValueError, TypeError) as error:
        raise ValueError(f"{where}: {error}") from None
    return attack


def _attack_object(spec: Any, model, where: str, dt: float | None = None):
    """The attack of a ``spec`` (``dt``: the file's sampling period, a sinusoid's or a
    chirp's unless it sets its own: :func:`~difffilter.threats.with_sampling_period`)."""
    if spec is None:
        return None
    if not isinstance(spec, Mapping) or "kind" not in spec:
        raise ValueError(f"{where} must be a mapping with a 'kind'; got {spec!r}")
    kind = spec["kind"]
    if kind in PAPER_ATTACKS:
        params = {k: v for k, v in spec.items() if k != "kind"}
        try:
            return PAPER_ATTACKS[kind](**params)
        except (TypeError, ValueError) as error:
            raise ValueError(f"{where} ({kind}): {error}") from None
    # an attack of one's own, package.module:object, as a threat set writes it (a user trial's
    # YAML scenario could not name the attack its threat set named)
    own = isinstance(kind, str) and ":" in kind
    if kind not in THREATS and not own:
        valid = ", ".join(sorted((*THREATS, *PAPER_ATTACKS)))
        raise ValueError(
            f"{where}: unknown kind {kind!r}; valid: {valid}, or an attack of your own as "
            "package.module:object"
        )
    try:
        return threat_from_dict(with_sampling_period(dict(spec), dt), model)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{where}: {error}") from None


#: The fields of each schedule kind: (required, optional).
_SCHEDULE_FIELDS = {
    "round_robin": ({"groups"}, {"start"}),
    "packet_loss": ({"rate"}, {"packets"}),
    "burst_loss": ({"to_bad", "to_good"}, {"loss_good", "loss_bad", "packets"}),
}


def _schedule(spec: Any, where: str):
    if spec is None or spec == "all":
        return AllSensors()
    kind = spec.get("kind") if isinstance(spec, Mapping) else None
    if kind in _SCHEDULE_FIELDS:
        required, optional = _SCHEDULE_FIELDS[kind]
        _check_fields(spec, {"kind"} | required | optional, where)
        missing = sorted(required - set(spec))
        if missing:
            raise ValueError(f"{where}: {kind} needs {', '.join(missing)}")
        try:
            if kind == "round_robin":
                return RoundRobin(spec["groups"], spec.get("start", 0))
            if kind == "burst_loss":
                numbers = {name: _number(spec[name], f"{where}.{name}")
                           for name in ("to_bad", "to_good", "loss_good", "loss_bad") if name in spec}  # fmt: skip
                return BurstLoss(**numbers, packets=spec.get("packets"))
            return PacketLoss(_number(spec["rate"], f"{where}.rate"), spec.get("packets"))
        except (TypeError, ValueError) as error:
            message = str(error)
            raise ValueError(
                message if message.startswith(where) else f"{where}: {message}"
            ) from None
    raise ValueError(f"{where} must be 'all', {{kind: round_robin, groups: [[...], ...]}}, "
                     f"{{kind: packet_loss, rate: r}} or {{kind: burst_loss, to_bad: p, to_good: "
                     f"q}}; got {spec!r}")  # fmt: skip


def _input_loss(spec: Any, where: str):
    """``{kind: packet_loss | burst_loss | round_robin, …, on_loss: hold | zero,
    acknowledged: true | false}`` → an :class:`~difffilter.input_loss.InputLossSchedule`
    (the schedule's fields as ``schedule:``'s, over the plant's inputs), or ``None``."""
    if spec is None:
        return None
    if not isinstance(spec, Mapping) or spec.get("kind") not in _SCHEDULE_FIELDS:
        raise ValueError(
            f"{where} must be {{kind: packet_loss, rate: r}}, {{kind: burst_loss, to_bad: p, "
            f"to_good: q}} or {{kind: round_robin, groups: [[...], ...]}}, with on_loss "
            f"(hold or zero) and acknowledged (true or false) optional; got {spec!r}"
        )
    required, optional = _SCHEDULE_FIELDS[spec["kind"]]
    _check_fields(spec, {"kind", "on_loss", "acknowledged"} | required | optional, where)
    channel = {k: v for k, v in spec.items() if k not in ("on_loss", "acknowledged")}
    schedule = _schedule(channel, where)
    try:
        return InputLossSchedule(schedule, spec.get("on_loss", "hold"),
                                 spec.get("acknowledged", True))  # fmt: skip
    except (TypeError, ValueError) as error:
        raise ValueError(f"{where}: {error}") from None


def _inputs(spec: Any, dt: float, where: str):
    if spec is None:
        return None
    if not isinstance(spec, Mapping):
        raise ValueError(f"{where} must be a mapping (module docstring); got {spec!r}")
    forms = {"function": ({"function"}, set()), "values": ({"values"}, set()),
             "sinusoid": ({"kind", "amplitude", "frequency"}, {"phase"}),
             "constant": ({"kind", "value"}, set())}  # fmt: skip
    form = next((f for f in ("function", "values") if f in spec), spec.get("kind"))
    if form in forms:
        required, optional = forms[form]
        _check_fields(spec, required | optional, where)
        missing = sorted(required - set(spec))
        if missing:
            raise ValueError(f"{where}: {form} needs {', '.join(missing)}")
    if form == "function":
        return _import(spec["function"], f"{where}.function")
    if form == "values":  # [T, du] or [runs, T, du]
        _refuse_booleans(spec["values"], f"{where}.values")
        try:
            values = torch.tensor(spec["values"], dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError):
            values = None
        if values is None or values.dim() not in (2, 3) or not bool(torch.isfinite(values).all()):
            raise ValueError(f"{where}.values must be finite numbers [T, du] or [runs, T, du]; "
                             f"got {spec['values']!r}")  # fmt: skip
        return values
    if form == "sinusoid":
        parts = {k: spec.get(k, 0.0) for k in ("amplitude", "frequency", "phase")}
        if not any(isinstance(v, list) for v in parts.values()):  # one input: k [T] → [T]
            amplitude, frequency, phase = (_number(v, f"{where}.{k}") for k, v in parts.items())
            return lambda k: amplitude * torch.sin(2 * math.pi * frequency * dt * k + phase)
        # one sinusoid per input: a list of du numbers (a number: the same for every input)
        amplitude, frequency, phase = (
            _vector(v if isinstance(v, list) else [v], f"{where}.{k}", torch.float64)
            for k, v in parts.items()
        )
        try:
            width = torch.broadcast_shapes(amplitude.shape, frequency.shape, phase.shape)
        except RuntimeError:
            raise ValueError(f"{where}: amplitude, frequency and phase must hold one number, or "
                             f"one per input (the same count); got {dict(parts)!r}") from None  # fmt: skip
        return lambda k: (amplitude.to(k.dtype) * torch.sin(
            2 * math.pi * frequency.to(k.dtype) * dt * k.unsqueeze(-1) + phase.to(k.dtype)
        )).expand(k.shape[0], width[0])  # fmt: skip
    if form == "constant":
        value = _vector([spec["value"]] if isinstance(spec["value"], (int, float)) else spec["value"],
                        f"{where}.value", torch.float64)  # fmt: skip
        return lambda k: value.to(k.dtype).expand(k.shape[0], value.shape[0])
    raise ValueError(f"{where} must be {{kind: sinusoid, amplitude, frequency}}, {{kind: "
                     f"constant, value}}, {{values: [...]}} or {{function: module:fn}}; got {spec!r}")  # fmt: skip
