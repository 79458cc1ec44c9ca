"""Scenarios from outside the repository: ``package.module:object`` wherever a scenario name
is taken, and installed plug-ins (the ``difffilter.scenarios`` entry points)."""

from __future__ import annotations

import json
import sys
import textwrap
from importlib.metadata import EntryPoint

import pytest

from difffilter.eval.cli import main as eval_main
from difffilter.models import registry

PLUGIN = textwrap.dedent("""
    import dataclasses

    import torch

    import difffilter as df
    from difffilter.models.attacks import SensorBias
    from difffilter.models.scenario import CustomScenario


    def plant(dtype):
        F = torch.tensor([[0.9, 0.1], [0.0, 0.95]], dtype=dtype)
        eye = torch.eye(2, dtype=dtype)
        return df.LinearGaussianModel(F, eye, 1e-3 * eye, 1e-2 * eye, torch.zeros(2, dtype=dtype), eye)


    SCENARIO = CustomScenario(
        name="plugin_plant_bias", family="plugin_plants", description="a user's plant, bias",
        model_fn=plant, attack=SensorBias((0.5, 0.0), tau=0.7, p_l=0.3), runs=3, steps=30,
        dt=1.0, num_particles=40, false_alarm_rate=0.01, state_unit="m", attack_unit="m",
    )


    def make():
        return dataclasses.replace(SCENARIO, name="plugin_plant_bias_made")


    NOT_A_SCENARIO = 3
""")


@pytest.fixture
def plugin(tmp_path, monkeypatch, isolated_registry):
    (tmp_path / "difffilter_user_plugin.py").write_text(PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    # the user's scenarios leave with the test (other tests list every headline scenario):
    # the isolated_registry fixture
    yield "difffilter_user_plugin"
    sys.modules.pop("difffilter_user_plugin", None)


def test_a_module_object_path_names_a_scenario_and_registers_it(plugin):
    scenario = registry.get(f"{plugin}:SCENARIO")
    assert scenario.name == "plugin_plant_bias" and registry.get("plugin_plant_bias") is scenario
    assert registry.get(f"{plugin}:make").name == "plugin_plant_bias_made"  # a function


@pytest.mark.parametrize(
    ("path", "why"),
    [
        ("no_such_module_xyz:S", "cannot import 'no_such_module_xyz'"),
        ("{plugin}:MISSING", "has no 'MISSING'"),
        ("{plugin}:NOT_A_SCENARIO", "is not a difffilter scenario"),
    ],
)
def test_a_bad_path_says_what_is_wrong(plugin, path, why):
    with pytest.raises(ValueError, match=why):
        registry.get(path.format(plugin=plugin))


def test_difffilter_eval_runs_a_scenario_of_ones_own(plugin, tmp_path, capsys):
    out = tmp_path / "reports"
    assert eval_main([f"{plugin}:SCENARIO", "--runs", "2", "--out", str(out), "--no-progress"]) == 0
    doc = json.loads((out / "plugin_plant_bias" / "metrics.json").read_text())
    assert doc["scenario"] == "plugin_plant_bias" and doc["runs"] == 2
    assert doc["scenario_units"] == {"state": "m", "attack": "m"}
    assert doc["estimators"]  # the generic estimators that fit a linear model ran


def test_installed_plugins_register_with_the_built_in_families_and_a_broken_one_warns(
    plugin, monkeypatch
):
    points = [
        EntryPoint("mine", f"{plugin}:SCENARIO", registry.PLUGIN_GROUP),
        EntryPoint("broken", "no_such_module_xyz:S", registry.PLUGIN_GROUP),
    ]
    monkeypatch.setattr(
        registry, "entry_points", lambda group: points if group == registry.PLUGIN_GROUP else []
    )
    monkeypatch.setattr(registry, "_LOADED", False)
    with pytest.warns(UserWarning, match="plug-in 'broken'.*failed to load"):
        names = registry.names()
    assert "plugin_plant_bias" in names and "four_tank_bias" in names


def test_training_takes_the_same_path(plugin):
    from difffilter.train.task import FilterEstimatorTask, ScenarioDataModule

    data = ScenarioDataModule(f"{plugin}:SCENARIO", batch_size=2, val_runs=2)
    task = FilterEstimatorTask(f"{plugin}:SCENARIO", filter="kf", hidden=4)
    assert data.scenario.name == task.scenario.name == "plugin_plant_bias"
    assert task.card().scenario == "plugin_plant_bias"
    assert data.val_dataloader().dataset[0]["y_recv"].shape == (2, 30, 2)


def test_both_command_lines_take_scenario_as_an_option(plugin, tmp_path, monkeypatch):
    from pathlib import Path

    from difffilter.train.cli import main as train_main

    out = tmp_path / "reports"
    assert eval_main(["--scenario", f"{plugin}:SCENARIO", "--runs", "2", "--out", str(out),
                      "--no-progress", "--far", "off"]) == 0  # fmt: skip
    assert (out / "plugin_plant_bias" / "metrics.json").is_file()
    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    config = str(root / "train" / "configs" / "four_tank.yaml")
    assert train_main(["fit", "--config", config, "--scenario", f"{plugin}:SCENARIO",
                       "--model.init_args.filter=ekf", "--trainer.fast_dev_run=1",
                       "--data.init_args.val_runs=2", "--data.init_args.batch_size=2"]) == 0  # fmt: skip


def test_a_plugin_module_that_registers_nothing_is_named(plugin, tmp_path, monkeypatch):
    """A plug-in naming a module that defines its scenarios but never calls ``register``
    was silently absent from every list."""
    (tmp_path / "difffilter_user_plugin_registering.py").write_text(
        "from difffilter.models import registry\n"
        "from difffilter_user_plugin import make\n"
        "registry.register(make())\n"
    )
    points = [EntryPoint("quiet", plugin, registry.PLUGIN_GROUP),
              EntryPoint("loud", "difffilter_user_plugin_registering", registry.PLUGIN_GROUP)]  # fmt: skip
    monkeypatch.setattr(
        registry, "entry_points", lambda group: points if group == registry.PLUGIN_GROUP else []
    )
    monkeypatch.setattr(registry, "_LOADED", False)
    with pytest.warns(UserWarning) as said:
        names = registry.names()
    quiet = [str(w.message) for w in said if "registered no scenario" in str(w.message)]
    assert len(quiet) == 1 and quiet[0].startswith(
        "difffilter: the scenario plug-in 'quiet' (difffilter_user_plugin) registered no "
        "scenario: a module must call"
    )  # and none for the module that registers its scenario
    assert "plugin_plant_bias_made" in names and "plugin_plant_bias" not in names
    sys.modules.pop("difffilter_user_plugin_registering", None)


def test_a_family_module_that_fails_to_import_fails_every_call_not_only_the_first(
    isolated_registry, monkeypatch
):
    """A contributor's trial: one broken module of ``difffilter.models`` failed the first
    call, and every later call found a registry marked loaded without the modules after
    it ("unknown scenario 'four_tank_bias'; known scenarios: (none)")."""
    import pkgutil

    real = pkgutil.iter_modules

    def with_a_broken_family(path):
        yield from real(path)
        yield pkgutil.ModuleInfo(None, "zz_broken_family_xyz", False)

    monkeypatch.setattr(registry.pkgutil, "iter_modules", with_a_broken_family)
    monkeypatch.setattr(registry, "_LOADED", False)
    for _ in range(2):  # the same error, named, each time
        with pytest.raises(ModuleNotFoundError) as raised:
            registry.get("four_tank_bias")
        assert "while importing difffilter.models.zz_broken_family_xyz" in "".join(
            raised.value.__notes__
        )
    monkeypatch.setattr(registry.pkgutil, "iter_modules", real)
    assert registry.get("four_tank_bias").name == "four_tank_bias"  # once fixed, it loads


def test_a_misspelt_estimator_of_a_scenario_is_named_before_any_work(plugin, tmp_path, capsys):
    """A contributor's trial: a scenario listing ``cusum_ekff`` failed only when it ran,
    after the scenarios before it, without naming it, and no report was written."""
    import dataclasses

    scenario = registry.get(f"{plugin}:SCENARIO")
    registry.register(dataclasses.replace(scenario, name="plugin_typo",
                                          estimators=("kf", "cusum_ekff")))  # fmt: skip
    out = tmp_path / "reports"
    assert eval_main(["plugin_typo", "--runs", "2", "--out", str(out), "--no-progress"]) == 2
    assert ("error: scenario 'plugin_typo' lists unknown estimator 'cusum_ekff' (did you mean "
            "'cusum_ekf'?)") in capsys.readouterr().err  # fmt: skip
    assert not (out / "plugin_typo").exists()
