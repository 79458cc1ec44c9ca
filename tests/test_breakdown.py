"""An estimator that breaks down on a study's data is left out with the reason; the others
are reported (a robotics trial: an EKF whose first prediction sat on a landmark, where the
range has no derivative, aborted the whole evaluation, every other estimator unreported).
"""

from __future__ import annotations

import json
import sys
import textwrap

import jsonschema
import pytest
import torch

import difffilter as df
from difffilter.eval.calibration import below_target_note, calibrate
from difffilter.eval.report import metrics_schema, write_report
from difffilter.eval.suite import BROKE_DOWN, run_suite
from difffilter.linalg import safe_cholesky
from difffilter.models.yaml_scenario import scenario_from_dict

# h(x) = (‖(x0, x1)‖, x1): no derivative at the origin, where the prior mean starts and the
# transition (a slow decay) keeps the EKF's first prediction
PLANT_MODULE = textwrap.dedent("""
    import torch


    def decay(x):
        return 0.9 * x


    def range_and_height(x):
        return torch.stack([torch.sqrt(x[..., 0] ** 2 + x[..., 1] ** 2), x[..., 1]], -1)
""")


@pytest.fixture
def at_the_sensor(tmp_path, monkeypatch):
    (tmp_path / "breakdown_plants.py").write_text(PLANT_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield scenario_from_dict({
        "name": "at_the_sensor", "family": "breakdown_tests", "dt": 0.1, "runs": 6,
        "steps": 12, "num_particles": 64, "false_alarm_rate": 0.05,
        "plant": {"transition": "breakdown_plants:decay", "observe": "breakdown_plants:range_and_height",
                  "Q": 1.0e-2, "R": 1.0e-2, "m0": [0.0, 0.0], "P0": 1.0e-2},
        "attack": {"kind": "bias", "value": 0.5, "entries": [1], "onset": 6, "share": 0.5},
    }, "at_the_sensor.yaml")  # fmt: skip
    sys.modules.pop("breakdown_plants", None)


def test_safe_cholesky_raises_the_breakdown_as_a_value_error():
    with pytest.raises(df.NumericalBreakdown, match="Cholesky factorisation failed") as caught:
        safe_cholesky(torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=torch.float64), name="S")
    assert isinstance(caught.value, ValueError)  # every `except ValueError` still holds


def test_the_ekf_that_cannot_linearise_is_left_out_and_the_others_reported(at_the_sensor,
                                                                            tmp_path):  # fmt: skip
    model = at_the_sensor.system(torch.float64)
    ys = torch.full((1, 3, 2), 0.1, dtype=torch.float64)
    with pytest.raises(df.NumericalBreakdown, match="observation Jacobian"):
        df.extended_kalman_filter(model, ys)

    names = ["chi_square_ekf", "cusum_ekf", "chi_square_ukf"]
    with pytest.warns(UserWarning) as warned:
        cal = calibrate(at_the_sensor, far=0.05, runs=4, estimators=names, progress=False)
    assert _broke_down(warned) == {"chi_square_ekf", "cusum_ekf"}
    # the EKF breaks down on the attack-free runs too: no threshold, and said why
    assert set(cal.thresholds) == {"chi_square_ukf"}
    assert set(cal.broke_down) == {"chi_square_ekf", "cusum_ekf"}
    assert "observation Jacobian" in cal.broke_down["chi_square_ekf"]
    assert "has no threshold" in below_target_note(cal.summary())
    with pytest.warns(UserWarning) as warned:
        result = run_suite(at_the_sensor, runs=4, estimators=names, progress=False,
                           calibration=cal)  # fmt: skip
    assert _broke_down(warned) == {"chi_square_ekf", "cusum_ekf"}
    assert list(result.outputs) == ["chi_square_ukf"]
    for name in ("chi_square_ekf", "cusum_ekf"):
        assert result.skipped[name].startswith(f"{BROKE_DOWN}: the observation Jacobian")
    assert result.metrics["chi_square_ukf"]["tpr_at_far"] is not None

    out = tmp_path / "report"
    write_report(out, result)
    doc = json.loads((out / "metrics.json").read_text())
    jsonschema.validate(doc, metrics_schema())
    assert doc["skipped"]["cusum_ekf"].startswith(BROKE_DOWN)
    assert set(doc["far"]["broke_down"]) == {"chi_square_ekf", "cusum_ekf"}
    report = (out / "report.md").read_text()
    assert "`chi_square_ekf` (broke down on this study's data" in report
    assert "`cusum_ekf` has no threshold" in report


def _broke_down(warned) -> set[str]:
    """The estimators named by the breakdown warnings of ``warned`` (each names its study)."""
    texts = [str(w.message) for w in warned]
    return {t.split(" on at_the_sensor broke down")[0] for t in texts if " broke down" in t}


def test_any_other_error_of_an_estimator_still_stops_the_study(at_the_sensor, monkeypatch):
    from difffilter.extended import ExtendedKalmanFilter

    def wrong(*args, **kwargs):
        raise ValueError("a wrong argument")

    monkeypatch.setattr(ExtendedKalmanFilter, "update", wrong)
    with pytest.raises(ValueError, match="chi_square_ekf on at_the_sensor: a wrong argument"):
        run_suite(at_the_sensor, runs=2, estimators=["chi_square_ekf"], progress=False)


def test_a_breakdown_under_one_threat_is_that_estimators_worst_case(tmp_path, monkeypatch):
    """Left out of the threat's cells, an estimator that broke down under it had its worst
    case taken over the other threats alone: more robust than one that ran and erred."""
    from difffilter.eval.robustness import load_threat_set, run_robustness, write_robustness
    from difffilter.extended import ExtendedKalmanFilter
    from difffilter.models import registry

    update = ExtendedKalmanFilter.update

    def breaks_on_a_huge_reading(self, carry, prediction, y, mask, **kwargs):
        if bool((y.abs() > 500).any()):
            raise df.NumericalBreakdown("a reading out of range (a test's breakdown)")
        return update(self, carry, prediction, y, mask, **kwargs)

    monkeypatch.setattr(ExtendedKalmanFilter, "update", breaks_on_a_huge_reading)
    sc = registry.get("four_tank_bias").with_steps(40)
    spec = tmp_path / "t.yaml"
    spec.write_text("threats:\n  bias: {kind: bias, value: 0.5, onset: 21}\n"
                    "  huge: {kind: bias, value: 1000.0, onset: 21}\n")  # fmt: skip
    threat_set = load_threat_set(sc, path=spec)
    threat_set.estimators = ("chi_square_ekf", "normal_pf")
    with pytest.warns(UserWarning) as warned:
        result = run_robustness(sc, threat_set, runs=6, progress=False)
    assert any("chi_square_ekf on four_tank_bias broke down" in str(w.message) for w in warned)
    cell = result.cells["huge"]["chi_square_ekf"]
    assert cell["broke_down"].startswith(f"{BROKE_DOWN}: a reading out of range")
    assert cell["tpr_at_far"] == 0.0 and cell["state_error_ratio"] is None
    assert result.cells["bias"]["chi_square_ekf"]["state_error_ratio"] > 1.0  # it ran there
    worst = result.worst_case["chi_square_ekf"]
    assert worst["tpr_at_far"] == 0.0 and worst["tpr_at_far_threat"] == "huge"
    assert worst["state_error_ratio"] == float("inf") and worst["state_error_ratio_broke_down"]
    assert worst["impact_threat"] == "huge"
    assert "broke_down" not in result.cells["huge"]["normal_pf"]  # the others as before
    write_robustness(tmp_path / "out", result)
    written = json.loads((tmp_path / "out" / "robustness.json").read_text())
    jsonschema.validate(written, metrics_schema())
    text = (tmp_path / "out" / "robustness.md").read_text()
    assert "Broke down under a threat" in text and "`chi_square_ekf` under `huge`" in text
    assert "broke down (huge)" in text
