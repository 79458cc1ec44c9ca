"""The headline acceptance (difffilter.eval.acceptance): the estimators' roles, the best
analytic estimator of a study, and each check at its boundary."""

from __future__ import annotations

import inspect
import math

import pytest

from difffilter.eval.acceptance import (
    best_analytic,
    judge,
    judge_robustness,
    reading_no_measurements,
    roles,
    state_metric,
)
from difffilter.models import estimators as registry


def test_every_estimator_that_reads_the_true_attack_is_an_oracle():
    # the factories that call oracle_attack read γ; nothing else may be called an oracle
    for name in registry.names():
        spec = registry.get(name)
        reads_truth = "oracle_attack(" in inspect.getsource(spec.factory)
        assert spec.oracle == reads_truth, name


def test_roles_of_the_papers_estimators():
    got = roles(["modified_pf", "modified_pf_unknown_pl", "modified_pf_est", "cusum_ekf",
                 "normal_pf_attack_free", "pf_nn_grad", "kf_nn_ekf", "uncompensated",
                 "kf_attack_free", "zhang_akf", "rrp_spf_nm", "pf_da", "rrp_pf_da"])  # fmt: skip
    assert got == {
        "modified_pf": "oracle", "modified_pf_unknown_pl": "oracle",
        "modified_pf_est": "analytic", "cusum_ekf": "analytic",
        "normal_pf_attack_free": "reference", "pf_nn_grad": "learned",
        "kf_nn_ekf": "learned", "uncompensated": "analytic", "kf_attack_free": "reference",
        "zhang_akf": "analytic", "rrp_spf_nm": "reference",
        "pf_da": "more_data", "rrp_pf_da": "analytic",  # pf_da: four packets a step, not one
    }  # fmt: skip


STUDY = {
    "modified_pf": {"tpr_at_far": 0.999, "state_rmse": 0.010, "attack_rmse": 0.010},
    "modified_pf_est": {"tpr_at_far": 0.98, "state_rmse": 0.024, "attack_rmse": 0.033},
    "mixture_likelihood_pf": {"tpr_at_far": 0.997, "state_rmse": 0.027, "attack_rmse": None},
    "cusum_ekf": {"tpr_at_far": 0.985, "state_rmse": 0.0226, "attack_rmse": None},
    "normal_pf_attack_free": {"tpr_at_far": None, "state_rmse": 0.016, "attack_rmse": None},
    "pf_nn_grad": {"tpr_at_far": 1.0, "state_rmse": 0.001, "attack_rmse": 0.001},
}


def test_the_best_analytic_leaves_out_oracles_references_and_networks():
    best = best_analytic(STUDY)
    assert best["tpr_at_far"] == (0.997, "mixture_likelihood_pf")
    assert best["state_rmse"] == (0.0226, "cusum_ekf")
    assert best["attack_rmse"] == (0.033, "modified_pf_est")
    assert "auc" not in best  # no analytic estimator reports it here


def test_each_check_holds_up_to_its_bound_and_not_beyond():
    best = best_analytic(STUDY)
    edge = {"tpr_at_far": 0.987, "state_rmse": 1.05 * 0.0226, "attack_rmse": 0.033,
            "fpr_at_far": 0.02}  # fmt: skip
    assert all(c.holds for c in judge(edge, best, far=0.01))
    for metric, worse in (("tpr_at_far", 0.9869), ("state_rmse", 1.051 * 0.0226),
                          ("attack_rmse", 0.0331), ("fpr_at_far", 0.0201),
                          ("fpr_at_far", 0.0049), ("attack_rmse", None)):  # fmt: skip
        checks = {c.metric: c for c in judge({**edge, metric: worse}, best, far=0.01)}
        assert not checks[metric].holds, (metric, worse)
        assert all(c.holds for m, c in checks.items() if m != metric)
    # where no analytic estimator estimates the attack there is no attack check
    no_attack = {k: v for k, v in best.items() if k != "attack_rmse"}
    assert [c.metric for c in judge(edge, no_attack, far=0.01)] == [
        "tpr_at_far", "state_rmse", "fpr_at_far"]  # fmt: skip


def test_tracking_is_judged_on_its_position_error_against_the_round_robin_filters():
    study = {"rrp_pf_da": {"state_rmse": 0.5, "rmse_p": 1.02, "tpr_at_far": 0.99},
             "pf_da": {"state_rmse": 0.4, "rmse_p": 0.554, "tpr_at_far": 0.994},
             "pf_nn_grad": {"state_rmse": 0.3, "rmse_p": 1.07, "tpr_at_far": 0.985,
                            "fpr_at_far": 0.01}}  # fmt: skip
    assert state_metric(study) == "rmse_p"
    best = best_analytic(study)
    # pf_da reads every sensor at every step: not a competitor on the Round-Robin data
    assert best["rmse_p"] == (1.02, "rrp_pf_da") and best["tpr_at_far"] == (0.99, "rrp_pf_da")
    assert "state_rmse" not in best
    checks = {c.metric: c.holds for c in judge(study["pf_nn_grad"], best, 0.01, "rmse_p")}
    assert checks == {"tpr_at_far": True, "rmse_p": True, "fpr_at_far": True}  # 1.07 ≤ 1.071
    worse = {**study["pf_nn_grad"], "rmse_p": 1.072}
    assert not {c.metric: c.holds for c in judge(worse, best, 0.01, "rmse_p")}["rmse_p"]
    assert state_metric({"a": {"state_rmse": 1.0, "rmse_p": None}}) == "state_rmse"


def test_the_worst_case_tpr_check_says_when_no_analytic_detector_sees_its_worst_threat():
    role_of = {"net": "learned", "chi": "analytic", "cusum": "analytic"}

    def cells(covert_tpr):  # the analytic detectors' worst threat is "covert"
        row = lambda tpr, rmse: {"tpr_at_far": tpr, "state_rmse": rmse}  # noqa: E731
        return {"bias": {"net": row(0.99, 1.0), "chi": row(0.98, 1.0), "cusum": row(0.97, 1.0)},
                "covert": {"net": row(0.012, 1.0), "chi": row(covert_tpr, 1.0),
                           "cusum": row(covert_tpr / 2, 1.0)}}  # fmt: skip

    for covert_tpr, far, unseen in [(0.015, 0.01, True), (0.02, 0.01, True), (0.021, 0.01, False),
                                    (0.3, 0.01, False), (0.015, 0.005, False)]:  # fmt: skip
        judged = judge_robustness(cells(covert_tpr), role_of, far)["net"]
        assert judged["best_analytic_worst_tpr"] == (covert_tpr, "chi", "covert")
        assert judged["worst_threat_undetected"] is unseen, (covert_tpr, far)
        assert judged["tpr_holds"] == (0.012 >= covert_tpr)
    assert judge_robustness(cells(0.015), role_of)["net"]["worst_threat_undetected"] is None


def test_a_best_analytic_that_reads_no_measurement_keeps_the_bar_and_names_the_best_reader():
    role_of = {"net": "learned", "open": "analytic", "chi": "analytic", "cusum": "analytic"}
    row = lambda rmse: {"tpr_at_far": 0.5, "state_rmse": rmse}  # noqa: E731
    cells = {  # a ramp drags every filter that reads the sensors; a bias is undone by "chi"
        "ramp": {"net": row(0.15), "open": row(0.05), "chi": row(0.20), "cusum": row(0.17)},
        "bias": {"net": row(0.018), "open": row(0.05), "chi": row(0.016), "cusum": row(0.04)},
    }
    judged = judge_robustness(cells, role_of, 0.01, blind={"open"})["net"]["state"]
    ramp, bias = judged["ramp"], judged["bias"]
    # the check is against the best of all, the open-loop prediction included
    assert (ramp["best"], ramp["best_estimator"]) == (0.05, "open")
    assert ramp["ratio"] == pytest.approx(3.0) and not ramp["holds"]
    # ... and the verdict names the best that reads the sensors beside it
    assert ramp["best_reads_no_measurements"] is True
    assert (ramp["best_reading"], ramp["best_reading_estimator"]) == (0.17, "cusum")
    assert ramp["ratio_reading"] == pytest.approx(0.15 / 0.17) and ramp["holds_reading"]
    # where a reader is best, nothing is added
    assert bias["best_estimator"] == "chi" and "best_reading" not in bias
    assert bias["holds"] == (0.018 <= 1.1 * 0.016)
    # without the registry's word every estimator counts as reading: the same checks
    plain = judge_robustness(cells, role_of, 0.01)["net"]["state"]
    assert "best_reading" not in plain["ramp"]
    assert {t: c["holds"] for t, c in plain.items()} == {t: c["holds"] for t, c in judged.items()}
    # the report marks the open-loop bar and gives the reader's column
    from difffilter.eval.robustness import _acceptance_section

    text = _acceptance_section("net", judge_robustness(cells, role_of, 0.01, blind={"open"})["net"])
    assert "| ramp | 0.15 | 0.05 (`open`†) | 3 |" in text
    assert "0.17 (`cusum`), 0.882×" in text and "† reads no measurement" in text
    assert "best that reads the sensors" not in _acceptance_section(
        "net", judge_robustness(cells, role_of, 0.01)["net"]
    )
    from difffilter.eval.robustness import _within_readers

    assert _within_readers(judged.values()) == " (1 within the best that reads the sensors)"
    assert _within_readers(plain.values()) == ""
    # the registry's word: the four-tank paper's open-loop account of method [31]
    assert reading_no_measurements(["open_loop_pf", "cusum_ekf", "pf_nn_grad"]) == ["open_loop_pf"]


def test_a_learned_number_that_is_missing_does_not_hold():
    best = best_analytic(STUDY)
    checks = judge({"tpr_at_far": float("nan")}, best, far=0.01)
    assert not any(c.holds for c in checks)
    with pytest.raises(ValueError, match="unknown estimator"):
        roles(["no_such_estimator"])


def test_a_calibrated_report_judges_its_learned_estimator_against_the_best_analytic(tmp_path):
    import json
    from dataclasses import replace

    from difffilter.eval.calibration import calibrate
    from difffilter.eval.report import write_report
    from difffilter.eval.suite import run_suite
    from difffilter.models import registry

    sc = replace(registry.get("robot_actuator_attack"), num_particles=20, steps=60)
    result = run_suite(sc, runs=3, calibration=calibrate(sc, runs=3, progress=False),
                       progress=False)  # fmt: skip
    doc = write_report(tmp_path, result)
    roles_written = json.loads((tmp_path / "metrics.json").read_text())["estimator_roles"]
    assert roles_written == roles(doc["estimators"])
    assert (
        roles_written["gaussian_nn_ekf"] == "learned" and roles_written["zhang_akf"] == "analytic"
    )
    report = (tmp_path / "report.md").read_text()
    # the scenario its network was trained on, from its card (a trial's network of another
    # motor of the same family ran without a word)
    assert doc["checkpoint"]["training_scenario"] == "robot_actuator_attack_turn_rates"
    assert "; trained on `robot_actuator_attack_turn_rates`), used by `gaussian_nn_ekf`" in report
    section = report.split("## Learned against the best analytic")[1]
    m = doc["estimators"]
    analytic = [n for n, r in roles_written.items() if r == "analytic"]
    best = min(analytic, key=lambda n: m[n]["state_rmse"])
    assert f"(`{best}`)" in section
    holds = m["gaussian_nn_ekf"]["state_rmse"] <= 1.05 * m[best]["state_rmse"]
    header = next(line for line in section.splitlines() if line.startswith("| learned"))
    row = next(line for line in section.splitlines() if line.startswith("| `gaussian_nn_ekf`"))
    column = [c.strip() for c in header.split("|")].index("state_rmse ≤ 1.05 × best")
    assert [c.strip() for c in row.split("|")][column].endswith("✓" if holds else "✗")
    # how sure: the same statistic under resampling of the runs (difffilter.eval.intervals)
    import jsonschema

    from difffilter.eval.report import metrics_schema

    written = json.loads((tmp_path / "metrics.json").read_text())
    jsonschema.validate(written, metrics_schema())
    mine = written["acceptance_intervals"]["estimators"]["gaussian_nn_ekf"]
    ratio = m["gaussian_nn_ekf"]["state_rmse"] / m[best]["state_rmse"]
    assert mine["state_rmse"]["estimate"] == pytest.approx(ratio, rel=1e-9)
    assert mine["state_rmse"]["low"] <= mine["state_rmse"]["high"]
    assert mine["fpr_at_far"]["estimate"] == pytest.approx(m["gaussian_nn_ekf"]["fpr_at_far"])
    assert "How sure each verdict is over these 3 runs" in section
    # and in TensorBoard's HPARAMS, to compare checkpoints by how sure their verdicts are
    from conftest import session_scalars

    (share,) = session_scalars(tmp_path / "tb" / "hparams" / "gaussian_nn_ekf")[
        "hparam/holds_share/state_rmse"
    ]
    assert share == pytest.approx(mine["state_rmse"]["holds_share"])
    # a learned threshold resting on clustered calibration alarms: the verdict says its
    # intervals do not carry that (a trial read "0 [0, 0], holds in 0 %" as certain)
    from difffilter.eval.report import _acceptance_section

    said = "The thresholds of `gaussian_nn_ekf` rest on calibration alarms that cluster"
    concentrated = (written["far"].get("concentrated") or {}).get("gaussian_nn_ekf")
    assert (said in section) == (concentrated is not None)
    entry = {"alarms": 51, "effective_alarms": 4.9}
    clustered = {**written, "far": {**written["far"], "concentrated": {"gaussian_nn_ekf": entry}}}
    assert said in _acceptance_section(clustered).body
    other = {**written, "far": {**written["far"], "concentrated": {"zhang_akf": entry}}}
    assert said not in _acceptance_section(other).body


def test_the_evaluations_acceptance_summary_has_a_row_per_judged_learned_estimator(tmp_path):
    from difffilter.eval.report import write_acceptance_summary

    role = {n: "analytic" for n in STUDY if n not in ("pf_nn_grad", "modified_pf")}
    role.update(pf_nn_grad="learned", modified_pf="oracle")
    judged = {"estimators": {**STUDY, "pf_nn_grad": {**STUDY["pf_nn_grad"], "fpr_at_far": 0.03}},
              "estimator_roles": role, "far": {"target": 0.01},
              "acceptance_intervals": {"estimators": {"pf_nn_grad": {
                  "tpr_at_far": {"holds_share": 0.53}, "fpr_at_far": {"holds_share": 0.0}}}}}  # fmt: skip
    uncalibrated = {**judged, "far": None}
    path = write_acceptance_summary(tmp_path, {"four_tank_bias": judged, "other": uncalibrated})
    rows = [line for line in path.read_text().splitlines() if line.startswith("| four_tank")]
    assert len(rows) == 1 and "| other |" not in path.read_text()
    cells = [c.strip() for c in rows[0].split("|")][1:-1]
    checks = {c.metric: c for c in judge(judged["estimators"]["pf_nn_grad"],
                                         best_analytic(judged["estimators"], role), 0.01)}  # fmt: skip
    assert cells[2] == "online"  # no checkpoint: a network that learns during the run
    assert cells[3].endswith("✓ (53 %)" if checks["tpr_at_far"].holds else "✗ (53 %)")
    assert cells[6] == "0.03 ✗ (0 %)" and cells[7] == "**fails**"  # outside [0.5 %, 2 %]
    assert write_acceptance_summary(tmp_path / "none", {"other": uncalibrated}) is None
    # a scenario judged on another state metric (tracking's rmse_p) names it in its cell
    ests = {n: {**m, "rmse_p": m["state_rmse"]} for n, m in judged["estimators"].items()}
    (tmp_path / "p").mkdir()
    path = write_acceptance_summary(tmp_path / "p", {"tracking": {**judged, "estimators": ests}})
    (row,) = [line for line in path.read_text().splitlines() if line.startswith("| tracking")]
    assert "(`rmse_p`)" in row.split("|")[5]
    assert "(`" not in rows[0].split("|")[5]  # state_rmse: the column's own
    # a checkpoint's network is said so, and listed before the networks that learn online
    # (a reviewer found the LFC paper's online learners' rows beside the library's claim)
    two = {**judged, "estimator_roles": {**role, "cusum_ekf": "learned"},
           "checkpoint": {"used_by": ["pf_nn_grad"]}}  # fmt: skip
    path = write_acceptance_summary(tmp_path / "p", {"four_tank_bias": two})
    rows = [line for line in path.read_text().splitlines() if line.startswith("| four_tank")]
    assert [r.split("|")[2:4] for r in rows] == [[" `pf_nn_grad` ", " checkpoint "],
                                                  [" `cusum_ekf` ", " online "]]  # fmt: skip
    # an evaluation that judges nothing into the same folder removes the earlier summary (a
    # user trial: difffilter-eval printed the earlier one as this evaluation's verdict)
    assert write_acceptance_summary(tmp_path / "p", {"other": uncalibrated}) is None
    assert not (tmp_path / "p" / "acceptance.md").exists()


def test_a_robustness_check_with_nothing_to_compare_does_not_hold():
    """The learned estimator alone, or a threat where no analytic estimator has a number:
    not judged, so not held (once "holds" over an empty comparison)."""
    from difffilter.eval.robustness import _acceptance_section

    alone = judge_robustness({"bias": {"net": {"tpr_at_far": 1.0, "state_rmse": 0.02}}},
                             {"net": "learned"}, 0.01)["net"]  # fmt: skip
    assert alone["best_analytic_worst_tpr"] is None and alone["tpr_holds"] is False
    assert alone["state"]["bias"]["best"] is None and alone["state"]["bias"]["holds"] is False
    assert alone["state_holds"] is False and alone["holds"] is False
    text = _acceptance_section("net", alone)
    assert "no analytic detector in the study" in text and "**not judged**" in text
    assert "| bias | 0.02 | — (no analytic estimator: not judged) |" in text
    # one threat where the analytic estimator has no state error: that threat fails
    role_of = {"net": "learned", "chi": "analytic"}
    cells = {"a": {"net": {"tpr_at_far": 0.9, "state_rmse": 1.0},
                   "chi": {"tpr_at_far": 0.8, "state_rmse": 1.0}},
             "b": {"net": {"tpr_at_far": 0.9, "state_rmse": 5.0},
                   "chi": {"tpr_at_far": 0.8, "state_rmse": math.nan}}}  # fmt: skip
    judged = judge_robustness(cells, role_of, 0.01)["net"]
    assert judged["tpr_holds"] is True and judged["state"]["a"]["holds"] is True
    assert judged["state"]["b"]["holds"] is False and judged["holds"] is False


def test_a_calibrated_study_with_no_analytic_number_says_its_learned_are_not_judged(tmp_path):
    """From a red-team trial: a calibrated study whose analytic estimators gave no number
    (``--estimators`` listing a learned one alone) had no "Learned against the best
    analytic" section and no acceptance row, without a word (the robustness report said
    "not judged" there)."""
    from difffilter.eval.report import _acceptance_section, write_acceptance_summary

    alone = {"estimators": {"pf_nn_grad": STUDY["pf_nn_grad"]},
             "estimator_roles": {"pf_nn_grad": "learned"}, "far": {"target": 0.01}}  # fmt: skip
    text = _acceptance_section(alone).body
    assert "**not judged**" in text
    (row,) = [line for line in text.splitlines() if line.startswith("| `pf_nn_grad`")]
    assert row.rstrip().endswith("| **fails** |")
    summary = write_acceptance_summary(tmp_path, {"four_tank_bias": alone}).read_text()
    assert "| four_tank_bias | `pf_nn_grad` |" in summary and "**fails**" in summary
    # one analytic estimator with a number: judged as before, without the note
    judged = {**alone, "estimators": {**alone["estimators"], "cusum_ekf": STUDY["cusum_ekf"]},
              "estimator_roles": {"pf_nn_grad": "learned", "cusum_ekf": "analytic"}}  # fmt: skip
    assert "not judged" not in _acceptance_section(judged).body


def test_a_metric_of_numpys_float_counts_and_a_tensor_is_refused():
    """``np.float32`` metrics had read as missing: another analytic estimator's 1.00 set the
    state bar where 0.40 is the best, so a learned 0.52 passed; the same learned numbers in
    float32 failed every check. A 0-d tensor (or ``True``) is refused by name now."""
    import numpy as np
    import torch

    from difffilter.eval.acceptance import best_analytic, judge

    role = {"a1": "analytic", "a2": "analytic", "L": "learned"}
    learned = {"tpr_at_far": 0.94, "state_rmse": 0.52, "fpr_at_far": 0.01}
    metrics = {"a1": {"tpr_at_far": 0.90, "state_rmse": 1.00},
               "a2": {"tpr_at_far": np.float32(0.95), "state_rmse": np.float32(0.40)}, "L": learned}  # fmt: skip
    best = best_analytic(metrics, role)
    assert best["state_rmse"][1] == "a2" and not judge(learned, best, 0.01)[1].holds
    as_f32 = {k: np.float32(v) for k, v in learned.items()}
    assert [c.holds for c in judge(as_f32, best, 0.01)] == [
        c.holds for c in judge(learned, best, 0.01)
    ]
    for bad in (torch.tensor(0.95), True):
        metrics["a2"]["tpr_at_far"] = bad
        with pytest.raises(TypeError, match="a metric's value must be a real number or None"):
            best_analytic(metrics, role)


def test_an_analytic_detector_absent_from_a_threat_sets_no_worst_case_bar():
    """Only a ``not_run`` cell had counted as not run: an analytic detector with no cell under
    a threat set the bar from its other threats (0.9 where a1's worst, 0.3, is the bar), as
    the docstring and the check's interval (``robustness_intervals``) say it must not."""
    from difffilter.eval.acceptance import judge_robustness

    role = {"a1": "analytic", "a2": "analytic", "L": "learned"}
    row = {"state_rmse": 1.0}
    cells = {
        "t1": {"a1": {"tpr_at_far": 0.3, **row}, "a2": {"tpr_at_far": 0.9, **row}, "L": {"tpr_at_far": 0.5, **row}},
        "t2": {"a1": {"tpr_at_far": 0.4, **row}, "L": {"tpr_at_far": 0.5, **row}},
    }  # fmt: skip
    verdict = judge_robustness(cells, role)["L"]
    assert verdict["best_analytic_worst_tpr"] == (0.3, "a1", "t1") and verdict["tpr_holds"]
