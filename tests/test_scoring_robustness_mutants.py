"""Mutation-review tests of eval/scoring.py and eval/robustness.py: each pins a behaviour
that a small mutation changed while the rest of the suite still passed. Every expected
number is computed by hand (numpy on tiny [B, T] arrays, or read off a small cells dict)."""

from __future__ import annotations

import math
import warnings
from types import SimpleNamespace

import numpy as np
import torch

from difffilter.eval import robustness as rb
from difffilter.eval import scoring
from difffilter.eval.robustness import ThreatSet, _activity, _idle, _worst_cases


def _auc_by_hand(scores: np.ndarray, flags: np.ndarray) -> float:
    """P(positive score > negative score) + P(tie) / 2 over every pair, NaN as -inf."""
    s = np.where(np.isnan(scores), -np.inf, scores).ravel()
    y = flags.ravel()
    pos, neg = s[y], s[~y]
    wins = sum(float(p > n) + 0.5 * float(p == n) for p in pos for n in neg)
    return wins / (len(pos) * len(neg))


def test_nan_scores_rank_lowest_in_auc_roc_and_tpr_at_budget():
    """A NaN score (no data at that step) ranks below every score: the AUC, the ROC and
    ``tpr_at_1pct_fpr`` of scoring's helpers against the pairwise AUC by hand (NaN as
    -inf) and the ROC read by hand. Kills: NaN mapped to the highest score (+inf)."""
    s = np.array([[0.5, np.nan, 0.2, 0.9], [np.nan, 0.7, 0.1, 0.3]])
    y = np.array([[True, False, False, True], [False, True, False, False]])
    scores, flags = torch.tensor(s), torch.tensor(y)
    truth = _auc_by_hand(s, y)
    assert truth == 1.0  # every positive above every negative once NaN is lowest
    assert scoring.auc(scores, flags) == truth
    fpr, tpr = scoring.roc(scores, flags)
    # thresholds 0.9, 0.7, 0.5 take the three positives before any negative
    assert float(tpr[fpr == 0].max()) == 1.0
    assert scoring._tpr_at(scores, flags, scoring.FALSE_ALARM_BUDGET) == 1.0


def test_activity_counts_only_values_injected_on_flagged_steps():
    """``_activity``'s ``injected`` reads the attack on the flagged steps only: a threat
    whose flagged step carries 0 and whose non-zero value lies on an unflagged step
    injected nothing (by hand: attack[flags] == [0]), so it is idle. Kills: ``injected``
    read over every step."""
    flags = torch.zeros(2, 4, dtype=torch.bool)
    flags[0, 1] = True
    attack = torch.zeros(2, 4, 1)
    attack[0, 3] = 2.0  # not flagged
    attack[1, 0] = -1.0  # not flagged, another run
    a = _activity(SimpleNamespace(flags=flags, attack=attack))
    assert a == {"attacked_runs": 1, "runs": 2, "attacked_steps": 1, "injected": False}
    assert _idle(a)


def test_worst_case_passes_over_a_tpr_or_auc_that_is_not_finite():
    """A TPR or AUC that is NaN (no attacked step) is no worst case: the lowest finite
    one of the other threats is, read by hand from the cells (tpr 0.7 and auc 0.9 under
    ``b``), with no ``_diverged`` flag. Kills: a non-finite lower-is-worse value taken as
    diverged (inf)."""
    nan = math.nan
    cells = {
        "a": {"kf": {"tpr_at_far": nan, "auc": nan, "state_error_ratio": 1.5, "impact": 0.2}},
        "b": {"kf": {"tpr_at_far": 0.7, "auc": 0.9, "state_error_ratio": 1.2, "impact": 0.4}},
        "c": {"kf": {"tpr_at_far": 0.95, "auc": 0.99, "state_error_ratio": 1.1, "impact": 0.1}},
    }
    w = _worst_cases(cells)["kf"]
    assert (w["tpr_at_far"], w["tpr_at_far_threat"]) == (0.7, "b")
    assert (w["auc"], w["auc_threat"]) == (0.9, "b")
    assert (w["state_error_ratio"], w["state_error_ratio_threat"]) == (1.5, "a")
    assert (w["impact"], w["impact_threat"]) == (0.4, "b")
    assert not any(k.endswith("_diverged") for k in w)


def test_run_robustness_leaves_an_idle_threat_out_of_the_worst_case(monkeypatch):
    """``run_robustness`` with its calibration and suites faked (no filter runs): threat
    ``zero`` flags steps but injects 0 (idle), ``bias`` injects 0.5. The worst case over
    the acting threats, read by hand from the cells, is ``bias``'s: TPR 0.8 and ratio
    2.0 / 1.0 = 2.0; the idle threat's worse TPR 0.01 and ratio 3.0 are left out. Kills:
    the worst case taken over every threat, idle ones included."""
    flags = torch.zeros(2, 3, dtype=torch.bool)
    flags[0, 1:] = True
    trajs = {
        "zero": SimpleNamespace(flags=flags, attack=torch.zeros(2, 3, 1)),
        "bias": SimpleNamespace(flags=flags, attack=torch.where(flags, 0.5, 0.0)[..., None]),
    }
    metrics = {
        "attack-free": {"kf": {"state_rmse": 1.0, "fpr_at_far": 0.01}},
        "zero": {"kf": {"state_rmse": 3.0, "tpr_at_far": 0.01, "auc": 0.5, "impact": 9.0}},
        "bias": {"kf": {"state_rmse": 2.0, "tpr_at_far": 0.8, "auc": 0.95, "impact": 1.0}},
    }

    def fake_suite(scenario, *, label, **_):
        key = label.split(": ")[1]
        return SimpleNamespace(metrics=metrics[key], skipped={}, traj=trajs.get(key))

    monkeypatch.setattr(rb, "calibrate", lambda *a, **k: SimpleNamespace(thresholds={"kf": 1.0}))
    monkeypatch.setattr(rb, "run_suite", fake_suite)
    monkeypatch.setattr(rb, "broken_down", lambda skipped: {})
    monkeypatch.setattr(rb, "threat_totals", lambda suite, roles: {})
    monkeypatch.setattr(rb, "roles", lambda m: {})
    monkeypatch.setattr(rb, "_check_threat", lambda scenario, model, threat: None)
    scenario = SimpleNamespace(name="toy", runs=2, with_threat=lambda threat: None,
                               system=lambda: None)  # fmt: skip
    threats = ThreatSet({"zero": object(), "bias": object()}, {"zero": {}, "bias": {}})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = rb.run_robustness(scenario, threats, progress=False)
    assert result.idle() == ["zero"]
    assert result.cells["zero"]["kf"]["state_error_ratio"] == 3.0  # the cell stays
    w = result.worst_case["kf"]
    assert (w["tpr_at_far"], w["tpr_at_far_threat"]) == (0.8, "bias")
    assert (w["state_error_ratio"], w["state_error_ratio_threat"]) == (2.0, "bias")
    assert (w["impact"], w["impact_threat"]) == (1.0, "bias")


def _traj(flags, x, attack, channel):
    return SimpleNamespace(flags=flags, x=x, attack=attack, mask=None,
                           info={"attack_channel": channel})  # fmt: skip


def test_attack_rmse_only_for_an_estimate_of_the_same_side_and_width():
    """``attack_rmse`` compares the attack estimate with the recorded attack only where
    both are on the same side of the plant and equally wide: by hand, with a sensor
    estimate [1, 3] against the attack [0, 1] on the two flagged steps,
    sqrt((1 + 4) / 2); an actuator estimate of a sensor attack, or a two-entry estimate of
    a one-entry attack, gives ``None``. Kills: the side check or the width check dropped."""
    from difffilter.attack import Channel
    from difffilter.estimator import EstimatorOutput

    flags = torch.tensor([[False, True, True, False]])
    x = torch.zeros(1, 4, 1)
    attack = torch.tensor([[0.0, 0.0, 1.0, 0.0]])[..., None]
    a_hat = torch.tensor([[5.0, 1.0, 3.0, 5.0]])[..., None]
    traj = _traj(flags, x, attack, Channel.SENSOR)
    same = EstimatorOutput(x.clone(), attack=a_hat)
    out = scoring.score(same, traj, dt=0.1, wall_s=1.0)
    assert math.isclose(out["attack_rmse"], math.sqrt((1.0 + 4.0) / 2))
    other_side = EstimatorOutput(x.clone(), attack=a_hat, attack_channel=Channel.ACTUATOR)
    assert scoring.score(other_side, traj, dt=0.1, wall_s=1.0)["attack_rmse"] is None
    wide = EstimatorOutput(x.clone(), attack=a_hat.expand(1, 4, 2).clone())
    wide_traj = _traj(flags, x, attack, Channel.SENSOR)
    assert scoring.score(wide, wide_traj, dt=0.1, wall_s=1.0)["attack_rmse"] is None


def test_auc_is_none_without_both_classes():
    """``scoring.auc`` is ``None`` where every step is attack-free (or every step
    attacked): no ROC exists (by hand: no positive/negative pair). Kills: a fallback of
    0.5 in place of ``None``."""
    scores = torch.tensor([[0.1, 0.4, 0.3]])
    assert scoring.auc(scores, torch.zeros(1, 3, dtype=torch.bool)) is None
    assert scoring.auc(scores, torch.ones(1, 3, dtype=torch.bool)) is None


def test_delay_at_far_alarms_strictly_above_the_threshold():
    """``detection_delay_at_far_steps`` uses the alarms ``score > threshold``: a score
    equal to the threshold at the onset is no alarm, so by hand the episode at steps
    1..3 is detected at step 2 (score 2 > 1): delay 1, ``_s`` = 1 * 0.5. Kills: the delay
    computed from ``score >= threshold``."""
    from difffilter.eval.calibration import calibrated_metrics

    flags = torch.tensor([[False, True, True, True, False]])
    scores = torch.tensor([[0.0, 1.0, 2.0, 0.0, 0.0]])
    x = torch.zeros(1, 5, 1)
    output = SimpleNamespace(detection=SimpleNamespace(scores=scores), means=x.clone())
    traj = _traj(flags, x, torch.zeros(1, 5, 1), "sensor")
    out = calibrated_metrics(output, traj, 1.0, dt=0.5)
    assert out["tpr_at_far"] == 1 / 3
    assert out["detection_delay_at_far_steps"] == 1.0
    assert out["detection_delay_at_far_s"] == 0.5


def test_diverged_state_error_is_the_worst_as_inf():
    """A non-finite state-error ratio or impact (an estimate that diverged) is the worst
    case as ``inf`` with ``_diverged`` set and the first such threat by name (``a``),
    whatever finite values other threats have (read by hand). Kills: the NaN itself kept
    as the worst value."""
    cells = {
        "a": {"kf": {"tpr_at_far": 0.9, "state_error_ratio": math.nan, "impact": math.nan}},
        "b": {"kf": {"tpr_at_far": 0.8, "state_error_ratio": 4.0, "impact": 2.0}},
        "c": {"kf": {"tpr_at_far": 0.7, "state_error_ratio": math.inf, "impact": 1.0}},
    }
    w = _worst_cases(cells)["kf"]
    assert w["state_error_ratio"] == math.inf and w["state_error_ratio_threat"] == "a"
    assert w["impact"] == math.inf and w["impact_threat"] == "a"
    assert w["state_error_ratio_diverged"] and w["impact_diverged"]
    assert (w["tpr_at_far"], w["tpr_at_far_threat"]) == (0.7, "c")


def test_cell_copies_the_metrics_and_has_no_ratio_without_a_positive_base():
    """``_cell`` keeps every cell metric as given (auc included) and the ratio
    state_rmse / attack-free state_rmse (by hand 3 / 2 = 1.5); with an attack-free RMSE
    of 0 or none it has no ratio (``None``, not a division error). Kills: a metric dropped
    from the cell, the base's checks dropped."""
    m = {"tpr_at_far": 0.4, "impact": 0.3, "auc": 0.77, "fpr_at_far": 0.02,
         "state_rmse": 3.0, "attack_rmse": 0.5, "other": 1}  # fmt: skip
    cell = rb._cell(m, {"state_rmse": 2.0})
    assert cell == {"tpr_at_far": 0.4, "impact": 0.3, "auc": 0.77, "fpr_at_far": 0.02,
                    "state_rmse": 3.0, "attack_rmse": 0.5, "state_error_ratio": 1.5}  # fmt: skip
    assert rb._cell(m, {"state_rmse": 0.0})["state_error_ratio"] is None
    assert rb._cell(m, {})["state_error_ratio"] is None
