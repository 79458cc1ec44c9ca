"""The report writer shared by every scenario: metrics.json, report.md, plots, TensorBoard.

``<out>/<scenario>/metrics.json`` (JSON Schema: ``eval/metrics.schema.json``)::

    {"scenario": str, "runs": int, "steps": int, "seed": int, "dt_s": float,
     "units": {"<metric>": "<unit>", ...},
     "paper": {...the paper's reference numbers...},
     "estimators": {"<name>": {"<metric>": number|null for every metric of
                               difffilter.eval.scoring.METRICS, ...extra keys}}}

Extra keys (scenario-specific numbers) may be added to an estimator entry or at the top
level; the metrics of :data:`~difffilter.eval.scoring.METRICS` are always present.

:func:`write_report` writes the whole report of a suite run: the generic sections every
scenario gets (settings, the estimator table, plots of RMSE over time, ROC curves and one
run's attack estimates and alarms) followed by the sections a family registers with
:func:`register_family` (its paper's table and discussion).
"""

from __future__ import annotations

import json
import math
import os
import re
import sys
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from difffilter.linalg import NumericalBreakdown
from difffilter.models import estimators as registry
from difffilter.models.atomic_write import write_atomically, write_json_atomically

from .acceptance import ANALYTIC, TOLERANCES, best_analytic, judge, role_mark, roles, state_metric
from .calibration import below_target_note
from .intervals import acceptance_intervals
from .provenance import software_line, software_record
from .scoring import METRICS

__all__ = [
    "Section",
    "FamilyReport",
    "register_family",
    "family_report",
    "report_writers",
    "metrics_schema",
    "write_report",
    "write_acceptance_summary",
    "markdown_table",
    "format_number",
    "share_suffix",
    "save_figure",
    "mark_incomplete",
    "clear_incomplete",
    "INCOMPLETE",
    "INCOMPLETE_KINDS",
]

#: The marker of a folder whose files an evaluation or a robustness study is writing
#: (:func:`mark_incomplete`): left there by one that was stopped or failed, whose files may
#: then mix with an earlier one's.
INCOMPLETE = "INCOMPLETE.md"

#: The kinds of run that mark a folder, each under a heading of its own in the one
#: ``INCOMPLETE.md``: an evaluation's and a robustness study's files lie side by side in
#: ``<out>`` and in a scenario's folder, and one kind run to its end had removed the marker
#: of the other, stopped there (its mixed files then unflagged).
INCOMPLETE_KINDS = ("evaluation", "robustness study")

_HEADINGS = {f"## {kind}": kind for kind in INCOMPLETE_KINDS}


def save_figure(fig, path: str | Path, **savefig) -> None:
    """``fig.savefig(path, **savefig)`` as a PNG that replaces ``path`` whole or not at all
    (:func:`~difffilter.models.atomic_write.write_atomically`)."""
    write_atomically(path, lambda partial: fig.savefig(partial, format="png", **savefig))


#: The line of an ``INCOMPLETE.md`` that records the PNGs a folder held before the write.
_BEFORE = "Figures here before it began (a rerun removes the others): "


def _check_kind(kind: str) -> None:
    if kind not in INCOMPLETE_KINDS:
        raise ValueError(f"kind: {kind!r} is not one of {', '.join(INCOMPLETE_KINDS)}")


def _marked(folder: Path) -> dict[str, str]:
    """The sections of ``<folder>/INCOMPLETE.md`` by kind, in the file's order (``{}`` where
    there is none). A marker of an earlier version, with no kind's heading, is one section:
    a robustness study's where its text says so, an evaluation's otherwise."""
    marker = folder / INCOMPLETE
    if not marker.is_file():
        return {}
    text = marker.read_text(encoding="utf-8")
    sections: dict[str, list[str]] = {}
    kind, unheaded = None, []
    for line in text.splitlines():
        if line.strip() in _HEADINGS:
            kind = _HEADINGS[line.strip()]
            sections[kind] = []
        elif kind is not None:
            sections[kind].append(line)
        elif not line.startswith("# "):
            unheaded.append(line)
    if not sections and "".join(unheaded).strip():
        sections["robustness study" if "robustness study" in text else "evaluation"] = unheaded
    return {k: "\n".join(lines).strip("\n") for k, lines in sections.items()}


def _write_marker(folder: Path, sections: dict[str, str]) -> None:
    """``<folder>/INCOMPLETE.md`` holding ``sections`` (kind: text), removed where none."""
    marker = folder / INCOMPLETE
    if not sections:
        marker.unlink(missing_ok=True)
        return
    write_atomically(marker, "# Incomplete\n" + "".join(
        f"\n## {kind}\n\n{text}\n" for kind, text in sections.items()
    ))  # fmt: skip


def mark_incomplete(
    folder: str | Path,
    what: str,
    *,
    figures_before: Iterable[str] | None = None,
    kind: str = "evaluation",
) -> Path:
    """Write ``<folder>/INCOMPLETE.md`` saying that ``what`` is being written there, and
    return its path, for the writer to call :func:`clear_incomplete` once every file is
    written: an error or an interrupt leaves it. An evaluation stopped midway into the folder
    of an earlier one had left its metrics.json beside the earlier report.md and
    leaderboard, with nothing to say that they were of two studies.

    ``kind`` (one of :data:`INCOMPLETE_KINDS`): the section of the file this write replaces;
    the other kind's section, left by a run of that kind stopped here, is kept, for only a
    run of its own kind to clear.

    ``figures_before``: the PNGs in the folder before this write, recorded on one line
    (:func:`_figures_before` reads it back) so that a rerun knows every other PNG there as
    the stopped write's, though no report.md lists it."""
    _check_kind(kind)
    folder = Path(folder)
    record = "" if figures_before is None else (
        f"\n\n{_BEFORE}{json.dumps(sorted(figures_before), ensure_ascii=False)}"
    )  # fmt: skip
    sections = _marked(folder)
    sections[kind] = (
        f"{what} began at {time.strftime('%Y-%m-%d %H:%M:%S')} (process {os.getpid()}) and has "
        "not ended: it is still running, or it was stopped or failed. Until it is run again to "
        f"its end, the files here may mix its results with an earlier {kind}'s: rerun the same "
        "command." + record
    )
    _write_marker(folder, sections)
    return folder / INCOMPLETE


def clear_incomplete(folder: str | Path, kind: str = "evaluation") -> None:
    """Remove ``kind``'s section of ``<folder>/INCOMPLETE.md`` (:func:`mark_incomplete`), and
    the file where no other kind's is left: a run of that kind has written every file."""
    _check_kind(kind)
    folder = Path(folder)
    sections = _marked(folder)
    if sections.pop(kind, None) is not None:  # (another kind's marker alone: left as it is)
        _write_marker(folder, sections)


def _figures_before(folder: Path) -> set[str] | None:
    """The PNGs the evaluation's section of ``<folder>/INCOMPLETE.md`` records as there
    before its write (:func:`mark_incomplete`), or ``None`` where there is no such record (no
    marker, or one of another kind of write)."""
    for line in _marked(folder).get("evaluation", "").splitlines():
        if line.startswith(_BEFORE):
            try:
                names = json.loads(line.removeprefix(_BEFORE))
            except ValueError:  # (an edited marker: read as one without a record)
                return None
            return {n for n in names if isinstance(n, str)} if isinstance(names, list) else None
    return None


def _pngs(folder: Path) -> set[str]:
    """The PNG files directly in ``folder``."""
    return {p.name for p in folder.glob("*.png") if p.is_file()}


def json_safe(value: Any) -> Any:
    """JSON-safe: tensors/numpy scalars to Python numbers, NaN/inf to ``None``, recursively
    through dicts (keys as strings), lists and tuples."""
    if hasattr(value, "item") and callable(value.item):
        try:
            value = value.item()
        except (ValueError, RuntimeError):
            value = value.tolist()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def format_number(value: Any, digits: int = 4, apart_from: Sequence[float] = ()) -> str:
    """Compact table formatting: ``—`` for missing values, scientific for small ones.
    ``apart_from``: numbers ``value`` must not print as unless it equals them (a check's
    bounds: an FPR of 0.020004 above a band's 0.02 printed "0.02 ✗"); digits are added, up
    to 8, as for a fraction just below 1."""
    if value is None:
        return "—"
    if isinstance(value, (bool, int)):
        return str(value)
    if isinstance(value, float):
        scientific = not (value == 0 or 1e-3 <= abs(value) < 1e4)
        digits = max(digits - 1, 1) if scientific else digits

        def shown(number: float) -> str:
            return f"{number:.{digits}{'e' if scientific else 'g'}}"

        def looks_like_another(text: str) -> bool:
            # a fraction just below 1 printed "1", a perfect detector's (an AUC of 0.99992)
            near_one = not scientific and abs(float(text)) == 1 != abs(value)
            return near_one or any(b != value and shown(b) == text for b in apart_from)

        text = shown(value)
        while looks_like_another(text) and digits < 8:
            digits += 1
            text = shown(value)
        return text
    return str(value)


def less(a: Any, b: Any) -> bool | None:
    """``a < b`` of two report numbers, ``None`` where either is missing (a metric that
    was not finite is written ``null``: one diverged run makes an RMSE so, and a family's
    claim had compared ``None < 1`` and stopped the report)."""
    return None if a is None or b is None else a < b


#: What a claim says where a number it compares is missing (:func:`less`).
NOT_JUDGED = "cannot be judged (a number is missing: an estimate was not finite)"


def verdict(holds: bool | None, yes: str = "holds", no: str = "does not hold") -> str:
    """``yes``, ``no``, or :data:`NOT_JUDGED` for ``None`` (:func:`less`)."""
    return NOT_JUDGED if holds is None else (yes if holds else no)


def share_suffix(interval: dict | None) -> str:
    """``" (53 %)"``: the share of resamples of the runs in which a check holds (an
    interval of :mod:`difffilter.eval.intervals`), or ``""`` where none was measured."""
    share = (interval or {}).get("holds_share")
    return "" if share is None else f" ({share_percent(share)} %)"


def share_percent(share: float) -> str:
    """``100 · share`` in whole percent, with the decimals it takes not to read 0 or 100
    where the check failed or held in some resamples (1,999 of 2,000: 99.95, not 100)."""
    text = f"{100 * share:.0f}"
    for digits in range(1, 9):  # (999,999 of 10⁶ had read 100.000)
        if share in (0.0, 1.0) or float(text) not in (0.0, 100.0):
            break
        text = f"{100 * share:.{digits}f}"
    return text


# ------------------------------------------------------------------ the generic report


@dataclass
class Section:
    """A titled part of report.md (markdown body; figures are file names in the folder)."""

    title: str
    body: str
    figures: list[str] = field(default_factory=list)


@dataclass
class FamilyReport:
    """What a family adds to the generic report.

    Attributes:
        extra: ``SuiteResult → dict`` of family numbers for metrics.json (top level),
            computed from the suite run (e.g. an attack-size sweep, a paper table); it
            may also add family keys to ``result.metrics[estimator]``.
        sections: ``(SuiteResult, doc, out, prepared) → [Section]`` after the generic
            sections; ``doc`` is the metrics.json content, ``out`` the folder (for its own
            plots), ``prepared`` what ``prepare`` returned (or ``None``).
        prepare: ``(scenarios, out=, seed=, checkpoint=, progress=, options=, far=) → object``,
            once per evaluation before the family's scenarios: a study they share (e.g.
            a validation the reports discuss). ``options`` holds the CLI's family flags.
        finish: ``(results, out, prepared) → None`` once after them: a summary across the
            family's scenarios (``results``: ``{scenario: metrics.json content}``).
        check_options: ``options → None``, ``ValueError`` naming a bad ``--option``: run
            before any scenario of the evaluation (``prepare`` checks them again).
        estimator_metrics: ``(SuiteResult, estimator) → dict``: cheap numbers of one
            estimator's outputs that the family reports beside the generic ones (tracking's
            position RMSE ``rmse_p``), for the studies that write no report (a training
            sweep's acceptance, :mod:`difffilter.eval.acceptance`).
        report_cost: what writing one of its scenarios' reports costs, in plain reports
            (the generic sections alone, about 2 s on a 2-core machine): how
            ``difffilter-eval --devices N`` shares the families' reports between its
            processes (:func:`report_writers`). Measured, not exact.
        needs: the estimators whose outputs ``extra`` and ``sections`` read: where one did
            not run (skipped, broken down, or left out of the run) the family's numbers
            and sections are left out with the reason (metrics.json's
            ``family_report_skipped``), as they are where ``extra``'s own runs break down
            (:class:`~difffilter.linalg.NumericalBreakdown`), and the generic report is
            written.
        writes: what ``prepare`` and ``finish`` write in ``<out>`` beside the scenarios'
            folders: file names, and folder names ending in ``/``. ``difffilter-eval``
            checks before any work that none is taken by the other kind (a folder named
            ``lfc_summary.md`` failed an evaluation at its very end).
    """

    extra: Callable[..., dict[str, Any]] | None = None
    sections: Callable[..., list[Section]] | None = None
    prepare: Callable[..., Any] | None = None
    finish: Callable[..., None] | None = None
    check_options: Callable[[dict], None] | None = None
    estimator_metrics: Callable[..., dict[str, Any]] | None = None
    report_cost: float = 1.0
    needs: tuple[str, ...] = ()
    writes: tuple[str, ...] = ()


_FAMILIES: dict[str, FamilyReport] = {}
_FAMILY_ORIGINS: dict[str, str] = {}


def register_family(family: str, report: FamilyReport) -> FamilyReport:
    """Register the report additions of ``family`` (one per family: another report for a
    family that has one is an error naming both modules; it replaced the first silently)."""
    origin = sys._getframe(1).f_globals.get("__name__", "?")
    if family in _FAMILIES and _FAMILIES[family] != report:
        raise ValueError(
            f"family {family!r} already has its report additions, registered by module "
            f"{_FAMILY_ORIGINS.get(family, '?')}; module {origin} registers others: a family "
            "has one FamilyReport (merge them, or give the family another name)"
        )
    _FAMILIES[family] = report
    _FAMILY_ORIGINS.setdefault(family, origin)
    return report


def report_writers(families: dict[str, list[str]], world: int) -> dict[str, int]:
    """``{family: rank}``: which of ``world`` processes writes each family's reports.

    Longest first onto the least loaded process (a family's scenarios stay together: its
    ``finish`` reads them all), each family weighing ``report_cost × its scenarios``;
    rank 0 starts one report behind (it writes the leaderboard too) and ties go to the
    higher rank. With ``world = 1`` every family is rank 0's.
    """
    load = [1.0] + [0.0] * (world - 1)
    cost = {f: family_report(f).report_cost * len(names) for f, names in families.items()}
    writers = {}
    for family in sorted(cost, key=lambda f: -cost[f]):
        rank = min(range(world), key=lambda r: (load[r], -r))
        writers[family] = rank
        load[rank] += cost[family]
    return writers


def family_report(family: str) -> FamilyReport:
    """What ``family`` registered (an empty :class:`FamilyReport` if nothing)."""
    from .families import load_all

    load_all()
    return _FAMILIES.get(family, FamilyReport())


def report_for(scenario) -> tuple[FamilyReport, str | None]:
    """``(its family's report additions, None)`` for ``scenario``, or ``(an empty
    FamilyReport, why they are left out)`` for a plant of one's own (a
    :class:`~difffilter.models.scenario.CustomScenario`) in a family whose registered
    scenarios are of another class: the sections read what only those have (a YAML plant of
    family ``tracking`` or ``robot`` failed after its whole study, and one of family ``lfc``
    got the LFC paper's summary table)."""
    from difffilter.models import registry
    from difffilter.models.scenario import CustomScenario

    report = family_report(scenario.family)
    if scenario.family not in _FAMILIES or not isinstance(scenario, CustomScenario):
        return report, None
    kinds = {type(registry.get(n)) for n in registry.names(family=scenario.family)
             if n != scenario.name}  # fmt: skip
    foreign = sorted(k.__name__ for k in kinds if not isinstance(scenario, k))
    if not foreign:  # (a family of one's own, its report written for its own plants)
        return report, None
    return FamilyReport(), (
        f"`{scenario.name}` is a plant of your own (a CustomScenario), and the {scenario.family} "
        f"family's sections read what only its {', '.join(foreign)} scenarios have"
    )


def metrics_schema() -> dict[str, Any]:
    """The JSON Schema of metrics.json (``eval/metrics.schema.json``; its units and
    descriptions are those of :data:`~difffilter.eval.scoring.METRICS`, tested)."""
    return json.loads((Path(__file__).parent / "metrics.schema.json").read_text(encoding="utf-8"))


def study_metrics(scenario: str, *, runs: int, steps: int, seed: int,
                  estimators: dict[str, dict[str, Any]]) -> dict[str, Any]:  # fmt: skip
    """The fields every metrics.json carries (``eval/metrics.schema.json``), for a study's
    own file (the LFC per-channel validation, the watermark study): ``estimators`` maps a
    name to the metrics it has, every other metric ``None``; the study adds its own keys
    beside these."""
    return {
        "scenario": scenario, "runs": runs, "steps": steps, "seed": seed,
        "units": {name: m.unit for name, m in METRICS.items()}, "paper": {},
        "estimators": {n: {**dict.fromkeys(METRICS), **m} for n, m in estimators.items()},
    }  # fmt: skip


def concrete_unit(doc: dict, metric: str) -> str:
    """``metric``'s unit in a metrics.json ``doc``: ``"state units"`` and ``"attack units"``
    read as the scenario's (``doc["scenario_units"]``, e.g. ``cm``) where it says them."""
    unit = doc["units"].get(metric) or METRICS[metric].unit
    named = doc.get("scenario_units") or {}
    return {"state units": named.get("state"), "attack units": named.get("attack")}.get(
        unit
    ) or unit


def markdown_table(header: list[str], rows: list[list[Any]]) -> str:
    """A markdown table (cells formatted with ``str``; numbers should be formatted first)."""
    lines = ["| " + " | ".join(map(str, header)) + " |", "|---" * len(header) + "|"]
    lines += ["| " + " | ".join(map(str, r)) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def _scenario_file(name: str) -> dict:
    """``{"scenario_file": {"path", "sha256"}}`` for a scenario read from a YAML file: its
    absolute path and :func:`~difffilter.models.yaml_scenario.scenario_file_digest` as the
    study read it (what the numbers were computed on, as a training card records it), with
    ``"sha256_now"`` and a warning where the file has changed since; ``{}`` for any other."""
    from difffilter.models import registry as scenarios
    from difffilter.models.yaml_scenario import scenario_file_digest

    source = scenarios.source_file(name)
    if source is None:
        return {}
    path, read = source
    record = {"path": str(path), "sha256": read}
    now = scenario_file_digest(path)
    if now != read:
        record["sha256_now"] = now
        warnings.warn(
            f"{path} changed during the study of {name}: its report records the file as the "
            "study read it (scenario_file.sha256), and the file now as sha256_now",
            stacklevel=2,
        )
    return {"scenario_file": record}


def write_report(out: str | Path, result, *, prepared: Any = None) -> dict[str, Any]:
    """Write metrics.json, report.md, plots and TensorBoard events of a suite run.

    metrics.json holds every metric of :data:`~difffilter.eval.scoring.METRICS` for every
    estimator (``None`` where it does not apply), with the units, the scenario's settings
    and paper numbers, and what the family's ``extra`` adds.

    Args:
        out: the scenario's folder (created).
        result: a :class:`~difffilter.eval.suite.SuiteResult`.
        prepared: what the family's ``prepare`` returned, for its sections.

    Returns the metrics.json content. Each file replaces the earlier evaluation's whole or
    not at all (:func:`~difffilter.models.atomic_write.write_atomically`); ``INCOMPLETE.md`` marks the folder while they are
    written (:func:`mark_incomplete`, the evaluation's section).
    """
    from .plots import png_bytes, standard_figures
    from .tensorboard import log_suite

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    shown_before = _figures_of(out / "report.md")  # an earlier evaluation's, if any
    sc = result.scenario
    family, foreign = report_for(sc)
    family_numbers, family_skipped = _family_numbers(family, result)  # may add estimator keys
    family_skipped = foreign or family_skipped
    doc = json_safe({
        "scenario": sc.name, "runs": result.runs, "steps": sc.steps, "seed": result.seed,
        # the study's dtype (a docs trial: a float32 study's report read as a float64 one's)
        "dtype": str(result.traj.x.dtype).removeprefix("torch."),
        "units": {name: m.unit for name, m in METRICS.items()},
        "scenario_units": {"state": sc.state_unit, "attack": sc.attack_unit},
        "network": network_of(sc, result.traj),
        "paper": sc.paper_numbers(),
        "estimators": {n: {**dict.fromkeys(METRICS), **m} for n, m in result.metrics.items()},
        "description": sc.description, "dt_s": sc.dt, "reference": result.reference,
        "estimator_descriptions": {n: registry.get(n).description for n in result.metrics},
        "estimator_roles": roles(result.metrics),
        "notes": list(sc.notes),
        "attacked_steps": int(result.traj.flags.sum()),
        "attack_free_steps": int((~result.traj.flags).sum()),
        "skipped": dict(result.skipped), "checkpoint": result.checkpoint,
        **_scenario_file(sc.name),
        "far": None if result.calibration is None else result.calibration.summary(),
        **({"checkpoints": result.checkpoints} if result.checkpoints else {}),
        **({"family_report_skipped": family_skipped} if family_skipped else {}),
        **family_numbers,
        "software": software_record(),
    })  # fmt: skip
    if doc["far"] is not None and (intervals := acceptance_intervals(
        result, doc["estimator_roles"], far=doc["far"]["target"],
        state_metric=state_metric(doc["estimators"]),
    )):  # fmt: skip
        doc["acceptance_intervals"] = json_safe(intervals)
    # The figures of a write stopped here before its report.md (the PNGs and the family's
    # figures come first) are listed by no report.md: its INCOMPLETE.md recorded the PNGs
    # that were here before it, so the others are its own. Kept in this write's record too,
    # so that a rerun stopped again still knows them.
    # A robustness study's heat map, drawn here after that stop (its section of the marker
    # leaves the evaluation's record as it was), is the study's own: its robustness.md shows it.
    present, recorded = _pngs(out), _figures_before(out)
    before = present if recorded is None else present & recorded
    stopped = present - before - _figures_of(out / "robustness.md")  # (none without a record)
    mark_incomplete(
        out, f"Writing the reports of {sc.name} into this folder", figures_before=before
    )
    write_json_atomically(out / "metrics.json", doc)
    figures = standard_figures(result)
    try:  # the figures closed also where a write fails (they had stayed open: 20+ in a
        # process that met failing writes, matplotlib's warning)
        sections = [_summary_section(doc, sc), _table_section(doc)]
        if (judged := _acceptance_section(doc)) is not None:
            sections.append(judged)
        sections.append(Section("Plots", "", [name for name, _ in figures]))
        if family_skipped:
            sections.append(
                Section(f"The {sc.family} family's sections", f"Left out: {family_skipped}.")
            )
        elif family.sections:
            sections += family.sections(result, doc, out, prepared)
        images = [(name, png_bytes(fig)) for name, fig in figures]  # each drawn once:
        for name, png in images:  # the file and TensorBoard's image are the same PNG
            write_atomically(out / name, png)
        write_atomically(out / "report.md", _markdown(doc, sc, sections))
        # the family's own figures too (its sections saved them in the folder)
        drawn = {name for name, _ in images}
        for section in sections:
            for name in section.figures:
                if name not in drawn and name.endswith(".png") and (out / name).is_file():
                    images.append((name, (out / name).read_bytes()))
                    drawn.add(name)
        log_suite(out / "tb", result, doc, images)
        # an earlier evaluation's figures this one does not draw (a detector's ROC where this run
        # has none), and a stopped one's: the folder shows one run, as the README says
        for name in (shown_before | stopped) - {n for section in sections for n in section.figures}:
            (out / name).unlink(missing_ok=True)
        clear_incomplete(out)  # every file of this evaluation written (a robustness study's stays)
    finally:
        import matplotlib.pyplot as plt

        for _, fig in figures:
            plt.close(fig)
    return doc


def _figures_of(report: Path) -> set[str]:
    """The figures a ``report.md`` shows: the files of its ``![name](name)`` lines (the
    folder's own, no path), empty where there is no report."""
    if not report.is_file():
        return set()
    return {name for alt, name in re.findall(r"^!\[([^\]]*)\]\(([^)/\\]+)\)$",
                                              report.read_text(encoding="utf-8"), flags=re.M)
            if alt == name}  # fmt: skip


def _trained_on(ckpt: dict) -> str:
    """``; trained on `X``` for a report's checkpoint line, where its card names the
    scenario of its training (a network of another plant of the family runs without a
    word: a trial's, trained on one motor, scored an AUC of 0.55 on a noisier one)."""
    trained = ckpt.get("training_scenario")
    return "" if trained is None else f"; trained on `{trained}`"


def _family_numbers(family: FamilyReport, result) -> tuple[dict[str, Any], str | None]:
    """``(family numbers, None)``, or ``({}, why)`` where an estimator the family reads did
    not run (:attr:`FamilyReport.needs`) or the family's own runs broke down."""
    missing = [n for n in family.needs if n not in result.outputs]
    if missing:
        why = "; ".join(f"`{n}` ({result.skipped.get(n, 'not in this run')})" for n in missing)
        return {}, f"they read estimators that did not run here: {why}"
    if family.extra is None:
        return {}, None
    try:
        return family.extra(result), None
    except NumericalBreakdown as exc:
        warnings.warn(f"{result.scenario.name}: the {result.scenario.family} family's report "
                      f"broke down and is left out: {exc}", stacklevel=3)  # fmt: skip
        return {}, f"an estimator broke down in the family's own runs: {exc}"


def network_of(sc, traj=None) -> dict:
    """``{"sensors": the schedule, "inputs": the input packets' loss or None}`` of a
    scenario, as metrics.json records it (a TCP-like and a UDP-like study differed by their
    names alone), and with the study's trajectories ``traj`` the share of its steps (run ×
    step) that received no measurement entry at all, ``"steps_without_data"`` (0 without a
    schedule): such a step scores no evidence, and an unattacked one counts among FPR's and
    AUC's negatives (a robotics trial at 90 % loss: 64 % of the steps, an FPR of 1.14 %
    over all of them against 3.46 % over the steps that received data)."""
    loss = sc.input_loss_schedule()
    inputs = None if loss is None else {
        "schedule": _described(loss.schedule), "on_loss": loss.on_loss.value,
        "acknowledged": loss.acknowledged,
    }  # fmt: skip
    network = {"sensors": _described(sc.schedule()), "inputs": inputs}
    if traj is not None:
        mask = getattr(traj, "mask", None)
        empty = 0.0 if mask is None else float((~mask.any(-1)).double().mean())
        network["steps_without_data"] = empty
    return network


def _described(schedule) -> str:
    """A schedule's repr, or its class's name where the repr is object's own, without the
    memory addresses a repr may hold (metrics.json would differ between identical runs)."""
    if type(schedule).__repr__ is object.__repr__:
        return type(schedule).__qualname__
    return re.sub(r" at 0x[0-9a-fA-F]+", "", repr(schedule))


def _calibration_spread(target: float, steps: int) -> str:
    """The sentence on how far a threshold chosen on ``steps`` attack-free steps may miss
    ``target`` on fresh runs: the binomial spread of an empirical quantile, ±2√(α(1 − α)/n),
    a floor (steps of one run alarm together, and runs differ). A user trial calibrated on
    16 runs of 100 steps met 1.40 % on fresh runs for a 1 % target (±0.50 points here)."""
    if not steps:
        return ""
    spread = 2 * math.sqrt(target * (1 - target) / steps)
    return (
        f" From {steps:,} calibration steps a threshold's rate on fresh runs is the target "
        f"within about ±{100 * spread:.2g} points at best (±2√(α(1 − α)/n), the binomial "
        "spread of a quantile; more where alarms cluster in runs): give more "
        "`--calibration-runs` for a tighter one."
    )


def _network_line(network: dict | None) -> str:
    """The report's sentence on a lossy network ("" where every packet arrives)."""
    if not network or (network["sensors"] == "AllSensors()" and network["inputs"] is None):
        return ""
    line = f"\nNetwork: measurements `{network['sensors']}`"
    empty = network.get("steps_without_data")
    if empty:
        line += (f" ({100 * empty:.3g} % of the steps received no measurement: an unattacked "
                 "one counts among the negatives of FPR and AUC)")  # fmt: skip
    inputs = network["inputs"]
    if inputs is not None:
        told = ("acknowledged (TCP-like: the estimators step with the inputs applied)"
                if inputs["acknowledged"] else
                "unacknowledged (UDP-like: the estimators step with the inputs sent)")  # fmt: skip
        line += (f"; input packets `{inputs['schedule']}`, the actuators "
                 f"{'holding their last input' if inputs['on_loss'] == 'hold' else 'applying zero'}"
                 f" where one is lost, {told}")  # fmt: skip
    return line + ".\n"


def _summary_section(doc: dict, sc) -> Section:
    body = (
        f"{doc['runs']} Monte Carlo runs × {doc['steps']} steps (dt = {doc['dt_s']} s), seed "
        f"{doc['seed']}; {doc['attacked_steps']} attacked and {doc['attack_free_steps']} "
        "attack-free steps. Every estimator sees the same runs and the same random numbers "
        "(named streams of one master seed). "
        + (f"Attack-free reference: `{doc['reference']}`.\n" if doc.get("reference") else "\n")
    )
    far = doc.get("far")
    if far and far.get("measured_on_calibration"):  # a scenario without detectors: no rate
        body += (
            f"\nDetectors are compared at one false-alarm rate, {100 * far['target']:g} %: each "
            f"threshold (`threshold_at_far`) comes from {far['calibration_runs']} attack-free "
            f"runs of their own seed ({far['calibration_seed']}), never from these runs; "
            "`fpr_at_far` is the rate met on this study's attack-free steps."
            f"{_calibration_spread(far['target'], far['calibration_runs'] * doc['steps'])}\n"
        )
        below = below_target_note(far)
        if below:
            body += f"\n{below}\n"
    body += _network_line(doc.get("network"))
    body += software_line(doc.get("software"))
    if doc.get("skipped"):
        body += "\nSkipped: " + "; ".join(f"`{k}` ({v})" for k, v in doc["skipped"].items())
        body += ".\n"
    ckpt = doc.get("checkpoint")
    if ckpt:
        users = ", ".join(f"`{n}`" for n in ckpt["used_by"]) or "no estimator (ignored)"
        body += (
            f"\nCheckpoint: `{ckpt['path']}` ({ckpt['source']}; sha256 "
            f"{ckpt['sha256'][:16]}…{_trained_on(ckpt)}), used by {users}.\n"
        )
    for name, own in (doc.get("checkpoints") or {}).items():
        body += (f"\nCheckpoint of `{name}`: `{own['path']}` (sha256 {own['sha256'][:16]}…"
                 f"{_trained_on(own)}).\n")  # fmt: skip
    if sc.paper:
        body += f"\nPaper: {sc.paper}.\n"
    if doc["notes"]:
        body += "\n" + "\n".join(f"- {n}" for n in doc["notes"]) + "\n"
    return Section("Setting", body)


#: The estimator table's columns: every metric but the raw counts.
_TABLE_COLUMNS = tuple(name for name, m in METRICS.items() if m.kind != "integer")


def _table_section(doc: dict) -> Section:
    est = doc["estimators"]
    cols = [c for c in _TABLE_COLUMNS if any(e.get(c) is not None for e in est.values())]
    rows = [[f"`{name}`", *(format_number(e.get(c), 3) for c in cols)] for name, e in est.items()]
    table = markdown_table(["estimator", *(f"{c} [{concrete_unit(doc, c)}]" for c in cols)], rows)
    role = doc.get("estimator_roles", {})
    desc = "\n".join(f"- `{n}`{role_mark(role.get(n))}: {d}"
                     for n, d in doc["estimator_descriptions"].items())  # fmt: skip
    defs = "\n".join(f"- `{c}` [{METRICS[c].unit}]: {METRICS[c].definition}" for c in cols)
    return Section("Estimators", f"{table}\n{desc}\n\nDefinitions:\n\n{defs}\n")


def _judged(doc: dict) -> dict[str, list] | None:
    """``{learned: [Check]}``: each learned estimator of a calibrated study (a metrics.json
    ``doc``) judged against the best analytic one (:mod:`difffilter.eval.acceptance`), or
    ``None`` where there is nothing to judge."""
    est, role = doc["estimators"], doc.get("estimator_roles", {})
    # one without a detection (no tpr_at_far) is judged too: its TPR check fails for want
    # of a number (it had no row, and escaped the verdicts without a word)
    learned = [n for n in est if role.get(n) == "learned"]
    broke = [n for n, role in _broken_down(doc).items() if role == "learned"]
    if doc.get("far") is None or not (learned or broke):
        return None
    far, metric = doc["far"]["target"], state_metric(est)
    # no analytic number to compare with (--estimators listing learned ones alone): judged
    # all the same, its checks not held (the section had vanished without a word, where the
    # robustness report says "not judged")
    best = best_analytic(est, role_of=role)
    # one that broke down on the study's data has no number: every check fails (left out,
    # it vanished from the verdicts while its rivals were judged)
    return {name: judge(est.get(name, {}), best, far, metric) for name in learned + broke}


def _broken_down(doc: dict) -> dict[str, str]:
    """``{estimator: role}`` of those that broke down on the study's data (``skipped``)."""
    from .suite import broken_down

    known = registry.names()
    return {n: registry.get(n).role for n in broken_down(doc.get("skipped") or {}) if n in known}


def _acceptance_section(doc: dict) -> Section | None:
    """Each learned estimator of a calibrated study against the best analytic one
    (:mod:`difffilter.eval.acceptance`), one row per learned estimator, or ``None`` where
    there is nothing to judge."""
    judged = _judged(doc)
    if judged is None:
        return None
    checks = next(iter(judged.values()))
    header = ["learned", *(f"{c.metric} {c.bound}" for c in checks), "every check"]
    rows = [["best analytic",
             *(f"{format_number(c.best, 4)} (`{c.best_estimator}`)" if c.best_estimator else "—"
               for c in checks), ""]]  # fmt: skip
    broke = _broken_down(doc)
    for name, mine in judged.items():
        cells = [f"{format_number(c.value, 4, c.limits)} {'✓' if c.holds else '✗'}" for c in mine]
        every = "holds" if all(c.holds for c in mine) else "**fails**"
        rows.append([f"`{name}`", *cells, "**fails** (broke down)" if name in broke else every])
    text = ("Each learned estimator at the calibrated rate against the best analytic one (per "
            f"metric the best of the estimators that are {ANALYTIC}; "
            "`difffilter.eval.acceptance`).\n\n")  # fmt: skip
    if not any(c.best_estimator for c in checks):
        text += (
            "No analytic estimator of this study gives a number to compare with (none "
            "ran, or none detects or estimates the state here): the learned estimators "
            "are **not judged**, and a check not judged does not hold.\n\n"
        )
    if rivals := [n for n, role in broke.items() if role == "analytic"]:
        text += ("Broke down on this study's data, so not among the analytic estimators "
                 "compared: " + ", ".join(f"`{n}`" for n in rivals) + ".\n\n")  # fmt: skip
    body = text + markdown_table(header, rows) + "\n"
    if doc.get("acceptance_intervals"):
        body += "\n" + _intervals_text(doc["acceptance_intervals"], [c.metric for c in checks],
                                       {c.metric: c.limits for c in checks})  # fmt: skip
    clustered = [n for n in judged if n in ((doc.get("far") or {}).get("concentrated") or {})]
    if clustered:  # (a trial: "0 [0, 0], holds in 0 %" read as certain; 1.01 % on 2,000 runs)
        body += (
            "\nThe thresholds of " + ", ".join(f"`{n}`" for n in clustered) + " rest on "
            "calibration alarms that cluster in a few runs (the calibration note under Setting): "
            "their false-alarm rate on fresh runs varies with the draw of calibration runs far "
            "more than these runs show, and the intervals hold the thresholds fixed, so the "
            "false-alarm verdict is less sure than its share says; judge it on more "
            "--calibration-runs.\n"
        )
    return Section("Learned against the best analytic", body)


#: How each check's resampled statistic reads in the intervals' table.
_STATISTIC_TEXT = {"difference": "{m} − best", "ratio": "{m} / best", "value": "{m}"}


def _interval_bar(metric: str, statistic: str) -> tuple[float, ...]:
    """The bar of a headline check's statistic (:func:`~.acceptance.judge`): the TPR
    difference's margin, the attack RMSE ratio's 1, the state metric's factor."""
    if statistic == "difference":
        return (-TOLERANCES["tpr_margin"],)
    if statistic == "ratio":
        return (1.0,) if metric == "attack_rmse" else (TOLERANCES["state_factor"],)
    return ()


def _intervals_text(intervals: dict, metrics: list[str], limits: dict | None = None) -> str:
    """The acceptance's intervals over the runs (:mod:`difffilter.eval.intervals`): per
    learned estimator and check, the statistic, its interval and the share of resamples
    in which the check holds. ``limits``: each check's bounds on its value (the verdict
    cells'), which a statistic that is the value itself (``fpr_at_far``'s band) is printed
    apart from (0.0200004 had read "0.02 [0.015, 0.02]" beside its "0.0200004 ✗": a
    reports trial)."""
    limits = limits or {}
    level, runs = intervals["level"], intervals["runs"]
    if runs < 2:
        return "How sure each verdict is: not estimated from one run (nothing to resample).\n"
    rows, kinds = [], {}
    for name, checks in intervals["estimators"].items():
        cells = []
        for metric in metrics:
            c = checks.get(metric)
            if c is None or c["low"] is None:
                cells.append("—")
                continue
            kinds[metric] = c["statistic"]
            # not printed as the check's bar unless they are it (a ratio 1.0500012 that
            # fails ≤ 1.05 had read "1.05 [1.05, 1.05], holds in 0 %")
            bar = _interval_bar(metric, c["statistic"])
            if c["statistic"] == "value":
                bar = tuple(b for b in limits.get(metric) or () if b is not None)
            cells.append(f"{format_number(c['estimate'], 4, bar)} [{format_number(c['low'], 4, bar)}, "
                         f"{format_number(c['high'], 4, bar)}], holds in {share_percent(c['holds_share'])} %")  # fmt: skip
        rows.append([f"`{name}`", *cells])
    header = ["learned", *(_STATISTIC_TEXT[kinds.get(m, "value")].format(m=m) for m in metrics)]
    return (
        f"How sure each verdict is over these {runs} runs: the check's statistic, its "
        f"{100 * level:g} % interval and the share of resamples in which the check holds "
        f"(paired bootstrap over the runs, {intervals['resamples']:,} resamples, the best "
        "analytic chosen again in each; the thresholds held fixed; "
        "`difffilter.eval.intervals`).\n\n" + markdown_table(header, rows) + "\n"
    )


def write_acceptance_summary(out: str | Path, docs: dict[str, dict]) -> Path | None:
    """``<out>/acceptance.md``: every calibrated scenario's learned estimators against the
    best analytic one, one row each (the checks of each report's "Learned against the best
    analytic", with the share of resamples in which each holds); ``None`` where no study
    judges a learned estimator (an earlier evaluation's file there removed). ``docs``: ``{scenario: metrics.json content}``."""
    columns = ("TPR", "state", "attack", "false alarms")
    rows = []
    for scenario, doc in docs.items():
        judged = _judged(doc)
        if judged is None:
            continue
        sure = (doc.get("acceptance_intervals") or {}).get("estimators", {})
        trained = _checkpoint_readers(doc)
        # the networks of a checkpoint first: those are the library's claim; the others learn
        # online during the run (the LFC paper's own estimators), judged alike
        for name, checks in sorted(judged.items(), key=lambda item: item[0] not in trained):
            cells = dict.fromkeys(columns, "—")
            for c in checks:
                column = _COLUMN_OF.get(c.metric, "state")
                # the state column holds each scenario's own state metric: named where it is
                # not state_rmse (tracking's rmse_p)
                named = f" (`{c.metric}`)" if column == "state" and c.metric != "state_rmse" else ""
                cells[column] = (
                    f"{format_number(c.value, 4, c.limits)}{named} {'✓' if c.holds else '✗'}"
                    + share_suffix(sure.get(name, {}).get(c.metric))
                )
            every = "holds" if all(c.holds for c in checks) else "**fails**"
            how = "checkpoint" if name in trained else "online"
            rows.append([scenario, f"`{name}`", how, *cells.values(), every])
    path = Path(out) / "acceptance.md"
    if not rows:  # an earlier evaluation's summary would be printed as this one's
        path.unlink(missing_ok=True)
        return None
    write_atomically(
        path,
        "# Learned against the best analytic\n\nEvery learned estimator at the calibrated "
        "false-alarm rate against, per metric, the best analytic estimator of its study (TPR ≥ "
        "the best − 0.01, state error ≤ 1.05 × the best, attack error ≤ the best, measured "
        "false-alarm rate within [α/2, 2α]; `difffilter.eval.acceptance`). In brackets: the "
        "share of resamples of the runs in which the check holds (`difffilter.eval.intervals`). "
        "Each scenario's `report.md` has the bests and the intervals. Trained: from a "
        "checkpoint (trained offline, the network the evaluation was given or the shipped "
        "one), or online (a network that learns during the run, as the LFC paper's own). "
        "A — is a check that does not apply: an attack column without an analytic attack "
        "estimate to compare with (the LFC's analytic estimators estimate none on the "
        "measured states), or a metric the study does not have.\n\n"
        + markdown_table(["scenario", "learned", "trained", *columns, "every check"], rows),
    )
    return path


def _checkpoint_readers(doc: dict) -> set[str]:
    """The estimators of a study that ran a checkpoint's network (``metrics.json``'s
    ``checkpoint.used_by`` and ``checkpoints``)."""
    return {*((doc.get("checkpoint") or {}).get("used_by") or ()), *(doc.get("checkpoints") or {})}


#: The summary's column of each check (the state metric's otherwise).
_COLUMN_OF = {"tpr_at_far": "TPR", "attack_rmse": "attack", "fpr_at_far": "false alarms"}


def _markdown(doc: dict, sc, sections: list[Section]) -> str:
    parts = [f"# {doc['scenario']}\n\n{doc['description']}\n"]
    for s in sections:
        parts.append(f"## {s.title}\n\n{s.body}")
        parts += [f"![{name}]({name})\n" for name in s.figures]
    return "\n".join(parts)
