"""``difffilter-train sweep``: one config trained on several seeds, each checkpoint judged as
the evaluation judges it, the spread reported and the median seed named.

For every seed ``s`` the sweep runs ``fit`` with ``--seed_everything s``, the network's
``model_seed s`` and the data's ``train_seed 1 + 10 s`` (the validation and test seeds
stay the config's), logging into ``<out>/runs/<name>/seed_<s>/``. A seed whose exported
estimator is already there is not trained again, and one interrupted after a Lightning
checkpoint resumes from its ``last.ckpt`` (written at every epoch): an interrupted sweep
loses at most the epoch it was in. Each seed's folder records what it was trained with
(``sweep_settings.json``: the config's values, the options after ``--`` and the values of a
config among them, ``-- --config threats.yaml``), and a sweep
with other settings into the same ``--out`` is refused before anything is trained.

Each seed's estimator is then evaluated on the headline scenarios of its family (or
``--scenarios``) with ``difffilter-eval``'s draws (``--seed 0``) and its calibration (every
threshold chosen on attack-free runs of their own seed for ``--far``), and the sweep
writes ``<out>/sweep.json`` and ``<out>/sweep.md``: per seed and scenario the estimator's
``tpr_at_far``, ``fpr_at_far`` (and ``fpr_at_far_after_attack``, its rate on the ten
attack-free steps after an attacked step), ``fpr`` (at the checkpoint's own threshold), ``auc``,
``state_rmse`` and ``attack_rmse`` (and the family's own, e.g. tracking's position RMSE
``rmse_p``), the ``threshold_at_far`` each was judged at with its rate on the calibration
runs (``far_measured_on_calibration``), and per metric the mean, min, max and spread
(max − min) over seeds (all four null where a seed's value is NaN, that seed named in
``not_a_number``).

The median seed is the one to ship (``difffilter-train export``), never the best, and it is
chosen on validation, not on the numbers the sweep reports: by default
(``--select-on validation``) each seed is ranked by the score its training chose its
weights by (the card's ``best_val_score``, the config's ``ModelCheckpoint`` monitor, e.g.
``val/auc``, on the config's validation runs, ``val_seed``), in the monitor's direction,
and the median of that ranking ships (for an even count the worse of the two middle seeds:
never the best). ``--select-on test`` ranks by the evaluation's ``--rank-by`` metric averaged over
the scenarios instead (what earlier sweeps did: a choice made on the test's own draws);
the sweep names that seed too, so a reader sees whether the two choices differ.

The sweep also judges every seed as the headline acceptance does
(:mod:`difffilter.eval.acceptance`): the scenario's analytic estimators run once on the
same draws, calibrated the same way (kept in ``<out>/baselines/<scenario>.json`` for the
next sweep with the same runs, rate and evaluation seed, and for a YAML scenario file the
same bytes, with their per-run totals in ``<scenario>.totals.pt``; a file's path is kept as
its stem and a digest of the path), and each seed's TPR, state error, attack error and measured
false-alarm rate are held against the best of them, with how sure each check is over the
runs (:func:`difffilter.eval.intervals.checks_intervals`: the seeds' runs are the
baselines' runs, so the comparison is paired)::

    difffilter-train sweep --config train/configs/four_tank.yaml --seeds 0 1 2 --out sweeps/four_tank

``--validation-only`` trains every seed and names the median on validation but runs
nothing on the test's draws: ``sweep.json`` and ``sweep.md`` hold the seeds' checkpoints,
validation scores and the median seed, and say that the test is held back. For a decision
made on validation before any test number exists (a rule written first: docs/papers.md);
the same command without it then evaluates the trained seeds without training them again.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
from pathlib import Path

from difffilter.interrupts import stop_words
from difffilter.models.atomic_write import (
    save_torch_atomically,
    write_atomically,
    write_json_atomically,
)

from .common import check_config_keys, make_writable_folder, train_seed_of

__all__ = ["sweep", "main", "METRICS", "SELECT_ON", "train_seed_of"]

#: The metrics the sweep reports per seed and scenario (eval.scoring's definitions).
METRICS = ("tpr_at_far", "fpr_at_far", "fpr_at_far_after_attack", "fpr", "auc", "state_rmse",
           "attack_rmse")  # fmt: skip
_LOWER_IS_BETTER = {"fpr_at_far", "fpr_at_far_after_attack", "fpr", "state_rmse", "attack_rmse"}
#: Where the median seed is chosen: the training's validation score, or the sweep's test.
SELECT_ON = ("validation", "test")


def _exported(folder: Path) -> Path | None:
    found = sorted(p for p in folder.glob("*.ckpt") if p.with_suffix(".json").is_file())
    return found[0] if found else None


def _fit(config: Path, seed: int, runs_dir: Path, extra: list[str], progress: bool = True) -> Path:
    """Train seed ``seed`` (or take its finished run, or resume it); its exported file.
    ``progress=False`` turns the trainer's progress bar off as well."""
    from .cli import main as cli_main

    # this config's run only: another config's run in the same folder (a grad and an EKF
    # config, one --out) was taken as "trained already", the other network reported
    # (a folder of other settings was refused before the first seed: sweep())
    folder, options, settings = _seed_run(config, seed, runs_dir, extra)
    existing = [folder] if folder.is_dir() else []
    if existing and (done := _exported(existing[0])) is not None:
        print(f"seed {seed}: trained already ({done})")
        return done
    args = [
        "fit", "--config", str(config), f"--seed_everything={seed}",
        f"--model.init_args.model_seed={seed}", f"--data.init_args.train_seed={train_seed_of(seed)}",
        f"--trainer.logger.init_args.save_dir={runs_dir}",
        f"--trainer.logger.init_args.version=seed_{seed}",
        *([] if progress else ["--trainer.enable_progress_bar=false"]),
        *options,
    ]  # fmt: skip
    folder.mkdir(parents=True, exist_ok=True)
    # whole or not at all: a record cut short refused every later sweep into this --out
    write_json_atomically(folder / _SETTINGS, settings)
    last = _newest_checkpoint(existing[0]) if existing else None
    if last is not None:
        print(f"seed {seed}: resuming from {last}")
        args += ["--ckpt_path", str(last)]
    from .last_checkpoint import RESUME_HINT

    os.environ[RESUME_HINT] = "rerun the same difffilter-train sweep command: it resumes this seed"
    stopped = None
    try:
        code = cli_main(args)
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM (train/cli.py leaves it to the sweep)
        code, stopped = 130, exc
    finally:
        del os.environ[RESUME_HINT]
    if code != 0:
        if not (folder / "checkpoints").is_dir():  # nothing trained (e.g. a misspelt option):
            # its settings are no record of a run, and refused the corrected command after it
            (folder / _SETTINGS).unlink(missing_ok=True)
        if code == 130:  # interrupted, not failed: main() ends the sweep with 130 (or 143)
            raise stopped if stopped is not None else KeyboardInterrupt()
        raise ValueError(f"seed {seed}: difffilter-train fit failed (its error is above)")
    done = _exported(folder) if folder.is_dir() else None
    if done is None:
        raise ValueError(f"seed {seed}: fit exported no estimator under {folder}")
    return done


def _newest_checkpoint(folder: Path) -> Path | None:
    """The checkpoint a seed's interrupted run resumes from: its ``last.ckpt``, else the
    newest of its checkpoints (a run that saved one but no ``last.ckpt``: a config without
    ``save_last``, or cut between Lightning's two saves), else ``None``."""
    last = folder / "checkpoints" / "last.ckpt"
    if last.is_file():
        return last
    saved = sorted(folder.glob("checkpoints/*.ckpt"), key=lambda p: p.stat().st_mtime_ns)
    return saved[-1] if saved else None


#: What a seed's run folder was trained with (:func:`_settings`), beside its logs.
_SETTINGS = "sweep_settings.json"


def _seed_run(config: Path, seed: int, runs_dir: Path, extra: list[str]):
    """Seed ``seed``'s run folder, its ``fit`` options (``{seed}`` filled in) and settings."""
    options = [option.replace("{seed}", str(seed)) for option in extra]
    # the name as the fit reads it, {seed} filled in (a name of net_{seed} had been looked
    # for literally: the fit exported into net_0/seed_0 and the sweep said it exported
    # nothing, then refused the rerun; a sweep trial)
    folder = runs_dir / _run_name(config, options) / f"seed_{seed}"
    return folder, options, _settings(config, options)


def _settings(config: Path, options: list[str]) -> dict:
    """What a seed trains with: the config's values (its YAML read, so a comment edited
    is no change) and the ``fit`` options after ``--`` (``{seed}`` filled in)."""
    import yaml

    from difffilter.models.yaml_scenario import is_yaml_path, scenario_file_digest

    try:
        values = yaml.safe_load(Path(config).read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError):  # fit itself then says what is wrong with it
        values = None
    # a config given among the options (a threat distribution's: -- --config threats.yaml),
    # by its values: an edited one is another training (by its path alone, a sweep after an
    # edit took the seeds trained on the old distribution as trained already)
    option_configs = {path: _yaml_values(path) for path in _option_configs(options)}
    # the scenario files named, by their bytes: an edited plant is another training
    named = [s for s in _strings([values, *option_configs.values()]) if is_yaml_path(s)]
    named += [option.split("=")[-1] for option in options if is_yaml_path(option.split("=")[-1])]
    files = {name: scenario_file_digest(name) for name in named}
    return {
        "config_file": str(config),
        "config": values,
        "options": options,
        "option_configs": option_configs,
        "scenario_files": files,
    }


def _yaml_values(path) -> object:
    """A YAML file's values, or ``None`` where it cannot be read (``fit`` says why)."""
    import yaml

    try:
        return yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError):
        return None


def _option_pairs(options) -> list[tuple[str, str | None]]:
    """``(key, value)`` of every option in ``options``, in order, as the command line reads
    them: ``--key=value`` or ``--key value`` (``None`` for a flag without a value)."""
    options, pairs, i = [str(option) for option in options], [], 0
    while i < len(options):
        key, eq, value = options[i].partition("=")
        if not eq:
            has_value = i + 1 < len(options) and not options[i + 1].startswith("--")
            value = options[i + 1] if has_value else None
            i += has_value
        pairs.append((key, value))
        i += 1
    return pairs


def _same_options(had, now) -> bool:
    """Whether two option lists set the same values: ``--key=value`` and ``--key value``,
    in any order, the last of a key's settings counting, as the command line reads them (a
    sweep's own options reordered or respelt had been refused as "other settings": a
    red-team trial). Where a ``--config`` is among them its place matters (what follows it
    overrides it): compared as written."""
    if not isinstance(had, list) or not isinstance(now, list):
        return had == now
    pairs = [_option_pairs(options) for options in (had, now)]
    if any(key == "--config" for options in pairs for key, _ in options):
        return had == now
    return dict(pairs[0]) == dict(pairs[1])


def _option_configs(options) -> list[str]:
    """The config files a seed's ``fit`` reads after the sweep's ``--config``: every
    ``--config`` among the options (``-- --config threats.yaml``), in order."""
    return [value for key, value in _option_pairs(options) if key == "--config" and value]


def _set_last(config: Path, options, keys: tuple[str, ...]):
    """The value a seed's ``fit`` gives the setting at the dotted path ``keys[0]`` (or one of
    its spellings, ``keys``), read as the command line reads it: ``config``'s, then every
    option in order, a ``--config`` among them by its file's values, the last one setting
    it winning. ``_UNSET`` where none sets it."""
    value = _dig(_yaml_values(config), keys[0])
    for key, given in _option_pairs(options):
        if key == "--config" and given:
            found = _dig(_yaml_values(given), keys[0])
            value = value if found is _UNSET else found
        elif key.removeprefix("--") in keys:
            value = None if given in (None, "", "null") else given
    return value


def _dig(values, dotted: str):
    """``values[a][b]…`` for ``dotted = "a.b…"``, or ``_UNSET`` where a level is missing."""
    for part in dotted.split("."):
        if not isinstance(values, dict) or part not in values:
            return _UNSET
        values = values[part]
    return values


def _strings(value) -> list[str]:
    """Every string inside a YAML document's values (mappings and lists walked)."""
    if isinstance(value, str):
        return [value]
    if isinstance(value, dict):
        return [s for v in value.values() for s in _strings(v)]
    if isinstance(value, list):
        return [s for v in value for s in _strings(v)]
    return []


def _same_scenario_files(had: dict, now: dict) -> bool:
    """Whether the scenario files a seed recorded are the files named now, each with the
    digest recorded (:func:`~difffilter.models.yaml_scenario.scenario_file_matches`: a
    record made before the digest covered the code a file names is the digest of its bytes)."""
    from difffilter.models.yaml_scenario import scenario_file_matches

    if set(had) != set(now):
        return False
    return all(had[name] == now[name]
               or (had[name] is not None and scenario_file_matches(had[name], name))
               for name in had)  # fmt: skip


def _check_same_settings(folder: Path, settings: dict, seed: int) -> None:
    """A seed's folder is reused (its export taken, its ``last.ckpt`` resumed) only for the
    settings it was trained with: a second sweep into the same ``--out`` with another
    option (``-- --model.init_args.hidden=8``) or an edited config took the first sweep's
    networks and reported them as the new settings'. A folder of a sweep before the record
    existed is taken as it is."""
    file = folder / _SETTINGS
    if not file.is_file():
        return
    try:
        had = json.loads(file.read_text(encoding="utf-8"))
        if not isinstance(had, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError) as error:  # (a bad byte, bad JSON: ValueErrors)
        # not a cache: it is what guards the resume of this seed, so nothing is guessed
        raise ValueError(
            f"seed {seed}: {file} cannot be read ({error}): it records what {folder} was "
            "trained with (cut short by an interrupt or a full disk?); delete that folder to "
            "train the seed again there, or give another --out"
        ) from None
    differ = [k for k in ("config", "options")
              if not (_same_options(had.get(k), settings[k]) if k == "options"
                      else had.get(k) == settings[k])]  # fmt: skip
    # (a folder of a sweep before the files were recorded is judged on the rest)
    if "option_configs" in had and had["option_configs"] != settings["option_configs"]:
        differ.append("option_configs")
    if "scenario_files" in had and not _same_scenario_files(had["scenario_files"],
                                                           settings["scenario_files"]):  # fmt: skip
        differ.append("scenario_files")
    described = {
        "options": f"the options {had.get('options')} (now {settings['options']})",
        "config": f"the config {had.get('config_file')}'s values as they were",
        "option_configs": "the option config(s) "
        + ", ".join(sorted(set(had.get("option_configs", {})) | set(settings["option_configs"])))
        + "' values as they were (they changed since)",
        "scenario_files": "the scenario file(s) "
        + ", ".join(sorted(set(had.get("scenario_files", {})) | set(settings["scenario_files"])))
        + " as they were (their contents, or the Python code they name, changed since)",
    }
    if differ:
        what = " and ".join(described[k] for k in differ)
        raise ValueError(
            f"seed {seed}: {folder} was trained with {what}; give another --out for these "
            "settings, or delete that folder to train them there"
        )


def _check_same_sweep(out: Path, config: Path, extra: list[str]) -> None:
    """``--out`` holds no sweep of another config or other options: a second sweep of
    another config into it (its seeds' folders apart) replaced the first's ``sweep.json``
    and ``sweep.md`` without a word. More seeds of the same sweep are welcome."""
    file = out / "sweep.json"
    if not file.is_file():
        return
    try:
        had = json.loads(file.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return  # not a sweep's: the seeds' own checks still hold
    same_config = Path(str(had.get("config"))).resolve() == Path(config).resolve()
    if not same_config or not _same_options(had.get("options", []), extra):
        raise ValueError(
            f"--out {out} holds the sweep of {had.get('config')} with the options "
            f"{had.get('options', [])}; this one is {config} with {extra}: give another --out"
        )


def _run_name(config: Path, extra: list[str]) -> str:
    """The logger's run name of ``config`` (``trainer.logger.init_args.name``), or of an
    option in ``extra`` that sets it (a ``--config`` among them included: it had been
    missed, and the sweep looked for the fit's export in another folder); Lightning's
    ``lightning_logs`` without one, and ``""`` for a name of ``null`` or ``""``, where the
    logger writes into its ``save_dir`` itself (read as the config's name, a sweep wrote its
    settings into one folder and trained into another, then said the fit exported nothing:
    a review)."""
    name = _set_last(config, extra, ("trainer.logger.init_args.name",))
    if name is _UNSET:
        name = "lightning_logs"
    return str(name) if name else ""


#: no name given (Lightning's default applies), as against a name of null
_UNSET = object()

#: the options that set the training scenario (train/cli.py expands ``--scenario``)
_SCENARIO_KEYS = ("model.init_args.scenario", "data.init_args.scenario", "scenario")


def _family_metrics(result, name: str) -> dict:
    """The family's own numbers of estimator ``name`` (``FamilyReport.estimator_metrics``)."""
    from difffilter.eval.report import report_for

    hook = report_for(result.scenario)[0].estimator_metrics
    return hook(result, name) if hook is not None else {}


def _scenarios_of(path: Path, scenarios) -> tuple[str, list[str]]:
    """The registry name of the estimator of ``path`` and the scenarios it is judged on:
    ``scenarios``, else its family's headline ones, else (a family of one's own, whose
    scenarios a new process has not registered: a sweep run again after ``--validation-only``
    had judged the seeds on none, silently) its training scenario as ``fit`` was given it."""
    from difffilter.models import registry
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    from .calibrate import _fit_scenario, estimator_name

    _, card = load_estimator_checkpoint(path)
    if not scenarios:
        scenarios = registry.names(card.scenario_family, headline_only=True)
    if not scenarios:
        given = _fit_scenario(path)
        if given is None:
            raise ValueError(
                f"{path}: its family {card.scenario_family!r} has no headline scenario "
                "registered here and its card names no scenario file or module:object to "
                "judge it on; give them with --scenarios"
            )
        scenarios = [registry.get(given).name]
    return estimator_name(card), list(scenarios)


def _calibrated_metrics(scenario, names, runs, far: float, progress: bool,
                        checkpoint=None, required: bool = False) -> tuple[dict, dict]:  # fmt: skip
    """``({estimator: {metric: value}}, {estimator: per-run totals})`` of ``names`` on
    ``scenario``'s draws (``--seed 0``), their detectors calibrated at ``far`` as
    ``difffilter-eval`` calibrates them, with the family's own numbers
    (:func:`_family_metrics`); the totals (:func:`difffilter.eval.intervals.run_totals`)
    give the acceptance's intervals over the runs. ``required``: each of ``names`` must run
    (a learned checkpoint judged), else a ``ValueError`` with why it did not (it broke down
    on the scenario's runs: a bare ``KeyError`` before); otherwise those that did not run
    are left out (a baseline's analytic estimators)."""
    from difffilter.eval.acceptance import state_metric
    from difffilter.eval.calibration import calibrate
    from difffilter.eval.intervals import study_totals
    from difffilter.eval.suite import apply_calibration, detectors, run_suite

    kwargs = dict(runs=runs, checkpoint=checkpoint, progress=progress)
    result = run_suite(scenario, estimators=list(names), **kwargs)
    for name in names if required else ():
        if name not in result.outputs:
            raise ValueError(f"{name} did not run on {scenario.name}: "
                             f"{result.skipped.get(name, 'it was left out')}")  # fmt: skip
    calibration = calibrate(scenario, far=far, estimators=detectors(result), **kwargs)
    apply_calibration(result, calibration)
    # the threshold each was judged at and its rate on the calibration runs, recorded: the
    # sweep's numbers had been tied to no threshold, and an export's card holds the fit's
    # own (a sweep trial)
    table = {name: {**{m: metrics.get(m) for m in METRICS},
                    "threshold_at_far": metrics.get("threshold_at_far"),
                    "far_measured_on_calibration": calibration.measured.get(name),
                    **_family_metrics(result, name)}
             for name, metrics in result.metrics.items()}  # fmt: skip
    return table, study_totals(result, list(result.outputs), state_metric(table))


def _evaluate(path: Path, scenarios, runs, far: float, progress: bool) -> tuple[dict, dict]:
    """``({"estimator": name, "scenarios": {scenario: {metric: value}}}, {scenario: per-run
    totals})`` of the estimator of ``path``, calibrated as ``difffilter-eval`` calibrates
    (``--seed 0``)."""
    from difffilter.models import registry

    name, scenarios = _scenarios_of(path, scenarios)
    table, totals = {}, {}
    for scenario_name in scenarios:
        metrics, run_totals = _calibrated_metrics(registry.get(scenario_name), [name], runs, far,
                                                  progress, checkpoint={name: str(path)},
                                                  required=True)  # fmt: skip
        table[scenario_name], totals[scenario_name] = metrics[name], run_totals[name]
    return {"estimator": name, "scenarios": table}, totals


def _baseline(scenario_name: str, runs, far: float, progress: bool,
              folder: Path) -> tuple[dict, dict]:  # fmt: skip
    """``({estimator: {metric: value}}, {estimator: per-run totals})`` of the scenario's
    analytic estimators on the sweep's draws, calibrated as the learned one is; read from
    ``folder`` (``<scenario>.json`` and ``<scenario>.totals.pt``) if a sweep with the same
    runs, rate and seed wrote them, else run and written there.

    Both files hold the key (runs, rate, seed, the scenario file's digest, the plant's
    and the library's fingerprints: :mod:`difffilter.models.calibration_cache`), and each is written whole
    or not at all, the totals first: a sweep interrupted between the two had left its key
    beside another study's totals, which the next sweep then read as its own. A file that
    cannot be read (cut short) is a cache: said in one line and computed again."""
    from difffilter.eval.acceptance import roles
    from difffilter.models import registry
    from difffilter.models.calibration_cache import library_fingerprint, model_fingerprint
    from difffilter.models.generic_estimators import DEFAULT_SUITE
    from difffilter.models.yaml_scenario import scenario_file_digest

    scenario = registry.get(scenario_name)
    # the plant and the library's code as well as the file: a scenario given as
    # module:object (or a registered name) had no digest, and an edited plant was judged
    # against the old plant's baselines (a cache trial: 0.093 read where 0.153 holds)
    key = {"scenario": scenario_name, "runs": runs, "far": far, "eval_seed": 0,
           "scenario_file_sha256": scenario_file_digest(scenario_name),
           "plant_sha256": model_fingerprint(scenario),
           "library_sha256": library_fingerprint()}  # fmt: skip
    stem = _cache_stem(scenario_name)
    file, totals_file = folder / f"{stem}.json", folder / f"{stem}.totals.pt"
    cached = _cached_baseline(file, totals_file, key)
    if cached is not None:
        return cached
    names = list(scenario.estimators or DEFAULT_SUITE)
    analytic = [n for n, role in roles(names).items() if role == "analytic"]
    table, totals = _calibrated_metrics(scenario, analytic, runs, far, progress)
    folder.mkdir(parents=True, exist_ok=True)
    _save_totals(totals_file, {"key": key, "totals": totals})  # the totals first, then the
    write_json_atomically(file, {"key": key, "estimators": table})  # table that vouches for them
    return table, totals


def _cached_baseline(file: Path, totals_file: Path, key: dict) -> tuple[dict, dict] | None:
    """The table of ``file`` and the totals of ``totals_file`` where both were written for
    ``key``; ``None`` where either is absent, of another key (or of a sweep before the
    totals held theirs) or cannot be read, the last said on stderr (a cache: computed again)."""
    import torch

    if not (file.is_file() and totals_file.is_file()):
        return None
    try:
        cached = json.loads(file.read_text(encoding="utf-8"))
        if not isinstance(cached, dict) or not isinstance(cached.get("estimators"), dict):
            raise ValueError("not a baselines table")
    except (OSError, ValueError) as error:  # (a bad byte, bad JSON: ValueErrors)
        _cache_unreadable(file, error)
        return None
    if cached.get("key") != key:
        return None  # another study's: computed again for this one
    try:
        saved = torch.load(totals_file, weights_only=True)
    except Exception as error:  # (torch names a file cut short in many ways)
        _cache_unreadable(totals_file, error)
        return None
    if not (isinstance(saved, dict) and saved.get("key") == key
            and isinstance(saved.get("totals"), dict)):  # fmt: skip
        return None  # another study's totals (or a sweep's before they held their key)
    return cached["estimators"], saved["totals"]


def _save_totals(path: Path, document) -> None:
    """``torch.save(document)`` to ``path``, whole or not at all."""

    save_torch_atomically(path, document)


def _cache_unreadable(file: Path, error: BaseException) -> None:
    said = str(error).strip()  # its first sentence (torch's runs on for lines)
    reason = said.splitlines()[0].split(". ")[0] if said else type(error).__name__
    print(f"difffilter-train sweep: warning: the cached baselines {file} cannot be read "
          f"({reason}); computing them again", file=sys.stderr)  # fmt: skip


def _cache_stem(scenario_name: str) -> str:
    """A file name in the baselines folder for ``scenario_name``: a YAML file's path by its
    stem and a digest of its absolute path (an absolute path had replaced the folder, so the
    baselines landed beside the plant's file and every later sweep of it read them), a
    ``module:object`` path with its separators replaced."""
    import hashlib

    from difffilter.models.yaml_scenario import is_yaml_path

    if is_yaml_path(scenario_name):
        where = hashlib.sha256(str(Path(scenario_name).resolve()).encode()).hexdigest()[:12]
        return f"{Path(scenario_name).stem}-{where}"
    return scenario_name.replace("/", "_").replace(":", "_").replace("\\", "_")


def _acceptance(per_seed: dict, baselines: dict, far: float, seed_totals: dict) -> dict:
    """Per scenario, the best analytic numbers, every seed's checks against them and how
    sure each check is over the runs (:func:`difffilter.eval.intervals.checks_intervals`:
    the seeds' and the baselines' runs are the same, ``--seed 0``)."""
    from difffilter.eval.acceptance import best_analytic, judge, state_metric
    from difffilter.eval.intervals import checks_intervals

    out = {}
    for scenario, (table, totals) in baselines.items():
        learned = {s: v["scenarios"][scenario] for s, v in per_seed.items()}
        metric = state_metric({**table, **{f"seed {s}": m for s, m in learned.items()}})
        # the table holds the analytic estimators only; the state metric is the one chosen
        # over the seeds' rows too (the analytic rows alone could choose another: a review)
        best = best_analytic(table, state=metric)
        checks = {str(s): [c.as_dict() for c in judge(m, best, far, metric)]
                  for s, m in learned.items()}  # fmt: skip
        intervals = {}
        role = {**dict.fromkeys(totals, "analytic"), "learned": "learned"}
        for s in learned:
            mine = seed_totals[s][scenario]
            found = checks_intervals({**totals, "learned": mine}, role, far=far, seed=0,
                                     runs=next(iter(mine.values())).shape[0], state_metric=metric)  # fmt: skip
            intervals[str(s)] = found["estimators"]["learned"]
        out[scenario] = {
            "state_metric": metric,
            "best_analytic": {k: {"value": v, "estimator": n} for k, (v, n) in best.items()},
            "checks": checks,
            "holds": {s: all(c["holds"] for c in cs) for s, cs in checks.items()},
            "intervals": intervals,
        }
    return out


def _summary(per_seed: dict) -> dict:
    """``{scenario: {metric: {mean, min, max, spread}}}`` over the seeds. A seed whose value
    is NaN or infinite (a filter that diverged) makes all four unknown (``None``, null in
    the JSON) and is named in ``not_a_number``: Python's ``min``/``max`` had skipped a NaN
    or not by the seeds' order, and a finite spread hid it (a sweep trial); two infinite
    values had made the spread NaN and written bare ``Infinity`` and ``NaN`` into the JSON,
    which strict readers refuse (a trial of the sweep's statistics)."""
    first = next(iter(per_seed.values()))["scenarios"]
    out = {}
    for scenario, metrics in first.items():
        out[scenario] = {}
        for metric in metrics:
            values = {seed: s["scenarios"][scenario][metric] for seed, s in per_seed.items()}
            values = {seed: v for seed, v in values.items() if v is not None}
            if not values:
                continue
            nan = [seed for seed, v in values.items() if not math.isfinite(v)]
            if nan:
                out[scenario][metric] = {"mean": None, "min": None, "max": None,
                                         "spread": None, "not_a_number": nan}  # fmt: skip
                continue
            low, high = min(values.values()), max(values.values())
            out[scenario][metric] = {"mean": statistics.fmean(values.values()), "min": low,
                                     "max": high, "spread": high - low}  # fmt: skip
    return out


def _median(scores: dict[int, float], higher_is_better: bool) -> int:
    """The seed whose score is the median of the scored seeds, ranked best first (for an
    even count the worse of the two middle ones, so that the best never ships where there
    are two or more; a seed with a NaN score is not ranked, unless none has a score; ties
    keep the seeds' order)."""
    scored = [seed for seed in scores if not math.isnan(scores[seed])] or list(scores)
    ranked = sorted(scored, key=lambda seed: -scores[seed] if higher_is_better else scores[seed])
    return ranked[len(ranked) // 2]


def _test_scores(per_seed: dict, rank_by: str) -> dict[int, float]:
    """``{seed: mean of rank_by over the evaluated scenarios}`` (NaN where none has it)."""
    out = {}
    for seed, entry in per_seed.items():
        values = [m[rank_by] for m in entry["scenarios"].values() if m[rank_by] is not None]
        out[seed] = statistics.fmean(values) if values else float("nan")
    return out


def _check_before_training(config: Path, out: Path, scenarios, runs, test: bool, extra) -> None:
    """``ValueError`` for what the evaluation after each training would refuse, said before
    the first training: ``--out`` a file, ``--runs`` below 1, ``--scenarios`` unknown or of
    another family than the config's training scenario (unless ``extra`` sets another)."""
    from difffilter.models import registry

    if out.exists() and not out.is_dir():
        raise ValueError(f"--out: {out} is a file; a sweep writes a folder there")
    if runs is not None and (isinstance(runs, bool) or not isinstance(runs, int) or runs < 1):
        raise ValueError(f"--runs must be an integer >= 1; got {runs!r}")
    _check_one_process(config, extra)
    if not (test and scenarios):
        return
    # the scenario the fit trains on, as it reads its configs and options (train/cli.py's
    # --scenario shortcut sets the model's and the data's)
    trained = _set_last(config, extra, _SCENARIO_KEYS)
    understood = {"--config", *(f"--{key}" for key in _SCENARIO_KEYS)}
    unread = any("scenario" in key and key not in understood for key, _ in _option_pairs(extra))
    family = None if trained in (None, _UNSET) or unread else registry.get(trained).family
    for name in scenarios:
        scenario = registry.get(name)  # an unknown name: its error, listing the valid ones
        if family is not None and scenario.family != family:
            raise ValueError(f"--scenarios: {name} is a {scenario.family} scenario; {config} "
                             f"trains a {family} estimator ({trained})")  # fmt: skip


def _check_one_process(config: Path, extra) -> None:
    """``ValueError`` where a seed's fit would run on several processes: Lightning's DDP
    starts its other processes by running the command line again, and a sweep's seeds are
    fits inside the sweep's process (a trial's ``-- --trainer.strategy=ddp
    --trainer.devices=2``: the other process ran a bare ``difffilter-train``, and Lightning
    killed the sweep, exit 137, no error line)."""
    devices = _set_last(config, extra, ("trainer.devices",))
    if isinstance(devices, str):  # as given on the command line: "2", "[0, 1]", "auto"
        import yaml

        try:
            devices = yaml.safe_load(devices)
        except yaml.YAMLError:
            return  # (Lightning refuses it itself)
    try:
        several = (len(devices) > 1 if isinstance(devices, list | tuple)
                   else devices not in (None, _UNSET, "auto") and int(devices) > 1)  # fmt: skip
    except (TypeError, ValueError):
        several = False  # (a spelling Lightning reads, or refuses, itself)
    if several:
        raise ValueError(
            f"a sweep trains its seeds one after another inside its own process, and a fit on "
            f"several processes (trainer.devices = {devices}) cannot be started from there: "
            "sweep with --trainer.devices=1, or train each seed with difffilter-train fit "
            "--config ... --seed_everything=N on several processes"
        )


def _check_keys_once(config: Path) -> None:
    """``ValueError`` naming ``config`` where it is no valid YAML (the monitor check read
    it first, with a parser traceback) or a mapping of it holds a key twice
    (:func:`~difffilter.models.yaml_scenario.check_unique_keys`): said before anything
    else reads it."""
    import yaml

    try:
        check_config_keys(config)
    except yaml.YAMLError as error:
        raise ValueError(f"--config: {config} is not valid YAML: {error}") from None


def _config_monitor(config: Path) -> dict | None:
    """``{"metric", "mode"}`` of the config's ``ModelCheckpoint`` (Lightning's mode default
    ``min``), or ``None``: for cards exported before they recorded their monitor."""
    import yaml

    trainer = (yaml.safe_load(config.read_text(encoding="utf-8")) or {}).get("trainer") or {}
    for callback in trainer.get("callbacks") or []:
        if isinstance(callback, dict) and str(callback.get("class_path", "")).endswith(
            "ModelCheckpoint"
        ):
            init = callback.get("init_args") or {}
            if init.get("monitor"):
                return {"metric": init["monitor"], "mode": init.get("mode", "min")}
    return None


def _validation_scores(cards: dict[int, dict], config: Path) -> tuple[dict[int, float], dict]:
    """``({seed: best_val_score}, {"metric", "mode"})``: the validation score each seed's
    training chose its weights by, from its card ``cards[seed]`` (its ``monitor``, else the
    config's)."""
    scores, monitors = {}, {}
    fallback = _config_monitor(config)  # for cards exported before they recorded theirs
    for seed, card in cards.items():
        monitor = card.get("monitor") or fallback
        score = card.get("best_val_score")
        if monitor is None or score is None:
            why = ("no validation ran before its training stopped (train at least one whole "
                   "epoch)" if monitor is not None
                   else "the config's ModelCheckpoint has no monitor")  # fmt: skip
            raise ValueError(
                f"seed {seed}: its card names no validation score its weights were chosen by "
                f"({why}); --select-on test ranks the seeds on the sweep's evaluation instead"
            )
        scores[seed], monitors[seed] = float(score), (monitor["metric"], monitor["mode"])
    if len(set(monitors.values())) > 1:
        raise ValueError(f"the seeds' weights were chosen by different validation scores "
                         f"({sorted(set(monitors.values()))}): they rank by no one of them; "
                         "--select-on test ranks them on the sweep's evaluation")  # fmt: skip
    metric, mode = next(iter(monitors.values()))
    return scores, {"metric": metric, "mode": mode}


def sweep(config, seeds=(0, 1, 2), out="sweeps", *, scenarios=None, runs: int | None = None,
          far: float = 0.01, rank_by: str = "tpr_at_far", select_on: str = "validation",
          extra=(), progress: bool = True, test: bool = True) -> dict:  # fmt: skip
    """Train ``config`` on every seed and evaluate each (module docstring); writes and
    returns the sweep's document. ``extra``: more ``fit`` options for every seed;
    ``test=False``: ``--validation-only`` (nothing run on the test's draws)."""
    config, out = Path(config), Path(out)
    if not config.is_file():
        raise FileNotFoundError(f"--config: {config} does not exist")
    _check_keys_once(config)  # before anything reads it (invalid, or a key twice)
    seeds = [int(s) for s in seeds]
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise ValueError(f"--seeds must be distinct integers >= 0; got {seeds}")
    if rank_by not in METRICS:
        raise ValueError(f"--rank-by must be one of {', '.join(METRICS)}; got {rank_by!r}")
    if select_on not in SELECT_ON:
        raise ValueError(f"--select-on must be one of {', '.join(SELECT_ON)}; got {select_on!r}")
    if not 0.0 < far < 1.0:
        raise ValueError(f"--far must lie in (0, 1); got {far!r}")
    if not test and select_on != "validation":
        raise ValueError("--validation-only chooses the median seed on validation; "
                         "--select-on test needs the test's draws")  # fmt: skip
    callbacks_given = any("callbacks" in option for option in extra) or any(
        _dig(_yaml_values(path), "trainer.callbacks") is not _UNSET
        for path in _option_configs(extra)
    )  # (a config among the options with callbacks of its own had been refused here)
    if select_on == "validation" and _config_monitor(config) is None and not callbacks_given:
        # said before hours of training, not after
        raise ValueError(f"--select-on validation ranks the seeds by the score their "
                         f"training chose its weights by, and {config} has no ModelCheckpoint "
                         "monitor; add one, or --select-on test")  # fmt: skip
    _check_before_training(config, out, scenarios, runs, test, extra)
    _check_same_sweep(out, config, list(extra))
    make_writable_folder(out)  # the last check: a refused sweep leaves no empty folder behind
    runs_dir = out / "runs"
    for seed in seeds:  # every seed's folder before the first is trained
        folder, _, settings = _seed_run(config, seed, runs_dir, list(extra))
        if folder.is_dir():
            _check_same_settings(folder, settings, seed)
    per_seed, cards, seed_totals = {}, {}, {}
    for seed in seeds:
        path = _fit(config, seed, runs_dir, list(extra), progress)
        card = cards[seed] = json.loads(path.with_suffix(".json").read_text(encoding="utf-8"))
        per_seed[seed] = {"checkpoint": str(path), "train_time_s": card.get("train_time_s")}
        if test:
            evaluated, seed_totals[seed] = _evaluate(path, scenarios, runs, far, progress)
            per_seed[seed].update(evaluated)
    by_test = None  # --validation-only: no test number names a seed
    if test:
        test_scores = _test_scores(per_seed, rank_by)
        by_test = _median(test_scores, rank_by not in _LOWER_IS_BETTER)
    if select_on == "validation":
        scores, monitor = _validation_scores(cards, config)
        median = _median(scores, monitor["mode"] == "max")
    else:
        scores, monitor, median = test_scores, None, by_test
    doc = {
        "config": str(config), "options": list(extra), "seeds": seeds, "far": far, "runs": runs,
        "eval_seed": 0 if test else None, "rank_by": rank_by if test else None,
        "select_on": select_on, "median_seed": median,
        "median_checkpoint": per_seed[median]["checkpoint"],
        "selection": {"monitor": monitor, "scores": {str(s): v for s, v in scores.items()},
                      "median_seed_by_test": by_test},
        "per_seed": {str(s): v for s, v in per_seed.items()},
    }  # fmt: skip
    if not test:
        doc["test"] = "held back"
        return _write(out, doc)
    _, judged = _scenarios_of(Path(per_seed[seeds[0]]["checkpoint"]), scenarios)
    baselines = {sc: _baseline(sc, runs, far, progress, out / "baselines") for sc in judged}
    doc["summary"] = _summary(per_seed)
    doc["acceptance"] = _acceptance(per_seed, baselines, far, seed_totals)
    return _write(out, doc)


def _write(out: Path, doc: dict) -> dict:
    """``<out>/sweep.json`` and ``<out>/sweep.md`` of ``doc``; returns it. In the JSON a NaN
    or infinite value (a seed's diverged error, the NaN score of a seed without the ranked
    metric) is null, as in the summary and metrics.json: bare ``NaN`` and ``Infinity`` had
    been written into ``per_seed`` and ``selection``, which strict readers refuse (a trial of
    the reports' JSON)."""
    from difffilter.eval.report import json_safe

    out.mkdir(parents=True, exist_ok=True)
    write_json_atomically(out / "sweep.json", json_safe(doc))
    write_atomically(out / "sweep.md", _markdown(doc))
    return doc


def _markdown(doc: dict) -> str:
    from difffilter.eval.report import format_number as f

    title = f"# Sweep of {doc['config']} over seeds {', '.join(map(str, doc['seeds']))}\n"
    if doc.get("test") == "held back":
        times = ", ".join(f"seed {s} " + ("not recorded" if (t := v.get("train_time_s")) is None
                                          else f"{f(t)} s") for s, v in doc["per_seed"].items())  # fmt: skip
        return (f"{title}\n{_selection_sentence(doc)}\n\nTraining time: {times}.\n\n"
                "The test evaluation is held back (`--validation-only`): no number of the test's "
                "draws exists yet. The same command without `--validation-only` evaluates these "
                "seeds without training them again.\n")  # fmt: skip
    lines = [
        title,
        f"Each seed's estimator on `difffilter-eval`'s runs (seed {doc['eval_seed']}), every "
        f"threshold calibrated for {100 * doc['far']:g} % false alarms on attack-free runs of "
        f"their own seed. {_selection_sentence(doc)}\n",
        "| scenario | metric | "
        + " | ".join(f"seed {s}" for s in doc["seeds"])
        + " | mean | spread (max − min) |",
        "|---|---|" + "---|" * (len(doc["seeds"]) + 2),
    ]
    for scenario, metrics in doc["summary"].items():
        for metric, stats in metrics.items():
            cells = [
                f(doc["per_seed"][str(s)]["scenarios"][scenario][metric]) for s in doc["seeds"]
            ]
            lines.append(f"| {scenario} | {metric} | " + " | ".join(cells)
                         + f" | {f(stats['mean'])} | {f(stats['spread'])} |")  # fmt: skip
    return "\n".join(lines + _acceptance_markdown(doc)) + "\n"


def _selection_sentence(doc: dict) -> str:
    """How the median seed was chosen, its scores per seed, and the test's choice beside."""
    from difffilter.eval.report import format_number as f

    selection, median = doc["selection"], doc["median_seed"]
    scores = ", ".join(f"seed {s} {f(v)}" for s, v in selection["scores"].items())
    by_test = selection["median_seed_by_test"]
    if doc["select_on"] == "test":
        return (f"Median seed by the evaluation's {doc['rank_by']} (chosen on these draws): "
                f"**{median}** (`{doc['median_checkpoint']}`; {scores}).")  # fmt: skip
    monitor = selection["monitor"]
    chosen = (f"Median seed on validation, by the score each training chose its weights by "
              f"({monitor['metric']}, {'higher' if monitor['mode'] == 'max' else 'lower'} is "
              f"better; its config's validation runs, not the test's): **{median}** "
              f"(`{doc['median_checkpoint']}`; {scores}).")  # fmt: skip
    if by_test is None:  # --validation-only: no test number to name a seed by
        return chosen
    beside = "the same seed" if by_test == median else f"seed {by_test}"
    return f"{chosen} The evaluation's {doc['rank_by']} below would name {beside}."


def _acceptance_markdown(doc: dict) -> list[str]:
    """The acceptance section: each check per seed (✓/✗) against the best analytic."""
    from difffilter.eval.acceptance import ANALYTIC, TOLERANCES
    from difffilter.eval.report import format_number as f
    from difffilter.eval.report import share_suffix

    accept = doc.get("acceptance") or {}
    if not accept:
        return []
    seeds = [str(s) for s in doc["seeds"]]
    lines = [
        "",
        "## Against the best analytic estimator",
        "",
        "The best analytic: per metric, the best of the scenario's analytic estimators "
        f"({ANALYTIC}) on the same runs, calibrated the same way."
        f" A seed holds a row when its TPR ≥ the best − {TOLERANCES['tpr_margin']:g}, "
        f"its state error ≤ {TOLERANCES['state_factor']:g} × the best, its attack error ≤ the "
        "best (where an analytic estimator estimates the attack) and its measured false-alarm "
        f"rate lies within [{TOLERANCES['fpr_band'][0]:g}α, {TOLERANCES['fpr_band'][1]:g}α]."
        " In brackets, how sure each check is: the share of resamples of the runs in which it "
        "holds (a paired bootstrap over the runs, the best analytic chosen again in each; "
        "`sweep.json`'s `intervals` give each check's statistic and its 95 % interval; "
        "`difffilter.eval.intervals`).",
        "",
        "| scenario | check | best analytic | " + " | ".join(f"seed {s}" for s in seeds) + " |",
        "|---|---|---|" + "---|" * len(seeds),
    ]
    for scenario, entry in accept.items():
        for i, check in enumerate(entry["checks"][seeds[0]]):
            best = (f"{f(check['best'])} (`{check['best_estimator']}`)"
                    if check["best"] is not None else "—")  # fmt: skip
            cells = []
            for s in seeds:
                c = entry["checks"][s][i]
                sure = (entry.get("intervals") or {}).get(s, {}).get(c["metric"])
                cells.append(f"{f(c['value'])} {'✓' if c['holds'] else '✗'}" + share_suffix(sure))
            lines.append(f"| {scenario} | {check['metric']} {check['bound']} | {best} | "
                         + " | ".join(cells) + " |")  # fmt: skip
        verdict = ["**holds**" if entry["holds"][s] else "fails" for s in seeds]
        lines.append(f"| {scenario} | every check | | " + " | ".join(verdict) + " |")
    median = str(doc["median_seed"])
    held = all(entry["holds"][median] for entry in accept.values())
    lines += [
        "",
        f"The median seed {median} {'holds every row' if held else 'does not hold every row'}.",
    ]
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="difffilter-train sweep",
        allow_abbrev=False,  # `--device cuda` had been read as --devices, "invalid int"
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Options after -- go to every seed's fit (e.g. -- --trainer.max_epochs=5); "
        "{seed} in them becomes the seed (a curriculum's second stage: -- "
        "--model.init_args.init_from=stage1/runs/<name>/seed_{seed}/<name>.ckpt).",
    )
    p.add_argument("--config", type=Path, required=True,
                   help="the training config (YAML); a second one, e.g. a threat "
                        "distribution's, goes after -- (-- --config threats.yaml)")  # fmt: skip
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds (0 1 2)")
    p.add_argument("--out", type=Path, required=True, help="the sweep's folder")
    p.add_argument("--scenarios", default=None,
                   help="comma-separated scenarios (default: the family's headline ones; a family "
                        "of your own: the training scenario)")  # fmt: skip
    p.add_argument("--runs", type=int, default=None, help="evaluation runs (the scenario's)")
    p.add_argument("--far", type=float, default=0.01, help="target false-alarm rate (0.01)")
    p.add_argument("--select-on", choices=SELECT_ON, default="validation",
                   help="where the median seed is chosen: each training's validation score "
                   "(default) or the sweep's evaluation (--rank-by)")  # fmt: skip
    p.add_argument("--rank-by", default="tpr_at_far",
                   help="the evaluation's metric that ranks the seeds under --select-on test "
                   "(and names the test's median beside the validation's)")  # fmt: skip
    p.add_argument("--validation-only", action="store_true",
                   help="train and name the median seed on validation, but run nothing on the "
                   "test's draws (run again without it to evaluate the trained seeds)")  # fmt: skip
    p.add_argument("--no-progress", action="store_true",
                   help="no progress bars (the trainings' included)")  # fmt: skip
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    args = p.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    scenarios = [s for s in args.scenarios.split(",") if s] if args.scenarios else None
    try:
        doc = sweep(args.config, args.seeds, args.out, scenarios=scenarios, runs=args.runs,
                    far=args.far, rank_by=args.rank_by, select_on=args.select_on, extra=extra,
                    progress=not args.no_progress, test=not args.validation_only)  # fmt: skip
    except (ValueError, FileNotFoundError) as exc:
        print(f"difffilter-train sweep: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # Ctrl-C: exit code 130, as difffilter-eval's (1 before)
        what, code = stop_words(exc)  # (SIGTERM: 143)
        print(f"difffilter-train sweep: {what}: the seeds trained are kept and the one "
              "being trained resumes from its last whole epoch; rerun the same command to go "
              "on", file=sys.stderr)  # fmt: skip
        return code
    print((Path(args.out) / "sweep.md").read_text(encoding="utf-8"))
    if args.validation_only:
        print(f"median seed {doc['median_seed']} on validation; the test is held back")
        return 0
    print(f"median seed {doc['median_seed']}: ship it with difffilter-train export "
          f"{doc['median_checkpoint']} --out <file>")  # fmt: skip
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
