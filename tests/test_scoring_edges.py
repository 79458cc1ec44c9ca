"""The scoring core at its edges, each against a value worked out by hand (a mutation
review of the metrics, acceptance, intervals and calibrated metrics: 57 mutants, 10
survived the suite, among them NaN scores ranked as 0 above negative ones, the ROC point at
exactly 1 % lost, a TPR of 1 where every step is attacked, a delay in steps divided by dt,
a best analytic of 0 that any value passed, the lowest AUC taken as the best, resamples with
no value counted as failing, and an impact by the largest component instead of the norm)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from difffilter import metrics as dm
from difffilter.attack import Channel
from difffilter.estimator import Detection, EstimatorOutput
from difffilter.eval import acceptance as ac
from difffilter.eval import intervals as iv
from difffilter.eval import scoring as sc
from difffilter.eval.calibration import calibrated_metrics


# --- difffilter/metrics.py ---------------------------------------------------------
def test_auc_of_tied_scores_is_half():
    # one positive and one negative tied: trapezoid gives 0.5 (a rectangle rule gives 1.0)
    assert dm.roc_auc(torch.tensor([1.0, 1.0]), torch.tensor([True, False])) == 0.5


def test_delay_uses_first_alarm_not_last():
    alarms = torch.tensor([[False, True, False, True, False]])
    attacked = torch.tensor([[True, True, True, True, False]])
    assert dm.detection_delay(alarms, attacked)["mean_delay"] == 1.0


def test_delay_keys_of_two_runs_with_one_episode_each_do_not_collide():
    alarms = torch.tensor([[False, False, True], [True, False, False]])
    attacked = torch.tensor([[False, True, True], [True, True, False]])
    d = dm.detection_delay(alarms, attacked)
    assert (d["episodes"], d["detected"], d["mean_delay"]) == (2, 2, 0.5)


def test_threshold_for_floor_and_index():
    s = torch.arange(10.0)  # far 0.15: floor(1.5) = 1 score above the threshold
    assert dm.threshold_for(s, 0.15) == 8.0
    assert dm.threshold_for(torch.arange(100.0), 0.29) == 70.0  # 29 above, despite round-off


def test_after_attack_window_is_1_to_steps_inclusive():
    flags = torch.zeros(1, 15, dtype=torch.bool)
    flags[0, 0] = True
    a = dm.after_attack(flags, 10)
    assert a[0].nonzero().flatten().tolist() == list(range(1, 11))


def test_nan_scores_rank_lowest_not_zero():
    s = dm.nan_as_lowest(torch.tensor([float("nan"), -1.0]))
    assert s[0] == -math.inf


# --- eval/scoring.py ---------------------------------------------------------------
def _traj(flags, x=None):
    B, T = flags.shape
    x = torch.zeros(B, T, 1) if x is None else x
    return SimpleNamespace(flags=flags, x=x, attack=torch.zeros(B, T, 1), info={}, mask=None)


def test_tpr_at_budget_reads_the_point_at_exactly_1pct():
    # 100 negatives, one of them scoring above every positive: fpr = 0.01 exactly is allowed
    neg = torch.zeros(100)
    neg[0] = 10.0
    scores = torch.cat([neg, torch.full((10,), 5.0)]).unsqueeze(0)
    flags = torch.cat(
        [torch.zeros(100, dtype=torch.bool), torch.ones(10, dtype=torch.bool)]
    ).unsqueeze(0)
    assert sc._tpr_at(scores, flags, 0.01) == 1.0


def test_tpr_at_budget_is_none_when_every_step_is_attacked():
    assert sc._tpr_at(torch.ones(1, 4), torch.ones(1, 4, dtype=torch.bool), 0.01) is None


def test_false_alarms_per_1000_steps_and_time_per_step():
    flags = torch.zeros(2, 50, dtype=torch.bool)
    alarms = torch.zeros(2, 50, dtype=torch.bool)
    alarms[0, 0] = True
    out = EstimatorOutput(
        means=torch.zeros(2, 50, 1), detection=Detection(scores=alarms.double(), alarms=alarms)
    )
    m = sc.score(out, _traj(flags), dt=0.1, wall_s=1.0)
    assert m["false_alarms_per_1000_steps"] == pytest.approx(10.0)
    assert m["time_per_step_s"] == pytest.approx(0.01)


@pytest.mark.parametrize(
    ("threshold", "expected"),
    [
        (None, None),
        (2.5, 2.5),
        (torch.tensor(2.5), 2.5),
        (torch.full((2, 4), 2.5), 2.5),  # one value throughout
        (torch.tensor([1.0, 2.0, 2.5, 2.5]), None),  # grows over the first steps
        (torch.tensor([[2.5] * 4, [3.0] * 4]), None),  # one per run
        (float("inf"), None),
    ],
)
def test_the_own_threshold_is_reported_where_it_is_one_number(threshold, expected):
    """``threshold`` is the detection's own τ where one number holds for every run and step
    (else ``null``), and the alarms it reports are those ``tpr`` and ``fpr`` count: with
    scores 0..7 and τ = 2.5, five alarms of eight steps, all on attack-free steps."""
    scores = torch.arange(8.0).reshape(2, 4)
    alarms = scores > 2.5
    out = EstimatorOutput(
        means=torch.zeros(2, 4, 1), detection=Detection(scores, alarms, threshold)
    )
    m = sc.score(out, _traj(torch.zeros(2, 4, dtype=torch.bool)), dt=1.0, wall_s=1.0)
    assert m["threshold"] == expected
    assert m["fpr"] == 5 / 8
    no_detection = EstimatorOutput(means=torch.zeros(2, 4, 1))
    assert sc.score(no_detection, _traj(torch.zeros(2, 4, dtype=torch.bool)), dt=1.0,
                    wall_s=1.0)["threshold"] is None  # fmt: skip


def test_detection_delay_s_is_steps_times_dt():
    flags = torch.tensor([[False, True, True, True]])
    alarms = torch.tensor([[False, False, True, False]])
    out = EstimatorOutput(
        means=torch.zeros(1, 4, 1), detection=Detection(scores=alarms.double(), alarms=alarms)
    )
    m = sc.score(out, _traj(flags), dt=0.5, wall_s=1.0)
    assert m["detection_delay_steps"] == 1.0 and m["detection_delay_s"] == 0.5


def test_rates_by_size_bins_are_left_open():
    flags = torch.ones(1, 2, dtype=torch.bool)
    rows = sc.rates_by_size(
        torch.tensor([[True, False]]), flags, torch.tensor([[1.0, 2.0]]), [1.0, 2.0]
    )
    assert rows[0]["steps"] == 1 and rows[0]["rate"] == 0.0


# --- eval/acceptance.py ------------------------------------------------------------
def test_best_analytic_tie_goes_to_first_in_study_order():
    metrics = {
        "zeta": {"tpr_at_far": 0.9, "state_rmse": 1.0},
        "alpha": {"tpr_at_far": 0.9, "state_rmse": 1.0},
    }
    best = ac.best_analytic(metrics, {"zeta": "analytic", "alpha": "analytic"})
    assert best["tpr_at_far"] == (0.9, "zeta") and best["state_rmse"] == (1.0, "zeta")


def test_best_analytic_auc_is_the_highest():
    metrics = {"a": {"auc": 0.6}, "b": {"auc": 0.9}}
    assert ac.best_analytic(metrics, {"a": "analytic", "b": "analytic"})["auc"] == (0.9, "b")


def test_best_analytic_ignores_oracles_and_references():
    metrics = {"o": {"state_rmse": 0.1}, "a": {"state_rmse": 1.0}}
    assert ac.best_analytic(metrics, {"o": "oracle", "a": "analytic"})["state_rmse"] == (1.0, "a")


def test_state_metric_needs_rmse_p_from_every_estimator():
    assert (
        ac.state_metric({"a": {"state_rmse": 1, "rmse_p": 1}, "b": {"state_rmse": 1}})
        == "state_rmse"
    )
    every = {"a": {"state_rmse": 1, "rmse_p": 1}, "b": {"state_rmse": 1, "rmse_p": 2}}
    assert ac.state_metric(every) == "rmse_p"


def _judge(**learned):
    best = {"tpr_at_far": (0.9, "a"), "state_rmse": (1.0, "a"), "attack_rmse": (1.0, "a")}
    base = {"tpr_at_far": 0.9, "state_rmse": 1.0, "attack_rmse": 1.0, "fpr_at_far": 0.01}
    return {c.metric: c.holds for c in ac.judge({**base, **learned}, best, far=0.01)}


def test_judge_tolerances_at_their_edges():
    assert _judge(state_rmse=1.05)["state_rmse"] and not _judge(state_rmse=1.06)["state_rmse"]
    assert _judge(tpr_at_far=0.89)["tpr_at_far"] and not _judge(tpr_at_far=0.885)["tpr_at_far"]
    assert _judge(attack_rmse=1.0)["attack_rmse"] and not _judge(attack_rmse=1.01)["attack_rmse"]
    assert _judge(fpr_at_far=0.005)["fpr_at_far"] and not _judge(fpr_at_far=0.0049)["fpr_at_far"]
    assert _judge(fpr_at_far=0.02)["fpr_at_far"] and not _judge(fpr_at_far=0.021)["fpr_at_far"]


def test_ratio_within_a_best_of_zero():
    assert ac.ratio_within(0.0, 0.0, 1.05) and not ac.ratio_within(0.1, 0.0, 1.05)


def test_judge_robustness_undetected_at_exactly_2_alpha_and_blind_reading():
    cells = {
        "t1": {
            "L": {"tpr_at_far": 0.5, "state_rmse": 1.0},
            "A": {"tpr_at_far": 0.02, "state_rmse": 1.0},
            "P": {"state_rmse": 2.0},
        },
        "t2": {
            "L": {"tpr_at_far": 0.9, "state_rmse": 1.1},
            "A": {"tpr_at_far": 0.8, "state_rmse": 1.0},
        },
    }
    out = ac.judge_robustness(
        cells, {"L": "learned", "A": "analytic", "P": "analytic"}, far=0.01, blind=("P",)
    )["L"]
    assert out["worst_threat_undetected"] is True
    assert out["worst_tpr"] == (0.5, "t1") and out["best_analytic_worst_tpr"] == (0.02, "A", "t1")
    assert "best_reads_no_measurements" not in out["state"]["t1"]  # the best (A) reads
    assert out["state"]["t2"]["holds"] and out["holds"]


def test_judge_robustness_state_factor_and_no_rival():
    cells = {
        "t": {"L": {"state_rmse": 1.08}, "A": {"state_rmse": 1.0}},
        "u": {"L": {"state_rmse": 1.0}},
    }
    out = ac.judge_robustness(cells, {"L": "learned", "A": "analytic"})["L"]
    assert out["state"]["t"]["holds"] is True and out["state"]["u"]["holds"] is False


# --- eval/intervals.py -------------------------------------------------------------
def test_summary_interval_is_central_and_share_ignores_nan():
    values = torch.cat([torch.tensor([0.0]), torch.arange(1.0, 101.0), torch.tensor([math.nan])])
    s = iv._summary(values, lambda v: v > 50, 0.9)
    assert s["low"] == pytest.approx(5.95) and s["high"] == pytest.approx(95.05)
    assert s["holds_share"] == 0.5


def test_two_runs_are_resampled_and_every_run_drawn():
    w = iv.resample_weights(3, 500, seed=0)
    assert bool((w[:, 2] > 0).any()) and iv._study_and_resamples(2, 5, 0).shape == (6, 2)


def test_attack_totals_count_entries_not_steps():
    flags = torch.tensor([[True, False]])
    traj = SimpleNamespace(
        flags=flags, x=torch.zeros(1, 2, 1), attack=torch.zeros(1, 2, 2), info={}
    )
    out = EstimatorOutput(means=torch.zeros(1, 2, 1), attack=torch.ones(1, 2, 2))
    t = iv.run_totals(out, traj, None)
    assert t["attack_n"].tolist() == [2.0]
    assert (
        float(iv.resampled_metric(t, "attack_rmse", torch.ones(1, 1, dtype=torch.float64))) == 1.0
    )


def test_best_ignores_nonfinite_per_resample():
    b = iv._best(
        {"a": torch.tensor([1.0, math.nan]), "b": torch.tensor([math.inf, 2.0])}, higher=False
    )
    assert b.tolist() == [1.0, 2.0]
    b = iv._best({"a": torch.tensor([1.0, -math.inf])}, higher=True)
    assert b[0] == 1.0 and math.isnan(b[1])


def test_stepwise_metric_is_mean_of_per_step_rmse(monkeypatch):
    monkeypatch.setattr(iv, "_STEPWISE", dict(iv._STEPWISE))  # registered for this test only
    iv.register_stepwise("_probe", lambda m, x: (m - x).square().sum(-1))
    t = {"step_se": torch.tensor([[1.0, 16.0]], dtype=torch.float64)}
    assert float(iv.resampled_metric(t, "_probe", torch.ones(1, 1, dtype=torch.float64))) == 2.5


# --- eval/calibration.py calibrated_metrics ----------------------------------------
def _cal(scores, flags, means, threshold):
    out = EstimatorOutput(
        means=means, detection=Detection(scores=scores, alarms=scores > threshold)
    )
    traj = SimpleNamespace(flags=flags, x=torch.zeros_like(means), attack=None, info={}, mask=None)
    return calibrated_metrics(out, traj, threshold, dt=0.1)


def test_impact_over_attacked_runs_only_and_false_alarm_before_onset():
    # run 0: a false alarm at step 0, attack at 1-2 unseen (error 3, 4 in 2-D: norm 5)
    # run 1: never attacked (its error must not enter the mean)
    flags = torch.tensor([[False, True, True], [False, False, False]])
    scores = torch.tensor([[5.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    means = torch.zeros(2, 3, 2)
    means[0, 2] = torch.tensor([3.0, 4.0])
    means[1, :] = 100.0
    m = _cal(scores, flags, means, 1.0)
    assert m["impact"] == 5.0
    assert m["fpr_at_far"] == 0.25 and m["tpr_at_far"] == 0.0


def test_alarms_are_strictly_above_the_threshold():
    flags = torch.tensor([[False, True]])
    m = _cal(torch.tensor([[1.0, 1.0]]), flags, torch.zeros(1, 2, 1), 1.0)
    assert m["fpr_at_far"] == 0.0 and m["tpr_at_far"] == 0.0


def test_after_attack_rate_counts_steps_1_to_10():
    flags = torch.zeros(1, 13, dtype=torch.bool)
    flags[0, 0] = True
    scores = torch.zeros(1, 13)
    scores[0, 11] = 2.0  # step 11: outside the window
    m = _cal(scores, flags, torch.zeros(1, 13, 1), 1.0)
    assert m["fpr_at_far_after_attack"] == 0.0


# --- episodes under a sensor schedule, a clean input, the attack RMSE --------------


def _masked(flags, own, channel=Channel.SENSOR):
    return SimpleNamespace(
        flags=torch.tensor([flags]),
        mask=torch.ones(1, len(flags), 1),
        info={"attack_flags": torch.tensor([own]), "attack_channel": channel},
    )


def test_an_alarm_on_a_lost_reading_does_not_detect():
    traj = _masked([False, True, False, True], [False, True, True, True])
    d = sc.episode_delay(torch.tensor([[False, False, True, True]]), traj)
    assert (d["episodes"], d["mean_delay"]) == (1, 2.0)


def test_an_episode_none_of_whose_readings_arrived_is_no_episode():
    traj = _masked(
        [False, False, False, False, True, False], [True, True, False, False, True, True]
    )
    assert sc.episode_steps(traj)[0].tolist() == [False, False, False, False, True, True]


def test_an_actuator_attack_keeps_the_flags_as_episodes():
    traj = _masked([False, True, False, True], [False, True, True, True], Channel.ACTUATOR)
    assert sc.episode_steps(traj)[0].tolist() == [False, True, False, True]


def test_a_clean_input_estimators_alarms_are_all_false():
    flags = torch.tensor([[False, True, True, False]])
    alarms = torch.tensor([[False, True, True, False]])
    out = EstimatorOutput(
        means=torch.zeros(1, 4, 1), detection=Detection(scores=alarms.double(), alarms=alarms)
    )
    m = sc.score(out, _traj(flags), dt=1.0, wall_s=1.0, attacked_input=False)
    assert m["fpr"] == 0.5 and m["false_alarms"] == 2 and m["tpr"] is None


def test_attack_rmse_reads_only_the_attacked_steps():
    flags = torch.tensor([[True, False]])
    traj = _traj(flags)
    traj.info = {"attack_channel": Channel.SENSOR}
    att = torch.tensor([[[2.0], [5.0]]])  # 5 on the clean step is not scored
    out = EstimatorOutput(means=torch.zeros(1, 2, 1), attack=att)
    assert sc.score(out, traj, dt=1.0, wall_s=1.0)["attack_rmse"] == 2.0


def test_one_run_is_not_resampled():
    assert iv._study_and_resamples(1, 5, 0).shape == (1, 1)


def test_run_totals_detection_counts_and_clean_input():
    flags = torch.tensor([[True, False, False]])
    scores = torch.tensor([[2.0, 2.0, 0.0]])
    traj = SimpleNamespace(
        flags=flags, x=torch.zeros(1, 3, 1), attack=torch.zeros(1, 3, 1), info={}
    )
    out = EstimatorOutput(
        means=torch.zeros(1, 3, 1), detection=Detection(scores=scores, alarms=scores > 1)
    )
    t = iv.run_totals(out, traj, 1.0)
    assert [t[k].item() for k in ("hits", "attacked", "false", "clear")] == [1, 1, 1, 2]
    t = iv.run_totals(out, traj, 1.0, attacked_input=False)
    assert [t[k].item() for k in ("hits", "attacked", "false", "clear")] == [0, 0, 2, 3]


def test_nan_scores_rank_below_negative_scores_in_auc_and_threshold():
    nan = float("nan")
    s = dm.nan_as_lowest(torch.tensor([nan, -1.0]))
    assert dm.roc_auc(s, torch.tensor([True, False])) == 0.0
    assert dm.threshold_for(torch.tensor([nan, nan, -1.0, -2.0]), 0.25) == -2.0
