"""Training across threats: a distribution over the threat library, drawn per run."""

from __future__ import annotations

import pytest
import torch

from difffilter.models import registry
from difffilter.threat_distribution import (
    HELD_OUT,
    KIND_ONLY,
    WITHIN,
    ThreatDistribution,
    _draw,
)
from difffilter.threats import Bias, Ramp
from difffilter.train.task import ScenarioDataModule, threat_batch, training_batch

MIX = {
    "none": {"weight": 1},
    "bias": {"weight": 3, "kind": "bias", "value": {"uniform": [1.0, 2.0], "signed": True},
             "onset": {"randint": [5, 9]}, "entries": {"choice": [[0], [1, 2]]}},
    "ramp": {"weight": 0, "kind": "ramp", "slope": {"loguniform": [0.01, 0.1]}, "onset": 3},
}  # fmt: skip


def test_threats_come_by_weight_with_their_fields_in_range_and_reproducibly():
    dist = ThreatDistribution(MIX, own="OWN")
    g = torch.Generator().manual_seed(0)
    draws = [dist.sample(g) for _ in range(2000)]
    names = [n for n, _ in draws]
    # Binomial(2000, 3/4): 1500 ± 4 × 19.4; ramp has weight 0
    assert 1422 < names.count("bias") < 1578 and "ramp" not in names
    assert all(a is None for n, a in draws if n == "none")
    biases = [a for n, a in draws if n == "bias"]
    assert all(isinstance(a, Bias) and 1.0 <= abs(a.value[0]) <= 2.0 for a in biases)
    assert 0.4 < sum(a.value[0] > 0 for a in biases) / len(biases) < 0.6  # signed
    assert {a.onset for a in biases} == {5, 6, 7, 8, 9}
    assert {a.entries for a in biases} == {(0,), (1, 2)}
    again = ThreatDistribution(MIX, own="OWN")
    g = torch.Generator().manual_seed(0)
    assert [again.sample(g) for _ in range(2000)] == draws
    ramp = ThreatDistribution(
        {"ramp": {**MIX["ramp"], "weight": 1}, "own": {"weight": 1}}, own="OWN"
    )
    g = torch.Generator().manual_seed(1)
    draws = [ramp.sample(g) for _ in range(400)]
    slopes = [a.slope[0] for n, a in draws if n == "ramp"]
    assert all(0.01 <= s <= 0.1 for s in slopes) and ("own", "OWN") in draws
    # log-uniform: half of the draws below the geometric mean √(0.01 · 0.1)
    assert 0.4 < sum(s < 0.1**1.5 for s in slopes) / len(slopes) < 0.6


def test_every_threat_the_distribution_draws_is_within_it_and_others_are_named():
    dist = ThreatDistribution(MIX)
    g = torch.Generator().manual_seed(3)
    for _ in range(300):  # the fields exactly as sample() draws them
        drawn = {k: _draw(v, g) for k, v in MIX["bias"].items() if k != "weight"}
        assert dist.covers(drawn) == WITHIN, drawn
    bias = {"kind": "bias", "value": 1.5, "onset": 7, "entries": [0]}
    assert dist.covers(bias) == WITHIN
    assert dist.covers({**bias, "value": -2.0}) == WITHIN  # signed: the magnitude counts
    assert dist.covers({**bias, "value": [1.5, 1.5], "entries": [1, 2]}) == WITHIN
    for other in [{"value": 2.5}, {"value": 0.5}, {"onset": 10}, {"onset": 6.5},
                  {"entries": [2]}, {"entries": None}, {"share": 0.5}, {"duration": 40},
                  {"value": [1.5, 1.2], "entries": [1, 2]}]:  # fmt: skip
        assert dist.covers({**bias, **other}) == KIND_ONLY, other
    without_entries = {k: v for k, v in bias.items() if k != "entries"}
    assert dist.covers(without_entries) == KIND_ONLY  # all entries: not among the choices
    # a kind drawn with weight 0, or never: held out
    assert dist.covers({"kind": "ramp", "slope": 0.05, "onset": 3}) == HELD_OUT
    assert dist.covers({"kind": "pulses", "amplitude": 1.0}) == HELD_OUT
    ramp = ThreatDistribution({"ramp": {**MIX["ramp"], "weight": 1}})
    assert ramp.covers({"kind": "ramp", "slope": 0.05, "onset": 3}) == WITHIN
    assert ramp.covers({"kind": "ramp", "slope": -0.05, "onset": 3}) == KIND_ONLY  # unsigned
    assert ramp.covers({"kind": "ramp", "slope": 0.05}) == KIND_ONLY  # onset defaults to 1
    # a signed range of negative numbers draws [lo, hi] and its negative (a trial: 0.5 and
    # -0.5 read "kind only" under [-1, -0.2], signed)
    negative = ThreatDistribution({"b": {"weight": 1, "kind": "bias",
                                         "value": {"uniform": [-1.0, -0.2], "signed": True}}})  # fmt: skip
    assert [negative.covers({"kind": "bias", "value": v}) for v in (0.5, -0.5, 0.1, -1.5)] == [
        WITHIN, WITHIN, KIND_ONLY, KIND_ONLY]  # fmt: skip


def test_every_entry_listed_is_the_attack_on_every_entry_where_the_model_says_how_many():
    """A trial: entries [0, 1, 2, 3] against a component of entries null (all four, the
    same attack on the four-tank's sensors) read "kind only"."""
    from difffilter.models import registry

    model = registry.get("four_tank_bias").system()
    every = ThreatDistribution({"b": {"weight": 1, "kind": "bias", "value": 0.5}}, model=model)
    assert every.covers({"kind": "bias", "value": 0.5, "entries": [0, 1, 2, 3]}) == WITHIN
    assert every.covers({"kind": "bias", "value": 0.5, "entries": [0]}) == KIND_ONLY
    chosen = ThreatDistribution({"b": {"weight": 1, "kind": "bias", "value": 0.5,
                                       "entries": {"choice": [[0], None]}}}, model=model)  # fmt: skip
    assert chosen.covers({"kind": "bias", "value": 0.5, "entries": [0, 1, 2, 3]}) == WITHIN
    assert chosen.covers({"kind": "bias", "value": 0.5}) == WITHIN
    assert chosen.covers({"kind": "bias", "value": 0.5, "entries": [2]}) == KIND_ONLY


@pytest.mark.parametrize(
    ("spec", "why"),
    [
        ({}, "non-empty mapping"),
        ({"bias": {"kind": "bias"}}, r"threats.bias: needs a mapping with a weight"),
        ({"bias": {"weight": -1, "kind": "bias"}}, r"threats.bias.weight must be a finite number >= 0"),
        ({"bias": {"weight": float("inf"), "kind": "bias"}}, r"threats.bias.weight must be a finite"),
        # every random field is checked at its extremes, not only at one draw
        ({"b": {"weight": 1, "kind": "bias", "onset": {"randint": [0, 100]}}}, r"threats.b: onset must be an integer >= 1"),
        ({"b": {"weight": 1, "kind": "pulses", "width": {"choice": [2, 9]}, "period": 5}}, r"threats.b: .*width"),
        ({"b": {"weight": 1, "kind": "chirp", "f0": {"uniform": [0.01, 0.1], "signed": True}}}, "f0 must be a finite number >="),
        ({"x": {"weight": 1, "kind": "teleport"}}, r"threats.x.kind must be one of"),
        ({"own": {"weight": 1, "value": 2}}, "reserved name 'own' takes a weight only"),
        ({"b": {"weight": 1, "kind": "bias", "value": {"uniform": [2, 1]}}}, r"threats.b.value: uniform needs lo <= hi"),
        ({"b": {"weight": 1, "kind": "bias", "onset": {"randint": [1.5, 3]}}}, "as integers"),
        ({"b": {"weight": 1, "kind": "bias", "value": {"uniform": [1, 2], "sine": 1}}}, "a random field is one of"),
        ({"b": {"weight": 1, "kind": "bias", "speed": 3}}, r"threats.b: threat 'bias' has no field\(s\) speed"),
        ({"b": {"weight": 0, "kind": "bias"}}, "must not all be 0"),
        ({"b": {"weight": 1, "kind": "bias", "value": {"uniform": [1, 2], "signed": "no"}}},
         r"threats.b.value: signed must be true or false; got 'no'"),
        # two random fields that constrain each other, at their extremes together (one at a
        # time, 26 of 500 draws of the replay failed at sampling, mid-training)
        ({"r": {"weight": 1, "kind": "replay", "delay": {"randint": [1, 20]}, "onset": {"randint": [15, 40]}}},
         r"threats.r: onset must exceed delay"),
        ({"p": {"weight": 1, "kind": "pulses", "period": {"randint": [4, 10]}, "width": {"randint": [1, 6]}}},
         r"threats.p: width must be <= period"),
    ],
)  # fmt: skip
def test_a_bad_distribution_names_the_threat_and_the_field(spec, why):
    with pytest.raises(ValueError, match=why):
        ThreatDistribution(spec)


@pytest.mark.parametrize(
    "threat, why",
    [
        ({"kind": "bias", "value": 0.5, "entries": {"choice": [[0], [7]]}},
         r"threats.x: entries \(7,\) name entries beyond the channel's 4"),
        ({"kind": "bias", "value": [0.1, 0.2]}, r"threats.x: value has 2 entries; the channel has 4"),
    ],
)  # fmt: skip
def test_a_threat_that_does_not_fit_the_model_is_named_at_construction(threat, why):
    """With the model given, entries and widths are checked against its channels now, not
    when a training batch first tabulates the attack."""
    from difffilter.models.four_tank import FourTankModel

    model = FourTankModel()  # dy = 4
    with pytest.raises(ValueError, match=why):
        ThreatDistribution({"x": {"weight": 1, **threat}}, model=model)
    ThreatDistribution({"x": {"weight": 1, **threat}})  # without the model it cannot know


def test_a_threat_batch_gives_each_run_its_own_threat_and_the_test_keeps_the_scenarios():
    from difffilter.models import registry

    scenario = registry.get("four_tank_bias")
    dist = ThreatDistribution(MIX, model=scenario.system(), own=scenario.threat)
    batch = threat_batch(scenario, dist, 40, seed=11, dtype=torch.float64)
    assert batch["attack"].shape == (40, 100, 4) and batch["flags"].shape == (40, 100)
    g = torch.Generator()
    g.manual_seed(__import__("difffilter").models.streams.Streams(11).seed_of("threats"))
    expected = [dist.sample(g) for _ in range(40)]
    for i, (name, attack) in enumerate(expected):
        a, flags = batch["attack"][i], batch["flags"][i]
        if name == "none":
            assert not flags.any() and not a.any()
            continue
        k0 = attack.onset - 1  # the 1-based onset's column
        assert not flags[:k0].any() and flags[k0:].all()
        want = torch.zeros(4, dtype=torch.float64)
        want[list(attack.entries)] = attack.value[0]
        assert torch.equal(a[k0:], want.expand(100 - k0, 4)) and not a[:k0].any()
    assert torch.equal(
        threat_batch(scenario, dist, 40, 11, torch.float64)["y_recv"], batch["y_recv"]
    )

    dm = ScenarioDataModule("four_tank_bias", val_runs=8, test_runs=3, threats=MIX)
    val = dm.val_dataloader().dataset[0]
    torch.testing.assert_close(val["x"], threat_batch(scenario, dist, 8, 2, torch.float32)["x"])
    test = dm.test_dataloader().dataset[0]  # the scenario's own attack, the evaluation's runs
    torch.testing.assert_close(
        test["attack"], training_batch(scenario, 3, 0, torch.float32)["attack"]
    )
    with pytest.raises(ValueError, match="threats: lfc_step is a closed-loop scenario"):
        ScenarioDataModule(
            "lfc_step", threats={"ramp": {"weight": 1, "kind": "ramp", "slope": 0.1}}
        )
    assert isinstance(
        ThreatDistribution({"r": {"weight": 1, "kind": "ramp", "slope": 0.1}}).sample(g)[1], Ramp
    )


@pytest.mark.parametrize(
    "scenario_name, width", [("four_tank_bias", 4), ("robot_actuator_attack", 2)]
)
def test_a_batch_of_attack_free_runs_records_zeros_as_wide_as_the_scenarios_attack(
    scenario_name, width
):
    """Every run of a batch drawn attack-free (``none``: a likely batch when ``none`` has a
    large weight) records the attack as zeros on the entries the scenario's own attack takes
    (the sensors; the robot's inputs), which the estimator's attack estimate is compared with
    (once, with no channels, the training loss failed on it)."""
    from difffilter.models import registry

    scenario = registry.get(scenario_name)
    dist = ThreatDistribution({"none": {"weight": 1}}, model=scenario.system(),
                              own=scenario.threat)  # fmt: skip
    batch = threat_batch(scenario, dist, 3, seed=5, dtype=torch.float64)
    assert batch["attack"].shape == (3, scenario.steps, width)
    assert not batch["attack"].any() and not batch["flags"].any()


def test_onsets_past_the_horizon_are_counted_and_the_data_module_warns():
    """A component whose 1-based onset can exceed the horizon acts on nothing in those
    draws (its runs train attack-free): ``onsets_past`` gives the share of such draws, the
    same share that sampling finds, and a data module with a shortened horizon warns."""
    spec = {
        **MIX,  # bias onsets 5…9; the ramp has weight 0 (never drawn: not named)
        "pick": {"weight": 1, "kind": "ramp", "slope": 0.1, "onset": {"choice": [2, 7, 8, 9]}},
        "late": {"weight": 1, "kind": "ramp", "slope": 0.1, "onset": 12},
        "early": {"weight": 1, "kind": "ramp", "slope": 0.1},  # the class default, onset 1
    }
    dist = ThreatDistribution(spec)
    assert dist.onsets_past(6) == {"bias": 3 / 5, "pick": 3 / 4, "late": 1.0}
    assert dist.onsets_past(9) == {"late": 1.0} and dist.onsets_past(12) == {}
    g = torch.Generator().manual_seed(4)
    draws = [dist.sample(g) for _ in range(3000)]
    for name, share in dist.onsets_past(6).items():
        onsets = [a.onset for n, a in draws if n == name]
        assert abs(sum(o > 6 for o in onsets) / len(onsets) - share) < 0.05, name

    with pytest.warns(UserWarning, match=r"threats\.bias: 60% of its onsets fall after"):
        short = ScenarioDataModule("four_tank_bias", val_runs=2, test_runs=1, steps=6, threats=MIX)
    batch = short.train_batch(0, 0)  # drawn as warned: the late onsets' runs attack-free
    assert batch["flags"].shape[-1] == 6 and not bool(batch["flags"].all())
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the full horizon: nothing to say
        ScenarioDataModule("four_tank_bias", val_runs=2, test_runs=1, threats=MIX)
    # every onset past the horizon, or a share of 0: the entry never acts (a trial's such
    # entries trained nothing and were listed on the card as trained on)
    with pytest.warns(UserWarning, match=r"threats\.late: 100% of its onsets.*a fit refuses it"):
        late = ScenarioDataModule("four_tank_bias", val_runs=2, test_runs=1, steps=9,
                                  threats={"late": spec["late"]})  # fmt: skip
    late.test_dataloader()  # a test reads the scenario's own attack: nothing refused
    # some onsets past the horizon: warned (without "a fit refuses it"), and a fit trains
    with pytest.warns(UserWarning, match=r"threats\.bias: 60% of its onsets") as said:
        short = ScenarioDataModule("four_tank_bias", val_runs=2, test_runs=1, steps=6,
                                   threats=MIX)  # fmt: skip
    assert not any("a fit refuses it" in str(w.message) for w in said)
    short.train_dataloader()
    with pytest.raises(ValueError, match=r"threats\.late: every onset falls after the last of "
                       r"the 9 steps, so it never acts"):  # fmt: skip
        late.train_dataloader()
    for never in (0, {"choice": [0, 0.0]}, {"uniform": [0, 0]}):  # (drawn zeros: a review)
        with pytest.raises(
            ValueError, match=r"threats\.half\.share is 0: the threat attacks no run"
        ):
            ThreatDistribution(
                {"half": {"weight": 1, "kind": "bias", "value": 0.5, "share": never}}
            )
    ThreatDistribution({"half": {"weight": 1, "kind": "bias", "value": 0.5,
                                 "share": {"choice": [0, 0.5]}}})  # some draws act  # fmt: skip
    ThreatDistribution({"off": {"weight": 0, "kind": "bias", "value": 0.5, "share": 0},
                        "none": {"weight": 1}})  # (weight 0: never drawn, nothing to say)  # fmt: skip


def test_a_covert_entry_acts_from_its_signals_onset():
    """A covert attack has no onset of its own: it acts from its signal's, which
    ``onsets_past`` reads (it had passed a covert entry whose signal began after the
    horizon: its runs trained attack-free, listed as trained on)."""
    from difffilter.models import registry

    model = registry.get("lfc_step").system()
    signal = {"kind": "bias", "value": 0.01, "entries": [0], "channel": "actuator"}
    dist = ThreatDistribution({
        "late": {"weight": 1, "kind": "covert", "signal": {**signal, "onset": 300}},
        "drawn": {"weight": 1, "kind": "covert", "signal": signal},  # the class default, 1
    }, model=model)  # fmt: skip
    assert dist.onsets_past(299) == {"late": 1.0}
    assert dist.onsets_past(300) == {}


def test_a_horizon_shorter_than_the_scenarios_own_attack_is_refused(isolated_registry):
    """A user trial shortened the horizon below the attack's onset: the runs trained
    attack-free, then Lightning failed at validation ("could not find the monitored key
    val/auc"). Training across threats warns instead (the test above)."""
    from conftest import constant_velocity

    from difffilter.models import registry
    from difffilter.models.scenario import CustomScenario
    from difffilter.threats import Bias
    from difffilter.train.task import ScenarioDataModule

    registry.register(CustomScenario(
        name="late_bias", family="custom", description="a bias from step 10", steps=30,
        model_fn=lambda dtype: constant_velocity(dtype=dtype), attack=Bias(1.0, onset=10),
    ))  # fmt: skip
    with pytest.raises(
        ValueError,
        match=r"steps=9: scenario 'late_bias''s attack does not fit .* starts at step 10",
    ):
        ScenarioDataModule("late_bias", val_runs=2, steps=9)
    assert ScenarioDataModule("late_bias", val_runs=2, steps=10).scenario.steps == 10


def test_a_misspelt_weight_or_draw_and_an_integer_drawn_as_a_float_say_what_to_write():
    """A training-distribution trial: ``wieght`` gave "needs a mapping with a weight" and
    ``unifrom`` "value must be a number or a sequence of numbers", naming neither slip; an
    onset drawn with ``uniform`` gave one drawn value, "must be an integer", and no way on."""
    bias = {"kind": "bias", "value": 0.5}
    with pytest.raises(ValueError, match=r"needs a mapping with a weight \(did you mean 'weight' "
                       r"for 'wieght'\?\)"):  # fmt: skip
        ThreatDistribution({"b": {"wieght": 1, **bias}})
    with pytest.raises(ValueError, match=r"threats\.b\.value: a mapping is a random draw, one of "
                       r"\{uniform\|loguniform\|randint\|choice: \.\.\.\} \(did you mean 'uniform' for "
                       r"'unifrom'\?\)"):  # fmt: skip
        ThreatDistribution({"b": {"weight": 1, "kind": "bias", "value": {"unifrom": [0.1, 0.2]}}})
    with pytest.raises(ValueError, match=r"onset must be an integer >= 1; got .* \(an integer "
                       r"field is drawn with randint: \[first, last\], both included\)"):  # fmt: skip
        ThreatDistribution({"b": {"weight": 1, **bias, "onset": {"uniform": [5, 20]}}})
    with pytest.raises(ValueError, match=r"onset must be an integer >= 1; got 2\.5$"):
        # (a constant onset beside another field drawn with uniform: no hint about draws)
        ThreatDistribution({"b": {"weight": 1, "kind": "bias", "value": {"uniform": [0.1, 0.2]},
                                  "onset": 2.5}})  # fmt: skip
    # no hint where nothing is near, nor randint for a choice of non-integers (a mutation
    # review: every misspelt key had passed with a guess, and every draw with randint's)
    with pytest.raises(ValueError, match="needs a mapping with a weight") as raised:
        ThreatDistribution({"b": bias})
    assert "did you mean" not in str(raised.value)
    with pytest.raises(ValueError, match="onset must be an integer") as raised:
        ThreatDistribution({"b": {"weight": 1, **bias, "onset": {"choice": [2.5, 3.5]}}})
    assert "randint" not in str(raised.value)
    # a mapping with a kind is a threat, not a misspelt draw: covert's signal (a review)
    robot = registry.get("robot_actuator_attack_turn_rates")
    covert = {"weight": 1, "kind": "covert",
              "signal": {"kind": "bias", "value": 0.01, "entries": [0], "onset": 3}}  # fmt: skip
    name, attack = ThreatDistribution({"cov": covert}, model=robot.system()).sample(
        torch.Generator().manual_seed(0))  # fmt: skip
    assert name == "cov" and type(attack).__name__ == "Covert"


def test_every_training_threat_must_attack_the_side_of_the_scenarios_own_attack(
    isolated_registry,
):
    """A user trial trained an actuator network (the scenario's attack on the input) across
    a distribution with a sensor bias: accepted, the own runs' targets zeroed and the sensor
    values given to the input network where the widths agreed, or a raw IndexError at
    validation where they did not. An entry on the other side (a channel drawn by choice
    too) is refused, naming it; one on the same side (a replacement beside a sensor attack)
    is taken."""
    from difffilter.models.scenario import CustomScenario

    registry.register(CustomScenario(
        name="input_bias", family="custom", description="d", steps=20, model_fn=_two_states_one_input,
        attack=Bias(2.0, channel="actuator", onset=5),
    ))  # fmt: skip
    sensor = {"own": {"weight": 0.5}, "sens": {"weight": 0.5, "kind": "bias", "value": 0.4}}
    with pytest.raises(ValueError, match=r"threats.sens: a sensor attack, and input_bias's own "
                                         r"attack is on the inputs \(actuator\)"):  # fmt: skip
        ScenarioDataModule("input_bias", val_runs=2, threats=sensor)
    either = {"own": {"weight": 0.5}, "mix": {"weight": 0.5, "kind": "bias", "value": 0.4,
                                              "channel": {"choice": ["actuator", "sensor"]}}}  # fmt: skip
    with pytest.raises(ValueError, match="threats.mix: a sensor attack"):
        ScenarioDataModule("input_bias", val_runs=2, threats=either)
    inputs = {"own": {"weight": 0.5},
              "ramp": {"weight": 0.5, "kind": "ramp", "slope": 0.1, "channel": "actuator"}}  # fmt: skip
    ScenarioDataModule("input_bias", val_runs=2, threats=inputs)
    registry.register(CustomScenario(
        name="sensor_bias", family="custom", description="d", steps=20, model_fn=_two_states_one_input,
        attack=Bias(2.0, onset=5),
    ))  # fmt: skip
    with pytest.raises(ValueError, match=r"threats.ramp: an actuator attack, and sensor_bias's "
                                         r"own attack is on the measurements"):  # fmt: skip
        ScenarioDataModule("sensor_bias", val_runs=2, threats=inputs)
    replay = {"own": {"weight": 0.5}, "rep": {"weight": 0.5, "kind": "replay", "delay": 3,
                                              "onset": 8}}  # fmt: skip
    ScenarioDataModule("sensor_bias", val_runs=2, threats=replay)


def test_training_threats_read_the_scenarios_sampling_period(isolated_registry):
    """A review: a sinusoid's ``omega`` in a training distribution had been read per step
    on a scenario of ``dt = 0.01`` (a zero signal with its flags set) while the robustness
    study read it in the scenario's time unit. Training reads the scenario's ``dt`` too,
    unless the entry sets its own; a covert signal drawn by choice as well."""
    from difffilter.models.scenario import CustomScenario

    registry.register(CustomScenario(
        name="fast_sampled", family="custom", description="d", steps=20, model_fn=_two_states_one_input,
        attack=Bias(2.0, onset=5), dt=0.01,
    ))  # fmt: skip
    spec = {"own": {"weight": 0.5},
            "sine": {"weight": 0.3, "kind": "sinusoid", "omega": 3.14159, "onset": 5},
            "own_dt": {"weight": 0.2, "kind": "chirp", "dt": 0.5, "onset": 5}}  # fmt: skip
    dm = ScenarioDataModule("fast_sampled", val_runs=2, threats=spec)
    assert dm.threats.spec["sine"]["dt"] == 0.01 and dm.threats.spec["own_dt"]["dt"] == 0.5
    assert dm.hparams["threats"] == spec  # recorded as given (a resume compares those)
    from difffilter.threats import with_sampling_period

    covert = {"kind": "covert", "signal": {"choice": [{"kind": "sinusoid"}, {"kind": "bias"}]}}
    timed = with_sampling_period(covert, 0.01)["signal"]["choice"]
    assert timed[0]["dt"] == 0.01 and "dt" not in timed[1]


def _two_states_one_input(dtype):
    """A two-state plant, both states measured, one input: the scenarios of the tests of
    the side and the sampling period of training threats."""
    import difffilter as df

    eye = torch.eye(2, dtype=dtype)
    return df.LinearGaussianModel(0.9 * eye, eye, 1e-3 * eye, 1e-2 * eye, torch.zeros(2, dtype=dtype),
                                  1e-2 * eye, B=torch.ones(2, 1, dtype=dtype))  # fmt: skip


def test_own_past_the_horizon_is_warned_and_refused_as_the_same_library_entry_is(
    isolated_registry,
):
    """A red-team trial: ``own`` whose attack starts past a shortened horizon was neither
    warned about nor refused (every ``own`` run trained attack-free, counted as ``own``),
    and ``own`` on a scenario without an attack was ``none`` under another name. Truth: the
    same attack written as a library entry, which is warned about and refused by a fit."""
    import warnings

    from conftest import constant_velocity

    from difffilter.models.scenario import CustomScenario

    registry.register(CustomScenario(
        name="late_bias", family="custom", description="a bias from step 10", steps=30,
        model_fn=lambda dtype: constant_velocity(dtype=dtype), attack=Bias(1.0, onset=10),
    ))  # fmt: skip
    said = {}
    for name, entry in (("own", {"weight": 1}),
                        ("b", {"weight": 1, "kind": "bias", "value": 1.0, "onset": 10})):  # fmt: skip
        with pytest.warns(UserWarning) as w:
            dm = ScenarioDataModule("late_bias", val_runs=2, steps=9,
                                    threats={name: entry, "none": {"weight": 1}})  # fmt: skip
        said[name] = [str(x.message).replace(f"threats.{name}:", "") for x in w]
        with pytest.raises(ValueError, match=rf"threats\.{name}: every onset falls after the "
                           r"last of the 9 steps, so it never acts"):  # fmt: skip
            dm.train_dataloader()
    assert said["own"] == said["b"] and "100% of its onsets" in said["own"][0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # onset 10 within 10 steps: nothing to say
        ScenarioDataModule("late_bias", val_runs=2, steps=10,
                           threats={"own": {"weight": 1}}).train_dataloader()  # fmt: skip
    assert registry.get("four_tank_filters").attack_model() is None
    with pytest.raises(ValueError, match=r"threats\.own: scenario 'four_tank_filters' has no "
                       r"attack of its own"):  # fmt: skip
        ScenarioDataModule("four_tank_filters", val_runs=2, steps=20,
                           threats={"own": {"weight": 1}, "none": {"weight": 1}})  # fmt: skip
    ScenarioDataModule("four_tank_filters", val_runs=2, steps=20,  # weight 0: never drawn
                       threats={"own": {"weight": 0}, "none": {"weight": 1}})  # fmt: skip


def test_a_share_of_zero_is_refused_however_it_is_written():
    """A red-team trial: ``share: {randint: [0, 0]}`` and a covert signal's ``share: 0``
    (every draw attacks no run) passed where ``share: 0`` is refused."""
    robot = registry.get("robot_actuator_attack_turn_rates").system()  # covert: inputs
    bias = {"kind": "bias", "value": 0.1}
    cases = {
        "b.share": {"kind": "bias", "value": 0.5, "share": {"randint": [0, 0]}},
        "b.signal.share": {"kind": "covert", "signal": {**bias, "share": 0}},
        "b.signal.share ": {"kind": "covert", "signal": {**bias, "share": {"choice": [0]}}},
        "b.signal.share  ": {"kind": "covert", "signal": {"choice": [
            {**bias, "share": 0}, {"kind": "ramp", "slope": 0.01, "share": {"randint": [0, 0]}}]}},
    }  # fmt: skip
    for where, entry in cases.items():
        with pytest.raises(ValueError, match=rf"threats\.{where.strip()} is 0: the threat "
                           r"attacks no run"):  # fmt: skip
            ThreatDistribution({"b": {"weight": 1, **entry}}, model=robot)
    # some draw acts: accepted (one signal of a choice with a share above 0, randint to 1)
    ThreatDistribution({"b": {"weight": 1, "kind": "covert", "signal": {"choice": [
        {**bias, "share": 0}, bias]}}}, model=robot)  # fmt: skip
    ThreatDistribution({"b": {"weight": 1, "kind": "bias", "value": 0.5,
                              "share": {"randint": [0, 1]}}}, model=robot)  # fmt: skip


def test_a_bad_signal_option_is_refused_whatever_its_place_in_the_choice():
    """A red-team trial: an integer field drawn by ``uniform`` in one option of a covert
    signal's ``choice`` passed construction when the check's one draw picked the other
    option, then failed at a later ``sample``. Truth: the order of a choice's options
    cannot change whether it is valid; the top-level analog is refused."""
    robot = registry.get("robot_actuator_attack_turn_rates").system()
    bias = {"kind": "bias", "value": 0.1, "onset": {"randint": [20, 40]}}
    ramp = {"kind": "ramp", "slope": 0.01, "onset": {"uniform": [20, 40]}}
    with pytest.raises(ValueError, match=r"threats\.r.*onset must be an integer"):
        ThreatDistribution({"r": {"weight": 1, **ramp}}, model=robot)
    for options in ([bias, ramp], [ramp, bias]):
        with pytest.raises(ValueError, match=r"threats\.c.*onset must be an integer"):
            ThreatDistribution({"c": {"weight": 1, "kind": "covert",
                                      "signal": {"choice": options}}}, model=robot)  # fmt: skip


def test_randint_bounds_beyond_int64_are_refused_and_a_huge_onset_is_checked_cheaply():
    """A red-team trial: ``randint: [1, 2**63 - 1]`` failed in torch's words ("Overflow
    when unpacking long long"), naming nothing, and an onset range to 2**62 made the
    construction check tabulate one run to its onset (7e18 bytes)."""
    from difffilter.threats import check_attack_fits

    four_tank = registry.get("four_tank_bias").system()
    for bounds in ([1, 2**63 - 1], [-(2**63) - 1, 3]):
        with pytest.raises(ValueError, match=r"threats\.a\.onset: randint needs .*int64"):
            ThreatDistribution({"a": {"weight": 1, "kind": "bias", "value": 0.5,
                                      "onset": {"randint": bounds}}}, model=four_tank)  # fmt: skip
    top = 2**63 - 2  # the largest hi that torch.randint(lo, hi + 1) takes
    assert _draw({"randint": [top, top]}, torch.Generator().manual_seed(0)) == top
    late = ThreatDistribution({"a": {"weight": 1, "kind": "bias", "value": 0.5,
                                     "onset": {"randint": [1, 2**62]}}}, model=four_tank)  # fmt: skip
    assert late.onsets_past(60) == {"a": (2**62 - 60) / 2**62}
    # a huge onset still has its width checked: 2 values on the 4 measurements
    with pytest.raises(ValueError, match=r"value has 2 entries; the channel has 4"):
        check_attack_fits(Bias([0.1, 0.2], onset=10**12), four_tank)
    with pytest.raises(ValueError, match=r"entries \(5,\) name entries beyond"):
        check_attack_fits(Bias(0.1, entries=[5], onset=2**62), four_tank)
    check_attack_fits(Bias(0.1, onset=2**62), four_tank)  # fits: nothing tabulated to 2**62


def test_covers_reads_entries_as_a_set():
    """A red-team trial: ``entries: [3, 2]`` read "kind only" where the distribution draws
    ``[2, 3]``, the same attack. Truth: the two attacks' tables are identical, so their
    labels are too; in either order on either side."""
    from difffilter.threats import threat_from_dict

    four_tank = registry.get("four_tank_bias").system()
    specs = [{"kind": "bias", "value": 0.5, "entries": e, "onset": 10} for e in ([2, 3], [3, 2])]
    tables = [threat_from_dict(s).sample((1,), 20, 4, torch.Generator().manual_seed(0),
                                         dtype=torch.float64) for s in specs]  # fmt: skip
    assert all(torch.equal(a, b) for a, b in zip(*tables))
    for drawn in ({"choice": [[2, 3], None]}, {"choice": [[3, 2]]}, [3, 2]):
        for model in (four_tank, None):
            dist = ThreatDistribution({"b": {"weight": 1, "kind": "bias", "value": {
                "uniform": [0.1, 1.0]}, "entries": drawn, "onset": {"randint": [5, 60]}}},
                model=model)  # fmt: skip
            assert [dist.covers(s) for s in specs] == [WITHIN, WITHIN], (drawn, model)
            assert dist.covers({**specs[0], "entries": [2]}) == KIND_ONLY
