"""Mutation-review checks of the scenarios' attacks (:mod:`difffilter.models.attacks`), the
communication schedules (:mod:`difffilter.models.schedules`) and the physical-watermark
study (:mod:`difffilter.eval.watermark`).

Each test evaluates the docstring's rule or equation independently (plain Python / numpy
in float64 on a small case, a closed form of the Gilbert–Elliott chain, a Monte Carlo
limit with a stated tolerance, a Mann–Whitney AUC written out here) and compares the
library with it.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from difffilter.attack import Channel
from difffilter.models.attacks import ActuatorInjection, Replacement, SensorBias, Signal
from difffilter.models.schedules import BurstLoss, PacketLoss, RoundRobin

# ------------------------------------------------------------------ sensor bias (eqs 3-4)


def test_sensor_bias_values_flags_and_dtype_follow_eqs_3_and_4():
    """``values[t] = γ_{t+1} = (1 − τ^{t+1}) γ̄`` (closed form of eq. 4 with γ_0 = 0), cast to
    the requested dtype; ``l_k = 1`` iff ``u_k < p_l`` with ``u_k`` the float64 uniforms of
    the generator (the docstring's rule); a wrong measurement size is refused."""
    gb, tau, p_l, T = (2.0, -1.0), 0.7, 0.4, 6
    attack = SensorBias(gamma_bar=gb, tau=tau, p_l=p_l)
    values, flags = attack.sample((3,), T, 2, torch.Generator().manual_seed(5), dtype=torch.float32)
    k = np.arange(1, T + 1, dtype=np.float64)[:, None]
    expected = (1.0 - tau**k) * np.array(gb)
    assert values.dtype == torch.float32 and values.shape == (3, T, 2)
    np.testing.assert_allclose(values[1].double().numpy(), expected, rtol=1e-6)
    u = torch.rand((3, T), generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    assert np.array_equal(flags.numpy(), u.numpy() < p_l)
    with pytest.raises(ValueError):
        attack.sample((3,), T, 3, dtype=torch.float64)


def test_sensor_bias_accepts_the_closed_bernoulli_bounds():
    """``p_l ∈ [0, 1]`` (eq. 3): ``p_l = 0`` never attacks a packet and ``p_l = 1`` always."""
    gen = torch.Generator().manual_seed(0)
    never = SensorBias(gamma_bar=(1.0,), p_l=0.0).sample_flags((50,), 20, gen)
    always = SensorBias(gamma_bar=(1.0,), p_l=1.0).sample_flags((50,), 20, gen)
    assert not bool(never.any()) and bool(always.all())


# ------------------------------------------------------------------ actuator injection


def test_actuator_injection_flags_from_the_0_based_start_and_refuses_bad_input():
    """``u_applied,k = u_k + a`` for ``k ≥ start`` (0-based): with ``start = 2`` of 5 steps
    the flags are ``[F, F, T, T, T]``; a negative start and a wrong input size are refused
    (a one-entry ``a`` must not broadcast onto three inputs)."""
    values, flags = ActuatorInjection(value=(0.5, -1.0), start=2).sample(
        4, 5, 2, dtype=torch.float64
    )
    assert flags.tolist() == [[False, False, True, True, True]] * 4
    assert values.shape == (4, 5, 2) and bool((values == torch.tensor([0.5, -1.0])).all())
    with pytest.raises(ValueError):
        ActuatorInjection(value=(1.0,), start=-1)
    with pytest.raises(ValueError):
        ActuatorInjection(value=(1.0,)).sample(2, 5, 3, dtype=torch.float64)


# ------------------------------------------------------------------ replacement attack


def test_replacement_draws_are_uniform_on_the_box_at_the_stated_rate():
    """``ξ_k ~ U(low, high)``: every draw in ``[low, high)``, mean ``(low + high) / 2`` and
    flag rate ``rate`` within 5 standard errors over 40 000 draws (seeded)."""
    lo, hi, rate = (1.0, -3.0), (2.0, 5.0), 0.3
    attack = Replacement(rate=rate, low=lo, high=hi)
    gen = torch.Generator().manual_seed(11)
    for values, flags in (
        attack.sample((200,), 200, 2, gen, dtype=torch.float64),
        attack.sample_groups((200,), 200, [[0], [1]], gen, dtype=torch.float64),
    ):
        v = values.reshape(-1, 2).numpy()
        low, high = np.array(lo), np.array(hi)
        assert (v >= low).all() and (v < high).all()
        se = (high - low) / np.sqrt(12 * v.shape[0])
        assert np.all(np.abs(v.mean(0) - (low + high) / 2) < 5 * se)
        f = flags.double().mean().item()
        assert abs(f - rate) < 5 * np.sqrt(rate * (1 - rate) / flags.numel())


def test_replacement_groups_draw_flags_first_then_the_box():
    """``sample_groups``: flags ``[*, T, G]`` are the float64 uniforms of the generator below
    ``rate``, drawn first, then the box ``low + (high − low) U`` (its docstring); with a
    single group it is :meth:`sample` (same draws, same order)."""
    lo, hi, rate = (-1.0, 0.5, 2.0), (1.0, 1.5, 6.0), 0.4
    attack = Replacement(rate=rate, low=lo, high=hi)
    groups = [[0, 2], [1]]
    values, flags = attack.sample_groups(
        (3,), 4, groups, torch.Generator().manual_seed(2), dtype=torch.float64
    )
    ref = torch.Generator().manual_seed(2)
    u = torch.rand((3, 4, 2), generator=ref, dtype=torch.float64).numpy()
    box = torch.rand((3, 4, 3), generator=ref, dtype=torch.float64).numpy()
    assert flags.shape == (3, 4, 2)
    assert np.array_equal(flags.numpy(), u < rate)
    np.testing.assert_allclose(
        values.numpy(), np.array(lo) + (np.array(hi) - np.array(lo)) * box, rtol=1e-15
    )
    one_v, one_f = attack.sample_groups(
        (3,), 4, [[0, 1, 2]], torch.Generator().manual_seed(9), dtype=torch.float64
    )
    v, f = attack.sample((3,), 4, 3, torch.Generator().manual_seed(9), dtype=torch.float64)
    assert torch.equal(one_v, v) and torch.equal(one_f[..., 0], f)


def test_replacement_entry_flags_and_injection_per_group():
    """Each entry takes its group's flag, and a flagged group's entries are replaced by the
    draws while the others keep the signal: a literal 1 × 2-step case with groups
    ``[[0, 3], [1, 2]]``."""
    groups = [[0, 3], [1, 2]]
    flags = torch.tensor([[[True, False], [False, True]]])
    assert Replacement.entry_flags(flags, groups).tolist() == [
        [[True, False, False, True], [False, True, True, False]]
    ]
    attack = Replacement(rate=0.5, low=(0.0,) * 4, high=(1.0,) * 4)
    signal = torch.arange(8.0).reshape(1, 2, 4)
    values = -torch.arange(1.0, 9.0).reshape(1, 2, 4)
    out = attack.inject_groups(signal, values, flags, groups)
    assert out.tolist() == [[[-1.0, 1.0, 2.0, -4.0], [4.0, -6.0, -7.0, 7.0]]]


def test_replacement_refuses_degenerate_or_mismatched_boxes():
    """``low < high`` entry by entry, equal lengths: a zero-width or ragged box is refused."""
    with pytest.raises(ValueError):
        Replacement(rate=0.1, low=(0.0, 1.0), high=(1.0, 1.0))
    with pytest.raises(ValueError):
        Replacement(rate=0.1, low=(0.0, 0.0), high=(1.0,))
    # sensor groups that do not cover the box's entries exactly once
    gen = torch.Generator().manual_seed(0)
    one = Replacement(rate=0.5, low=(0.0,), high=(1.0,))
    with pytest.raises(ValueError, match="cover the 1 measurement entries"):
        one.sample_groups(1, 2, [[0], [1]], gen, dtype=torch.float64)
    with pytest.raises(ValueError, match="cover the 2 measurement entries"):
        Replacement.entry_flags(torch.zeros(1, 2, 2, dtype=torch.bool), [[1], [2]])
    # an infinite box drew NaN measurements (U(−∞, ∞)): refused, as the other attacks refuse
    # non-finite values
    for low, high in (((-math.inf,), (math.inf,)), ((0.0,), (math.inf,)), ((math.nan,), (1.0,))):
        with pytest.raises(ValueError, match="finite boxes"):
            Replacement(rate=0.5, low=low, high=high)


# ------------------------------------------------------------------ known signal


def test_signal_flags_its_nonzero_entries_and_refuses_malformed_signals():
    """An entry is flagged where the signal is non-zero (a step where any is); a ``[1, dim]``
    signal (would broadcast to a constant attack), a 1-D one and a non-finite one are
    refused; the signal acts on the channel it is given (default the sensor channel)."""
    values = torch.tensor([[0.0, 0.0], [0.0, 2.0], [3.0, 4.0]])
    _, flags = Signal(values).sample(2, 3, 2, dtype=torch.float64)
    assert flags.tolist() == [[[False, False], [False, True], [True, True]]] * 2
    with pytest.raises(ValueError):
        Signal(torch.ones(1, 2)).sample(2, 3, 2, dtype=torch.float64)
    with pytest.raises(ValueError):
        Signal(torch.ones(3))
    assert Signal(values, channel="actuator").channel == Channel.ACTUATOR
    assert Signal(values).channel == Channel.SENSOR
    with pytest.raises(ValueError):
        Signal(torch.tensor([[0.0, float("nan")]]))


# ------------------------------------------------------------------ Round-Robin


def test_round_robin_mask_is_eq_3_of_the_rrp_paper():
    """``γ_k = mod(k + γ_ini − 2, n) + 1`` (1-based group at 1-based step ``k``) with
    ``start = γ_ini − 1``, evaluated in plain Python: the received entries are exactly
    those of group ``γ_k``, for three two-entry groups and ``start = 1``."""
    groups = ((0, 1), (2, 3), (4, 5))
    n, start, T = 3, 1, 7
    mask = RoundRobin(groups, start=start).mask((2,), T, 6)
    gamma_ini = start + 1
    expected = []
    for k in range(1, T + 1):
        g = (k + gamma_ini - 2) % n + 1
        expected.append([i in groups[g - 1] for i in range(6)])
    assert mask.shape == (2, T, 6)
    assert mask[0].tolist() == expected and mask[1].tolist() == expected


def test_round_robin_with_one_group_receives_everything():
    """``n = 1``: ``γ_k = mod(k + γ_ini − 2, 1) + 1 = 1`` at every step, so every entry is
    received at every step."""
    assert bool(RoundRobin(((0, 1, 2),)).mask((2,), 5, 3).all())


def test_round_robin_and_packets_refuse_bad_groups():
    """Groups must cover every entry exactly once: a missing entry, an entry in two groups
    and a negative start are refused."""
    with pytest.raises(ValueError):
        RoundRobin(((0,), (2,))).mask(1, 3, 3)
    with pytest.raises(ValueError):
        RoundRobin(((0, 1), (1, 2)))
    with pytest.raises(ValueError):
        RoundRobin(((0,), (1,)), start=-1)


# ------------------------------------------------------------------ packet loss


def test_packet_loss_drops_whole_packets_at_the_rate():
    """With ``packets`` the entries of a packet arrive together (one draw per packet and
    step), the mask is ``[*, T, dy]``, and the arrival rate is ``1 − rate`` within 5
    standard errors; ``rate = 1`` (nothing would arrive) is refused."""
    rate = 0.25
    mask = PacketLoss(rate, packets=((0, 2), (1, 3))).mask(
        (400,), 100, 4, torch.Generator().manual_seed(3)
    )
    assert mask.shape == (400, 100, 4)
    assert torch.equal(mask[..., 0], mask[..., 2]) and torch.equal(mask[..., 1], mask[..., 3])
    assert not torch.equal(mask[..., 0], mask[..., 1])
    arrived = mask[..., :2].double().mean().item()
    assert abs(arrived - (1 - rate)) < 5 * np.sqrt(rate * (1 - rate) / (400 * 100 * 2))
    with pytest.raises(ValueError):
        PacketLoss(1.0)


# ------------------------------------------------------------------ burst loss (Gilbert-Elliott)


def _gilbert_elliott(to_bad, to_good, loss_good, loss_bad):
    """Closed forms in numpy float64: stationary law, the per-step loss rate and the joint
    probability that two consecutive measurements are both lost."""
    pi = np.array([to_good, to_bad]) / (to_bad + to_good)  # (G, B)
    P = np.array([[1 - to_bad, to_bad], [to_good, 1 - to_good]])
    loss = np.array([loss_good, loss_bad])
    rate = pi @ loss
    both = sum(pi[s] * P[s, t] * loss[s] * loss[t] for s in range(2) for t in range(2))
    return rate, both


def test_burst_loss_rate_property_is_the_stationary_loss_rate():
    """``rate = π_B · loss_bad + (1 − π_B) · loss_good`` with ``π_B = to_bad / (to_bad +
    to_good)``, against the closed form."""
    channel = BurstLoss(to_bad=0.2, to_good=0.6, loss_good=0.05, loss_bad=0.9)
    rate, _ = _gilbert_elliott(0.2, 0.6, 0.05, 0.9)
    assert channel.bad_share == pytest.approx(0.25, abs=1e-15)
    assert channel.rate == pytest.approx(rate, abs=1e-15)


def test_burst_loss_monte_carlo_matches_the_markov_chain():
    """Monte Carlo over 100 000 independent links (seeded): at each of the first steps the
    loss rate is the stationary one (the chain starts in its stationary law) and the
    share of (step 0, step 1) and (step 2, step 3) both lost is ``Σ π_s P_{st} l_s l_t``
    (the chain's transition, a loss drawn independently of the move); tolerance 0.006,
    about 4 standard errors."""
    to_bad, to_good, lg, lb = 0.3, 0.6, 0.1, 0.9
    mask = BurstLoss(to_bad, to_good, loss_good=lg, loss_bad=lb).mask(
        (50_000,), 4, 2, torch.Generator().manual_seed(7)
    )
    lost = (~mask).double().numpy()  # [N, T, links]
    rate, both = _gilbert_elliott(to_bad, to_good, lg, lb)
    for k in range(4):
        assert abs(lost[:, k].mean() - rate) < 0.006, k
    for k in (0, 2):
        assert abs((lost[:, k] * lost[:, k + 1]).mean() - both) < 0.006, k


def test_burst_loss_first_transition_is_a_fresh_draw():
    """The defaults (loss 0 in G, 1 in B) make the state visible: ``P(lost at step 2 |
    lost at step 1) = 1 − to_good`` for the chain's first move too (a fresh uniform, not
    the one that drew the initial state), Monte Carlo over 100 000 links, tolerance 0.01."""
    to_bad, to_good = 0.3, 0.6
    lost = ~BurstLoss(to_bad, to_good).mask((100_000,), 3, 1, torch.Generator().manual_seed(1))
    lost = lost[..., 0].numpy()
    for k in (0, 1):
        stay = lost[lost[:, k], k + 1].mean()
        assert abs(stay - (1 - to_good)) < 0.01, k
        come = lost[~lost[:, k], k + 1].mean()
        assert abs(come - to_bad) < 0.01, k


def test_burst_loss_refuses_parameters_outside_their_ranges():
    """``to_bad, to_good ∈ (0, 1]`` and ``loss_good < 1``."""
    with pytest.raises(ValueError):
        BurstLoss(to_bad=0.0, to_good=0.5)
    with pytest.raises(ValueError):
        BurstLoss(to_bad=0.5, to_good=0.0)
    with pytest.raises(ValueError):
        BurstLoss(to_bad=0.5, to_good=0.5, loss_good=1.0)


# ------------------------------------------------------------------ the watermark study


def test_watermark_cost_is_the_lqr_weighted_mean_over_the_control_inputs():
    """``J = mean over runs and steps of ‖X_k‖² + ‖U_k‖²`` with ``U = [U_1, U_2]`` (the
    load entries of ``us`` carry no cost), against numpy on a random 2 × 3 case."""
    from difffilter.eval.watermark import _cost

    rng = np.random.default_rng(0)
    x, us = rng.normal(size=(2, 3, 4)), rng.normal(size=(2, 3, 4))
    loop = SimpleNamespace(
        trajectories=SimpleNamespace(x=torch.from_numpy(x), us=torch.from_numpy(us))
    )
    expected = (x**2).sum(-1).mean() + (us[..., :2] ** 2).sum(-1).mean()
    assert _cost(loop) == pytest.approx(expected, rel=1e-14)


def _mann_whitney(scores, flags):
    """Pooled ROC AUC by the Mann–Whitney count (ties half), numpy float64."""
    pos, neg = scores[flags], scores[~flags]
    greater = (pos[:, None] > neg[None, :]).sum() + 0.5 * (pos[:, None] == neg[None, :]).sum()
    return greater / (pos.size * neg.size)


def test_watermark_study_rows_against_their_definitions(monkeypatch):
    """On 2 runs, every row against its definition recomputed from the loops the study ran
    (spied): the AUC and TPR over the full-window steps (0-based ``t ≥ w − 1``), the AUC
    after the splice without the windows containing the first replayed step (1-based
    ``onset``), the threshold from the calibration runs (``far = 1 %``), the false-alarm
    rate of the study's attack-free runs at it, the attack-free control cost of the study
    runs and its relative increase; the seamless replay models the closed loop
    ``A − B K₁``, and the calibration runs' watermark is drawn from another seed than the
    study runs'."""
    from difffilter.eval import watermark
    from difffilter.models import registry
    from difffilter.models.lfc import LFCPlant, lqr_gain

    calls, seeds = [], []
    real_loop, real_mark = watermark.lfc_loop, watermark.Watermarked

    def spy(plant, estimator, xi, theta, load, attack=None, **kw):
        out = real_loop(plant, estimator, xi, theta, load, attack=attack, **kw)
        calls.append((attack, kw.get("watermark") is not None, out))
        return out

    def mark(inner, std, gen):
        seeds.append(gen.initial_seed())
        return real_mark(inner, std, gen)

    monkeypatch.setattr(watermark, "lfc_loop", spy)
    monkeypatch.setattr(watermark, "Watermarked", mark)
    w, onset = 50, 700
    scenario = registry.get("lfc_step")
    doc = watermark.watermark_study(scenario, runs=2, window=w, onset=onset, seed=0)
    # per watermark setting: calibration, clean study, plain replay, seamless replay
    assert len(calls) == 8
    costs = {}
    for i, marked in ((0, "without watermark"), (4, "with watermark")):
        _, _, clean = calls[i + 1]
        # threshold: the smallest τ with #{s > τ} ≤ ⌊α n⌋ over the calibration runs' full
        # windows (α = 1 %), and the false-alarm rate of the study's attack-free runs at it
        cal = np.sort(calls[i][2].output.detection.scores[:, w - 1 :].double().numpy().ravel())
        tau = cal[::-1][int(np.floor(0.01 * cal.size))]
        free = clean.output.detection.scores[:, w - 1 :].double().numpy()
        tr = clean.trajectories
        x, us = tr.x.double().numpy(), tr.us.double().numpy()
        costs[marked] = (x**2).sum(-1).mean() + (us[..., :2] ** 2).sum(-1).mean()
        for j, label in ((2, "plain replay"), (3, "seamless replay")):
            attack, _, out = calls[i + j]
            row = doc["rows"][f"{label}, {marked}"]
            scores = out.output.detection.scores.double().numpy()
            flags = out.trajectories.flags.numpy().astype(bool)
            t = np.arange(scores.shape[1])
            full = t >= w - 1
            s, f = scores[:, full], flags[:, full]
            assert row["auc"] == pytest.approx(_mann_whitney(s.ravel(), f.ravel()), abs=1e-12)
            assert row["tpr_at_far"] == pytest.approx((s[f] > row["threshold"]).mean(), abs=1e-15)
            sees = (t - w + 1 <= onset - 1) & (onset - 1 <= t)  # window holds step `onset`
            keep = full & ~sees
            after = _mann_whitney(scores[:, keep].ravel(), flags[:, keep].ravel())
            assert row["auc_after_splice"] == pytest.approx(after, abs=1e-12)
            assert row["control_cost"] == pytest.approx(costs[marked], rel=1e-12)
            assert row["threshold"] == pytest.approx(tau, rel=1e-12)
            assert row["fpr_at_far"] == pytest.approx((free > tau).mean(), abs=1e-15)
            if label == "seamless replay":
                plant = LFCPlant(dt=scenario.dt)
                phi = (plant.Ad - plant.Bd @ lqr_gain(plant)).double().numpy()
                np.testing.assert_allclose(np.asarray(attack.loop[0], dtype=float), phi, atol=1e-12)
    increase = costs["with watermark"] / costs["without watermark"] - 1
    assert doc["control_cost_increase"] == pytest.approx(increase, rel=1e-9)
    # watermark generators: calibration, study (clean), study (2 replays)
    assert len(seeds) == 4 and seeds[0] != seeds[1] and seeds[1] == seeds[2] == seeds[3]


@pytest.mark.parametrize(
    ("steps", "window", "onset"), [(40, 5, 12), (40, 5, 3), (40, 5, 1), (40, 5, 36), (12, 4, 9)]
)
def test_the_windows_left_out_after_the_splice_are_those_holding_the_onset(steps, window, onset):
    """The windows left out of the AUC after the splice, by brute force: the full window
    ending at 1-based step ``s`` holds steps ``s − w + 1 … s``; it is left out exactly
    where it holds ``onset``. An onset earlier than the window had wrapped the slice round
    to the end of the run and left out none."""
    from difffilter.eval.watermark import windows_past_splice

    ends = range(window, steps + 1)
    expected = [not (s - window + 1 <= onset <= s) for s in ends]
    assert windows_past_splice(steps, window, onset).tolist() == expected
