"""What a trial of the threat models found: the stealthy crafting's budget under a mask, the
coverage of covert threats, a choice of covert signals with random fields, the robustness
study's sizes and a seamless replay's settings."""

import pytest
import torch

import difffilter as df
from difffilter.fdi import ChiSquareDetector, GatedFilter
from difffilter.loop import DrawnNoise, closed_loop, open_loop
from difffilter.stealthy import (
    CraftedAttack,
    StealthySettings,
    attacked_pairs,
    craft_stealthy_attack,
)
from difffilter.threat_distribution import HELD_OUT, KIND_ONLY, WITHIN, ThreatDistribution
from difffilter.threats import Replay, check_attack_fits

F64 = torch.float64
EYE = torch.eye(2, dtype=F64)


def _tanks():
    return df.LinearGaussianModel(torch.diag(torch.tensor([0.95, 0.98], dtype=F64)), EYE,
                                  1e-4 * EYE, 1e-3 * EYE, torch.zeros(2, dtype=F64),
                                  1e-3 * EYE)  # fmt: skip


def _round_robin(runs: int, steps: int, sensors: int) -> torch.Tensor:
    """Sensor ``(k − 1) mod sensors`` alone delivers step ``k`` (1-based)."""
    mask = torch.zeros(runs, steps, sensors, dtype=torch.bool)
    for s in range(sensors):
        mask[:, s::sensors, s] = True
    return mask


# -- difffilter/stealthy.py: the budget over the steps the loop flags -----------------------
@pytest.mark.filterwarnings("ignore:craft_stealthy_attack:RuntimeWarning")
def test_the_crafting_holds_the_rates_and_error_over_the_steps_the_loop_flags():
    """Under a Round-Robin mask with ``entries=(0,)`` the loop flags a step attacked only
    where entry 0 arrives (every other step): the first iterate's alarm rate, its budget
    ``p(0) + ε`` and ``J`` are those over these (run, step) pairs, recomputed here from the
    loop's own flags. (They had been over every step from the onset: the budget ε bounded a
    rise diluted by the steps without the attacked entry, 1.5 ε and 4.4 ε in a trial.)"""
    tanks, steps, onset, runs = _tanks(), 30, 5, 8
    mask = _round_robin(runs, steps, 2)
    xs, ys, _ = tanks.simulate(steps, (runs,), generator=torch.Generator().manual_seed(1))
    gated, tau, init = GatedFilter(ChiSquareDetector(2, 0.005), df.KalmanFilter()), 2.0, 3.0
    settings = StealthySettings(iterations=1, init=init, slack=0.05)
    crafted = craft_stealthy_attack(gated, tanks, ys, xs, tau, far=0.01, mask=mask,
                                    onset=onset, entries=(0,), settings=settings,
                                    warn_far_off=False)  # fmt: skip
    values = torch.zeros(steps, 2, dtype=F64)  # the first iterate: init σ₀ on entry 0
    values[onset - 1 :, 0] = init * 1e-3**0.5
    loop = closed_loop(tanks, steps, noise=DrawnNoise(torch.Generator().manual_seed(0)),
                       x0=torch.zeros(runs, 2, dtype=F64), mask=mask,
                       attack=CraftedAttack(values, onset, entries=(0,)))  # fmt: skip
    flagged = loop.trajectories.flags
    assert int(flagged.sum()) == runs * 13  # steps 5, 7, …, 29: entry 0's, from the onset
    assert torch.equal(attacked_pairs(runs, steps, onset, (0,), mask), flagged)
    with torch.no_grad():
        free = open_loop(gated, tanks, ys, mask=mask)
        attacked = open_loop(gated, tanks, ys + values, mask=mask)
    rate = float((attacked.detection.scores > tau)[flagged].double().mean())
    budget = float((free.detection.scores > tau)[flagged].double().mean()) + 0.05
    error = float((attacked.means - xs).square().sum(-1)[flagged].mean())
    everywhere = float((attacked.detection.scores > tau)[:, onset - 1 :].double().mean())
    assert abs(rate - everywhere) > 0.02  # (the old set of steps reads another rate)
    _, j, _, p, b = crafted.history[0]
    assert p == pytest.approx(rate, abs=1e-12)
    assert b == pytest.approx(budget, abs=1e-12)
    assert j == pytest.approx(error, rel=1e-9)


def test_a_batch_that_receives_no_attacked_entry_is_refused_naming_it():
    tanks, steps = _tanks(), 12
    mask = torch.ones(4, steps, 2, dtype=torch.bool)
    mask[..., 0] = False  # entry 0 never arrives
    xs, ys, _ = tanks.simulate(steps, (4,), generator=torch.Generator().manual_seed(0))
    gated = GatedFilter(ChiSquareDetector(2, 0.005), df.KalmanFilter())
    with pytest.raises(ValueError, match="the training batch receives no attacked entry"):
        craft_stealthy_attack(gated, tanks, ys, xs, 2.0, far=0.01, mask=mask, onset=3,
                              entries=(0,), settings=StealthySettings(iterations=1),
                              warn_far_off=False)  # fmt: skip


def test_the_crafted_reports_steps_are_those_the_loop_attacks():
    """``attacked_steps`` of a crafting: per run, from the onset, where an attacked entry
    arrives (a four-sensor cycle with entries [0, 1]: half the steps); it had been
    ``steps − onset + 1`` whatever the mask."""
    from difffilter.eval.stealthy import StealthySpec, _attacked_per_run

    mask = _round_robin(3, 20, 4)
    spec = StealthySpec(against="chi_square_ekf", onset=5, entries=(0, 1))
    assert _attacked_per_run(mask, 20, spec) == 8  # steps 5, 6, 9, 10, 13, 14, 17, 18
    assert _attacked_per_run(None, 20, spec) == 16
    ragged = mask.clone()
    ragged[0, 4] = False  # run 0 loses step 5
    assert _attacked_per_run(ragged, 20, spec) == pytest.approx(23 / 3)


def test_the_noise_sentence_counts_the_studys_own_attacked_steps():
    from difffilter.eval.robustness import _batch_noise_text

    report = {"settings": {"slack": 0.01}, "study_runs": 40, "attacked_steps": 91,
              "crafted": {"attacked_steps": 880}, "selection": {"runs": 256, "iteration": 3}}  # fmt: skip
    text = _batch_noise_text(report)
    assert "40 runs (880 attacked steps in all)" in text
    assert "varies by at least 0.0034" in text  # √(0.01 · 0.99 / 880)


# -- difffilter/threat_distribution.py: covert signals, field by field -------------------
def _plant():
    return df.LinearGaussianModel(0.9 * EYE, EYE, 0.01 * EYE, 0.01 * EYE,
                                  torch.zeros(2, dtype=F64), EYE, B=EYE)  # fmt: skip


def test_a_covert_threat_is_within_where_its_signal_could_be_drawn():
    ranged = ThreatDistribution({"covert": {"weight": 1.0, "kind": "covert", "signal": {
        "kind": "bias", "value": {"uniform": [0.05, 0.2]}, "onset": {"randint": [20, 40]}}}},
        model=_plant())  # fmt: skip
    assert ranged.covers({"kind": "covert", "signal": {"kind": "bias", "value": 0.1,
                                                       "onset": 30}}) == WITHIN  # fmt: skip
    assert ranged.covers({"kind": "covert", "signal": {"kind": "bias", "value": 0.5,
                                                       "onset": 30}}) == KIND_ONLY  # fmt: skip
    assert ranged.covers({"kind": "covert", "signal": {"kind": "ramp", "slope": 0.1,
                                                       "onset": 30}}) == KIND_ONLY  # fmt: skip
    assert ranged.covers({"kind": "bias", "value": 0.1}) == HELD_OUT
    const = ThreatDistribution({"covert": {"weight": 1.0, "kind": "covert", "signal": {
        "kind": "bias", "value": 0.1, "onset": 30}}}, model=_plant())  # fmt: skip
    for same in ({"value": [0.1]}, {"channel": "actuator"}, {"duration": None},
                 {"entries": [0, 1]}):  # fmt: skip
        signal = {"kind": "bias", "value": 0.1, "onset": 30, **same}
        assert const.covers({"kind": "covert", "signal": signal}) == WITHIN, same
    assert const.covers({"kind": "covert", "signal": {"kind": "bias", "value": 0.1, "onset": 30,
                                                      "entries": [0]}}) == KIND_ONLY  # fmt: skip


def test_a_choice_of_covert_signals_draws_each_ones_own_fields():
    """A covert ``signal`` by ``choice`` of mappings with random fields: the one chosen has
    its fields drawn (they had been passed on as mappings and refused as "onset must be an
    integer"), its coverage is field by field, and a bad draw inside is named by its place."""
    signals = [{"kind": "bias", "value": 0.1, "onset": {"randint": [5, 10]}},
               {"kind": "ramp", "slope": 0.01, "onset": {"randint": [5, 10]}}]  # fmt: skip
    dist = ThreatDistribution({"covert": {"weight": 1.0, "kind": "covert",
                                          "signal": {"choice": signals}}}, model=_plant())  # fmt: skip
    drawn = [dist.sample(torch.Generator().manual_seed(s))[1].signal for s in range(40)]
    assert {type(d).__name__ for d in drawn} == {"Bias", "Ramp"}
    assert {d.onset for d in drawn} == set(range(5, 11))
    assert dist.covers({"kind": "covert", "signal": {"kind": "ramp", "slope": 0.01,
                                                     "onset": 7}}) == WITHIN  # fmt: skip
    assert dist.covers({"kind": "covert", "signal": {"kind": "ramp", "slope": 0.01,
                                                     "onset": 12}}) == KIND_ONLY  # fmt: skip
    bad = [signals[0], {**signals[1], "onset": {"randint": [10, 5]}}]
    with pytest.raises(ValueError, match=r"threats\.covert\.signal\.choice\[1\]\.onset: "
                                         "randint needs lo <= hi"):  # fmt: skip
        ThreatDistribution({"covert": {"weight": 1.0, "kind": "covert",
                                       "signal": {"choice": bad}}}, model=_plant())  # fmt: skip


def test_every_chosen_signal_is_checked_at_its_extremes_at_construction():
    """An option whose fields constrain each other (pulses: a width range that reaches past
    the period) fails at construction, at the extreme, not at the draws that reach it (a
    width of 1–7 against a period of 6 had been accepted: one draw of its fields checked)."""
    signals = [{"kind": "bias", "value": 0.1, "onset": 5},
               {"kind": "pulses", "amplitude": 0.1, "period": 6,
                "width": {"randint": [1, 7]}, "onset": 5}]  # fmt: skip
    with pytest.raises(ValueError, match="threats.covert: width must be <= period; got width=7"):
        ThreatDistribution({"covert": {"weight": 1.0, "kind": "covert",
                                       "signal": {"choice": signals}}}, model=_plant())  # fmt: skip
    signals[1]["width"] = {"randint": [1, 6]}  # within the period at both ends
    ThreatDistribution({"covert": {"weight": 1.0, "kind": "covert",
                                   "signal": {"choice": signals}}}, model=_plant())  # fmt: skip


# -- eval/robustness.py: the study's sizes ---------------------------------------------------
@pytest.mark.parametrize("given", [{"runs": 0}, {"runs": False}, {"runs": -3}, {"runs": 2.5},
                                   {"calibration_runs": 0}])  # fmt: skip
def test_a_study_of_no_runs_is_refused_naming_the_argument(given):
    from difffilter.eval.robustness import ThreatSet, run_robustness
    from difffilter.models import registry
    from difffilter.threats import Bias

    threat_set = ThreatSet({"bias": Bias(0.5, onset=21)}, runs=6, estimators=("chi_square_ekf",))
    name = next(iter(given))
    with pytest.raises(ValueError, match=rf"^{name} must be a positive integer"):
        run_robustness(registry.get("four_tank_bias"), threat_set, progress=False, **given)


# -- difffilter/threats.py: a seamless replay's settings ---------------------------------------
def test_a_seamless_replay_of_the_wrong_width_is_refused_before_the_study():
    from difffilter.eval.robustness import ThreatSet, run_robustness
    from difffilter.models import registry

    scenario = registry.get("four_tank_bias")  # four measurements
    replay = Replay(delay=5, onset=30, loop=(EYE, EYE))
    with pytest.raises(ValueError, match="loop C has 2 rows; the model has 4 measurements"):
        check_attack_fits(replay, scenario.system(), scenario.steps)
    threat_set = ThreatSet({"replay": replay}, runs=4, estimators=("chi_square_ekf",))
    with pytest.raises(ValueError, match="threat 'replay': the replay's loop C has 2 rows"):
        run_robustness(scenario, threat_set, progress=False)
    check_attack_fits(Replay(delay=5, onset=30, loop=(EYE, torch.ones(4, 2, dtype=F64))),
                      scenario.system(), scenario.steps)  # fmt: skip


def test_a_level_window_without_a_splice_is_refused():
    for more in ({}, {"live": True}):
        with pytest.raises(ValueError, match="level_window=3 sets the frames of a seamless"):
            Replay(delay=5, onset=10, level_window=3, **more)
    assert Replay(delay=5, onset=10).level_window is None
    assert Replay(delay=5, onset=10, loop=(EYE, EYE)).level_window == 5
    assert Replay(delay=5, onset=10, loop=(EYE, EYE), level_window=2).level_window == 2


def test_numpy_scalars_and_0d_tensors_are_one_number_for_a_threats_values():
    """A second trial: ``Bias(value=np.int64(2))`` and ``Ramp(slope=np.float32(0.1))`` were
    refused as "not a number or a sequence of numbers" (only ``int``/``float`` counted)."""
    import numpy as np

    from difffilter.threats import Bias, Ramp

    assert Bias(value=np.int64(2)).value == Bias(value=2).value == (2.0,)
    assert Bias(value=torch.tensor(0.5)).value == (0.5,)
    assert Bias(value=np.array(0.25)).value == (0.25,)
    assert Ramp(slope=np.float32(0.5)).slope == Ramp(slope=0.5).slope
    assert [Bias(value=b).value for b in np.arange(1, 3)] == [(1.0,), (2.0,)]
    with pytest.raises(ValueError, match="must be a number or a sequence of numbers"):
        Bias(value="2")
