"""What a trial of the "your own plant" path found: a zero-size bias (a null-attack
control) stopped the whole study, the papers' attacks let quoted numbers and booleans
through to fail at the first draw in torch's words, and two YAML errors blamed the wrong
field."""

from __future__ import annotations

import math
import sys
import textwrap
from dataclasses import replace

import pytest
import torch

from difffilter.models.attacks import Replacement, SensorBias
from difffilter.models.yaml_scenario import scenario_from_dict, scenario_from_yaml
from difffilter.threats import Bias, KSigmaBias

PLANT = {"F": [[0.95, 0.04], [-0.02, 0.8]], "H": [[1.0, 0.0]], "Q": 1.0e-4, "R": 1.0e-3}


def _scenario(attack, **extra):
    return scenario_from_dict({"name": "zb", "steps": 40, "runs": 4, "plant": dict(PLANT),
                               "attack": attack, **extra})  # fmt: skip


@pytest.mark.parametrize(
    "attack",
    [{"kind": "bias", "value": 0.0, "onset": 20}, {"kind": "ksigma_bias", "k": 0, "onset": 20},
     {"kind": "sensor_bias", "gamma_bar": [0.0]}],
)  # fmt: skip
def test_a_bias_of_size_zero_takes_the_one_noise_std_floor_and_runs(attack):
    """γ_min of half a zero bias was 0, which the PoA detector refuses: every estimator of
    the study was lost. It is now the documented default, one noise standard deviation."""
    from difffilter.eval.suite import run_suite

    scenario = _scenario(attack)
    model = scenario.system()
    assert scenario.attack_norm_floor(model) == pytest.approx(math.sqrt(1e-3))
    out = run_suite(scenario, runs=4, progress=False)
    assert "modified_pf" in out.metrics and "modified_pf" not in out.skipped
    nonzero = replace(scenario, attack=Bias(0.5, onset=20))
    assert nonzero.attack_norm_floor(model) == pytest.approx(0.25)
    assert isinstance(_scenario(attack).attack_model(), (Bias, KSigmaBias, SensorBias))


@pytest.mark.parametrize(
    ("make", "message"),
    [(lambda: SensorBias((0.3,), tau="0.9"), "tau must be a real number; got str"),
     (lambda: SensorBias((0.3,), p_l="0.5"), "p_l must be a real number; got str"),
     (lambda: SensorBias((0.3,), p_l=True), "p_l must be a real number; got bool"),
     (lambda: SensorBias(("a",)), "gamma_bar must be a non-empty sequence of finite numbers"),
     (lambda: Replacement("0.1", (-1.0,), (1.0,)), "rate must be a real number; got str"),
     (lambda: Replacement(0.1, ("a",), (1.0,)), "low must be lists of finite numbers")],
)  # fmt: skip
def test_the_papers_attacks_name_a_field_that_is_no_number(make, message):
    with pytest.raises((TypeError, ValueError), match=message):
        make()


def test_a_sensor_bias_of_one_number_is_one_entry():
    """``gamma_bar: 0.3`` on a one-sensor plant ("'float' object is not iterable" before)."""
    assert SensorBias(0.3).gamma_bar == (0.3,)
    scenario = _scenario({"kind": "sensor_bias", "gamma_bar": 0.3, "tau": 0.5})
    torch.testing.assert_close(scenario.attack_model().values(3)[:, 0],
                               torch.tensor([0.15, 0.225, 0.2625], dtype=torch.float64))  # fmt: skip


def test_a_plant_function_of_the_wrong_dtype_and_a_nonlinear_plants_inputs_name_their_fields(
    tmp_path, monkeypatch
):
    (tmp_path / "plants32.py").write_text(
        textwrap.dedent("""\
        import torch
        import difffilter as df

        def motor32(dtype):  # float32 whatever it is asked
            f = torch.float32
            return df.LinearGaussianModel(
                torch.tensor([[0.9]], dtype=f), torch.eye(1, dtype=f), 1e-4 * torch.eye(1, dtype=f),
                1e-3 * torch.eye(1, dtype=f), torch.zeros(1, dtype=f), torch.eye(1, dtype=f),
                B=torch.eye(1, dtype=f))

        def decay(x):
            return 0.9 * x
    """)
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "plants32", raising=False)
    path = tmp_path / "a.yaml"
    path.write_text("name: m32\nsteps: 40\nplant: {model: plants32:motor32}\n")
    with pytest.raises(ValueError, match=r"a.yaml: plant.model: plants32:motor32\(torch.float64\) "
                                         r"returned a model of torch.float32"):  # fmt: skip
        scenario_from_yaml(str(path))
    path.write_text("name: nl\nsteps: 40\nplant: {transition: plants32:decay, H: [[1.0]], "
                    "m0: [1.0], Q: 1.0e-3, R: 1.0e-2}\ninputs: {kind: constant, value: 1.0}\n")  # fmt: skip
    with pytest.raises(ValueError, match=r"the plant has 0 input\(s\) \(plant.dim_u\)"):
        scenario_from_yaml(str(path))


@pytest.mark.parametrize(
    ("field", "value", "named"),
    [
        ("Q", True, "plant.Q"),  # `Q: yes` had been an identity
        ("R", [True], "plant.R"),  # `R: [on]`
        ("m0", [True, False], "plant.m0"),  # `m0: [on, off]`: [1, 0]
        ("F", [[0.95, True], [-0.02, 0.8]], "plant.F"),
    ],
)
def test_booleans_in_a_plants_matrices_are_refused_by_name(field, value, named):
    """A second trial: YAML reads yes/no/on/off as booleans, and ``torch.tensor`` took them
    for 1 and 0 without a word, where ``dt: true`` is refused by name."""
    plant = dict(PLANT, **{field: value})
    with pytest.raises(ValueError, match=rf"{named}: True is a boolean"):
        scenario_from_dict({"name": "b", "steps": 20, "plant": plant})


@pytest.mark.parametrize(
    "inputs", [{"kind": "constant", "value": True}, {"values": [[1.0], [False]]}]
)
def test_booleans_in_a_plants_inputs_are_refused_by_name(inputs):
    plant = dict(PLANT, B=[[0.0], [0.2]])
    with pytest.raises(ValueError, match=r"inputs.* is a boolean"):
        scenario_from_dict({"name": "b", "steps": 2, "plant": plant, "inputs": inputs})
