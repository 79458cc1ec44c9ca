"""The gradient-crafted stealthy attack on a small linear plant: it keeps the χ² detector's
alarm rate within its budget on fresh noise, and drags the estimate further than a
constant bias that alarms as often."""

from __future__ import annotations

import math

import pytest
import torch

import difffilter as df
from difffilter import fdi
from difffilter.eval.calibration import threshold_for
from difffilter.loop import DrawnNoise, closed_loop, open_loop
from difffilter.stealthy import (
    CraftedAttack,
    StealthySettings,
    _keeps_budget,
    craft_stealthy_attack,
)
from difffilter.threats import KSigmaBias

F64 = torch.float64
T, ONSET = 60, 11


def _plant():
    """Two slow tanks (time constants 20 and 50 steps), both measured."""
    F = torch.diag(torch.tensor([0.95, 0.98], dtype=F64))
    eye = torch.eye(2, dtype=F64)
    return df.LinearGaussianModel(F, eye, 1e-4 * eye, 1e-3 * eye, torch.zeros(2, dtype=F64),
                                  1e-3 * eye)  # fmt: skip


def _runs(runs, seed, attack=None):
    plant = _plant()
    loop = closed_loop(plant, T, noise=DrawnNoise(torch.Generator().manual_seed(seed)),
                       x0=torch.zeros(runs, 2, dtype=F64), attack=attack)  # fmt: skip
    return loop.trajectories


def _judge(estimator, tau, attack, runs=400, seed=99):
    tr = _runs(runs, seed, attack)
    out = open_loop(estimator, _plant(), tr.y_recv)
    on = torch.arange(1, T + 1) >= ONSET
    alarm = float((out.detection.scores > tau)[:, on].double().mean())
    error = math.sqrt(float((out.means - tr.x).square().sum(-1)[:, on].mean()))
    return alarm, error


@pytest.fixture(scope="module")
def crafted():
    estimator = fdi.GatedFilter(fdi.ChiSquareDetector(2, 0.01), df.KalmanFilter())
    free = _runs(400, 1)
    tau = threshold_for(open_loop(estimator, _plant(), free.y_recv).detection.scores, 0.01)
    first = _runs(32, 2)

    def batch(it):
        tr = _runs(32, 100 + it)
        return tr.y_true, tr.x

    # temperature 0.25 σ_s (= 0.5 in units of this χ²(2) statistic, what the test was sized with)
    settings = StealthySettings(iterations=150, lr=0.03, slack=0.005, temperature=0.25)
    attack = craft_stealthy_attack(estimator, _plant(), first.y_true, first.x, tau, far=0.01,
                                   onset=ONSET, settings=settings, resample=batch)  # fmt: skip
    return estimator, tau, attack


def test_the_crafted_attack_acts_only_in_its_window(crafted):
    _, _, attack = crafted
    assert isinstance(attack, CraftedAttack) and attack.values.shape == (T, 2)
    assert torch.equal(attack.values[: ONSET - 1], torch.zeros(ONSET - 1, 2, dtype=F64))
    assert attack.values[ONSET - 1 :].abs().sum() > 0
    assert len(attack.history) == 150
    # the first batch's budget: its attack-free hard alarm rate plus ε (not the first
    # iterate's rate, which carries the starting bias); later rows hold their own batch's
    estimator, tau, _ = crafted
    out = open_loop(estimator, _plant(), _runs(32, 2).y_true)
    on = torch.arange(1, T + 1) >= ONSET
    free_rate = float((out.detection.scores > tau)[:, on].double().mean())
    assert attack.budget == pytest.approx(free_rate + 0.005, abs=1e-12)
    assert attack.history[0][3] != free_rate  # the start (0.3 σ) alarms otherwise


def test_the_statistic_stays_within_its_budget_on_fresh_noise_and_drags_the_estimate(crafted):
    estimator, tau, attack = crafted
    free_rate, free_error = _judge(estimator, tau, None)
    rate, error = _judge(estimator, tau, attack)
    assert rate <= free_rate + 0.005 + 0.006  # the budget ε, plus Monte Carlo slack (4σ)
    assert error > 2 * free_error
    # a constant bias that alarms as often (found by bisection on k) drags it less (1.5× here;
    # 3.5× on the four-tank plant, whose slow tanks leave more room: robustness report)
    lo, hi = 0.0, 8.0
    for _ in range(14):
        mid = 0.5 * (lo + hi)
        bias = KSigmaBias.of(_plant(), mid, onset=ONSET)
        lo, hi = (mid, hi) if _judge(estimator, tau, bias)[0] < rate else (lo, mid)
    assert error > 1.2 * _judge(estimator, tau, KSigmaBias.of(_plant(), hi, onset=ONSET))[1]


@pytest.mark.parametrize("seed", [2, 3, 5])
def test_the_budget_holds_on_fresh_noise_for_an_attack_chosen_on_held_out_runs(seed):
    """The budget ε is a promise about noise the attacker never saw: judged on 2,000 fresh
    runs, the alarm rate rises by at most ε (plus 4 binomial standard deviations of a
    rise of ε). Before 2026-12-02 the budget was the first batch's p(0) + ε, the objective
    J/J₀ let the penalty be swamped, and the iterate kept was the best within budget on
    its own batch: on these seeds the rise was 1.58, 1.32 and 1.60 ε (0.67–0.80 ε since)."""
    estimator = fdi.GatedFilter(fdi.ChiSquareDetector(2, 0.01), df.KalmanFilter())
    tau = threshold_for(open_loop(estimator, _plant(), _runs(400, 1).y_recv).detection.scores,
                        0.01)  # fmt: skip
    first, held_out = _runs(32, 2 + 1000 * seed), _runs(128, 777 + seed)

    def batch(it):
        tr = _runs(32, 100 + it + 1000 * seed)
        return tr.y_true, tr.x

    settings = StealthySettings(iterations=150, lr=0.03, slack=0.005, temperature=0.25)
    attack = craft_stealthy_attack(estimator, _plant(), first.y_true, first.x, tau, far=0.01,
                                   onset=ONSET, settings=settings, resample=batch,
                                   select=(held_out.y_true, held_out.x))  # fmt: skip
    assert attack.selection["iteration"] is not None, attack.selection
    free_rate, free_error = _judge(estimator, tau, None, runs=2000, seed=5)
    rate, error = _judge(estimator, tau, attack, runs=2000, seed=5)
    steps = 2000 * (T - ONSET + 1)
    assert rate - free_rate <= 0.005 + 4 * math.sqrt(0.005 / steps), (rate, free_rate)
    assert error > 2.5 * free_error, (error, free_error)  # (2.9–3.3× here)


def test_bad_arguments_are_named():
    estimator = fdi.GatedFilter(fdi.ChiSquareDetector(2, 0.01), df.KalmanFilter())
    tr = _runs(4, 0)
    with pytest.raises(ValueError, match="onset"):
        craft_stealthy_attack(estimator, _plant(), tr.y_true, tr.x, 9.0, far=0.01, onset=0)
    with pytest.raises(ValueError, match="values must be a tensor"):
        CraftedAttack(torch.zeros(3), 1)
    # one run attacked at its last step only: the spread of one score is NaN (Adam then
    # turned the attack into NaN and the filter refused its input)
    with pytest.raises(ValueError, match="at least two attacked"):
        craft_stealthy_attack(estimator, _plant(), tr.y_true[:1], tr.x[:1], 9.0, far=0.01, onset=T)
    # what a user trial found accepted or failing far from its cause
    craft = lambda **kw: craft_stealthy_attack(  # noqa: E731
        estimator, _plant(), kw.pop("ys", tr.y_true), kw.pop("xs", tr.x), kw.pop("tau", 9.0),
        far=kw.pop("far", 0.01), onset=ONSET, **kw,
    )  # fmt: skip
    for tau in (math.nan, math.inf):  # (it failed as "ys contains NaN")
        with pytest.raises(ValueError, match="threshold must be a finite number"):
            craft(tau=tau)
    with pytest.raises(ValueError, match="far must be a false-alarm rate"):
        craft(far=-5)
    for entries in ((7,), (-1,), (), (0, 0)):  # an IndexError; -1 attacked the last entry
        with pytest.raises(
            ValueError, match=r"entries must be distinct measurement entries in \[0, 2\)"
        ):
            craft(entries=entries)
    with pytest.raises(ValueError, match=r"ys must be a tensor \[B, T, dy = 2\]"):
        craft(ys=tr.y_true[0])
    with pytest.raises(ValueError, match=r"xs must be a tensor \[B, T, dx = 2\]"):
        craft(xs=tr.x[..., :1])
    bad = tr.x.clone()
    bad[1, ONSET + 1, 0] = math.nan  # (it had been blamed on ys, finite)
    with pytest.raises(
        ValueError, match=rf"xs contains NaN or Inf values \(first at index \(1, {ONSET + 1}, 0\)\)"
    ):
        craft(xs=bad)
    with pytest.raises(ValueError, match="xs must hold the states of ys's runs"):
        craft(xs=tr.x[:2])
    with pytest.raises(TypeError, match="settings must be a StealthySettings"):
        craft(settings={"iterations": 3})
    with pytest.raises(ValueError, match=r"onset must be an integer in \[1, 3\]"):
        CraftedAttack(torch.zeros(3, 2), 0)


def test_an_attack_exactly_on_its_budget_keeps_it():
    # 58 alarms of 10,000 attack-free, ε = 0.003: 88 alarms are exactly ε more, yet
    # 88/10,000 > 58/10,000 + 0.003 in floating point (0.0088 > 0.008799999999999999)
    n, free, slack = 10_000, 58, 0.003
    budget = free / n + slack
    on_budget, over = (free + round(slack * n)) / n, (free + round(slack * n) + 1) / n
    assert on_budget > budget  # the round-off the predicate admits
    assert _keeps_budget(on_budget, budget) and not _keeps_budget(over, budget)
    history = [(0, 1.0, 0.0, on_budget), (1, 2.0, 0.0, over), (2, 0.5, 0.0, free / n)]
    attack = CraftedAttack(torch.zeros(3, 1, dtype=F64), 1, history, budget=budget)
    assert [h[0] for h in attack.within_budget()] == [0, 2]
    assert CraftedAttack(torch.zeros(3, 1), 1, history).within_budget() == history  # no budget


@pytest.mark.parametrize("against", ["pf_nn_grad", "normal_pf"])
def test_the_attacker_sees_the_particle_filters_of_the_suite_and_their_gradient(against):
    """``detector_step`` gives the suite's learned estimator and its PF with the PoA detector
    (the same numbers on the same runs: the particle filters start from the study's
    draws), and the crafting gets a gradient through the particle filter and the
    detector's statistic (the learned head's probability, the PoA's β)."""
    from difffilter.eval.stealthy import _context, detector_step
    from difffilter.eval.suite import run_suite
    from difffilter.models import registry
    from difffilter.models.streams import Streams

    scenario, runs = registry.get("four_tank_bias"), 6
    suite = run_suite(scenario, runs=runs, seed=3, estimators=[against], progress=False)
    ctx = _context(scenario, runs, 3)
    estimator, start = detector_step(ctx, against)
    gens = {k: Streams(3)(k) for k in ("plant", "attack", "schedule")}
    tr = scenario.simulate(runs, gens, model=ctx.model)
    with torch.no_grad():
        out = open_loop(estimator, ctx.model, tr.y_recv, tr.us, carry=start(runs))
    expected = suite.outputs[against]
    torch.testing.assert_close(out.means, expected.means, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.detection.scores, expected.detection.scores, rtol=0, atol=1e-12)

    free = scenario.with_threat(None).simulate(runs, gens, model=ctx.model)
    settings = StealthySettings(iterations=3, lr=0.05)
    attack = craft_stealthy_attack(estimator, ctx.model, free.y_true, free.x, 0.5, far=0.01,
                                   onset=21, settings=settings, start=start)  # fmt: skip
    moved = [h[1] for h in attack.history]
    assert moved[2] != moved[0]  # the increments moved: a gradient reached them
    with pytest.raises(ValueError, match="not a gated Gaussian filter .*, normal_pf nor a learned"):
        detector_step(ctx, "kf_attack_free")


@pytest.mark.parametrize("name", ["cusum_ekf", "chi_square_ukf"])
def test_estimator_step_is_the_registered_detector_of_the_study(name):
    """The public ``estimator_step`` (for a loop of one's own, a user trial found none): on
    the study's runs its step object gives the suite's numbers, the CUSUM calibrated alike."""
    from difffilter.eval.stealthy import estimator_step
    from difffilter.eval.suite import run_suite
    from difffilter.models import registry

    scenario, runs = registry.get("four_tank_bias"), 5
    suite = run_suite(scenario, runs=runs, seed=2, estimators=[name], progress=False)
    estimator, start = estimator_step(scenario, name, runs=runs, seed=2)
    assert start is None
    tr = suite.traj
    with torch.no_grad():
        out = open_loop(estimator, suite.context.model, tr.y_recv, tr.us, mask=tr.mask)
    expected = suite.outputs[name]
    torch.testing.assert_close(out.means, expected.means, rtol=0, atol=1e-9)
    torch.testing.assert_close(out.detection.scores, expected.detection.scores, rtol=0, atol=1e-9)
    assert torch.equal(out.detection.alarms, expected.detection.alarms)
    # the LFC's learned estimator has no step object: said so (a closed-loop trial was told
    # "cannot craft against", and crafted nothing)
    with pytest.raises(ValueError, match=r"no step object for 'kf_nn_grad': not a gated Gaussian "
                       r"filter.*LFC closed loop"):  # fmt: skip
        estimator_step(registry.get("lfc_step"), "kf_nn_grad", runs=2)


def test_a_crafting_that_kept_no_iterate_says_why_its_attack_is_zero():
    """Without ``select``, an attack of zeros where no iterate kept the alarm budget had come
    back without a word, to be read as a detector that withstood the attack."""
    estimator = fdi.GatedFilter(fdi.ChiSquareDetector(2, 0.01), df.KalmanFilter())
    tau = threshold_for(open_loop(estimator, _plant(), _runs(400, 1).y_recv).detection.scores,
                        0.01)  # fmt: skip
    first = _runs(32, 2)
    loud = StealthySettings(iterations=3, lr=1e-6, init=50.0, penalty=0.0)  # alarms at once
    with pytest.warns(RuntimeWarning, match="no iterate kept the budget on its own batch: "
                      "the attack returned is zero"):  # fmt: skip
        attack = craft_stealthy_attack(estimator, _plant(), first.y_true, first.x, tau,
                                       far=0.01, onset=ONSET, settings=loud)  # fmt: skip
    assert not bool(attack.values.any()) and attack.within_budget() == []


def test_an_attack_crafted_on_some_entries_flags_those_entries():
    """``craft_stealthy_attack(entries=...)``'s attack flags per entry: under a mask, a step
    where only the other entries arrived carries no attack and is not labelled attacked
    (a trial: every step of a round-robin schedule had been, 8 of 8 where 4 carried it, as
    ``Bias(entries=...)`` labels them right). Without ``entries`` the flags are per run, as
    before. Truth: the steps where entry 0 arrived."""
    estimator = fdi.GatedFilter(fdi.ChiSquareDetector(2, 0.01), df.KalmanFilter())
    tr = _runs(8, 3)
    attack = craft_stealthy_attack(estimator, _plant(), tr.y_true, tr.x, 9.0, far=0.01,
                                   onset=3, entries=(0,),
                                   settings=StealthySettings(iterations=2))  # fmt: skip
    assert attack.entries == (0,)
    values, flags = attack.sample((2,), T, 2, dtype=F64)
    assert flags.shape == (2, T, 2) and not bool(flags[..., 1].any())
    assert flags[0, :, 0].tolist() == [k >= 3 for k in range(1, T + 1)]
    mask = torch.zeros(2, T, 2, dtype=torch.bool)
    mask[:, 0::2, 0], mask[:, 1::2, 1] = True, True  # entry 0 at odd steps, entry 1 at even
    loop = closed_loop(_plant(), T, noise=DrawnNoise(torch.Generator().manual_seed(0)),
                       x0=torch.zeros(2, 2, dtype=F64), attack=CraftedAttack(
                           torch.full((T, 2), 0.1, dtype=F64) * torch.tensor([1.0, 0.0],
                           dtype=F64), onset=3, entries=(0,)), mask=mask)  # fmt: skip
    expected = mask[..., 0] & (torch.arange(1, T + 1) >= 3)
    assert torch.equal(loop.trajectories.flags, expected)
    whole = CraftedAttack(torch.zeros(T, 2, dtype=F64), onset=3).sample((2,), T, 2, dtype=F64)
    assert whole[1].shape == (2, T)
    with pytest.raises(ValueError, match="entries must be distinct measurement entries"):
        CraftedAttack(torch.zeros(T, 2, dtype=F64), onset=3, entries=(2,))


def test_crafting_against_a_filter_that_draws_needs_its_generator():
    """A particle filter's crafting (the shipped four-tank ``pf_nn_grad``) with neither
    ``generator`` nor ``start``: refused by name, since its runs drew from torch's global
    generator and the attacked and attack-free runs filtered with other particles (the
    budget's ``p(a) − p(0)`` was 0.31 points at the zero attack, about ε, and no crafting
    repeated itself); with the study's start, the zero attack's rise is exactly 0."""
    from difffilter.eval.stealthy import _context, detector_step
    from difffilter.models import registry
    from difffilter.models.streams import Streams

    sc = registry.get("four_tank_bias")
    ctx = _context(sc, 4, 0)
    pf, start = detector_step(ctx, "pf_nn_grad")
    tr = sc.with_threat(None).simulate(4, Streams(5).simulation("x/"), model=ctx.model)
    settings = StealthySettings(iterations=1, init=0.0)
    kw = dict(far=0.01, us=tr.us, mask=tr.mask, onset=21, settings=settings)
    with pytest.raises(ValueError, match="draws random numbers, and neither generator nor start"):
        craft_stealthy_attack(pf, ctx.model, tr.y_true, tr.x, 0.5, **kw)
    attack = craft_stealthy_attack(pf, ctx.model, tr.y_true, tr.x, 0.5, start=start, **kw)
    assert attack.history[0][2] == 0.0  # p̃(a) − p̃(0) of the zero attack
