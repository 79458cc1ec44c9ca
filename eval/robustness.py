"""The robustness report: every estimator against every threat, at one false-alarm rate.

For one scenario, with its threat set (data: ``eval/threats/<scenario>.yaml``, else
``<family>.yaml``; :func:`load_threat_set`)::

    calibration    attack-free runs of their own seed → every detector's τ_α
    attack-free    the study's runs without attack      → each estimator's RMSE₀, FPR at τ_α
    threat j       the same runs (common random numbers) under threat j, the estimators
                   keeping their own assumptions about attacks

and per estimator × threat: ``tpr_at_far`` (TPR at τ_α), ``state_error_ratio`` =
``state_rmse`` under the threat / ``RMSE₀``, and ``impact`` (the estimation error caused
before the first alarm, :mod:`~difffilter.eval.calibration`). The worst case of an
estimator is its lowest TPR, highest ratio and highest impact over the threats.

:func:`write_robustness` writes ``robustness.json`` (the metrics.json schema: its
``estimators`` are the attack-free study's metrics; ``threats``, ``cells`` and
``worst_case`` hold the rest), ``robustness.md`` and ``robustness.png`` (heat maps).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from difffilter._checks import check_positive_int
from difffilter.linalg import NumericalBreakdown
from difffilter.models.atomic_write import write_atomically, write_json_atomically
from difffilter.models.yaml_scenario import read_yaml
from difffilter.threat_distribution import threat_spec
from difffilter.threats import check_attack_fits, threat_from_dict, with_sampling_period

from .acceptance import (
    ANALYTIC,
    ROBUST_STATE_FACTOR,
    judge_robustness,
    reading_no_measurements,
    roles,
)
from .calibration import below_target_note, calibrate
from .coverage import checkpoint_of, training_coverage
from .intervals import LEVEL, RESAMPLES, robustness_intervals, threat_totals
from .provenance import software_line, software_record
from .report import (
    _network_line,
    clear_incomplete,
    format_number,
    json_safe,
    mark_incomplete,
    markdown_table,
    network_of,
    save_figure,
    share_percent,
    share_suffix,
)
from .scoring import METRICS
from .stealthy import StealthySpec, craft_threat, crafted_error, same_rate_bias
from .suite import broken_down, run_suite

__all__ = ["ThreatSet", "load_threat_set", "run_robustness", "write_robustness", "CELL_METRICS",
           "robustness_scenarios", "write_robustness_summary"]  # fmt: skip

THREAT_DIR = Path(__file__).parent / "threats"
#: When the best analytic worst-case TPR is at most this (``worst_threat_undetected``).
UNSEEN_TEXT = "2α, the top of the false-alarm band"

#: What each cell of the robustness tables holds (``state_error_ratio`` is robustness's own).
CELL_METRICS = ("tpr_at_far", "state_error_ratio", "impact", "auc", "fpr_at_far", "state_rmse",
                "attack_rmse")  # fmt: skip
#: Worst case: the lowest of these over the threats …
LOWER_IS_WORSE = ("tpr_at_far", "auc")
#: … and the highest of these.
HIGHER_IS_WORSE = ("state_error_ratio", "impact")

#: A robustness study's section of an ``INCOMPLETE.md``
#: (:func:`~difffilter.eval.report.mark_incomplete`): an evaluation's is its own.
MARKER_KIND = "robustness study"


@dataclass
class ThreatSet:
    """A scenario's threats: ``{name: attack}`` with their plain specs, and the study's size
    (``runs``: ``None`` for the scenario's; ``estimators``: ``None`` for the scenario's)."""

    threats: dict[str, Any]
    specs: dict[str, dict] = field(default_factory=dict)
    runs: int | None = None
    estimators: tuple[str, ...] | None = None
    source: str = ""

    def __post_init__(self):
        # the reports list the threats by their specs: a threat given in Python without one
        # was left out of robustness.md's list and robustness.json's "threats" (a copy: the
        # caller's mapping stays as it was given)
        if self.runs is not None:  # (0 had fallen through to the scenario's 100 runs)
            check_positive_int(self.runs, "ThreatSet.runs")
        if not self.threats:  # (the study had run and written empty tables: no verdict)
            raise ValueError("ThreatSet.threats names no threat: give {name: attack}, at least one")
        self.specs = dict(self.specs)
        for name, attack in self.threats.items():
            if name not in self.specs:
                # a threat of the library by its spec, as a file gives it (the class path
                # alone lost its fields, and training coverage read it as one's own: "held
                # out" for the very bias trained on)
                spec = threat_spec(attack)
                if spec is None:
                    kind = type(attack)
                    spec = {"kind": f"{kind.__module__}:{kind.__qualname__}"}
                self.specs[name] = spec
        extra = sorted(set(self.specs) - set(self.threats))
        if extra:
            raise ValueError(f"specs of no threat: {', '.join(extra)}; threats: "
                             f"{', '.join(self.threats)}")  # fmt: skip


def _threat_file(scenario) -> Path:
    for stem in (scenario.name, scenario.family):
        path = THREAT_DIR / f"{stem}.yaml"
        if path.is_file():
            return path
    known = sorted(p.stem for p in THREAT_DIR.glob("*.yaml"))
    raise ValueError(
        f"scenario {scenario.name!r} has no threat set (eval/threats/{scenario.name}.yaml or "
        f"{scenario.family}.yaml); threat sets exist for: {', '.join(known)}; give one of "
        "your own with --threat-set FILE.yaml (docs/threats.md)"
    )


def load_threat_set(scenario, names="all", path: str | Path | None = None) -> ThreatSet:
    """The threats of ``scenario`` from its YAML (``path`` overrides the lookup), those named
    in ``names`` (``"all"``, a sequence, or the command line's comma-separated string; an
    unknown name is an error listing the valid).

    The YAML holds ``threats: {name: {kind: …, fields}}`` (:func:`~difffilter.threats.
    threat_from_dict`), or ``threats_from: <file>`` (another file's, beside it, less those
    named in ``exclude``), and optionally ``runs`` and ``estimators``."""
    if isinstance(names, str) and names != "all":  # the command line's form: "bias,ramp"
        names = [n.strip() for n in names.split(",") if n.strip()]  # (it had read letters)
    if not isinstance(names, str):
        names = list(names)
        if not names:  # (it gave an empty study)
            raise ValueError("--threats: no threat named; give names, or all")
    path = Path(path) if path is not None else _threat_file(scenario)
    data = _read_threat_file(path)
    if "exclude" in data and "threats_from" not in data:  # (it was ignored: all ran)
        raise ValueError(f"{path}: exclude leaves out threats of threats_from's file; this file "
                         "names no threats_from: remove the threats from 'threats' instead")  # fmt: skip
    if "threats_from" in data and "threats" in data:  # (its own were dropped, unsaid)
        raise ValueError(f"{path}: give threats or threats_from, not both (threats_from takes "
                         "another file's threats whole, less those in exclude)")  # fmt: skip
    if "threats_from" in data:  # another file's threats, this file's study size
        shared_path = path.parent / str(data["threats_from"])
        if not shared_path.is_file():  # (a trial's name of a shipped set was looked for
            # beside its own file, and the error did not say where)
            raise ValueError(
                f"{path}: threats_from {data['threats_from']}: no file {shared_path} (a "
                "relative name is read beside the file that names it; the shipped threat "
                f"sets are in {THREAT_DIR}: give such a set by its path)"
            )
        shared = _read_threat_file(shared_path, origin=path)
        offered = shared.get("threats") or {}
        left_out = data.get("exclude") or ()
        if isinstance(left_out, str) or not all(isinstance(n, str) for n in left_out):
            raise ValueError(f"{path}: exclude must be a list of threat names; got {left_out!r}")
        missing = sorted(set(left_out) - set(offered))
        if missing:  # (a misspelt name excluded nothing, silently)
            raise ValueError(
                f"{path}: exclude names threat(s) {', '.join(missing)} that "
                f"{data['threats_from']} does not define; it defines: {', '.join(offered)}"
            )
        kept = {n: t for n, t in offered.items() if n not in set(left_out)}
        data = {**data, "threats": kept}
    _check_set_period(data, path, scenario)
    specs = data.get("threats") or {}
    if not isinstance(specs, dict) or not specs:
        raise ValueError(f"{path}: 'threats' must be a non-empty mapping of threat names to "
                         f"their specs; got {data.get('threats')!r}")  # fmt: skip
    named = [n for n in specs if not isinstance(n, str)]
    if named:  # (YAML reads 2: and on: as a number and true: --threats 2 crashed)
        how = ("quote it as you wrote it" if isinstance(named[0], float)  # (1e5: 100000.0)
               else f"quote it ('{named[0]}':)")  # fmt: skip
        raise ValueError(f"{path}: threat names must be text; got {named[0]!r}"
                         f"{' (YAML reads it as a number)' if isinstance(named[0], float) else ''}"
                         f": {how}")  # fmt: skip
    # (" all", "all,": the whole set, unless a threat of the set is named all)
    every = names == "all" or (names == ["all"] and "all" not in specs)
    chosen = list(specs) if every else list(names)
    if not every and "all" in chosen and "all" not in specs:  # (it was "unknown")
        raise ValueError("--threats: all stands alone (every threat of the set); got "
                         f"{','.join(chosen)}")  # fmt: skip
    unknown = [n for n in chosen if n not in specs]
    if unknown:
        raise ValueError(
            f"--threats: unknown threat(s) {', '.join(unknown)} for {scenario.name}; valid: "
            f"{', '.join(specs)} (or 'all')"
        )
    model = scenario.system()
    threats = {}
    for name in chosen:
        if not isinstance(specs[name], dict):  # (a bare "a:" had failed as "not iterable")
            raise ValueError(f"{path}: threat {name!r}: a threat is a mapping {{kind: …, "
                             f"fields}}; got {specs[name]!r}")  # fmt: skip
        try:
            spec = dict(specs[name])
            if spec.get("kind") == "stealthy":  # crafted when the study runs (eval.stealthy)
                threats[name] = StealthySpec.from_dict(spec)
            else:
                # a sinusoid's or chirp's frequency in the scenario's time unit, as its
                # YAML file's attack reads it, where the threat sets no dt of its own
                threats[name] = threat_from_dict(
                    with_sampling_period(spec, getattr(scenario, "dt", None)), model=model
                )
            _check_threat(scenario, model, threats[name])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: threat {name!r}: {exc}") from None
    estimators, runs = data.get("estimators"), data.get("runs")
    if estimators is not None:
        _check_set_estimators(estimators, path)
    if runs is not None and (isinstance(runs, bool) or not isinstance(runs, int) or runs < 1):
        # (0 read as "not given": the scenario's 100 runs ran; -3 failed naming no file)
        raise ValueError(f"{path}: runs must be an integer >= 1 (or left out: the "
                         f"scenario's); got {runs!r}")  # fmt: skip
    return ThreatSet(threats, {n: dict(specs[n]) for n in chosen}, runs,
                     None if estimators is None else tuple(estimators), str(path))  # fmt: skip


def _check_set_period(data: dict, path: Path, scenario) -> None:
    """A threat set that says its sampling period (``dt:``, its onsets, delays and slopes
    are in steps of it) runs only on scenarios of that period: ``lfc_sine_1ms`` had run
    the LFC set written for 10 ms steps, its onsets, replay and chirp ten times as early
    and its sinusoid ten times as fast, without a word."""
    period = data.get("dt")
    if period is None:
        return
    if isinstance(period, bool) or not isinstance(period, (int, float)) or not period > 0:
        raise ValueError(f"{path}: dt must be the set's sampling period in seconds (> 0); "
                         f"got {period!r}")  # fmt: skip
    own = getattr(scenario, "dt", None)
    if own is not None and not math.isclose(float(own), float(period), rel_tol=1e-9):
        raise ValueError(
            f"{path}: its threats are written for steps of dt = {period:g} s (onsets, delays "
            f"and slopes in steps of it), and {scenario.name} steps {float(own):g} s: give "
            "it a threat set of its own (--threat-set FILE.yaml, docs/threats.md)"
        )


def _check_set_estimators(estimators, path) -> None:
    """A threat set's ``estimators``: a non-empty list of registered names (a string was
    read letter by letter, "unknown estimator 'c'", and no error named the file or key)."""
    from difffilter.models import estimators as known

    if (
        not isinstance(estimators, list)
        or not estimators
        or not all(isinstance(e, str) for e in estimators)
    ):
        raise ValueError(f"{path}: estimators must be a non-empty list of estimator names "
                         f"(e.g. [chi_square_kf]); got {estimators!r}")  # fmt: skip
    for name in estimators:
        try:
            known.get(name)
        except ValueError as exc:
            raise ValueError(f"{path}: estimators: {exc}") from None


def _check_threat(scenario, model, threat) -> None:
    """Raise where ``threat`` cannot run on ``scenario`` (``model``: its system): refused
    before the study, not when its turn comes after the calibration and the threats before
    it (an adaptive threat on an open-loop scenario: a trial's third; an onset past the
    horizon, named as the scenario's own attack from inside the study)."""
    if isinstance(threat, StealthySpec):  # crafted when the study runs (eval.stealthy)
        threat.check_fits(model)
    else:
        scenario.with_threat(threat)
    # (a crafted threat: its onset only; a library threat: its widths too)
    check_attack_fits(threat, model, getattr(scenario, "steps", None))
    if getattr(threat, "conceals", False) and scenario.input_loss_schedule():
        raise ValueError(
            "a covert attack's concealment assumes its input packets arrive, and "
            f"{scenario.name} loses some (input_loss): leave it out of this scenario's "
            "study (exclude:)"
        )


#: The keys a threat-set file may hold (:func:`load_threat_set`).
THREAT_FILE_KEYS = ("threats", "threats_from", "exclude", "runs", "estimators", "dt")


def _read_threat_file(path: Path, origin: Path | None = None) -> dict:
    """A threat-set file's mapping, or a ``ValueError`` naming the file: it is missing, not
    YAML, not a mapping, or holds a key other than :data:`THREAT_FILE_KEYS` (a misspelt
    ``threatz:`` was ignored, and the threats looked empty)."""
    named = f"{origin}: threats_from {path.name}" if origin is not None else str(path)
    data = read_yaml(path, named)
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ValueError(
            f"{named}: a threat set is a mapping (threats: {{name: {{kind: …}}}}, runs, "
            f"estimators); got a {type(data).__name__}"
        )
    unknown = sorted(str(k) for k in data if k not in THREAT_FILE_KEYS)
    if unknown:
        raise ValueError(
            f"{named}: unknown key(s) {', '.join(unknown)}; a threat set holds "
            f"{', '.join(THREAT_FILE_KEYS)}"
        )
    return data


def robustness_scenarios(names) -> list[str]:
    """``names`` with one scenario per attack-free setting: the scenarios that differ only in
    their own attack (the four LFC ones) give the same robustness study, run once."""
    from difffilter.models import registry

    seen, out = set(), []
    for name in names:
        key = registry.get(name).attack_free_key()
        if key not in seen:
            seen.add(key)
            out.append(name)
    return out


@dataclass
class RobustnessResult:
    """What :func:`run_robustness` measured (module docstring)."""

    scenario: Any
    runs: int
    seed: int
    threat_set: ThreatSet
    calibration: Any
    attack_free: Any  # SuiteResult
    cells: dict[str, dict[str, dict[str, Any]]] = field(default_factory=dict)
    worst_case: dict[str, dict[str, Any]] = field(default_factory=dict)
    stealthy: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: ``{threat: {estimator: per-run totals}}`` (:func:`~.intervals.threat_totals`)
    run_totals: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: ``{threat: {"attacked_runs", "runs", "attacked_steps", "injected"}}``: what each
    #: threat did on the study's runs (:func:`_activity`)
    activity: dict[str, dict[str, Any]] = field(default_factory=dict)

    def idle(self) -> list[str]:
        """The threats that attacked no run, or injected nothing where they flagged steps:
        left out of the worst case and the acceptance (a 50 % draw that attacked none of 3
        runs was counted as a threat the learned estimator withstood)."""
        return [t for t, a in self.activity.items() if _idle(a)]

    def acting(self, table: dict[str, Any]) -> dict[str, Any]:
        """``table`` (``{threat: …}``) without the :meth:`idle` threats."""
        idle = set(self.idle())
        return {t: v for t, v in table.items() if t not in idle}


def run_robustness(
    scenario,
    threat_set: ThreatSet,
    *,
    runs: int | None = None,
    seed: int = 0,
    far: float = 0.01,
    calibration_runs: int | None = None,
    add=(),
    checkpoint=None,
    progress: bool = True,
    cache: dict | None = None,
) -> RobustnessResult:
    """Calibrate, run attack-free, run every threat of ``threat_set`` (module docstring):
    ``runs`` (default the threat set's, else the scenario's), the threat set's estimators
    and ``add``, every threshold at ``far`` from ``calibration_runs`` attack-free runs."""
    from tqdm.auto import tqdm

    model = scenario.system() if threat_set.threats else None
    for name, threat in threat_set.threats.items():  # refused before any run, not at its turn
        try:  # (a ThreatSet made in Python was not checked as a file's is)
            _check_threat(scenario, model, threat)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"threat {name!r}: {exc}") from None
    # a size given is checked, not replaced (0 and False had fallen through to the defaults
    # without a word; -3 had failed in calibrate() as "study_runs", not an argument here)
    for name, size in (("runs", runs), ("calibration_runs", calibration_runs)):
        if size is not None:
            check_positive_int(size, name)
    runs = runs or threat_set.runs or scenario.runs
    targets = [t.against for t in threat_set.threats.values() if isinstance(t, StealthySpec)]
    add = tuple(dict.fromkeys((*add, *targets)))  # a crafted attack's detector is calibrated
    kwargs = dict(runs=runs, estimators=threat_set.estimators, add=add,
                  checkpoint=checkpoint, progress=progress, cache=cache)  # fmt: skip
    cal = calibrate(scenario, far=far, seed=seed, study_runs=runs,
                    **{**kwargs, "runs": calibration_runs or runs})  # fmt: skip
    free = run_suite(scenario.with_threat(None), seed=seed, calibration=cal, **kwargs,
                     label=f"{scenario.name}: attack-free")  # fmt: skip
    result = RobustnessResult(scenario, runs, seed, threat_set, cal, free)
    bar = tqdm(threat_set.threats.items(), desc=f"{scenario.name} threats", disable=not progress)
    for name, threat in bar:
        bar.set_postfix_str(name)
        if isinstance(threat, StealthySpec):
            threat = _crafted(result, name, threat, progress, checkpoint)
        suite = run_suite(scenario.with_threat(threat), seed=seed, calibration=cal, **kwargs,
                          label=f"{scenario.name}: {name}")  # fmt: skip
        result.cells[name] = {
            est: _cell(m, free.metrics.get(est, {})) for est, m in suite.metrics.items()
        }
        broke = {est: why for est, why in broken_down(suite.skipped).items() if est in free.metrics}
        result.cells[name].update({est: _broken_cell(why, est in cal.thresholds)
                                   for est, why in broke.items()})  # fmt: skip
        # ran attack-free, skipped under this threat (an adaptive threat meets only the
        # estimators with a loop of their own): a cell that says so, and no worst case over
        # the other threats alone (kf's read 29 where the same observer's was 290)
        result.cells[name].update({est: _not_run_cell(why) for est, why in suite.skipped.items()
                                   if est in free.metrics and est not in result.cells[name]})  # fmt: skip
        result.run_totals[name] = threat_totals(suite, roles(suite.metrics))
        result.run_totals[name].update({est: _broken_totals(suite.traj, est in cal.thresholds)
                                        for est in broke})  # fmt: skip
        result.activity[name] = _activity(suite.traj)
        if name in result.idle():
            warnings.warn(f"{scenario.name}: threat {name!r} {_idle_text(result.activity[name])}: "
                          "it is left out of the worst case and the acceptance", stacklevel=2)  # fmt: skip
    result.worst_case = _worst_cases(result.acting(result.cells))
    return result


def _activity(traj) -> dict[str, Any]:
    """What a threat did on a study's trajectories: the runs and steps it flagged as
    attacked, and whether it injected anything non-zero there."""
    flags = traj.flags
    injected = bool(flags.any()) and bool((traj.attack[flags] != 0).any())
    return {"attacked_runs": int(flags.any(-1).sum()), "runs": int(flags.shape[0]),
            "attacked_steps": int(flags.sum()), "injected": injected}  # fmt: skip


def _idle(activity: dict[str, Any]) -> bool:
    """Whether a threat of :func:`_activity` did not act: no run attacked, or nothing
    injected where it flagged steps."""
    return not (activity["attacked_runs"] and activity["injected"])


def _idle_text(activity: dict[str, Any]) -> str:
    if not activity["attacked_runs"]:
        return f"attacked none of the {activity['runs']} runs"
    return (f"flagged {activity['attacked_steps']} steps of {activity['attacked_runs']} runs "
            "as attacked but injected nothing there (a value of 0)")  # fmt: skip


def _crafted(result: RobustnessResult, name: str, spec: StealthySpec, progress: bool,
             checkpoint=None):  # fmt: skip
    """Craft stealthy threat ``name`` against its detector, and compare it on the study's
    runs with the weakest constant bias that alarms as often (``result.stealthy[name]``)."""
    sc, cal = result.scenario, result.calibration
    common = dict(seed=result.seed, checkpoint=checkpoint)
    skipped = (result.attack_free.skipped or {}).get(spec.against)
    if spec.against not in cal.thresholds and skipped:  # (it had said "not calibrated in this
        # study: add it to the threat set's estimators", where it was and did not run)
        raise ValueError(f"threat {name!r} is crafted against {spec.against!r}, which does not "
                         f"run in this study: {skipped}")  # fmt: skip
    try:
        attack, report = craft_threat(name, spec, sc, cal, progress=progress,
                                      study_runs=result.runs, **common)  # fmt: skip
        tau = report["threshold"]
        judged = crafted_error(sc, spec.against, attack, tau, runs=result.runs, **common)
        bias = same_rate_bias(sc, spec.against, judged["alarm_rate"], tau, onset=spec.onset,
                              entries=spec.entries, runs=result.runs, **common)  # fmt: skip
    except NumericalBreakdown as exc:  # (a threat that cannot be made: not one estimator's skip)
        raise ValueError(f"threat {name!r}: {spec.against!r}, which it is crafted against, "
                         f"broke down while it was crafted and judged: {exc}") from exc  # fmt: skip
    report.update(crafted=judged, same_rate_bias=bias, study_runs=result.runs,
                  error_ratio_to_bias=judged["state_error"] / bias["state_error"],
                  # the attack itself, so that it can be judged again without crafting it
                  # anew (a trial re-ran the crafting for it): CraftedAttack(values, onset,
                  # entries=entries)
                  values=attack.values.tolist(), onset=attack.onset,
                  entries=None if attack.entries is None else list(attack.entries))  # fmt: skip
    result.stealthy[name] = report
    return attack


def _broken_cell(why: str, detects: bool) -> dict[str, Any]:
    """The cell of an estimator that ran attack-free and broke down under a threat
    (:class:`~difffilter.linalg.NumericalBreakdown`): its state error counts as diverged in
    the worst case (:func:`_worst_cases`) and, where it detects at a calibrated threshold,
    it raised no alarm, so a TPR of 0 and an impact counted as diverged too; left out, it
    made its worst case over the other threats alone."""
    return {**dict.fromkeys(CELL_METRICS), "tpr_at_far": 0.0 if detects else None,
            "broke_down": why}  # fmt: skip


def _not_run_cell(why: str) -> dict[str, Any]:
    """The cell of an estimator that ran attack-free and was skipped under a threat (``why``):
    no number, and no worst case of any metric (:func:`_worst_cases`: ``<metric>_not_run``)."""
    return {**dict.fromkeys(CELL_METRICS), "not_run": why}


def _broken_totals(traj, detects: bool) -> dict[str, Any]:
    """The per-run totals of :func:`_broken_cell` for the intervals
    (:func:`~difffilter.eval.intervals.robustness_intervals`): no hit on any attacked step
    where it detects, and ``broke_down`` (its state check holds in no resample)."""
    totals: dict[str, Any] = {"broke_down": True}
    if detects:
        attacked = traj.flags.sum(1).double()
        totals.update(hits=attacked.new_zeros(attacked.shape), attacked=attacked)
    return totals


def _cell(m: dict, free: dict) -> dict[str, Any]:
    """One estimator's numbers under one threat; ``diverged``: the metrics that are not
    finite (written ``null``, they had read "—" in the tables, as a number that does not
    apply)."""
    cell = {k: m.get(k) for k in CELL_METRICS if k != "state_error_ratio"}
    base = free.get("state_rmse")
    ratio = None
    if base and m.get("state_rmse") is not None and base > 0:
        ratio = m["state_rmse"] / base
    cell["state_error_ratio"] = ratio
    diverged = [k for k, v in cell.items() if isinstance(v, float) and not math.isfinite(v)]
    if diverged:
        cell["diverged"] = diverged
    return cell


def _worst_cases(cells) -> dict[str, dict[str, Any]]:
    """Each estimator's worst value of each metric over the threats, with the threat; of
    threats tied at it, the first by name (not by the order ``--threats`` listed them), and
    ``<metric>_tied`` the number of the others (absent where none ties).

    A state error or impact that is not finite (an estimate that diverged to NaN or inf
    under a threat) is the worst there is: ``inf``, with ``<metric>_diverged`` set (it was
    passed over, so an estimator that diverged looked more robust than one that did not:
    13.7 against 30 in a trial), and so is one that broke down (:func:`_broken_cell`:
    ``<metric>_broke_down`` set too). A TPR or AUC that is not finite (no attacked step) is
    no worst case, nor is a missing value."""
    worst: dict[str, dict[str, Any]] = {}
    for threat, row in sorted(cells.items()):
        for est, cell in row.items():
            w = worst.setdefault(est, {})
            if cell.get("not_run"):  # no number there: no worst case (the first such threat)
                for key in LOWER_IS_WORSE + HIGHER_IS_WORSE:
                    if not w.get(f"{key}_not_run"):
                        w[key], w[f"{key}_threat"], w[f"{key}_not_run"] = None, threat, True
                        for flag in ("tied", "diverged", "broke_down"):
                            w.pop(f"{key}_{flag}", None)
                continue
            broke = bool(cell.get("broke_down"))
            detects = cell.get("tpr_at_far") is not None  # (a broken cell's: where it detects)
            for key in LOWER_IS_WORSE + HIGHER_IS_WORSE:
                value = cell.get(key)
                if broke and (key == "state_error_ratio" or (key == "impact" and detects)):
                    value = math.inf
                if value is None or w.get(f"{key}_not_run"):
                    continue
                if not math.isfinite(value):
                    if key in LOWER_IS_WORSE:
                        continue
                    if not w.get(f"{key}_diverged"):  # the first threat by name it diverged on
                        w[key], w[f"{key}_threat"], w[f"{key}_diverged"] = math.inf, threat, True
                        w.pop(f"{key}_tied", None)  # (a tie of finite values had stayed)
                        if broke:
                            w[f"{key}_broke_down"] = True
                    else:  # more threats it diverged on
                        w[f"{key}_tied"] = w.get(f"{key}_tied", 0) + 1
                    continue
                sign = -1 if key in LOWER_IS_WORSE else 1
                if key not in w or sign * value > sign * w[key]:
                    w[key], w[f"{key}_threat"] = value, threat
                    w.pop(f"{key}_tied", None)
                elif value == w[key] and not w.get(f"{key}_diverged"):
                    # more threats at the worst: the one named is only the first by name (a
                    # user trial read a TPR of 0 on every threat as the first one's alone)
                    w[f"{key}_tied"] = w.get(f"{key}_tied", 0) + 1
    return worst


def _worst_text(worst: dict[str, Any], key: str) -> str:
    """A worst case for a table: ``value (threat)``, ``diverged (threat)`` where the
    estimate was not finite (robustness.json's ``null`` with ``<key>_diverged``), ``—``
    where there is none."""
    threat = worst.get(f"{key}_threat")
    tied = worst.get(f"{key}_tied")
    more = f"; {tied} more tied" if tied else ""
    if worst.get(f"{key}_not_run"):
        return f"not run ({threat})"
    if worst.get(f"{key}_broke_down"):
        return f"broke down ({threat}{more})"
    if worst.get(f"{key}_diverged"):
        return f"diverged ({threat}{more})"
    value = worst.get(key)
    return "—" if value is None else f"{format_number(value, 3)} ({threat}{more})"


def write_robustness(out: str | Path, result: RobustnessResult) -> dict[str, Any]:
    """Write ``robustness.json``, ``robustness.md`` and ``robustness.png`` under ``out``
    (created), each whole or not at all, ``INCOMPLETE.md`` there while they are written
    (:func:`~difffilter.eval.report.mark_incomplete`, its ``robustness study`` section, which
    leaves an evaluation's alone); returns the JSON content."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sc, free = result.scenario, result.attack_free
    doc = json_safe({
        "scenario": sc.name, "runs": result.runs, "steps": sc.steps, "seed": result.seed,
        # (the leaderboard's delays are coloured by it: its rows after a robustness study
        # had dt_s null, a review)
        "dt_s": sc.dt,
        "units": {name: m.unit for name, m in METRICS.items()}, "paper": {},
        "scenario_units": {"state": sc.state_unit, "attack": sc.attack_unit},
        "estimators": {n: {**dict.fromkeys(METRICS), **m} for n, m in free.metrics.items()},
        "far": result.calibration.summary(), "threat_set": result.threat_set.source,
        "threats": result.threat_set.specs, "cells": result.cells,
        "worst_case": result.worst_case, "skipped": dict(free.skipped),
        "stealthy": result.stealthy,
        "checkpoint": free.checkpoint,
        "estimator_roles": roles(free.metrics),
        "reads_no_measurements": reading_no_measurements(free.metrics),
        "network": network_of(sc),
        "software": software_record(),
    })  # fmt: skip
    doc["threat_activity"] = result.activity
    # which threats read the true state x (Attack.reads_state: an insider, who knows the noise)
    doc["threat_reads_state"] = {name: bool(getattr(attack, "reads_state", True))
                                 for name, attack in result.threat_set.threats.items()}  # fmt: skip
    # ... and which read the estimator's output (Attack.reads_view: adaptive, in a closed loop)
    doc["threat_reads_view"] = {name: bool(getattr(attack, "reads_view", False))
                                for name, attack in result.threat_set.threats.items()}  # fmt: skip
    acceptance = judge_robustness(result.acting(doc["cells"]), doc["estimator_roles"],
                                  result.calibration.far, blind=doc["reads_no_measurements"])  # fmt: skip
    intervals = robustness_intervals(result.acting(result.run_totals), doc["estimator_roles"],
                                     runs=result.runs, seed=result.seed)  # fmt: skip
    model = sc.system() if acceptance else None  # for threat kinds that read it
    for name, judged in acceptance.items():
        judged["training"] = training_coverage(checkpoint_of(name, free), doc["threats"], model,
                                               own=sc.attack_model(), dt=getattr(sc, "dt", None))  # fmt: skip
        mine = intervals.get(name, {})
        judged["worst_tpr_interval"] = mine.get("worst_tpr")
        for threat, check in judged["state"].items():
            check["interval"] = mine.get("state", {}).get(threat)
    doc["acceptance"] = json_safe(acceptance)
    mark_incomplete(
        out, f"Writing the robustness study of {sc.name} into this folder", kind=MARKER_KIND
    )
    write_json_atomically(out / "robustness.json", doc)
    write_atomically(out / "robustness.md", _markdown(doc, sc))
    _heatmap(out / "robustness.png", doc, sc)
    clear_incomplete(out, MARKER_KIND)  # (an evaluation's section, left by one stopped here, stays)
    return doc


_TITLES = {
    "tpr_at_far": "Detection rate at the calibrated threshold (`tpr_at_far`, higher is better)",
    "state_error_ratio": "State error under the threat / attack-free (`state_error_ratio`, "
    "lower is better)",
    "impact": "Estimation error caused before the first alarm (`impact` [{state_unit}], lower "
    "is better)",
}


def _markdown(doc: dict, sc) -> str:
    far, threats = doc["far"], list(doc["threats"])
    ests = list(doc["estimators"])
    parts = [
        f"# Robustness: {doc['scenario']}\n\n{sc.description}\n",
        f"{doc['runs']} runs × {doc['steps']} steps, seed {doc['seed']}. Every detector is "
        f"judged at one false-alarm rate, {100 * far['target']:g} %: its threshold comes from "
        f"{far['calibration_runs']} attack-free runs of their own seed "
        f"({far['calibration_seed']}). Every threat runs on the same plant noise as the "
        "attack-free column (common random numbers); the estimators keep their own "
        "assumptions about attacks. Threat set: "
        + (f"`{Path(doc['threat_set']).name}`.\n" if doc.get("threat_set")
           else "built in Python (no file).\n")
        + _network_line(doc.get("network"))
        + software_line(doc.get("software")),
    ]  # fmt: skip
    below = below_target_note(far)
    if below:
        parts.append(f"{below}\n")
    broke = broken_down(doc.get("skipped") or {})
    not_run = {k: v for k, v in (doc.get("skipped") or {}).items() if k not in broke}
    if not_run:  # (a trial's threat set named `kf` on a nonlinear plant: unsaid)
        parts.append("Not run on this scenario: " + "; ".join(
            f"`{name}` ({why})" for name, why in not_run.items()) + ".\n")  # fmt: skip
    if broke:
        parts.append("Broke down on the attack-free runs (no cells): " + "; ".join(
            f"`{name}` ({why})" for name, why in broke.items()) + ".\n")  # fmt: skip
    idle = {t: a for t, a in (doc.get("threat_activity") or {}).items() if _idle(a)}
    if idle:
        parts.append("Left out of the worst case and the acceptance, as threats that did not act "
                     "on these runs: " + "; ".join(f"`{t}` {_idle_text(a)}" for t, a in idle.items())
                     + " (their columns are shown, not judged).\n")  # fmt: skip
    broke = [f"`{est}` under `{t}` ({cell['broke_down']})" for t, row in doc["cells"].items()
             for est, cell in row.items() if cell.get("broke_down")]  # fmt: skip
    if broke:
        parts.append(
            "Broke down under a threat (no alarm: TPR 0; its state error and impact "
            "count as diverged in the worst case): " + "; ".join(broke) + ".\n"
        )
    for metric, title in _TITLES.items():
        title = title.format(state_unit=sc.state_unit)  # (the scenario's, as its other tables)
        header = ["estimator", "attack-free FPR", *threats, "worst"]
        rows = []
        for est in ests:
            worst = doc["worst_case"].get(est, {})
            rows.append([f"`{est}`", format_number(doc["estimators"][est].get("fpr_at_far"), 3),
                         *(_cell_text(doc["cells"][t].get(est, {}), metric) for t in threats),
                         _worst_text(worst, metric)])  # fmt: skip
        parts.append(f"## {title}\n\n{markdown_table(header, rows)}")
    parts.append(_false_alarm_table(doc, ests, threats))
    insiders = doc.get("threat_reads_state") or {}
    adaptive = doc.get("threat_reads_view") or {}
    insider = " (reads the true state x_k: an insider, who knows the measurement noise)"
    reader = (" (adaptive: reads each estimator's last output, its estimate, score and alarm "
              "at its own threshold)")  # fmt: skip
    specs = "\n".join(f"- `{n}`: {s}{insider if insiders.get(n) else ''}"
                      f"{reader if adaptive.get(n) else ''}"
                      for n, s in doc["threats"].items())  # fmt: skip
    parts.append(f"## Threats\n\n{specs}\n\n![robustness.png](robustness.png)\n")
    parts += [_stealthy_section(n, r) for n, r in (doc.get("stealthy") or {}).items()]
    parts += [_acceptance_section(n, a) for n, a in (doc.get("acceptance") or {}).items()]
    return "\n".join(parts)


def _false_alarm_table(doc: dict, ests: list, threats: list) -> str:
    """The false-alarm rate at τ_α of each estimator under each threat, on the steps the
    threat left unattacked (no worst case: the threats are judged by the tables above)."""
    header = ["estimator", "attack-free FPR", *threats]
    rows = [[f"`{est}`", format_number(doc["estimators"][est].get("fpr_at_far"), 3),
             *(_cell_text(doc["cells"][t].get(est, {}), "fpr_at_far") for t in threats)]
            for est in ests]  # fmt: skip
    return (
        "## False-alarm rate under each threat (`fpr_at_far` on the steps it left unattacked: "
        "before its onset, after its end, and the runs it did not attack)\n\n"
        "A detector whose calibration alarms fall at start-up reads higher here the earlier "
        "the onset (its first steps are a larger share of the unattacked ones); one that "
        "keeps alarming after an attack ends reads higher under the longer ones.\n\n"
        + markdown_table(header, rows)
    )


def _cell_text(cell: dict, metric: str) -> str:
    """One estimator's ``metric`` under one threat for a table: ``broke down`` where it
    broke down there and has no such number (``—`` read as "does not apply")."""
    value = cell.get(metric)
    if value is None and cell.get("broke_down"):
        return "broke down"
    if value is None and cell.get("not_run"):
        return "not run"
    if metric in (cell.get("diverged") or ()):  # (null in the JSON: it had read "—",
        return "diverged"  # which says "does not apply")
    return format_number(value, 3)


def _acceptance_section(name: str, a: dict) -> str:
    """The learned estimator ``name`` against the analytic ones over the threats."""
    mine, best = a["worst_tpr"], a["best_analytic_worst_tpr"]
    training = a.get("training")
    seen = (training or {}).get("threats", {})
    lines = [
        f"## `{name}` against the best analytic over the threats\n",
        f"Analytic: {ANALYTIC} (`difffilter.eval.acceptance`).\n",
    ]
    if best is None:
        lines.append(
            "- Worst TPR over the threats: no analytic detector in the study to compare "
            "with: **not judged** (the check does not hold)."
        )
    else:
        # each printed apart from the other (the check compares them with no margin)
        mine_text = format_number(
            mine[0] if mine else None, 4, apart_from=(best[0],) if best[0] is not None else ()
        )
        best_text = format_number(best[0], 4, apart_from=(mine[0],) if mine else ())
        lines.append(
            f"- Worst TPR over the threats: {mine_text}"
            f"{f' ({mine[1]})' if mine else ''}, against the best analytic worst case "
            f"{best_text} (`{best[1]}`, {best[2]}): "
            f"{'holds' if a['tpr_holds'] else '**does not hold**'}"
            + _gap_text(a.get("worst_tpr_interval")) + "."
            + (f" No TPR of its own on {', '.join(a['tpr_missing'])}, where an analytic "
               "detector has one: not judged." if a.get("tpr_missing") else "")
            + (f" No analytic detector sees its worst threat above {UNSEEN_TEXT}: this check "
               "compares false-alarm rates on it, not detection."
               if a.get("worst_threat_undetected") else "")
        )  # fmt: skip
    blind = any(c.get("best_reads_no_measurements") for c in a["state"].values())
    rows = [[t, format_number(c["value"], 4),
             (f"{format_number(c['best'], 4)} (`{c['best_estimator']}`"
              f"{'†' if c.get('best_reads_no_measurements') else ''})"
              if c["best"] is not None else "— (no analytic estimator: not judged)"),
             # apart from the bar: 1.1004 (fails) and 1.0996 (holds) had both printed 1.1
             # (a reports trial), as the headline report's cells print apart already
             format_number(c["ratio"], 3, apart_from=(ROBUST_STATE_FACTOR,)),
             _interval_cell(c.get("interval"), apart_from=(ROBUST_STATE_FACTOR,)),
             "yes" if c["holds"] else "**no**", seen.get(t, "—"),
             *([_reading_cell(c)] if blind else [])]
            for t, c in a["state"].items()]  # fmt: skip
    lines.append(f"- State RMSE ≤ {ROBUST_STATE_FACTOR:g} × the best analytic's on every threat: "
                 f"{'holds' if a['state_holds'] else '**does not hold**'}. The interval: the ratio's "
                 f"{100 * LEVEL:g} % interval over the runs and the share of resamples within "
                 f"{ROBUST_STATE_FACTOR:g}× (paired bootstrap over the runs, {RESAMPLES:,} "
                 "resamples, the best analytic chosen again in each; `difffilter.eval.intervals`). "
                 "This ratio is to the best analytic's RMSE under the same threat, not the "
                 "tables' `state_error_ratio`, which divides by the estimator's own "
                 "attack-free error.\n")  # fmt: skip
    lines.append(_training_line(training))
    if blind:
        lines.append("- † reads no measurement (an open-loop prediction): no sensor attack moves "
                     "its error, so it sets the bar wherever the attack drags every filter that "
                     "reads the sensors. The check stays against it; the last column gives the "
                     "best analytic that reads them, and the learned value's ratio to it.\n")  # fmt: skip
    lines.append(markdown_table(["threat", name, "best analytic", "ratio to it", "interval", "holds",
                                 "in training",
                                 *(["best that reads the sensors (ratio)"] if blind else [])],
                                rows))  # fmt: skip
    return "\n".join(lines)


def _reading_cell(check: dict) -> str:
    """The best analytic that reads the sensors, where the best reads none, and the ratio."""
    if not check.get("best_reads_no_measurements"):
        return ""
    return (f"{format_number(check['best_reading'], 4)} (`{check['best_reading_estimator']}`), "
            f"{format_number(check['ratio_reading'], 3, apart_from=(ROBUST_STATE_FACTOR,))}×")  # fmt: skip


def _training_line(training: dict | None) -> str:
    """What the learned estimator was trained on, for its threats' "in training" column."""
    if training is None:
        return ("- In training: not known (it ran with no trained checkpoint, or with one "
                "that has no card beside it to say how it was trained).\n")  # fmt: skip
    adversarial = ", with adversarial training" if training["adversarial"] else ""
    return (f"- Trained on {training['trained_on']}{adversarial}: \"in training\" says whether "
            "each threat could have been drawn in training (within), only its kind (kind "
            "only) or not even that (held out), or that the card cannot say (not known: a "
            "threat of your own class beside a scenario attack of your own); "
            "`difffilter.eval.coverage`.\n")  # fmt: skip


def _gap_text(interval: dict | None) -> str:
    if not interval or interval.get("low") is None:
        return ""
    return (f" (the difference {format_number(interval['estimate'], 3)}, "
            f"{100 * LEVEL:g} % interval [{format_number(interval['low'], 3)}, "
            f"{format_number(interval['high'], 3)}] over the runs; it holds in "
            f"{share_percent(interval['holds_share'])} % of the resamples)")  # fmt: skip


def _interval_cell(interval: dict | None, apart_from=()) -> str:
    """``[low, high]`` and the share of resamples that hold, each end printed apart from
    the bars in ``apart_from``."""
    if not interval or interval.get("low") is None:
        return "—"
    low, high = (format_number(interval[k], 3, apart_from=apart_from) for k in ("low", "high"))
    return f"[{low}, {high}]" + share_suffix(interval)


def _stealthy_section(name: str, r: dict) -> str:
    c, b, st = r["crafted"], r["same_rate_bias"], r["settings"]
    matched = b.get("matched", True)
    # a bias of 0 σ is no attack: the crafted attack alarmed no more often than none on
    # these runs (a trial's report had compared it with "constant bias 0 σ")
    bias = matched and bool(b["k_sigma"])
    ratio = format_number(r["error_ratio_to_bias"], 3)
    # not matched by a bias of k > 0: no bias up to k σ alarms as often (same_rate_bias)
    strongest = not matched and bool(b["k_sigma"])
    bias_row = (f"constant bias {format_number(b['k_sigma'], 3)} σ (the weakest that alarms "
                "as often)" if bias
                else f"constant bias {format_number(b['k_sigma'], 3)} σ (the strongest tried: "
                "none alarms as often)" if strongest
                else "no attack (no constant bias alarms as rarely)" if not matched
                else "no attack (it alarms as often)")  # fmt: skip
    verdict = (
        f"\nThe crafted attack's error is {ratio}× that of the weakest constant bias that "
        f"alarms at least as often (the bias's alarm rate {format_number(b['alarm_rate'], 4)} "
        f"against the crafted attack's {format_number(c['alarm_rate'], 4)}: rates are counts "
        "of steps, so they need not be equal)."
        if bias
        else f"\nNo constant bias up to {format_number(b['k_sigma'], 3)} σ alarms as often as the "
        f"crafted attack (its alarm rate {format_number(b['alarm_rate'], 4)} against the crafted "
        f"attack's {format_number(c['alarm_rate'], 4)}): the crafted attack's error is {ratio}× "
        "that of the strongest bias tried."
        if strongest
        else f"\nThe crafted attack alarms {'exactly as often as' if matched else 'less often than'} "
        f"the runs without attack ({format_number(c['alarm_rate'], 4)} against "
        f"{format_number(b['alarm_rate'], 4)}){'' if matched else ': no constant bias is as quiet'}"
        f", and its error is {ratio}× the attack-free error."
    )
    if bias and r["error_ratio_to_bias"] is not None and r["error_ratio_to_bias"] < 1:
        verdict += (" Below 1: the crafting found no attack stronger than that bias (more "
                    "iterations or another lr may; docs/threats.md).")  # fmt: skip
    return (
        f"## The crafted stealthy attack `{name}`\n\n"
        f"Crafted by gradient through `{r['against']}` (its threshold τ = "
        f"{format_number(r['threshold'], 4)} at the calibrated rate) to maximise the "
        "estimation error while the alarm rate over the attacked steps rises by at most "
        f"{100 * st['slack']:g} points over the same runs without attack: Adam, {st['iterations']} "
        f"iterations at lr {st['lr']} (σ per step), {r['train_runs']} fresh training runs per "
        f"iteration, sigmoid temperature {st['temperature']}, penalty {st['penalty']}; "
        f"{r['iterations_within_budget']} iterates kept the budget on their own batch"
        f"{_selection_text(r)}.\n\n"
        + markdown_table(
            [
                "attack (the study's runs)",
                f"`{r['against']}` alarm rate",
                "RMS error ‖x̂ − x‖ over the attacked steps",
            ],
            [
                ["crafted", format_number(c["alarm_rate"], 4), format_number(c["state_error"], 4)],
                [bias_row, format_number(b["alarm_rate"], 4), format_number(b["state_error"], 4)],
            ],
        )  # fmt: skip
        + "\nThe error is √(mean over runs and attacked steps of ‖x̂_k − x_k‖²), the "
        "crafting's objective: not the tables' `state_rmse`, which is per state component "
        "and over every step (a trial read the two as one)."
        + verdict
        + _batch_noise_text(r)
        + " A constant "
        "bias is the simplest yardstick, not the strongest: a ramp or a constant innovation "
        "offset at the same rate comes closer to the crafted error (docs/threats.md)."
        + " Every other estimator meets it as a threat of the tables above (transfer: it was "
        "crafted against one detector only).\n"
    )


def _selection_text(r: dict) -> str:
    """How the attack was chosen among the iterates within budget: on held-out runs
    (``r["selection"]``, :func:`difffilter.stealthy.craft_stealthy_attack`)."""
    sel = r["selection"]
    judged = len(sel["judged"])
    if not judged:
        return ", so the attack is zero"
    if sel["iteration"] is None:
        return (f"; none of the {judged} of largest error judged on {sel['runs']} held-out "
                "runs kept it there, so the attack is zero")  # fmt: skip
    rate = sel["judged"][-1][2]
    return (
        f"; judged on {sel['runs']} held-out runs in order of decreasing error, iterate "
        f"{sel['iteration']} (the {_ordinal(judged)} judged) kept it there (alarm rate "
        f"{format_number(rate, 4)} against {format_number(sel['budget'], 4)}) and is the attack"
    )


def _ordinal(n: int) -> str:
    return f"{n}{'th' if 10 <= n % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(n % 10, 'th')}"


def _batch_noise_text(r: dict) -> str:
    """How far the study's runs may show the budget: where an attack was chosen, one
    standard deviation of a rise of ``ε`` over the study's own runs' attacked steps
    (binomial at ``ε``, the steps taken as independent: a lower bound, a review measured
    1.45–1.8× that over fresh batches); where none was, nothing to judge. (The sentence had
    said the training batches' noise was "about half" of ε whatever the batch; with the
    budget of the first batch alone, a trial's 16 runs × 80 steps had a whole ε of it.)"""
    slack = r["settings"]["slack"]
    if r["selection"]["iteration"] is None:
        return (" No attack kept the budget, so the study's runs above meet none: raise "
                "the penalty or the candidates, or lower lr (docs/threats.md).")  # fmt: skip
    # the study's own attacked (run, step) pairs, as the loop flags them (a report written
    # before they were recorded: runs × the steps per run the crafting counted)
    steps = r["crafted"].get("attacked_steps") or round(r["study_runs"] * r["attacked_steps"])
    spread = math.sqrt(slack * (1 - slack) / steps)
    return (
        " Each iterate is held to its own batch's attack-free rate plus ε, and the attack "
        f"was chosen on {r['selection']['runs']} held-out runs, so on fresh noise its rise is "
        "near ε where those runs are many and above it where they are few (the best of "
        "several candidates on a small batch: 0.85–1.02 ε measured with 256, 1.3–1.8 ε with "
        "64; docs/threats.md); the study's runs (above) carry noise of their own: over their "
        f"{r['study_runs']} runs ({steps} attacked steps in all) a rise of ε varies "
        f"by at least {format_number(spread, 2)} ({spread / slack:.2g} of ε; one binomial "
        "standard deviation, steps taken as independent: the spread measured over fresh "
        "batches is larger)."
    )


def _heatmap(path: Path, doc: dict, sc) -> None:
    """One panel per headline cell metric, stacked: estimators × threats, coloured good →
    bad. The state-error ratio on a logarithmic colour scale whose bar reads ratios (1 to
    10 or the largest); text white on the darkest cells. (Side by side the panels made a
    figure 24 inches wide whose 6-point text was unreadable at a page's width, and the
    ratio's bar read log10 of what the cells printed, clipped at 10: a figure review.)"""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from matplotlib.colors import LogNorm, Normalize

    from .plots import text_colour

    threats, ests = list(doc["threats"]), list(doc["estimators"])
    height = 0.3 * len(ests) + 1.6
    fig, axes = plt.subplots(3, 1, figsize=(max(6.0, 0.75 * len(threats) + 3), 3 * height))
    panels = (("tpr_at_far", "RdYlGn", False), ("state_error_ratio", "RdYlGn_r", True),
              ("impact", "RdYlGn_r", False))  # fmt: skip
    for ax, (metric, cmap, log) in zip(axes, panels):
        grid = np.array([[np.nan if doc["cells"][t].get(e, {}).get(metric) is None
                          else doc["cells"][t][e][metric] for t in threats] for e in ests],
                        float)  # fmt: skip
        finite = grid[np.isfinite(grid)]
        top = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
        if log:  # a ratio: 1 (as without attack) green, 10× or the largest red
            norm = LogNorm(vmin=1.0, vmax=max(10.0, top))
        else:
            norm = Normalize(0.0, 1.0 if metric == "tpr_at_far" else top)
        shown = np.where(np.isfinite(grid), np.clip(grid, 1e-12, None), np.nan)
        image = ax.imshow(shown, aspect="auto", cmap=cmap, norm=norm)
        bar = fig.colorbar(image, ax=ax, fraction=0.035, pad=0.015)
        if log:  # ticks read as ratios, not powers of ten
            ticks = [v for v in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000) if v <= norm.vmax]
            bar.set_ticks(ticks, labels=[f"{v:g}" for v in ticks])
            bar.ax.minorticks_off()
        bar.ax.tick_params(labelsize=7)
        colours = norm(np.clip(shown, norm.vmin, norm.vmax))
        for (i, j), value in np.ndenumerate(grid):
            text = "—" if np.isnan(value) else format_number(float(value), 2)
            shade = float(colours[i, j]) if np.isfinite(value) else math.nan
            ax.text(j, i, text, ha="center", va="center", fontsize=7,
                    color=text_colour(shade))  # fmt: skip
        ax.set_xticks(range(len(threats)), threats, rotation=30, ha="right", fontsize=7)
        ax.set_yticks(range(len(ests)), ests, fontsize=7)
        scale = " (log colour scale)" if log else ""
        ax.set_title(f"{metric} [{sc.unit_of(_unit(metric))}]{scale}", fontsize=9)
    fig.suptitle(f"{doc['scenario']}: robustness at {100 * doc['far']['target']:g} % FAR",
                 fontsize=10)  # fmt: skip
    fig.tight_layout(rect=(0, 0, 1, 0.98))  # (the title of the figure above the first's)
    save_figure(fig, path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def _unit(metric: str) -> str:
    return "ratio" if metric == "state_error_ratio" else METRICS[metric].unit


def write_robustness_summary(out: str | Path, docs: dict[str, dict]) -> Path:
    """``<out>/robustness.md``: every scenario × estimator's worst case over its threats
    (with the threat that caused it), and the leaderboard of the attack-free studies with
    the worst-case columns (:func:`~difffilter.eval.leaderboard.write_leaderboard`)."""
    from .leaderboard import write_leaderboard

    out = Path(out)
    rows = []
    for scenario, doc in docs.items():
        for est, entry in doc["estimators"].items():
            w = doc["worst_case"].get(est, {})

            def worst(key, w=w):
                return _worst_text(w, key)

            rows.append([scenario, f"`{est}`", format_number(entry.get("fpr_at_far"), 3),
                         worst("tpr_at_far"), worst("state_error_ratio"), worst("impact")])  # fmt: skip
    header = ["scenario", "estimator", "attack-free fpr_at_far", "worst tpr_at_far",
              "worst state_error_ratio", "worst impact [its scenario's state unit]"]  # fmt: skip
    far = next(iter(docs.values()))["far"]["target"] if docs else 0.01
    path = out / "robustness.md"
    write_atomically(
        path,
        f"# Robustness\n\nEvery estimator's worst case over its scenario's threats, every "
        f"detector at {100 * far:g} % false alarms (thresholds from attack-free runs of "
        "their own seed); the threat that caused it in brackets. Details per scenario in "
        "`<scenario>/robustness.md`.\n\n"
        + markdown_table(header, rows)
        + "\n"
        + _acceptance_summary(docs),
    )
    write_leaderboard(out, docs)
    # the leaderboard replaced was an evaluation's, and its acceptance.md went with it: the
    # verdicts of this study are in robustness.md (an old file was printed as current)
    (out / "acceptance.md").unlink(missing_ok=True)
    return path


def _within_readers(checks) -> str:
    """``" (n within the best that reads the sensors)"`` where some threat's best analytic
    reads no measurement (:func:`~.acceptance.judge_robustness`), else ``""``: how many
    threats hold when every such bar is replaced by the best estimator that reads them."""
    checks = list(checks)
    if not any(c.get("best_reads_no_measurements") for c in checks):
        return ""
    n = sum(c.get("holds_reading", c["holds"]) for c in checks)
    return f" ({n} within the best that reads the sensors)"


def _acceptance_summary(docs: dict[str, dict]) -> str:
    """Each learned estimator's robustness acceptance per scenario, with how sure: the
    worst-case TPR check's share of resamples, and the threats within the state factor
    (those that hold in at least 95 % of the resamples, and those in at most 5 %)."""
    rows, any_unseen = [], False
    for scenario, doc in docs.items():
        for name, a in (doc.get("acceptance") or {}).items():
            tpr = (
                ("holds" if a["tpr_holds"] else "**fails**")
                + share_suffix(a.get("worst_tpr_interval"))
                + ("; worst threat undetected†" if a.get("worst_threat_undetected") else "")
            )
            any_unseen = any_unseen or bool(a.get("worst_threat_undetected"))
            checks = a["state"].values()
            shares = [c["interval"]["holds_share"] for c in checks
                      if c.get("interval") and c["interval"].get("holds_share") is not None]  # fmt: skip
            rows.append([scenario, f"`{name}`", tpr,
                         f"{sum(c['holds'] for c in checks)} of {len(checks)}"
                         + _within_readers(checks),
                         f"{sum(v >= 0.95 for v in shares)} / {sum(v <= 0.05 for v in shares)}",
                         "holds" if a["holds"] else "**fails**"])  # fmt: skip
    if not rows:
        return ""
    header = ["scenario", "learned", "worst TPR ≥ best analytic's worst (share of resamples)",
              f"threats within {ROBUST_STATE_FACTOR:g}× the best analytic's state RMSE",
              "sure within / sure beyond (holds in ≥ 95 % / ≤ 5 % of resamples)",
              "every check"]  # fmt: skip
    return (
        "\n## Learned against the best analytic over the threats\n\nThe robustness "
        "acceptance (`difffilter.eval.acceptance`) per scenario, with how sure each verdict is "
        "over the runs (paired bootstrap, `difffilter.eval.intervals`; details in each "
        "`<scenario>/robustness.md`).\n\n"
        + markdown_table(header, rows)
        + "\n"
        + (
            f"† No analytic detector sees the worst threat above {UNSEEN_TEXT}: the "
            "worst-case TPR check compares false-alarm rates there.\n"
            if any_unseen
            else ""
        )
    )
