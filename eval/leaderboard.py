"""The leaderboard of one evaluation: every scenario × estimator on the headline metrics.

:func:`write_leaderboard` writes, under the evaluation's output folder,
``leaderboard.md`` (one table), ``leaderboard.json`` (its rows), ``leaderboard.png``
(one heatmap per metric, estimators × scenarios) and TensorBoard events in
``tb_leaderboard/`` (one HPARAMS row per scenario × estimator, with the checkpoint's
sha256, so that runs of different checkpoints compare side by side).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .report import format_number, markdown_table  # noqa: E402
from .scoring import HEADLINE, METRICS  # noqa: E402

__all__ = ["COLUMNS", "leaderboard_rows", "write_leaderboard"]

#: The leaderboard's columns: the headline metrics (the vs-attack-free RMSE is per scenario).
COLUMNS = tuple(m for m in HEADLINE if m != "state_rmse_vs_attack_free")


def leaderboard_rows(results: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """``[{scenario, estimator, checkpoint, <metric>: value}]`` from ``{scenario: metrics.json}``."""
    rows = []
    for scenario, doc in results.items():
        ckpt = doc.get("checkpoint") or {}
        for name, entry in (doc.get("estimators") or {}).items():
            used = name in ckpt.get("used_by", ())
            row = {"scenario": scenario, "estimator": name}
            row["checkpoint"] = ckpt.get("sha256", "")[:12] if used else None
            row.update({m: entry.get(m) for m in COLUMNS})
            rows.append(row)
    return rows


def write_leaderboard(out: str | Path, results: dict[str, dict[str, Any]]) -> Path:
    """Write the leaderboard files of ``results`` under ``out``; returns the markdown's path."""
    out = Path(out)
    rows = leaderboard_rows(results)
    (out / "leaderboard.json").write_text(json.dumps(rows, indent=2) + "\n")
    header = ["scenario", "estimator", *(f"{m} [{METRICS[m].unit}]" for m in COLUMNS)]
    cells = [
        [r["scenario"], f"`{r['estimator']}`", *(format_number(r[m], 3) for m in COLUMNS)]
        for r in rows
    ]
    path = out / "leaderboard.md"
    path.write_text(
        "# Leaderboard\n\nEvery scenario × estimator of this evaluation (definitions and "
        "units: docs/metrics.md; per-scenario details in `<scenario>/report.md`).\n\n"
        + markdown_table(header, cells)
        + "\n![leaderboard.png](leaderboard.png)\n"
    )
    _heatmaps(out / "leaderboard.png", rows)
    _hparams(out / "tb_leaderboard", rows)
    return path


HIGHER_IS_BETTER = {"auc", "tpr_at_1pct_fpr"}


def _heatmaps(path: Path, rows: list[dict[str, Any]]) -> None:
    """One panel per metric, estimators × scenarios, each cell annotated with its value and
    coloured by its rank within its scenario (green: best of that scenario)."""
    scenarios = list(dict.fromkeys(r["scenario"] for r in rows))
    estimators = list(dict.fromkeys(r["estimator"] for r in rows))
    index = {(r["scenario"], r["estimator"]): r for r in rows}
    size = (2.0 * len(COLUMNS) + 2, 0.32 * len(estimators) + 1.5)
    fig, axes = plt.subplots(1, len(COLUMNS), figsize=size, sharey=True, squeeze=False)
    for ax, metric in zip(axes[0], COLUMNS):
        values = [[index.get((s, e), {}).get(metric) for s in scenarios] for e in estimators]
        grid = np.array([[np.nan if v is None else v for v in row] for row in values], float)
        grid[~np.isfinite(grid)] = np.nan
        # min-max per scenario column (a single value or a tie counts as best)
        with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns
            lo, hi = np.nanmin(grid, 0), np.nanmax(grid, 0)
            frac = np.where(
                hi > lo, (grid - lo) / (hi - lo), 1.0 if metric in HIGHER_IS_BETTER else 0.0
            )
        goodness = np.where(
            np.isnan(grid), np.nan, frac if metric in HIGHER_IS_BETTER else 1 - frac
        )
        ax.imshow(goodness, aspect="auto", cmap="RdYlGn", vmin=0, vmax=1)
        for (i, j), value in np.ndenumerate(grid):
            if not np.isnan(value):
                ax.text(j, i, format_number(float(value), 2), ha="center", va="center", fontsize=5)
        ax.set_xticks(range(len(scenarios)), scenarios, rotation=60, ha="right", fontsize=6)
        ax.set_title(f"{metric} [{METRICS[metric].unit}]", fontsize=7)
    axes[0, 0].set_yticks(range(len(estimators)), estimators, fontsize=6)
    fig.suptitle(
        "estimators × scenarios; green = best within its scenario, blank = n/a", fontsize=8
    )
    fig.savefig(path, dpi=130, bbox_inches="tight")
    plt.close(fig)


def _hparams(logdir: Path, rows: list[dict[str, Any]]) -> None:
    from torch.utils.tensorboard import SummaryWriter

    with SummaryWriter(str(logdir)) as w:
        for r in rows:
            metrics = {f"leaderboard/{m}": r[m] for m in COLUMNS if r[m] is not None}
            hparams = {k: r[k] or "none" for k in ("scenario", "estimator", "checkpoint")}
            w.add_hparams(hparams, metrics, run_name=f"{r['scenario']}/{r['estimator']}")
