"""Findings of a red-team trial of the threshold calibration (each failed before its fix)."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from difffilter.estimator import Detection, EstimatorOutput
from difffilter.eval.calibration import alarms_at, below_target_note, calibrate
from difffilter.models import estimators, registry


@pytest.fixture
def own_estimators(monkeypatch):
    estimators.names()
    monkeypatch.setattr(estimators, "ESTIMATORS", dict(estimators.ESTIMATORS))


def _scoring_a_share(share_without_score: float):
    """A detector whose score is noise-driven, about U(0, 1), NaN (no data) on a share of
    the steps."""

    def factory(ctx):
        def run(traj):
            y = traj.y_recv.double()
            runs, steps = y.shape[:2]
            u = (y.reshape(runs, steps, -1).sum(-1) * 1000.0).frac().abs()
            scores = torch.where(u < share_without_score, torch.full_like(u, math.nan), u)
            return EstimatorOutput(torch.zeros(runs, steps, ctx.model.dim_x, dtype=y.dtype),
                                   detection=Detection(scores, scores > 0.99, 0.99))  # fmt: skip

        return run

    return factory


def test_the_resolution_of_a_calibration_counts_every_step_its_threshold_counts(own_estimators):
    """The diagnostics counted the scored steps alone where the threshold allows ⌊α n⌋
    alarms over every step (NaN its lowest score): a detector scoring 5 % of 5,000 steps
    was listed as resting on 2.35 alarms (its threshold rested on 50); one scoring 0.5 %,
    whose every scored step alarms, was said to have α n < 1."""
    estimators.register("rt_nan95", "95 % of steps without a score")(_scoring_a_share(0.95))
    estimators.register("rt_nan995", "99.5 % without a score")(_scoring_a_share(0.995))
    sc = registry.get("four_tank_bias")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate(sc, far=0.01, runs=50, seed=0, estimators=["rt_nan95", "rt_nan995"],
                        progress=False)  # fmt: skip
    n = 50 * sc.steps
    assert cal.steps == {"rt_nan95": n, "rt_nan995": n}
    assert cal.scored["rt_nan95"] < 0.1 * n and cal.scored["rt_nan995"] < 0.01 * n
    assert round(cal.measured["rt_nan95"] * n) == math.floor(0.01 * n)  # 50 alarms
    summary = cal.summary()
    assert "unresolved" not in summary and "rt_nan95" not in summary.get("below_target", {})
    assert cal.thresholds["rt_nan995"] == -math.inf
    assert summary["below_target"]["rt_nan995"]["cause"] == "few scores"
    note = below_target_note(summary)
    assert "every scored step alarms" in note and "α n < 1" not in note


def test_a_nan_threshold_is_refused():
    """A NaN threshold (np.quantile over scores holding a NaN) alarmed nowhere: TPR and FPR
    read 0 without a word."""
    scores = torch.tensor([0.1, 0.5, 2.0])
    with pytest.raises(ValueError, match="threshold must be a number"):
        alarms_at(scores, math.nan)
    assert alarms_at(scores, math.inf).tolist() == [False] * 3
    assert alarms_at(scores, -math.inf).tolist() == [True] * 3
