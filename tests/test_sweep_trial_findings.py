"""Findings of a trial of ``difffilter-train sweep``: its summary and its record."""

from __future__ import annotations

import math

import pytest
import torch

from train.sweep import _calibrated_metrics, _summary

NAN = math.nan


def _per_seed(values):
    return {str(s): {"scenarios": {"four_tank_bias": {"state_rmse": v}}} for s, v in values}


@pytest.mark.parametrize("order", [[(0, 0.5), (1, NAN), (2, 0.9)], [(1, NAN), (0, 0.5), (2, 0.9)]])
def test_a_seed_of_nan_makes_the_summary_unknown_in_any_order(order):
    """Python's min and max skip a NaN or not by the seeds' order: seeds 0 1 2 had a finite
    spread 0.4 beside a NaN mean (the diverged seed hidden), seeds 1 0 2 a NaN spread."""
    stats = _summary(_per_seed(order))["four_tank_bias"]["state_rmse"]
    assert stats == {"mean": None, "min": None, "max": None, "spread": None,
                     "not_a_number": ["1"]}  # fmt: skip


def test_the_summary_of_finite_seeds_is_their_mean_and_spread():
    stats = _summary(_per_seed([(0, 0.5), (1, 0.7), (2, 0.9)]))["four_tank_bias"]["state_rmse"]
    assert stats == pytest.approx({"mean": 0.7, "min": 0.5, "max": 0.9, "spread": 0.4})


def test_a_seeds_metrics_record_the_threshold_they_were_judged_at():
    """The sweep calibrated every estimator's threshold and recorded it nowhere: its
    ``tpr_at_far`` could be tied to no threshold. Now each row holds the threshold and its
    rate on the calibration runs, those of ``calibrate`` itself."""
    from difffilter.eval.calibration import calibrate
    from difffilter.models import registry

    torch.manual_seed(0)
    scenario = registry.get("four_tank_bias").with_steps(30)
    table, _ = _calibrated_metrics(scenario, ["chi_square_ekf"], 4, 0.05, False)
    row = table["chi_square_ekf"]
    calibration = calibrate(scenario, far=0.05, estimators=["chi_square_ekf"], runs=4,
                            progress=False)  # fmt: skip
    assert row["threshold_at_far"] == pytest.approx(calibration.thresholds["chi_square_ekf"])
    assert row["far_measured_on_calibration"] == pytest.approx(
        calibration.measured["chi_square_ekf"]
    )


def test_sweep_json_is_strict_json_where_a_seed_diverged_or_lacks_the_ranked_metric(tmp_path):
    """A trial of the reports' JSON: sweep.json took a diverged seed's ``inf`` error into
    ``per_seed`` and the NaN test score of a seed without the ``--rank-by`` metric into
    ``selection``, bare ``Infinity`` and ``NaN`` that strict readers refuse; both are null
    now (the summary's ``not_a_number`` names the seed)."""
    import json

    from train.sweep import _median, _test_scores, _write

    finite = {"state_rmse": 0.02, "detection_delay_steps": 3.0}
    diverged = {"state_rmse": math.inf, "detection_delay_steps": None}
    per_seed = {s: {"checkpoint": f"{s}.ckpt", "train_time_s": 1.0,
                    "scenarios": {"four_tank_bias": m}}
                for s, m in ((0, finite), (1, diverged))}  # fmt: skip
    scores = _test_scores(per_seed, "detection_delay_steps")
    assert math.isnan(scores[1])
    median = _median(scores, False)
    doc = {"config": "c.yaml", "options": [], "seeds": [0, 1], "far": 0.01, "runs": 4,
           "eval_seed": 0, "rank_by": "detection_delay_steps", "select_on": "test",
           "median_seed": median, "median_checkpoint": per_seed[median]["checkpoint"],
           "selection": {"monitor": None, "scores": {str(s): v for s, v in scores.items()},
                         "median_seed_by_test": median},
           "per_seed": {str(s): v for s, v in per_seed.items()}, "test": "held back",
           "summary": _summary(per_seed)}  # fmt: skip

    def refuse(constant):
        raise ValueError(f"non-standard JSON constant {constant}")

    _write(tmp_path, doc)
    written = json.loads((tmp_path / "sweep.json").read_text(), parse_constant=refuse)
    assert written["selection"]["scores"] == {"0": 3.0, "1": None}
    assert written["per_seed"]["1"]["scenarios"]["four_tank_bias"]["state_rmse"] is None
    assert written["summary"]["four_tank_bias"]["state_rmse"]["not_a_number"] == [1]
    assert math.isinf(doc["per_seed"]["1"]["scenarios"]["four_tank_bias"]["state_rmse"])
