"""The threat library on a small linear plant, each against its known answer: what the
receiver gets minus what the plant measured is exactly the threat's formula, inside its
window, on its entries and its share of runs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter.attack import Channel
from difffilter.loop import DrawnNoise, KnownInputs, closed_loop
from difffilter.threats import (
    THREATS,
    Bias,
    Chirp,
    Covert,
    KSigmaBias,
    Pulses,
    Ramp,
    RandomWalk,
    Replay,
    Sinusoid,
    threat_from_dict,
)

F64 = torch.float64
T = 40


def _plant():
    F = torch.tensor([[0.9, 0.1, 0.0], [0.0, 0.8, 0.1], [0.0, 0.0, 0.7]], dtype=F64)
    H = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]], dtype=F64)
    eye = torch.eye(3, dtype=F64)
    R = torch.diag(torch.tensor([0.04, 0.09], dtype=F64))
    B = torch.tensor([[0.0], [0.0], [1.0]], dtype=F64)
    return df.LinearGaussianModel(F, H, 1e-2 * eye, R, torch.zeros(3, dtype=F64), eye, B=B)


def _run(attack, runs=3, seed=0, steps=T):
    plant = _plant()
    controller = None
    if Channel(attack.channel) is Channel.ACTUATOR:
        controller = KnownInputs(torch.zeros(runs, steps, 1, dtype=F64))
    return closed_loop(
        plant, steps, noise=DrawnNoise(torch.Generator().manual_seed(seed)),
        x0=torch.zeros(runs, 3, dtype=F64), attack=attack, controller=controller,
        attack_generator=torch.Generator().manual_seed(seed + 1),
    ).trajectories  # fmt: skip


def _injected(tr):
    return tr.y_recv - tr.y_true


def _s(onset, steps=T):
    return torch.arange(1, steps + 1, dtype=F64) - onset


def test_a_bias_is_its_value_inside_its_window_and_zero_outside():
    tr = _run(Bias((0.5, -1.0), onset=10, duration=5))
    a = _injected(tr)
    on = (_s(10) >= 0) & (_s(10) < 5)
    torch.testing.assert_close(a[:, on], torch.tensor([0.5, -1.0], dtype=F64).expand(3, 5, 2))
    assert torch.equal(a[:, ~on], torch.zeros(3, T - 5, 2, dtype=F64))
    assert torch.equal(tr.flags, on.expand(3, T))


def test_a_ksigma_bias_reads_the_noise_standard_deviations_of_the_model():
    attack = KSigmaBias.of(_plant(), 1.5)
    assert attack.sigma == pytest.approx((0.2, 0.3))
    torch.testing.assert_close(_injected(_run(attack))[0, 0], torch.tensor([0.3, 0.45], dtype=F64))


def test_a_ramp_grows_by_its_slope_every_step_from_the_onset():
    tr = _run(Ramp(slope=(0.1, 0.02), onset=5))
    s = _s(5)
    expected = (s + 1).clamp_min(0).unsqueeze(-1) * torch.tensor([0.1, 0.02], dtype=F64)
    expected[s < 0] = 0
    torch.testing.assert_close(_injected(tr), expected.expand(3, T, 2))


def test_a_random_walk_starts_at_zero_and_its_increments_have_the_given_spread():
    walk = RandomWalk(step_std=0.3, onset=11)
    values, flags = walk.sample((4000,), T, 2, torch.Generator().manual_seed(3), dtype=F64)
    assert torch.equal(values[:, :10], torch.zeros(4000, 10, 2, dtype=F64))
    steps = values[:, 11:].diff(dim=1)
    assert abs(float(steps.std()) - 0.3) < 0.01 and abs(float(steps.mean())) < 0.01
    # every run walks its own way: the final values spread like sqrt(30) steps
    assert abs(float(values[:, -1].std()) - 0.3 * math.sqrt(T - 10)) < 0.05
    assert flags[:, 10:].all() and not flags[:, :10].any()


def test_pulses_repeat_with_their_period_and_width():
    values, _ = Pulses(amplitude=2.0, period=4, width=1, onset=3).sample(
        (1,), 12, 1, None, dtype=F64
    )
    assert values[0, :, 0].tolist() == [0, 0, 2, 0, 0, 0, 2, 0, 0, 0, 2, 0]


def test_a_sinusoid_and_a_chirp_follow_their_formulas():
    values, _ = Sinusoid(amplitude=1.5, omega=10.0, phase=0.3, dt=0.01, onset=2).sample(
        (), 30, 1, None, dtype=F64
    )
    s = _s(2, 30)
    expected = torch.where(s >= 0, 1.5 * torch.sin(0.1 * s + 0.3), torch.zeros_like(s))
    torch.testing.assert_close(values[:, 0], expected)
    chirp = Chirp(amplitude=1.0, f0=0.01, f1=0.1, sweep=200, onset=1)
    phase = chirp.phase(torch.arange(0, 400, dtype=F64))
    frequency = phase.diff() / (2 * math.pi)  # cycles per step, the mid-step frequency
    torch.testing.assert_close(frequency[0], torch.tensor(0.01 + 0.09 / 400, dtype=F64))
    torch.testing.assert_close(frequency[-1], torch.tensor(0.1, dtype=F64))
    values, _ = chirp.sample((), 400, 1, None, dtype=F64)
    torch.testing.assert_close(values[:, 0], torch.sin(phase))


def test_replay_delivers_the_measurement_of_d_steps_before_on_its_share_of_runs():
    tr = _run(Replay(delay=4, onset=10, share=0.5), runs=400)
    attacked = tr.flags.any(-1)
    assert 160 < int(attacked.sum()) < 240  # Binomial(400, 1/2): ± 4 σ
    t0 = 9
    recorded = t0 - 4 + torch.arange(T - t0) % 4  # y_(k-d) while it lasts, then again
    assert torch.equal(tr.y_recv[attacked, t0:], tr.y_true[attacked][:, recorded])
    assert torch.equal(tr.y_recv[~attacked], tr.y_true[~attacked])
    assert tr.flags[attacked, t0:].all()


def test_a_finite_replay_hands_back_the_true_measurements_after_it():
    tr = _run(Replay(delay=3, onset=6, duration=5))
    assert torch.equal(tr.y_recv[:, 5:10], tr.y_true[:, [2, 3, 4, 2, 3]])
    assert torch.equal(tr.y_recv[:, 10:], tr.y_true[:, 10:])
    assert tr.flags[:, 5:10].all() and not tr.flags[:, 10:].any()
    with pytest.raises(ValueError, match="live must be True or False"):
        Replay(delay=3, onset=6, live="yes")


def test_a_seamless_replay_continues_a_noise_free_loop_exactly_across_its_passes():
    # x_{k+1} = Φ x_k measured without noise (C = I): with w = 1 the gap's free response
    # turns the recording into the live trajectory, at the splice and at every wrap
    phi = _plant().transition_matrix(0)
    x0 = torch.tensor([[1.0, -2.0, 0.5], [0.3, 0.7, -1.0]], dtype=F64)
    ys = [x0]
    for _ in range(T - 1):
        ys.append(ys[-1] @ phi.mT)
    ys = torch.stack(ys, dim=1)  # y_1 … y_T  [2, T, 3]
    replay = Replay(delay=6, onset=12, loop=(phi, torch.eye(3, dtype=F64)), level_window=1)
    state = replay.init((2,), T, 3, dtype=F64)
    received = []
    for k in range(1, T + 1):
        state, value, flag = replay.step(state, k, y=ys[:, k - 1])
        received.append(value if bool(flag.all()) else ys[:, k - 1])
    torch.testing.assert_close(torch.stack(received, 1), ys, rtol=0, atol=1e-12)
    plain = Replay(delay=6, onset=12)  # the plain replay jumps back at the splice
    state = plain.init((2,), T, 3, dtype=F64)
    for k in range(1, 13):
        state, value, _ = plain.step(state, k, y=ys[:, k - 1])
    torch.testing.assert_close(value, ys[:, 5])


def test_a_seamless_replay_checks_its_loop_model():
    eye = torch.eye(3, dtype=F64)
    with pytest.raises(ValueError, match=r"loop must be \(Φ \[n, n\], C \[dy, n\]\)"):
        Replay(delay=6, onset=12, loop=(eye, torch.eye(2, dtype=F64)))
    with pytest.raises(ValueError, match="loop needs live=False"):
        Replay(delay=6, onset=12, loop=(eye, eye), live=True)
    with pytest.raises(ValueError, match="level_window must be at most delay"):
        Replay(delay=6, onset=12, loop=(eye, eye), level_window=7)
    replay = threat_from_dict({"kind": "replay", "delay": 3, "onset": 5, "level_window": 2,
                               "loop": [eye.tolist(), eye.tolist()]})  # fmt: skip
    state = replay.init((1,), 8, 2, dtype=F64)
    with pytest.raises(ValueError, match="loop's C has 3 rows but the measurement has 2"):
        for k in range(1, 6):
            state, _, _ = replay.step(state, k, y=torch.ones(1, 2, dtype=F64))


def test_share_and_entries_choose_the_runs_and_the_measurements_attacked():
    tr = _run(Bias(1.0, share=0.25, entries=(1,)), runs=800)
    attacked = tr.flags.all(-1)
    assert torch.equal(attacked, tr.flags.any(-1))  # a run is attacked throughout or not at all
    assert abs(float(attacked.double().mean()) - 0.25) < 0.06
    a = tr.attack  # the change the loop made, l_k a_k
    torch.testing.assert_close(a, _injected(tr))
    assert torch.equal(a[..., 0], torch.zeros_like(a[..., 0]))  # entry 0 is never touched
    assert torch.equal(a[attacked][..., 1], torch.ones_like(a[attacked][..., 1]))
    assert torch.equal(a[~attacked], torch.zeros_like(a[~attacked]))


def test_a_shaped_attack_on_the_actuator_drives_the_plant_only():
    tr = _run(Bias(0.7, channel="actuator", onset=3))
    assert torch.equal(tr.y_recv, tr.y_true)  # the sensors are honest
    assert torch.equal(tr.attack[:, 2:], torch.full((3, T - 2, 1), 0.7, dtype=F64))
    free = _run(Bias(0.0, channel="actuator", onset=3))
    assert not torch.equal(tr.x, free.x)


class _Feedback:
    """``u_k = −K ỹ_k``: a controller that reacts to what it receives."""

    def init(self, batch_shape, dtype, device):
        return torch.zeros(*batch_shape, 1, dtype=dtype, device=device)

    def __call__(self, k, y, out):
        return -(y @ torch.tensor([[0.3], [0.5]], dtype=y.dtype))


def _feedback_loop(attack, runs=4, steps=T):
    return closed_loop(
        _plant(), steps, noise=DrawnNoise(torch.Generator().manual_seed(3)),
        x0=torch.zeros(runs, 3, dtype=F64), attack=attack, controller=_Feedback(),
        attack_generator=torch.Generator().manual_seed(4),
    ).trajectories  # fmt: skip


def test_a_covert_attack_hands_the_receiver_the_attack_free_loop_while_the_plant_drifts():
    """Smith 2015 on a linear plant in closed loop: what the receiver (and so the
    controller) gets is the attack-free loop's measurement, and the plant's state is the
    attack-free state plus the attack's own deviation ``δ_k = F δ_{k−1} + B a_k``."""
    plant = _plant()
    attack = Covert(Ramp(0.2, channel="actuator", onset=6), plant)
    tr, free = _feedback_loop(attack), _feedback_loop(None)
    torch.testing.assert_close(tr.y_recv, free.y_recv, rtol=0, atol=1e-12)
    torch.testing.assert_close(tr.us, free.us, rtol=0, atol=1e-12)
    delta, deviations = torch.zeros(3, dtype=F64), []
    for k in range(1, T + 1):
        a = 0.2 * (k - 6 + 1) if k >= 6 else 0.0
        delta = plant.F @ delta + plant.B[:, 0] * a
        deviations.append(delta)
    expected = torch.stack(deviations).expand(4, T, 3)
    torch.testing.assert_close(tr.x - free.x, expected, rtol=0, atol=1e-10)
    assert float(expected[:, -1].norm(dim=-1).min()) > 1.0  # the plant went far
    torch.testing.assert_close(tr.info["attack_concealment"], tr.y_recv - tr.y_true)
    assert torch.equal(tr.flags, (_s(6) >= 0).expand(4, T))  # from the onset, every run


def test_a_covert_attack_on_a_share_of_runs_leaves_the_others_alone():
    attack = Covert(Bias(0.5, channel="actuator", onset=3, share=0.5), _plant())
    tr, free = _feedback_loop(attack, runs=16), _feedback_loop(None, runs=16)
    attacked = tr.flags.any(-1)
    assert 0 < int(attacked.sum()) < 16
    torch.testing.assert_close(tr.y_recv, free.y_recv, rtol=0, atol=1e-12)
    assert torch.equal(tr.x[~attacked], free.x[~attacked])
    assert not torch.allclose(tr.x[attacked], free.x[attacked])


def test_a_covert_attack_names_what_it_needs():
    with pytest.raises(ValueError, match="signal must act on the actuators"):
        Covert(Bias(1.0), _plant())
    with pytest.raises(ValueError, match="signal must be a shaped attack"):
        Covert(Replay(2, 4), _plant())
    with pytest.raises(ValueError, match="plant must be a model"):
        Covert(Bias(1.0, channel="actuator"), object())
    with pytest.raises(ValueError, match="needs the model"):
        threat_from_dict({"kind": "covert", "signal": {"kind": "bias", "value": 1.0}})
    with pytest.raises(ValueError, match="needs signal"):
        threat_from_dict({"kind": "covert"}, model=_plant())


def test_every_threat_is_built_from_data_and_bad_data_is_named():
    specs = {
        "bias": {"value": 1.0}, "ksigma_bias": {"k": 2.0}, "ramp": {"slope": 0.1},
        "random_walk": {"step_std": 0.1}, "pulses": {"amplitude": 1.0, "period": 5, "width": 2},
        "sinusoid": {"amplitude": 1.0, "omega": 0.5}, "chirp": {"f1": 0.3},
        "replay": {"delay": 3, "onset": 5},
        "covert": {"signal": {"kind": "ramp", "slope": 0.1, "onset": 5}},
    }  # fmt: skip
    assert set(specs) == set(THREATS)
    for kind, params in specs.items():
        window = {} if kind == "covert" else {"onset": 5}
        threat = threat_from_dict({"kind": kind, **window, **params}, model=_plant())
        assert isinstance(threat, THREATS[kind])
        _run(threat)  # runs in the loop
    with pytest.raises(ValueError, match="unknown threat kind 'spoof'.*bias"):
        threat_from_dict({"kind": "spoof"})
    with pytest.raises(ValueError, match="no field.*slop.*valid"):
        threat_from_dict({"kind": "ramp", "slop": 1.0})
    with pytest.raises(ValueError, match="share"):
        Bias(1.0, share=1.5)
    with pytest.raises(ValueError, match="onset"):
        Ramp(0.1, onset=0)
    with pytest.raises(ValueError, match="width"):
        Pulses(1.0, period=2, width=3)
    with pytest.raises(ValueError, match="value has 3 entries; the channel has 2"):
        _run(Bias((1.0, 2.0, 3.0)))
    # a quoted number is not read character by character (once the vector (1, 0))
    with pytest.raises(ValueError, match="value must be a number or a sequence of numbers"):
        threat_from_dict({"kind": "bias", "value": "10"})
    for bad, message in (({"f0": math.inf}, "f0 must be a finite number >= 0"),
                         ({"f1": math.nan}, "f1 must be a finite number >= 0"),
                         ({"dt": math.inf}, "dt must be a finite number > 0"),
                         ({"f0": -0.1}, "f0 must be a finite number >= 0")):  # fmt: skip
        with pytest.raises(ValueError, match=message):
            threat_from_dict({"kind": "chirp", **bad})
    # fields of the wrong type are named where they are given (a user trial found them
    # failing at sampling, or as "could not convert string to float")
    for kind, bad, message in (
        ("ksigma_bias", {"k": "x", "sigma": 1.0}, "k must be a finite number; got 'x'"),
        ("ksigma_bias", {"k": None, "sigma": 1.0}, "k must be a finite number; got None"),
        ("sinusoid", {"omega": "1"}, "omega must be a finite number; got '1'"),
        ("sinusoid", {"dt": "1"}, "dt must be a finite number; got '1'"),
        ("sinusoid", {"dt": 0.0}, "dt must be a finite number > 0"),
        ("chirp", {"f1": [0.1]}, r"f1 must be a finite number; got \[0.1\]"),
        (
            "bias",
            {"entries": 2},
            r"entries must be None or a list of indices >= 0 \(e.g. \[0, 2\]\); got 2",
        ),
        ("bias", {"entries": "02"}, "entries must be None or a list of indices"),
    ):
        with pytest.raises(ValueError, match=message):
            threat_from_dict({"kind": kind, **bad})
    assert Sinusoid(omega=np.float32(2.0), dt=np.int64(1)).omega == 2.0  # numpy numbers: plain
    assert threat_from_dict({"kind": "bias", "entries": [1]}).entries == (1,)  # a list: a tuple
    with pytest.raises(ValueError, match="covert threat's plant is the model of the scenario"):
        threat_from_dict(
            {"kind": "covert", "signal": {"kind": "bias"}, "plant": "x"}, model=_plant()
        )


def test_a_library_threat_on_the_tracking_scenario_keeps_its_plant_and_its_schedule():
    """Tracking simulates per-sensor packets under Round-Robin access: a threat of the
    library rides on the packets sent, on the same plant draws as the attack-free runs."""
    from difffilter.models import registry
    from difffilter.models.streams import Streams

    sc = registry.get("tracking_rrp_deception")

    def gens():
        return {k: Streams(0)(k) for k in ("plant", "attack", "schedule")}

    free = sc.with_threat(None).simulate(3, gens())
    ramp = sc.with_threat(Ramp(slope=0.5, onset=30)).simulate(3, gens())
    assert torch.equal(free.x, ramp.x) and torch.equal(free.mask, ramp.mask)
    assert not ramp.flags[:, :29].any() and ramp.flags[:, 30:].all()
    sent = ramp.mask[:, 40]  # the packet of step 41: its entries carry 0.5 · 12
    delta = ramp.info["y_all"][:, 40] - free.info["y_all"][:, 40]
    torch.testing.assert_close(delta[sent], torch.full_like(delta[sent], 6.0))
    # attacked steps are the threat's window, as on every other scenario: a pulse train's
    # quiet steps count (once only the steps whose packet changed did)
    pulses = sc.with_threat(Pulses(2.0, period=12, width=4, onset=30))
    got = pulses.simulate(3, gens())
    quiet = (torch.arange(29, got.flags.shape[1]) - 29) % 12 >= 4
    assert not got.flags[:, :29].any() and got.flags[:, 29:].all()
    assert got.info["sensor_flags"][:, 29:].all() and not got.info["sensor_flags"][:, :29].any()
    assert torch.equal(got.info["y_all"][:, 29:][:, quiet], free.info["y_all"][:, 29:][:, quiet])


def test_a_threat_set_file_that_is_not_one_is_named_with_its_path(tmp_path):
    """A user trial found a raw PyYAML traceback, an AttributeError for a list, and a
    misspelt key or excluded name ignored in silence."""
    from difffilter.eval.robustness import load_threat_set
    from difffilter.models import registry

    sc = registry.get("four_tank_bias")

    def load(text, name="set.yaml"):
        path = tmp_path / name
        path.write_text(text)
        return load_threat_set(sc, "all", path=path)

    for text, message in (
        ("threats: {a: {kind: bias\n", "set.yaml is not valid YAML"),
        ("- kind: bias\n", "set.yaml: a threat set is a mapping .* got a list"),
        ("threatz: {a: {kind: bias}}\n", "set.yaml: unknown key.s. threatz; a threat set holds threats, threats_from"),
        # where it looked (a trial named a shipped set beside a file of its own)
        ("threats_from: nowhere.yaml\n", r"set.yaml: threats_from nowhere.yaml: no file "
         r".*nowhere.yaml \(a relative name is read beside the file that names it; the "
         r"shipped threat sets are in .*threats: give such a set by its path\)"),
        ("threats_from: shared.yaml\nexclude: [bais]\n", "exclude names threat.s. bais that shared.yaml .*: bias, ramp"),
        ("threats_from: shared.yaml\nexclude: bias\n", "exclude must be a list of threat names"),
    ):  # fmt: skip
        (tmp_path / "shared.yaml").write_text(
            "threats: {bias: {kind: bias, onset: 5}, ramp: {kind: ramp, onset: 5}}\n"
        )
        with pytest.raises(ValueError, match=message):
            load(text)
    kept = load("threats_from: shared.yaml\nexclude: [ramp]\nruns: 3\n")
    assert list(kept.threats) == ["bias"] and kept.runs == 3
    with pytest.raises(ValueError, match="absent.yaml does not exist"):
        load_threat_set(sc, "all", path=tmp_path / "absent.yaml")


def test_a_study_whose_attack_starts_after_its_last_step_is_refused():
    """run_suite checked nothing: an onset past the horizon gave a full report with no
    attacked step and every detection metric None (the YAML and threat-set routes refuse)."""
    from difffilter.eval.suite import run_suite
    from difffilter.models import registry

    sc = registry.get("four_tank_bias").with_steps(20)
    with pytest.raises(
        ValueError, match="'four_tank_bias': its attack does not fit: it starts at step 21"
    ):
        run_suite(
            sc.with_threat(Bias(0.1, onset=21)),
            runs=2,
            estimators=["chi_square_ekf"],
            progress=False,
        )
    out = run_suite(
        sc.with_threat(Bias(0.1, onset=20)), runs=2, estimators=["chi_square_ekf"], progress=False
    )
    assert int(out.traj.flags.sum()) == 2  # the last step of both runs


def test_a_stealthy_kind_outside_a_threat_set_says_where_it_is_made():
    with pytest.raises(ValueError, match="'stealthy' threat is crafted against an estimator"):
        threat_from_dict({"kind": "stealthy"})


_OWN_ATTACKS = """
import torch
from difffilter.attack import Attack, TabulatedAttack
from difffilter.threats import Bias


class Drift(TabulatedAttack):
    def __init__(self, rate, onset=1):
        self.rate, self.onset = rate, onset

    def sample(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        k = torch.arange(num_steps, dtype=dtype)
        values = (self.rate * (k - self.onset + 1)).clamp_min(0)[:, None].expand(num_steps, dim)
        flags = (k >= self.onset - 1).expand(*batch_shape, num_steps)
        return values.expand(*batch_shape, num_steps, dim).clone(), flags.clone()


def noise_sized(model, k=2.0, onset=1):
    return Bias(value=k * float(model.measurement_noise.cov[0, 0].sqrt()), onset=onset)


READY = Bias(value=0.25, onset=3)
NOT_AN_ATTACK = 3
"""


def test_a_threat_of_ones_own_is_named_by_its_module_in_a_threat_set(tmp_path, monkeypatch):
    """A user trial: a threat set took only the library's kinds, so an attack of one's own
    could join a robustness study only through the undocumented Python API (and a ThreatSet
    built there without specs dropped the threat from the report's list)."""
    from difffilter.eval.robustness import ThreatSet, load_threat_set
    from difffilter.models import registry
    from difffilter.threats import Bias, threat_from_dict

    (tmp_path / "my_trial_attacks.py").write_text(_OWN_ATTACKS)
    monkeypatch.syspath_prepend(str(tmp_path))
    scenario = registry.get("four_tank_bias")
    model = scenario.system()
    drift = threat_from_dict({"kind": "my_trial_attacks:Drift", "rate": 0.01, "onset": 5})
    assert type(drift).__name__ == "Drift" and drift.rate == 0.01 and drift.onset == 5
    sized = threat_from_dict({"kind": "my_trial_attacks:noise_sized", "k": 3.0}, model)
    sigma = float(model.measurement_noise.cov[0, 0].sqrt())
    assert isinstance(sized, Bias) and math.isclose(sized.value[0], 3.0 * sigma, rel_tol=1e-12)
    assert threat_from_dict({"kind": "my_trial_attacks:READY"}).value == (0.25,)
    for spec, why in (
        ({"kind": "my_trial_attacks:READY", "onset": 4}, "is an attack object: it takes no fields"),
        ({"kind": "my_trial_attacks:NOT_AN_ATTACK"}, "is a int: name an Attack subclass"),
        ({"kind": "my_trial_attacks:Drift", "slope": 1}, "unexpected keyword argument 'slope'"),
        ({"kind": "my_trial_attacks:Nothing"}, "my_trial_attacks has no 'Nothing'"),
        ({"kind": "rampp"}, "valid: bias.*also stealthy.*package.module:object"),
    ):  # fmt: skip
        with pytest.raises(ValueError, match=why):
            threat_from_dict(spec, model)
    (tmp_path / "set.yaml").write_text(
        "runs: 4\nthreats:\n  drift: {kind: 'my_trial_attacks:Drift', rate: 0.01, onset: 21}\n"
        "  ramp: {kind: ramp, slope: 0.005, onset: 21}\n"
    )
    loaded = load_threat_set(scenario, path=tmp_path / "set.yaml")
    assert type(loaded.threats["drift"]).__name__ == "Drift"
    assert loaded.specs["drift"]["kind"] == "my_trial_attacks:Drift"
    given = {"ramp": {"kind": "ramp"}}
    made = ThreatSet({"drift": drift, "ramp": loaded.threats["ramp"]}, given)
    assert made.specs["drift"] == {"kind": "my_trial_attacks:Drift"} and "drift" not in given
    with pytest.raises(ValueError, match="specs of no threat: pulses"):
        ThreatSet({"drift": drift}, {"pulses": {"kind": "pulses"}})


def test_an_attacker_crafts_against_a_particle_filter_on_draws_of_its_own(monkeypatch):
    """From a threat-model trial: the crafting against normal_pf started from the study's
    own initial particles (the first 64 runs', bit for bit): the attacker optimised against
    the defender's random draws, which no attacker knows. Its draws are its own now; the
    study's are unchanged."""
    from types import SimpleNamespace

    from difffilter.eval import stealthy
    from difffilter.models import registry

    scenario = registry.get("four_tank_bias")
    captured = {}

    def fake_craft(estimator, model, ys, xs, tau, *, start, **kwargs):
        captured["start"] = start
        return SimpleNamespace(within_budget=lambda: [], history=[], budget=0.0, selection=None)

    monkeypatch.setattr(stealthy, "craft_stealthy_attack", fake_craft)
    calibration = SimpleNamespace(thresholds={"normal_pf": 0.5}, far=0.01)
    spec = stealthy.StealthySpec(against="normal_pf", onset=21, train_runs=8)
    stealthy.craft_threat("probe", spec, scenario, calibration, seed=0)
    crafting = captured["start"](8).particles
    _, study_start = stealthy.estimator_step(scenario, "normal_pf", runs=8, seed=0)
    study = study_start(8).particles
    assert crafting.shape == study.shape and not torch.equal(crafting, study)
    again = stealthy.estimator_step(scenario, "normal_pf", runs=8, seed=0)[1](8).particles
    assert torch.equal(again, study)  # the study's common random numbers as they were


def test_the_far_off_warning_is_left_out_for_a_detector_whose_alarms_fall_at_start_up(
    monkeypatch,
):
    """A review: crafting against normal_pf warned that its first batch's attack-free rate
    (none of the attacked steps) was far from the 1 % target, asking whether the threshold
    was calibrated and the inputs given, which they were: its calibrated alarms fall at
    start-up (``Calibration.startup``, said in the report). The warning stays for others."""
    import warnings
    from types import SimpleNamespace

    from difffilter.eval import stealthy
    from difffilter.models import registry

    def far_off(*args, **kwargs):
        if not kwargs.get("warn_far_off", True):  # (as the crafting does)
            return SimpleNamespace(within_budget=lambda: [], history=[], budget=0.0, selection=None)
        warnings.warn("craft_stealthy_attack: the detector alarms on 0 % of …", RuntimeWarning,
                      stacklevel=2)  # fmt: skip
        return SimpleNamespace(within_budget=lambda: [], history=[], budget=0.0, selection=None)

    monkeypatch.setattr(stealthy, "craft_stealthy_attack", far_off)
    scenario = registry.get("four_tank_bias")
    spec = stealthy.StealthySpec(against="normal_pf", onset=21, train_runs=2, selection_runs=2)
    for startup, expected in (({"normal_pf": {"alarms_at_first_step": 1.0}}, 0), ({}, 1)):
        calibration = SimpleNamespace(thresholds={"normal_pf": 0.5}, far=0.01, startup=startup)
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            stealthy.craft_threat("probe", spec, scenario, calibration, seed=0)
        assert sum("alarms on" in str(w.message) for w in seen) == expected, startup


def test_the_crafting_gives_the_detector_the_inputs_and_receptions_of_the_study():
    """From a threat-model trial: the crafting ran the detector without the plant's known
    inputs (and without the sensor schedule), so on a plant with inputs its attack-free
    steps alarmed at 49–73 % against a 1 % threshold and the budget bounded nothing (the
    crafted attack alarmed on 47 % of the study's attacked steps). Given the study's inputs
    and receptions, the first iterate's training rate is about the false-alarm rate."""
    from types import SimpleNamespace

    from difffilter.eval import stealthy
    from difffilter.loop import open_loop
    from difffilter.models.streams import Streams
    from difffilter.models.yaml_scenario import scenario_from_dict

    scenario = scenario_from_dict({
        "name": "motor_inputs", "runs": 8, "steps": 60, "dt": 0.1,
        "plant": {"F": [[0.9, 0.1], [0.0, 0.85]], "B": [[0.0], [0.5]],
                  "H": [[1.0, 0.0], [0.0, 1.0]], "Q": 1.0e-2, "R": 4.0e-2, "P0": 0.1},
        "inputs": {"kind": "sinusoid", "amplitude": 1.0, "frequency": 0.5},
        "schedule": {"kind": "packet_loss", "rate": 0.2},
        "estimators": ["chi_square_kf"],
    }, "motor.yaml")  # fmt: skip
    est, _ = stealthy.estimator_step(scenario, "chi_square_kf", runs=64, seed=0)
    tr = scenario.with_threat(None).simulate(64, Streams(5).simulation(), model=scenario.system())
    with torch.no_grad():
        free = open_loop(est, scenario.system(), tr.y_recv, tr.us, mask=tr.mask)
    tau = float(free.detection.scores[:, 20:].flatten().quantile(0.99))  # calibrated so
    spec = stealthy.StealthySpec.from_dict(
        {
            "kind": "stealthy",
            "against": "chi_square_kf",
            "onset": 21,
            "train_runs": 32,
            "iterations": 1,
        }  # fmt: skip
    )
    calibration = SimpleNamespace(thresholds={"chi_square_kf": tau}, far=0.01)
    _, report = stealthy.craft_threat("probe", spec, scenario, calibration, seed=0)
    assert report["history"][0]["alarm_rate"] < 0.05


def test_the_documented_study_start_runs_open_loop_on_the_carrys_own_model():
    """A docs trial (docs/threats.md): ``open_loop(estimator, scenario.system(), ys,
    carry=start(B))`` was refused, ``scenario.system()`` building a new model at every call,
    and the error only said to start the carry from that model (losing the study's common
    random numbers). The recipe is now ``carry = start(B)``, ``open_loop(estimator,
    carry.model, ys, carry=carry)``, and the error names it."""
    import difffilter as df
    from difffilter.eval import stealthy
    from difffilter.models import registry

    scenario = registry.get("four_tank_bias")
    estimator, start = stealthy.estimator_step(scenario, "normal_pf", runs=2, seed=0)
    carry = start(2)
    ys = torch.zeros(2, 3, carry.model.dim_y, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"open_loop\(estimator, carry\.model, ys, carry=carry\)"):
        df.open_loop(estimator, scenario.system(), ys, carry=carry)
    out = df.open_loop(estimator, carry.model, ys, carry=carry)
    assert out.means.shape == (2, 3, carry.model.dim_x) and torch.isfinite(out.means).all()


def test_a_repeated_entry_and_a_covert_signal_off_the_actuators_are_refused():
    """From a trial of the library: ``entries: [0, 0]`` (a typo for ``[0, 1]``) attacked
    entry 0 alone, silently, in every shaped threat and a stealthy threat set's entry (which
    failed only when crafted, after the calibration); a covert threat's signal written with
    ``channel: sensor`` (or any other) was moved to the actuators silently. Each is refused,
    naming the field; ``channel: actuator`` is still taken."""
    from difffilter.eval.stealthy import StealthySpec

    for kind, field in (("bias", {"value": 1.0}), ("ramp", {"slope": 0.1})):
        with pytest.raises(ValueError, match=r"entries must be distinct indices; got \[0, 0\]"):
            threat_from_dict({"kind": kind, **field, "entries": [0, 0]})
    with pytest.raises(ValueError, match="entries must be distinct measurement indices"):
        StealthySpec.from_dict({"kind": "stealthy", "against": "chi_square_kf", "entries": [1, 1]})
    plant = _plant()
    for channel in ("sensor", "replacement", "nonsense"):
        with pytest.raises(ValueError, match="a covert threat's signal acts on the actuators"):
            threat_from_dict({"kind": "covert", "signal": {"kind": "bias", "value": 0.1,
                                                            "channel": channel}}, plant)  # fmt: skip
    covert = threat_from_dict(
        {"kind": "covert", "signal": {"kind": "bias", "value": 0.1, "channel": "actuator"}}, plant
    )
    assert covert.signal.channel is Channel.ACTUATOR


def test_a_shaped_attack_of_ones_own_that_returns_the_wrong_shape_is_named():
    """An attack of one's own whose ``shape`` returns a column too many or a step too few had
    escaped ``check_attack_fits`` (and a YAML scenario's loader) as torch's raw expand
    error; ``Shaped.sample`` names the class, what it returned and what it must."""
    from dataclasses import dataclass

    from difffilter.threats import Shaped, check_attack_fits

    @dataclass(frozen=True)
    class Wide(Shaped):
        def shape(self, s, dim, batch, generator, dtype):
            return torch.ones(s.shape[0], dim + 1, dtype=dtype)

    @dataclass(frozen=True)
    class Short(Shaped):
        def shape(self, s, dim, batch, generator, dtype):
            return torch.ones(s.shape[0] - 1, dim, dtype=dtype)

    with pytest.raises(ValueError, match=r"Wide.shape returned \(30, 3\); it must return the "
                                         r"attack's values \[T, dim\] = \[30, 2\]"):  # fmt: skip
        check_attack_fits(Wide(), _plant(), 30)
    with pytest.raises(ValueError, match=r"Short.shape returned \(29, 2\)"):
        Short().sample((4,), 30, 2, dtype=F64)


def test_review_a_covert_channel_in_any_case_and_a_shape_that_broadcasts_are_taken():
    """A review of the checks above: a covert signal's ``channel: ACTUATOR`` (every other
    threat reads a channel in any case) had been refused, and an attack of one's own whose
    ``shape`` returns ``[T, 1]`` or ``[1, T, dim]`` (which broadcast, and ran before) too."""
    from dataclasses import dataclass

    from difffilter.threats import Shaped

    covert = threat_from_dict(
        {"kind": "covert", "signal": {"kind": "bias", "value": 0.1, "channel": "ACTUATOR"}},
        _plant(),
    )
    assert covert.signal.channel is Channel.ACTUATOR

    @dataclass(frozen=True)
    class Column(Shaped):
        def shape(self, s, dim, batch, generator, dtype):
            return torch.ones(s.shape[0], 1, dtype=dtype)

    @dataclass(frozen=True)
    class Lead(Shaped):
        def shape(self, s, dim, batch, generator, dtype):
            return torch.ones(1, s.shape[0], dim, dtype=dtype)

    for cls in (Column, Lead):
        values, _ = cls(onset=1).sample((3,), 5, 2, dtype=F64)
        assert values.shape == (3, 5, 2) and bool((values == 1).all())
