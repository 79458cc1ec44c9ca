"""The leaderboard across the scenarios of one evaluation."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import session_scalars

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


def test_colours_measure_the_distance_to_the_best_of_each_scenario():
    import numpy as np

    from difffilter.eval.leaderboard import cell_goodness

    col = {m: i for i, m in enumerate(COLUMNS)}
    grid = np.full((4, len(COLUMNS)), np.nan)
    grid[:, col["auc"]] = [0.999, 0.997, 0.949, 0.5]
    grid[:, col["state_rmse"]] = [0.1, 0.1, 1.0, np.sqrt(10) * 0.1]
    grid[:, col["detection_delay_at_far_s"]] = [0.0, 0.01, 1.0, 0.0]
    good = cell_goodness(grid, ["a"] * 4)
    assert good[:, col["auc"]] == pytest.approx([1.0, 0.98, 0.5, 0.0])  # 0.1 below the best: red
    rmse = good[:, col["state_rmse"]]  # log10 of the ratio, with a floor of 5 % of the largest
    f = 0.05
    assert rmse == pytest.approx(
        [1, 1, 1 - np.log10(1.05 / (0.1 + f)), 1 - np.log10((0.316 + f) / 0.15)], abs=1e-3
    )
    delay = good[:, col["detection_delay_at_far_s"]]  # zeros are the best; 0.01 is near them
    assert delay == pytest.approx([1, 1 - np.log10(0.06 / 0.05), 0, 1])
    assert np.isnan(good[:, col["attack_rmse"]]).all()  # n/a stays blank
    other = cell_goodness(np.vstack([grid, grid * 10]), ["a"] * 4 + ["b"] * 4)
    assert other[4:, col["state_rmse"]] == pytest.approx(rmse, abs=1e-12)  # scale-free per scenario


def test_units_are_the_scenarios_shared_in_the_header_or_per_row_when_mixed(tmp_path):
    def with_units(state, attack, **values):
        return doc(["kf"], **values) | {"scenario_units": {"state": state, "attack": attack}}

    same = {"tank_a": with_units("cm", "cm", state_rmse=0.5), "tank_b": with_units("cm", "cm")}
    (tmp_path / "same").mkdir(), (tmp_path / "mixed").mkdir()
    md = write_leaderboard(tmp_path / "same", same).read_text()
    assert (
        "state_rmse [cm]" in md and "attack_rmse [cm]" in md and "units (state; attack)" not in md
    )
    mixed = {"tank": with_units("cm", "cm"), "grid": with_units("p.u.", "p.u."), "old": doc(["kf"])}
    md = write_leaderboard(tmp_path / "mixed", mixed).read_text()
    assert "state_rmse [state units]" in md and "units (state; attack)" in md
    assert "| tank | `kf` | cm; cm |" in md and "| grid | `kf` | p.u.; p.u. |" in md
    assert "| old | `kf` | state units; attack units |" in md  # a study that names none


def test_a_second_leaderboard_into_the_same_folder_holds_only_its_own_rows(tmp_path):
    """A user trial: tb_leaderboard kept the first evaluation's HPARAMS rows beside the
    second's, while leaderboard.md held only the second's."""

    write_leaderboard(tmp_path, {"plant_a": doc(["kf", "pf"], state_rmse=0.5)})
    write_leaderboard(tmp_path, {"plant_a": doc(["kf"], state_rmse=0.25)})
    files = list((tmp_path / "tb_leaderboard").rglob("events.out.tfevents*"))
    runs = {p.parent.relative_to(tmp_path / "tb_leaderboard").as_posix() for p in files}
    assert runs == {".", "plant_a/kf"} and len(files) == 2
    row = session_scalars(tmp_path / "tb_leaderboard" / "plant_a" / "kf")
    assert row["leaderboard/state_rmse"] == [0.25]


def test_a_robustness_leaderboard_says_what_its_columns_are_and_plots_the_worst_case(
    tmp_path, monkeypatch
):
    """A user trial: the robustness study's leaderboard kept the attack-free study's empty
    detection columns unexplained, sent readers to a report.md it does not write, and its
    figure left out the worst-case columns; the figure also printed placeholder units."""
    from difffilter.eval import leaderboard

    drawn = {}
    monkeypatch.setattr(leaderboard, "_heatmaps", lambda path, rows, units: drawn.update(units))
    study = doc(["kf", "net"], state_rmse=0.5, time_per_step_s=1e-4)
    study |= {"worst_case": {"kf": {"tpr_at_far": 0.3, "state_error_ratio": 2.0},
                             "net": {"tpr_at_far": 0.5, "state_error_ratio": 1.5}},
              "scenario_units": {"state": "cm", "attack": "cm"}}  # fmt: skip
    md = write_leaderboard(tmp_path, {"tank": study}).read_text()
    assert "robustness study" in md and "`<scenario>/robustness.md`" in md
    assert "`<scenario>/report.md`" not in md and "auc" not in md and "tpr_at_1pct_fpr" not in md
    assert "worst_tpr_at_far [fraction]" in md and "| tank | `net` |" in md
    # the attack-free columns with a value, then the worst case
    assert list(drawn) == ["state_rmse", "time_per_step_s", "worst_tpr_at_far",
                           "worst_state_error_ratio"]  # fmt: skip
    assert drawn["state_rmse"] == "cm" and drawn["worst_state_error_ratio"] == "ratio"
    good = leaderboard.cell_goodness(np.array([[0.3], [0.5]]), ["t", "t"], ["worst_tpr_at_far"])
    assert good[:, 0].tolist() == pytest.approx([0.0, 1.0])  # a higher worst-case TPR is better


def test_a_leaderboard_of_no_estimator_says_so(tmp_path):
    """A contributor's trial: a scenario none of whose estimators fit it failed in
    matplotlib ("Invalid shape (0,) for image data") after its report was written."""
    md = write_leaderboard(tmp_path, {"plant": {"estimators": {}, "checkpoint": None}}).read_text()
    assert "No estimator ran" in md and not (tmp_path / "leaderboard.png").exists()
    assert json.loads((tmp_path / "leaderboard.json").read_text()) == []


def test_the_leaderboard_lists_the_estimators_a_scenario_left_out(tmp_path):
    """A reviewer looked for the shipped network's row after --ckpt of another estimator's
    checkpoint: it was skipped, said only in metrics.json and report.md."""
    results = {"plant_a": doc(["kf"], state_rmse=0.5) | {"skipped": {"net": "no --ckpt given"}},
               "plant_b": doc(["kf"], state_rmse=0.5)}  # fmt: skip
    md = write_leaderboard(tmp_path, results).read_text()
    assert "Not run (no row above):\n\n- plant_a: `net` (no --ckpt given)\n" in md
    alone = write_leaderboard(tmp_path, {"plant_b": doc(["kf"], state_rmse=0.5)}).read_text()
    assert "Not run" not in alone


def test_the_best_is_set_by_the_ranked_estimators_and_roles_are_marked(tmp_path):
    """A reviewer: the best of a scenario (green) was set by an oracle's attack RMSE and the
    attack-free reference's state RMSE, unmarked; a worst-case TPR whose best is 0.005 (no
    one detects) painted every 0 green; the robustness leaderboard's TensorBoard rows left
    out the worst-case columns, its point."""

    from difffilter.eval.leaderboard import UNDETECTED, cell_goodness

    col = {m: i for i, m in enumerate(COLUMNS)}
    grid = np.full((3, len(COLUMNS)), np.nan)
    grid[:, col["attack_rmse"]] = [0.01, 0.1, 1.0]  # the oracle, then two others
    grid[:, col["tpr_at_far"]] = [0.9, 0.5, 0.4]
    grid[:, col["tpr_at_1pct_fpr"]] = [0.0, UNDETECTED, 0.0]
    good = cell_goodness(grid, ["a"] * 3, ranked=np.array([False, True, True]))
    assert good[:, col["attack_rmse"]] == pytest.approx([1.0, 1.0, 1 - np.log10(1.05 / 0.15)])
    assert good[:, col["tpr_at_far"]] == pytest.approx([1.0, 1.0, 0.0])  # 0.1 below the ranked best
    assert np.isnan(good[:, col["tpr_at_1pct_fpr"]]).all()  # no one detects: no colour
    # the band scales with the calibrated rate (a trial at --far 0.02: 0.026 painted green)
    grid[:, col["tpr_at_far"]] = [0.0, 0.026, 0.01]
    at = {far: cell_goodness(grid, ["a"] * 3, targets=np.full(3, far))[:, col["tpr_at_far"]]
          for far in (0.01, 0.02)}  # fmt: skip
    assert not np.isnan(at[0.01]).any() and np.isnan(at[0.02]).all()
    # ... and tpr_at_1pct_fpr, read at 1 % whatever the calibrated rate, keeps 0.02 (a review)
    grid[:, col["tpr_at_1pct_fpr"]] = [0.0, 0.015, 0.0]
    low = cell_goodness(grid, ["a"] * 3, targets=np.full(3, 0.001))[:, col["tpr_at_1pct_fpr"]]
    assert np.isnan(low).all()
    unranked = cell_goodness(grid, ["a"] * 3)
    assert unranked[1, col["attack_rmse"]] < 1  # the oracle is the best when it may be

    study = doc(["oracle_pf", "reference_pf", "kf"], attack_rmse=0.5, tpr_at_far=0.7)
    study["estimator_roles"] = {
        "oracle_pf": "oracle",
        "reference_pf": "reference",
        "kf": "analytic",
    }
    rows = leaderboard_rows({"tank": study})
    assert [r["role"] for r in rows] == ["oracle", "reference", "analytic"]
    (tmp_path / "a").mkdir(), (tmp_path / "b").mkdir()
    md = write_leaderboard(tmp_path / "a", {"tank": study}).read_text()
    assert "`oracle_pf` (oracle)" in md and "`reference_pf` (reference)" in md
    assert "| `kf` |" in md and "tpr_at_far [fraction]" in md and "role is marked" in md

    robust = doc(["kf"], state_rmse=0.5) | {
        "worst_case": {"kf": {"tpr_at_far": 0.3, "state_error_ratio": 2.0}}
    }
    write_leaderboard(tmp_path / "b", {"tank": robust})
    tags = set(session_scalars(tmp_path / "b" / "tb_leaderboard" / "tank" / "kf"))
    assert {"leaderboard/worst_tpr_at_far", "leaderboard/worst_state_error_ratio"} <= tags


def test_a_fraction_just_below_one_is_not_printed_as_one():
    """An AUC of 0.999924 printed "1" in report.md and the leaderboard, a perfect
    detector's figure."""
    from difffilter.eval.report import format_number

    assert format_number(0.999924, 3) == "0.9999" and format_number(0.999924) == "0.9999"
    assert format_number(1.0, 3) == "1" and format_number(0.9996) == "0.9996"
    assert format_number(1.00004) == "1.00004" and format_number(12.0004) == "12"
    assert format_number(1 - 1e-12) == "1"  # at most eight digits


def test_the_false_alarm_column_is_coloured_by_its_distance_to_the_calibrated_band():
    """A review: coloured "lower is better", a detector that never alarms was green and the
    ones calibrated to α red; the acceptance judges the rate against [α/2, 2α]."""
    from difffilter.eval.leaderboard import cell_goodness

    v = np.array([[0.0], [0.01], [0.006], [0.02], [0.2], [0.05], [np.nan]])
    good = cell_goodness(v, ["a"] * 7, ["fpr_at_far"], targets=np.full(7, 0.01))[:, 0]
    assert good[0] == 0 and good[1] == good[2] == good[3] == 1  # never alarms; in the band
    assert good[4] == 0 and 0 < good[5] < 1  # 10x above 2α: red; 2.5x: between
    assert np.isnan(good[6])
    assert np.isnan(cell_goodness(v, ["a"] * 7, ["fpr_at_far"])[:, 0]).all()  # no target


def test_a_delay_below_one_step_is_no_difference_and_a_diverged_worst_case_is_red():
    """A re-check: at the calibrated threshold the χ² test was one step late in one of 243
    episodes (0.004 s) beside detectors of delay 0, and was painted red; a diverged worst
    state error was left uncoloured ('—')."""
    from difffilter.eval.leaderboard import cell_goodness

    delays = np.array([[0.0], [0.00412], [0.0082], [1.0], [10.0]])
    good = cell_goodness(delays, ["a"] * 5, ["detection_delay_at_far_s"],
                         steps_s=np.full(5, 1.0))[:, 0]  # fmt: skip
    assert good[0] == 1 and good[1] > 0.99 and good[2] > 0.99  # within a step of the best
    assert good[3] == pytest.approx(0.9) and good[4] == 0  # one step late; ten: red
    # ten steps behind a slow best is red too (a trial: 0.83 behind a best of 20 steps, by a
    # log rule that reached 0 only behind a best of 0)
    slow = cell_goodness(np.array([[2.0], [3.0], [2.5]]), ["a"] * 3, ["detection_delay_at_far_s"],
                         steps_s=np.full(3, 0.1))[:, 0]  # fmt: skip
    assert slow[0] == 1 and slow[1] == 0 and slow[2] == pytest.approx(0.5)
    worst = np.array([[1.2], [np.inf], [3.0]])
    good = cell_goodness(worst, ["a"] * 3, ["worst_state_error_ratio"])[:, 0]
    assert good[0] == 1 and good[1] == 0


def test_a_diverged_worst_case_reads_diverged_in_the_robustness_leaderboard():
    from difffilter.eval.leaderboard import leaderboard_rows

    doc = {"estimators": {"mine": {}, "kf": {}}, "far": {"target": 0.01}, "dt_s": 1.0,
           "worst_case": {"mine": {"state_error_ratio": None, "state_error_ratio_diverged": True,
                                   "state_error_ratio_threat": "bias"},
                          "kf": {"state_error_ratio": 2.0}}}  # fmt: skip
    rows = {r["estimator"]: r for r in leaderboard_rows({"s": doc})}
    assert rows["mine"]["worst_state_error_ratio"] == math.inf
    assert rows["mine"]["worst_state_error_ratio_diverged"] is True
    assert rows["kf"]["worst_state_error_ratio"] == 2.0


def test_a_worst_case_not_run_or_broken_down_says_so_in_the_leaderboard(tmp_path):
    """An estimator not run under a threat had a worst case of "—" in leaderboard.md and
    null without a flag in leaderboard.json, as a metric that does not apply, where
    robustness.md says "not run (ramp)" (a red-team trial)."""
    free = {"fpr_at_far": 0.01, "state_rmse": 0.1}
    results = {"s": {"estimators": {"kf": dict(free), "nn": dict(free), "pf": dict(free)},
                     "far": {"target": 0.01}, "dt_s": 1.0,
                     "worst_case": {
                         "kf": {"tpr_at_far": 0.5, "state_error_ratio": 2.0},
                         "nn": {m: None for m in ("tpr_at_far", "state_error_ratio")}
                         | {"tpr_at_far_not_run": True, "state_error_ratio_not_run": True},
                         "pf": {"tpr_at_far": 0.4, "state_error_ratio": None,
                                "state_error_ratio_diverged": True,
                                "state_error_ratio_broke_down": True}}}}  # fmt: skip
    rows = {r["estimator"]: r for r in leaderboard_rows(results)}
    assert rows["nn"]["worst_tpr_at_far_not_run"] and rows["nn"]["worst_state_error_ratio_not_run"]
    assert rows["pf"]["worst_state_error_ratio_broke_down"]
    md = write_leaderboard(tmp_path, results).read_text()
    cells = {line.split("|")[2].strip(): line for line in md.splitlines()
             if line.startswith("| s ")}  # fmt: skip
    assert cells["`nn`"].rstrip(" |").endswith("not run | not run")
    assert cells["`pf`"].rstrip(" |").endswith("0.4 | broke down")
    saved = {r["estimator"]: r for r in json.loads((tmp_path / "leaderboard.json").read_text())}
    assert saved["nn"]["worst_state_error_ratio_not_run"] is True


def test_a_scenario_without_detectors_is_not_said_to_be_uncalibrated(tmp_path):
    """At the default --far, a scenario of filters alone (no estimator raises alarms) had
    its leaderboard say "Nothing was calibrated (`--far off`)" (a red-team trial)."""
    results = {"plant": doc(["kf", "ekf"], state_rmse=0.5) | {"far": {"target": 0.01}}}
    md = write_leaderboard(tmp_path, results).read_text()
    assert "--far off" not in md and "No estimator here raises alarms" in md
    assert "_at_far" not in next(line for line in md.splitlines() if line.startswith("| scen"))


def test_a_leaderboard_of_an_uncalibrated_evaluation_has_no_columns_at_a_rate(tmp_path):
    """A docs trial: ``--far off`` left three ``*_at_far`` columns of "—" under text that
    described them; they are left out and the text says why. Where one estimator has a
    calibrated value, the columns stay."""
    results = {"plant": doc(["kf", "pf"], state_rmse=0.5, auc=0.9)}
    md = write_leaderboard(tmp_path, results).read_text()
    header = next(line for line in md.splitlines() if line.startswith("| scenario"))
    assert "auc" in header and "state_rmse" in header and "_at_far" not in header
    assert "Nothing was calibrated (`--far off`)" in md and "no acceptance summary" in md
    (tmp_path / "c").mkdir()
    results["plant"]["estimators"]["kf"]["tpr_at_far"] = 0.7
    md = write_leaderboard(tmp_path / "c", results).read_text()
    assert "tpr_at_far [fraction]" in md and "Nothing was calibrated" not in md


def test_a_rate_read_at_a_threshold_outside_its_false_alarm_band_is_hatched():
    """The four-tank normal PF's tpr_at_far 0.991 at fpr_at_far 0.566 was painted green as
    the best (a figure review): the cells read at such a threshold are hatched."""
    from difffilter.eval.leaderboard import off_band_cells

    cols = ["auc", "tpr_at_far", "fpr_at_far", "detection_delay_at_far_s"]
    rows = [{"fpr_at_far": 0.566, "far_target": 0.01}, {"fpr_at_far": 0.01, "far_target": 0.01},
            {"fpr_at_far": 0.004, "far_target": 0.01}, {"fpr_at_far": 0.0051, "far_target": 0.01},
            {"fpr_at_far": None, "far_target": 0.01}, {"fpr_at_far": 0.5, "far_target": None},
            {"fpr_at_far": float("nan"), "far_target": 0.01}]  # fmt: skip
    assert off_band_cells(rows, cols) == [(0, 1), (0, 3), (2, 1), (2, 3)]


def test_clearing_an_earlier_runs_events_removes_the_folders_it_leaves_empty(tmp_path):
    """A second evaluation into one --out replaced the events but left the first run's
    estimator and scenario folders empty: empty runs in TensorBoard's list."""
    from difffilter.eval.tensorboard import clear_events

    logdir = tmp_path / "tb_leaderboard"
    for run in ("robot/zhang_akf", "robot/mdpf_local_1", "four_tank_bias/pf_nn_grad"):
        (logdir / run).mkdir(parents=True)
        (logdir / run / "events.out.tfevents.1.vm.1.0").write_bytes(b"x")
    (logdir / "four_tank_bias" / "notes.txt").write_text("mine")  # not an event: kept
    (logdir / "events.out.tfevents.2.vm.1.0").write_bytes(b"x")
    clear_events(logdir)
    assert sorted(p.relative_to(logdir).as_posix() for p in logdir.rglob("*")) == [
        "four_tank_bias", "four_tank_bias/notes.txt"]  # fmt: skip
    assert logdir.is_dir()
