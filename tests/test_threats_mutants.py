"""Mutation review of the threat library, the threat distribution and the stealthy
crafting: each test pins one behaviour that a small mutant of the code changed and the
existing tests let through, against an independent truth (the formula evaluated by hand
in numpy on a tiny horizon, or the frequencies of a draw against their law within a few
standard errors, with a fixed seed)."""

from __future__ import annotations

import math

import numpy as np
import torch

from difffilter.threats import Bias, Ramp, Replay

F64 = torch.float64


def test_a_shaped_attack_tabulates_zero_outside_its_entries():
    """``a_k`` is zero outside ``entries`` (module docstring of threats: "Outside entries
    the value is zero"), not only unflagged: the table ``sample`` returns, checked
    against the bias written by hand in numpy on 4 steps."""
    for attack in (Bias((1.0, 2.0, 3.0), entries=(1,), onset=2), Ramp(0.5, entries=(0, 2))):
        values, flags = attack.sample((2,), 4, 3, torch.Generator().manual_seed(0), dtype=F64)
        k = np.arange(1, 5)
        on = k >= attack.onset
        picked = np.zeros(3, bool)
        picked[list(attack.entries)] = True
        if isinstance(attack, Bias):
            shape = np.broadcast_to(np.array([1.0, 2.0, 3.0]), (4, 3))
        else:
            shape = np.outer(k - attack.onset + 1, np.full(3, 0.5))
        expected = np.where(on[:, None] & picked, shape, 0.0)
        np.testing.assert_array_equal(values.numpy(), np.broadcast_to(expected, (2, 4, 3)))
        np.testing.assert_array_equal(
            flags.numpy(), np.broadcast_to(on[:, None] & picked, (2, 4, 3))
        )


def test_a_replay_attacks_its_share_of_runs_for_a_share_other_than_one_half():
    """A replay attacks a run with probability ``share`` (one Bernoulli per run, drawn at
    ``init``): the attacked fraction of 4,000 runs at ``share = 0.2`` is within 4
    standard errors of 0.2 (``√(0.2·0.8/4000) ≈ 0.0063``), and each run is attacked over the
    whole window or not at all."""
    replay = Replay(delay=2, onset=3, share=0.2)
    runs = 4000
    state = replay.init((runs,), 6, 1, torch.Generator().manual_seed(5), dtype=F64)
    flags = []
    y = torch.zeros(runs, 1, dtype=F64)
    for k in range(1, 7):
        state, _, flag = replay.step(state, k, y=y)
        flags.append(flag)
    flags = torch.stack(flags, -1)
    assert not flags[:, :2].any()
    attacked = flags[:, 2]
    assert torch.equal(flags[:, 2:], attacked.unsqueeze(-1).expand(runs, 4))
    se = math.sqrt(0.2 * 0.8 / runs)
    assert abs(float(attacked.double().mean()) - 0.2) < 4 * se


def _stealthy_setup():
    """A two-state plant (R = 10⁻³ I, σ = √10⁻³), its χ²-gated Kalman filter and 4
    attack-free runs of 6 steps drawn from seed ``seed``."""
    import difffilter as df
    from difffilter import fdi

    eye = torch.eye(2, dtype=F64)
    F = torch.diag(torch.tensor([0.95, 0.98], dtype=F64))
    zero = torch.zeros(2, dtype=F64)
    plant = df.LinearGaussianModel(F, eye, 1e-4 * eye, 1e-3 * eye, zero, 1e-3 * eye)
    est = fdi.GatedFilter(fdi.ChiSquareDetector(2, 0.01), df.KalmanFilter())
    return plant, est


def _simulate(plant, seed):
    xs, ys, _ = plant.simulate(6, (4,), generator=torch.Generator().manual_seed(seed))
    return xs, ys


def test_the_crafted_attack_touches_only_its_entries():
    """``entries``: the crafted attack is zero outside them. One iteration with a
    threshold no score reaches keeps the first iterate, the documented start ``init·σ``
    from the onset on, which numpy writes by hand: ``0.3·√10⁻³`` on entry 1 at steps
    ``k ≥ 3`` of 6, zero elsewhere (entry 0 included)."""
    from difffilter.stealthy import StealthySettings, craft_stealthy_attack

    plant, est = _stealthy_setup()
    xs, ys = _simulate(plant, 3)
    c = craft_stealthy_attack(est, plant, ys, xs, 1e9, far=0.01, onset=3, entries=(1,),
                              settings=StealthySettings(iterations=1), warn_far_off=False)  # fmt: skip
    expected = np.zeros((6, 2))
    expected[2:, 1] = 0.3 * math.sqrt(1e-3)
    np.testing.assert_allclose(c.values.numpy(), expected, rtol=1e-12, atol=0)


def test_each_resampled_batch_is_held_to_its_own_attack_free_rate():
    """With ``resample``, iterate ``i``'s budget (``history[i][4]``) is its own batch's
    attack-free alarm rate over the attacked steps plus ``ε`` (module docstring), counted
    here by hand in numpy from the filter's attack-free scores on that batch; ``τ`` is
    the median attack-free score so that the batches' rates differ."""
    from difffilter.loop import open_loop
    from difffilter.stealthy import StealthySettings, craft_stealthy_attack

    plant, est = _stealthy_setup()
    batches = [_simulate(plant, seed) for seed in (3, 11, 12)]
    onset, slack = 2, 0.01
    on = np.arange(1, 7) >= onset
    scores = [open_loop(est, plant, ys).detection.scores.numpy() for _, ys in batches]
    tau = float(np.median(scores[0][:, on]))
    free = [float((s[:, on] > tau).mean()) for s in scores]
    assert len(set(free)) > 1  # the batches alarm differently: the test can tell them apart
    c = craft_stealthy_attack(
        est, plant, batches[0][1], batches[0][0], tau, far=0.01, onset=onset,
        settings=StealthySettings(iterations=3, slack=slack), warn_far_off=False,
        resample=lambda it: (batches[it][1], batches[it][0]),
    )  # fmt: skip
    assert [h[4] for h in c.history] == [p + slack for p in free]
    assert c.budget == free[0] + slack


def test_every_entry_of_the_actuators_is_as_many_as_the_model_has_inputs():
    """``covers``: ``entries: null`` is the list of every entry of the threat's *channel*,
    ``[0 … du − 1]`` on the actuators and ``[0 … dy − 1]`` on the sensors. On a plant with
    ``dy = 2`` measurements and ``du = 1`` input, a component on the actuators with
    ``entries: [0]`` draws the actuator bias on every entry (written with ``null`` or left
    out), and one on the sensors with ``[0, 1]`` the sensor bias on every entry."""
    import difffilter as df
    from difffilter.threat_distribution import KIND_ONLY, WITHIN, ThreatDistribution

    eye = torch.eye(3, dtype=F64)
    H = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]], dtype=F64)
    B = torch.tensor([[0.0], [0.0], [1.0]], dtype=F64)
    model = df.LinearGaussianModel(0.9 * eye, H, 1e-2 * eye, 0.04 * torch.eye(2, dtype=F64),
                                   torch.zeros(3, dtype=F64), eye, B=B)  # fmt: skip
    assert (model.dim_u, model.dim_y) == (1, 2)
    bias = {"kind": "bias", "value": 0.5}
    actuator = ThreatDistribution(
        {"act": {"weight": 1, **bias, "channel": "actuator", "entries": [0]}}, model=model
    )
    assert actuator.covers({**bias, "channel": "actuator", "entries": None}) == WITHIN
    assert actuator.covers({**bias, "channel": "actuator"}) == WITHIN
    assert actuator.covers({**bias, "channel": "actuator", "entries": [0, 1]}) == KIND_ONLY
    sensor = ThreatDistribution({"s": {"weight": 1, **bias, "entries": [0, 1]}}, model=model)
    assert sensor.covers({**bias, "entries": None}) == WITHIN


def test_a_signed_field_is_checked_at_its_negated_extremes_at_construction():
    """A ``signed`` draw gives ``lo … hi`` and its negatives, so construction checks the
    threat at the negated extremes too: a sinusoid's ``dt`` drawn signed is negative in
    half of the draws (``dt`` must be positive), and is refused when the distribution is
    made, whatever the first draw (here, after the amplitude's draw, a positive one)."""
    import pytest

    from difffilter.threat_distribution import ThreatDistribution

    spec = {"weight": 1, "kind": "sinusoid", "amplitude": {"uniform": [1.0, 2.0]},
            "dt": {"uniform": [0.5, 1.0], "signed": True}}  # fmt: skip
    fields = {k: v for k, v in spec.items() if k != "weight"}
    from difffilter.threat_distribution import _draw

    g = torch.Generator().manual_seed(0)
    assert [_draw(v, g) for v in fields.values()][-1] > 0  # the first draw alone passes
    with pytest.raises(ValueError, match=r"threats\.s: dt must be"):
        ThreatDistribution({"s": spec})


def test_a_ksigma_bias_is_k_standard_deviations_for_any_k():
    """``a = k σ`` on every attacked entry (threats' table), for ``k`` other than the
    class default 1.5 (negative too): the table against ``k·σ`` written by hand in numpy
    from the onset on, zero before it."""
    from difffilter.threats import KSigmaBias

    sigma = np.array([0.2, 0.3])
    for k in (2.5, -0.7):
        values, _ = KSigmaBias(k=k, sigma=tuple(sigma), onset=2).sample((1,), 4, 2, dtype=F64)
        expected = np.zeros((4, 2))
        expected[1:] = k * sigma
        np.testing.assert_allclose(values[0].numpy(), expected, rtol=1e-15, atol=0)
