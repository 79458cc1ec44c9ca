"""Two-area LFC plant, attack generators and scenario registry (models/lfc.py)."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.control import controllability_rank, zoh_discretize
from difffilter.models import registry
from difffilter.models.lfc import (
    EXCLUDED_OMEGA,
    LFCParameters,
    LFCPlant,
    continuous_model,
    random_attacks,
    sawtooth_pulse_train,
    scenario_attack,
)


def _rk4(A, B, x, u, dt, substeps=2000):
    """Fine RK4 integration of ẋ = Ax + Bu with u held constant."""
    h = dt / substeps

    def f(v):
        return A @ v + B @ u

    for _ in range(substeps):
        k1 = f(x)
        k2 = f(x + 0.5 * h * k1)
        k3 = f(x + 0.5 * h * k2)
        k4 = f(x + h * k3)
        x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


@pytest.mark.parametrize("dt", [0.01, 0.001, 0.2])
def test_zoh_matches_fine_integration(dt):
    A, B, F = continuous_model()
    g = torch.Generator().manual_seed(3)
    x0 = torch.randn(10, generator=g, dtype=torch.float64)
    u = torch.randn(4, generator=g, dtype=torch.float64)
    BF = torch.cat([B, F], dim=1)
    Ad, BFd = zoh_discretize(A, BF, dt)
    exact = Ad @ x0 + BFd @ u
    fine = _rk4(A, BF, x0, u, dt)
    assert torch.allclose(exact, fine, atol=1e-11, rtol=1e-9)


def test_plant_buffers_and_structure():
    plant = LFCPlant(dt=0.01)
    A, B, F = plant.A, plant.B, plant.F
    p = LFCParameters()
    # Spot checks of eqs (35)-(41).
    assert A[0, 0] == pytest.approx(-p.damping[0] / p.inertia[0])
    assert A[2, 0] == pytest.approx(-1 / (p.droop[0] * p.governor_time[0]))
    assert A[3, 0] == pytest.approx(2 * math.pi * p.tie_stiffness)
    assert A[3, 5] == pytest.approx(-2 * math.pi * p.tie_stiffness)
    assert A[8, 0] == pytest.approx(-2 * math.pi * p.tie_stiffness)
    assert A[9, 5] == pytest.approx(p.freq_bias[1]) and A[9, 8] == 1.0
    assert B[2, 0] == pytest.approx(1 / p.governor_time[0]) and B[7, 1] == pytest.approx(1 / 0.17)
    assert F[0, 0] == pytest.approx(-1 / p.inertia[0]) and F[5, 1] == pytest.approx(-1 / 12)
    # The sum of the tie-line flows is conserved: e4 + e9 is a left null vector of [A, B].
    w = torch.zeros(10, dtype=torch.float64)
    w[3] = w[8] = 1.0
    assert torch.allclose(w @ A, torch.zeros(10, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(w @ B, torch.zeros(2, dtype=torch.float64))
    assert torch.equal(plant.C, torch.eye(10, dtype=torch.float64))
    one_ms = LFCPlant(dt=0.001)
    # Same process-noise intensity at both sampling times (1e-6 per 10 ms step).
    assert plant.process_var == pytest.approx(1e-6) and one_ms.process_var == pytest.approx(1e-7)
    # Ten 1 ms steps equal one 10 ms step (semigroup property of the exact ZOH).
    assert torch.allclose(torch.linalg.matrix_power(one_ms.Ad, 10), plant.Ad, atol=1e-12)


def test_controllability_rank_is_nine():
    A, B, _ = continuous_model()
    assert controllability_rank(A, B) == 9
    # With one tie-line flow also actuated the system becomes controllable.
    B2 = torch.cat([B, torch.eye(10, dtype=torch.float64)[:, 3:4]], dim=1)
    assert controllability_rank(A, B2) == 10


def test_plant_noise_is_seeded():
    plant = LFCPlant()
    a = plant.sample_noise(3, 7, torch.Generator().manual_seed(1))
    b = plant.sample_noise(3, 7, torch.Generator().manual_seed(1))
    assert a[0].shape == (3, 7, 10) and torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    big = plant.sample_noise(200, 200, torch.Generator().manual_seed(2))
    assert big[0].std().item() == pytest.approx(1e-3, rel=0.02)
    assert big[1].std().item() == pytest.approx(1e-2, rel=0.02)
    with pytest.raises(ValueError, match="generator"):
        plant.sample_noise(1, 1, None)


def test_scenario_attacks_exact_values():
    t = 0.01 * torch.arange(1, 1001, dtype=torch.float64)
    step = scenario_attack("step", t)
    assert step[298, 2] == 0 and step[299, 2] == 0.4 and step[499, 2] == 0.4 and step[500, 2] == 0
    assert step[600, 2] == 0 and step[699, 2] == 0.9 and step[799, 2] == 0.9 and step[800, 2] == 0
    assert step[:, [0, 1, 3, 4, 5, 6, 7, 8, 9]].abs().sum() == 0
    sine = scenario_attack("sine", t)
    assert sine[298, 2] == 0
    assert sine[299, 2].item() == pytest.approx(1.5 * math.sin(30.0))
    assert sine[549, 2].item() == pytest.approx(1.5 * math.sin(55.0))
    sim = scenario_attack("simultaneous", t)
    assert sim[8, 2] == 0 and sim[9, 2] == 0.6 and sim[499, 2] == 0.6 and sim[500, 2] == 0
    assert sim[699, 2] == 1.2 and sim[799, 2] == 1.2 and sim[800, 2] == 0
    assert sim[9, 7].item() == pytest.approx(0.9 * math.sin(1.0))
    assert sim[249, 7].item() == pytest.approx(0.9 * math.sin(25.0))
    assert sim[600, 7] == 0 and sim[749, 7] == pytest.approx(0.1)
    saw = scenario_attack("sawtooth", t)
    # pulstran(t, 0:0.5:10, tripuls(., 0.2, 1)): a ramp from 0 at d-0.1 to 1 at d+0.1, then 0.
    assert saw[0, 2].item() == pytest.approx(0.55)  # t = 0.01 on the first pulse (d = 0)
    assert saw[8, 2].item() == pytest.approx(0.95) and saw[9, 2] == 0  # t = 0.09, 0.10
    assert saw[39, 2].item() == 0.0  # t = 0.40: the ramp starts at 0, exactly (not 1e-15)
    assert saw[40, 2].item() == pytest.approx(0.05)  # t = 0.41
    assert saw[49, 2].item() == pytest.approx(0.5) and saw[58, 2].item() == pytest.approx(0.95)
    assert saw[59, 2] == 0
    assert saw[:, 2].max().item() == pytest.approx(0.95)
    assert torch.equal(scenario_attack("none", t), torch.zeros(1000, 10, dtype=torch.float64))
    with pytest.raises(ValueError, match="LFCAttack"):
        scenario_attack("bogus", t)
    with pytest.raises(ValueError, match="random_attacks"):
        scenario_attack("random", t)


def test_the_sawtooth_is_exactly_zero_at_every_ramp_start():
    """Round-off at the ramp starts (k·dt against the pulse's start) left 1e-15 at 16 of
    the 20 starts, which counted those steps as attacked: 396 flagged steps a run, not 380,
    and every detection rate of lfc_sawtooth about 0.04 low."""
    t = 0.01 * torch.arange(1, 1001, dtype=torch.float64)
    saw = sawtooth_pulse_train(t)
    assert int((saw != 0).sum()) == 20 * 19  # 20 pulses of 19 nonzero steps (0.01 … 0.19)
    assert saw[saw != 0].min().item() == pytest.approx(0.05)


def test_sawtooth_general_skew():
    t = torch.linspace(-0.3, 0.3, 601, dtype=torch.float64)
    sym = sawtooth_pulse_train(t, width=0.2, period=10.0, skew=0.0, start=0.0, stop=0.0)
    # Symmetric triangle: peak 1 at 0, zero beyond ±0.1, value 0.5 at ±0.05.
    assert sym[300].item() == pytest.approx(1.0)
    assert sym[250].item() == pytest.approx(0.5) and sym[350].item() == pytest.approx(0.5)
    assert sym[:195].abs().sum() == 0 and sym[405:].abs().sum() == 0


def test_registry_entries():
    assert {"lfc_step", "lfc_sine", "lfc_simultaneous", "lfc_sawtooth", "lfc_sine_1ms"} <= set(
        registry.names(family="lfc")
    )
    sc = registry.get("lfc_simultaneous")
    assert sc.attacked_channels == (2, 7) and sc.steps == 1000 and sc.family == "lfc"
    assert sc.paper_table["proposed_ad"] == pytest.approx(0.133867)
    assert any("[DEF]" in n for n in sc.notes)
    one_ms = registry.get("lfc_sine_1ms")
    assert one_ms.steps == 10000
    a10 = registry.get("lfc_sine").attack_signal()
    a1 = one_ms.attack_signal()
    assert torch.allclose(a1[9::10], a10, atol=1e-12)


def test_random_attacks_seeded_and_shaped():
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    a = random_attacks(64, 500, 0.01, generator=g1)
    b = random_attacks(64, 500, 0.01, generator=g2)
    assert a.shape == (64, 500, 10) and torch.equal(a, b)
    assert a.abs().max() <= 2.0 * 3 + 1e-9  # up to three events may add on one channel
    assert (a.abs().sum(dim=(1, 2)) == 0).any()  # some runs are attack-free
    only = random_attacks(
        32, 300, 0.01, generator=torch.Generator().manual_seed(1), channels=(4,), min_events=1
    )
    others = [c for c in range(10) if c != 4]
    assert only[..., others].abs().sum() == 0 and (only[..., 4].abs().sum(1) > 0).all()
    with pytest.raises(ValueError, match="channels"):
        random_attacks(2, 10, 0.01, generator=torch.Generator(), channels=(12,))
    with pytest.raises(ValueError, match="generator"):
        random_attacks(2, 10, 0.01, generator=None)


def test_random_sinusoids_avoid_the_test_carrier():
    # One sinusoid per run on channel 0: its dominant frequency must avoid 9..11 rad/s.
    g = torch.Generator().manual_seed(11)
    n, T, dt = 400, 2000, 0.01
    a = random_attacks(n, T, dt, generator=g, channels=(0,), min_events=1, max_events=1)[..., 0]
    spec = torch.fft.rfft(a, dim=1).abs()
    freqs = 2 * math.pi * torch.fft.rfftfreq(T, d=dt)
    peak = freqs[spec[:, 1:].argmax(dim=1) + 1]
    # Steps/ramps/pulse trains put their peak at low frequency; no sinusoid peaks in the band.
    lo, hi = EXCLUDED_OMEGA
    assert not bool(((peak > lo + 0.2) & (peak < hi - 0.2)).any())


def test_an_actuator_attack_acts_on_the_control_inputs_and_a_covert_one_there_conceals():
    """The LFC input is ``[U₁, U₂, ΔP_l1, ΔP_l2]``; the loads are the plant's, and the
    observers' model (the covert attacker's) has no load columns. A covert attack whose
    signal left ``entries`` out (all four) had concealed nothing: the received measurement
    0.017 off the attack-free one (a trial). An actuator attack on the loads is refused,
    by the loop and by ``with_threat``; on ``U₁`` the covert attack hands the receiver the
    attack-free measurement (float64 round-off). Truth: the attack-free loop on the same
    draws."""
    import difffilter as df
    from difffilter.models.lfc import LFCPlant, lfc_loop
    from difffilter.models.streams import Streams
    from difffilter.threats import Bias, threat_from_dict

    sc = registry.get("lfc_step")
    d = sc.exogenous(2, {k: Streams(0)(k) for k in ("plant", "attack")})
    xi, theta = d["xi"][:, :330], d["theta"][:, :330]
    plant, model = LFCPlant(dt=sc.dt, dtype=xi.dtype), sc.system()

    def covert(entries):
        signal = {"kind": "bias", "value": 0.01, "onset": 300}
        if entries != "all":
            signal["entries"] = entries
        return threat_from_dict({"kind": "covert", "signal": signal}, model)

    for attack in (covert("all"), covert([2]), covert([1, 3]),
                   Bias(0.1, channel="actuator", onset=300)):  # fmt: skip
        with pytest.raises(ValueError, match="acts on the control inputs U1, U2"):
            lfc_loop(plant, df.KalmanFilter(), xi, theta, d["load"], attack=attack)
        with pytest.raises(ValueError, match="the loads, which no network carries"):
            sc.with_threat(attack)
    free = lfc_loop(plant, df.KalmanFilter(), xi, theta, d["load"], compensate=False)
    run = lfc_loop(plant, df.KalmanFilter(), xi, theta, d["load"], attack=covert([0]),
                   compensate=False)  # fmt: skip
    assert float((run.trajectories.x - free.trajectories.x).abs().max()) > 1e-3  # it acts
    received = run.trajectories.y_recv - free.trajectories.y_recv
    assert float(received.abs().max()) < 1e-12
    sc.with_threat(covert([0, 1]))  # the control inputs: taken
