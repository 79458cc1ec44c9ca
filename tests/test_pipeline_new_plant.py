"""A new nonlinear plant from the public API alone, through every generic estimator."""

import json

import jsonschema
import pytest
import torch

import difffilter as df
from difffilter.eval.report import metrics_schema, write_report
from difffilter.eval.suite import run_suite
from difffilter.models.attacks import SensorBias
from difffilter.models.generic_estimators import DEFAULT_SUITE, default_estimators
from difffilter.models.scenario import CustomScenario

DT = 0.05


def pendulum(dtype):
    """Damped pendulum, angle and rate; measures sin(angle) and the rate."""

    def f(x):
        theta, omega = x[..., 0], x[..., 1]
        return torch.stack(
            [theta + DT * omega, omega - DT * (9.81 * torch.sin(theta) + 0.5 * omega)], -1
        )

    def h(x):
        return torch.stack([torch.sin(x[..., 0]), x[..., 1]], -1)

    eye = torch.eye(2, dtype=dtype)
    return df.NonlinearGaussianModel(
        f, h, 1e-4 * eye, 1e-3 * eye, torch.tensor([0.5, 0.0], dtype=dtype), 1e-2 * eye
    )


SCENARIO = CustomScenario(
    name="pendulum_bias",
    family="pendulum",
    description="damped pendulum, bias on the angle sensor",
    model_fn=pendulum,
    attack=SensorBias((0.4, 0.0), tau=0.7, p_l=0.3),
    runs=16,
    steps=60,
    dt=DT,
    num_particles=200,
    false_alarm_rate=0.01,
)


def test_every_generic_estimator_runs_on_a_new_nonlinear_plant(tmp_path):
    result = run_suite(SCENARIO, seed=0, progress=False)
    doc = write_report(tmp_path / "pendulum_bias", result)
    names = [n for n in default_estimators(SCENARIO) if n not in result.skipped]
    assert list(doc["estimators"]) == names and "chi_square_kf" not in names
    # what was left out is listed with the reason: the KF pair (nonlinear model), the
    # learned estimators (no checkpoint)
    assert "linear model" in result.skipped["chi_square_kf"]
    assert "checkpoint" in result.skipped["pf_nn_grad"]
    assert set(result.skipped) | set(doc["estimators"]) == set(DEFAULT_SUITE)
    jsonschema.validate(
        json.loads((tmp_path / "pendulum_bias" / "metrics.json").read_text()), metrics_schema()
    )
    assert "## Estimators" in (tmp_path / "pendulum_bias" / "report.md").read_text()
    est = doc["estimators"]
    for name in names:  # the attack-free reference tracks the plant; nothing diverges
        assert est[name]["state_rmse"] < 0.2, name
    assert est["normal_pf_attack_free"]["state_rmse_vs_attack_free"] == 0.0
    for name in (
        "modified_pf",
        "chi_square_ekf",
        "cusum_ekf",
        "chi_square_ukf",
        "mixture_likelihood_pf",
    ):
        assert est[name]["auc"] > 0.8, (name, est[name]["auc"])
    # compensating the oracle attack beats ignoring it
    assert est["modified_pf"]["state_rmse"] < est["normal_pf"]["state_rmse"]
    assert est["modified_pf_est"]["attack_rmse"] < 0.4  # below the bias itself


def test_the_poa_floor_is_half_the_norm_of_the_bias_as_injected():
    """γ_min: one value is a bias on every entry, ``entries`` zero the others (it read the
    stored tuple: Bias(0.5) gave 0.25 where Bias((0.5, 0.5)), the same attack, gave 0.354)."""
    import dataclasses
    import math

    from difffilter.threats import Bias, KSigmaBias

    model = pendulum(torch.float64)
    sigma = model.measurement_cov(1).diagonal().sqrt().tolist()
    expected = {
        # a k-sigma bias is a bias of k σ (it fell back to one noise std, ‖σ‖, for any k)
        KSigmaBias.of(model, 3.0): 0.5 * 3.0 * math.hypot(*sigma),
        KSigmaBias.of(model, 3.0, entries=(0,)): 0.5 * 3.0 * sigma[0],
        Bias(value=0.5): 0.5 * math.hypot(0.5, 0.5),
        Bias(value=(0.5, 0.5)): 0.5 * math.hypot(0.5, 0.5),
        Bias(value=(0.5, 0.3), entries=(0,)): 0.25,
        Bias(value=0.5, entries=(1,)): 0.25,
    }
    for attack, floor in expected.items():
        scenario = dataclasses.replace(SCENARIO, attack=attack)
        assert math.isclose(scenario.attack_norm_floor(model), floor, rel_tol=1e-12), attack


@pytest.mark.slow
def test_a_scenario_of_ones_own_runs_the_robustness_study_on_its_own_threat_set(
    tmp_path, capsys, isolated_registry
):
    """``--threat-set FILE``: the threats of a scenario without a set in eval/threats (it
    could not be studied without editing the repository)."""
    from difffilter.eval.cli import main

    # module:object registers the scenario: in this test's registry only (a headline
    # scenario without a threat set would stay for every later test of the process:
    # the isolated_registry fixture)

    threats = tmp_path / "pendulum.yaml"
    threats.write_text("runs: 2\nthreats:\n  ramp: {kind: ramp, slope: 0.02, onset: 21}\n")
    argv = ["--scenario", "test_pipeline_new_plant:SCENARIO", "--threats", "all", "--runs", "2",
            "--out", str(tmp_path / "out"), "--no-progress"]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "has no threat set" in err and "with --threat-set FILE.yaml" in err
    assert main([*argv, "--threat-set", str(tmp_path / "missing.yaml")]) == 2
    assert "--threat-set: no file" in capsys.readouterr().err
    assert main([*argv, "--threat-set", str(threats)]) == 0
    doc = json.loads((tmp_path / "out" / "pendulum_bias" / "robustness.json").read_text())
    assert "ramp" in json.dumps(doc)
