"""A user's own plants from outside the package, as a new user writes them: a Van der Pol
oscillator with a ramp on one sensor, and a DC motor with a known sinusoidal input and an
actuator attack, each as a Python module and as YAML. The default suite runs on them
without a crash, lists what it leaves out with the reason, never scores an attack estimate
against an attack on another channel, and the generic training config trains on them."""

from __future__ import annotations

import json
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from difffilter.attack import Channel
from difffilter.estimator import EstimatorOutput
from difffilter.eval.cli import main as eval_main
from difffilter.eval.scoring import score
from difffilter.eval.suite import run_suite
from difffilter.models import registry
from difffilter.models.generic_estimators import DEFAULT_SUITE

ROOT = Path(__file__).resolve().parents[1]

# The user's code: plant, attack and scenario, with the library's attacks (<= 25 lines each).
VDP = textwrap.dedent("""
    import torch
    import difffilter as df
    from difffilter.models.scenario import CustomScenario
    from difffilter.threats import Ramp


    def vdp_step(x, dt=0.05, mu=1.0):
        p, v = x[..., 0], x[..., 1]
        return torch.stack([p + dt * v, v + dt * (mu * (1 - p * p) * v - p)], -1)


    def vdp(dtype):
        eye = torch.eye(2, dtype=dtype)
        return df.NonlinearGaussianModel(vdp_step, lambda x: x, 1e-4 * eye, 1e-2 * eye,
                                         torch.tensor([2.0, 0.0], dtype=dtype), 1e-2 * eye)


    vdp_ramp = CustomScenario(
        name="vdp_ramp", family="user_plants", description="Van der Pol, ramp on the position sensor",
        model_fn=vdp, attack=Ramp(slope=0.01, entries=(0,), onset=20, share=0.5),
        runs=4, steps=50, dt=0.05, num_particles=100, false_alarm_rate=0.01)
""")
MOTOR = textwrap.dedent("""
    import math
    import torch
    import difffilter as df
    from difffilter.models.scenario import CustomScenario
    from difffilter.threats import Bias


    def motor(dtype):
        F = torch.tensor([[0.95, 0.04], [-0.02, 0.8]], dtype=dtype)
        B, H = torch.tensor([[0.0], [0.2]], dtype=dtype), torch.tensor([[1.0, 0.0]], dtype=dtype)
        eye = torch.eye(2, dtype=dtype)
        return df.LinearGaussianModel(F, H, 1e-4 * eye, 1e-3 * torch.eye(1, dtype=dtype),
                                      torch.zeros(2, dtype=dtype), 1e-2 * eye, B=B)


    motor_actuator = CustomScenario(
        name="motor_actuator", family="user_plants", description="DC motor, actuator bias",
        model_fn=motor, known_inputs=lambda k: torch.sin(2 * math.pi * 0.5 * 0.01 * k),
        attack=Bias(value=0.5, channel="actuator", onset=20, share=0.5),
        runs=4, steps=50, dt=0.01, num_particles=100, false_alarm_rate=0.01,
        state_unit="rad/s, A", attack_unit="V")
""")
VDP_YAML = textwrap.dedent("""
    name: vdp_ramp_yaml
    family: user_plants
    description: Van der Pol oscillator, ramp on the position sensor
    dt: 0.05
    runs: 4
    steps: 50
    num_particles: 100
    false_alarm_rate: 0.01
    plant:
      transition: user_vdp:vdp_step
      H: [[1.0, 0.0], [0.0, 1.0]]
      Q: 1.0e-4
      R: 1.0e-2
      m0: [2.0, 0.0]
      P0: 1.0e-2
    attack: {kind: ramp, slope: 0.01, entries: [0], onset: 20, share: 0.5}
""")
MOTOR_YAML = textwrap.dedent("""
    name: motor_actuator_yaml
    family: user_plants
    description: DC motor, known sinusoidal input, bias on the actuator
    dt: 0.01
    runs: 4
    steps: 50
    num_particles: 100
    false_alarm_rate: 0.01
    units: {state: "rad/s, A", attack: V}
    plant:
      F: [[0.95, 0.04], [-0.02, 0.8]]
      B: [[0.0], [0.2]]
      H: [[1.0, 0.0]]
      Q: 1.0e-4
      R: 1.0e-3
      P0: 1.0e-2
    inputs: {kind: sinusoid, amplitude: 1.0, frequency: 0.5}
    attack: {kind: bias, channel: actuator, value: 0.5, onset: 20, share: 0.5}
""")


@pytest.fixture
def plants(tmp_path, monkeypatch, isolated_registry):
    """The two modules and the two YAML files in a folder outside the package."""
    (tmp_path / "user_vdp.py").write_text(VDP)
    (tmp_path / "user_motor.py").write_text(MOTOR)
    (tmp_path / "vdp.yaml").write_text(VDP_YAML)
    (tmp_path / "motor.yaml").write_text(MOTOR_YAML)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path / "cache"))
    yield tmp_path
    for name in ("user_vdp", "user_motor"):
        sys.modules.pop(name, None)


def test_the_user_code_is_short():
    for code in (VDP, MOTOR):
        assert len(code.strip().splitlines()) <= 25


def _evaluate(path: str, out: Path) -> dict:
    assert eval_main(["--scenario", path, "--out", str(out), "--no-progress"]) == 0
    name = registry.get(path).name
    return json.loads((out / name / "metrics.json").read_text())


@pytest.mark.parametrize("path", ["user_vdp:vdp_ramp", "{tmp}/vdp.yaml"])
def test_the_oscillator_runs_the_default_suite(plants, path):
    doc = _evaluate(path.format(tmp=plants), plants / "reports")
    ran, skipped = set(doc["estimators"]), doc["skipped"]
    assert ran | set(skipped) == set(DEFAULT_SUITE) and not ran & set(skipped)
    assert "linear model" in skipped["chi_square_kf"] and "linear model" in skipped["cusum_kf"]
    assert "deception density" in skipped["mixture_likelihood_pf"]
    assert "checkpoint" in skipped["pf_nn_grad"]
    # a ramp has no steady state: PoA's ‖γ‖_min defaults to one noise std, no error
    assert {"normal_pf", "modified_pf", "normal_pf_attack_free"} <= ran
    # a sensor attack: the sensor-side estimates are scored against it
    assert doc["estimators"]["modified_pf_est"]["attack_rmse"] is not None
    assert doc["estimators"]["chi_square_ekf"]["auc"] > 0.6


@pytest.mark.parametrize("path", ["user_motor:motor_actuator", "{tmp}/motor.yaml"])
def test_the_motor_runs_the_default_suite_and_nothing_compares_channels(plants, path):
    doc = _evaluate(path.format(tmp=plants), plants / "reports")
    ran, skipped = set(doc["estimators"]), doc["skipped"]
    assert ran | set(skipped) == set(DEFAULT_SUITE)
    # y carries the actuator attack: no attack-free reference, no sensor-side oracle
    assert "no attack-free reference" in skipped["normal_pf_attack_free"]
    assert "actuators" in skipped["modified_pf"] and "actuators" in skipped["modified_pf_est"]
    assert {"chi_square_kf", "cusum_kf", "normal_pf"} <= ran
    for name, metrics in doc["estimators"].items():
        assert metrics["state_rmse_vs_attack_free"] is None, name
        assert metrics["attack_rmse"] is None, name  # no estimate of the actuator attack here
    assert doc["scenario_units"]["attack"] == "V"


def test_yaml_and_python_give_the_same_motor(plants):
    py, yml = registry.get("user_motor:motor_actuator"), registry.get(f"{plants}/motor.yaml")
    gens = {k: torch.Generator().manual_seed(3) for k in ("plant", "attack", "schedule")}
    a = py.simulate(3, gens)
    gens = {k: torch.Generator().manual_seed(3) for k in ("plant", "attack", "schedule")}
    b = yml.simulate(3, gens)
    torch.testing.assert_close(a.us, b.us)
    torch.testing.assert_close(a.x, b.x)
    torch.testing.assert_close(a.attack, b.attack)


def test_scoring_refuses_an_estimate_of_another_channel():
    B, T = 2, 5
    flags = torch.zeros(B, T, dtype=torch.bool)
    flags[:, 2:] = True

    class Traj:  # one sensor, one actuator: the shapes agree, the quantities do not
        x = torch.zeros(B, T, 2)
        attack = torch.ones(B, T, 1) * flags.unsqueeze(-1)
        info = {"attack_channel": Channel.ACTUATOR}

    Traj.flags = flags
    sensor_side = EstimatorOutput(torch.zeros(B, T, 2), attack=torch.zeros(B, T, 1))
    assert score(sensor_side, Traj, dt=1.0, wall_s=0.0)["attack_rmse"] is None
    actuator_side = EstimatorOutput(torch.zeros(B, T, 2), attack=torch.zeros(B, T, 1),
                                    attack_channel="actuator")  # fmt: skip
    assert score(actuator_side, Traj, dt=1.0, wall_s=0.0)["attack_rmse"] == pytest.approx(1.0)


def test_another_familys_estimator_by_name_is_skipped_with_the_reason(plants):
    scenario = registry.get("user_vdp:vdp_ramp")
    result = run_suite(scenario, runs=2, progress=False,
                       estimators=["kf_nn_ekf", "zhang_akf", "rrp_pf_da", "kf_linearised", "ekf"])  # fmt: skip
    assert list(result.outputs) == ["ekf"]
    assert "lfc family" in result.skipped["kf_nn_ekf"]
    assert "robot family" in result.skipped["zhang_akf"]
    assert "tracking family" in result.skipped["rrp_pf_da"]
    assert "needs a FourTankModel" in result.skipped["kf_linearised"]


@pytest.mark.parametrize("path", ["user_motor:motor_actuator", "{tmp}/motor.yaml",
                                  "user_vdp:vdp_ramp"])  # fmt: skip
def test_the_generic_config_trains_on_them(plants, path, monkeypatch):
    from difffilter.train.cli import main as train_main

    monkeypatch.chdir(plants)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    config = str(ROOT / "train" / "configs" / "generic.yaml")
    assert train_main(["fit", "--config", config, "--scenario", path.format(tmp=plants),
                       "--trainer.fast_dev_run=1", "--data.init_args.val_runs=2",
                       "--data.init_args.batch_size=2"]) == 0  # fmt: skip


def test_a_bad_yaml_scenario_names_the_file_and_the_field(tmp_path):
    from difffilter.models.yaml_scenario import scenario_from_yaml

    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nplant: {F: [[1.0]], H: [[1.0]], Q: 1.0}\n")
    with pytest.raises(ValueError, match=r"bad.yaml: plant.R is required"):
        scenario_from_yaml(bad)
    bad.write_text("name: x\nplant: {F: [[1.0]], H: [[1.0]], Q: 1.0, R: 1.0}\nattak: {}\n")
    with pytest.raises(ValueError, match=r"bad.yaml: unknown field\(s\) attak"):
        scenario_from_yaml(bad)
    bad.write_text("name: x\nplant: {F: [[1.0]], H: [[1.0]], Q: 1.0, R: 1.0}\n"
                   "attack: {kind: ramp, slop: 1}\n")  # fmt: skip
    with pytest.raises(ValueError, match=r"bad.yaml: attack: threat 'ramp' has no field\(s\) slop"):
        scenario_from_yaml(bad)
    with pytest.raises(ValueError, match="does not exist"):
        registry.get(str(tmp_path / "missing.yaml"))
    # checked by the file when it loads (a user trial met them later, without the file)
    plant = "plant: {F: [[1.0]], H: [[1.0]], Q: 1.0, R: 1.0}\n"
    for line, why in (("false_alarm_rate: 5.0", r"bad.yaml: false_alarm_rate must be a rate in \(0, 1\); got 5.0"),
                      ("gamma_min: -1.0", "bad.yaml: gamma_min must be a number > 0; got -1.0")):  # fmt: skip
        bad.write_text(f"name: x\n{plant}{line}\n")
        with pytest.raises(ValueError, match=why):
            scenario_from_yaml(bad)
    # an exponent without a decimal point is a number (YAML 1.1 read it as text), a quoted
    # one is text, with the hint
    bad.write_text("name: x\nplant: {F: [[1.0]], H: [[1.0]], Q: 1e-5, R: 2E+1}\n")
    model = scenario_from_yaml(bad).system()
    assert float(model.process_noise.cov) == 1e-5 and float(model.measurement_noise.cov) == 20.0
    bad.write_text("name: x\nplant: {F: [[1.0]], H: [[1.0]], Q: '1e-5', R: 1.0}\n")
    with pytest.raises(ValueError, match=r"'1e-5' is text here, in quotes: write the number"):
        scenario_from_yaml(bad)
    # a number to Python that YAML reads as text even unquoted: YAML's own spelling named
    bad.write_text("name: x\nplant: {F: [[1.0]], H: [[1.0]], Q: inf, R: 1.0}\n")
    with pytest.raises(ValueError, match=r"YAML reads 'inf' as text: write a number such as"):
        scenario_from_yaml(bad)
    bad.write_text("name: x\nplant: {F: [[1.0]], H: [[1.0]], Q: .5e-4, R: 1.0}\n")
    assert float(scenario_from_yaml(bad).system().process_noise.cov) == 5e-5


def test_known_inputs_that_do_not_fit_say_so(plants):
    import dataclasses

    scenario = registry.get("user_motor:motor_actuator")
    wrong = dataclasses.replace(scenario, known_inputs=torch.zeros(10, 1))
    with pytest.raises(ValueError, match=r"known_inputs .* \[50, 1\]"):
        wrong.inputs(2, torch.float64)
    assert scenario.inputs(3, torch.float64).shape == (3, 50, 1)


@pytest.mark.parametrize(
    ("change", "why"),
    [
        # the plant: shapes, functions on m0, fields another field replaces
        ({"plant": {"m0": [0.0, 0.0, 0.0]}}, r"plant.m0 has 3 entries; the state has 2"),
        ({"plant": {"H": [[1.0, 0.0, 0.0]]}}, r"plant.H must have dx = 2 columns"),
        ({"plant": {"R": [[1.0, 0.0], [0.0, 1.0]]}}, r"plant.R must be 1 × 1"),
        ({"plant": {"B": [[0.2]]}}, r"plant.B must have dx = 2 rows"),
        ({"plant": {"transition": "user_vdp:vdp_step"}}, r"plant: transition replaces F and B"),
        ({"plant": {"model": "user_vdp:vdp"}}, r"plant: model gives the whole plant; remove B, F"),
        ({"plant": {"dim_u": 1}}, r"plant.dim_u is for a transition function"),
        ({"plant": {"m0": "zero"}}, r"plant.m0 must be a list of numbers"),
        # the run's settings
        ({"dt": 0}, r"dt must be a sampling period > 0"),
        ({"dt": "fast"}, r"dt must be a finite number"),
        ({"runs": "4"}, r"motor.yaml: runs must be an integer >= 1"),
        # the attack: never acting, wider than its channel
        ({"attack": {"onset": 60}}, r"attack: it starts at step 60, after the last step \(50\)"),
        ({"attack": {"entries": [5]}}, r"motor.yaml: attack: entries \(5,\) name entries beyond"),
        ({"attack": {"value": [0.5, 0.5, 0.5]}}, r"motor.yaml: attack: value has 3 entries"),
        # the known inputs and the schedule
        ({"inputs": {"amplitud": 1.0}}, r"inputs: unknown field\(s\) amplitud"),
        ({"inputs": {"phse": 1.0}}, r"inputs: unknown field\(s\) phse"),
        ({"inputs": {"amplitude": float("nan")}}, r"inputs.amplitude must be a finite number"),
        ({"schedule": {"kind": "packet_loss", "rat": 0.1}}, r"schedule: unknown field\(s\) rat"),
        ({"schedule": {"kind": "round_robin"}}, r"schedule: round_robin needs groups"),
    ],
)  # fmt: skip
def test_a_bad_field_is_named_with_its_file_before_anything_runs(change, why, plants):
    """The documented motor with one field changed: each of these once ran on something
    else (an input typo dropped, an attack after the horizon) or failed deep inside torch."""
    import yaml

    from difffilter.models.yaml_scenario import scenario_from_yaml

    doc = yaml.safe_load(MOTOR_YAML)
    for key, value in change.items():
        if isinstance(value, dict) and isinstance(doc.get(key), dict):
            doc[key] = {**doc[key], **value}
        else:
            doc[key] = value
    path = plants / "motor.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ValueError, match=why):
        scenario_from_yaml(path)


@pytest.mark.parametrize(
    "file, replace, why",
    [
        # a covert attack's signal: its onset and width (it ran with no attacked step, or
        # failed at the first run with a message that named neither file nor field)
        ("motor.yaml", {"attack": {"kind": "covert", "signal": {"kind": "bias", "value": 0.5, "onset": 500}}},
         r"motor.yaml: attack: it starts at step 500, after the last step \(50\)"),
        ("motor.yaml", {"attack": {"kind": "covert", "signal": {"kind": "bias", "value": 0.5, "entries": [3]}}},
         r"motor.yaml: attack: entries \(3,\) name entries beyond the channel's 1"),
        ("vdp.yaml", {"attack": {"kind": "bias", "channel": "actuator", "value": 0.5}},
         r"vdp.yaml: attack: an actuator attack needs a model with inputs"),
        ("motor.yaml", {"attack": {"kind": "bias", "value": 0.5, "share": "0.5"}},
         r"motor.yaml: attack: share must be a number in \[0, 1\]"),
        # the schedule's groups and the known inputs against the plant's widths
        ("motor.yaml", {"schedule": {"kind": "round_robin", "groups": [[0], [1]]}},
         r"motor.yaml: schedule: groups must cover the 1 measurement entries"),
        ("motor.yaml", {"schedule": {"kind": "round_robin", "groups": [[0]], "start": True}},
         r"motor.yaml: schedule: start must be the 0-based index of a group"),
        ("motor.yaml", {"inputs": {"kind": "constant", "value": [1.0, 2.0]}},
         r"motor.yaml: inputs: they give 2 value\(s\) per step and the plant has 1 input"),
        ("motor.yaml", {"inputs": {"values": [[1.0, 2.0]] * 50}},
         r"motor.yaml: inputs: they give 2 value\(s\) per step and the plant has 1 input"),
    ],
)  # fmt: skip
def test_what_must_fit_the_plant_is_checked_when_the_file_loads(file, replace, why, plants):
    import yaml

    from difffilter.models.yaml_scenario import scenario_from_yaml

    doc = {**yaml.safe_load((plants / file).read_text()), **replace}
    path = plants / file
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ValueError, match=why):
        scenario_from_yaml(path)


def test_a_plant_function_of_the_wrong_width_or_failing_is_named(plants):
    """A transition returning one of two states (broadcast into both) or failing, and an
    observation of more entries than R: named at load."""
    import yaml

    from difffilter.models.yaml_scenario import scenario_from_yaml

    (plants / "user_bad.py").write_text(textwrap.dedent("""
        import torch
        def narrow(x):
            return x[..., :1]
        def one_state(x):
            return torch.stack([x[0] + 0.1 * x[1], x[1] - 0.1 * torch.sin(x[0])])
        def broken(x):
            raise RuntimeError("no")
        def three(x):
            return torch.cat([x, x[..., :1]], -1)
        def driven(x, u):
            return x + u[..., :1]
        def driven_by_torch(x, u):
            return x + torch.sin(u)
        def number(dtype):
            return 3
        def own_bug(x, u, k):
            raise RuntimeError("own bug")
    """))  # fmt: skip
    base = yaml.safe_load(VDP_YAML)
    # (the model's own probe, NonlinearGaussianModel._check_widths, names the first)
    cases = [({"transition": "user_bad:narrow"},
              r"plant: transition returns \(3, 1\) for x \[3, 2\] .*Q is 2×2, so it must return \[\.\.\., 2\]$"),
             # written for one state: x[0], x[1] are runs (a teaching trial: wrong numbers
             # on two runs, no error)
             ({"transition": "user_bad:one_state"},
              r"transition returns \(2, 2\) for x \[3, 2\] .*must keep x's runs: \[3, 2\].*x\[\.\.\., i\]"),
             ({"transition": "user_bad:broken"}, r"plant.transition failed on m0: RuntimeError: no"),
             ({"observe": "user_bad:three", "R": [[1.0, 0.0], [0.0, 1.0]]},
              r"plant.R must be 3 × 3 \(there are 3 outputs, as observe returns at m0"),
             # the state's size came from m0, and the error blamed Q alone
             ({"m0": [2.0, 0.0, 0.0], "H": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], "Q": [1e-4, 1e-4]},
              r"plant.Q must be 3 × 3 \(the state has 3 entries, as m0 has"),
             # (a robotics trial: "'NoneType' object is not subscriptable" alone)
             ({"transition": "user_bad:driven"},
              r"plant: transition takes an input u but fails on u=None.*give dim_u="),
             # (torch names it "not NoneType", without quotes: a review)
             ({"transition": "user_bad:driven_by_torch"},
              r"plant: transition takes an input u but fails on u=None.*give dim_u=")]  # fmt: skip
    for change, why in cases:
        doc = {**base, "plant": {**base["plant"], **change}}
        if "observe" in change:
            doc["plant"].pop("H")
        path = plants / "vdp_bad.yaml"
        path.write_text(yaml.safe_dump(doc))
        with pytest.raises(ValueError, match=why):
            scenario_from_yaml(path)
    # a model: that is no function of the dtype (a trial: "'torch.dtype' object is not
    # subscriptable" alone)
    path.write_text(yaml.safe_dump({**base, "plant": {"model": "user_bad:three"}}))
    with pytest.raises(ValueError, match=r"plant.model: user_bad:three\(dtype\) raised TypeError"):
        scenario_from_yaml(path)
    path.write_text(yaml.safe_dump({**base, "plant": {"model": "user_bad:number"}}))
    with pytest.raises(ValueError, match=r"plant.model: user_bad:number\(dtype\) returned a int"):
        scenario_from_yaml(path)
    # the dim_u hint only where the missing input was read (not on a bug of its own)
    doc = {**base, "plant": {**base["plant"], "transition": "user_bad:own_bug"}}
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ValueError, match="own bug") as error:
        scenario_from_yaml(path)
    assert "dim_u" not in str(error.value)
    # one string is a list of one, never its characters
    doc = {**base, "estimators": "chi_square_kf", "notes": "one note"}
    path.write_text(yaml.safe_dump(doc))
    scenario = scenario_from_yaml(path)
    assert scenario.estimators == ("chi_square_kf",) and scenario.notes == ("one note",)
    sys.modules.pop("user_bad", None)


def test_a_plant_that_gives_nan_or_is_not_torch_is_named_not_the_measurements(plants):
    """A user trial: a transition that took sqrt of a negative number was reported as NaN
    measurements ("Pass nonfinite='skip'"), and one written with numpy failed inside
    torch.func ("Cannot access data pointer of Tensor that doesn't have storage")."""
    import dataclasses

    import numpy as np

    import difffilter as df

    vdp = registry.get("user_vdp:vdp_ramp")

    def nan_model(dtype):  # x = 2.0, 1.8, 1.6, 1.4: NaN from k = 4 (sqrt(1.4 - 1.5))
        eye = torch.eye(2, dtype=dtype)
        return df.NonlinearGaussianModel(
            lambda x: torch.stack([x[..., 0] - 0.2 + 0.0 * torch.sqrt(x[..., 0] - 1.5),
                                   x[..., 1]], -1),
            lambda x: x, 1e-4 * eye, 1e-2 * eye, torch.tensor([2.0, 0.0], dtype=dtype),
            1e-6 * eye)  # fmt: skip

    with pytest.raises(ValueError, match=r"simulated plant's state is NaN or Inf at step k = 4 "
                                         r"of run 0 .* the model's transition"):  # fmt: skip
        run_suite(dataclasses.replace(vdp, model_fn=nan_model), runs=2, estimators=["ekf"],
                  progress=False)  # fmt: skip

    def numpy_step(x):
        return torch.as_tensor(np.asarray(x) * 0.9)

    def numpy_model(dtype):
        eye = torch.eye(2, dtype=dtype)
        return df.NonlinearGaussianModel(numpy_step, lambda x: x, 1e-4 * eye, 1e-2 * eye,
                                         torch.tensor([2.0, 0.0], dtype=dtype), 1e-2 * eye)  # fmt: skip

    with pytest.raises(RuntimeError, match=r"differentiating the transition of "
                                           r"NonlinearGaussianModel with torch.func.*no numpy"):  # fmt: skip
        run_suite(dataclasses.replace(vdp, model_fn=numpy_model), runs=2, estimators=["ekf"],
                  progress=False)  # fmt: skip


def test_a_model_function_without_the_dtype_is_named(plants):
    import dataclasses

    vdp = registry.get("user_vdp:vdp_ramp")
    with pytest.raises(TypeError, match=r"'vdp_ramp': model_fn must take the dtype.*\(\)"):
        dataclasses.replace(vdp, model_fn=lambda: None)


def test_a_shorter_horizon_takes_the_first_rows_of_tabulated_inputs():
    """``with_steps`` of a scenario whose known inputs are a table of its full horizon: the
    first rows (once an error: [1, 6, 1] against [.., 4, 1]); and the plant's noise never
    comes from torch's global generator."""
    import difffilter as df
    from difffilter.models.scenario import CustomScenario
    from difffilter.models.streams import Streams

    def plant(dtype):
        one = torch.ones(1, 1, dtype=dtype)
        return df.LinearGaussianModel(one, one, one, one, torch.zeros(1, dtype=dtype), one, B=one)

    table = torch.arange(6.0).reshape(6, 1)
    sc = CustomScenario(name="short_inputs", family="user_plants", description="tabulated inputs",
                        model_fn=plant, known_inputs=table, steps=6)  # fmt: skip
    short = sc.with_steps(4)
    torch.testing.assert_close(short.inputs(2, torch.float64), table[:4].expand(2, 4, 1).double())
    gens = {k: Streams(0)(k) for k in ("plant", "attack", "schedule")}
    assert short.simulate(2, gens).x.shape == (2, 4, 1)
    with pytest.raises(ValueError, match="generators must hold 'plant'"):
        short.simulate(2, {"attack": gens["attack"]})
    with pytest.raises(TypeError, match="generators must be a mapping .*got Generator"):
        short.simulate(2, gens["plant"])  # a bare generator had failed on `.get`


def test_a_table_of_inputs_per_run_serves_studies_of_any_size_and_the_default_suite(monkeypatch):
    """A ``[R, T, du]`` table: run ``i`` takes row ``i mod R``. A user trial found the
    documented shape refused by the default suite: the CUSUM's calibration (at least 50
    runs) asked for a table of 50 runs, its cache fingerprint for one."""
    import difffilter as df
    from difffilter.eval.suite import run_suite
    from difffilter.models.scenario import CustomScenario
    from difffilter.threats import Bias

    monkeypatch.setenv("DIFFFILTER_CACHE", "off")

    def plant(dtype):
        e = torch.eye(1, dtype=dtype)
        return df.LinearGaussianModel(
            0.9 * e, e, 0.01 * e, 0.01 * e, torch.zeros(1, dtype=dtype), e, B=e
        )

    table = torch.arange(3 * 8, dtype=torch.float64).reshape(3, 8, 1)
    sc = CustomScenario(name="per_run_inputs", family="user_plants", description="a table per run",
                        model_fn=plant, known_inputs=table, steps=8, runs=3,
                        attack=Bias(0.5, onset=4))  # fmt: skip
    torch.testing.assert_close(sc.inputs(5, torch.float64), table[[0, 1, 2, 0, 1]])
    torch.testing.assert_close(sc.inputs(2, torch.float64), table[:2])
    result = run_suite(sc, progress=False, estimators=["chi_square_kf", "cusum_kf"])
    assert set(result.metrics) == {"chi_square_kf", "cusum_kf"}
    torch.testing.assert_close(result.traj.us, table)


def test_a_cusum_calibration_follows_an_edited_plant_in_the_same_process(monkeypatch):
    """The process's CUSUM cache was keyed on the scenario's name and settings only: a plant
    edited in the same session reused the first plant's threshold."""
    import difffilter as df
    from difffilter.models.estimators import SuiteContext
    from difffilter.models.scenario import CustomScenario
    from difffilter.models.streams import Streams

    monkeypatch.setenv("DIFFFILTER_CACHE", "off")

    def plant(r):
        def model(dtype):
            e = torch.eye(1, dtype=dtype)
            return df.LinearGaussianModel(0.5 * e, e, e, r * e, torch.zeros(1, dtype=dtype), e)

        return model

    thresholds = []
    for r in (1.0, 100.0):
        sc = CustomScenario(name="edited", family="user_plants", description="R edited",
                            model_fn=plant(r), steps=20, runs=4)  # fmt: skip
        ctx = SuiteContext(sc, sc.system(), 4, Streams(0))
        thresholds.append(float(ctx.cusum(df.KalmanFilter()).threshold))
    assert thresholds[0] != thresholds[1]


def test_a_bad_field_is_named_once_and_a_replacement_box_by_its_fields(plants):
    """The file and field once, not twice (``motor.yaml: plant: …motor.yaml: plant.R``); a
    replacement's scalar bounds said "'int' object is not iterable"."""
    import yaml

    from difffilter.models.yaml_scenario import scenario_from_yaml

    doc = yaml.safe_load(MOTOR_YAML)
    doc["plant"] = {**doc["plant"], "R": [[1.0, 0.0], [0.0, 1.0]]}
    path = plants / "motor.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ValueError) as error:
        scenario_from_yaml(path)
    assert str(error.value).count("motor.yaml") == 1 and "plant.R must be 1 × 1" in str(error.value)
    doc = yaml.safe_load(MOTOR_YAML)
    doc["attack"] = {"kind": "replacement", "rate": 0.2, "low": -1, "high": 1}
    path.write_text(yaml.safe_dump(doc))
    # one number is a one-entry bound (as gamma_bar and actuator_injection's value take it)
    attack = scenario_from_yaml(path).attack_model()
    assert (attack.low, attack.high) == ((-1.0,), (1.0,))
    doc["attack"] = {"kind": "replacement", "rate": 0.2, "low": "-1", "high": 1}
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ValueError, match=r"attack \(replacement\): low must be lists of finite"):
        scenario_from_yaml(path)
