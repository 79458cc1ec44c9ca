"""The terminal summary printed by difffilter-eval and make demo."""

from difffilter.eval.report import summary_table


def _row(**values):
    keys = ("state_rmse", "state_rmse_vs_attack_free", "attack_rmse", "tpr", "fpr", "auc")
    return {k: values.get(k) for k in keys}


def test_summary_lists_every_estimator_and_drops_empty_columns():
    results = {
        "four_tank_bias": {
            "runs": 3,
            "steps": 10,
            "estimators": {
                "normal_pf": _row(state_rmse=0.117, tpr=0.97, fpr=0.326, auc=0.831),
                "modified_pf": _row(state_rmse=0.0198, tpr=0.97, fpr=1.99e-4, auc=0.993),
            },
        },
        "lfc_per_channel": {"runs": None, "steps": 1000, "estimators": {}},
    }
    text = summary_table(results)
    lines = text.splitlines()
    assert lines[0] == "four_tank_bias (3 runs × 10 steps)"
    assert "attack RMSE" not in lines[1] and "vs attack-free" not in lines[1]  # empty: dropped
    assert lines[1].split() == ["estimator", "state", "RMSE", "TPR", "FPR", "AUC"]
    assert lines[2].split() == ["normal_pf", "0.117", "0.97", "0.326", "0.831"]
    assert lines[3].split() == ["modified_pf", "0.0198", "0.97", "1.99e-04", "0.993"]
    assert "lfc_per_channel" not in text  # no estimators: no block
