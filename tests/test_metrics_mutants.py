"""Mutation-review checks of ``difffilter.metrics`` against independent truths.

Each test evaluates a metric's definition (the module docstrings and docs/metrics.md) by
hand in plain Python / numpy float64 on a small case, and compares the library's value:
RMSE by numpy, confusion counts and rates by explicit loops over the steps, the ROC by a
threshold sweep loop, the AUC by the Mann–Whitney pair count (ties ½), detection delays
by walking each run's episodes, ``threshold_for`` by sorting and checking the rule
(``#{s > τ} ≤ ⌊α n⌋``, and the next lower candidate alarms more), ``steps_since_attack``
and the alarm rates by loops over the steps.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter import metrics


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# ----------------------------------------------------------------------------- RMSE


def test_rmse_against_numpy_over_all_entries_and_over_chosen_dims():
    """``rmse`` is √mean((x̂ − x)²): checked against numpy float64 over all entries, over
    one dim and over a tuple of dims, with a truth that broadcasts."""
    g = _gen(0)
    est = torch.randn(2, 3, 4, generator=g, dtype=torch.float64)
    truth = torch.randn(3, 4, generator=g, dtype=torch.float64)
    e, x = est.numpy(), truth.numpy()
    d2 = (e - x) ** 2
    assert metrics.rmse(est, truth).item() == pytest.approx(math.sqrt(d2.mean()), rel=1e-12)
    np.testing.assert_allclose(
        metrics.rmse(est, truth, dim=1).numpy(), np.sqrt(d2.mean(axis=1)), rtol=1e-12
    )
    np.testing.assert_allclose(
        metrics.rmse(est, truth, dim=(0, 2)).numpy(), np.sqrt(d2.mean(axis=(0, 2))), rtol=1e-12
    )


# ------------------------------------------------------------ confusion counts and rates


def _loop_counts(alarms, attacked, valid):
    c = {"tp": 0, "fp": 0, "tn": 0, "fn": 0}
    for a, y, v in zip(alarms, attacked, valid):
        if not v:
            continue
        key = ("t" if a == y else "f") + ("p" if a else "n")
        c[key] += 1
    return c


def test_counts_and_rates_against_a_loop_with_a_broadcast_valid_mask():
    """TP/FP/TN/FN pooled over the valid steps, TPR = TP/(TP+FN), FPR = FP/(FP+TN),
    ``false_alarms`` = FP and ``missed_attacks`` = FN: against a loop over every (run, step),
    with ``valid`` given per step ``[T]`` and broadcast over the runs."""
    g = _gen(1)
    B, T = 4, 9
    alarms = torch.rand(B, T, generator=g) < 0.5
    attacked = torch.rand(B, T, generator=g) < 0.4
    valid_t = torch.rand(T, generator=g) < 0.7
    valid_t[0] = True
    valid_t[1] = False
    valid = valid_t.expand(B, T)
    want = _loop_counts(
        alarms.flatten().tolist(), attacked.flatten().tolist(), valid.flatten().tolist()
    )
    assert metrics.detection_counts(alarms, attacked, valid_t) == want
    r = metrics.detection_rates(alarms, attacked, valid_t)
    assert r["tpr"] == pytest.approx(want["tp"] / (want["tp"] + want["fn"]), abs=1e-15)
    assert r["fpr"] == pytest.approx(want["fp"] / (want["fp"] + want["tn"]), abs=1e-15)
    assert r["false_alarms"] == want["fp"]
    assert r["missed_attacks"] == want["fn"]
    # every one of the four counts depends on valid: the loop without a mask differs
    allc = _loop_counts(alarms.flatten().tolist(), attacked.flatten().tolist(), [True] * (B * T))
    assert metrics.detection_counts(alarms, attacked) == allc
    assert all(allc[k] != want[k] for k in want)


def test_rates_without_a_denominator_are_nan_not_zero():
    """A rate with no attacked (or no attack-free) valid step is NaN (docs: ``null``)."""
    alarms = torch.tensor([[True, False, True]])
    none = torch.zeros(1, 3, dtype=torch.bool)
    r = metrics.detection_rates(alarms, none)
    assert math.isnan(r["tpr"]) and r["fpr"] == pytest.approx(2 / 3)
    r = metrics.detection_rates(alarms, ~none)
    assert math.isnan(r["fpr"]) and r["tpr"] == pytest.approx(2 / 3)


def test_labels_that_do_not_fit_the_alarms_are_refused():
    """A labels or valid tensor that does not broadcast to the alarms' shape raises
    ValueError naming it (not a torch error, not a silent partial count)."""
    alarms = torch.zeros(2, 5, dtype=torch.bool)
    with pytest.raises(ValueError, match="attacked"):
        metrics.detection_counts(alarms, torch.zeros(2, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="valid"):
        metrics.detection_rates(
            alarms, torch.zeros(2, 5, dtype=torch.bool), torch.ones(3, dtype=torch.bool)
        )
    with pytest.raises(ValueError, match="labels"):
        metrics.roc_auc(torch.zeros(2, 5), torch.zeros(2, 1, 5, dtype=torch.bool))


# ----------------------------------------------------------------------------- ROC


def _loop_roc(scores, labels):
    """Threshold sweep, alarm when s ≥ τ over the distinct scores in decreasing order,
    from (0, 0) at τ = +∞."""
    pos = sum(labels)
    neg = len(labels) - pos
    fpr, tpr, thr = [0.0], [0.0], [math.inf]
    for tau in sorted(set(scores), reverse=True):
        tp = sum(1 for s, y in zip(scores, labels) if s >= tau and y)
        fp = sum(1 for s, y in zip(scores, labels) if s >= tau and not y)
        fpr.append(fp / neg if neg else 0.0)
        tpr.append(tp / pos if pos else 0.0)
        thr.append(tau)
    return fpr, tpr, thr


def _mann_whitney(scores, labels):
    p = [s for s, y in zip(scores, labels) if y]
    n = [s for s, y in zip(scores, labels) if not y]
    wins = sum(1.0 if a > b else 0.5 if a == b else 0.0 for a in p for b in n)
    return wins / (len(p) * len(n))


def test_roc_curve_with_ties_and_a_valid_mask_against_a_threshold_sweep():
    """Every point of ``roc_curve`` (tied scores grouped, the invalid steps left out, an
    invalid step's NaN allowed) against a loop sweeping τ over the distinct valid scores;
    float64 rates, thresholds +∞ then the distinct scores in decreasing order."""
    g = _gen(2)
    B, T = 3, 12
    scores = torch.randint(0, 6, (B, T), generator=g).double() / 2
    labels = torch.rand(B, T, generator=g) < 0.4
    valid = torch.rand(B, T, generator=g) < 0.75
    scores[~valid] = math.nan
    fpr, tpr, thr = metrics.roc_curve(scores, labels, valid)
    s = scores[valid].tolist()
    y = labels[valid].tolist()
    want_f, want_t, want_thr = _loop_roc(s, y)
    assert fpr.dtype == tpr.dtype == thr.dtype == torch.float64
    np.testing.assert_allclose(fpr.numpy(), want_f, atol=1e-15)
    np.testing.assert_allclose(tpr.numpy(), want_t, atol=1e-15)
    assert thr.tolist() == want_thr
    assert (fpr[-1].item(), tpr[-1].item()) == (1.0, 1.0)


def test_roc_curve_without_positives_ends_at_one_zero():
    """Without an attacked step the curve ends at (1, 0), without an attack-free one at
    (0, 1): the rate without a denominator stays 0."""
    s = torch.tensor([0.3, 0.1, 0.2])
    fpr, tpr, _ = metrics.roc_curve(s, torch.zeros(3, dtype=torch.bool))
    assert fpr.tolist() == [0.0, 1 / 3, 2 / 3, 1.0] and tpr.tolist() == [0.0] * 4
    fpr, tpr, _ = metrics.roc_curve(s, torch.ones(3, dtype=torch.bool))
    assert tpr.tolist() == [0.0, 1 / 3, 2 / 3, 1.0] and fpr.tolist() == [0.0] * 4


@pytest.mark.parametrize("seed", [3, 4])
def test_auc_is_the_mann_whitney_pair_count_with_ties_and_valid(seed):
    """``roc_auc`` = P(s⁺ > s⁻) + ½ P(s⁺ = s⁻) over the valid steps: against the explicit
    pair count on discrete (tied) scores, labels broadcast from ``[T]``, a NaN on an
    invalid step."""
    g = _gen(seed)
    B, T = 3, 15
    scores = torch.randint(0, 5, (B, T), generator=g).double()
    labels_t = torch.rand(T, generator=g) < 0.5
    labels_t[:2] = torch.tensor([True, False])
    valid = torch.rand(B, T, generator=g) < 0.8
    valid[0, :2] = True
    scores[~valid] = math.nan
    y = labels_t.expand(B, T)
    want = _mann_whitney(scores[valid].tolist(), y[valid].tolist())
    assert metrics.roc_auc(scores, labels_t, valid) == pytest.approx(want, abs=1e-14)
    # the trapezoids over the curve give the same number (docs' formula)
    fpr, tpr, _ = metrics.roc_curve(scores, labels_t, valid)
    f, t = fpr.numpy(), tpr.numpy()
    assert float(np.sum(np.diff(f) * (t[1:] + t[:-1]) / 2)) == pytest.approx(want, abs=1e-14)


def test_auc_of_unbalanced_continuous_scores_and_of_nearly_tied_float64_scores():
    """More attack-free than attacked steps (the denominator is #pos · #neg) on continuous
    scores, and float64 scores 1e-12 apart that only tie if cast to float32: against the
    pair count."""
    g = _gen(5)
    s = torch.randn(40, generator=g, dtype=torch.float64)
    y = torch.zeros(40, dtype=torch.bool)
    y[torch.randperm(40, generator=g)[:7]] = True
    s[y] += 0.7
    assert metrics.roc_auc(s, y) == pytest.approx(_mann_whitney(s.tolist(), y.tolist()), abs=1e-14)
    s = torch.tensor([1.0 + 1e-12, 1.0, 1.0 + 2e-12, 0.5], dtype=torch.float64)
    y = torch.tensor([True, False, True, False])
    assert metrics.roc_auc(s, y) == 1.0 == _mann_whitney(s.tolist(), y.tolist())


def test_auc_is_nan_when_the_valid_steps_hold_one_class_and_nan_scores_are_refused():
    """One class among the *valid* steps (the other only on invalid ones) gives NaN; a NaN
    on a valid step raises, on an invalid step it is ignored."""
    s = torch.tensor([[0.1, 0.9, 0.4, 0.3]])
    y = torch.tensor([[True, False, True, True]])
    valid = torch.tensor([[True, False, True, True]])
    assert math.isnan(metrics.roc_auc(s, y, valid))
    assert math.isnan(metrics.roc_auc(s, ~y, valid))
    s_nan = s.clone()
    s_nan[0, 1] = math.nan
    y2 = torch.tensor([[True, False, False, True]])
    v2 = torch.tensor([[True, False, True, True]])
    assert metrics.roc_auc(s_nan, y2, v2) == pytest.approx(
        _mann_whitney([0.1, 0.4, 0.3], [True, False, True])
    )
    with pytest.raises(ValueError, match="NaN"):
        metrics.roc_auc(s_nan, y2)
    with pytest.raises(ValueError, match="NaN"):
        metrics.roc_curve(s_nan, y2)


# ----------------------------------------------------------------------- detection delay


def _loop_delay(alarms, attacked):
    """Walk each run: episodes are maximal runs of attacked steps; the delay is the first
    alarm inside the episode minus its onset."""
    delays, episodes = [], 0
    for a_run, y_run in zip(alarms, attacked):
        t, T = 0, len(y_run)
        while t < T:
            if not y_run[t]:
                t += 1
                continue
            on = t
            while t < T and y_run[t]:
                t += 1
            episodes += 1
            hits = [k for k in range(on, t) if a_run[k]]
            if hits:
                delays.append(hits[0] - on)
    return delays, episodes


@pytest.mark.parametrize("seed", [6, 7, 8])
def test_detection_delay_against_walking_the_episodes(seed):
    """Mean delay, episodes, detected and missed against a loop over each run's episodes,
    on runs with different numbers of episodes, episodes at step 0 and at the last step,
    alarms before onsets and between episodes, and a ``[2, 3, T]`` batch."""
    g = _gen(seed)
    shape = (2, 3, 14)
    attacked = torch.rand(shape, generator=g) < 0.45
    alarms = torch.rand(shape, generator=g) < 0.3
    attacked[0, 0, 0] = True
    attacked[1, 2, -1] = True
    a2, y2 = alarms.reshape(-1, 14).tolist(), attacked.reshape(-1, 14).tolist()
    delays, episodes = _loop_delay(a2, y2)
    d = metrics.detection_delay(alarms, attacked)
    assert d["episodes"] == episodes
    assert d["detected"] == len(delays)
    assert d["missed"] == episodes - len(delays)
    assert d["mean_delay"] == pytest.approx(sum(delays) / len(delays), abs=1e-12)


def test_detection_delay_by_hand_on_the_first_step_and_on_runs_of_unequal_episode_counts():
    """Run 0: one episode at steps 0–2, alarm at 1 (delay 1). Run 1: episodes 1–2 (alarm
    before it at 0 and after it at 3: missed), 5 (alarm at 5: delay 0) and 7–9 (alarm
    at 9: delay 2). Mean (1 + 0 + 2)/3 = 1, 4 episodes, 3 detected, 1 missed."""
    y = torch.tensor(
        [[1, 1, 1, 0, 0, 0, 0, 0, 0, 0], [0, 1, 1, 0, 0, 1, 0, 1, 1, 1]], dtype=torch.bool
    )
    a = torch.tensor(
        [[0, 1, 0, 0, 1, 0, 0, 0, 0, 0], [1, 0, 0, 1, 0, 1, 0, 0, 0, 1]], dtype=torch.bool
    )
    assert metrics.detection_delay(a, y) == {
        "mean_delay": 1.0,
        "episodes": 4,
        "detected": 3,
        "missed": 1,
    }
    # no run: nothing to score
    d = metrics.detection_delay(a[:0], y[:0])
    assert d["episodes"] == d["detected"] == d["missed"] == 0 and math.isnan(d["mean_delay"])


# ------------------------------------------------------------------ threshold_for


def _check_threshold(values, far, tau):
    """The rule by sorting: NaN counts as a step that never alarms, at most ⌊α n⌋ scores
    exceed τ, τ is one of the scores (or −∞), and the next lower candidate exceeds the
    budget."""
    arr = np.asarray(values, dtype=np.float64)
    n = arr.size
    arr = np.where(np.isnan(arr), -np.inf, arr)
    allowed = math.floor(round(far * n, 9))
    assert int((arr > tau).sum()) <= allowed
    lower = np.sort(np.unique(arr[arr < tau]))
    if tau != -math.inf:
        assert tau in arr
        # the largest candidate below τ (or −∞ if none) would allow too many alarms
        nxt = lower[-1] if lower.size else -math.inf
        assert int((arr > nxt).sum()) > allowed


@pytest.mark.parametrize("far", [0.01, 0.05, 0.1, 0.29, 0.5, 0.99])
def test_threshold_for_meets_the_rule_on_ties_nan_and_infinities(far):
    """The smallest τ with #{s > τ} ≤ ⌊α n⌋: checked by sorting in numpy, on 100 float32
    scores with ties, two NaN (lowest, counted in n), a +∞ and a −∞."""
    g = _gen(9)
    s = torch.randint(0, 30, (10, 10), generator=g).float() / 4
    s[0, 0], s[1, 1] = math.nan, math.nan
    s[2, 2], s[3, 3] = math.inf, -math.inf
    tau = metrics.threshold_for(s, far)
    _check_threshold(s.double().flatten().numpy(), far, tau)


def test_threshold_for_by_hand():
    """Hand cases: ⌊0.29 · 100⌋ = 29 alarms on 0 … 99 give τ = 70; three +∞ scores of
    ten at α = 0.2 give τ = +∞ (not the largest float); all-NaN gives −∞;
    α = 0.75 on four scores gives the smallest; α = 0.1 on ten scores with a NaN counts
    the NaN in n."""
    s = torch.arange(100.0).flip(0)
    assert metrics.threshold_for(s, 0.29) == 70.0
    # ⌊0.75 · 4⌋ = 3 alarms allowed: τ is the smallest score, 1 (−∞ would alarm 4)
    assert metrics.threshold_for(torch.tensor([4.0, 3.0, 2.0, 1.0]), 0.75) == 1.0
    inf3 = torch.tensor([math.inf] * 3 + [1.0] * 7)
    assert metrics.threshold_for(inf3, 0.2) == math.inf
    assert metrics.threshold_for(inf3, 0.3) == 1.0
    assert metrics.threshold_for(torch.full((4,), math.nan), 0.1) == -math.inf
    # n = 10 (one NaN): ⌊0.1 · 10⌋ = 1 alarm allowed, so τ = 2nd largest = 8
    s10 = torch.tensor([9.0, 8.0, 7.0, math.nan, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    assert metrics.threshold_for(s10, 0.1) == 8.0
    # −∞ scores are steps too: ⌊0.5 · 4⌋ = 2 of [5, −∞, −∞, −∞] may exceed: τ = −∞
    assert (
        metrics.threshold_for(torch.tensor([5.0, -math.inf, -math.inf, -math.inf]), 0.5)
        == -math.inf
    )
    assert (
        metrics.threshold_for(torch.tensor([5.0, -math.inf, -math.inf, -math.inf]), 0.25)
        == -math.inf
    )
    assert metrics.threshold_for(torch.tensor([5.0, 4.0, -math.inf, -math.inf]), 0.25) == 4.0


def test_threshold_for_keeps_float64_precision():
    """float64 scores 1e-12 apart stay distinct (a float32 cast would tie them)."""
    s = torch.tensor([1.0 + 3e-12, 1.0 + 2e-12, 1.0 + 1e-12, 1.0], dtype=torch.float64)
    assert metrics.threshold_for(s, 0.25) == 1.0 + 2e-12


# ------------------------------------------------------------- finite_scores / nan_as_lowest


def test_finite_scores_and_nan_as_lowest():
    """NaN becomes −∞, ±∞ and finite values stay (checked elementwise against numpy);
    ``finite_scores`` is float64 and flat, holding the float32 values exactly."""
    x = torch.tensor([[0.1, math.nan], [math.inf, -math.inf]], dtype=torch.float32)
    want = np.array([np.float32(0.1), -np.inf, np.inf, -np.inf], dtype=np.float64)
    f = metrics.finite_scores(x)
    assert f.dtype == torch.float64 and f.shape == (4,)
    assert f.tolist() == want.tolist()
    n = metrics.nan_as_lowest(x)
    assert n.dtype == torch.float32 and n.shape == (2, 2)
    assert n.flatten().tolist() == want.tolist()


# ------------------------------------------------- steps since an attack, after an attack


def _loop_since(flags):
    """flags: nested list [B][T][A] → steps since the last attacked step ≤ k, or −1."""
    out = []
    for run in flags:
        T, A = len(run), len(run[0])
        res = [[-1] * A for _ in range(T)]
        for a in range(A):
            last = -1
            for k in range(T):
                if run[k][a]:
                    last = k
                res[k][a] = k - last if last >= 0 else -1
        out.append(res)
    return out


def test_steps_since_attack_and_after_attack_against_a_loop_with_areas():
    """``steps_since_attack`` on ``[B, T, A]`` flags (time on dim 1, an attack at step 0),
    and ``after_attack(flags, 3)`` = steps since in 1 … 3, against loops."""
    g = _gen(10)
    flags = torch.rand(3, 11, 2, generator=g) < 0.2
    flags[0, 0, 0] = True
    flags[1, :, 1] = False
    flags[2, 4, 1] = True
    flags[2, 5:, 1] = False
    want = torch.tensor(_loop_since(flags.tolist()))
    got = metrics.steps_since_attack(flags)
    assert got.dtype == torch.int64
    assert torch.equal(got, want)
    after = metrics.after_attack(flags, 3)
    assert torch.equal(after, (want >= 1) & (want <= 3))
    assert bool(after[2, 7, 1]) and not bool(after[2, 8, 1]) and not bool(after[2, 4, 1])


def test_steps_since_attack_refuses_non_bool_flags():
    """Integer flags raise (they are not masks)."""
    with pytest.raises(ValueError, match="bool"):
        metrics.steps_since_attack(torch.zeros(2, 3, dtype=torch.uint8))


@pytest.mark.parametrize("before", [False, True])
def test_alarm_rate_since_attack_against_a_loop(before):
    """Bins [e_i, e_{i+1}) of the steps since the last attack (edges (1, 2, 4)), the last
    open, and with ``before`` the steps before a run's first attack as the last bin:
    counts and alarm shares against a loop over the steps."""
    g = _gen(11)
    flags = torch.rand(4, 16, generator=g) < 0.15
    flags[0, 0] = True
    flags[1, 5] = True
    alarms = torch.rand(4, 16, generator=g) < 0.5
    edges = (1, 2, 4)
    since = _loop_since([[[v] for v in run] for run in flags.tolist()])
    M = len(edges) + int(before)
    cnt, hit = [0] * M, [0] * M
    for b in range(4):
        for k in range(16):
            s = since[b][k][0]
            if s < 0:
                if not before:
                    continue
                i = len(edges)
            elif s < edges[0]:
                continue
            else:
                i = max(j for j, e in enumerate(edges) if s >= e)
            cnt[i] += 1
            hit[i] += bool(alarms[b, k])
    rates, counts = metrics.alarm_rate_since_attack(alarms, flags, edges, before=before)
    assert counts.tolist() == cnt
    want = [h / c if c else math.nan for h, c in zip(hit, cnt)]
    np.testing.assert_allclose(rates.numpy(), want, atol=1e-15)
    assert all(c > 0 for c in cnt)


def test_alarm_rate_since_attack_refuses_bad_edges():
    """Edges must be increasing integers ≥ 1: 0 and repeated edges raise."""
    f = torch.zeros(1, 4, dtype=torch.bool)
    for edges in [(0, 2), (2, 2), (3, 1), ()]:
        with pytest.raises(ValueError, match="edges"):
            metrics.alarm_rate_since_attack(f, f, edges)


def test_alarm_rate_since_attack_empty_bins_are_nan_and_before_is_always_a_bin():
    """An empty bin's rate is NaN (0/0), not 0; with ``before`` and every run attacked
    from step 0 the before-bin is still there, empty: M = len(edges) + 1. Hand-counted:
    flags at step 0 of both runs, T = 4, edges (1, 2, 50): steps 1 → bin 0, 2–3 → bin 1."""
    flags = torch.tensor([[1, 0, 0, 0], [1, 0, 0, 0]], dtype=torch.bool)
    alarms = torch.tensor([[1, 1, 0, 1], [0, 0, 0, 0]], dtype=torch.bool)
    rates, counts = metrics.alarm_rate_since_attack(alarms, flags, (1, 2, 50), before=True)
    assert counts.tolist() == [2, 4, 0, 0]
    assert rates[:2].tolist() == [1 / 2, 1 / 4]
    assert math.isnan(rates[2]) and math.isnan(rates[3])


def test_misfitting_delay_inputs_and_bad_threshold_inputs_are_refused():
    """``detection_delay`` names a labels tensor that does not fit; ``threshold_for``
    refuses a numpy array (TypeError) and an empty tensor (ValueError)."""
    with pytest.raises(ValueError, match="attacked"):
        metrics.detection_delay(
            torch.zeros(2, 5, dtype=torch.bool), torch.zeros(2, 4, dtype=torch.bool)
        )
    with pytest.raises(TypeError, match="torch.Tensor"):
        metrics.threshold_for(np.arange(10.0), 0.1)
    with pytest.raises(ValueError, match="at least one"):
        metrics.threshold_for(torch.zeros(0), 0.1)


def test_zero_one_labels_of_every_run_beside_a_valid_mask_per_run():
    """A trial: labels ``[T]`` as 0/1 floats beside ``valid [B, T]`` failed in a raw expand
    error (valid was expanded to the labels' shape); bool labels worked. Both now give the
    same AUC and counts."""
    from difffilter import metrics as dm

    g = torch.Generator().manual_seed(0)
    s = torch.randn(3, 5, generator=g)
    lab = torch.tensor([0.0, 1.0, 0.0, 1.0, 1.0])
    v = torch.ones(3, 5, dtype=torch.bool)
    v[0, 0] = False
    assert dm.roc_auc(s, lab, v) == dm.roc_auc(s, lab.bool(), v)
    assert dm.detection_counts(s > 0, lab, v) == dm.detection_counts(s > 0, lab.bool(), v)
    bad = lab.clone()
    bad[2] = 0.5  # a score passed for a label, scored in runs 1 and 2
    with pytest.raises(ValueError, match="must be bool"):
        dm.roc_auc(s, bad, v)
