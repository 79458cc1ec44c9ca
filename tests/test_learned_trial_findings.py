"""Findings of a trial of the learned estimator as a user loads and calibrates it
(2026-12-04).

* ``load_estimator`` ran the tracking checkpoint with its card's 200 particles (its
  training filter) while its threshold had been calibrated with the scenario's 500: 1.36 %
  false alarms on fresh attack-free runs for a 1 % target, 1.19 % at 500.
* A card with a NaN threshold loaded without a word and never alarmed; ``standardize:
  "no"`` read as true; a target rate of 2 loaded; a threshold edited in the JSON card beside
  the checkpoint was ignored silently (the checkpoint's own card runs).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest
import torch

import difffilter
from difffilter.models import registry
from difffilter.models.generic_estimators import deception_of
from difffilter.models.learned_estimator import calibrated_particles
from difffilter.models.neural_estimator import (
    EstimatorCard,
    load_estimator_checkpoint,
    save_estimator_checkpoint,
)

ROOT = Path(__file__).resolve().parents[1] / "checkpoints"


def test_a_pf_checkpoint_runs_with_the_particles_its_threshold_was_calibrated_with():
    _, tracking = load_estimator_checkpoint(ROOT / "tracking_nn_grad.ckpt")
    assert tracking.num_particles == 200  # the training filter's
    # recorded since its recalibration of 2026-12-06: the scenario's particles
    assert tracking.extra["calibration"]["num_particles"] == 500
    assert calibrated_particles(tracking) == 500
    # a card calibrated before they were recorded was scored through its scenario's
    # registered entry: the scenario's particles
    unrecorded = {k: v for k, v in tracking.extra["calibration"].items() if k != "num_particles"}
    before = dataclasses.replace(tracking, extra={**tracking.extra, "calibration": unrecorded})
    assert (
        calibrated_particles(before) == registry.get("tracking_rrp_deception").num_particles == 500
    )
    scenario = registry.get("tracking_rrp_deception")
    deception = deception_of(scenario.attack_model(), torch.float64)[0]
    loaded = difffilter.load_estimator(ROOT / "tracking_nn_grad.ckpt", deception=deception)
    assert loaded.estimator.inner.num_particles == 500
    given = difffilter.load_estimator(ROOT / "tracking_nn_grad.ckpt", deception=deception,
                                      num_particles=64)  # fmt: skip
    assert given.estimator.inner.num_particles == 64
    _, four_tank = load_estimator_checkpoint(ROOT / "four_tank_nn_grad.ckpt")
    assert calibrated_particles(four_tank) == 100 == four_tank.num_particles


def test_the_recorded_particles_come_first_and_a_card_without_calibration_keeps_its_own():
    card = EstimatorCard(filter="pf", num_particles=200, extra={
        "calibration": {"scenario": "tracking_rrp_deception", "num_particles": 333}})  # fmt: skip
    assert calibrated_particles(card) == 333
    assert calibrated_particles(dataclasses.replace(card, extra={})) == 200
    # a scenario of one's own, not registered here: the card's
    unknown = dataclasses.replace(card, extra={"calibration": {"scenario": "my_plant"}})
    assert calibrated_particles(unknown) == 200


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("threshold", float("nan"), "threshold must be a number"),
        ("threshold", "0.1", "threshold must be a number"),
        ("standardize", "no", "standardize must be true or false"),
        ("gating", 1, "gating must be true or false"),
        ("target_false_alarm_rate", 2.0, "target_false_alarm_rate must be a rate"),
        ("target_false_alarm_rate", float("nan"), "target_false_alarm_rate must be a rate"),
        ("restart", 0.0, "restart must be a rate"),
        ("num_particles", 0, "num_particles must be a positive integer"),
        ("num_particles", 2.5, "num_particles must be a positive integer"),
    ],
)
def test_a_card_with_a_value_it_cannot_run_with_is_refused(field, value, message):
    with pytest.raises(ValueError, match=message):
        EstimatorCard(**{field: value})


def test_infinite_thresholds_stay_legal():
    """The threshold rule may give ±inf (no score above it, or every one): still a card."""
    assert EstimatorCard(threshold=float("inf")).threshold == float("inf")
    assert EstimatorCard(threshold=-float("inf")).threshold == -float("inf")


def test_a_checkpoint_whose_own_card_is_broken_is_refused_by_name(tmp_path):
    blob = torch.load(ROOT / "four_tank_nn_grad.ckpt", weights_only=True)
    blob["observer"] = {**blob["observer"], "threshold": float("nan")}
    path = tmp_path / "nan.ckpt"
    torch.save(blob, path)  # no JSON card beside it: no sha256 to compare
    with pytest.raises(ValueError, match=r"unreadable card \(threshold must be a number"):
        load_estimator_checkpoint(path)


def test_a_json_card_that_says_otherwise_than_the_checkpoint_is_refused(tmp_path):
    src = ROOT / "four_tank_nn_grad.ckpt"
    shutil.copy(src, tmp_path / "c.ckpt")
    document = json.loads(src.with_suffix(".json").read_text())
    (tmp_path / "c.json").write_text(json.dumps(document))
    _, card = load_estimator_checkpoint(tmp_path / "c.ckpt")  # as shipped: the same card
    document["observer"]["threshold"] = 999.0
    (tmp_path / "c.json").write_text(json.dumps(document))
    with pytest.raises(ValueError, match=r"threshold = 999.0 there, 0.092\d* inside"):
        load_estimator_checkpoint(tmp_path / "c.ckpt")
    # an explicit sha256 compares no JSON card
    net, _ = load_estimator_checkpoint(tmp_path / "c.ckpt", expected_sha256=document["sha256"])
    assert net is not None


def test_calibrate_and_export_write_cards_that_agree(tmp_path):
    """What the library writes passes the comparison: a saved checkpoint with a JSON card
    made from the same card."""
    net, card = load_estimator_checkpoint(ROOT / "robot_nn_ekf.ckpt")
    out = tmp_path / "r.ckpt"
    digest = save_estimator_checkpoint(out, net, dataclasses.replace(card, threshold=7.5))
    _, saved = load_estimator_checkpoint(out)
    out.with_suffix(".json").write_text(json.dumps({"sha256": digest, "observer": saved.to_dict()}))
    _, again = load_estimator_checkpoint(out)
    assert again.threshold == 7.5
