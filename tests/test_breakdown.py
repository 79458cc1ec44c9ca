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
from difffilter.eval.provenance import software_line, software_record
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
    # which code wrote it (eval/provenance.py), in the JSON and in the summary
    assert doc["software"] == software_record()
    assert software_line(doc["software"]).strip() in report
    assert "`cusum_ekf` has no threshold" in report


def _broke_down(warned) -> set[str]:
    """The estimators named by the breakdown warnings of ``warned`` (each names its study)."""
    texts = [str(w.message) for w in warned]
    return {t.split(" broke down on at_the_sensor")[0] for t in texts if " broke down on" in t}


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
    assert any("chi_square_ekf broke down on four_tank_bias: huge" in str(w.message)
               for w in warned)  # fmt: skip
    cell = result.cells["huge"]["chi_square_ekf"]
    assert cell["broke_down"].startswith("a reading out of range")
    assert cell["tpr_at_far"] == 0.0 and cell["state_error_ratio"] is None
    assert result.cells["bias"]["chi_square_ekf"]["state_error_ratio"] > 1.0  # it ran there
    worst = result.worst_case["chi_square_ekf"]
    assert worst["tpr_at_far"] == 0.0 and worst["tpr_at_far_threat"] == "huge"
    assert worst["state_error_ratio"] == float("inf") and worst["state_error_ratio_broke_down"]
    assert worst["impact_threat"] == "huge"
    assert "broke_down" not in result.cells["huge"]["normal_pf"]  # the others as before
    write_robustness(tmp_path / "out", result)

    def refuse(constant):  # strict JSON: the broken-down cells' inf is null (a mutation
        raise ValueError(f"non-standard JSON constant {constant}")  # trial: not pinned)

    written = json.loads((tmp_path / "out" / "robustness.json").read_text(), parse_constant=refuse)
    jsonschema.validate(written, metrics_schema())
    assert written["software"] == software_record()
    # its dt, which the leaderboard's rows read (null after a robustness study: a review)
    assert written["dt_s"] == sc.dt == 1.0
    from difffilter.eval.leaderboard import leaderboard_rows

    assert {row["dt_s"] for row in leaderboard_rows({"four_tank_bias": written})} == {1.0}
    text = (tmp_path / "out" / "robustness.md").read_text()
    assert "Broke down under a threat" in text and "`chi_square_ekf` under `huge`" in text
    assert "broke down (huge)" in text


def test_the_default_suite_runs_where_the_poa_thresholds_cannot_be_computed(at_the_sensor):
    """From a review: the probability-of-attack detector's factory linearises h at the
    prior mean, where it has no derivative here; 'G contains NaN or Inf' stopped the default
    suite before any estimator ran."""
    with pytest.warns(UserWarning):
        result = run_suite(at_the_sensor, runs=3, progress=False)
    assert result.skipped["normal_pf"].startswith(f"{BROKE_DOWN}: the observation Jacobian")
    assert "PoA detector" in result.skipped["normal_pf"]
    assert "chi_square_ukf" in result.outputs and "normal_pf" not in result.outputs


def test_a_learned_estimator_that_broke_down_fails_the_acceptance_and_a_rival_is_named():
    """From a review: a learned estimator that broke down vanished from the verdicts (no
    row, acceptance.md removed); an analytic one vanished from the comparison unsaid."""
    from difffilter.eval.report import _acceptance_section, _judged

    metrics = {"tpr_at_far": 0.9, "state_rmse": 1.0, "fpr_at_far": 0.01, "auc": 0.99}
    doc = {"estimators": {"chi_square_kf": metrics}, "far": {"target": 0.01},
           "estimator_roles": {"chi_square_kf": "analytic"},
           "skipped": {"kf_nn_grad": f"{BROKE_DOWN}: S lost definiteness",
                       "cusum_kf": f"{BROKE_DOWN}: S lost definiteness",
                       "udp_kf": "needs lost input packets"}}  # fmt: skip
    judged = _judged(doc)
    assert list(judged) == ["kf_nn_grad"] and not any(c.holds for c in judged["kf_nn_grad"])
    text = _acceptance_section(doc).body
    assert "| `kf_nn_grad` |" in text and "**fails** (broke down)" in text
    assert "not among the analytic estimators compared: `cusum_kf`" in text


def test_a_broken_estimator_without_a_threshold_gets_no_tpr_and_the_intervals_agree():
    """From a review: an estimator with no detector was given a TPR of 0 where it broke
    down (and so a worst-case TPR); the robustness intervals left its threat out (the check
    failed at −1 while its interval said 0, holding in every resample)."""
    import torch

    from difffilter.eval.intervals import robustness_intervals
    from difffilter.eval.robustness import _broken_cell, _broken_totals, _worst_cases
    from difffilter.loop import Trajectories

    plain, gated = _broken_cell("why", detects=False), _broken_cell("why", detects=True)
    assert plain["tpr_at_far"] is None and gated["tpr_at_far"] == 0.0
    ran = {"tpr_at_far": 1.0, "state_error_ratio": 1.2, "impact": 0.3, "state_rmse": 0.1}
    worst = _worst_cases({"a": {"ekf": ran, "kf": ran}, "b": {"ekf": plain, "kf": gated}})
    assert worst["ekf"]["tpr_at_far"] == 1.0 and worst["ekf"]["impact"] == 0.3  # no detector
    assert worst["ekf"]["state_error_ratio_broke_down"]
    assert worst["kf"]["tpr_at_far"] == 0.0 and worst["kf"]["impact_broke_down"]

    runs = 6
    flags = torch.zeros(runs, 5, dtype=torch.bool)
    flags[:, 2:] = True
    x = torch.zeros(runs, 5, 1)
    traj = Trajectories(x, x, x, None, None, x, flags, {})
    ok = {"se": torch.ones(runs).double(), "n": torch.full((runs,), 5.0).double(),
          "hits": flags.sum(1).double(),
          "attacked": flags.sum(1).double()}  # fmt: skip
    totals = {"a": {"chi": ok, "net": ok}, "b": {"chi": ok, "net": _broken_totals(traj, True)}}
    out = robustness_intervals(totals, {"chi": "analytic", "net": "learned"}, runs=runs, seed=0)
    assert out["net"]["worst_tpr"]["estimate"] == -1.0  # 0 against 1, as the check
    assert out["net"]["worst_tpr"]["holds_share"] == 0.0
    assert out["net"]["state"]["b"]["holds_share"] == 0.0
    assert out["net"]["state"]["a"]["estimate"] == pytest.approx(1.0)


def test_a_threat_crafted_against_a_broken_detector_is_refused_by_name():
    from difffilter.eval.calibration import Calibration
    from difffilter.eval.stealthy import StealthySpec, craft_threat
    from difffilter.models import registry

    cal = Calibration(0.01, 4, 0, broke_down={"chi_square_ekf": "S lost definiteness"})
    spec = StealthySpec(against="chi_square_ekf", onset=5)
    with pytest.raises(ValueError, match="threat 'st' is crafted against 'chi_square_ekf', "
                                         "which broke down on the calibration runs"):  # fmt: skip
        craft_threat("st", spec, registry.get("four_tank_bias"), cal, seed=0)


def test_the_ekf_names_a_transition_that_gave_nan_not_h():
    """From a review: a NaN predicted mean (f's square root of a negative level) was blamed
    on h's Jacobian, 'e.g. a range measured at the sensor's own position'."""
    model = df.NonlinearGaussianModel(
        lambda x: torch.sqrt(x - 1.0), lambda x: x, torch.eye(1, dtype=torch.float64),
        torch.eye(1, dtype=torch.float64), torch.zeros(1, dtype=torch.float64),
        torch.eye(1, dtype=torch.float64),
    )  # fmt: skip
    with pytest.raises(df.NumericalBreakdown, match="predicted mean at step 1 is NaN or inf: "
                                                    "the transition f"):  # fmt: skip
        df.extended_kalman_filter(model, torch.zeros(1, 2, 1, dtype=torch.float64))


def test_a_family_report_that_reads_a_broken_estimator_is_left_out_with_the_reason(
    at_the_sensor, tmp_path, monkeypatch
):
    """From a review: the four-tank report reran every estimator of its attack-size sweep,
    the one the study had left out too, and its breakdown there stopped the evaluation."""
    from difffilter.eval import report as report_module
    from difffilter.eval.report import FamilyReport

    def sections(result, doc, out, prepared):
        raise AssertionError("not written: it reads an estimator that did not run")

    family = FamilyReport(extra=lambda result: {"mine": 1}, sections=sections,
                          needs=("chi_square_ekf", "chi_square_ukf"))  # fmt: skip
    monkeypatch.setitem(report_module._FAMILIES, "breakdown_tests", family)
    with pytest.warns(UserWarning):
        result = run_suite(at_the_sensor, runs=3, progress=False,
                           estimators=["chi_square_ekf", "chi_square_ukf"])  # fmt: skip
    doc = write_report(tmp_path, result)
    assert "mine" not in doc and doc["family_report_skipped"].startswith(
        "they read estimators that did not run here: `chi_square_ekf` (broke down"
    )
    assert (
        "## The breakdown_tests family's sections\n\nLeft out: they read"
        in (tmp_path / "report.md").read_text()
    )

    def breaks(result):
        raise df.NumericalBreakdown("its own sweep broke down")

    family = FamilyReport(extra=breaks, sections=sections, needs=("chi_square_ukf",))
    monkeypatch.setitem(report_module._FAMILIES, "breakdown_tests", family)
    with pytest.warns(UserWarning, match="family's report broke down"):
        doc = write_report(tmp_path, result)
    assert "its own sweep broke down" in doc["family_report_skipped"]


def test_a_sweep_names_a_learned_checkpoint_that_broke_down(at_the_sensor):
    """From a review: a bare KeyError where the judged estimator broke down."""
    from difffilter.train.sweep import _calibrated_metrics

    with (
        pytest.warns(UserWarning),
        pytest.raises(
            ValueError, match="chi_square_ekf did not run on at_the_sensor: broke down on this"
        ),
    ):
        _calibrated_metrics(at_the_sensor, ["chi_square_ekf"], 3, 0.05, False, required=True)


def test_a_transition_jacobian_not_finite_at_the_estimate_is_named():
    """An ekfukf trial: ``∂f/∂x`` NaN or inf at the estimate (torch.func's Jacobian of
    ``sqrt(|x0|)`` at 0; a closed form returning inf) was reported as a failed ``S`` blaming
    ``Q``, ``R`` and ``P0``; the observation Jacobian's case was named already."""
    from difffilter.ssm import NonlinearGaussianModel

    f64 = dict(dtype=torch.float64)
    Q, R, P0 = 0.01 * torch.eye(2, **f64), 0.1 * torch.eye(1, **f64), torch.eye(2, **f64)
    ys = torch.ones(5, 1, **f64)

    def h(x):
        return x[..., :1] ** 2

    def root(x):
        return torch.stack([torch.sqrt(x[..., 0].abs()), x[..., 1]], -1)

    def shear(x):
        return torch.stack([x[..., 0] + 0.1 * x[..., 1], x[..., 1]], -1)

    def infinite(x):
        return torch.full((*x.shape[:-1], 2, 2), float("inf"), **f64)

    for model in (
        NonlinearGaussianModel(root, h, Q, R, torch.zeros(2, **f64), P0),
        NonlinearGaussianModel(
            shear, h, Q, R, torch.tensor([1.0, 0.0], **f64), P0, transition_jacobian=infinite
        ),  # fmt: skip
    ):
        with pytest.raises(df.NumericalBreakdown, match=r"predicted covariance F P Fᵀ \+ Q at "
                           "step 1 is NaN or inf from a finite P: the transition Jacobian"):  # fmt: skip
            df.extended_kalman_filter(model, ys)
    df.unscented_kalman_filter(NonlinearGaussianModel(root, h, Q, R, torch.zeros(2, **f64), P0), ys)


def test_an_overflowing_ekf_covariance_is_said_to_be_one_of_two_causes():
    """A review: an unstable plant run long without measurements overflows ``P⁻`` with a
    finite ``F``; the message names the overflow beside a non-finite Jacobian."""
    one = torch.ones(1, 1, dtype=torch.float64)
    model = df.LinearGaussianModel(
        2.0 * one, one, one, one, torch.zeros(1, dtype=torch.float64), one
    )
    mask = torch.zeros(1, 530, 1, dtype=torch.bool)
    mask[:, -1] = True  # 4^k overflows near k = 512
    with pytest.raises(df.NumericalBreakdown, match="or the covariance overflowed"):
        df.open_loop(df.ExtendedKalmanFilter(), model, torch.zeros(1, 530, 1, dtype=torch.float64),
                     mask=mask)  # fmt: skip
