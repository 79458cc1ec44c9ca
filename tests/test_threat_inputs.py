"""The threat library's inputs, from a fuzzing trial: numpy integers taken as integers, a
covert signal's fields drawn at random and counted by ``onsets_past``, a resumed loop past
its attack's table named by ``horizon``, and each bad input named in the library's words
(a threat set made in Python, a generator of the wrong type, a covert attacker's model of
another dtype, a CUSUM calibration without bisections)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter.fdi import CusumDetector
from difffilter.loop import DrawnNoise, closed_loop
from difffilter.threat_distribution import ThreatDistribution
from difffilter.threats import Bias, Covert, Pulses, Ramp, RandomWalk, threat_from_dict

F64 = torch.float64


def _plant(dtype=F64):
    eye = torch.eye(2, dtype=dtype)
    F = torch.tensor([[1.02, 0.1], [0.0, 0.95]], dtype=dtype)
    B = torch.tensor([[0.0], [0.1]], dtype=dtype)
    return df.LinearGaussianModel(F, eye, 0.01 * eye, 0.04 * eye, torch.zeros(2, dtype=dtype),
                                  0.1 * eye, B=B)  # fmt: skip


def test_numpy_integers_are_integers_in_a_threats_window():
    bias = Bias(1.0, onset=np.int64(3), duration=np.int32(4), entries=np.array([0, 2]))
    assert (bias.onset, bias.duration, bias.entries) == (3, 4, (0, 2))
    assert all(type(v) is int for v in (bias.onset, bias.duration, *bias.entries))
    pulses = Pulses(amplitude=1.0, period=np.int64(4), width=np.int64(2))
    assert (pulses.period, pulses.width) == (4, 2) and type(pulses.period) is int
    # the same table as with Python's integers
    plain = Bias(1.0, onset=3, duration=4, entries=(0, 2)).sample(2, 10, 3, dtype=F64)
    assert all(torch.equal(a, b) for a, b in zip(bias.sample(2, 10, 3, dtype=F64), plain))
    with pytest.raises(ValueError, match="entries must be None or a non-empty list of integer"):
        Bias(1.0, entries=[0.5])
    with pytest.raises(ValueError, match="onset must be an integer >= 1; got"):
        Bias(1.0, onset=np.int64(0))


def test_a_kind_that_is_not_a_name_is_named_with_the_valid_ones():
    with pytest.raises(ValueError, match=r"unknown threat kind \['bias'\]; valid: bias"):
        threat_from_dict({"kind": ["bias"]})
    with pytest.raises(ValueError, match=r"threats.b.kind must be one of bias.*got \['bias'\]"):
        ThreatDistribution({"b": {"weight": 1, "kind": ["bias"]}})


def test_a_covert_signal_must_be_shaped_and_is_told_so():
    with pytest.raises(
        ValueError, match="covert threat's signal must be a shaped threat.*'replay'"
    ):
        threat_from_dict({"kind": "covert", "signal": {"kind": "replay", "delay": 2, "onset": 5}},
                         model=_plant())  # fmt: skip


def test_a_covert_signals_fields_may_be_drawn_and_their_onsets_are_counted():
    entry = {"weight": 1, "kind": "covert",
             "signal": {"kind": "bias", "value": {"uniform": [0.1, 0.2]},
                        "onset": {"randint": [40, 50]}}}  # fmt: skip
    dist = ThreatDistribution({"c": entry}, model=_plant())
    g = torch.Generator().manual_seed(0)
    drawn = [dist.sample(g)[1] for _ in range(200)]
    assert all(isinstance(a, Covert) for a in drawn)
    assert {a.signal.onset for a in drawn} == set(range(40, 51))
    assert all(0.1 <= a.signal.value[0] <= 0.2 for a in drawn)
    again = ThreatDistribution({"c": entry}, model=_plant()).sample(
        torch.Generator().manual_seed(0))[1]  # fmt: skip
    assert again == drawn[0]  # reproducible
    assert dist.onsets_past(45) == {"c": pytest.approx(5 / 11)}
    assert dist.onsets_past(50) == {}
    # a signal drawn whole by choice: each option's onset, equally likely
    chosen = ThreatDistribution({"c": {"weight": 1, "kind": "covert", "signal": {"choice": [
        {"kind": "bias", "value": 0.1, "onset": 50}, {"kind": "bias", "value": 0.2, "onset": 60}]}}},
        model=_plant())  # fmt: skip
    assert chosen.onsets_past(30) == {"c": 1.0}  # (it read {} before: every draw is past 30)
    assert chosen.onsets_past(55) == {"c": 0.5}
    # a nested draw is checked at its extremes with the signal's other fields, as a field is
    with pytest.raises(ValueError, match="width must be <= period"):
        ThreatDistribution({"c": {"weight": 1, "kind": "covert", "signal": {
            "kind": "pulses", "period": 10, "width": {"randint": [1, 12]}}}}, model=_plant())  # fmt: skip
    with pytest.raises(ValueError, match=r"threats.c.signal.onset: randint needs lo <= hi"):
        ThreatDistribution({"c": {"weight": 1, "kind": "covert", "signal": {
            "kind": "bias", "onset": {"randint": [9, 5]}}}}, model=_plant())  # fmt: skip


def test_sampling_a_distribution_names_a_generator_of_the_wrong_type():
    dist = ThreatDistribution({"b": {"weight": 1, "kind": "bias"}})
    for wrong in (123, df.Generators.of(torch.Generator())):
        with pytest.raises(TypeError, match="generator must be a torch.Generator"):
            dist.sample(wrong)


def _loop(steps, **kwargs):
    g = torch.Generator().manual_seed(0)
    return closed_loop(_plant(), steps, noise=DrawnNoise(g), **kwargs)


def test_a_loop_resumed_past_its_attacks_table_names_horizon():
    attack = Ramp(0.01, onset=5)
    first = _loop(12, x0=torch.zeros(3, 2, dtype=F64), attack=attack)
    with pytest.raises(ValueError, match=r"horizon: attack Ramp was tabulated for steps 1 … 12.*"
                                         r"horizon=30 or more"):  # fmt: skip
        _loop(18, attack=attack, state=first.state)
    # with the whole loop's horizon at the start, the same resume runs, as one loop would
    first = _loop(12, x0=torch.zeros(3, 2, dtype=F64), attack=attack, horizon=30)
    assert _loop(18, attack=attack, state=first.state).state.k == 30
    covert = Covert(Bias(0.1, channel="actuator"), _plant())
    assert covert.last_step(covert.init(3, 12, 1, dtype=F64)) == 12
    assert RandomWalk(0.1).last_step(RandomWalk(0.1).init(3, 7, 2, dtype=F64)) == 7


def test_a_loops_attack_generator_must_be_a_torch_generator():
    with pytest.raises(TypeError, match="attack_generator must be a torch.Generator or None"):
        _loop(5, x0=torch.zeros(2, 2, dtype=F64), attack=RandomWalk(0.1),
              attack_generator=df.Generators.of(torch.Generator()))  # fmt: skip


def test_a_covert_attackers_model_of_another_dtype_is_converted_for_the_loop():
    """A float64 attacker's model in a float32 loop (a YAML scenario's covert attack is built
    from the float64 plant, and the suite and the training run float32 loops) is a float32
    copy; its concealment is the float64 one's up to float32 round-off. It had stopped every
    float32 loop."""
    plant = _plant(F64)
    covert = Covert(Bias(0.1, channel="actuator", onset=2), plant)
    assert covert.init(2, 5, 1, dtype=F64)[-1] is plant
    x = torch.tensor([[0.3, -0.2], [1.0, 0.5]], dtype=F64)
    u = torch.tensor([[0.1], [-0.4]], dtype=F64)
    hidden = {}
    for dtype in (F64, torch.float32):
        state = covert.init(2, 5, 1, dtype=dtype)
        assert state[-1].F.dtype == dtype
        for k in (1, 2, 3):
            state, value, _ = covert.step(state, k, x=x.to(dtype), u=u.to(dtype))
            state, hidden[dtype] = covert.conceal(state, k, y=None, x=x.to(dtype))
        assert hidden[dtype].dtype == dtype
    assert plant.F.dtype == F64  # the defender's model is left as it is
    assert hidden[F64].abs().max() > 1e-3
    torch.testing.assert_close(hidden[torch.float32].double(), hidden[F64], rtol=1e-5, atol=1e-6)

    class Functions:  # the attacker's model as plain functions: nothing to convert
        initial = plant.initial
        dim_u = 1

        def transition(self, x, u, k):
            return plant.transition(x, u, k)

        def observe(self, x, k):
            return plant.observe(x, k)

    with pytest.raises(ValueError, match="is torch.float64 on cpu and the loop torch.float32 "
                                         "on cpu, and it is not an nn.Module"):  # fmt: skip
        Covert(Bias(0.1, channel="actuator"), Functions()).init(2, 5, 1, dtype=torch.float32)


def test_a_cusum_calibration_names_its_rate_and_its_bisections():
    g = (
        torch.randn(20, 50, 2, generator=torch.Generator().manual_seed(0), dtype=F64)
        .square()
        .sum(-1)
    )
    with pytest.raises(ValueError, match="false_alarm_rate must be a false-alarm rate in"):
        CusumDetector(3.0).calibrate(g, "0.01")
    for wrong in (0, -1):  # (0 bisections returned max Σg: no alarm at all, where 1 % was asked)
        with pytest.raises(ValueError, match="iterations must be a positive integer"):
            CusumDetector(3.0).calibrate(g, 0.01, iterations=wrong)


def test_a_threat_set_made_in_python_names_the_threat_that_does_not_fit_before_any_run():
    from difffilter.eval.robustness import ThreatSet, run_robustness
    from difffilter.models.scenario import CustomScenario

    scenario = CustomScenario(name="mine", family="my_plants", description="a linear plant",
                              model_fn=_plant, attack=Ramp(0.01, onset=20, share=0.5), runs=4,
                              steps=60, dt=0.1, num_particles=50)  # fmt: skip
    threats = ThreatSet({"ok": Bias(0.5, onset=10), "late_one": Bias(0.5, onset=61)}, runs=4,
                        estimators=("chi_square_kf",))  # fmt: skip
    # (it read "scenario 'mine': its attack does not fit", after the calibration had run)
    with pytest.raises(ValueError, match=r"threat 'late_one': it starts at step 61, after the "
                                         r"last step \(60\)"):  # fmt: skip
        run_robustness(scenario, threats, progress=False)


def test_a_yaml_covert_attack_runs_the_suite_in_float32(tmp_path):
    """docs/your-own-plant.md's YAML attack of kind covert, on the float32 suite (the dtype
    of the training): it had stopped on the attacker's float64 model."""
    from difffilter.eval.suite import run_suite
    from difffilter.models.yaml_scenario import scenario_from_yaml

    path = tmp_path / "covert.yaml"
    path.write_text(
        "name: motor_covert\nfamily: my_plants\ndt: 0.01\nruns: 4\nsteps: 40\n"
        "plant:\n  F: [[0.95, 0.04], [-0.02, 0.8]]\n  B: [[0.0], [0.2]]\n  H: [[1.0, 0.0]]\n"
        "  Q: 1.0e-4\n  R: 1.0e-3\n  P0: 1.0e-2\n"
        "inputs: {kind: sinusoid, amplitude: 1.0, frequency: 0.5}\n"
        "attack: {kind: covert, signal: {kind: bias, value: 0.5, onset: 20}}\n"
    )
    scenario = scenario_from_yaml(str(path))
    results = {}
    for dtype in (F64, torch.float32):
        out = run_suite(scenario, runs=4, progress=False, dtype=dtype, estimators=["chi_square_kf"])
        results[dtype] = out.metrics["chi_square_kf"]["state_rmse"]
    assert results[torch.float32] == pytest.approx(results[F64], rel=1e-3)


@pytest.mark.parametrize(
    ("kind", "field", "value"),
    [("bias", "value", [True, 0.5]), ("ramp", "slope", [True]),
     ("ksigma_bias", "sigma", [1.0, True]), ("bias", "value", ["0.5", "1"]),
     ("sinusoid", "amplitude", [0.5, "1"]), ("random_walk", "step_std", [False])],
)  # fmt: skip
def test_a_vector_fields_entries_are_numbers_never_bools_or_strings(kind, field, value):
    # A threat-library trial: each entry went through float(), so YAML's `[yes, 0.5]` was a
    # bias of 1.0 on entry 0 and ["0.5"] a bias of 0.5, where a bare `true` is refused.
    fields = {"kind": kind, field: value, **({"k": 1.0} if kind == "ksigma_bias" else {})}
    with pytest.raises(ValueError, match=f"{field} must be a number or a sequence of numbers"):
        threat_from_dict(fields)


def test_a_vector_fields_entries_may_be_numpy_and_tensor_scalars():
    bias = threat_from_dict({"kind": "bias", "value": [np.float32(0.5), torch.tensor(1.0), 2]})
    assert bias.value == (0.5, 1.0, 2.0)
    assert Bias(np.array([0.5, 1.0])).value == Bias(torch.tensor([0.5, 1.0])).value == (0.5, 1.0)
