"""The leaderboard across the scenarios of one evaluation."""

from __future__ import annotations

import json

from difffilter.eval.leaderboard import COLUMNS, leaderboard_rows, write_leaderboard
from difffilter.eval.scoring import METRICS


def doc(names, ckpt=None, **values):
    entries = {n: dict.fromkeys(METRICS) | values for n in names}
    return {"estimators": entries, "checkpoint": ckpt}


def test_rows_tables_plot_and_hparams(tmp_path):
    ckpt = {"sha256": "ab" * 32, "used_by": ["net"], "path": "x", "source": "--ckpt"}
    results = {
        "plant_a": doc(["kf", "pf"], state_rmse=0.5, auc=0.9),
        "plant_b": doc(["kf", "net"], ckpt=ckpt, state_rmse=2.0, attack_rmse=0.1),
    }
    rows = leaderboard_rows(results)
    assert [(r["scenario"], r["estimator"]) for r in rows] == [
        ("plant_a", "kf"),
        ("plant_a", "pf"),
        ("plant_b", "kf"),
        ("plant_b", "net"),
    ]
    assert [r["checkpoint"] for r in rows] == [None, None, None, "ab" * 6]
    assert rows[0]["auc"] == 0.9 and rows[2]["auc"] is None and set(COLUMNS) <= set(rows[0])
    md = write_leaderboard(tmp_path, results).read_text()
    assert md.count("| plant_") == 4 and "`net`" in md and "—" in md  # missing values shown as —
    assert json.loads((tmp_path / "leaderboard.json").read_text()) == rows
    assert (tmp_path / "leaderboard.png").read_bytes()[:4] == b"\x89PNG"
    runs = {
        p.parent.relative_to(tmp_path / "tb_leaderboard").as_posix()
        for p in (tmp_path / "tb_leaderboard").rglob("events.out.tfevents*")
    }
    assert {"plant_a/kf", "plant_b/net"} <= runs  # one HPARAMS row per scenario × estimator
