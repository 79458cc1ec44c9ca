"""Which of a robustness study's threats a learned estimator met in training (its card)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest

from difffilter.eval.coverage import checkpoint_of, training_coverage

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "checkpoints" / "four_tank_nn_grad.ckpt"
THREATS = {
    "bias": {"kind": "bias", "value": 0.5, "onset": 21},
    "bias_half_runs": {"kind": "bias", "value": 0.5, "onset": 21, "share": 0.5},
    "ramp": {"kind": "ramp", "slope": 0.005, "onset": 21},
    "replay": {"kind": "replay", "delay": 20, "onset": 41},
    "crafted": {"kind": "stealthy", "against": "pf_nn_grad", "onset": 21},
}


def _with_card(tmp_path: Path, data_config: dict, model_config: dict) -> Path:
    """A copy of the shipped checkpoint whose card says it was trained as given."""
    path = tmp_path / "net.ckpt"
    shutil.copy(SHIPPED, path)
    card = json.loads(SHIPPED.with_suffix(".json").read_text())
    card["data_config"] = {**card["data_config"], **data_config}
    card["model_config"] = {**card["model_config"], **model_config}
    path.with_suffix(".json").write_text(json.dumps(card))
    return path


def test_a_network_trained_across_threats_has_its_threats_labelled_from_its_card(tmp_path):
    threats = {"own": {"weight": 0.5},
               "bias": {"weight": 0.3, "kind": "bias", "value": {"loguniform": [0.05, 1.5]},
                        "onset": {"randint": [5, 60]}},
               "ramp": {"weight": 0.2, "kind": "ramp", "slope": {"loguniform": [0.01, 0.03]},
                        "onset": {"randint": [5, 60]}}}  # fmt: skip
    path = _with_card(tmp_path, {"threats": threats}, {"adversarial_runs": 4})
    got = training_coverage(path, THREATS)
    assert got == {"trained_on": "a distribution over threats", "adversarial": True,
                   "threats": {"bias": "within", "bias_half_runs": "kind only",
                               "ramp": "kind only", "replay": "held out",
                               "crafted": "kind only"}}  # fmt: skip
    # configured adversarially, but the weights chosen before the first crafting (the
    # card's count, a trial's epoch-0 weights): no crafted attack met, the crafted threat
    # held out; a count above 0 and a card from before the count was kept: kind only
    card = json.loads(path.with_suffix(".json").read_text())
    for craftings, want in ((0, "held out"), (3, "kind only"), (None, "kind only")):
        card.pop("adversarial_craftings", None)
        if craftings is not None:
            card["adversarial_craftings"] = craftings
        path.with_suffix(".json").write_text(json.dumps(card))
        got = training_coverage(path, THREATS)
        assert got["threats"]["crafted"] == want and got["adversarial"] is (want == "kind only")
    # (a scenario the registry does not know, a user's module's: the study's attack is the
    # one trained on; a registered one's own attack is read from it, test below)
    plain = _with_card(tmp_path, {"threats": None, "scenario": "my_plants:ramp_plant"},
                       {"adversarial_runs": 0})  # fmt: skip
    assert training_coverage(plain, THREATS) == {
        "trained_on": "its scenario's attack", "adversarial": False,
        "threats": dict.fromkeys(THREATS, "held out")}  # fmt: skip
    # trained on its scenario's attack alone, a ramp of the library (a user trial's plant):
    # a ramp differing only in its share is "kind only", the same ramp "within", not
    # "held out"; with the distribution's own, likewise
    from difffilter.threats import Ramp

    own = Ramp(slope=0.005, onset=21, share=0.5)
    assert training_coverage(plain, THREATS, own=own)["threats"] == {
        "bias": "held out", "bias_half_runs": "held out", "ramp": "kind only",
        "replay": "held out", "crafted": "held out"}  # fmt: skip
    same = {"ramp": {"kind": "ramp", "slope": 0.005, "onset": 21, "share": 0.5}}
    assert training_coverage(plain, same, own=own)["threats"] == {"ramp": "within"}
    across = _with_card(tmp_path, {"threats": threats, "scenario": "my_plants:ramp_plant"},
                        {"adversarial_runs": 0})  # own: 0.5  # fmt: skip
    assert training_coverage(across, same, own=own)["threats"] == {"ramp": "within"}
    assert training_coverage(across, same)["threats"] == {"ramp": "kind only"}  # slope drawn
    # a scenario attack of a user's class: a threat of a user's class may be that attack
    # (a user trial's network read "held out" on the scaling attack it was trained on); a
    # library threat is still held out, and against a library own a user's class is too
    mine = {"scale30": {"kind": "my_attacks:Scaling", "alpha": 0.3, "onset": 40},
            "ramp": THREATS["ramp"]}  # fmt: skip
    assert training_coverage(across, mine)["threats"]["scale30"] == "held out"
    (tmp_path / "own").mkdir()
    plain = _with_card(tmp_path / "own", {"threats": None, "scenario": "my_plants:ramp_plant"},
                       {"adversarial_runs": 0})  # fmt: skip
    assert training_coverage(plain, mine, own=object())["threats"] == {
        "scale30": "not known", "ramp": "held out"}  # fmt: skip
    assert training_coverage(plain, mine, own=own)["threats"] == {
        "scale30": "held out", "ramp": "kind only"}  # fmt: skip
    # and so for a distribution whose own (of a user's class) was drawn: it met that attack
    # (it had read "held out" where the same network trained on it alone reads "not known")
    assert training_coverage(across, mine, own=object())["threats"]["scale30"] == "not known"
    card = json.loads(across.with_suffix(".json").read_text())
    card["threats_drawn"] = {"own": 0, "bias": 5, "ramp": 3}  # own never drawn: held out
    across.with_suffix(".json").write_text(json.dumps(card))
    assert training_coverage(across, mine, own=object())["threats"]["scale30"] == "held out"
    # no card beside the file: nothing is claimed
    alone = tmp_path / "alone" / "net.ckpt"
    alone.parent.mkdir()
    shutil.copy(SHIPPED, alone)
    assert training_coverage(alone, THREATS) is None and training_coverage(None, THREATS) is None


def test_the_checkpoint_an_estimator_ran_with_is_its_own_else_the_default_it_used():
    suite = SimpleNamespace(checkpoints={"pf_nn_ekf": {"path": "b.ckpt"}},
                            checkpoint={"path": "a.ckpt", "used_by": ["pf_nn_grad"]})  # fmt: skip
    assert checkpoint_of("pf_nn_ekf", suite) == "b.ckpt"
    assert checkpoint_of("pf_nn_grad", suite) == "a.ckpt"
    assert checkpoint_of("kf_nn_grad", suite) is None
    assert checkpoint_of("pf_nn_grad", SimpleNamespace(checkpoints={}, checkpoint=None)) is None


def test_the_attack_trained_on_is_that_of_the_scenario_the_card_names(tmp_path):
    """A coverage trial: the study's scenario's attack had been credited to the network. The
    shipped four-tank network (trained on four_tank_bias, whose attack is no library threat)
    read "within" on a library bias it never met, studied on a four-tank scenario of one's
    own whose attack that bias is."""
    from difffilter.threats import Bias

    study_attack = Bias(0.5, onset=21)
    same = {"bias": {"kind": "bias", "value": 0.5, "onset": 21}}
    shipped = _with_card(tmp_path, {}, {})  # data_config.scenario: four_tank_bias
    assert training_coverage(shipped, same, own=study_attack)["threats"] == {"bias": "held out"}
    user = _with_card(tmp_path, {"scenario": "my_plants:bias_plant"}, {})  # not registered
    assert training_coverage(user, same, own=study_attack)["threats"] == {"bias": "within"}


def test_a_scenario_file_read_as_trained_unless_gone_or_edited(tmp_path):
    """A review: a card naming a YAML file was read through the registry (a file of the
    study's scenario name collided, and the study's attack was credited) and as it is now
    (edited since, its new attack was credited). It is read itself, and only where its
    digest is the card's; else what it could have covered is "not known"."""
    from difffilter.models.yaml_scenario import scenario_file_digest
    from difffilter.threats import Ramp

    plant = tmp_path / "plant.yaml"
    doc = (
        "name: coverage_plant\nfamily: my_plants\ndescription: a scalar plant\ndt: 0.1\n"
        "runs: 4\nsteps: 20\nnum_particles: 50\nfalse_alarm_rate: 0.01\n"
        "plant: {F: [[0.9]], H: [[1.0]], Q: 1.0e-2, R: 1.0e-2, P0: 1.0e-1}\n"
        "attack: {kind: bias, channel: sensor, value: 0.5, onset: 5}\n"
    )
    plant.write_text(doc, encoding="utf-8")
    card = _with_card(tmp_path, {"scenario": str(plant)}, {})
    meta = json.loads(card.with_suffix(".json").read_text())
    meta["scenario_file_sha256"] = scenario_file_digest(str(plant))
    card.with_suffix(".json").write_text(json.dumps(meta))
    threats = {"bias": {"kind": "bias", "value": 0.5, "onset": 5},
               "other": {"kind": "bias", "value": 0.7, "onset": 5},
               "ramp": {"kind": "ramp", "slope": 0.1, "onset": 5}}  # fmt: skip
    study = Ramp(slope=0.1, onset=5)  # the study's own attack: not what was trained on
    assert training_coverage(card, threats, own=study)["threats"] == {
        "bias": "within", "other": "kind only", "ramp": "held out"}  # fmt: skip
    threats = {"bias": threats["bias"]}
    plant.write_text(doc + "\n# edited\n", encoding="utf-8")  # its digest moves
    assert training_coverage(card, threats)["threats"] == {"bias": "not known"}
    plant.unlink()
    assert training_coverage(card, threats)["threats"] == {"bias": "not known"}


def test_a_card_of_another_versions_distribution_labels_its_threats_not_known(tmp_path):
    """A coverage trial: a distribution this version refuses (a share of 0, written before
    it was refused) had failed the robustness report after the whole study had run."""
    threats = {"own": {"weight": 0.5},
               "off": {"weight": 0.5, "kind": "ramp", "slope": 0.01, "onset": 21,
                       "share": {"randint": [0, 0]}}}  # fmt: skip
    path = _with_card(tmp_path, {"threats": threats}, {})
    with pytest.warns(UserWarning, match="cannot be read by this version .*share is 0"):
        got = training_coverage(path, THREATS)
    assert got["threats"] == dict.fromkeys(THREATS, "not known")


@pytest.mark.parametrize(
    ("threats", "message"),
    [({"bias": {"kind": "bais", "value": 0.5}}, r"threats\['bias'\] must be a mapping whose kind"),
     ({"bias": {"value": 0.5}}, r"threats\['bias'\] must be a mapping whose kind"),
     (["bias"], "threats must be a mapping"),
     ({"bias": "bias"}, r"threats\['bias'\] must be a mapping")],
)  # fmt: skip
def test_bad_threats_are_named(threats, message):
    with pytest.raises(ValueError, match=message):
        training_coverage(SHIPPED, threats)


def test_a_bad_dt_is_named_as_dt():
    with pytest.raises(ValueError, match="dt must be"):
        training_coverage(SHIPPED, {"bias": {"kind": "bias", "value": 0.5}}, dt=-1.0)
