"""Findings of a trial of docs/adding-a-scenario.md: a module path written as a file's
(``./my_plants:scenario`` in ``--scenario``, ``--import`` or a YAML plant's
``transition:``) ended in importlib's ``TypeError`` traceback, naming no file or field; a
single need without the tuple's comma (``needs=(LINEAR_MODEL)``) in "'Need' object is
not iterable", naming neither the estimator nor ``needs``."""

from __future__ import annotations

import pytest
import torch

from difffilter._imports import import_object, import_plugin
from difffilter.models import estimators
from difffilter.models.estimators import register
from difffilter.models.needs import LINEAR_MODEL

PATH_HINT = r"a file's path, not a module's name\); give a module's name, not a file's path"


@pytest.mark.parametrize("name", ["./my_plants", "../plants/my_plants", "plants/my_plants"])
def test_a_files_path_is_named_as_one_where_a_module_goes(name):
    with pytest.raises(ValueError, match=rf"plant.yaml: plant.transition: cannot import .*"
                                         rf"{PATH_HINT}.*'my_plants'"):  # fmt: skip
        import_object(f"{name}:step", "plant.yaml: plant.transition")
    with pytest.raises(ValueError, match=rf"--import {name}: cannot import .*{PATH_HINT}"):
        import_plugin(name, f"--import {name}")


def test_the_dotted_name_suggested_is_the_paths_own():
    with pytest.raises(ValueError, match=r"from the file's folder 'my_plants', or a dotted "
                                         r"name from the working folder \(plants.my_plants\)"):  # fmt: skip
        import_object("./plants/my_plants.py:scenario", "scenario")


def test_one_need_alone_is_a_need_and_anything_else_is_named(monkeypatch):
    estimators.names()  # the built-ins loaded first: a copy of the unloaded registry takes them away
    monkeypatch.setattr(estimators, "ESTIMATORS", dict(estimators.ESTIMATORS))

    @register("trial_single_need", "one need, no comma", needs=(LINEAR_MODEL))
    def _factory(ctx):
        return lambda tr: None

    assert estimators.ESTIMATORS["trial_single_need"].needs == (LINEAR_MODEL,)
    for bad in (3, ("linear",)):
        with pytest.raises(TypeError, match=r"estimator 'trial_bad': needs must be a Need of "
                                            r"difffilter.models.needs or a tuple"):  # fmt: skip
            register("trial_bad", "bad needs", needs=bad)


def test_a_python_scenario_with_input_loss_and_no_inputs_is_refused_as_the_yaml_one():
    """A CustomScenario with input_loss, no known_inputs and no actuator attack ran on zero
    inputs, so a lost packet changed nothing while the report announced the loss (udp_kf
    equal to kf to 1e-17); the YAML form of the same scenario is refused (a trial)."""
    import difffilter as df
    from difffilter.input_loss import InputLossSchedule
    from difffilter.models.scenario import CustomScenario
    from difffilter.models.schedules import PacketLoss

    def plant(dtype):
        eye = torch.eye(2, dtype=dtype)
        return df.LinearGaussianModel(0.9 * eye, eye, 0.01 * eye, 0.01 * eye,
                                      torch.zeros(2, dtype=dtype), eye,
                                      B=torch.ones(2, 1, dtype=dtype))  # fmt: skip

    loss = InputLossSchedule(PacketLoss(0.3))
    with pytest.raises(ValueError, match="input_loss needs inputs to lose"):
        CustomScenario(name="motor", family="mine", description="", model_fn=plant,
                       input_loss=loss)  # fmt: skip
    CustomScenario(name="motor", family="mine", description="", model_fn=plant, input_loss=loss,
                   known_inputs=torch.zeros(100, 1, dtype=torch.float64))  # fmt: skip


def test_an_input_loss_schedule_that_does_not_fit_the_inputs_says_so():
    """Its error spoke of "the 1 measurement entries" for a plant of two sensors and one
    input, and named no input_loss (a trial)."""
    from difffilter.input_loss import InputLossSchedule
    from difffilter.models.schedules import PacketLoss

    loss = InputLossSchedule(PacketLoss(0.3, packets=((0,), (1,))))
    with pytest.raises(ValueError, match=r"^input_loss: .*the plant's 1 input\(s\), not its"):
        loss.draw(2, 5, 1, torch.Generator().manual_seed(0))
