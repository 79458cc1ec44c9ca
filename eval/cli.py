"""``difffilter-eval``: Monte Carlo evaluation of every estimator on a scenario.

Usage::

    difffilter-eval four_tank_bias --runs 100 --out reports/
    difffilter-eval lfc --runs 20          # the shipped checkpoints/lfc_nn_grad.ckpt
    difffilter-eval lfc --ckpt lightning_logs/lfc_nn_grad/version_0/lfc_nn_grad.ckpt
    difffilter-eval all
    difffilter-eval --list

Each scenario writes ``<out>/<scenario>/{metrics.json, report.md, *.png}`` and
TensorBoard events under ``<out>/<scenario>/tb`` (``tensorboard --logdir <out>``).
A family name (``four_tank``, ``lfc``, …) selects its headline scenarios. Each file is
replaced whole or not at all; ``INCOMPLETE.md`` marks ``<out>`` and a scenario's folder
while an evaluation or a robustness study writes there (left by one that was stopped or
failed, with a section per kind that only a run of that kind to its end removes), and one
evaluation at a time writes into an ``--out`` (``<out>/.difffilter.lock``).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import math
import os
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

import yaml

# torch, the registry and the suite are imported where they are used, so that --help
# answers at once

__all__ = ["main", "build_parser", "resolve_scenarios", "evaluate", "check_arguments",
           "check_output_folder", "hold_output_folder", "EVALUATION_SEED"]  # fmt: skip

#: The master seed of the default study (``--seed``): its runs are the test runs, which
#: no training, validation or monitor may draw (``difffilter.train.task`` refuses them).
EVALUATION_SEED = 0


class _GivenOnce(argparse.Action):
    """An option whose value is one list: given twice, the first list had been dropped
    without a word (``--estimators a --estimators b`` ran ``b`` alone; a red-team trial)."""

    def __call__(self, parser, namespace, values, option_string=None):
        seen = namespace.__dict__.setdefault("_given_once", set())
        if self.dest in seen:
            parser.error(f"{option_string}: given twice; give one comma-separated list (A,B,…)")
        seen.add(self.dest)
        setattr(namespace, self.dest, values)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="difffilter-eval",
        allow_abbrev=False,  # `--device cuda` had been read as --devices, "invalid int"
        description=(
            "Evaluate estimators and detectors on a scenario and write metrics.json, "
            "report.md, plots and TensorBoard logs."
        ),
    )
    p.add_argument(
        "scenario",
        nargs="?",
        help="scenario name, family name or 'all' (see --list), or package.module:object for "
        "a scenario of your own (docs/adding-a-scenario.md)",
    )
    p.add_argument(
        "--scenario",
        dest="scenario_option",
        default=None,
        metavar="NAME",
        help="the scenario, as the positional argument (e.g. --scenario my_plants:scenario)",
    )
    p.add_argument(
        "--ckpt",
        action="append",
        default=None,
        metavar="[NAME=]PATH",
        help="trained estimator: an exported file or a Lightning checkpoint of a training run "
        "(default: the scenario's shipped checkpoint, if it has one); one trained on another "
        "scenario family than the scenarios evaluated is an error. NAME=PATH (repeatable) "
        "gives estimator NAME its own checkpoint and runs it: --ckpt pf_nn_grad=a.ckpt "
        "--ckpt pf_nn_ekf=b.ckpt compares two in one run",
    )
    p.add_argument(
        "--runs", type=int, default=None, help="Monte Carlo runs (default: the scenario family's)"
    )
    p.add_argument(
        "--estimators",
        action=_GivenOnce,
        type=_estimator_list,
        default=None,
        metavar="A,B,…",
        help="the registered estimators to run instead of each scenario's own (e.g. "
        "chi_square_kf,cusum_kf); a family's tables that need another are left out with the "
        "reason",
    )
    p.add_argument(
        "--add-estimators",
        action=_GivenOnce,
        type=_estimator_list,
        default=[],
        metavar="A,B,…",
        help="registered estimators to run beside each scenario's own (e.g. pf_nn_ekf with an "
        "EKF-trained --ckpt)",
    )
    p.add_argument(
        "--out", type=_folder, default=Path("reports"), help="output folder (default: reports/)"
    )
    p.add_argument(
        "--seed",
        type=int,
        default=EVALUATION_SEED,
        help=f"master seed of every random draw (default {EVALUATION_SEED})",
    )
    p.add_argument(
        "-o",
        "--option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        type=_option,
        help="an option of the scenario family's report, repeatable (VALUE read as YAML), e.g. "
        "lfc's per_channel=true: the per-channel validation on random attacks (docs/scenarios.md;"
        " a family's own studies take their size from these options, not from --runs)",
    )
    p.add_argument(
        "--devices",
        type=int,
        default=1,
        help="processes that share each scenario's estimators (torch.distributed, gloo on "
        "CPU); the metrics are those of one process (default 1)",
    )
    p.add_argument(
        "--far",
        type=_far,
        default=0.01,
        metavar="RATE",
        help="the false-alarm rate every detector is judged at: its threshold comes from "
        "attack-free runs of their own seed (default 0.01; 'off' skips the calibration)",
    )
    p.add_argument(
        "--calibration-runs",
        type=int,
        default=None,
        metavar="N",
        help="attack-free runs behind each threshold (default: --runs, else the scenario's)",
    )
    p.add_argument(
        "--threats",
        action=_GivenOnce,
        type=_threats,
        default=None,
        metavar="all|A,B,…",
        help="the robustness study instead of the scenario's report: every estimator against "
        "these threats of the scenario's threat set (eval/threats/*.yaml), at --far; the "
        "scenario 'robustness' runs it on every headline scenario (default: all threats)",
    )
    p.add_argument(
        "--threat-set",
        type=Path,
        default=None,
        metavar="FILE.yaml",
        help="with --threats: the threat set to read instead of the scenario's in "
        "eval/threats/ (a scenario of your own; the format of docs/threats.md)",
    )
    p.add_argument(
        "--import",
        dest="imports",
        action="append",
        default=[],
        metavar="MODULE",
        help="import MODULE first (repeatable; from the working folder too): a module of your "
        "own that registers estimators (difffilter.models.estimators.register) to run with "
        "--add-estimators, or scenarios (docs/adding-a-scenario.md)",
    )
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    p.add_argument(
        "--list",
        action="store_true",
        help="list the registered scenarios and exit (with a family or all: those alone)",
    )
    return p


def _far(text: str) -> float | None:
    if text.strip().lower() in ("off", "none"):
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a rate in (0, 1) or 'off'; got {text!r}")
    return value


def _estimator_list(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:  # ("" ran the scenario's own, as if the option were not given)
        raise argparse.ArgumentTypeError("expected estimator names separated by commas")
    return names


def _folder(text: str) -> Path:
    if not text.strip():  # (Path("") is ".": the reports went into the current folder)
        raise argparse.ArgumentTypeError("expected a folder; got an empty name")
    return Path(text)


def _threats(text: str):
    if text.strip() == "all":
        return "all"
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise argparse.ArgumentTypeError("expected 'all' or threat names separated by commas")
    return names


def _option(text: str) -> tuple[str, object]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE; got {text!r}")
    from difffilter.models.yaml_scenario import load_yaml_text

    try:
        return key, load_yaml_text(value)  # (1e-2 a number, as in the YAML files)
    except yaml.YAMLError as error:  # argparse turns only these into a usage error
        raise argparse.ArgumentTypeError(
            f"{key}: {value!r} is not a YAML value ({str(error).splitlines()[0]})"
        ) from None


def resolve_scenarios(name: str) -> list[str]:
    """Expand ``name`` (a scenario, a family or ``all``) to scenario names; ``ValueError`` if unknown.

    ``all`` and a family name run the scenarios marked ``headline``; variants are run by
    their own names; ``package.module:object`` is a scenario from outside the repository
    (registered under its own name, :mod:`difffilter.models.registry`).
    """
    from difffilter.models import registry

    if name in ("all", "robustness"):
        return registry.names(headline_only=True)
    if name in registry.families():
        return registry.names(name, headline_only=True) or registry.names(name)
    from difffilter.models.yaml_scenario import is_yaml_path

    # a scenario of the user's: its own errors (a file's, whatever the extension's case:
    # Bad.YAML's error had read "unknown scenario")
    if ":" in name or is_yaml_path(name):
        return [registry.get(name).name]
    try:
        return [registry.get(name).name]
    except ValueError:
        targets = ["all", "robustness", *registry.families()]
        hint = registry.nearest(name, [*registry.names(), *targets])
        raise ValueError(
            f"unknown scenario {name!r}; {hint}known scenarios: {', '.join(registry.names())}; "
            f"also {', '.join(targets)} (difffilter-eval --list)"
        ) from None


def evaluate(
    scenarios: Sequence[str],
    *,
    ckpt: Path | None,
    runs: int | None,
    out: Path,
    seed: int,
    progress: bool,
    family_options: dict | None = None,
    add_estimators: Sequence[str] = (),
    estimators: Sequence[str] | None = None,
    far: float | None = 0.01,
    calibration_runs: int | None = None,
) -> dict:
    """Evaluate every scenario with the Monte Carlo suite; returns ``{scenario: metrics}``.

    Scenarios are taken family by family: the family's ``prepare`` (a study its reports
    share) runs once before its scenarios, its ``finish`` (a summary across them) once
    after (:class:`~difffilter.eval.report.FamilyReport`); ``family_options``
    (``--option KEY=VALUE``) reach ``prepare`` as its options; ``estimators`` replace each
    scenario's own (``None``: its own), ``add_estimators`` run beside them. With ``far``
    every detector is judged at that false-alarm rate, its threshold calibrated on
    ``calibration_runs`` attack-free runs of their own seed
    (:mod:`~difffilter.eval.calibration`). Ends with the leaderboard of every scenario ×
    estimator (:mod:`~difffilter.eval.leaderboard`: ``<out>/leaderboard.{md,json,png}``,
    ``tb_leaderboard``). From its first write into ``out`` to the leaderboard's,
    ``<out>/INCOMPLETE.md`` says that the folder's files may be of two evaluations
    (:func:`~difffilter.eval.report.mark_incomplete`, its ``evaluation`` section: a stopped
    robustness study's stays).
    """
    from difffilter.models import registry

    from .calibration import calibrate
    from .leaderboard import write_leaderboard
    from .report import (
        clear_incomplete,
        family_report,
        mark_incomplete,
        report_for,
        report_writers,
        write_acceptance_summary,
    )
    from .suite import apply_calibration, detectors, process_group, run_suite

    check_arguments(runs=runs, ckpt=ckpt, calibration_runs=calibration_runs)
    families: dict[str, list[str]] = {}
    for name in scenarios:
        families.setdefault(registry.get(name).family, []).append(name)
    check_family_options(list((family_options or {}).items()), scenarios)
    cache: dict = {}  # shared by the suites of this call (e.g. common attack-free runs)
    rank, world = process_group()
    # With --devices N every process holds every result after each suite's gather; each
    # family's reports are written by one of them, after the last suite (a report written
    # between two suites would hold the others at the next gather).
    writers = report_writers(families, world)
    prepared, held, docs = {}, {}, {}

    marked: list[Path] = []

    def writing() -> None:  # before this process's first write into out
        if not marked:
            Path(out).mkdir(parents=True, exist_ok=True)
            marked.append(mark_incomplete(out, "An evaluation into this folder"))

    for family, names in families.items():
        report = family_report(family)
        mine = writers[family] == rank
        native = [n for n in names if report_for(registry.get(n))[1] is None]
        if report.prepare and mine and native:
            writing()
            prepared[family] = report.prepare(
                native, out=Path(out), seed=seed, checkpoint=ckpt, progress=progress,
                options=dict(family_options or {}), far=far,
            )  # fmt: skip
        for name in names:
            scenario = registry.get(name)
            result = run_suite(
                scenario, runs=runs, seed=seed, progress=progress, checkpoint=ckpt,
                cache=cache, add=add_estimators, estimators=estimators,
            )  # fmt: skip
            if far is not None:  # after the study: only its detectors need attack-free runs
                apply_calibration(result, calibrate(
                    scenario, far=far, runs=calibration_runs or runs, seed=seed,
                    estimators=detectors(result), checkpoint=ckpt, progress=progress,
                    cache=cache, study_runs=scenario.runs if runs is None else runs,
                ))  # fmt: skip
            if mine:
                held.setdefault(family, {})[name] = result
            if rank == 0 and add_estimators:
                note_skipped_additions(add_estimators, result.skipped, name)
        if world == 1:  # one process: each family's reports as soon as its suites are done
            writing()
            docs.update(_write_family(family, held.pop(family), out, prepared.get(family)))
    for family, results in held.items():
        writing()
        docs.update(_write_family(family, results, out, prepared.get(family)))
    if world > 1:
        from .suite import gather_objects

        parts = gather_objects(docs, world)
        merged = {k: v for part in parts for k, v in part.items()}
        docs = {name: merged[name] for names in families.values() for name in names}
    if rank == 0:
        writing()
        write_leaderboard(out, docs)
        write_acceptance_summary(out, docs)
        # every process's reports are written (they were gathered above): the folder is whole
        # as far as evaluations go (a stopped robustness study's section stays)
        clear_incomplete(out)
    return docs if rank == 0 else {}


def check_family_options(options, scenarios: Sequence[str]) -> None:
    """``--option`` pairs ``[(key, value)]`` checked before any work, by every family of
    ``scenarios`` that takes options (:attr:`FamilyReport.check_options`): a bad key for
    the LFC family in ``all`` failed after the four-tank suites had run and written their
    reports. A key given twice is refused (the last won, silently)."""
    if not options:
        return
    from difffilter.models import registry

    from .report import family_report, report_for

    keys = [key for key, _ in options]
    twice = sorted({k for k in keys if keys.count(k) > 1})
    if twice:
        raise ValueError(f"--option {', '.join(twice)}: given twice; give each key once")
    families = list(dict.fromkeys(registry.get(name).family for name in scenarios))
    # a family takes options through its own scenarios only (its studies run on them): a
    # plant of one's own declared in the lfc family had -o watermark=true accepted and no
    # study run (a red-team trial)
    native = {registry.get(n).family for n in scenarios if report_for(registry.get(n))[1] is None}
    takers = [f for f in families if family_report(f).prepare is not None and f in native]
    if not takers:
        own = [f for f in families if family_report(f).prepare is not None]
        if own:
            raise ValueError(
                f"--option: the {', '.join(own)} family's options run its studies on its own "
                f"scenarios, and {', '.join(scenarios)} are plants of your own: no option "
                "would take effect (docs/scenarios.md)"
            )
        raise ValueError(
            f"--option: the families evaluated ({', '.join(families)}) take no options; "
            "lfc does (docs/scenarios.md)"
        )
    for family in takers:
        check = family_report(family).check_options
        if check is not None:
            check(dict(options))


def check_scenario_estimators(names: Sequence[str]) -> None:
    """Every estimator the scenarios ``names`` list is registered, checked before any work:
    a misspelt name in a scenario of one's own was found only when that scenario ran, after
    the others, and no report was written."""
    from difffilter.models import registry

    for name in names:
        _check_estimator_names(registry.get(name).estimators, f"scenario {name!r} lists ")


def _check_estimator_names(names, where: str) -> None:
    """Each of ``names`` is a registered estimator; the registry's error (the nearest name
    included) after ``where`` otherwise."""
    from difffilter.models import estimators

    for name in names or ():
        try:
            estimators.get(name)
        except ValueError as error:
            raise ValueError(f"{where}{error}") from None


def note_skipped_additions(added, skipped: dict[str, str], scenario: str) -> None:
    """Say on stderr which ``--add-estimators`` a scenario left out, and why: asked for by
    name, they were dropped silently (the reason only in ``report.md`` and ``metrics.json``'s
    ``skipped``). A note, not an error: ``all --add-estimators X`` may fit some scenarios."""
    for name in added or ():
        if name in skipped:
            print(f"note: --add-estimators {name} does not run on {scenario}: {skipped[name]}",
                  file=sys.stderr)  # fmt: skip


def _write_family(family: str, results: dict, out, prepared) -> dict:
    """Each scenario's report of ``results`` (``{scenario: SuiteResult}``) and the family's
    summary; returns ``{scenario: metrics.json content}``."""
    from .report import family_report, report_for, write_report

    done = {name: write_report(Path(out) / name, result, prepared=prepared)
            for name, result in results.items()}  # fmt: skip
    report = family_report(family)
    # the family's summary of its own scenarios (a plant of one's own in it: left out)
    native = {
        name: doc for name, doc in done.items() if report_for(results[name].scenario)[1] is None
    }
    if report.finish and native:
        report.finish(native, Path(out), prepared)
    return done


def check_arguments(*, runs: int | None = None, ckpt=None, devices: int = 1,
                    calibration_runs: int | None = None, seed: int = 0,
                    add_estimators: Sequence[str] = (),
                    estimators: Sequence[str] | None = None) -> None:  # fmt: skip
    """``ValueError``/``FileNotFoundError`` naming the option, before any work."""
    checked = (("--runs", runs), ("--devices", devices), ("--calibration-runs", calibration_runs))
    for name, value in checked:
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):  # fmt: skip
            raise ValueError(f"{name} must be an integer >= 1; got {value!r}")
    cpus = os.cpu_count() or 1
    if devices is not None and devices > max(cpus, 2):
        # each process runs on one core and holds ~0.4 GB: 100 sat silent for minutes
        raise ValueError(
            f"--devices {devices}: this machine has {cpus} CPU(s); each process runs on one "
            f"core (and holds about 0.4 GB), so use at most {max(cpus, 2)}"
        )
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"--seed must be an integer >= 0; got {seed!r}")
    _check_estimator_names(add_estimators, "--add-estimators: ")
    _check_estimator_names(estimators, "--estimators: ")
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    for _, path in _checkpoint_paths(ckpt):
        try:
            load_estimator_checkpoint(path)  # a missing or bad file fails here
        except (ValueError, FileNotFoundError) as error:
            raise type(error)(f"--ckpt: {str(error).removeprefix('ckpt: ')}") from None


def parse_checkpoints(values: Sequence[str] | None):
    """``--ckpt`` values → ``None``, one ``Path`` (every estimator that uses one) or
    ``{estimator: Path}`` (``NAME=PATH`` entries; a plain path among them is ``"*"``, the
    others' default). ``ValueError`` naming ``--ckpt`` for two plain paths or an unknown
    estimator name."""
    if not values:
        return None
    from difffilter.models import estimators as known

    named, plain = {}, []
    for value in values:
        name, sep, path = str(value).partition("=")
        if not str(value).strip() or (sep and name in known.ESTIMATORS and not path.strip()):
            # (Path("") is "."; the error had said "no checkpoint file at .")
            raise ValueError(f"--ckpt {value!r}: an empty path; give a checkpoint file "
                             "(PATH or NAME=PATH)")  # fmt: skip
        if sep and name in known.ESTIMATORS:
            if name in named:  # (the first was dropped without a word)
                raise ValueError(
                    f"--ckpt: {name} is given twice ({named[name]} and {path}): one checkpoint "
                    "per estimator in one evaluation; compare two of one kind in two "
                    "evaluations with their own --out, or one as pf_nn_ekf=… if trained by EKF"
                )
            named[name] = Path(path)
        elif sep and not Path(value).exists() and "/" not in name:
            raise ValueError(
                f"--ckpt {value}: {name!r} is not a registered estimator nor a file; "
                f"estimators: {', '.join(sorted(known.ESTIMATORS))}"
            )
        else:
            plain.append(Path(value))
    if len(plain) > 1:
        raise ValueError(
            "--ckpt: one checkpoint for every estimator at most; give the others as NAME=PATH"
        )
    if not named:
        return plain[0]
    return {**named, **({"*": plain[0]} if plain else {})}


def _checkpoint_paths(ckpt) -> list[tuple[str, Path]]:
    """``[(how it was given, path)]`` of a parsed ``--ckpt``."""
    if ckpt is None:
        return []
    if isinstance(ckpt, dict):
        return [(str(p) if n == "*" else f"{n}={p}", Path(p)) for n, p in ckpt.items()]
    return [(str(ckpt), Path(ckpt))]


def check_checkpoint_fits(ckpt, names: Sequence[str]) -> None:
    """``ValueError`` (one line, naming ``--ckpt``) if a checkpoint's card says it was
    trained on a scenario family none of ``names`` belongs to: no estimator could use it,
    and a report without it would look like one that used it."""
    from difffilter.models import registry
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    families = sorted({registry.get(n).family for n in names})
    for given, path in _checkpoint_paths(ckpt):
        card = load_estimator_checkpoint(path)[1]
        if card.scenario_family is not None and card.scenario_family not in families:
            what = (f"{names[0]} is a {families[0]} scenario" if len(names) == 1 else
                    f"the {len(names)} scenarios evaluated are {'/'.join(families)} ones")  # fmt: skip
            raise ValueError(
                f"--ckpt {given} was trained on {card.scenario_family} scenarios (its card), "
                f"and {what}: none of their estimators can use it"
            )


def _note_training_plants(ckpt, names: Sequence[str]) -> None:
    """Say on stderr where a checkpoint runs on a scenario of its family whose plant is not
    the one it was trained on (:mod:`difffilter.models.plant_match`): a note, not an error."""
    from difffilter.models.plant_match import training_plant_notes

    for line in training_plant_notes(_checkpoint_paths(ckpt), names):
        print(line, file=sys.stderr)
    for line in _own_checkpoint_notes(ckpt, names):
        print(line, file=sys.stderr)


def _own_checkpoint_notes(ckpt, names: Sequence[str]) -> list[str]:
    """The notes of :func:`_note_training_plants` for the scenarios' own checkpoints, which
    their learned estimators load where ``--ckpt`` gives no default (a scenario's network
    trained on another plant of its family had run without the note ``--ckpt`` gets)."""
    from difffilter.models import registry
    from difffilter.models.estimators import split_checkpoints
    from difffilter.models.plant_match import training_plant_notes

    if split_checkpoints(ckpt)[0] is not None:  # --ckpt's own, noted above
        return []
    own: dict[Path, list[str]] = {}
    for name in names:
        path = registry.get(name).shipped_checkpoint()
        if path is not None:
            own.setdefault(path, []).append(name)
    return [line for path, sharing in own.items()
            for line in training_plant_notes(
                [(f"{registry.get(sharing[0]).checkpoint} (the scenario's own, no --ckpt)",
                  path)], sharing, flag="")]  # fmt: skip


def _launch(devices: int, argv: list[str]) -> int:
    """Run ``difffilter-eval`` in ``devices`` spawned CPU processes of one gloo group (a
    file rendezvous in a temporary folder); each process writes its share of the reports,
    rank 0 the leaderboard. Returns the exit code of the first process that failed on its
    own (:func:`_join_workers`), else 0.

    Plain ``torch.multiprocessing``: a spawned process imports only what the evaluation
    needs (Lightning's launcher cost each process about 5 s of imports)."""
    import tempfile

    import torch.multiprocessing as mp

    with tempfile.TemporaryDirectory(prefix="difffilter-eval-") as folder:
        store = Path(folder) / "rendezvous"
        context = mp.start_processes(_worker, args=(devices, f"file://{store}", argv),
                                     nprocs=devices, start_method="spawn", join=False)  # fmt: skip
        try:
            return _join_workers(context)
        finally:  # (an interrupt: the workers got it too; none outlives the command)
            for process in context.processes:
                if process.is_alive():
                    process.terminate()
                process.join()


#: A worker's exit code where a gather failed because another worker had left
#: (:class:`~difffilter.eval.suite.PeerLost`): that one failed, and says why.
PEER_LOST = 75
#: Seconds the other workers get to end on their own after one failed, before they are
#: stopped (a peer waiting in a gather ends at once; one still computing is stopped).
FAILURE_GRACE_S = 10.0


def _join_workers(context, grace_s: float = FAILURE_GRACE_S) -> int:
    """Wait for the workers of ``context``; the exit code of the first that failed on its
    own, its traceback printed where it raised one (its own error line was printed by it),
    else 0. A worker that failed because a peer had left (:data:`PEER_LOST`) is not
    reported: ``torch.multiprocessing``'s join had reported whichever worker it saw first,
    so the peer's gloo traceback and exit code 1 could stand for another's one-line error
    and exit code 2 (a CLI trial: 3 runs of 8)."""
    import multiprocessing.connection
    import pickle
    import time

    processes = context.processes
    waiting = {process.sentinel: i for i, process in enumerate(processes)}
    failed, deadline = None, None
    while waiting:
        timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
        ready = multiprocessing.connection.wait(list(waiting), timeout=timeout)
        if not ready:  # the grace is over: the others are stopped (_launch)
            break
        for sentinel in ready:
            i = waiting.pop(sentinel)
            processes[i].join()
            if processes[i].exitcode not in (0, PEER_LOST) and failed is None:
                failed, deadline = i, time.monotonic() + grace_s
    if failed is None:
        if any(process.exitcode == PEER_LOST for process in processes):
            print("difffilter-eval: error: the --devices processes lost each other in a "
                  "gather, none having failed on its own; rerun, or with --devices 1",
                  file=sys.stderr)  # fmt: skip
            return 1
        return 0
    code, error_file = processes[failed].exitcode, context.error_files[failed]
    if os.access(error_file, os.R_OK):  # it raised: its traceback, as one process prints it
        with open(error_file, "rb") as fh:
            print(pickle.load(fh), file=sys.stderr, end="")
        return 1
    if code < 0:  # a signal
        import signal

        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = str(-code)
        # the kernel's out-of-memory killer sends SIGKILL; a SIGTERM came from outside
        why = ("(out of memory?); rerun with --devices 1 to use less" if name == "SIGKILL"
               else "from outside the evaluation")  # fmt: skip
        print(f"difffilter-eval: error: process {failed} of --devices {len(processes)} was "
              f"killed by signal {name} {why}", file=sys.stderr)  # fmt: skip
        return 1
    return code


def _worker(rank: int, world: int, rendezvous: str, argv: list[str]) -> None:
    import torch
    import torch.distributed as dist

    from .suite import PeerLost

    if "OMP_NUM_THREADS" not in os.environ:  # the cores shared out between the processes
        threads = max(1, (os.cpu_count() or 1) // world)
        torch.set_num_threads(threads)
        os.environ["OMP_NUM_THREADS"] = str(threads)
    # a gather waits as long as the other process's share takes (the LFC online learners,
    # a family's prepare study: torch's default of 30 minutes had ended a long study as
    # "lost each other"); a process that failed is seen by the launcher, not by this wait
    dist.init_process_group("gloo", init_method=rendezvous, rank=rank, world_size=world,
                            timeout=datetime.timedelta(days=7))  # fmt: skip
    from difffilter.interrupts import sigterm_as_interrupt

    try:
        # SIGTERM (how the launcher stops its workers) as an interrupt, so that a file
        # being written is removed, not left as a stray .partial (an interrupts trial)
        with sigterm_as_interrupt():
            code = _main([*argv, "--devices", "1"] + (["--no-progress"] if rank else []))
    except KeyboardInterrupt:  # the launching process says it, once
        code = 130
    except PeerLost:  # another process failed and says why: quietly
        code = PEER_LOST
    finally:
        dist.destroy_process_group()
    if code:
        raise SystemExit(code)


#: The files an evaluation writes at the top of ``--out`` (a folder by one of these names
#: failed the evaluation after its suites had run).
TOP_FILES = ("leaderboard.md", "leaderboard.json", "leaderboard.png", "acceptance.md",
             "robustness.md", "robustness.json")  # fmt: skip
#: The folders it writes there (a file by one of these names failed it the same way: the
#: leaderboard's TensorBoard events, after every suite and report).
TOP_FOLDERS = ("tb_leaderboard",)
#: What a scenario's report writes in ``<out>/<scenario>/`` (:func:`~difffilter.eval.report.
#: write_report`): a folder named metrics.json, or a file named tb, failed the evaluation
#: after its suite had run, with a traceback (a docs trial).
SCENARIO_FILES, SCENARIO_FOLDERS = ("metrics.json", "report.md"), ("tb",)


def check_output_folder(out: Path, scenarios: Sequence[str] = ()) -> None:
    """Create ``out`` and prove it writable, with no folder where a file will go and no
    file where a folder will go (a scenario's, ``tb_leaderboard``, what the scenarios'
    families write there: :attr:`~difffilter.eval.report.FamilyReport.writes`);
    ``ValueError`` naming ``--out`` otherwise."""
    from difffilter.models import registry

    from .report import INCOMPLETE, family_report

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out: {out} exists and is not a folder")
    files = dict.fromkeys(TOP_FILES, "the evaluation writes a file there")
    folders = dict.fromkeys(TOP_FOLDERS, "the evaluation writes a folder there")
    for family in dict.fromkeys(registry.get(name).family for name in scenarios):
        for path in family_report(family).writes:
            kind = folders if path.endswith("/") else files
            kind[path.rstrip("/")] = (
                f"the {family} family writes a {'folder' if kind is folders else 'file'} there"
            )
    # a scenario named like what the evaluation writes at the top of --out: its folder
    # would be that file (the study ran, then failed), or the leaderboard's clean-up of
    # tb_leaderboard/ removed the scenario's own events (a red-team trial)
    taken = {path.split("/")[0]: why for path, why in (files | folders).items()}
    taken |= {INCOMPLETE: "it marks an unfinished evaluation or robustness study with a file "
                          "of that name",
              LOCK_FILE: "it holds a lock file of that name"}  # fmt: skip
    for name in scenarios:
        if name in taken:
            raise ValueError(
                f"scenario {name!r}: its reports go in {out / name}/, and {taken[name]}: "
                "give the scenario another name"
            )
    for name in scenarios:
        files |= {f"{name}/{f}": f"scenario {name}'s report writes a file there"
                  for f in SCENARIO_FILES}  # fmt: skip
        folders |= {f"{name}/{f}": f"scenario {name}'s report writes a folder there"
                    for f in SCENARIO_FOLDERS}  # fmt: skip
    for name, why in files.items():
        if (out / name).is_dir():
            raise ValueError(f"--out: {out / name} is a folder; {why}")
    folders |= {
        name: f"scenario {name}'s reports go in a folder of that name" for name in scenarios
    }
    for name, why in folders.items():
        if (out / name).exists() and not (out / name).is_dir():
            raise ValueError(f"--out: {out / name} is a file; {why}")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".difffilter-write-check-{os.getpid()}"  # one per process (--devices)
        probe.write_text("", encoding="utf-8")
        probe.unlink()
    except OSError as exc:
        raise ValueError(f"--out: cannot write to {out} ({exc.strerror or exc})") from None


#: The file in ``--out`` an evaluation holds locked while it writes there
#: (:func:`hold_output_folder`); it stays, the lock goes with the process.
LOCK_FILE = ".difffilter.lock"


def _remove_if_nothing_written(out: Path) -> None:
    """Remove ``out``, made by a study that was then refused, where nothing but its lock
    file was written into it (checks made after the folder was held, a threat set's or a
    checkpoint's, had left an empty ``--out`` holding ``.difffilter.lock``: an evaluation
    trial)."""
    try:
        if {p.name for p in out.iterdir()} <= {LOCK_FILE}:
            (out / LOCK_FILE).unlink(missing_ok=True)
            out.rmdir()
    except OSError:  # (another process writing there now, or no folder at all: left as is)
        pass


@contextlib.contextmanager
def hold_output_folder(out: Path) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``<out>/.difffilter.lock`` (``out`` exists) while an
    evaluation writes into ``out``; ``ValueError`` naming ``--out`` where another process
    holds it: two evaluations into one folder at once had both exited 0, one's metrics.json
    beside both's TensorBoard events. A no-op without ``fcntl`` (Windows) or where the file
    system refuses locks."""
    try:
        import fcntl
    except ImportError:  # not POSIX
        yield
        return
    path = Path(out) / LOCK_FILE
    try:
        handle = open(path, "a+")  # (not truncated: the holder's process id is in it)
    except OSError as exc:
        raise ValueError(f"--out: cannot write {path} ({exc.strerror or exc})") from None
    with handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip()
            which = f" (process {holder})" if holder.isdigit() else ""
            raise ValueError(
                f"--out {out}: another difffilter-eval{which} is writing into this folder; "
                "wait for it to end, or give another --out"
            ) from None
        except OSError:  # a file system without locks (some network ones): as before
            yield
            return
        handle.seek(0)
        handle.truncate()
        handle.write(f"{os.getpid()}\n")
        handle.flush()
        yield


def main(argv: Sequence[str] | None = None) -> int:
    """The command line (:func:`build_parser`); an interrupt (Ctrl-C) ends it with one line
    and exit code 130, SIGTERM with one line and 143, not a traceback from wherever the
    study was (a CLI trial) or, for SIGTERM, silently."""
    from difffilter.interrupts import (
        console_output_tolerant,
        reader_left,
        sigterm_as_interrupt,
        stop_words,
    )

    console_output_tolerant()
    try:
        with sigterm_as_interrupt():
            return _main(argv)
    except KeyboardInterrupt as exc:
        what, code = stop_words(exc)
        print(f"difffilter-eval: {what}: the reports under --out may be incomplete; "
              "rerun the same command to evaluate again", file=sys.stderr)  # fmt: skip
        return code
    except BrokenPipeError:  # `… | head`: the reader left after the reports were written;
        # a traceback and exit 1 had read as a failed run under pipefail (an interrupts trial)
        reader_left()
        return 0


def _main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)  # --help, usage errors before heavy imports
    if unknown:
        hint = ""
        if any(a.split("=")[0] in ("--device", "--gpu", "--cuda") for a in unknown):
            hint = (" (the evaluation runs on the CPU; --devices N is the number of CPU "
                    "processes that share each scenario's estimators)")  # fmt: skip
        parser.error(f"unrecognized arguments: {' '.join(unknown)}{hint}")
    if args.scenario_option is not None:
        if args.scenario not in (None, args.scenario_option):
            parser.error(
                f"two scenarios given: {args.scenario!r} and --scenario {args.scenario_option!r}"
            )
        args.scenario = args.scenario_option
    from difffilter._imports import import_plugin
    from difffilter.models import registry

    for module in args.imports:  # (each worker of --devices imports them too: it reruns main)
        try:
            import_plugin(module, f"--import {module}")
        except ValueError as exc:
            parser.error(str(exc))
    if args.list:
        shown = registry.all_scenarios()
        if args.scenario in ("all", "robustness"):  # what that name runs: the headline ones
            shown = [s for s in shown if s.name in registry.names(headline_only=True)]
        elif args.scenario in registry.families():  # the family's every scenario
            shown = [s for s in shown if s.family == args.scenario]
        elif args.scenario is not None:  # (it was ignored: the whole list, without a word)
            parser.error(f"--list {args.scenario}: give a family ({', '.join(registry.families())}) "
                         "or all to list their scenarios, or --list alone for every one")  # fmt: skip
        for s in shown:
            print(f"{s.name:28s} [{s.family}] {s.description}")
        print(f"\nalso: all (every headline scenario), robustness (their threats), and each "
              f"family's headline scenarios by its name: {', '.join(registry.families())}")  # fmt: skip
        return 0
    if not args.scenario:
        parser.error("a scenario name is required (or --list)")
    with contextlib.ExitStack() as held:  # the lock on --out, till the command ends
        return _study(args, argv, held)


def _study(args, argv: Sequence[str] | None, held: contextlib.ExitStack) -> int:
    """The evaluation (or robustness study) ``args`` ask for, ``--out`` locked into ``held``
    (:func:`hold_output_folder`); its exit code."""
    from difffilter.runtime import tune_cpu_allocator

    from .suite import process_group  # the suite (torch) only for a study

    tune_cpu_allocator()
    created = not Path(args.out).exists()  # (a refusal removes the folder it made, below)
    try:
        names = resolve_scenarios(args.scenario)
        args.ckpt = parse_checkpoints(args.ckpt)
        check_arguments(runs=args.runs, ckpt=args.ckpt, devices=args.devices,
                        calibration_runs=args.calibration_runs, seed=args.seed,
                        add_estimators=args.add_estimators,
                        estimators=args.estimators)  # fmt: skip
        if args.far is None and args.calibration_runs is not None:
            raise ValueError("--calibration-runs with --far off: nothing is calibrated")
        check_checkpoint_fits(args.ckpt, names)
        if process_group()[1] == 1:  # said once: by the launching process, not each worker
            _note_training_plants(args.ckpt, names)
        check_scenario_estimators(names)
        check_family_options(args.option, names)
        threats = args.threats or ("all" if args.scenario == "robustness" else None)
        if args.threat_set is not None and threats is None:
            raise ValueError("--threat-set names the threats of --threats: give --threats too")
        # before any work, not after the evaluation; after the other checks, so that a run
        # they refuse leaves no empty --out behind
        check_output_folder(args.out, names)
        if process_group()[1] == 1:  # (a --devices worker: its launching process holds it)
            held.enter_context(hold_output_folder(args.out))
        if threats is not None:
            return _robustness(names, threats, args)
        if args.devices > 1:  # checked here; the workers run the rest
            code = _launch(args.devices, list(sys.argv[1:] if argv is None else argv))
            if code != 0 and created:  # (a worker's refusal had left --out with its lock
                _remove_if_nothing_written(Path(args.out))  # alone, as one process does not)
            return code
        results = evaluate(
            names,
            ckpt=args.ckpt,
            runs=args.runs,
            out=args.out,
            seed=args.seed,
            progress=not args.no_progress,
            family_options=dict(args.option or ()),
            add_estimators=args.add_estimators,
            estimators=args.estimators,
            far=args.far,
            calibration_runs=args.calibration_runs,
        )
    except (ValueError, FileNotFoundError) as exc:
        if created:
            _remove_if_nothing_written(Path(args.out))
        print(f"difffilter-eval: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a report not written (a full disk): one line, not a traceback
        print(f"difffilter-eval: error: {_write_error(exc, args.out)}", file=sys.stderr)
        return 2
    if process_group()[0] > 0:
        return 0
    print("\n" + (args.out / "leaderboard.md").read_text(encoding="utf-8"))
    if (summary := args.out / "acceptance.md").is_file():
        print(summary.read_text(encoding="utf-8"))
    elif args.far is None:  # (a docs trial looked for the summary and found no word why)
        print("note: --far off: nothing calibrated, so no acceptance.md (the acceptance judges "
              "every estimator at one calibrated false-alarm rate)")  # fmt: skip
    unused = [n for n, doc in results.items() if not (doc.get("checkpoint") or {}).get("used_by")]
    given = args.ckpt.get("*") if isinstance(args.ckpt, dict) else args.ckpt
    if given is not None and unused:  # the checkpoint for every estimator, unused somewhere
        print(f"note: --ckpt {given} is used by no estimator of {', '.join(unused)}")
    _say_shipped(results)
    print(
        f"reports written under {args.out}/ (<scenario>/report.md); open the TensorBoard "
        f"logs with: tensorboard --logdir {args.out}"
    )
    if not any(doc.get("estimators") for doc in results.values()):
        # (a docs trial: every estimator asked for was skipped, and the command said so only
        # in a file and exited 0, so a script took the empty reports for results)
        print("difffilter-eval: error: no estimator ran (each one's reason is listed under "
              "\"Not run\" above)", file=sys.stderr)  # fmt: skip
        return 1
    return 0


def _write_error(exc: OSError, out: Path) -> str:
    """The line of an ``OSError`` met during a study: the file under ``out`` it could not
    write (the report writers name theirs, :func:`~difffilter.models.atomic_write.write_atomically`) and
    the reason; another file's, or no file's, as the error names it."""
    reason = exc.strerror or str(exc)
    if exc.filename is None:  # (e.g. a write of TensorBoard's names no file)
        return f"{reason} (the reports under {out} may be incomplete)"
    path = os.fsdecode(exc.filename)
    if Path(os.path.abspath(path)).is_relative_to(os.path.abspath(out)):
        return f"could not write {path}: {reason}"
    return f"{path}: {reason}"


def _say_shipped(results: dict) -> None:
    """Name the shipped checkpoints the scenarios ran without ``--ckpt`` (a user trial found
    them only in each ``report.md``), one line per file; "no --ckpt" only where none was
    given (``--ckpt NAME=PATH`` for one estimator leaves the others the shipped one)."""
    shipped: dict[tuple[str, str], list[str]] = {}
    for scenario, doc in results.items():
        ckpt = doc.get("checkpoint") or {}
        source = str(ckpt.get("source", ""))
        if source.startswith("shipped") and ckpt.get("used_by"):
            lead = "no --ckpt" if "no --ckpt given" in source else "not named by --ckpt"
            shipped.setdefault((lead, Path(ckpt["path"]).name), []).append(
                f"{scenario} ({', '.join(ckpt['used_by'])})"
            )
    for (lead, name), where in shipped.items():
        print(f"{lead}: the shipped checkpoints/{name} ran on {'; '.join(where)}")


def _robustness(names: list[str], threats, args) -> int:
    """``--threats`` / ``robustness``: the robustness study of each scenario (one per
    attack-free setting), its files under ``<out>/<scenario>/``, and the summary."""
    from difffilter.models import registry

    from .report import clear_incomplete, mark_incomplete
    from .robustness import (
        MARKER_KIND,
        load_threat_set,
        robustness_scenarios,
        run_robustness,
        write_robustness,
        write_robustness_summary,
    )

    if args.far is None:
        raise ValueError("--far off: the robustness study compares detectors at one --far")
    if args.devices > 1:
        raise ValueError("--devices: the robustness study runs in one process")
    if args.option:  # (checked, then never read: -o watermark=true ran no watermark study)
        raise ValueError(
            "--option: the robustness study (--threats) writes no scenario report, so a "
            "family's report options would go unused; drop --option, or run without --threats"
        )
    chosen = robustness_scenarios(names)
    if args.threat_set is not None and not args.threat_set.is_file():
        raise ValueError(f"--threat-set: no file {args.threat_set}")
    families = sorted({registry.get(n).family for n in chosen})
    if args.threat_set is not None and len(families) > 1:
        # (the four-tank set's 0.005 cm ramp went to the LFC, robot and tracking plants)
        raise ValueError(
            f"--threat-set: one file's threats for the scenarios of {len(families)} families "
            f"({', '.join(families)}); a threat set is in one plant's units: evaluate one "
            "family (e.g. difffilter-eval lfc --threats all --threat-set FILE)"
        )
    sets = {n: load_threat_set(registry.get(n), threats, path=args.threat_set)
            for n in chosen}  # errors first  # fmt: skip
    if args.estimators is not None:  # the command line's over a threat file's
        for threat_set in sets.values():
            threat_set.estimators = tuple(args.estimators)
    cache: dict = {}
    docs, incomplete = {}, None
    for name, threat_set in sets.items():
        result = run_robustness(
            registry.get(name), threat_set, runs=args.runs, seed=args.seed, far=args.far,
            add=args.add_estimators,
            calibration_runs=args.calibration_runs, checkpoint=args.ckpt,
            progress=not args.no_progress, cache=cache,
        )  # fmt: skip
        if incomplete is None:  # (the first write into --out: INCOMPLETE.md till the last)
            incomplete = mark_incomplete(
                args.out, "A robustness study into this folder", kind=MARKER_KIND
            )
        docs[name] = write_robustness(args.out / name, result)
        if args.add_estimators:
            note_skipped_additions(args.add_estimators, docs[name]["skipped"], name)
    evaluated = (args.out / "acceptance.md").is_file()  # an evaluation's, into this --out
    summary = write_robustness_summary(args.out, docs)
    if incomplete is not None:  # (an evaluation's section, left by one stopped here, stays)
        clear_incomplete(args.out, MARKER_KIND)
    print("\n" + summary.read_text(encoding="utf-8"))
    print(f"robustness reports written under {args.out}/ (<scenario>/robustness.md)")
    if evaluated:  # (it went without a word: a trial)
        print(f"note: {args.out}/leaderboard.* are now this study's, and the evaluation's "
              "acceptance.md went with the leaderboard it judged (this study's verdicts are in "
              "robustness.md); each scenario's report.md and metrics.json stay")  # fmt: skip
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
