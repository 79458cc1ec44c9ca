"""difffilter-eval's command line doing less than asked, silently (a red-team trial).

* ``-o watermark=true`` on a plant of one's own declared in the lfc family was accepted and
  ran no study (the family's studies run on its own scenarios).
* ``package.module:function`` returning two scenarios evaluated the first alone.
* A scenario named like what the evaluation writes at the top of ``--out``
  (``tb_leaderboard``, ``leaderboard.md``) ran its study, then lost its TensorBoard events
  or failed.
* ``--estimators a --estimators b`` ran ``b`` alone.
"""

import sys

import pytest
from conftest import registry_copy

from difffilter.eval import cli as eval_cli

_YAML = """\
name: {name}
family: {family}
description: DC motor, bias on the actuator
dt: 0.01
runs: 2
steps: 30
plant:
  F: [[0.95, 0.04], [-0.02, 0.8]]
  B: [[0.0], [0.2]]
  H: [[1.0, 0.0]]
  Q: 1.0e-4
  R: 1.0e-3
  P0: 1.0e-2
inputs: {{kind: sinusoid, amplitude: 1.0, frequency: 0.5}}
attack: {{kind: bias, channel: actuator, value: 0.5, onset: 10}}
"""


@pytest.fixture(autouse=True)
def _registry_restored():
    """The plants these tests register leave the registry as it was (one of family lfc had
    joined the lfc family of later tests; its files and calls had stayed: a review)."""
    with registry_copy():
        yield


def _error(argv, capsys, monkeypatch):
    def no_suite(*args, **kwargs):
        raise AssertionError("a suite ran before the command line was refused")

    monkeypatch.setattr("difffilter.eval.suite.run_suite", no_suite)
    assert eval_cli.main(argv) == 2
    return capsys.readouterr().err


def test_an_option_on_a_plant_of_ones_own_in_the_lfc_family_is_refused(
    tmp_path, capsys, monkeypatch
):
    plant = tmp_path / "motor_lfc_trial.yaml"
    plant.write_text(_YAML.format(name="motor_lfc_trial", family="lfc"))
    err = _error([str(plant), "--runs", "2", "--out", str(tmp_path / "o"), "-o", "watermark=true",
                  "--no-progress"], capsys, monkeypatch)  # fmt: skip
    assert "plants of your own: no option would take effect" in err


@pytest.mark.parametrize("name", ["tb_leaderboard", "leaderboard.md", "INCOMPLETE.md"])
def test_a_scenario_named_like_a_top_level_output_is_refused(tmp_path, capsys, monkeypatch, name):
    plant = tmp_path / "plant.yaml"
    plant.write_text(_YAML.format(name=name, family="my_plants_trial"))
    err = _error([str(plant), "--runs", "2", "--out", str(tmp_path / "o"), "--far", "off",
                  "--no-progress"], capsys, monkeypatch)  # fmt: skip
    assert f"scenario '{name}': its reports go in" in err
    assert "give the scenario another name" in err


@pytest.mark.parametrize("option", ["--estimators", "--add-estimators", "--threats"])
def test_a_list_option_given_twice_is_refused(tmp_path, capsys, monkeypatch, option):
    values = ("chi_square_ekf", "cusum_ekf") if option != "--threats" else ("bias", "ramp")
    with pytest.raises(SystemExit) as stop:  # a usage error, from the parser
        eval_cli.main(["four_tank_bias", option, values[0], option, values[1],
                       "--out", str(tmp_path / "o")])  # fmt: skip
    assert stop.value.code == 2
    assert f"{option}: given twice" in capsys.readouterr().err


def test_a_path_whose_function_gives_two_scenarios_is_refused(tmp_path, monkeypatch):
    (tmp_path / "two_plants_trial.py").write_text(
        "import dataclasses, torch\n"
        "import difffilter as df\n"
        "from difffilter.models.scenario import CustomScenario\n"
        "def _model(dtype):\n"
        "    eye = torch.eye(2, dtype=dtype)\n"
        "    return df.LinearGaussianModel(eye, eye, 1e-4 * eye, 1e-2 * eye, torch.zeros(2, dtype=dtype), eye)\n"
        "_a = CustomScenario(name='two_trial_a', family='two_trial', description='a', model_fn=_model)\n"
        "def plants():\n"
        "    return [_a, dataclasses.replace(_a, name='two_trial_b')]\n"
    )
    monkeypatch.setattr(sys, "path", [str(tmp_path), *sys.path])
    with pytest.raises(ValueError, match="gave 2 scenarios; a path names one"):
        eval_cli.resolve_scenarios("two_plants_trial:plants")
