"""Metrics and residual detectors against hand-computed values and known distributions."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter import metrics
from difffilter.fdi.detectors import (
    ChiSquareDetector,
    CusumDetector,
    chi_square_quantile,
    normalized_innovation_squared,
)


def test_detection_rates_and_counts():
    alarms = torch.tensor([[1, 0, 1, 0, 0], [0, 0, 1, 1, 0]], dtype=torch.bool)
    attacked = torch.tensor([[1, 1, 0, 0, 0], [0, 0, 1, 1, 1]], dtype=torch.bool)
    r = metrics.detection_rates(alarms, attacked)
    assert (r["tp"], r["fp"], r["tn"], r["fn"]) == (3, 1, 4, 2)
    assert r["tpr"] == pytest.approx(3 / 5) and r["fpr"] == pytest.approx(1 / 5)
    assert r["false_alarms"] == 1 and r["missed_attacks"] == 2


def test_roc_auc_matches_pairwise_definition():
    g = torch.Generator().manual_seed(0)
    labels = torch.rand(400, generator=g) < 0.4
    scores = torch.randn(400, generator=g) + labels.double() * 1.0
    scores[::7] = 0.5  # ties
    pos, neg = scores[labels], scores[~labels]
    diff = pos[:, None] - neg[None, :]
    pairwise = ((diff > 0).double() + 0.5 * (diff == 0).double()).mean().item()
    assert metrics.roc_auc(scores, labels) == pytest.approx(pairwise, abs=1e-12)
    assert math.isnan(metrics.roc_auc(scores, torch.ones(400, dtype=torch.bool)))


def test_a_perfect_detectors_auc_is_one_not_one_plus_round_off():
    """A statistician's trial read AUC = 1.0000000000000002 in lfc_step's metrics.json."""
    g = torch.Generator().manual_seed(0)
    hits = 0
    for _ in range(60):  # perfectly separated scores of random sizes and class shares
        n = int(torch.randint(20, 3000, (1,), generator=g))
        labels = torch.rand(n, generator=g) < torch.rand(1, generator=g)
        if bool(labels.all()) or not bool(labels.any()):
            continue
        scores = labels.double() * 2 + torch.rand(n, generator=g, dtype=torch.float64)
        fpr, tpr, _ = metrics.roc_curve(scores, labels)
        hits += float(torch.trapezoid(tpr, fpr)) > 1.0  # the round-off is there
        assert metrics.roc_auc(scores, labels) == 1.0
    assert hits >= 1


def test_detection_delay_episodes():
    attacked = torch.tensor([[0, 1, 1, 1, 0, 0, 1, 1], [1, 1, 0, 0, 0, 0, 0, 0]], dtype=torch.bool)
    alarms = torch.tensor([[0, 0, 0, 1, 0, 1, 0, 0], [1, 0, 0, 0, 0, 0, 0, 0]], dtype=torch.bool)
    d = metrics.detection_delay(alarms, attacked)
    assert d["episodes"] == 3 and d["detected"] == 2 and d["missed"] == 1
    assert d["mean_delay"] == pytest.approx((2 + 0) / 2)
    empty = metrics.detection_delay(alarms[:, :0], attacked[:, :0])  # T = 0: no episode
    assert empty["episodes"] == 0 and math.isnan(empty["mean_delay"])


def test_the_threshold_allows_floor_of_alpha_n_alarms_whatever_the_round_off():
    """0.29 · 100 = 28.999999999999996: the floor dropped one allowed alarm."""
    scores = torch.arange(100, dtype=torch.float64)
    tau = metrics.threshold_for(scores, 0.29)
    assert int((scores > tau).sum()) == 29
    assert int((scores > metrics.threshold_for(scores, 0.01)).sum()) == 1


def test_steps_since_attack_hand_counted_and_against_a_loop():
    """0 on an attacked step, then 1, 2, … until the next; −1 before a run's first attack;
    each area its own. Then random flags against a loop over the steps."""
    flags = torch.tensor([[0, 1, 1, 0, 0, 1, 0], [0, 0, 0, 0, 0, 0, 0]], dtype=torch.bool)
    expected = torch.tensor([[-1, 0, 0, 1, 2, 0, 1], [-1] * 7])
    assert torch.equal(metrics.steps_since_attack(flags), expected)
    areas = torch.stack([flags, flags.roll(1, dims=1)], -1)
    assert torch.equal(metrics.steps_since_attack(areas)[..., 0], expected)

    gen = torch.Generator().manual_seed(0)
    flags = torch.rand(6, 300, 2, generator=gen) < 0.03
    since = torch.full((6, 2), -1)
    for k in range(300):  # the reference: count up from each attacked step
        since = torch.where(flags[:, k], 0, torch.where(since >= 0, since + 1, since))
        assert torch.equal(metrics.steps_since_attack(flags)[:, k], since)


def test_alarm_rate_since_attack_hand_counted():
    """Bins [1, 3), [3, ∞) of the steps since the last attack: attacked steps and those
    before a run's first attack count in none."""
    flags = torch.tensor([[0, 1, 0, 0, 0, 0], [1, 0, 0, 0, 0, 0]], dtype=torch.bool)
    alarms = torch.tensor([[1, 1, 1, 0, 1, 1], [1, 1, 1, 1, 0, 0]], dtype=torch.bool)
    # since: [-1, 0, 1, 2, 3, 4], [0, 1, 2, 3, 4, 5]
    rates, counts = metrics.alarm_rate_since_attack(alarms, flags, edges=(1, 3))
    assert counts.tolist() == [4, 5]
    assert rates.tolist() == pytest.approx([3 / 4, 3 / 5])
    rates, counts = metrics.alarm_rate_since_attack(alarms, flags, edges=(2, 10))
    assert counts.tolist() == [7, 0] and rates[0].item() == pytest.approx(4 / 7)
    assert math.isnan(rates[1].item())  # an empty bin
    rates, counts = metrics.alarm_rate_since_attack(alarms, flags, edges=(1, 3), before=True)
    assert counts.tolist() == [4, 5, 1]  # the last bin: run 0's step 0, before its attack
    assert rates.tolist() == pytest.approx([3 / 4, 3 / 5, 1.0])
    after = metrics.after_attack(flags, 2)  # fpr_at_far_after_attack's steps: the bin [1, 3)
    assert alarms[after].double().mean().item() == pytest.approx(3 / 4)
    with pytest.raises(ValueError, match="edges must be increasing"):
        metrics.alarm_rate_since_attack(alarms, flags, edges=(3, 3))
    with pytest.raises(ValueError, match="alarms must be a bool tensor"):
        metrics.alarm_rate_since_attack(alarms.float(), flags)
    with pytest.raises(ValueError, match="flags must be a bool tensor"):
        metrics.steps_since_attack(flags.long())


def test_rmse():
    assert metrics.rmse(torch.tensor([1.0, 3.0]), torch.tensor([0.0, 0.0])).item() == pytest.approx(
        math.sqrt(5)
    )


@pytest.mark.parametrize(
    "dof,prob,expected",
    [(1, 0.95, 3.841458820694124), (2, 0.99, 9.21034037197618), (4, 0.999, 18.46682695290317)],
)
def test_chi_square_quantile_against_tables(dof, prob, expected):
    assert chi_square_quantile(dof, prob) == pytest.approx(expected, rel=1e-9)


def test_chi_square_detector_false_alarm_rate_on_model_consistent_innovations():
    g = torch.Generator().manual_seed(1)
    S = torch.tensor([[2.0, 0.3], [0.3, 0.5]], dtype=torch.float64)
    L = torch.linalg.cholesky(S)
    innov = torch.randn(200, 500, 2, dtype=torch.float64, generator=g) @ L.T
    det = ChiSquareDetector(dim=2, false_alarm_rate=0.05)
    _, alarms = det.detect(innov, S.expand(200, 500, 2, 2))
    rate = alarms.double().mean().item()
    assert abs(rate - 0.05) < 4 * math.sqrt(0.05 * 0.95 / alarms.numel())
    # windowed statistic: sums of W consecutive g's against χ²_{mW}
    detw = ChiSquareDetector(dim=2, false_alarm_rate=0.05, window=4)
    s, a = detw.detect(innov, S.expand(200, 500, 2, 2))
    g_ = normalized_innovation_squared(innov, S.expand(200, 500, 2, 2))
    torch.testing.assert_close(s[:, 10], g_[:, 7:11].sum(-1))
    assert abs(a[:, 3:].double().mean().item() - 0.05) < 0.01


def test_cusum_hand_computed_and_calibration():
    det = CusumDetector(bias=2.0, threshold=3.0)
    g = torch.tensor([[1.0, 4.0, 3.5, 0.0, 5.0, 2.0]])
    stat, alarm = det.run(g)
    # S: 0, 2, 3.5 (>3 alarm, reset 0), 0, 3 (not > 3), 3
    torch.testing.assert_close(stat, torch.tensor([[0.0, 2.0, 3.5, 0.0, 3.0, 3.0]]))
    assert alarm.tolist() == [[False, False, True, False, False, False]]
    gen = torch.Generator().manual_seed(2)
    free = (torch.randn(300, 200, 2, generator=gen) ** 2).sum(-1)  # χ²_2 statistics
    det = CusumDetector(bias=3.0)
    tau = det.calibrate(free, 0.01)
    rate = det.run(free)[1].double().mean().item()
    assert tau > 0 and rate <= 0.01 + 1e-9 and rate > 0.005
    # a rate above what the statistic reaches at τ = 0 (an API trial: 0.99 gave τ ≈ 0 and a
    # rate of 0.21, unsaid)
    most = det.run(free, 0.0)[1].double().mean().item()
    with pytest.raises(ValueError, match=f"out of reach.*at most {most:.4g}") as caught:
        CusumDetector(bias=3.0).calibrate(free, 0.99)
    # 60,000 steps are enough to see 0.99: only the rate is blamed
    assert "needs at least" not in str(caught.value)
    # too few steps to see the rate at all (a one-step YAML scenario, 8 runs: none crossed b,
    # and the rate alone was blamed): the sample's size is named with what it needs
    few = torch.tensor([[0.5], [1.0], [2.9], [0.1], [0.0], [1.5], [2.0], [0.7]])
    with pytest.raises(
        ValueError,
        match=r"at most 0 of these 8 steps \(g_attack_free \(8, 1\)\), at τ = 0; a rate of "
        r"0\.01 needs at least 100 attack-free steps",
    ):
        CusumDetector(bias=3.0).calibrate(few, 0.01)
    # a subnormal rate: the error, not an OverflowError from the count (a review)
    with pytest.raises(ValueError, match=r"out of reach.*at τ = 0$"):
        CusumDetector(bias=3.0).calibrate(few, 1e-320)
    # a drift below E[g] = 2 (a closed-loop trial's b = 1, taken without a word)
    with pytest.warns(
        UserWarning, match=r"drift b = 1 is not above the mean of g_attack_free \(1\.99"
    ):
        CusumDetector(bias=1.0).calibrate(free, 0.01)


def test_cusum_scores_reset_at_zero_and_a_late_alarm_is_a_miss():
    """S_k = max(0, S_{k−1} + g_k − b): g = (0, 0, 5), b = 1 → (0, 0, 4) in ``scores`` (the
    ROC's statistic; only ``run`` was checked by hand). An alarm after its episode ended
    detects nothing: the episode is missed."""
    s = CusumDetector(bias=1.0).scores(torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64))
    assert s.tolist() == [0.0, 0.0, 4.0]
    attacked = torch.zeros(1, 10, dtype=torch.bool)
    attacked[0, 2:5] = True
    alarms = torch.zeros(1, 10, dtype=torch.bool)
    alarms[0, 6] = True
    d = metrics.detection_delay(alarms, attacked)
    assert (d["episodes"], d["detected"], d["missed"]) == (1, 0, 1)


def test_chi_square_on_a_masked_result_is_judged_by_the_entries_received():
    """A user trial: a masked KF result (half the entries lost) fed to ``detect`` alarmed
    at 0.016 for a nominal 0.05 (window 5: 0.002): an unreceived entry has innovation 0
    and variance 1, so ``g_k`` has as many degrees of freedom as entries received."""
    import difffilter as df

    model = df.LinearGaussianModel(
        torch.tensor([[0.9, 0.1], [0.0, 0.95]]), torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]),
        0.1 * torch.eye(2), 0.2 * torch.eye(3), torch.zeros(2), torch.eye(2),
    ).to(torch.float64)  # fmt: skip
    gen = torch.Generator().manual_seed(1)
    _, ys, _ = model.simulate(200, batch_shape=(250,), generator=gen)
    mask = torch.rand(ys.shape, generator=gen, dtype=torch.float64) > 0.5
    kf = df.kalman_filter(model, ys, mask=mask)
    received = mask.any(-1)
    for window in (1, 5):  # 50,000 steps: the rate's standard error is 0.001
        det = ChiSquareDetector(3, 0.05, window=window)
        _, blind = det.detect(kf.innovations, kf.innovation_covs)
        assert blind.double().mean() < 0.02
        _, alarms = det.detect(kf.innovations, kf.innovation_covs, mask=mask)
        assert float(alarms[received].double().mean()) == pytest.approx(0.05, abs=0.0035)
        if window == 1:
            assert not bool(alarms[~received].any())  # nothing received: nothing to judge
    with pytest.raises(ValueError, match=r"innovations have 3 entries a step; this detector "
                       r"was made for dim = 1"):  # fmt: skip
        ChiSquareDetector(1).detect(kf.innovations, kf.innovation_covs)


def test_a_windowed_chi_square_keeps_its_sums_over_a_long_float32_run():
    """A numerics trial: the window's sums, differences of running totals over the whole
    run, lost their precision in float32 (score errors of 0.06 at T = 1e6). Summed in
    float64, they are the window's own sums to float32's precision."""
    g = torch.rand(1, 400_000, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    det = ChiSquareDetector(dim=2, window=10)
    exact = det._windowed(g)  # float64 throughout
    direct = g.unfold(-1, 10, 1).sum(-1)  # each full window summed on its own
    torch.testing.assert_close(exact[..., 9:], direct, rtol=1e-9, atol=1e-9)
    low = det._windowed(g.float())
    assert low.dtype == torch.float32
    assert float((low.double() - exact).abs().max()) < 1e-5
