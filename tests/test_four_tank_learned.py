"""Issue-9 acceptance of the shipped ``four_tank_nn_grad`` checkpoint (``pf_nn_grad``).

The reported figures: ``difffilter-eval four_tank_bias --runs 100`` (seeds 0 and 1). This
test runs the three estimators it needs on the same 100 runs of seed 0 (about 5 s):
attack RMSE at most 1.2 × ``modified_pf_est``'s, detection AUC at least 0.995, at most
0.5 % false alarms at the threshold chosen on validation attacks (saved with the weights),
and a compensated state RMSE against the attack-free PF no worse than ``modified_pf_est``'s.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from difffilter.eval.suite import run_suite
from difffilter.models import registry
from difffilter.models.neural_estimator import load_estimator_checkpoint

CKPT = Path(__file__).resolve().parents[1] / "checkpoints" / "four_tank_nn_grad.ckpt"


@pytest.fixture(scope="module")
def metrics():
    result = run_suite(
        registry.get("four_tank_bias"),
        runs=100,
        seed=0,
        estimators=("normal_pf_attack_free", "modified_pf_est", "pf_nn_grad"),
        progress=False,
    )
    assert result.checkpoint["path"].endswith("four_tank_nn_grad.ckpt")  # the shipped default
    return result.metrics


def test_the_shipped_checkpoint_carries_its_validation_threshold():
    _, observer = load_estimator_checkpoint(CKPT)
    assert observer.filter == "pf" and observer.scenario_family == "four_tank"
    assert 0.0 < observer.threshold < 1.0 and observer.target_false_alarm_rate <= 0.005


def test_attack_estimate_within_1_2_of_the_modified_pf_with_estimated_gamma(metrics):
    assert metrics["pf_nn_grad"]["attack_rmse"] <= 1.2 * metrics["modified_pf_est"]["attack_rmse"]


def test_detection_auc_and_false_alarms_at_the_operating_threshold(metrics):
    assert metrics["pf_nn_grad"]["auc"] >= 0.995
    assert metrics["pf_nn_grad"]["fpr"] <= 0.005


def test_compensated_state_no_worse_than_the_modified_pf_with_estimated_gamma(metrics):
    ours = metrics["pf_nn_grad"]["state_rmse_vs_attack_free"]
    assert ours <= metrics["modified_pf_est"]["state_rmse_vs_attack_free"]


def test_the_ekf_trained_checkpoint_halves_the_attack_error(metrics):
    """``checkpoints/four_tank_nn_ekf.ckpt`` (train/configs/four_tank_ekf.yaml, the EKF over
    the weights) on the same 100 runs: attack RMSE at most 0.6 × ``modified_pf_est``'s
    (0.50 measured), AUC at least 0.99 without a probability head, ≤ 0.5 % false alarms."""
    ekf = CKPT.with_name("four_tank_nn_ekf.ckpt")
    result = run_suite(registry.get("four_tank_bias"), runs=100, seed=0,
                       estimators=("pf_nn_ekf",), checkpoint=ekf, progress=False)  # fmt: skip
    ours = result.metrics["pf_nn_ekf"]
    assert ours["attack_rmse"] <= 0.6 * metrics["modified_pf_est"]["attack_rmse"]
    assert ours["auc"] >= 0.99 and ours["fpr"] <= 0.005
