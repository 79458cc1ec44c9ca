"""Findings of a red-team trial of the family reports (2026-12-06): a number written
``null`` (a diverged estimate) or an estimator a study left out stopped the report, or
was read as a number."""

from __future__ import annotations

import copy
import types

import pytest

from eval.report import NOT_JUDGED, less, verdict


def test_less_and_verdict_say_when_a_number_is_missing():
    assert less(1.0, 2.0) is True and less(2.0, 1.0) is False
    assert less(None, 1.0) is None and less(1.0, None) is None
    assert verdict(True) == "holds" and verdict(False) == "does not hold"
    assert verdict(None) == NOT_JUDGED


def test_the_robot_claims_leave_out_the_group_filters_that_did_not_run():
    from eval.families.robot import _claims

    doc = {"estimators": {"zhang_akf": {"position_rmse": 0.999},
                          "mdpf_fused_ci": {"position_rmse": 1.727}}}  # fmt: skip
    text = _claims(doc)
    # a stand-in of 1e9 cm had been reported as a win against Zhang on one group
    assert "one group" not in text and "e+09" not in text
    assert "does not hold against Zhang with all six lidars" in text
    doc["estimators"]["zhang_akf_group2"] = {"position_rmse": 2.5}
    assert "against Zhang on one group (2.5 cm) it holds" in _claims(doc)


def test_the_robot_claims_say_a_diverged_estimate_cannot_be_judged():
    from eval.families.robot import _claims

    doc = {
        "estimators": {"zhang_akf": {"position_rmse": None},
                       "mdpf_fused_ci": {"position_rmse": 1.7}},
        "fusion": {"mdpf_fused_ci": {"ratio_all": None, "ratio_late": 0.9}},
        "attack": {"mean_rel_error_k44": [None, 0.05], "all_runs_within_10pct_at_end": True},
        "compensation": {"mean_deviation_from_attack_free_cm": None,
                         "uncompensated_mean_deviation_from_attack_free_cm": 3.0,
                         "deviation_from_attack_free_cm": 1.0},
    }  # fmt: skip
    text = _claims(doc)  # None < 1 had raised TypeError: no report.md
    assert text.count(NOT_JUDGED) == 3


def test_the_tracking_verdict_on_a_diverged_proposal_is_not_judged():
    from eval.families.tracking import _equal_time_verdict

    eq = {"time_per_run_batched_s": 1.0, "rmse_p": 2.0}
    said = _equal_time_verdict(eq, {"time_per_run_batched_s": 1.0, "rmse_p": None})
    assert said == f"whether the EKF proposal helps {NOT_JUDGED}."
    assert "helps" in _equal_time_verdict(eq, {"time_per_run_batched_s": 1.0, "rmse_p": 1.0})


def test_the_lfc_summary_leaves_a_null_out_of_the_mean(tmp_path):
    from eval.families.lfc import CORE, MAIN, _finish

    est = {n: {"attack_rmse_eq43": 0.5} for n in MAIN}
    docs = {s: {"estimators": copy.deepcopy(est), "paper": {}} for s in CORE}
    docs["lfc_sine"]["estimators"]["kf_nn_ekf"]["attack_rmse_eq43"] = None
    _finish(docs, tmp_path, None)  # the sum had raised TypeError: no lfc_summary.md
    mean_row = next(line for line in (tmp_path / "lfc_summary.md").read_text().splitlines()
                    if line.startswith("| mean of I–IV"))  # fmt: skip
    assert mean_row.split("|")[2].strip() == "—" and mean_row.split("|")[3].strip() == "0.5"


def test_the_lfc_explanation_ranks_a_missing_number_last_and_compares_no_order():
    from difffilter.models.lfc import STATE_NAMES
    from eval.families.lfc import PER_CHANNEL, _explain

    table = {n: {s: 0.1 * (i + 1) for s in STATE_NAMES} for i, n in enumerate(PER_CHANNEL)}
    table["kf_nn_ekf"][STATE_NAMES[2]] = None
    est = {"kf_nn_ekf": {"attack_rmse_eq43": None, "state5_rmse": None},
           "traditional_ad": {"attack_rmse_eq43": 0.3, "state5_rmse": 0.1},
           "uncompensated": {"state5_rmse": 0.1}}  # fmt: skip
    text = _explain(types.SimpleNamespace(attacked_channels=[2]), table, est)
    ranked = next(t for t in text.split(". ") if "random attacks rank" in t)
    assert ranked.rstrip(".").endswith("kf_nn_ekf —")
    assert "a number is missing (an estimate was not finite), so no order is compared" in text


@pytest.mark.slow
def test_a_four_tank_report_of_the_needed_estimators_alone_is_written(tmp_path):
    # Table 4 read method [31]'s two filters, which are not among the family's needs
    import warnings

    from difffilter.models import registry
    from eval.families import load_all
    from eval.report import write_report
    from eval.suite import run_suite

    load_all()
    names = [
        "normal_pf_attack_free",
        "normal_pf",
        "normal_pf_literal",
        "modified_pf",
        "chi_square_ekf",
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = run_suite(registry.get("four_tank_bias"), runs=2, seed=0, progress=False,
                           estimators=names)  # fmt: skip
        write_report(tmp_path, result)
    report = (tmp_path / "report.md").read_text()
    assert "(Not in this study: `mixture_likelihood_pf`, `open_loop_pf`.)" in report
