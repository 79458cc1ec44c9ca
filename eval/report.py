"""The report schema shared by every evaluation (docs/architecture.md, "Reports").

``<out>/<scenario>/metrics.json``::

    {"scenario": str, "runs": int, "steps": int, "seed": int,
     "paper": {...the paper's reference numbers...},
     "estimators": {"<name>": {"state_rmse": float, "state_rmse_vs_attack_free": float|null,
                               "attack_rmse": float|null, "tpr": float|null, "fpr": float|null,
                               "auc": float|null, "detection_delay": float|null,
                               "false_alarms": int|null, "missed_attacks": int|null,
                               "time_per_step_s": float, ...extra keys}}}

Extra keys (scenario-specific numbers) may be added to an estimator entry or at the
top level; the listed keys are always present.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

__all__ = [
    "REQUIRED_KEYS",
    "estimator_entry",
    "write_metrics",
    "read_metrics",
    "format_number",
    "summary_table",
]

REQUIRED_KEYS = (
    "state_rmse",
    "state_rmse_vs_attack_free",
    "attack_rmse",
    "tpr",
    "fpr",
    "auc",
    "detection_delay",
    "false_alarms",
    "missed_attacks",
    "time_per_step_s",
)


def _clean(value: Any) -> Any:
    """JSON-safe: tensors/numpy scalars to Python numbers, NaN/inf to ``None``."""
    if hasattr(value, "item") and callable(value.item):
        try:
            value = value.item()
        except (ValueError, RuntimeError):
            value = value.tolist()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return value


def estimator_entry(
    *,
    state_rmse: float,
    time_per_step_s: float,
    state_rmse_vs_attack_free: float | None = None,
    attack_rmse: float | None = None,
    tpr: float | None = None,
    fpr: float | None = None,
    auc: float | None = None,
    detection_delay: float | None = None,
    false_alarms: int | None = None,
    missed_attacks: int | None = None,
    **extra: Any,
) -> dict[str, Any]:
    """One estimator's entry with every required key (``None`` where not applicable)."""
    entry = {
        "state_rmse": state_rmse,
        "state_rmse_vs_attack_free": state_rmse_vs_attack_free,
        "attack_rmse": attack_rmse,
        "tpr": tpr,
        "fpr": fpr,
        "auc": auc,
        "detection_delay": detection_delay,
        "false_alarms": false_alarms,
        "missed_attacks": missed_attacks,
        "time_per_step_s": time_per_step_s,
        **extra,
    }
    return _clean(entry)


def write_metrics(
    path: str | Path,
    *,
    scenario: str,
    runs: int,
    steps: int,
    seed: int,
    paper: dict[str, Any],
    estimators: dict[str, dict[str, Any]],
    **extra: Any,
) -> Path:
    """Validate and write ``metrics.json``; returns its path."""
    for name, entry in estimators.items():
        missing = [k for k in REQUIRED_KEYS if k not in entry]
        if missing:
            raise ValueError(f"estimator {name!r} lacks required metric keys {missing}")
    doc = {
        "scenario": scenario,
        "runs": runs,
        "steps": steps,
        "seed": seed,
        "paper": paper,
        "estimators": estimators,
        **extra,
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_clean(doc), indent=2, sort_keys=False) + "\n")
    return path


def read_metrics(path: str | Path) -> dict[str, Any]:
    """Load a ``metrics.json`` written by :func:`write_metrics` (``FileNotFoundError`` if absent)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no metrics file at {path}")
    return json.loads(path.read_text())


def format_number(value: Any, digits: int = 4) -> str:
    """Compact table formatting: ``—`` for missing values, scientific for small ones."""
    if value is None:
        return "—"
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if value == 0 or 1e-3 <= abs(value) < 1e4:
            return f"{value:.{digits}g}"
        return f"{value:.{max(digits - 1, 1)}e}"
    return str(value)


SUMMARY_COLUMNS = {  # metrics.json key -> terminal column label
    "state_rmse": "state RMSE",
    "state_rmse_vs_attack_free": "vs attack-free",
    "state5_rmse": "state-5 RMSE",
    "attack_rmse": "attack RMSE",
    "tpr": "TPR",
    "fpr": "FPR",
    "auc": "AUC",
}


def summary_table(results: dict[str, dict[str, Any]], digits: int = 3) -> str:
    """Plain-text headline table of ``{scenario: metrics}`` for the terminal.

    One block per scenario that has estimators, one row per estimator, the headline columns
    of :data:`SUMMARY_COLUMNS`; a column empty for every estimator of a scenario is dropped.
    The full numbers are in each scenario's ``metrics.json`` and ``report.md``.
    """
    blocks = []
    for scenario, metrics in results.items():
        rows = metrics.get("estimators") or {}
        if not rows:
            continue
        columns = [c for c in SUMMARY_COLUMNS if any(r.get(c) is not None for r in rows.values())]
        width = max(len(n) for n in [*rows, "estimator"])
        head = f"{'estimator':{width}s}" + "".join(f" {SUMMARY_COLUMNS[c]:>14s}" for c in columns)
        lines = [f"{scenario} ({metrics.get('runs')} runs × {metrics.get('steps')} steps)", head]
        for name, row in rows.items():
            cells = "".join(f" {format_number(row.get(c), digits):>14s}" for c in columns)
            lines.append(f"{name:{width}s}{cells}")
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)
