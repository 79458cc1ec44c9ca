"""What a user writes by hand, from a fuzzing trial of YAML scenarios, threat sets and
``difffilter-eval``: each mistake named by its file and field before any run (a name that
is a path wrote reports outside ``--out``; option values, empty estimator lists, a
threat set's ``exclude`` without ``threats_from`` or its own threats beside it, numeric
threat names and a string of estimators were taken or failed mid-study), and a plant of
one's own in a built-in family gets the generic report instead of failing in the
family's sections."""

from __future__ import annotations

import pytest
import torch

from difffilter.eval.report import FamilyReport, report_for
from difffilter.eval.robustness import load_threat_set
from difffilter.models import registry
from difffilter.models.attacks import ActuatorInjection
from difffilter.models.yaml_scenario import scenario_from_dict, scenario_from_yaml

PLANT = {"F": [[0.9]], "H": [[1.0]], "Q": 1.0e-3, "R": 1.0e-2, "P0": 1.0}


def _doc(**fields):
    return {"name": "mine_fuzz", "family": "my_plants", "steps": 20, "plant": PLANT, **fields}


@pytest.mark.parametrize("name", ["../escaped", "/abs/dir", "", "  ", ".", "a\\b"])
def test_a_scenario_name_that_is_a_path_is_refused(name):
    with pytest.raises(ValueError, match=r"f.yaml: name must be a non-empty name without '/'"):
        scenario_from_dict(_doc(name=name), where="f.yaml")


def test_a_blank_name_is_named_not_read_as_none():
    with pytest.raises(ValueError, match=r"f.yaml: name must be a name \(text\); got None"):
        scenario_from_dict(_doc(name=None), where="f.yaml")


@pytest.mark.parametrize(
    ("options", "message"),
    [({"cusum_bias": "big"}, "cusum_bias must be a finite number > 0; got 'big'"),
     ({"cusum_bias": [1, 2]}, "cusum_bias must be a finite number > 0"),
     ({"cusum_bias": -1}, "cusum_bias must be a finite number > 0; got -1"),
     ({"poa_eta": "abc", "poa_zeta": 0.5}, "poa_eta must be a finite number >= 0; got 'abc'"),
     ({"poa_eta": 0.1, "poa_zeta": 1}, r"poa_zeta must be a number in \[0, 1\); got 1"),
     (["cusum_bias", 2.0], "options must be a mapping of option: value")],
)  # fmt: skip
def test_option_values_are_checked_when_the_file_is_read(options, message):
    with pytest.raises(ValueError, match=f"f.yaml: (options: estimator option )?{message}"):
        scenario_from_dict(_doc(options=options), where="f.yaml")
    assert scenario_from_dict(_doc(options={"cusum_bias": 2.5}), where="f.yaml").options == {
        "cusum_bias": 2.5
    }


def test_an_empty_estimator_list_is_refused():
    with pytest.raises(ValueError, match="f.yaml: estimators: an empty list names no estimator"):
        scenario_from_dict(_doc(estimators=[]), where="f.yaml")


def test_a_file_that_is_not_utf8_is_named(tmp_path):
    path = tmp_path / "latin1.yaml"
    path.write_bytes("name: caf\xe9\nplant: {F: [[1.0]]}\n".encode("latin-1"))
    with pytest.raises(ValueError, match=r"latin1.yaml' is not UTF-8 text .*save it as UTF-8"):
        scenario_from_yaml(path)


def test_an_actuator_injection_takes_a_number_alone_as_one_inputs_value():
    attack = ActuatorInjection(value=0.5, start=2)
    assert attack.value == (0.5,)
    values, flags = attack.sample(3, 5, 1, dtype=torch.float64)
    assert values.shape == (3, 5, 1) and bool((values == 0.5).all())
    assert flags[0].tolist() == [False, False, True, True, True]
    with pytest.raises(ValueError, match="value has 1 entries but the input has 2"):
        attack.sample(3, 5, 2, dtype=torch.float64)  # (not spread over two inputs)
    with pytest.raises(ValueError, match="value must be a non-empty sequence of finite numbers"):
        ActuatorInjection(value="big")


def test_a_plant_of_ones_own_in_a_built_in_family_gets_the_generic_report():
    for family, native in (("tracking", "TrackingScenario"), ("lfc", "LFCScenario")):
        scenario = scenario_from_dict(_doc(name=f"mine_in_{family}", family=family))
        report, why = report_for(scenario)
        assert report == FamilyReport()
        assert why and native in why and "a plant of your own" in why
        built_in = registry.get(registry.names(family=family)[0])
        assert report_for(built_in)[1] is None  # the family's own keep their sections
    # a family of one's own (no other class in it): its report, if it registered one, applies
    assert report_for(scenario_from_dict(_doc(name="mine_alone")))[1] is None


def test_a_yaml_file_with_an_upper_case_extension_gets_its_own_error(tmp_path):
    from difffilter.eval.cli import resolve_scenarios

    bad = tmp_path / "Bad.YAML"
    bad.write_text("name: bad_case\nrunz: 3\nplant: {F: [[1.0]]}\n")
    with pytest.raises(ValueError, match=r"Bad.YAML: unknown field\(s\) runz"):
        resolve_scenarios(str(bad))
    with pytest.raises(ValueError, match="Missing.YML' does not exist"):
        resolve_scenarios(str(tmp_path / "Missing.YML"))


@pytest.fixture
def scenario():
    return registry.get("four_tank_bias")


def _set(tmp_path, text: str, name="set.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


BIAS = "{kind: bias, value: 0.5, onset: 30}"


def test_a_threat_sets_exclude_needs_threats_from_and_threats_from_stands_alone(tmp_path, scenario):
    path = _set(tmp_path, f"threats: {{b: {BIAS}, c: {BIAS}}}\nexclude: [b]\n")
    with pytest.raises(ValueError, match="exclude leaves out threats of threats_from's file"):
        load_threat_set(scenario, "all", path)  # (both had run)
    _set(tmp_path, f"threats: {{b: {BIAS}, r: {BIAS}}}\n", "shared.yaml")
    path = _set(tmp_path, f"threats_from: shared.yaml\nthreats: {{mine: {BIAS}}}\n")
    with pytest.raises(ValueError, match="give threats or threats_from, not both"):
        load_threat_set(scenario, "all", path)  # (mine had been dropped)
    path = _set(tmp_path, "threats_from: shared.yaml\nexclude: [b]\n")
    assert list(load_threat_set(scenario, "all", path).threats) == ["r"]


def test_a_threat_set_names_its_threats_in_text_and_its_estimators_in_a_list(tmp_path, scenario):
    path = _set(tmp_path, f"threats: {{2: {BIAS}, on: {BIAS}}}\n")
    with pytest.raises(ValueError, match=r"set.yaml: threat names must be text; got 2: quote it"):
        load_threat_set(scenario, "2", path)  # (a TypeError while naming the unknown one)
    path = _set(tmp_path, f"threats: {{b: {BIAS}}}\nestimators: chi_square_ekf\n")
    with pytest.raises(ValueError, match="set.yaml: estimators must be a non-empty list of"):
        load_threat_set(scenario, "all", path)  # (read letter by letter: "unknown 'c'")
    path = _set(tmp_path, f"threats: {{b: {BIAS}}}\nestimators: [chi_square_ekf, nope]\n")
    with pytest.raises(ValueError, match="set.yaml: estimators: unknown estimator 'nope'"):
        load_threat_set(scenario, "all", path)


def test_an_exponent_without_a_decimal_point_is_a_number_in_every_yaml_we_read(tmp_path, scenario):
    """YAML 1.1 (PyYAML) reads ``5e-1`` as text: a threat's ``value: 5e-1`` was "not a
    number" and ``-o watermark_std=1e-2`` "a number > 0 ... got '1e-2'" (a CLI trial), while
    the training configs' loader and ``--far 1e-2`` took them as numbers."""
    from difffilter.eval.cli import build_parser
    from difffilter.eval.families.lfc import _checked_options

    path = _set(tmp_path, "threats: {b: {kind: bias, value: 5e-1, onset: 30}}\n")
    (threat,) = load_threat_set(scenario, "all", path).threats.values()
    assert threat.value == (0.5,)
    args = build_parser().parse_args(
        ["lfc_step", "-o", "watermark=true", "-o", "watermark_std=1e-2", "-o", "x=2E+1"]
    )
    options = dict(args.option)
    assert options["watermark_std"] == 0.01 and options["x"] == 20.0
    _checked_options({"watermark": True, "watermark_std": options["watermark_std"]})
    # a threat named 1e5 is a number now: the error says so and does not spell it 100000.0
    path = _set(tmp_path, "threats: {1e5: {kind: bias, value: 0.5, onset: 30}}\n")
    with pytest.raises(ValueError, match=r"got 100000.0 \(YAML reads it as a number\): quote it "
                       r"as you wrote it$"):  # fmt: skip
        load_threat_set(scenario, "all", path)
    # text stays text, and YAML's own forms are as before
    args = build_parser().parse_args(["lfc_step", "-o", "a=e5", "-o", "b=1e", "-o", "c=0x10"])
    assert dict(args.option) == {"a": "e5", "b": "1e", "c": 16}
