"""A scenario whose known inputs are lost on the way to the actuators (YAML ``input_loss``,
``CustomScenario.input_loss``): parsed and checked by the file, drawn from its own seed
stream, and what the estimators are given."""

from __future__ import annotations

import dataclasses
import textwrap
from pathlib import Path

import pytest
import torch

from difffilter.input_loss import InputLossSchedule, OnLoss
from difffilter.models.schedules import BurstLoss, PacketLoss
from difffilter.models.streams import Streams
from difffilter.models.yaml_scenario import scenario_from_dict, scenario_from_yaml

MOTOR = {
    "name": "motor_lossy",
    "runs": 6,
    "steps": 40,
    "dt": 0.01,
    "plant": {
        "F": [[0.95, 0.04], [-0.02, 0.8]],
        "B": [[0.0], [0.2]],
        "H": [[1.0, 0.0]],
        "Q": 1.0e-4,
        "R": 1.0e-3,
        "P0": 1.0e-2,
    },  # fmt: skip
    "inputs": {"kind": "sinusoid", "amplitude": 1.0, "frequency": 2.0},
}


def _with(**fields):
    return scenario_from_dict({**MOTOR, **fields}, "motor.yaml")


def test_the_yaml_field_is_an_input_loss_schedule(tmp_path):
    path = tmp_path / "motor.yaml"
    path.write_text(
        textwrap.dedent("""
        name: motor_lossy
        plant: {F: [[0.95, 0.04], [-0.02, 0.8]], B: [[0.0], [0.2]], H: [[1.0, 0.0]],
                Q: 1.0e-4, R: 1.0e-3}
        inputs: {kind: constant, value: 1.0}
        input_loss: {kind: burst_loss, to_bad: 0.1, to_good: 0.3, on_loss: zero,
                     acknowledged: false}
    """)
    )
    loss = scenario_from_yaml(path).input_loss_schedule()
    assert loss == InputLossSchedule(BurstLoss(to_bad=0.1, to_good=0.3), OnLoss.ZERO, False)
    assert _with().input_loss_schedule() is None
    default = _with(input_loss={"kind": "packet_loss", "rate": 0.2}).input_loss
    assert default.on_loss is OnLoss.HOLD and default.acknowledged is True


@pytest.mark.parametrize("spec, why", [
    ({"kind": "all"}, "must be {kind: packet_loss"),
    ("packet_loss", "must be {kind: packet_loss"),
    ({"kind": "packet_loss"}, "packet_loss needs rate"),
    ({"kind": "packet_loss", "rate": 1.5}, "rate must be a number in"),
    ({"kind": "packet_loss", "rate": 0.1, "on_loss": "drop"}, "'drop' is not a OnLoss"),
    ({"kind": "packet_loss", "rate": 0.1, "acknowledged": "yes"}, "acknowledged must be"),
    ({"kind": "packet_loss", "rate": 0.1, "packets": [[0, 1]]}, "the plant's 1 input(s), not its measurements"),
    ({"kind": "packet_loss", "rate": 0.1, "delay": 2}, "unknown field"),
])  # fmt: skip
def test_a_bad_input_loss_is_named_with_the_file_and_the_field(spec, why):
    with pytest.raises(ValueError, match="motor.yaml: input_loss") as error:
        _with(input_loss=spec)
    assert why in str(error.value)


def test_a_plant_without_inputs_has_none_to_lose():
    plant = {k: v for k, v in MOTOR["plant"].items() if k != "B"}
    with pytest.raises(ValueError, match="no input to lose"):
        _with(plant=plant, inputs=None, input_loss={"kind": "packet_loss", "rate": 0.1})


def test_the_scenario_draws_the_arrivals_from_their_own_stream():
    """The arrivals come from the stream "input_schedule": a rate of zero leaves every other
    draw (plant noise, sensor schedule) as the scenario without input loss has it."""
    lossy = _with(input_loss={"kind": "packet_loss", "rate": 0.4})
    tr = lossy.simulate(6, Streams(3).simulation())
    expected = PacketLoss(0.4).mask((6,), 40, 1, Streams(3)("input_schedule"))
    assert torch.equal(tr.info["input_mask"], expected)
    applied = tr.info["inputs_applied"]
    torch.testing.assert_close(tr.us, applied, rtol=0, atol=0)  # acknowledged, no attack
    sent = lossy.inputs(6, torch.float64)
    assert not torch.equal(applied, sent)
    lost = ~expected[:, 1:, 0]
    assert torch.equal(applied[:, 1:][lost], applied[:, :-1][lost])  # held
    plain = _with().simulate(6, Streams(3).simulation())
    never = _with(input_loss={"kind": "packet_loss", "rate": 0.0}).simulate(
        6, Streams(3).simulation()
    )
    assert torch.equal(plain.x, never.x) and torch.equal(plain.y_recv, never.y_recv)
    udp = _with(input_loss={"kind": "packet_loss", "rate": 0.4, "acknowledged": False})
    tr_udp = udp.simulate(6, Streams(3).simulation())
    assert torch.equal(tr_udp.x, tr.x) and torch.equal(tr_udp.us, sent)


def test_the_suite_gives_the_estimators_the_inputs_they_know(monkeypatch, tmp_path):
    """Through run_suite: the Kalman filter steps with the acknowledged inputs (its means are
    the filter's on tr.us, the applied inputs) and, unacknowledged, with the sent ones,
    which a lost packet makes wrong (its state error several times larger)."""
    from difffilter import kalman_filter
    from difffilter.eval.suite import run_suite

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    rmse = {}
    for acked in (True, False):
        sc = _with(input_loss={"kind": "packet_loss", "rate": 0.3, "on_loss": "zero",
                               "acknowledged": acked},
                   inputs={"kind": "sinusoid", "amplitude": 3.0, "frequency": 2.0},
                   estimators=["kf"])  # fmt: skip
        result = run_suite(sc, runs=6, progress=False)
        tr = result.traj
        ref = kalman_filter(sc.system(torch.float64), tr.y_recv, tr.us)
        torch.testing.assert_close(result.outputs["kf"].means, ref.means,
                                   rtol=0, atol=1e-10)  # fmt: skip
        rmse[acked] = result.metrics["kf"]["state_rmse"]
        us = tr.info["inputs_applied"] if acked else sc.inputs(6, torch.float64)
        assert torch.equal(tr.us, us)
    assert rmse[False] > 3 * rmse[True]


def test_a_misspelt_field_lists_every_field_and_a_covert_attack_is_refused_at_load():
    with pytest.raises(ValueError, match="unknown field.*acknowleged.*valid: acknowledged, kind, "
                                         "on_loss, packets, rate"):  # fmt: skip
        _with(input_loss={"kind": "packet_loss", "rate": 0.1, "acknowleged": False})
    with pytest.raises(ValueError, match="motor.yaml.*conceals"):
        _with(input_loss={"kind": "packet_loss", "rate": 0.1},
              attack={"kind": "covert", "signal": {"kind": "bias", "value": 0.5,
                                                   "channel": "actuator"}})  # fmt: skip


def test_the_calibration_draws_its_arrivals_from_its_own_stream(monkeypatch, tmp_path):
    """The detectors' attack-free calibration runs draw the input arrivals from the stream
    calibration/input_schedule (they came from torch's global generator: a CUSUM threshold
    of 18.48 or 14.73 by the global seed)."""
    from difffilter.models.estimators import SuiteContext

    sc = _with(input_loss={"kind": "packet_loss", "rate": 0.4, "acknowledged": False})
    masks = []
    for global_seed in (0, 1):
        torch.manual_seed(global_seed)
        ctx = SuiteContext(scenario=sc, model=sc.system(torch.float64), runs=6,
                           streams=Streams(3))  # fmt: skip
        masks.append(ctx.calibration.info["input_mask"])
    assert torch.equal(masks[0], masks[1])
    expected = PacketLoss(0.4).mask((50,), 40, 1, Streams(3)("calibration/input_schedule"))
    assert torch.equal(masks[0], expected)


def test_the_report_records_the_network_and_a_covert_threat_is_named_in_the_threat_set(
    monkeypatch, tmp_path
):
    """metrics.json and report.md say what the network lost (a TCP-like and a UDP-like study
    were told apart by their names alone); a threat set's covert attack on a scenario that
    loses inputs is named with the file and the threat before the study runs."""
    import json

    from difffilter.eval.report import network_of, write_report
    from difffilter.eval.robustness import load_threat_set
    from difffilter.eval.suite import run_suite

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    sc = _with(input_loss={"kind": "packet_loss", "rate": 0.3, "on_loss": "zero",
                           "acknowledged": False}, estimators=["kf"])  # fmt: skip
    assert network_of(sc) == {
        "sensors": "AllSensors()",
        "inputs": {
            "schedule": "PacketLoss(rate=0.3, packets=None)",
            "on_loss": "zero",
            "acknowledged": False,
        },
    }
    assert network_of(_with())["inputs"] is None
    write_report(tmp_path / "out", run_suite(sc, runs=4, progress=False))
    doc = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert doc["network"] == {**network_of(sc), "steps_without_data": 0.0}
    import jsonschema

    schema = json.loads(
        (Path(__file__).resolve().parents[1] / "eval" / "metrics.schema.json").read_text()
    )
    jsonschema.validate(doc, schema)

    class EveryOther:  # a schedule of one's own, with object's repr (a memory address)
        def mask(self, batch_shape, num_steps, dim, generator=None, *, device=None):
            return (
                (torch.arange(num_steps) % 2 == 0)
                .unsqueeze(-1)
                .expand(*batch_shape, num_steps, dim)
            )

    own = dataclasses.replace(sc, protocol=EveryOther())
    assert network_of(own)["sensors"].endswith("EveryOther")
    text = (tmp_path / "out" / "report.md").read_text()
    assert "applying zero where one is lost, unacknowledged (UDP-like" in text
    threats = tmp_path / "threats.yaml"
    threats.write_text(
        textwrap.dedent("""
        threats:
          bias: {kind: bias, value: 0.5, channel: actuator, onset: 5}
          hidden: {kind: covert, signal: {kind: bias, value: 0.5, channel: actuator, onset: 5}}
    """)
    )
    assert set(load_threat_set(sc, ["bias"], path=threats).threats) == {"bias"}
    with pytest.raises(ValueError, match=r"threats.yaml: threat 'hidden'.*input packets arrive"):
        load_threat_set(sc, "all", path=threats)


def test_a_sinusoid_per_input_from_yaml():
    """A networked-control trial's two-input plant could not take a YAML sinusoid (one input
    only, 'got [1, 80, 1]'): a list gives one per input; numbers keep the one input."""
    plant = {**MOTOR["plant"], "B": [[0.0, 0.1], [0.2, 0.0]]}
    sc = _with(plant=plant, inputs={"kind": "sinusoid", "amplitude": [1.0, 0.5],
                                    "frequency": 2.0, "phase": [0.0, 1.0]})  # fmt: skip
    us = sc.inputs(3, torch.float64)
    k = torch.arange(40, dtype=torch.float64)
    expected = torch.stack([torch.sin(2 * torch.pi * 2.0 * 0.01 * k),
                            0.5 * torch.sin(2 * torch.pi * 2.0 * 0.01 * k + 1.0)], -1)  # fmt: skip
    torch.testing.assert_close(us, expected.expand(3, 40, 2), rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="one per input"):
        _with(plant=plant, inputs={"kind": "sinusoid", "amplitude": [1.0, 0.5, 2.0],
                                   "frequency": [1.0, 2.0]})  # fmt: skip
    one = _with().inputs(2, torch.float64)
    assert one.shape == (2, 40, 1)


def test_the_udp_like_filters_run_where_inputs_are_lost_unacknowledged(monkeypatch, tmp_path):
    """udp_kf and its gated pair: the scenario's ExpectedInputKalmanFilter (arrival rate
    1 − the loss rate, the scenario's on_loss) on the study's trajectories, in the default
    suite; skipped with the reason where there is no such filter."""
    from difffilter import ExpectedInputKalmanFilter, open_loop
    from difffilter.eval.suite import run_suite
    from difffilter.models.generic_estimators import default_estimators, expected_input_filter

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    lossy = {"kind": "packet_loss", "rate": 0.3, "on_loss": "hold", "acknowledged": False}
    sc = _with(input_loss=lossy, estimators=["udp_kf", "chi_square_udp_kf", "kf"],
               inputs={"kind": "sinusoid", "amplitude": 3.0, "frequency": 2.0})  # fmt: skip
    result = run_suite(sc, runs=40, progress=False)
    tr = result.traj
    model = sc.system(torch.float64)
    ref = open_loop(ExpectedInputKalmanFilter(0.7, on_loss="hold"), model, tr.y_recv, tr.us)
    torch.testing.assert_close(result.outputs["udp_kf"].means, ref.means, rtol=0, atol=1e-12)
    gated = result.outputs["chi_square_udp_kf"]
    assert gated.means.shape == ref.means.shape and gated.scores.shape == ref.means.shape[:-1]
    assert result.metrics["udp_kf"]["state_rmse"] < result.metrics["kf"]["state_rmse"]
    assert {"chi_square_udp_kf", "cusum_udp_kf"} <= set(default_estimators(sc))
    two = {**MOTOR["plant"], "B": [[0.0, 0.1], [0.2, 0.0]]}
    own = _with(plant=two, inputs={"kind": "constant", "value": [1.0, 0.5]}, input_loss=lossy)
    one = _with(plant=two, inputs={"kind": "constant", "value": [1.0, 0.5]},
                input_loss={**lossy, "packets": [[0, 1]]})  # fmt: skip
    assert expected_input_filter(own, own.system()).independent is True
    assert expected_input_filter(one, one.system()).independent is False
    for scenario, why in (
        (_with(), "this scenario loses none"),
        (_with(input_loss={**lossy, "acknowledged": True}), "are acknowledged"),
        (_with(input_loss={"kind": "round_robin", "groups": [[0]], "acknowledged": False}),
         "follow a RoundRobin"),
    ):  # fmt: skip
        assert "udp_kf" not in "".join(default_estimators(scenario))
        with pytest.raises(ValueError, match=why):
            expected_input_filter(scenario, scenario.system())


def test_the_robustness_report_records_the_network_and_no_crafted_insider(monkeypatch, tmp_path):
    """From a threat-model trial: robustness.json and .md did not say what the network lost
    (report.md and metrics.json did), and a crafted stealthy threat was marked an insider
    that reads the true state (read from its spec, which has no reads_state: True)."""
    import json

    from difffilter.eval.report import network_of
    from difffilter.eval.robustness import load_threat_set, run_robustness, write_robustness
    from difffilter.eval.stealthy import StealthySpec

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    sc = _with(input_loss={"kind": "packet_loss", "rate": 0.3, "on_loss": "zero",
                           "acknowledged": False}, estimators=["chi_square_kf"])  # fmt: skip
    threats = tmp_path / "threats.yaml"
    threats.write_text("threats:\n  bias: {kind: bias, value: 0.5, channel: actuator, onset: 5}\n")
    result = run_robustness(sc, load_threat_set(sc, ["bias"], path=threats), runs=6,
                            progress=False)  # fmt: skip
    doc = write_robustness(tmp_path / "out", result)
    assert doc["network"] == network_of(sc)
    assert json.loads((tmp_path / "out" / "robustness.json").read_text())["network"]["inputs"] == {
        "schedule": "PacketLoss(rate=0.3, packets=None)",
        "on_loss": "zero",
        "acknowledged": False,
    }
    text = (tmp_path / "out" / "robustness.md").read_text()
    assert "applying zero where one is lost, unacknowledged (UDP-like" in text
    assert StealthySpec().reads_state is False


def test_input_loss_on_a_plant_without_inputs_is_refused_unless_an_attack_rides_in_them():
    """A trial's plant with B and no inputs: ran on zero inputs, the loss changing nothing
    while the report announced it. Refused now; an actuator attack in the packets is a loss
    that matters."""
    lossy = {"kind": "packet_loss", "rate": 0.3}
    with pytest.raises(ValueError, match="motor.yaml: input_loss: the plant has no inputs:"):
        _with(inputs=None, input_loss=lossy)
    sc = _with(inputs=None, input_loss=lossy,
               attack={"kind": "bias", "value": 0.5, "channel": "actuator", "onset": 5})  # fmt: skip
    assert sc.input_loss_schedule() is not None


def test_a_lost_reading_does_not_split_a_sensor_attacks_episode(monkeypatch, tmp_path):
    """A threat-model trial: under 20 % sensor loss the steps of a sensor attack whose reading
    was lost are not labelled attacked, and the detection delay timed each fragment from its
    own start (33 attacked runs, 242 episodes, 2.1 steps against 10.8 from the onsets). The
    episodes are the attack's own steps now: one per attacked run, its delay from the onset,
    written out here; TPR keeps the received steps."""
    from difffilter.eval.suite import run_suite

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    sc = _with(schedule={"kind": "packet_loss", "rate": 0.3}, runs=16,
               attack={"kind": "bias", "value": 0.05, "onset": 10, "share": 0.5},
               estimators=["chi_square_kf"])  # fmt: skip
    result = run_suite(sc, runs=16, progress=False)
    tr, metrics = result.traj, result.metrics["chi_square_kf"]
    own = tr.info["attack_flags"]
    own = own.any(-1) if own.dim() == 3 else own
    assert bool((own & ~tr.flags).any())  # some attacked readings were lost
    alarms = result.outputs["chi_square_kf"].detection.alarms
    delays, episodes = [], 0
    for run in range(16):
        steps = own[run].nonzero().flatten().tolist()
        if not steps:
            continue
        assert steps == list(range(steps[0], steps[-1] + 1))  # one window a run
        if not bool(tr.flags[run].any()):  # none of its readings arrived: no attack seen
            continue
        episodes += 1
        hits = [t for t in steps if bool(alarms[run, t] & tr.flags[run, t])]
        if hits:
            delays.append(hits[0] - steps[0])
    assert metrics["attack_episodes"] == episodes and metrics["episodes_detected"] == len(delays)
    assert metrics["detection_delay_steps"] == pytest.approx(sum(delays) / len(delays), abs=1e-12)
    assert metrics["tpr"] == pytest.approx(float(alarms[tr.flags].double().mean()), abs=1e-12)


def test_cusum_calibrations_of_two_filter_settings_are_two(monkeypatch, tmp_path):
    """A review: the CUSUM cache keyed a filter by its class's name, so two settings of the
    UDP-like filter shared one τ (5.71 where the second's own is 12.5); bursts of input loss
    leave the UDP-like filters out, with the reason."""
    from difffilter import ExpectedInputKalmanFilter
    from difffilter.models.estimators import SuiteContext
    from difffilter.models.generic_estimators import default_estimators

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    sc = _with(input_loss={"kind": "packet_loss", "rate": 0.3, "on_loss": "hold",
                           "acknowledged": False},
               inputs={"kind": "sinusoid", "amplitude": 3.0, "frequency": 2.0})  # fmt: skip
    ctx = SuiteContext(sc, sc.system(torch.float64), 8, Streams(0))
    first = ctx.cusum(ExpectedInputKalmanFilter(0.7, on_loss="hold"))
    second = ctx.cusum(ExpectedInputKalmanFilter(0.1, on_loss="zero"))
    fresh = SuiteContext(sc, sc.system(torch.float64), 8, Streams(0))
    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path / "other"))
    alone = fresh.cusum(ExpectedInputKalmanFilter(0.1, on_loss="zero"))
    assert second.threshold == alone.threshold != first.threshold
    bursts = _with(input_loss={"kind": "burst_loss", "to_bad": 0.1, "to_good": 0.3,
                               "acknowledged": False})  # fmt: skip
    assert "chi_square_udp_kf" not in default_estimators(bursts)
    from difffilter.models.estimators import get

    assert "in bursts" in get("udp_kf").unmet(bursts, bursts.system())


def test_an_attack_whose_readings_were_all_lost_is_no_episode():
    """A review: under the attack's own steps as episodes, a two-step attack under 50 % loss
    whose readings were all lost counted as a missed episode (122 of 400 runs), and a
    detection was any alarm in the episode where impact reads one on a received step."""
    from types import SimpleNamespace

    from difffilter.eval.scoring import episode_delay, episode_steps

    own = torch.zeros(3, 8, dtype=torch.bool)
    own[:, 3:5] = True
    mask = torch.ones(3, 8, 1, dtype=torch.bool)
    mask[0, 3:5] = False  # run 0: both attacked readings lost
    mask[1, 3] = False  # run 1: the first lost, the second arrived
    flags = own & mask[..., 0]
    traj = SimpleNamespace(flags=flags, mask=mask, info={"attack_flags": own})
    steps = episode_steps(traj)
    assert not bool(steps[0].any()) and steps[1, 3:5].all() and steps[2, 3:5].all()
    alarms = torch.zeros(3, 8, dtype=torch.bool)
    alarms[1, 3] = True  # at the lost reading: no detection
    alarms[1, 4] = alarms[2, 3] = True
    delay = episode_delay(alarms, traj)
    assert (delay["episodes"], delay["detected"]) == (2, 2) and delay["mean_delay"] == 0.5


def test_the_report_says_how_many_steps_received_nothing(monkeypatch, tmp_path):
    """A robotics trial at 90 % loss: 64 % of the steps received nothing and count among the
    negatives of FPR and AUC (1.14 % over all steps, 3.46 % over those with data), and the
    report did not say how many. metrics.json's network and report.md say it now."""
    import json

    from difffilter.eval.report import write_report
    from difffilter.eval.suite import run_suite

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    sc = _with(schedule={"kind": "packet_loss", "rate": 0.6}, estimators=["chi_square_kf"])
    result = run_suite(sc, runs=6, progress=False)
    write_report(tmp_path / "out", result)
    doc = json.loads((tmp_path / "out" / "metrics.json").read_text())
    expected = float((~result.traj.mask.any(-1)).double().mean())
    assert 0.4 < expected < 0.8 and doc["network"]["steps_without_data"] == expected
    text = (tmp_path / "out" / "report.md").read_text()
    assert f"({100 * expected:.3g} % of the steps received no measurement" in text


def test_inputs_of_the_wrong_width_and_a_ragged_matrix_are_named():
    """From a training trial: two amplitudes on a one-input plant said only "known_inputs
    ... got [1, 100, 2]"; a ragged row of F only "(nested) lists of numbers"."""
    two = {"kind": "sinusoid", "amplitude": [2.0, 1.0], "frequency": 0.2}
    with pytest.raises(ValueError, match=r"motor.yaml: inputs: they give 2 value\(s\) per step "
                                         r"and the plant has 1 input\(s\)"):  # fmt: skip
        _with(inputs=two)
    with pytest.raises(ValueError, match=r"they give 3 value\(s\)"):
        _with(inputs={"values": [[1.0, 2.0, 3.0]] * 40})
    ragged = {**MOTOR["plant"], "F": [[0.95], [-0.02, 0.8]]}
    with pytest.raises(ValueError, match=r"plant.F: its rows have \[1, 2\] entries: every row"):
        _with(plant=ragged)
    assert _with(inputs={"kind": "constant", "value": [0.5]}).inputs(2, torch.float64).shape == (
        2,
        40,
        1,
    )


def test_a_users_input_function_is_judged_at_the_studys_length(tmp_path, monkeypatch):
    """From a review: the width check called the user's function for one step, where one
    that squeezes its output gives [2] for two inputs, read as one input per step."""
    (tmp_path / "squeezed_inputs.py").write_text(
        "import torch\n\n\ndef two(k):\n"
        "    return torch.stack([torch.sin(k), torch.cos(k)], -1).squeeze()\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    plant = {**MOTOR["plant"], "B": [[0.1, 0.0], [0.0, 0.2]]}
    sc = _with(plant=plant, inputs={"function": "squeezed_inputs:two"})
    assert sc.inputs(4, torch.float64).shape == (4, 40, 2)


def test_a_loss_schedule_without_its_generator_is_refused():
    """A trial: a scenario's input losses, simulated from generators without
    "input_schedule", had drawn from torch's global generator: two identical calls gave
    other arrivals (the state 0.038 apart), neither difffilter-eval's."""
    lossy = _with(input_loss={"kind": "packet_loss", "rate": 0.4})
    gens = {k: Streams(3)(k) for k in ("plant", "attack", "schedule")}
    with pytest.raises(ValueError, match="PacketLoss draws its losses from generator"):
        lossy.simulate(6, gens)
    for schedule in (PacketLoss(0.2), BurstLoss(0.1, 0.5)):
        with pytest.raises(ValueError, match="draws its losses from generator"):
            schedule.mask((2,), 5, 1)
        assert schedule.mask((2,), 0, 1).shape == (2, 0, 1)  # nothing to draw


def test_a_users_input_loss_schedule_drawing_globally_is_warned_about():
    """A schedules trial: a user's own arrival schedule (any object with ``mask``), its
    stream left out of ``generators``, drew from torch's global generator without the
    warning a measurement schedule's gets; two identical calls differed."""
    from difffilter import LinearGaussianModel
    from difffilter.models.scenario import simulate

    class Coin:
        def mask(self, batch_shape, num_steps, dim, generator=None, *, device=None):
            b = (batch_shape,) if isinstance(batch_shape, int) else tuple(batch_shape)
            return torch.rand(*b, num_steps, dim, generator=generator, device=device) >= 0.5

    f64 = torch.float64
    eye = torch.eye(2, dtype=f64)
    model = LinearGaussianModel(torch.tensor([[0.9, 0.1], [0.0, 0.8]], dtype=f64), eye,
                                0.01 * eye, 0.1 * eye, torch.zeros(2, dtype=f64), eye,
                                B=torch.tensor([[0.0], [1.0]], dtype=f64))  # fmt: skip
    loss = InputLossSchedule(Coin(), "hold", True)
    us = torch.ones(4, 20, 1, dtype=f64)
    gens = {"plant": torch.Generator().manual_seed(0)}
    with pytest.warns(UserWarning, match="'input_schedule' stream"):
        simulate(model, 4, 20, generators=gens, us=us, input_loss=loss)
    with_stream = {**Streams(0).simulation()}
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # its stream given: no warning
        simulate(model, 4, 20, generators=with_stream, us=us, input_loss=loss)
