"""A scenario asked for its model on a device it cannot build there refuses by name.

The LFC, robot and tracking scenarios (and a generic scenario whose ``model_fn`` takes only
the dtype) built their models on the CPU whatever ``device`` was given: ``system(device=
"cuda")`` returned a CPU model, and a study believed to run on the GPU ran on the CPU or
failed at its first step far from the cause.
"""

import pytest
import torch

from difffilter.models.registry import get as get_scenario


@pytest.mark.parametrize("name", ["lfc_step", "robot_actuator_attack", "tracking_rrp_deception"])
def test_a_device_the_plant_is_not_built_on_is_refused(name):
    scenario = get_scenario(name)
    with pytest.raises(ValueError, match=r"system\(device='meta'\).*CPU only"):
        scenario.system(torch.float64, device="meta")


@pytest.mark.parametrize("name", ["lfc_step", "robot_actuator_attack", "tracking_rrp_deception"])
def test_the_cpu_and_no_device_give_the_same_model(name):
    scenario = get_scenario(name)
    for device in (None, "cpu", torch.device("cpu")):
        model = scenario.system(torch.float64, device=device)
        assert model.initial.mean.device.type == "cpu"


def test_a_generic_scenario_whose_model_fn_ignores_the_device_is_refused():
    from difffilter import LinearGaussianModel
    from difffilter.models.scenario import CustomScenario

    def model_fn(dtype):
        eye = torch.eye(2, dtype=dtype)
        return LinearGaussianModel(eye, eye, 0.1 * eye, 0.1 * eye, torch.zeros(2, dtype=dtype), eye)

    scenario = CustomScenario(
        name="device_probe", family="device_probe", description="d", model_fn=model_fn
    )
    assert scenario.system(torch.float64, device="cpu").initial.mean.device.type == "cpu"
    with pytest.raises(ValueError, match="device_probe.*CPU only"):
        scenario.system(torch.float64, device="meta")
