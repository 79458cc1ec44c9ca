"""The threshold a fit's validation chose travels in the card with the statistic it was
chosen for (``FilterEstimatorTask._threshold_record``), so that the LFC entries, which read
a card's threshold only where its ``calibration`` names the entry and the statistic, alarm
at it by default; what a validation did not choose is not recorded."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
import yaml

from difffilter.metrics import threshold_for
from difffilter.models import registry
from difffilter.models.lfc_estimators import PROBABILITY, confirmed_statistic
from difffilter.train.task import FilterEstimatorTask, training_batch

CONFIG = Path(__file__).parents[1] / "train" / "configs" / "lfc.yaml"


def _task(**options) -> FilterEstimatorTask:
    config = yaml.safe_load(CONFIG.read_text())["model"]["init_args"]
    return FilterEstimatorTask(**{**config, "hidden": 4, **options})


def _validate(task: FilterEstimatorTask) -> dict:
    """One validation without a trainer: the threshold chosen on the batch's quiet steps."""
    scenario = registry.get("lfc_random_attacks").with_steps(80)
    batch = training_batch(scenario, 3, 11, torch.float32)
    with pytest.warns(UserWarning, match="self.log"):  # no trainer to log to
        return task._scores("val", scenario, batch, None)


@pytest.mark.parametrize("confirm", [None, 0.01])
def test_a_validation_s_threshold_is_recorded_for_the_head_s_statistic(confirm):
    task = _task(confirm=confirm)
    assert "calibration" not in task.card().extra  # no validation has chosen one yet
    scores = _validate(task)
    card = task.card()
    record = card.extra["calibration"]
    assert record["estimator"] == card.estimator == "kf_nn_grad"
    assert record["score"] == confirmed_statistic(PROBABILITY, confirm)
    assert record["threshold"] == card.threshold == scores["threshold"]
    assert record["target"] == card.target_false_alarm_rate == 0.01
    # the rate met where it was chosen: the batch's attack-free steps, recomputed here
    assert record["measured_on_calibration"] == pytest.approx(scores["fpr"], abs=1e-12)
    assert 0.0 <= record["measured_on_calibration"] <= 0.01


def test_no_record_for_a_network_without_a_head():
    task = _task(detection_head=False, restart=None, confirm=None, gating=False)
    _validate(task)
    assert "calibration" not in task.card().extra  # its score is not what the entries read


def test_the_rate_travels_with_the_threshold_through_a_state_dict():
    task = _task()
    _validate(task)
    state = task.state_dict()
    fresh = _task()
    fresh.load_state_dict(state)
    assert fresh.card().extra == task.card().extra
    # a checkpoint from before the rate was kept loads, with the rate unknown: no record
    old = {k: v for k, v in state.items() if k != "alarm_threshold_rate"}
    older = _task()
    older.load_state_dict(old)
    assert float(older.alarm_threshold) == float(task.alarm_threshold)
    assert math.isnan(float(older.alarm_threshold_rate))
    assert "calibration" not in older.card().extra


def test_the_recorded_threshold_is_threshold_for_on_the_quiet_steps():
    task = _task()
    scenario = registry.get("lfc_random_attacks").with_steps(80)
    batch = training_batch(scenario, 3, 11, torch.float32)
    out, truth = task._evaluate(scenario, batch)
    quiet = out.detection.scores[~truth["flags"]]
    with pytest.warns(UserWarning, match="self.log"):
        task._scores("val", scenario, batch, None)
    assert float(task.alarm_threshold) == threshold_for(quiet, 0.01)
