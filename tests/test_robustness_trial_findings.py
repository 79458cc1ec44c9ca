"""Findings of a red-team trial of the robustness report (2026-12-06)."""

from __future__ import annotations

import math
from functools import partial

import pytest
import torch

from difffilter.attack import Attack, Channel
from difffilter.models import registry
from difffilter.threats import Bias
from eval.robustness import (
    ThreatSet,
    _cell,
    _cell_text,
    _worst_cases,
    _worst_text,
    load_threat_set,
    run_robustness,
)


def test_a_threat_an_estimator_was_not_run_under_leaves_no_worst_case():
    # its worst case had been taken over the other threats alone (29 where 290 was due)
    cells = {"bias": {"kf": {"state_error_ratio": 29.0, "tpr_at_far": 0.5}},
             "adaptive": {"kf": {"state_error_ratio": None, "tpr_at_far": None,
                                 "not_run": "no closed loop of its own"}}}  # fmt: skip
    worst = _worst_cases(cells)["kf"]
    assert worst["state_error_ratio"] is None and worst["state_error_ratio_not_run"]
    assert worst["tpr_at_far"] is None and worst["tpr_at_far_threat"] == "adaptive"
    assert _worst_text(worst, "state_error_ratio") == "not run (adaptive)"
    assert _cell_text(cells["adaptive"]["kf"], "tpr_at_far") == "not run"


def test_a_tie_is_counted_among_diverged_threats_and_dropped_for_finite_ones():
    # a = b = 2 tied, then c diverged: the tie of the finite values had stayed beside it
    cells = {t: {"e": {"state_error_ratio": v}} for t, v in
             (("a", 2.0), ("b", 2.0), ("c", math.nan), ("d", math.inf))}  # fmt: skip
    worst = _worst_cases(cells)["e"]
    assert worst["state_error_ratio_diverged"] and worst["state_error_ratio_threat"] == "c"
    assert worst["state_error_ratio_tied"] == 1  # d: diverged too
    assert _worst_text(worst, "state_error_ratio") == "diverged (c; 1 more tied)"


def test_a_diverged_cell_says_so():
    cell = _cell({"state_rmse": math.inf, "tpr_at_far": 0.5}, {"state_rmse": 1.0})
    assert cell["diverged"] == ["state_rmse", "state_error_ratio"]
    assert _cell_text(cell, "state_error_ratio") == "diverged"  # it had read "—"
    assert _cell_text(cell, "attack_rmse") == "—"


def test_a_threat_set_built_in_python_keeps_its_library_specs():
    # the class path alone had lost the fields: training coverage read it as one's own
    ts = ThreatSet({"bias": Bias(value=0.5, onset=21)})
    assert ts.specs["bias"]["kind"] == "bias" and ts.specs["bias"]["value"] == [0.5]
    assert ts.specs["bias"]["onset"] == 21


@pytest.mark.parametrize("runs", [0, -2])
def test_a_threat_sets_runs_are_checked(runs):
    with pytest.raises(ValueError, match="ThreatSet.runs"):
        ThreatSet({"bias": Bias(value=0.5)}, runs=runs)


def test_a_threat_set_of_another_sampling_period_is_refused():
    # the LFC set counts its onsets, delays and slopes in 10 ms steps; lfc_sine_1ms had run it
    with pytest.raises(
        ValueError, match=r"written for steps of dt = 0\.01 s .* lfc_sine_1ms steps 0\.001 s"
    ):
        load_threat_set(registry.get("lfc_sine_1ms"))
    assert load_threat_set(registry.get("lfc_step"), "bias").threats


@pytest.mark.parametrize("entry", ["a:", "a: 5"])
def test_a_threat_that_is_not_a_mapping_is_named(tmp_path, entry):
    path = tmp_path / "set.yaml"
    path.write_text(f"threats:\n  {entry}\n")
    with pytest.raises(ValueError, match="threat 'a': a threat is a mapping"):
        load_threat_set(registry.get("four_tank_bias"), path=path)


class _AdaptiveBias(Attack):
    """A constant bias that declares it reads the estimator's output."""

    channel = Channel.SENSOR
    reads_state = False
    reads_view = True

    def init(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        return torch.zeros(batch_shape, dtype=dtype, device=device)

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        value = torch.zeros_like(y)
        value[..., 2] = 4.0
        return state, value, torch.full(y.shape[:-1], k >= 300)


@pytest.mark.slow
def test_an_estimator_skipped_under_an_adaptive_threat_has_a_cell_that_says_so():
    threats = ThreatSet({"bias": Bias(value=0.4, entries=(2,), onset=300), "adaptive": _AdaptiveBias()},
                        runs=2, estimators=("chi_square_kf", "kf", "uncompensated"))  # fmt: skip
    result = run_robustness(registry.get("lfc_step"), threats, progress=False)
    cell = result.cells["adaptive"]["kf"]
    assert cell["not_run"] and cell["state_error_ratio"] is None
    assert result.worst_case["kf"]["state_error_ratio_not_run"]


def test_the_worst_case_tpr_is_not_judged_without_a_tpr_where_an_analytic_one_detects():
    """A learned estimator not run under a threat had that threat left out of its worst
    case while the analytic ones kept it: 0.90 on an easy threat passed against the bar of
    0.05 set on the hard one (a trial)."""
    from difffilter.eval.acceptance import judge_robustness

    role = {"net": "learned", "chi": "analytic"}
    cells = {"bias": {"net": {"tpr_at_far": 0.9, "state_rmse": 1.0},
                      "chi": {"tpr_at_far": 0.8, "state_rmse": 1.0}},
             "replay": {"net": {"tpr_at_far": None, "state_rmse": None, "not_run": "no loop"},
                        "chi": {"tpr_at_far": 0.05, "state_rmse": 2.0}}}  # fmt: skip
    verdict = judge_robustness(cells, role, far=0.01)["net"]
    assert verdict["tpr_missing"] == ["replay"] and not verdict["tpr_holds"]
    # where nobody detects the threat, it counts for the state error alone, as before
    cells["replay"]["chi"]["tpr_at_far"] = None
    cells["replay"]["net"] = {"tpr_at_far": None, "state_rmse": 2.0}
    verdict = judge_robustness(cells, role, far=0.01)["net"]
    assert verdict["tpr_missing"] == [] and verdict["tpr_holds"] and verdict["holds"]


@pytest.mark.parametrize("far", [1.0, -0.3, math.nan])
def test_judge_robustness_refuses_a_false_alarm_rate_outside_zero_one(far):
    """``far=1`` (meant as 1 %) had marked a worst-case TPR of 0.5 "undetected" (a trial)."""
    from difffilter.eval.acceptance import judge_robustness

    with pytest.raises(ValueError, match="far"):
        judge_robustness({}, {}, far=far)


def test_an_analytic_detector_not_run_under_a_threat_sets_no_worst_case_bar():
    """Its minimum over the other threats alone (0.359 on a ramp) had become the bar, which
    the learned estimator's 0.05 failed against the only real analytic worst case, 0.0125
    (a trial); the resampled gap of the intervals took the same partial minimum."""
    from difffilter.eval.acceptance import judge_robustness
    from difffilter.eval.intervals import robustness_intervals
    from difffilter.eval.robustness import _not_run_cell

    roles = {"chi": "analytic", "cusum": "analytic", "net": "learned"}
    cells = {"ramp": {"chi": {"tpr_at_far": 0.359, "state_rmse": 0.16},
                      "cusum": {"tpr_at_far": 0.406, "state_rmse": 0.16},
                      "net": {"tpr_at_far": 0.544, "state_rmse": 0.16}},
             "replay": {"chi": _not_run_cell("skipped under this threat"),
                        "cusum": {"tpr_at_far": 0.0125, "state_rmse": 0.038},
                        "net": {"tpr_at_far": 0.05, "state_rmse": 0.038}}}  # fmt: skip
    verdict = judge_robustness(cells, roles, 0.01)["net"]
    assert verdict["best_analytic_worst_tpr"] == (0.0125, "cusum", "replay")
    assert verdict["tpr_holds"] and verdict["worst_threat_undetected"]
    # the intervals: the not-run detector is absent from that threat's per-run totals
    runs = 4

    def totals(tpr, rmse):  # each run: 10 attacked steps, 10 steps of state error
        full = partial(torch.full, (runs,), dtype=torch.float64)
        return {"hits": full(tpr * 10), "attacked": full(10.0), "se": full(rmse**2 * 10),
                "n": full(10.0)}  # fmt: skip

    per_run = {"ramp": {n: totals(c["tpr_at_far"], c["state_rmse"])
                        for n, c in cells["ramp"].items()},
               "replay": {n: totals(c["tpr_at_far"], c["state_rmse"])
                          for n, c in cells["replay"].items() if n != "chi"}}  # fmt: skip
    gap = robustness_intervals(per_run, roles, runs=runs, resamples=20, seed=0)["net"]["worst_tpr"]
    assert gap["estimate"] == pytest.approx(0.05 - 0.0125)


def test_the_reading_ratio_prints_apart_from_the_bar():
    """1.1004, over the 1.1× bar (not counted within it), had printed "1.1×" (a trial)."""
    from difffilter.eval.robustness import _reading_cell

    check = {"best_reads_no_measurements": True, "best_reading": 0.16,
             "best_reading_estimator": "chi", "ratio_reading": 1.1004}  # fmt: skip
    assert _reading_cell(check).endswith("1.1004×")


def test_a_threat_set_of_no_threat_is_refused_when_made():
    """``ThreatSet({})`` in Python: refused by name, as the command line's empty --threats
    and a file's empty threat mapping are (it had run the calibration and the attack-free
    study, then written empty tables and heat maps, and no verdict for the learned
    estimator)."""
    with pytest.raises(ValueError, match="ThreatSet.threats names no threat"):
        ThreatSet({})
