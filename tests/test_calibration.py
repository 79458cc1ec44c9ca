"""Every detector at one false-alarm rate: thresholds from attack-free runs of their own
seed meet the target on fresh attack-free runs of every family (issue acceptance: within
[0.5 %, 2 %] at 1 %)."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.eval.calibration import (
    alarms_at,
    calibrate,
    calibrated_metrics,
    calibration_seed,
    threshold_for,
)
from difffilter.eval.suite import run_suite
from difffilter.models import registry


def test_the_threshold_lets_through_at_most_the_target_share_of_scores():
    scores = torch.randperm(1000, generator=torch.Generator().manual_seed(0)).double()
    tau = threshold_for(scores.reshape(10, 100), 0.01)
    assert tau == 989.0 and int((scores > tau).sum()) == 10
    assert threshold_for(torch.full((50,), 3.0), 0.05) == 3.0  # ties never alarm
    nan_first = torch.tensor([math.nan, 1.0, 2.0, 3.0])  # NaN scores rank lowest
    assert threshold_for(nan_first, 0.3) == 2.0
    # infinite scores stay infinite: with 3 of 100 at +inf the threshold at 1 % is +inf (not
    # the largest float, over which the raw scores would alarm 3 % of the time)
    three_inf = torch.cat([torch.full((3,), math.inf), torch.arange(97.0)]).double()
    tau = threshold_for(three_inf, 0.01)
    assert tau == math.inf and float((three_inf > tau).double().mean()) == 0.0
    assert alarms_at(three_inf, tau).sum() == 0
    assert threshold_for(torch.tensor([-math.inf, -math.inf, 1.0]), 0.34) == -math.inf
    for bad in (0.0, 1.0, -0.1, "0.01", float("nan")):  # (a string raised a TypeError)
        with pytest.raises(ValueError, match=r"far must be a false-alarm rate in \(0, 1\)"):
            threshold_for(scores, bad)
    with pytest.raises(TypeError, match=r"scores must be a torch.Tensor \(torch.as_tensor"):
        threshold_for(scores.numpy(), 0.01)  # (it failed on the array's missing .double())
    with pytest.raises(ValueError, match="at least one"):
        threshold_for(torch.zeros(0), 0.01)


def test_calibrated_metrics_read_the_scores_at_the_threshold():
    from difffilter.estimator import Detection, EstimatorOutput
    from difffilter.loop import Trajectories

    scores = torch.tensor([[0.0, 2.0, 5.0, 1.0], [3.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    flags = torch.tensor([[False, True, True, True], [False, False, False, False]])
    x = torch.zeros(2, 4, 1, dtype=torch.float64)
    means = torch.tensor([[0.0, 0.5, 4.0, 9.0], [0.0, 0.0, 0.0, 0.0]]).double().unsqueeze(-1)
    out = EstimatorOutput(means, detection=Detection(scores, scores > 2.5, 2.5))
    traj = Trajectories(x, x, x, None, None, x, flags, {})
    m = calibrated_metrics(out, traj, 1.5)
    assert m["tpr_at_far"] == pytest.approx(2 / 3)  # 2.0 and 5.0 of 2, 5, 1
    assert m["fpr_at_far"] == pytest.approx(1 / 5)  # the 3.0 of run 2
    assert m["impact"] == pytest.approx(0.0)  # run 1 alarms at its first attacked step
    m = calibrated_metrics(out, traj, 6.0)  # never an alarm: the worst error, 9
    assert m["impact"] == pytest.approx(9.0) and m["tpr_at_far"] == 0.0
    assert calibrated_metrics(out, traj, None)["tpr_at_far"] is None


def test_the_false_alarms_an_attack_leaves_behind():
    """fpr_at_far_after_attack reads the attack-free steps 1 … 10 after an attacked step of
    the same run (counted by hand here), not those before an attack, farther after it or in
    an attack-free run; fpr_at_far counts them all."""
    from difffilter.estimator import Detection, EstimatorOutput
    from difffilter.eval.scoring import AFTER_ATTACK_STEPS, METRICS
    from difffilter.loop import Trajectories
    from difffilter.metrics import after_attack

    assert AFTER_ATTACK_STEPS == 10 and "1 to 10 steps after" in METRICS[
        "fpr_at_far_after_attack"].definition  # fmt: skip
    T = 30
    flags = torch.zeros(3, T, dtype=torch.bool)
    flags[0, 5:8] = True  # 8 … 17 are after it, 18 … 29 farther
    flags[1, 2] = flags[1, 6] = True  # 3 … 5 and 7 … 16 after one of them
    want = torch.zeros(3, T, dtype=torch.bool)
    want[0, 8:18] = True
    want[1, 3:6] = want[1, 7:17] = True
    assert torch.equal(after_attack(flags, 10), want)
    scores = torch.zeros(3, T, dtype=torch.float64)
    scores[0, 8:11] = scores[0, 20] = scores[1, 16] = scores[1, 17] = scores[2, 9] = 1.0
    scores[0, 0] = 1.0  # before the attack: a false alarm, not one it left behind
    x = torch.zeros(3, T, 1, dtype=torch.float64)
    out = EstimatorOutput(x.clone(), detection=Detection(scores, scores > 0.5, 0.5))
    m = calibrated_metrics(out, Trajectories(x, x, x, None, None, x, flags, {}), 0.5)
    assert m["fpr_at_far_after_attack"] == pytest.approx(4 / 23)  # 8, 9, 10 and 16 of 23
    assert m["fpr_at_far"] == pytest.approx(8 / (3 * T - 5))  # with 0, 20, 17 and run 3
    no_attack = Trajectories(x, x, x, None, None, x, torch.zeros_like(flags), {})
    assert calibrated_metrics(out, no_attack, 0.5)["fpr_at_far_after_attack"] is None


CASES = {  # scenario, Monte Carlo runs, horizon (None: the scenario's), detectors
    "four_tank_bias": (100, None, None),
    "lfc_step": (20, 400, ("chi_square_kf", "cusum_kf", "kf_nn_grad", "traditional_ad")),
    "robot_actuator_attack": (60, None, ("zhang_akf", "mdpf_fused_ci", "gaussian_nn_ekf")),
    "tracking_rrp_deception": (40, None, ("rrp_pf_da", "ukf_chi_square", "pf_nn_grad")),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_every_detector_meets_the_target_false_alarm_rate_on_fresh_attack_free_runs(name):
    runs, steps, estimators = CASES[name]
    scenario = registry.get(name)
    scenario = scenario if steps is None else scenario.with_steps(steps)
    cal = calibrate(scenario, far=0.01, runs=runs, seed=0, estimators=estimators, progress=False)
    assert cal.seed == calibration_seed(0) != 0
    fresh = run_suite(scenario.with_threat(None), runs=runs, seed=7, estimators=estimators,
                      progress=False, calibration=cal)  # fmt: skip
    rates = {n: m["fpr_at_far"] for n, m in fresh.metrics.items() if n in cal.thresholds}
    assert rates, f"{name}: no detector was calibrated"
    for detector, rate in rates.items():
        assert 0.005 <= rate <= 0.02, f"{name}/{detector}: false-alarm rate {rate:.4f} at 1 %"


def test_two_suites_of_one_scenario_calibrate_cusum_once(monkeypatch, tmp_path):
    from difffilter import fdi
    from difffilter.eval.suite import run_suite
    from difffilter.models import estimators, registry

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    estimators._CUSUM_CACHE.clear()
    calls = []
    real = fdi.cusum_detector_for
    monkeypatch.setattr(fdi, "cusum_detector_for", lambda *a, **k: calls.append(1) or real(*a, **k))
    scenario = registry.get("four_tank_bias")
    first = run_suite(scenario, runs=2, estimators=["cusum_ekf"], progress=False)
    second = run_suite(scenario, runs=2, estimators=["cusum_ekf"], progress=False)
    assert len(calls) == 1
    assert first.metrics["cusum_ekf"]["auc"] == second.metrics["cusum_ekf"]["auc"]
    run_suite(scenario, runs=2, seed=1, estimators=["cusum_ekf"], progress=False)
    assert len(calls) == 2  # another seed: other calibration runs
    # a later process (the memory cache empty) reads both from the cache folder
    estimators._CUSUM_CACHE.clear()
    third = run_suite(scenario, runs=2, estimators=["cusum_ekf"], progress=False)
    assert len(calls) == 2 and len(list((tmp_path / "calibrations").glob("cusum-*.json"))) == 2
    assert third.metrics["cusum_ekf"] == {**first.metrics["cusum_ekf"],
                                          "time_per_step_s": third.metrics["cusum_ekf"]["time_per_step_s"]}  # fmt: skip


def test_the_calibration_cache_tells_plants_apart(tmp_path, monkeypatch):
    from conftest import constant_velocity

    from difffilter.models.calibration_cache import cached, model_fingerprint

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    a, b = constant_velocity(q=0.1), constant_velocity(q=0.2)
    assert model_fingerprint(a) == model_fingerprint(constant_velocity(q=0.1))
    assert model_fingerprint(a) != model_fingerprint(b)
    # as the CUSUM cache passes it: the plant inside a tuple (its noise once too deep to hash)
    assert model_fingerprint((a, None, None)) != model_fingerprint((b, None, None))

    def f(x, dt=0.1):
        return x + dt

    def g(x, dt=0.2):
        return x + dt

    assert model_fingerprint(f) != model_fingerprint(g)  # a default argument changed

    def f_kw(x, *, dt=0.1):
        return x + dt

    def g_kw(x, *, dt=0.2):
        return x + dt

    assert model_fingerprint(f_kw) != model_fingerprint(g_kw)  # a keyword-only one (a review)
    assert cached("t", (1,), a, lambda: {"v": 1.0}) == {"v": 1.0}
    assert cached("t", (1,), a, lambda: {"v": 2.0}) == {"v": 1.0}  # read back
    assert cached("t", (1,), b, lambda: {"v": 3.0}) == {"v": 3.0}  # another plant
    monkeypatch.setenv("DIFFFILTER_CACHE", "off")
    assert cached("t", (1,), a, lambda: {"v": 4.0}) == {"v": 4.0}


def test_the_fingerprint_sees_the_constants_and_helpers_a_plant_reads(tmp_path, monkeypatch):
    """A user trial edited a plant's module-level constant (G = 9.81 → 2.0) and the body of
    a helper its transition calls: the fingerprint did not change, and the edited plant
    read the original's cached CUSUM threshold. (torch.sin → torch.cos, the same bytecode
    with another name, did not change it either.)"""
    import importlib

    from difffilter.models.calibration_cache import model_fingerprint

    source = (
        "import torch\nG = {g}\n\ndef _rate(x):\n    return {rate}\n\n"
        "def f(x):\n    return x + 0.1 * _rate(x)\n"
    )
    variants = {"plant_a": ("9.81", "-G * torch.sin(x)"), "plant_b": ("9.81", "-G * torch.sin(x)"),
                "plant_g": ("2.0", "-G * torch.sin(x)"), "plant_h": ("9.81", "-G * torch.cos(x)"),
                # a constant in numpy, read as a module-level array
                "plant_n": ("__import__('numpy').array([9.81])", "-float(G[0]) * torch.sin(x)"),
                "plant_m": ("__import__('numpy').array([2.0])", "-float(G[0]) * torch.sin(x)")}  # fmt: skip
    for name, (g, rate) in variants.items():
        (tmp_path / f"{name}.py").write_text(source.format(g=g, rate=rate))
    monkeypatch.syspath_prepend(str(tmp_path))
    prints = {n: model_fingerprint(importlib.import_module(n).f) for n in variants}
    assert prints["plant_a"] == prints["plant_b"]  # the same plant in another module
    assert len({prints["plant_a"], prints["plant_g"], prints["plant_h"]}) == 3
    assert prints["plant_n"] != prints["plant_m"]  # a numpy constant by its values


def test_the_fingerprint_sees_the_methods_of_a_plant_subclass(tmp_path, monkeypatch):
    """A user trial edited ``observe`` of a ``StateSpaceModel`` subclass (``h = x³`` →
    ``4x³``): the fingerprint hashed the class by its name, and the edited plant read the
    original's CUSUM threshold (708 against 3366). The same class in another module gives
    the same fingerprint; an edited method, default or inherited method another one."""
    import importlib

    from difffilter.models.calibration_cache import model_fingerprint

    source = (
        "import torch\nfrom difffilter.ssm import LinearGaussianModel\n\n"
        "class Base(LinearGaussianModel):\n    def transition(self, x, u, k):\n"
        "        return {f}\n\n"
        "class Plant(Base):\n    def observe(self, x, k, scale={scale}):\n"
        "        return scale * x ** 3\n\n"
        "def make():\n    eye = torch.eye(1, dtype=torch.float64)\n"
        "    return Plant(0.9 * eye, eye, 0.1 * eye, eye, torch.zeros(1, dtype=torch.float64), eye)\n"
    )
    variants = {"sub_a": ("0.9 * x", "1.0"), "sub_b": ("0.9 * x", "1.0"),
                "sub_scale": ("0.9 * x", "4.0"), "sub_base": ("0.8 * x", "1.0"),
                # a default that is a function: by its code, not its repr's address (a review)
                "sub_fn": ("0.9 * x", "lambda: 1.0")}  # fmt: skip
    for name, (f, scale) in variants.items():
        (tmp_path / f"{name}.py").write_text(source.format(f=f, scale=scale))
    monkeypatch.syspath_prepend(str(tmp_path))
    prints = {n: model_fingerprint(importlib.import_module(n).make()) for n in variants}
    assert prints["sub_a"] == prints["sub_b"]
    assert len({prints["sub_a"], prints["sub_scale"], prints["sub_base"], prints["sub_fn"]}) == 4


def test_a_fingerprint_is_the_same_in_every_process(tmp_path):
    """A nested function's code object has an address in its repr: hashed by content, the
    fingerprint (and so the cache file) is the same in a later process."""
    import subprocess
    import sys

    (tmp_path / "fp_plant.py").write_text(
        "def make(scale=2.0):\n    def f(x):\n        return scale * x\n    return f\n"
    )
    code = ("import fp_plant; from difffilter.models.calibration_cache import model_fingerprint;"
            " print(model_fingerprint(fp_plant.make()))")  # fmt: skip
    runs = [subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                           text=True, check=True).stdout for _ in range(2)]  # fmt: skip
    assert runs[0] == runs[1] and len(runs[0].strip()) == 64


def test_a_study_calibrated_afterwards_on_its_detectors_reads_the_same_thresholds(monkeypatch):
    """``difffilter-eval`` runs the study first and then calibrates only the estimators that
    detect: the thresholds and calibrated metrics equal those of calibrating every
    estimator beforehand, and a study without a detector runs no calibration at all."""
    from difffilter.eval import suite as suite_module
    from difffilter.eval.suite import apply_calibration, detectors

    scenario = registry.get("four_tank_bias").with_steps(60)
    names = ["open_loop_pf", "chi_square_ekf", "cusum_ekf"]  # the first detects nothing
    before = calibrate(scenario, runs=8, estimators=names, progress=False)
    study = run_suite(scenario, runs=8, estimators=names, progress=False, calibration=before)
    after = run_suite(scenario, runs=8, estimators=names, progress=False)
    assert detectors(after) == ["chi_square_ekf", "cusum_ekf"]
    apply_calibration(after, calibrate(scenario, runs=8, estimators=detectors(after),
                                       progress=False))  # fmt: skip
    assert after.calibration.thresholds == before.thresholds
    for name in names:
        for key in ("threshold_at_far", "tpr_at_far", "fpr_at_far", "impact"):
            assert after.metrics[name][key] == study.metrics[name][key], (name, key)

    def no_suite(*args, **kwargs):
        raise AssertionError("a calibration without detectors ran a suite")

    monkeypatch.setattr(suite_module, "run_suite", no_suite)
    empty = calibrate(scenario, runs=8, estimators=[], progress=False)
    assert empty.thresholds == {} and empty.runs == 8 and empty.seed == calibration_seed(0)


def test_calibrate_and_run_suite_name_a_string_of_estimators_and_a_bad_rate():
    """A user trial: estimators="chi_square_ekf" failed as "unknown estimator 'c'", and
    far="abc" as "could not convert string to float"."""
    from difffilter.eval.calibration import calibrate
    from difffilter.eval.suite import run_suite
    from difffilter.models import registry

    sc = registry.get("four_tank_bias")
    with pytest.raises(
        ValueError,
        match=r"estimators must be a list of estimator names \(e.g. \['chi_square_ekf'\]\)",
    ):
        calibrate(sc, estimators="chi_square_ekf", runs=2, progress=False)
    with pytest.raises(ValueError, match="add must be a list of estimator names"):
        run_suite(sc, runs=2, add="cusum_ekf", progress=False)
    for far in ("abc", 0.0, 1.5, None):
        with pytest.raises(ValueError, match="far must be a false-alarm rate in"):
            calibrate(sc, far=far, runs=2, progress=False)
    with pytest.raises(ValueError, match=r"far must be a false-alarm rate in \(0, 1\); got None"):
        calibrate(sc, far=None, runs=2, progress=False)  # not "… or None; got None"


def test_run_suite_takes_an_empty_list_as_nothing_and_a_calibration_object_only():
    """A user trial: ``run_suite(estimators=[])`` ran the scenario's whole suite (and
    ``calibrate(estimators=[], add=[x])`` calibrated it all, not x), and ``calibration=0.01``
    failed after the study on an AttributeError."""
    from difffilter.eval.calibration import calibrate
    from difffilter.eval.suite import run_suite
    from difffilter.models import registry

    sc = registry.get("four_tank_bias")
    with pytest.raises(ValueError, match="estimators is empty and nothing is added: nothing to"):
        run_suite(sc, runs=2, estimators=[], progress=False)
    only = run_suite(sc, runs=2, estimators=[], add=["chi_square_ekf"], progress=False)
    assert list(only.outputs) == ["chi_square_ekf"]
    cal = calibrate(sc, runs=2, estimators=[], add=["chi_square_ekf"], progress=False)
    assert list(cal.thresholds) == ["chi_square_ekf"]
    with pytest.raises(ValueError, match=r"calibration must be None or the Calibration "
                       r"calibrate\(scenario, far=…\) returns .*got float 0.01"):  # fmt: skip
        run_suite(sc, runs=2, estimators=["chi_square_ekf"], calibration=0.01, progress=False)
    # a docs trial: float16 met torch's "cholesky_cpu" not implemented for 'Half'
    with pytest.raises(
        ValueError,
        match=r"dtype must be torch.float32 or torch.float64; got "
        r"torch.float16",
    ):
        run_suite(sc, runs=2, estimators=["chi_square_ekf"], dtype=torch.float16, progress=False)


def test_the_calibrations_progress_bar_says_it_is_the_calibration(capsys):
    """A user trial: the calibration's bar and the study's both read "four_tank_bias: n/12",
    and the calibration can take as long as the study."""
    from difffilter.eval.calibration import calibrate
    from difffilter.eval.suite import run_suite
    from difffilter.models import registry

    sc = registry.get("four_tank_bias")
    calibrate(sc, runs=2, estimators=["chi_square_ekf"], progress=True)
    assert "four_tank_bias: calibrating at 0.01 (attack-free runs)" in capsys.readouterr().err
    run_suite(sc, runs=2, estimators=["chi_square_ekf"], progress=True)
    err = capsys.readouterr().err
    assert "four_tank_bias" in err and "calibrating" not in err


def _pendulum(dtype):
    import difffilter as df

    def step(x):  # a damped pendulum, Euler steps of 0.05 s
        return torch.stack([x[..., 0] + 0.05 * x[..., 1],
                            x[..., 1] - 0.05 * (9.81 * torch.sin(x[..., 0]) + 0.3 * x[..., 1])],
                           -1)  # fmt: skip

    def observe(x):
        return torch.stack([torch.sin(x[..., 0]), x[..., 1]], -1)

    return df.NonlinearGaussianModel(
        step, observe, torch.diag(torch.tensor([1e-5, 1e-3], dtype=dtype)),
        torch.diag(torch.tensor([1e-3, 1e-2], dtype=dtype)),
        torch.tensor([0.8, 0.0], dtype=dtype), 1e-2 * torch.eye(2, dtype=dtype),
    )  # fmt: skip


def test_a_detector_whose_scores_tie_at_the_threshold_is_named_below_the_target(monkeypatch):
    """A user trial's pendulum: the particle filters' PoA β is 1 (every particle beyond η)
    on 2-3 % of attack-free steps, so τ = 1 at 1 % and no step alarms; the detection rate
    that was reported came from β = 1 + 4e-16 (round-off). The calibration names such
    detectors, with the share tied at τ, and the report says so."""
    from difffilter.eval.calibration import below_target_note
    from difffilter.models.scenario import CustomScenario
    from difffilter.threats import Ramp

    monkeypatch.setenv("DIFFFILTER_CACHE", "off")
    scenario = CustomScenario(name="pendulum_ties", family="pendulum_ties", description="d",
                              model_fn=_pendulum, attack=Ramp(slope=0.005, entries=(0,), onset=40),
                              runs=8, steps=120, num_particles=200)  # fmt: skip
    # said from Python too (a teaching trial read its "0.0" as "detects nothing")
    with pytest.warns(UserWarning, match=r"Below the 1 % target.*`normal_pf` alarms on 0\.00 %"):
        cal = calibrate(scenario, estimators=["normal_pf", "chi_square_ekf"], progress=False)
    assert cal.thresholds["normal_pf"] == 1.0 and cal.measured["normal_pf"] == 0.0
    assert 0.01 < cal.tied["normal_pf"] < 0.1 and "chi_square_ekf" not in cal.tied
    below = cal.summary()["below_target"]
    assert set(below) == {"normal_pf"} and below["normal_pf"]["threshold"] == 1.0
    note = below_target_note(cal.summary())
    assert "`normal_pf` alarms on 0.00 %" in note and "no threshold meets the rate" in note
    study = run_suite(scenario, runs=8, seed=3, estimators=["normal_pf"], progress=False)
    assert float(study.outputs["normal_pf"].detection.scores.max()) <= 1.0  # never 1 + ε
    assert "below_target" not in calibrate(
        registry.get("four_tank_bias").with_steps(40), runs=4, estimators=["chi_square_ekf"],
        progress=False).summary()  # fmt: skip


def test_the_note_names_why_a_rate_fell_short_and_when_the_calibration_is_coarse():
    """An auditor's trial: "their scores are discrete and tie there" was said of continuous
    χ² and CUSUM scores calibrated at 0.1 % on 500 steps (not one step may alarm), and of a
    detector with no score at all; a calibration on 2,000 steps at 0.1 % (two expected
    alarms) said nothing, though its thresholds met 0.15 % on average on fresh runs."""
    from difffilter.eval.calibration import RESOLVED, Calibration, below_target_note

    cal = Calibration(0.001, 5, 0, thresholds={"chi": 9.0, "pf": 1.0, "nan": -math.inf},
                      measured={"chi": 0.0, "pf": 0.0, "nan": 0.0},
                      tied={"chi": 0.002, "pf": 0.3, "nan": 0.0},
                      steps={"chi": 500, "pf": 5000, "nan": 0})  # fmt: skip
    below = cal.summary()["below_target"]
    assert {n: b["cause"] for n, b in below.items()} == {
        "chi": "too few steps", "pf": "ties", "nan": "no score"}  # fmt: skip
    note = below_target_note(cal.summary())
    assert "`chi` alarms on 0.00 %" in note and "α n < 1" in note
    assert "`pf` alarms on 0.00 %" in note and "tie there" in note and "every score NaN" in note
    coarse = Calibration(0.001, 20, 0, thresholds={"chi": 9.0}, measured={"chi": 0.001},
                         steps={"chi": 2000})  # fmt: skip
    assert coarse.summary()["unresolved"] == {"chi": 2000} and 0.001 * 2000 < RESOLVED
    note = below_target_note(coarse.summary())
    assert "2,000 steps: 2 alarms expected" in note and "about 0.15 %" in note
    fine = Calibration(0.01, 100, 0, thresholds={"chi": 9.0}, measured={"chi": 0.01},
                       steps={"chi": 10_000})  # fmt: skip
    assert "unresolved" not in fine.summary() and below_target_note(fine.summary()) is None
    # an older metrics.json's entry has no cause: read as ties
    old = {"target": 0.01, "below_target": {"pf": {"measured_on_calibration": 0.0,
                                                  "threshold": 1.0, "tied_at_threshold": 0.1}}}  # fmt: skip
    assert "tie there" in below_target_note(old)


def test_the_delay_at_the_calibrated_threshold_reads_those_alarms_not_the_estimators():
    """An estimator alarming at every step has its own delay 0; at the common threshold
    its delay is that of its scores (a plug-in author's trial: the leaderboard's delay was
    the estimator's own)."""
    from difffilter.estimator import Detection, EstimatorOutput
    from difffilter.loop import Trajectories

    scores = torch.tensor([[0.0, 1.0, 1.0, 4.0, 0.0, 3.0], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]],
                          dtype=torch.float64)  # fmt: skip
    flags = torch.tensor([[False, True, True, True, False, True], [False, True, True, False,
                                                                  False, False]])  # fmt: skip
    x = torch.zeros(2, 6, 1, dtype=torch.float64)
    out = EstimatorOutput(x, detection=Detection(scores, torch.ones_like(flags), -math.inf))
    traj = Trajectories(x, x, x, None, None, x, flags, {})
    # episodes: run 1 steps 1-3 (first score > 2 at step 3: delay 2) and step 5 (delay 0);
    # run 2 steps 1-2 never above 2 (missed): mean (2 + 0) / 2 = 1
    m = calibrated_metrics(out, traj, 2.0, dt=0.5)
    assert (m["detection_delay_at_far_steps"], m["detection_delay_at_far_s"]) == (1.0, 0.5)
    assert calibrated_metrics(out, traj, 10.0, dt=0.5)["detection_delay_at_far_s"] is None


def test_a_below_target_note_takes_an_infinite_threshold():
    """+inf scores on 40 % of the calibration steps made the threshold +inf, null in
    metrics.json, and the report writer raised formatting it."""
    from difffilter.eval.calibration import below_target_note

    far = {"target": 0.01, "below_target": {"mine": {
        "measured_on_calibration": 0.0, "threshold": None, "tied_at_threshold": 0.4,
        "cause": "ties"}}}  # fmt: skip
    assert "±∞" in below_target_note(far)


def test_the_threshold_is_picked_on_the_scores_of_the_detector_judged(tmp_path, monkeypatch):
    """From a threat-model trial: the calibration's suite built its CUSUM from the
    calibration seed's attack-free runs, another τ than the study's CUSUM (23.58 against
    26.52), and picked the threshold on that detector's scores (where scores pass τ, its
    resets and gating differ: here a Kalman filter overconfident under unacknowledged input
    loss). It runs the study's detector now: the same τ, and the threshold the study
    detector's scores on the calibration runs give."""
    from difffilter.eval.calibration import _finite_scores
    from difffilter.models.yaml_scenario import scenario_from_dict

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    sc = scenario_from_dict({
        "name": "motor_udp", "runs": 50, "steps": 100, "dt": 0.1,
        "plant": {"F": [[0.9, 0.1], [0.0, 0.85]], "B": [[0.0], [0.5]],
                  "H": [[1.0, 0.0], [0.0, 1.0]], "Q": 1.0e-2, "R": 4.0e-2, "P0": 0.1},
        "inputs": {"kind": "sinusoid", "amplitude": 1.0, "frequency": 0.5},
        "input_loss": {"kind": "packet_loss", "rate": 0.3, "on_loss": "zero",
                       "acknowledged": False},
        "estimators": ["cusum_kf"],
    }, "motor.yaml")  # fmt: skip
    study = run_suite(sc, estimators=["cusum_kf"], progress=False)
    judged = run_suite(sc.with_threat(None), seed=calibration_seed(0), detector_seed=0,
                       estimators=["cusum_kf"], progress=False)  # fmt: skip
    own = run_suite(sc.with_threat(None), seed=calibration_seed(0), estimators=["cusum_kf"],
                    progress=False)  # fmt: skip
    tau = [r.outputs["cusum_kf"].detection.threshold for r in (study, judged, own)]
    assert tau[0] == tau[1] != tau[2]
    cal = calibrate(sc, estimators=["cusum_kf"], progress=False)
    picked = [threshold_for(_finite_scores(r.outputs["cusum_kf"].detection.scores), 0.01)
              for r in (judged, own)]  # fmt: skip
    assert picked[0] != picked[1] and cal.thresholds["cusum_kf"] == picked[0]


def test_a_calibration_of_other_runs_judges_the_studys_cusum(tmp_path, monkeypatch):
    """A review: with --calibration-runs other than --runs the calibration's CUSUM took its
    own τ from max(calibration runs, 50) attack-free runs (11.37 against the study's 11.57
    at 120 and 60 runs); it follows the study's runs now."""
    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    sc = registry.get("four_tank_bias").with_steps(30)
    study = run_suite(sc, runs=60, estimators=["cusum_ekf"], progress=False)
    judged = run_suite(sc.with_threat(None), runs=120, seed=calibration_seed(0),
                       detector_seed=0, detector_runs=60, estimators=["cusum_ekf"],
                       progress=False)  # fmt: skip
    other = run_suite(sc.with_threat(None), runs=120, seed=calibration_seed(0),
                      detector_seed=0, estimators=["cusum_ekf"], progress=False)  # fmt: skip
    tau = [r.outputs["cusum_ekf"].detection.threshold for r in (study, judged, other)]
    assert tau[0] == tau[1] != tau[2]
    from difffilter.eval.calibration import _finite_scores

    cal = calibrate(sc, runs=120, study_runs=60, estimators=["cusum_ekf"], progress=False)
    scores = _finite_scores(judged.outputs["cusum_ekf"].detection.scores)
    assert cal.thresholds["cusum_ekf"] == threshold_for(scores, 0.01)


def test_a_detector_that_spends_its_rate_at_start_up_is_named():
    """A threat-set trial: the four-tank particle filters' probability of attack is above 0
    at step 1 of every attack-free run and 0 almost everywhere after, so at 1 % (T = 100)
    their threshold is 0 and every calibration alarm is at step 1: "1 % false alarms" while
    the rate from step 2 on is 0, said nowhere. The calibration names them, with both
    shares counted here on scores made by hand, and the report's note says it."""
    from difffilter.eval.calibration import Calibration, _startup, below_target_note

    scores = torch.zeros(10, 100)
    scores[:, 0] = 0.3  # every run's first step
    scores[3, 50] = 0.2  # one later alarm: 10 of 11 alarms at step 1
    chi = torch.rand(10, 100, generator=torch.Generator().manual_seed(0))
    got = _startup(scores, 0.0)
    assert got == {"alarms_at_first_step": pytest.approx(10 / 11),
                   "rate_after_first_step": pytest.approx(1 / 990)}  # fmt: skip
    assert _startup(chi, float(threshold_for(chi, 0.01))) is None  # spread over the run
    assert _startup(scores, 1.0) is None  # no alarm at all
    assert _startup(scores[:, :1], 0.0) is None  # one step: no "after"
    cal = Calibration(0.01, 10, 0, thresholds={"pf": 0.0}, measured={"pf": 11 / 1000},
                      steps={"pf": 1000}, startup={"pf": got})  # fmt: skip
    assert cal.summary()["startup"] == {"pf": got}
    note = below_target_note(cal.summary())
    assert "`pf`: 91 % of the alarms at step 1, 0.10 % of the steps from step 2 on" in note
    two = Calibration(0.01, 10, 0, startup={"a": got, "b": got}).summary()
    assert "`a`, `b`: 91 % of the alarms at step 1" in below_target_note(two)
    assert "start-up" in note
    # a study's calibration: the four-tank particle filter's alarms all at step 1, χ²'s not
    cal = calibrate(registry.get("four_tank_bias").with_steps(40), runs=6,
                    estimators=["normal_pf", "chi_square_ekf"], far=0.05, progress=False)  # fmt: skip
    assert set(cal.startup) == {"normal_pf"}
    assert cal.startup["normal_pf"]["alarms_at_first_step"] == 1.0
    assert cal.startup["normal_pf"]["rate_after_first_step"] == 0.0
    # 1 step in 40 alarms: exactly half the 5 % target, below it (the trial's 1.00 % at 2 %)
    assert cal.measured["normal_pf"] == 0.025 and set(cal.tied) == {"normal_pf"}


def test_a_threshold_at_the_lowest_score_is_named():
    """An LFC trial: on 4 calibration runs the learned head's threshold was 0, its lowest
    score, so it alarmed wherever its score was above 0 at all (exactly its χ²
    confirmation's alarms), and nothing said so: the calibration names such a detector."""
    from difffilter.eval.calibration import Calibration, _at_floor, below_target_note

    head = torch.zeros(1000, dtype=torch.float64)
    head[:9] = 0.4  # 0.9 % of the steps above the floor
    assert _at_floor(head, float(threshold_for(head, 0.01))) == pytest.approx(0.991)
    chi = torch.rand(1000, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    assert _at_floor(chi, float(threshold_for(chi, 0.01))) is None
    nan_first = torch.cat([torch.full((5,), -math.inf, dtype=torch.float64), head])
    assert _at_floor(nan_first, 0.0) == pytest.approx(991 / 1005)  # (NaN: no score, −∞)
    summary = Calibration(0.01, 4, 0, thresholds={"kf_nn_grad": 0.0}, measured={"kf_nn_grad": 0.009},
                          at_floor={"kf_nn_grad": 0.991}).summary()  # fmt: skip
    assert summary["at_floor"] == {"kf_nn_grad": 0.991}
    note = below_target_note(summary)
    assert "At their lowest score: `kf_nn_grad` (99 % of its scores there)" in note


def test_alarms_held_by_a_few_runs_are_named_with_what_they_are_worth():
    """A calibration trial: the LFC online learners' alarms fall in a few runs (the top 5
    of 20 held 69–77 %), so a 20-run calibration met 0.13–0.36 % on fresh runs while its
    step count (200 alarms expected) read as resolved. Their dispersion over runs, by hand;
    independent alarms are not listed (a review: the participation ratio of before listed a
    third of independent χ² calibrations); the summary and the note name them."""
    import jsonschema

    from difffilter.eval.calibration import Calibration, alarm_clustering, below_target_note
    from difffilter.eval.report import metrics_schema

    scores = torch.zeros(20, 100, dtype=torch.float64)
    scores[0, :15] = scores[1, :5] = 1.0  # 20 alarms at τ = 0.5, in two runs
    counts = torch.tensor([15.0, 5.0] + [0.0] * 18)
    dispersion = float(((counts - 1.0) ** 2).sum() / 19)  # variance / mean, mean 1
    got = alarm_clustering(scores, 0.5)
    assert got == {"alarms": 20, "effective_alarms": pytest.approx(20 / dispersion)}
    assert 20 / dispersion == pytest.approx(380 / 230)  # 14² + 4² + 18 · 1² = 230 over 19
    nan = scores.clone()
    nan[0, :5] = math.nan  # a NaN score never alarms: 10 and 5
    assert alarm_clustering(nan, 0.5)["alarms"] == 15
    assert alarm_clustering(scores, 2.0) is None and alarm_clustering(scores[:1], 0.5) is None
    spread = torch.zeros(20, 100, dtype=torch.float64)
    spread[:, :1] = 1.0  # one alarm in every run: no dispersion at all
    assert alarm_clustering(spread, 0.5) is None
    g = torch.Generator().manual_seed(0)
    listed = 0
    for _ in range(200):  # independent χ² alarms: 100 runs × 100 steps at 0.1 %, N ≈ 10, where
        # N / D < 10 by chance in about a third of the draws: the dispersion test must keep
        # them off (a review: at 1 % the N / D bar alone kept every draw off)
        chi = torch.randn(100, 100, generator=g, dtype=torch.float64) ** 2
        listed += alarm_clustering(chi, float(threshold_for(chi.flatten(), 0.001))) is not None
    assert listed <= 4  # 5 in 1,000 measured
    entry = {"alarms": 200, "effective_alarms": 2.86}
    summary = Calibration(0.01, 20, 0, thresholds={"kf_nn_ekf": 0.3}, measured={"kf_nn_ekf": 0.01},
                          concentrated={"kf_nn_ekf": entry}).summary()  # fmt: skip
    assert summary["concentrated"] == {"kf_nn_ekf": entry}
    far_schema = metrics_schema()["properties"]["far"]
    jsonschema.validate(summary, far_schema)
    with pytest.raises(jsonschema.ValidationError):  # (the number of before is refused)
        jsonschema.validate({**summary, "concentrated": {"kf_nn_ekf": 2.86}}, far_schema)
    note = below_target_note(summary)
    assert "Alarms in few runs" in note
    assert "a few of the 20 runs (`kf_nn_ekf` 200 alarms worth 2.9 independent ones)" in note
    plain = Calibration(0.01, 20, 0, thresholds={"chi": 9.0}, measured={"chi": 0.01}).summary()
    assert "concentrated" not in plain and below_target_note(plain) is None


def test_a_calibration_of_another_scenario_or_horizon_warns_and_a_named_estimator_without_threshold_too():
    """A calibration trial: thresholds of 100 steps judged runs of 50 (2.0 % false alarms)
    or 300 (0.34 %), or another plant's, without a word; ``estimators=["zhang_akf"]`` on
    the four-tank plant (another family's) or ``["open_loop_pf"]`` (no detection score)
    gave an empty calibration silently; ``study_runs=0`` was taken as the default."""
    import warnings

    from difffilter.eval.suite import apply_calibration

    scenario = registry.get("four_tank_bias").with_steps(30)
    cal = calibrate(scenario, runs=4, estimators=["chi_square_ekf"], progress=False)
    assert cal.scenario == scenario.attack_free_key()
    with warnings.catch_warnings():  # the scenario calibrated, under any threat: silent
        warnings.simplefilter("error")
        run_suite(scenario.with_threat(None), runs=2, estimators=["chi_square_ekf"],
                  progress=False, calibration=cal)  # fmt: skip
        ok = run_suite(scenario, runs=2, estimators=["chi_square_ekf"], progress=False)
        apply_calibration(ok, cal)
    other = scenario.with_steps(20)
    with pytest.warns(UserWarning, match="made on 'four_tank_bias' over 30 steps, the study "
                      "runs 'four_tank_bias' over 20 steps"):  # fmt: skip
        judged = run_suite(other, runs=2, estimators=["chi_square_ekf"], progress=False,
                           calibration=cal)  # fmt: skip
    assert judged.metrics["chi_square_ekf"]["threshold_at_far"] == cal.thresholds["chi_square_ekf"]
    late = run_suite(other, runs=2, estimators=["chi_square_ekf"], progress=False)
    with pytest.warns(UserWarning, match="calibration was made on 'four_tank_bias' over 30"):
        apply_calibration(late, cal)
    with pytest.warns(UserWarning, match="no threshold for 'zhang_akf': "):
        assert (
            calibrate(scenario, runs=2, estimators=["zhang_akf"], progress=False).thresholds == {}
        )
    with pytest.warns(
        UserWarning, match="no threshold for 'open_loop_pf': it reports no detection"
    ):
        calibrate(scenario, runs=2, estimators=["open_loop_pf"], progress=False)
    with warnings.catch_warnings():  # a study's own list, detectors among the rest: silent
        warnings.simplefilter("error")
        calibrate(scenario, runs=4, estimators=["open_loop_pf", "chi_square_ekf"], far=0.05,
                  progress=False)  # fmt: skip
        # another family's --add-estimators entry: the CLI notes it once (a review: every
        # scenario of a robustness study warned again)
        calibrate(scenario, runs=4, estimators=["chi_square_ekf"], add=("zhang_akf",), far=0.05,
                  progress=False)  # fmt: skip
    for bad in (0, -5, 2.5, True):
        with pytest.raises(
            ValueError, match=r"study_runs must be a positive integer \(>= 1\); got "
        ):
            calibrate(scenario, runs=2, estimators=["chi_square_ekf"], study_runs=bad,
                      progress=False)  # fmt: skip


def _fake_suite(monkeypatch, scores):
    """``run_suite`` replaced by one whose estimator ``d`` scores ``scores [runs, steps]``."""
    from types import SimpleNamespace

    import difffilter.eval.suite as suite

    def run(*args, **kwargs):
        return SimpleNamespace(outputs={"d": SimpleNamespace(detection=SimpleNamespace(
            scores=scores))}, skipped={})  # fmt: skip

    monkeypatch.setattr(suite, "run_suite", run)


def test_calibrate_lists_alarms_held_by_a_few_runs_once(monkeypatch):
    """End to end through :func:`calibrate` (a mutation review: the clustering test and the
    summary were tested alone, and a calibration that never filled ``concentrated`` passed):
    200 alarms held by 2 of 20 runs are listed with what they are worth; 8 alarms in one
    run at α n = 8 are listed under ``unresolved`` alone, not twice."""
    import warnings

    monkeypatch.setenv("DIFFFILTER_CACHE", "off")
    g = torch.Generator().manual_seed(0)
    scores = torch.rand(20, 100, generator=g, dtype=torch.float64) * 1e-3
    scores[:2] += 1.0  # every step of runs 0 and 1 above every other run's
    _fake_suite(monkeypatch, scores)
    scenario = registry.get("four_tank_bias").with_steps(100)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate(scenario, runs=20, far=0.1, estimators=["d"], progress=False)
    held = cal.concentrated["d"]
    assert set(cal.concentrated) == {"d"} and held["alarms"] == 200
    assert 1.5 < held["effective_alarms"] < 3  # D = 90 alarms a run's variance over its mean
    few = torch.rand(40, 10, generator=g, dtype=torch.float64) * 1e-3
    few[0, :8] = 1.0  # 8 of 400 steps at 2 %, all in run 0: α n = 8, unresolved
    _fake_suite(monkeypatch, few)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate(scenario.with_steps(10), runs=40, far=0.02, estimators=["d"],
                        progress=False)  # fmt: skip
    assert cal.concentrated == {} and "d" in cal.summary()["unresolved"]


def test_a_calibration_of_another_plant_of_the_same_horizon_is_named_and_nothing_is_kept_bare():
    """A mutation review: the mismatch had been tested on another horizon of one plant
    only (a check of the horizon alone passed); an empty calibration keeps its scenario;
    another family's estimator is named with the reason it did not run."""
    from difffilter.eval.calibration import calibration_mismatch

    scenario = registry.get("four_tank_bias").with_steps(30)
    cal = calibrate(scenario, runs=2, estimators=[], progress=False)
    assert cal.thresholds == {} and cal.scenario == scenario.attack_free_key()
    noisy = registry.get("four_tank_bias_high_noise").with_steps(30)
    why = calibration_mismatch(cal, noisy)
    assert why is not None and "'four_tank_bias' over 30" in why
    assert "'four_tank_bias_high_noise' over 30" in why
    with pytest.warns(UserWarning, match="no threshold for 'zhang_akf': an estimator of the "
                      "robot family"):  # fmt: skip
        calibrate(scenario, runs=2, estimators=["zhang_akf"], progress=False)
