"""The leaderboard's best and hatching, and the watermark study's inputs (a red-team trial).

* An estimator fed more data than the others (role ``more_data``: the tracking plant's
  ``pf_da``, every sensor's packet at every step) had set its scenario's green best, where
  the acceptance leaves it out of the best.
* A robustness leaderboard's ``worst_tpr_at_far``, read at the calibrated threshold, was
  never hatched where that threshold missed its false-alarm band (no ``tpr_at_far`` column
  beside it): a 0.991 at 57 % false alarms painted as the best.
* ``watermark_study`` ran its "with watermark" rows without one for a std of 0 or less or
  NaN, and counted its window and replay in steps whatever the scenario's step (the 1 ms
  scenario: a 0.05 s window, a 0.4–0.7 s recording replayed 31 times).
"""

import math

import numpy as np
import pytest

from difffilter.eval import leaderboard as board
from difffilter.eval import watermark
from difffilter.models import registry


def _goodness(doc, cols):
    rows = board.leaderboard_rows({"scenario": doc})
    grid = np.array([[np.nan if r.get(m) is None else r[m] for m in cols] for r in rows], float)
    good = board.cell_goodness(grid, [r["scenario"] for r in rows], cols, board.ranked_rows(rows),
                               np.full(len(rows), 0.01), np.full(len(rows), np.nan))  # fmt: skip
    return rows, {r["estimator"]: good[i] for i, r in enumerate(rows)}


def test_an_estimator_fed_more_data_does_not_set_the_best():
    doc = {"runs": 3, "seed": 0, "far": {"target": 0.01},
           "estimator_roles": {"pf_da": "more_data", "rrp_pf_da": "analytic", "learned": "learned"},
           "estimators": {"pf_da": {"state_rmse": 0.554}, "rrp_pf_da": {"state_rmse": 1.024},
                          "learned": {"state_rmse": 1.02}}}  # fmt: skip
    _, good = _goodness(doc, ["state_rmse"])
    assert good["learned"][0] == pytest.approx(1.0)  # was 0.75: measured against pf_da
    assert good["rrp_pf_da"][0] > 0.99


def test_a_worst_case_detection_rate_at_an_off_band_threshold_is_hatched():
    doc = {"runs": 2, "seed": 0, "far": {"target": 0.01},
           "estimator_roles": {"normal_pf": "analytic", "chi_square_ekf": "analytic"},
           "estimators": {"normal_pf": {"state_rmse": 0.13, "fpr_at_far": 0.57},
                          "chi_square_ekf": {"state_rmse": 0.02, "fpr_at_far": 0.01}},
           "worst_case": {"normal_pf": {"tpr_at_far": 0.991, "state_error_ratio": 1.0},
                          "chi_square_ekf": {"tpr_at_far": 0.60, "state_error_ratio": 1.0}}}  # fmt: skip
    cols = ["fpr_at_far", "state_rmse", "worst_tpr_at_far", "worst_state_error_ratio"]
    rows = board.leaderboard_rows({"four_tank_bias": doc})
    normal = [r["estimator"] for r in rows].index("normal_pf")
    assert board.off_band_cells(rows, cols) == [(normal, cols.index("worst_tpr_at_far"))]


@pytest.mark.parametrize("std", [0.0, -0.1, math.nan, math.inf, True])
def test_a_watermark_of_no_size_is_refused(std):
    with pytest.raises(ValueError, match="std must be a (finite|real) number"):
        watermark.watermark_study(registry.get("lfc_step"), runs=1, std=std)


@pytest.mark.parametrize("runs", [0, 2.5, True])
def test_the_watermark_study_runs_must_be_a_count(runs):
    with pytest.raises(ValueError, match="runs must be a positive integer"):
        watermark.watermark_study(registry.get("lfc_step"), runs=runs)


class _Stop(Exception):
    pass


@pytest.mark.parametrize(
    ("name", "window", "steps"), [("lfc_step", 50, 1000), ("lfc_sine_1ms", 500, None)]
)
def test_the_watermark_defaults_are_times_in_the_scenarios_steps(monkeypatch, name, window, steps):
    seen = {}

    def first_loop(plant, estimator, xi, *args, attack=None, **kwargs):
        seen.update(window=estimator.detector.window, steps=xi.shape[1])
        raise _Stop

    monkeypatch.setattr(watermark, "lfc_loop", first_loop)
    with pytest.raises(_Stop):
        watermark.watermark_study(registry.get(name), runs=1)
    assert seen["window"] == window  # 0.5 s (was 50 steps at 1 ms too: 0.05 s)
    assert steps is None or seen["steps"] == steps
