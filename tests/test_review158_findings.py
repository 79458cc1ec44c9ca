"""Review 158: a mutation review of the stealthy crafting (``difffilter/stealthy.py``) and
its evaluation (``eval/stealthy.py``). The first test is a bug (``same_rate_bias`` called a
bias that never reached the crafted attack's alarm rate "matched"); the others pin what
plausible wrong implementations left unpinned (each names the mutant it kills)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

import difffilter as df
from difffilter import fdi

F64 = torch.float64


def _plant(r=(1e-3, 1e-3)):
    """Two slow tanks, both measured, measurement noise ``R = diag(r)``."""
    eye = torch.eye(2, dtype=F64)
    F = torch.diag(torch.tensor([0.95, 0.98], dtype=F64))
    R = torch.diag(torch.tensor(r, dtype=F64))
    return df.LinearGaussianModel(F, eye, 1e-4 * eye, R, torch.zeros(2, dtype=F64), 1e-3 * eye)


def _gated():
    return fdi.GatedFilter(fdi.ChiSquareDetector(2, 0.01), df.KalmanFilter())


def _runs(plant, seed, runs=4, T=6):
    xs, ys, _ = plant.simulate(T, (runs,), generator=torch.Generator().manual_seed(seed))
    return ys, xs


# -- eval/stealthy.py: same_rate_bias -----------------------------------------------------
def _saturating_judge(*args, **kwargs):
    """A detector whose alarm rate under a constant bias levels off at 0.03 (a filter that
    learns the bias alarms at its transient only): ``0.02 + 0.01 k`` up to ``k = 1``."""
    return lambda attack: {"alarm_rate": min(0.02 + 0.01 * attack.k, 0.03),
                           "state_error": 1.0 + attack.k}  # fmt: skip


def test_a_rate_no_bias_reaches_is_not_matched(monkeypatch):
    """BUG: ``matched`` is "whether a bias reaches rate" (docstring); where no bias up to
    ``k = 1024`` alarms as often the bisection ran between 512 and 1024 and returned 1024 σ
    as matched, its alarm rate 0.03 below the crafted attack's 0.035, and the report called
    it "the weakest that alarms as often"."""
    from difffilter.eval import stealthy
    from difffilter.eval.robustness import _stealthy_section
    from difffilter.models import registry

    monkeypatch.setattr(stealthy, "_judge", _saturating_judge)
    sc = registry.get("four_tank_bias")
    got = stealthy.same_rate_bias(sc, "chi_square_ekf", 0.035, 9.0, onset=5, runs=2, seed=0)
    assert got["matched"] is False, got
    assert got["alarm_rate"] == 0.03 and got["k_sigma"] >= 1e3, got
    report = {"crafted": {"alarm_rate": 0.035, "state_error": 3.0}, "same_rate_bias": got,
              "settings": {"slack": 0.003, "iterations": 5, "lr": 0.01, "temperature": 0.18,
                           "penalty": 50.0},
              "against": "chi_square_ekf", "threshold": 9.0, "train_runs": 4,
              "iterations_within_budget": 2, "error_ratio_to_bias": 3.0 / 1025.0,
              "budget": 0.013, "attacked_steps": 80, "study_runs": 100,
              "selection": {"runs": 256, "budget": 0.0131, "iteration": 41,
                            "judged": [[41, 1.9, 0.0129]]}}  # fmt: skip
    text = _stealthy_section("stealthy_x", report)
    assert "the weakest that alarms as often" not in text
    assert "less often than the runs without attack" not in text
    assert "No constant bias up to 1.02e+03 σ alarms as often" in text or (
        "No constant bias up to 1024 σ alarms as often" in text
    ), text


def test_the_same_rate_bias_alarms_at_least_as_often_on_the_threats_entries(monkeypatch):
    """The bias returned is the upper end of the bisection (it alarms at least as often;
    mutant: the lower end, which alarms less) and lies on the crafted threat's ``entries``
    (mutant: every entry, another attack than the one compared)."""
    from difffilter.eval import stealthy
    from difffilter.models import registry

    seen = []

    def judge(*args, **kwargs):
        def one(attack):
            seen.append(attack.entries)
            return {"alarm_rate": 0.02 + 0.01 * attack.k, "state_error": 1.0 + attack.k}

        return one

    monkeypatch.setattr(stealthy, "_judge", judge)
    sc = registry.get("four_tank_bias")
    got = stealthy.same_rate_bias(sc, "chi_square_ekf", 0.035, 9.0, onset=5, entries=(1, 3),
                                  runs=2, seed=0)  # fmt: skip
    assert got["matched"] and got["alarm_rate"] >= 0.035, got
    assert set(seen) == {(1, 3)}, seen


# -- eval/stealthy.py: craft_threat --------------------------------------------------------
def test_craft_threat_draws_fresh_training_runs_and_its_held_out_runs(monkeypatch):
    """Every iteration's training batch is a fresh draw (mutant: one stream for every
    iteration, the same runs each time, which the resampling exists to avoid), the held-out
    batch has ``selection_runs`` runs (mutant: ``train_runs``); the report counts the
    attacked steps ``T − onset + 1`` and the iterates within budget (mutants: ``T − onset``,
    every iterate)."""
    from difffilter.eval import stealthy
    from difffilter.models import registry
    from difffilter.stealthy import CraftedAttack

    got = {}
    rows = [(0, 1.0, 0.0, 0.01, 0.02), (1, 2.0, 0.0, 0.03, 0.02), (2, 3.0, 0.0, 0.02, 0.025)]

    def fake_craft(estimator, model, ys, xs, tau, *, onset, resample, select, **kwargs):
        got.update(ys=ys, resample=resample, select=select)
        return CraftedAttack(torch.zeros(ys.shape[-2:], dtype=ys.dtype), onset, rows,
                             budget=0.02)  # fmt: skip

    monkeypatch.setattr(stealthy, "craft_stealthy_attack", fake_craft)
    sc = registry.get("four_tank_bias")
    spec = stealthy.StealthySpec(against="chi_square_ekf", onset=21, train_runs=3,
                                 selection_runs=5)  # fmt: skip
    calibration = SimpleNamespace(thresholds={"chi_square_ekf": 9.0}, far=0.01)
    _, report = stealthy.craft_threat("probe", spec, sc, calibration, seed=0)
    first, second, third = got["ys"], got["resample"](1)[0], got["resample"](2)[0]
    assert first.shape[0] == second.shape[0] == 3
    assert not torch.equal(first, second) and not torch.equal(second, third)
    assert got["select"][0].shape[0] == 5
    assert report["attacked_steps"] == sc.steps - 21 + 1
    assert report["iterations_within_budget"] == 2


# -- difffilter/stealthy.py ----------------------------------------------------------------
def test_the_start_is_init_times_each_entrys_own_sigma():
    """The start: a bias of ``init`` times the measurement noise's standard deviation
    (StealthySettings), entry by entry: ``0.3 √R_ii`` with ``R = diag(10⁻³, 4·10⁻³)``
    (mutant: the first entry's σ for every entry; the other tests' plants have one σ)."""
    from difffilter.stealthy import StealthySettings, craft_stealthy_attack

    plant = _plant((1e-3, 4e-3))
    ys, xs = _runs(plant, 3)
    c = craft_stealthy_attack(_gated(), plant, ys, xs, 1e9, far=0.01, onset=3,
                              settings=StealthySettings(iterations=1), warn_far_off=False)  # fmt: skip
    want = torch.zeros(6, 2, dtype=F64)
    want[2:] = 0.3 * torch.tensor([math.sqrt(1e-3), math.sqrt(4e-3)], dtype=F64)
    torch.testing.assert_close(c.values, want, rtol=1e-12, atol=0)


def test_without_select_the_iterate_of_largest_error_within_budget_is_returned():
    """Without ``select``: the largest ``J`` within budget on its own batch (docstring),
    not the last one within budget (mutant). Batches alternate, the even ones with their
    true states offset by 1 (a ``J`` about 2, against about 10⁻³ on the odd ones), so the
    last iterate (3, odd) is not the largest; the attack returned gives, on the even
    batch, the ``J`` of the history's largest."""
    from difffilter.loop import open_loop
    from difffilter.stealthy import StealthySettings, craft_stealthy_attack

    plant, est = _plant(), _gated()
    (ys0, xs0), (ys1, xs1) = _runs(plant, 3), _runs(plant, 11)
    even = (ys0, xs0 + 1.0)
    c = craft_stealthy_attack(
        est, plant, *even, 1e9, far=0.01, onset=3, warn_far_off=False,
        settings=StealthySettings(iterations=4, lr=0.05),
        resample=lambda it: even if it % 2 == 0 else (ys1, xs1),
    )  # fmt: skip
    best = max(c.history, key=lambda h: h[1])
    assert best[0] in (0, 2) and len(c.within_budget()) == 4
    with torch.no_grad():
        out = open_loop(est, plant, even[0] + c.values)
    on = torch.arange(1, 7) >= 3
    J = float((out.means - even[1]).square().sum(-1)[:, on].mean())
    assert J == pytest.approx(best[1], rel=1e-12), (J, [h[:2] for h in c.history])


def test_the_held_out_batch_judges_in_decreasing_error_the_first_that_keeps_it_at_most_candidates(
    monkeypatch,
):
    """``select``: the iterates within budget are judged in order of decreasing ``J``
    (mutant: increasing), the first that keeps the held-out budget is the attack (mutant:
    the last), and at most ``candidates`` are judged (mutant: all). The budget test is
    scripted: every training iterate keeps it; on the held-out batch the answers are
    ``held``."""
    import difffilter.stealthy as st

    plant, est = _plant(), _gated()
    ys, xs = _runs(plant, 3)
    real = st._keeps_budget

    def craft(held, candidates=32):
        calls = []

        def scripted(rate, budget):
            calls.append(real(rate, budget))
            return True if len(calls) <= 5 else held[len(calls) - 6]

        monkeypatch.setattr(st, "_keeps_budget", scripted)
        settings = st.StealthySettings(iterations=5, lr=0.05, candidates=candidates)
        return st.craft_stealthy_attack(est, plant, ys, xs, 1e9, far=0.01, onset=3,
                                        settings=settings, select=(ys, xs),
                                        warn_far_off=False)  # fmt: skip

    c = craft([False, True, True, True, True])
    order = [h[0] for h in sorted(c.history, key=lambda h: -h[1])]
    assert [j[0] for j in c.selection["judged"]] == order[:2], (c.selection, order)
    assert c.selection["iteration"] == order[1]
    with pytest.warns(RuntimeWarning, match="none of the 3 iterates"):
        c = craft([False] * 5, candidates=3)
    assert [j[0] for j in c.selection["judged"]] == order[:3]
    assert c.selection["iteration"] is None and not bool(c.values.any())


def test_the_estimators_own_draws_are_the_generators_at_every_run():
    """``generator``: ``() → generator`` of the estimator's draws, the same at every
    iteration (docstring): a particle filter's first ``J`` is that of ``open_loop`` with
    ``generator()`` on the first iterate (mutants: the generator ignored, the global one
    drawn instead; one generator for every run, the attack-free run's draws spent before
    the attacked run's)."""
    from difffilter.loop import open_loop
    from difffilter.stealthy import StealthySettings, craft_stealthy_attack

    plant = _plant()
    ys, xs = _runs(plant, 3)
    pf = fdi.PoAParticleFilter(64, fdi.PoADetector(0.05, 0.5))

    def generator():
        return torch.Generator().manual_seed(7)

    torch.manual_seed(0)
    c = craft_stealthy_attack(pf, plant, ys, xs, 2.0, far=0.01, onset=3, generator=generator,
                              settings=StealthySettings(iterations=1), warn_far_off=False)  # fmt: skip
    torch.manual_seed(1)  # the global generator must not matter
    with torch.no_grad():
        out = open_loop(pf, plant, ys + c.values, generator=generator())
    on = torch.arange(1, 7) >= 3
    J = float((out.means - xs).square().sum(-1)[:, on].mean())
    assert c.history[0][1] == pytest.approx(J, rel=1e-12), (c.history[0][1], J)


@pytest.mark.parametrize("penalty, lr, init", [(50.0, 0.05, 3.0), (0.0, 0.3, 0.3)])
def test_the_next_iterates_are_adam_steps_on_the_documented_loss(penalty, lr, init):
    """``L(a) = − log J(a) + ρ max(0, p̃(a) − p̃(0) − ε)² / ε²`` on the increments, Adam at
    ``lr`` (module docstring), written out here; ``J`` of the later iterates match
    (mutants: the penalty without its ``1/ε²``, ``−J`` for ``−log J``, both unseen by the
    tests of the first iterate). ``τ`` is the median attack-free score and the start 3 σ,
    so the penalty is active; without it (``ρ = 0``) only ``log J`` drives Adam, whose
    steps after the first see the scale of the gradient (``∇J / J`` against ``∇J``)."""
    from difffilter.loop import open_loop
    from difffilter.stealthy import StealthySettings, craft_stealthy_attack

    plant, est = _plant(), _gated()
    ys, xs = _runs(plant, 3)
    T, onset = 6, 3
    on = torch.arange(1, T + 1) >= onset
    with torch.no_grad():
        free = open_loop(est, plant, ys).detection.scores
    tau = float(free[:, on].median())
    s = StealthySettings(iterations=4, lr=lr, slack=0.001, init=init, penalty=penalty)
    c = craft_stealthy_attack(est, plant, ys, xs, tau, far=0.01, onset=onset, settings=s,
                              warn_far_off=False)  # fmt: skip
    t = s.temperature * float(free[:, on].std()) + 1e-12

    def smoothed(scores):
        return torch.sigmoid((scores - tau) / t)[:, on].mean()

    raw = torch.zeros(T, 2, dtype=F64)
    raw[onset - 1] = s.init
    raw.requires_grad_(True)
    adam, window = torch.optim.Adam([raw], lr=s.lr), on.to(F64)[:, None].expand(T, 2)
    Js, excess = [], []
    for _ in range(4):
        out = open_loop(est, plant, ys + raw.cumsum(0) * math.sqrt(1e-3) * window)
        J = (out.means - xs).square().sum(-1)[:, on].mean()
        rise = smoothed(out.detection.scores) - smoothed(free)
        loss = -J.log() + s.penalty * torch.relu(rise - s.slack).square() / s.slack**2
        Js.append(float(J.detach()))
        excess.append(float(rise.detach()) - s.slack)
        adam.zero_grad()
        loss.backward()
        adam.step()
    assert penalty == 0 or max(excess) > 0, "(setup) the penalty is never active"
    for row, J in zip(c.history, Js, strict=True):
        assert row[1] == pytest.approx(J, rel=1e-10), ([h[1] for h in c.history], Js)


# -- eval/stealthy.py: the detector crafted against is the one judged ----------------------
class _Crafted(Exception):
    """Raised by a stand-in crafting once it has seen the estimator it was given."""


def test_a_crafted_threat_meets_the_cusum_the_study_judges(monkeypatch):
    """The crafting differentiates through "the named detector's own step object" (module
    docstring of ``eval/stealthy.py``). A CUSUM's own τ (its resets and its gate) is
    calibrated on ``max(runs, 50)`` attack-free runs, ``runs`` the study's; the crafting's
    context had ``train_runs`` (64) as its runs, so against four_tank_bias's 100-run study
    it crafted through a CUSUM of τ 11.2605 while the study judged one of τ 11.2146."""
    from difffilter.eval import robustness, stealthy
    from difffilter.models import registry

    seen = {}

    def capture(estimator, *args, **kwargs):
        seen["detector"] = estimator.detector
        raise _Crafted

    monkeypatch.setattr(stealthy, "craft_stealthy_attack", capture)
    sc = registry.get("four_tank_bias")
    result = SimpleNamespace(
        scenario=sc, runs=100, seed=0, stealthy={}, attack_free=SimpleNamespace(skipped={}),
        calibration=SimpleNamespace(thresholds={"cusum_ekf": 5.0}, far=0.01),
    )  # fmt: skip
    spec = stealthy.StealthySpec(against="cusum_ekf", onset=21)  # train_runs 64
    with pytest.raises(_Crafted):
        robustness._crafted(result, "probe", spec, progress=False)
    study, _ = stealthy.estimator_step(sc, "cusum_ekf", runs=100, seed=0)
    crafted = seen["detector"]
    assert (crafted.bias, crafted.threshold) == (study.detector.bias, study.detector.threshold)
