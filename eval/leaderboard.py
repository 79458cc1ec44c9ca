"""The leaderboard of one evaluation: every scenario × estimator on the headline metrics.

:func:`write_leaderboard` writes, under the evaluation's output folder,
``leaderboard.md`` (one table), ``leaderboard.json`` (its rows), ``leaderboard.png`` (the
table, each cell coloured by its distance to its scenario's best) and TensorBoard events in
``tb_leaderboard/`` (one HPARAMS row per scenario × estimator, with the checkpoint's
sha256, so that runs of different checkpoints compare side by side).
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from difffilter.models.atomic_write import write_atomically, write_json_atomically  # noqa: E402

from .acceptance import role_mark  # noqa: E402
from .plots import text_colour  # noqa: E402
from .report import format_number, json_safe, markdown_table, save_figure  # noqa: E402
from .scoring import HEADLINE, METRICS  # noqa: E402

__all__ = ["COLUMNS", "leaderboard_rows", "write_leaderboard"]

#: The leaderboard's columns: the headline metrics (the vs-attack-free RMSE is per
#: scenario), with the detection rate at the calibrated threshold (``tpr_at_far``, the
#: rate every detector is judged at) and the false-alarm rate it meets on this study's
#: attack-free steps (``fpr_at_far``) beside the ROC's ``tpr_at_1pct_fpr`` (its threshold
#: chosen on the study's own runs, attacked ones included), and the detection delay at the
#: calibrated threshold (``detection_delay_at_far_s``) in place of the delay at each
#: estimator's own alarms: a detector alarming at every step had the best delay, 0, and
#: with the TPR alone a detector alarming on 96 % of the attack-free steps looked as good
#: as the χ² test (a plug-in author's trial).
_IN_PLACE = {"tpr_at_1pct_fpr": ("tpr_at_1pct_fpr", "tpr_at_far", "fpr_at_far"),
             "detection_delay_s": ("detection_delay_at_far_s",)}  # fmt: skip
COLUMNS = tuple(
    c for m in HEADLINE if m != "state_rmse_vs_attack_free" for c in _IN_PLACE.get(m, (m,))
)
#: Roles marked beside an estimator's name (an analytic one is unmarked); the best of a
#: scenario, green in the figure, is that of the estimators that are neither
#: (:data:`UNRANKED`).
#: ``more_data`` too: an estimator fed more than the others (the tracking plant's
#: ``pf_da``, every sensor's packet at every step) had set its scenario's best, where the
#: acceptance leaves it out of the best as well (a red-team trial).
UNRANKED = ("oracle", "reference", "more_data")
#: The columns at the calibrated threshold (none where nothing was calibrated).
_AT_FAR = ("tpr_at_far", "fpr_at_far", "detection_delay_at_far_s")
#: The worst case over a robustness study's threats, as ``worst_<metric>`` columns.
WORST = ("tpr_at_far", "state_error_ratio")
_WORST_UNITS = {"worst_tpr_at_far": "fraction", "worst_state_error_ratio": "ratio"}


def leaderboard_rows(results: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """``[{scenario, estimator, checkpoint, <metric>: value}]`` from ``{scenario: metrics.json}``."""
    rows = []
    for scenario, doc in results.items():
        ckpt = doc.get("checkpoint") or {}
        for name, entry in (doc.get("estimators") or {}).items():
            used = name in ckpt.get("used_by", ())
            row = {"scenario": scenario, "estimator": name,
                   "role": (doc.get("estimator_roles") or {}).get(name)}  # fmt: skip
            named = doc.get("scenario_units") or {}
            row["units"] = {"state": named.get("state", "state units"),
                            "attack": named.get("attack", "attack units")}  # fmt: skip
            own = (doc.get("checkpoints") or {}).get(name)  # --ckpt NAME=PATH: its own file
            if own is not None:
                row["checkpoint"] = own["sha256"][:12]
            else:
                row["checkpoint"] = ckpt.get("sha256", "")[:12] if used else None
            row.update({m: entry.get(m) for m in COLUMNS})
            # which study: its rows in TensorBoard told two seeds apart by nothing (a trial)
            row["seed"], row["runs"] = doc.get("seed"), doc.get("runs")
            row["far_target"] = (doc.get("far") or {}).get("target")  # fpr_at_far's colour
            row["dt_s"] = doc.get("dt_s")  # a delay's colour: one step is its resolution
            worst = (doc.get("worst_case") or {}).get(name)
            if worst is not None:  # a robustness study: the worst case over its threats
                # (a diverged state error is the worst there is: inf, null in the JSON
                # with worst_<metric>_diverged)
                row.update({f"worst_{m}": math.inf if worst.get(f"{m}_diverged") else worst.get(m)
                            for m in WORST})  # fmt: skip
                # (and why there is no number: not run under a threat, broken down; a
                # "not run" had printed "—", as a metric that does not apply)
                row.update({f"worst_{m}_{flag}": True for m in WORST for flag in _FLAGS
                            if worst.get(f"{m}_{flag}")})  # fmt: skip
            rows.append(row)
    return rows


def write_leaderboard(out: str | Path, results: dict[str, dict[str, Any]]) -> Path:
    """Write the leaderboard files of ``results`` under ``out``; returns the markdown's path.
    Of a robustness study (rows with ``worst_*`` columns) the headline columns are its
    attack-free runs', the detection columns that are empty there left out, and the
    worst-case columns follow (in the table and its figure)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)  # (as the other writers: a missing folder failed)
    rows = leaderboard_rows(results)
    # (inf as null, its worst_<metric>_diverged saying why: json.dumps wrote the bare token
    # Infinity, which strict JSON readers refuse: a review)
    write_json_atomically(out / "leaderboard.json", json_safe(rows))
    if not rows:  # (the figure of no rows failed in matplotlib, after every report was written)
        path = out / "leaderboard.md"
        write_atomically(path, "# Leaderboard\n\nNo estimator ran: each scenario's `report.md` "
                         "lists those skipped and why.\n" + _skipped(results))  # fmt: skip
        (out / "leaderboard.png").unlink(missing_ok=True)
        _hparams(out / "tb_leaderboard", rows)
        return path
    worst = [c for c in _WORST_UNITS if any(c in r for r in rows)]
    cols = list(COLUMNS)
    # nothing calibrated (--far off): no threshold, so no columns at one (a docs trial read
    # three columns of "—" under text describing them)
    calibrated = any(r.get(m) is not None for r in rows for m in _AT_FAR)
    if worst:  # attack-free runs: no attack to detect, nothing in the detection columns
        cols = [m for m in cols if any(r.get(m) is not None for r in rows)]
    elif not calibrated:
        cols = [m for m in cols if m not in _AT_FAR]
    cols += worst
    units = {**{m: METRICS[m].unit for m in COLUMNS}, **_WORST_UNITS}
    # one unit per column where every scenario shares it; else the row's units in a column
    shared = {}
    for kind in ("state", "attack"):
        values = {r["units"][kind] for r in rows}
        if len(values) == 1:
            shared[f"{kind} units"] = values.pop()
    units = {m: shared.get(u, u) for m, u in units.items()}
    mixed = len(shared) < 2
    header = ["scenario", "estimator", *(f"{m} [{units[m]}]" for m in cols)]
    if mixed:
        header.insert(2, "units (state; attack)")
    cells = []
    for r in rows:
        cell = [r["scenario"], f"`{r['estimator']}`{_role_mark(r)}",
                *(_flag_text(r, m) or _value_text(r, m, r.get(m)) for m in cols)]  # fmt: skip
        if mixed:
            cell.insert(2, f"{r['units']['state']}; {r['units']['attack']}")
        cells.append(cell)
    intro = (
        "Every scenario × estimator of this robustness study: the first columns on its "
        "attack-free runs, the `worst_` columns the worst case over the scenario's threats "
        "(definitions and units: docs/metrics.md; per-scenario details in "
        "`<scenario>/robustness.md`, the worst cases with their threats in `robustness.md`)."
        if worst
        else "Every scenario × estimator of this evaluation (definitions and units: "
        "docs/metrics.md; per-scenario details in `<scenario>/report.md`). `tpr_at_far` is "
        "the detection rate at the threshold calibrated on attack-free runs, the rate every "
        "detector is judged at, `fpr_at_far` the false-alarm rate that threshold meets on "
        "this study's attack-free steps (those after an attack included) and "
        "`detection_delay_at_far_s` the delay at it; `tpr_at_1pct_fpr` reads the ROC of the "
        "study's own runs."
        if calibrated
        else "Every scenario × estimator of this evaluation (definitions and units: "
        "docs/metrics.md; per-scenario details in `<scenario>/report.md`). No estimator here "
        "raises alarms, so none has a threshold at the target false-alarm rate: there are no "
        "`*_at_far` columns; `tpr_at_1pct_fpr` reads the ROC of the study's own runs."
        # (--far given, a scenario of filters alone: it had said "--far off", a trial)
        if any(r.get("far_target") is not None for r in rows)
        else "Every scenario × estimator of this evaluation (definitions and units: "
        "docs/metrics.md; per-scenario details in `<scenario>/report.md`). Nothing was "
        "calibrated (`--far off`): no detector has a threshold at a false-alarm rate, so "
        "there are no `*_at_far` columns and no acceptance summary; `tpr_at_1pct_fpr` reads "
        "the ROC of the study's own runs."
    )
    if any(r.get("role") not in (None, "analytic") for r in rows):
        intro += (" An estimator's role is marked beside its name where it is not an analytic "
                  "one: an oracle reads what no deployed estimator knows (the true attack's "
                  "size, the plant's load), a reference runs on the attack-free measurements; "
                  "neither sets the best of a scenario in the figure.")  # fmt: skip
    path = out / "leaderboard.md"
    write_atomically(
        path,
        f"# Leaderboard\n\n{intro}\n\n"
        + markdown_table(header, cells)
        + _skipped(results)
        + "\n![leaderboard.png](leaderboard.png)\n",
    )
    _heatmaps(out / "leaderboard.png", rows, {m: units[m] for m in cols})
    _hparams(out / "tb_leaderboard", rows)
    return path


#: Why a worst case has no number (or an infinite one), in the order a cell says it
#: (``worst_<metric>_<flag>``, from the robustness study's worst cases).
_FLAGS = ("not_run", "broke_down", "diverged")


def _flag_text(row: dict[str, Any], metric: str) -> str | None:
    """``"not run"``, ``"broke down"`` or ``"diverged"`` where ``row``'s worst case of
    ``metric`` carries that flag, else ``None``."""
    for flag in _FLAGS:
        if row.get(f"{metric}_{flag}"):
            return flag.replace("_", " ")
    return None


def _role_mark(row: dict[str, Any]) -> str:
    """``" (oracle)"`` beside a name whose role is not analytic (``""`` for one that is,
    or whose study recorded no roles)."""
    return role_mark(row.get("role"))


def _skipped(results: dict[str, dict[str, Any]]) -> str:
    """The estimators a scenario left out, with why: a reader looked for a row that was not
    there (``--ckpt`` of another estimator's checkpoint leaves the scenario's own out)."""
    lines = [f"- {scenario}: `{name}` ({why})" for scenario, doc in results.items()
             for name, why in (doc.get("skipped") or {}).items()]  # fmt: skip
    return "\nNot run (no row above):\n\n" + "\n".join(lines) + "\n" if lines else ""


HIGHER_IS_BETTER = {"auc", "tpr_at_1pct_fpr", "tpr_at_far", "worst_tpr_at_far"}
#: Detection rates: a column of a scenario whose best is at most this (twice the 1 %
#: false-alarm budget, the top of the calibrated false-alarm band) is left uncoloured:
#: no estimator detects, and every 0 beside a best of 0.005 was painted "best".
DETECTION_RATES = {"tpr_at_1pct_fpr", "tpr_at_far", "worst_tpr_at_far"}
UNDETECTED = 0.02
#: The detection rates at the calibrated threshold, whose band is twice the calibrated rate
#: (``tpr_at_1pct_fpr`` is read at 1 % of the study's own ROC whatever ``--far`` says).
AT_FAR = {"tpr_at_far", "worst_tpr_at_far"}


#: Columns coloured by their distance to the calibrated false-alarm band [α/2, 2α] (the
#: acceptance's), not to the best: a detector that never alarms (0) is not the best there.
ON_TARGET = {"fpr_at_far"}


#: Delay columns: a difference below one sampling period is no difference (one late step in
#: 243 episodes, 0.004 s against 0, painted the χ² test red beside an estimator of delay 0).
DELAYS = {"detection_delay_s", "detection_delay_at_far_s"}


def cell_goodness(grid: np.ndarray, scenarios: list[str], columns=COLUMNS,
                  ranked: np.ndarray | None = None, targets: np.ndarray | None = None,
                  steps_s: np.ndarray | None = None,
                  off_band: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """``grid [rows, columns]`` → colour in [0, 1] (1: the best of the row's scenario): for
    AUC and TPR 1 − (best − v)/0.1, so 0.1 below the best is 0; otherwise
    1 − log10((v + f)/(best + f)), so 10× the best is 0, with a floor f of 5 % of the
    scenario's largest value so that zeros and round-off differences do not paint a cell red.
    ``ranked [rows]`` (bool): the rows that may set the best (not an oracle nor the
    reference; all rows where none of a scenario is, or without it); a row that is not
    may be better than the best and reads 1. NaN (no colour) where the value is missing,
    and in a detection-rate column whose best is at most twice the scenario's ``targets``
    (the columns of :data:`AT_FAR`; :data:`UNDETECTED` for ``tpr_at_1pct_fpr`` and without
    a target: :func:`_undetected`). A column of
    :data:`ON_TARGET` is 1 inside ``[α/2, 2α]`` of its row's target ``targets [rows]`` (the
    calibrated rate; uncoloured without one) and falls to 0 at 10× outside it. A delay
    column (:data:`DELAYS`) with its scenario's sampling period ``steps_s [rows]`` falls
    linearly with the steps behind the best: ``1 − (v − best)/(10 Δt)``, 10 steps behind
    is 0 (without a period, the log rule). ``+inf`` (a diverged worst case)
    in a lower-is-better column is 0. ``off_band [rows, columns]`` (bool): cells read at a
    calibrated threshold whose false-alarm rate is outside its band (:func:`off_band_cells`),
    which may not set the best either (a detection rate of 0.9925 at 98.7 % false alarms
    had been the best, and an in-band 0.975 painted 0.82: a report trial)."""
    scen, good = np.array(scenarios), np.full_like(grid, np.nan)
    ranked = np.ones(len(scenarios), bool) if ranked is None else np.asarray(ranked, bool)
    higher = np.array([m in HIGHER_IS_BETTER for m in columns])
    rates = np.array([m in DETECTION_RATES for m in columns])
    calibrated = np.array([m in AT_FAR for m in columns])
    delays = np.array([m in DELAYS for m in columns])
    diverged = np.isposinf(grid) & ~higher
    grid = np.where(np.isfinite(grid), grid, np.nan)
    for s in dict.fromkeys(scenarios):
        rows = scen == s
        g = grid[rows]
        comparable = g if off_band is None else np.where(off_band[rows], np.nan, g)
        judged = comparable[ranked[rows]] if ranked[rows].any() else comparable
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns
            lo, hi = np.nanmin(judged, 0), np.nanmax(judged, 0)
            floor = np.maximum(0.05 * np.abs(np.nanmax(g, 0)), 1e-300)
            shortfall = np.where(higher, (hi - g) / 0.1, np.log10((g + floor) / (lo + floor)))
            if steps_s is not None and np.isfinite(steps_s[rows]).any():
                # steps behind the best, linearly: the log rule read 10 steps behind a best
                # of 20 as 0.83 (nearly green), where the legend says red
                step = np.nanmax(steps_s[rows])
                shortfall = np.where(delays, (g - lo) / (10 * step), shortfall)
        colour = np.clip(1 - shortfall, 0, 1)
        band = np.where(calibrated, _undetected(targets, rows), UNDETECTED)
        colour[:, rates & ~(hi > band)] = np.nan
        colour[diverged[rows]] = 0.0
        good[rows] = colour
    on_target = np.array([m in ON_TARGET for m in columns])
    if on_target.any():
        alpha = (np.full(len(scenarios), np.nan) if targets is None
                 else np.asarray(targets, float))[:, None]  # fmt: skip
        v = grid[:, on_target]
        with np.errstate(divide="ignore", invalid="ignore"):
            outside = np.maximum(np.log10(v / (2 * alpha)), np.log10((alpha / 2) / v))
        good[:, on_target] = np.where(np.isnan(v) | np.isnan(alpha), np.nan,
                                      np.clip(1 - np.maximum(outside, 0), 0, 1))  # fmt: skip
    return good


def _undetected(targets: np.ndarray | None, rows: np.ndarray) -> float:
    """The detection rate at or below which a scenario's column is left uncoloured: twice
    its calibrated false-alarm rate (the top of the calibrated band), :data:`UNDETECTED`
    (twice 1 %) where the rows have none (a rate of 2 % is chance at a 2 % budget: a
    study at ``--far 0.02`` had painted 0.026 green)."""
    if targets is None:
        return UNDETECTED
    alpha = np.asarray(targets, float)[rows]
    alpha = alpha[np.isfinite(alpha)]
    return float(2 * alpha.max()) if alpha.size else UNDETECTED


def _value_text(row: dict[str, Any], metric: str, value) -> str:
    """A cell's number, three digits; a false-alarm rate never printed as its row's band
    edge ``α/2`` or ``2α`` unless it is one (0.0200004 had printed "0.02" in a row hatched
    as outside the band [0.005, 0.02]: a report trial)."""
    alpha = row.get("far_target")
    edges = (alpha / 2, 2 * alpha) if metric in ON_TARGET and alpha is not None else ()
    return format_number(value, 3, apart_from=edges)


def _heatmaps(path: Path, rows: list[dict[str, Any]], units: dict[str, str]) -> None:
    """The leaderboard as a coloured table: a row per scenario × estimator, a column per
    metric of ``units`` (``{metric: its unit as the table prints it}``), each cell annotated
    with its value and coloured by :func:`cell_goodness`."""
    cols = list(units)
    grid = np.array([[np.nan if r.get(m) is None else r[m] for m in cols] for r in rows], float)
    grid[np.isneginf(grid)], scenarios = np.nan, [r["scenario"] for r in rows]  # (+inf: diverged)
    fig, ax = plt.subplots(figsize=(1.1 * len(cols) + 3, 0.2 * len(rows) + 1.2))
    ranked = ranked_rows(rows)
    cmap = plt.get_cmap("RdYlGn").with_extremes(bad="white")
    targets = np.array([np.nan if r.get("far_target") is None else r["far_target"]
                        for r in rows])  # fmt: skip
    steps_s = np.array([np.nan if r.get("dt_s") is None else r["dt_s"] for r in rows], float)
    hatched = off_band_cells(rows, cols)
    off_band = np.zeros(grid.shape, bool)
    off_band[tuple(np.array(hatched, int).reshape(-1, 2).T)] = True
    goodness = cell_goodness(grid, scenarios, cols, ranked, targets, steps_s, off_band)
    ax.imshow(goodness, aspect="auto", cmap=cmap, vmin=0, vmax=1)
    for (i, j), value in np.ndenumerate(grid):
        text = (_flag_text(rows[i], cols[j]) or ("—" if np.isnan(value) else "diverged"
                if np.isposinf(value) else _value_text(rows[i], cols[j], float(value))))  # fmt: skip
        ax.text(j, i, text, ha="center", va="center", fontsize=6,
                color=text_colour(float(goodness[i, j])))  # fmt: skip
    for i, j in hatched:
        ax.add_patch(plt.Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, hatch="////",
                                   edgecolor="0.35", lw=0))  # fmt: skip
    for i in np.flatnonzero(np.array(scenarios[1:]) != np.array(scenarios[:-1])):
        ax.axhline(i + 0.5, color="black", linewidth=0.8)  # between two scenarios
    ax.set_yticks(range(len(rows)),
                  [f"{s} · {r['estimator']}{_role_mark(r)}" for s, r in zip(scenarios, rows)])  # fmt: skip
    ax.set_xticks(range(len(cols)), [f"{m}\n[{unit}]" for m, unit in units.items()])
    ax.tick_params(labelsize=6, top=True, labeltop=True, bottom=False, labelbottom=False)
    ax.set_title("green: the best of its scenario (of the estimators not marked oracle, "
                 "reference or more data); red: 10× it (v + f against best + f, f = 5 % of "
                 "the scenario's largest; 0.1 below: AUC, TPR; a delay: 10 steps behind);\n"
                 "fpr_at_far: green inside [α/2, 2α], red 10× outside; white: no value, or a "
                 "detection rate no estimator of the scenario lifts above 2α (2 × its "
                 "calibrated false-alarm rate; 0.02 for tpr_at_1pct_fpr); hatched: read at a "
                 "threshold whose fpr_at_far is outside [α/2, 2α] (never the best)",
                 fontsize=7)  # fmt: skip
    save_figure(fig, path, dpi=130, bbox_inches="tight")
    plt.close(fig)


#: The columns read at the calibrated threshold (:data:`_AT_FAR` but its false-alarm rate):
#: their values stand only where that threshold met its false-alarm band.
#: A robustness leaderboard's worst-case detection rate is read there too (with no
#: ``tpr_at_far`` column beside it, a 0.991 at 57 % false alarms had been left unhatched).
AT_CALIBRATED_THRESHOLD = (*(m for m in _AT_FAR if m != "fpr_at_far"), "worst_tpr_at_far")


def ranked_rows(rows: list[dict[str, Any]]) -> np.ndarray:
    """``[rows]`` bool: the rows that may set their scenario's best (not :data:`UNRANKED`)."""
    return np.array([r.get("role") not in UNRANKED for r in rows], dtype=bool)


def off_band_cells(rows: list[dict[str, Any]], cols: list[str]) -> list[tuple[int, int]]:
    """``[(row, column)]`` of the cells of :data:`AT_CALIBRATED_THRESHOLD` whose row's
    ``fpr_at_far`` lies outside ``[α/2, 2α]`` of its ``far_target``: a detection rate
    bought with false alarms (the four-tank normal PF's 0.991 at 57 % false alarms was
    painted green as the best: a figure review)."""
    cells = []
    for i, r in enumerate(rows):
        rate, alpha = r.get("fpr_at_far"), r.get("far_target")
        if rate is None or alpha is None or not np.isfinite([rate, alpha]).all():
            continue
        if alpha / 2 <= rate <= 2 * alpha:
            continue
        cells += [(i, j) for j, m in enumerate(cols) if m in AT_CALIBRATED_THRESHOLD]
    return cells


def _hparams(logdir: Path, rows: list[dict[str, Any]]) -> None:
    """One HPARAMS row per scenario × estimator; the folder holds this leaderboard's rows
    only (an earlier evaluation's events into the same ``--out`` removed, as its
    ``leaderboard.md`` is replaced)."""
    from torch.utils.tensorboard import SummaryWriter

    from .tensorboard import add_session, clear_events

    clear_events(logdir)
    with SummaryWriter(str(logdir)) as w:
        for r in rows:
            metrics = {
                f"leaderboard/{m}": r[m] for m in (*COLUMNS, *_WORST_UNITS) if r.get(m) is not None
            }  # (a robustness study's worst case too)
            hparams = {k: r[k] or "none" for k in ("scenario", "estimator", "checkpoint")}
            hparams.update({k: r[k] for k in ("seed", "runs") if r.get(k) is not None})
            add_session(w, f"{r['scenario']}/{r['estimator']}", hparams, metrics)
