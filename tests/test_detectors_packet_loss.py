"""The detectors under packet loss (a packet-loss researcher's trial): the online χ² step
judged every step against χ²_m (0.07 % alarms for 1 % where one of three entries arrived),
a threshold calibrated on the raw statistic pooled the degrees of freedom (0.07 %, 0.79 %,
1.79 % for 1, 2, 3 entries received), CUSUM's ``detect`` took no mask (a threshold
calibrated for 1 % through the gated filter alarmed 0.69 % there), and the gated χ²
filter refused a window with a mask."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.stats import chi2

import difffilter as df
from difffilter import metrics
from difffilter.fdi import (
    ChiSquareDetector,
    CusumDetector,
    chi_square_equivalent,
    gated_gaussian_filter,
    missing_entries_counted,
)

F64 = torch.float64


def _model():
    return df.LinearGaussianModel(
        torch.tensor([[0.9, 0.1], [0.0, 0.95]]), torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]),
        0.1 * torch.eye(2), 0.2 * torch.eye(3), torch.zeros(2), torch.eye(2),
    ).to(F64)  # fmt: skip


def _lossy(runs=60, steps=50, seed=3):
    model = _model()
    gen = torch.Generator().manual_seed(seed)
    _, ys, _ = model.simulate(steps, batch_shape=(runs,), generator=gen)
    mask = torch.rand(ys.shape, generator=gen, dtype=F64) > 0.3
    return model, ys, mask


def test_the_equivalent_statistic_has_the_same_tail_probability():
    """``x = F⁻¹_{χ²_D}(F_{χ²_d}(g))``: scipy's tails of ``x`` and ``g`` agree, unchanged
    where ``d = D``, 0 where ``d = 0``; beyond the tail's underflow ``x`` solves the
    tails' asymptotic series; the derivative is ``f_d(g) / f_D(x)`` (finite differences)."""
    g = torch.tensor([1e-3, 0.5, 2.0, 7.0, 30.0, 200.0, 900.0], dtype=F64)
    for d in (1, 2, 5):
        x = chi_square_equivalent(g, d, 6)
        assert chi2.sf(x.numpy(), 6) == pytest.approx(chi2.sf(g.numpy(), d), rel=1e-9)
        assert chi2.cdf(x.numpy(), 6) == pytest.approx(chi2.cdf(g.numpy(), d), rel=1e-9)
    # scipy.stats.chi2's map itself, bit for bit (the step calls scipy.special directly)
    gen = torch.Generator().manual_seed(4)
    many = torch.cat([torch.rand(500, generator=gen, dtype=F64) * 60, g,
                      torch.tensor([-1e-17, -2.0], dtype=F64)])  # fmt: skip
    dof = torch.randint(1, 6, many.shape, generator=gen).to(F64)
    tail = chi2.sf(many.numpy(), dof.numpy())
    lower = chi2.ppf(chi2.cdf(many.numpy(), dof.numpy()), 6)
    want = torch.from_numpy(chi2.isf(tail, 6)).where(
        torch.from_numpy(tail <= 0.5), torch.from_numpy(lower)
    )
    assert torch.equal(chi_square_equivalent(many, dof, 6), want)
    same = chi_square_equivalent(g, torch.tensor(6.0), 6)
    assert torch.equal(same, g)
    assert torch.equal(chi_square_equivalent(g, 0, 6), torch.zeros_like(g))

    def log_tail(x, k, terms=4):  # log P(χ²_k > x) for large x: the incomplete gamma's series
        a, z = k / 2, x / 2
        series, term = 1.0, 1.0
        for j in range(1, terms):
            term *= (a - j) / z
            series += term
        return (a - 1) * math.log(z) - z - math.lgamma(a) + math.log(series)

    for gb, d, big in ((2000.0, 1, 6), (5000.0, 3, 8), (1.5e4, 2, 3)):
        x = float(chi_square_equivalent(torch.tensor([gb], dtype=F64), d, big))
        assert log_tail(x, big) == pytest.approx(log_tail(gb, d), rel=1e-6)
        assert math.isfinite(x) and x > gb - 1  # not the inf of an underflowed tail
    g = torch.tensor([0.7, 3.0, 12.0], dtype=F64, requires_grad=True)
    x = chi_square_equivalent(g, 2, 5)
    (grad,) = torch.autograd.grad(x.sum(), g)
    h = 1e-6
    fd = (
        chi_square_equivalent(g.detach() + h, 2, 5) - chi_square_equivalent(g.detach() - h, 2, 5)
    ) / (2 * h)
    torch.testing.assert_close(grad, fd, rtol=1e-6, atol=0)
    with pytest.raises(ValueError, match=r"dof must lie in \[0, full_dof\]"):
        chi_square_equivalent(g.detach(), 4, 3)


def test_one_threshold_on_the_scores_is_one_rate_for_every_number_of_entries_received():
    """Statistics of 1, 2 and 3 degrees of freedom (exact χ² draws), one threshold
    calibrated on all of them at 1 %: the rate is 1 % for each, where the raw statistic's
    was 0.07 %, 0.79 % and 1.79 % in the trial's filter."""
    gen = torch.Generator().manual_seed(0)
    n = 200_000
    dof = torch.arange(1, 4, dtype=F64).repeat_interleave(n)
    # χ²_d as a sum of d squared normals (the draw is the model's, not the map's)
    z = torch.randn(3 * n, 3, dtype=F64, generator=gen)
    g = (z**2 * (torch.arange(3, dtype=F64) < dof[:, None])).sum(-1)
    raw = metrics.threshold_for(g, 0.01)
    assert float((g[:n] > raw).double().mean()) < 0.003  # the pooled raw threshold (the fault)
    tau = metrics.threshold_for(chi_square_equivalent(g, dof, 3), 0.01)
    scores = chi_square_equivalent(g, dof, 3)
    for d in range(3):  # 200,000 draws each: the rate's standard error is 0.00022
        rate = float((scores[d * n : (d + 1) * n] > tau).double().mean())
        assert rate == pytest.approx(0.01, abs=0.0012)


@pytest.mark.parametrize("window", [1, 3])
def test_the_online_chi_square_step_with_a_mask_is_detect_with_the_mask(window):
    """Step by step with each step's mask: the scores and alarms of ``detect`` on the
    whole sequence; without a mask the step is as before (every entry received)."""
    model, ys, mask = _lossy()
    mask[:5, 10] = False  # whole packets lost
    kf = df.kalman_filter(model, ys, mask=mask)
    g = df.fdi.normalized_innovation_squared(kf.innovations, kf.innovation_covs)
    det = ChiSquareDetector(3, 0.05, window=window)
    scores, alarms = det.detect(kf.innovations, kf.innovation_covs, mask=mask)
    state = det.init((ys.shape[0],))
    for t in range(ys.shape[1]):
        state, s, a = det.step(state, g[:, t], mask[:, t])
        torch.testing.assert_close(s, scores[:, t], rtol=1e-12, atol=1e-12)
        assert torch.equal(a, alarms[:, t])
    assert not bool(alarms[:5, 10].any()) or window > 1
    full = ChiSquareDetector(3, 0.05, window=window)
    plain_scores, plain_alarms = full.detect(kf.innovations, kf.innovation_covs)
    state = full.init((ys.shape[0],))
    for t in range(ys.shape[1]):
        state, s, a = full.step(state, g[:, t])
        torch.testing.assert_close(s, plain_scores[:, t], rtol=1e-12, atol=1e-12)
        assert torch.equal(a, plain_alarms[:, t])
    # a step's alarms are its equivalent score above the full window's quantile
    thresholds = det.thresholds(ys.shape[1])
    received = det._windowed(mask.sum(-1).double()) > 0
    agree = (scores > thresholds) == alarms
    assert bool(agree[received].all())


def test_the_gated_filter_takes_a_windowed_chi_square_with_a_mask_and_nonfinite():
    """The gated filter (not gating) alarms where ``detect`` on its innovations does, with a
    window under a mask (refused before); ``nonfinite="skip"`` is the explicit mask."""
    model, ys, mask = _lossy(runs=20, steps=30)
    det = ChiSquareDetector(3, 0.05, window=3)
    out = gated_gaussian_filter(model, ys, mask=mask, detector=det, filter=df.KalmanFilter(),
                                gate=False)  # fmt: skip
    kf = df.kalman_filter(model, ys, mask=mask)
    scores, alarms = det.detect(kf.innovations, kf.innovation_covs, mask=mask)
    torch.testing.assert_close(out.detection.scores, scores, rtol=1e-10, atol=1e-10)
    assert torch.equal(out.detection.alarms, alarms)
    holed = torch.where(mask, ys, torch.nan)
    skipped = gated_gaussian_filter(model, holed, detector=ChiSquareDetector(3, 0.05),
                                    filter=df.KalmanFilter(), nonfinite="skip")  # fmt: skip
    masked = gated_gaussian_filter(model, ys, mask=mask, detector=ChiSquareDetector(3, 0.05),
                                   filter=df.KalmanFilter())  # fmt: skip
    torch.testing.assert_close(skipped.means, masked.means, rtol=0, atol=0)
    assert torch.equal(skipped.detection.alarms, masked.detection.alarms)


def test_cusum_detect_with_a_mask_counts_the_missing_entries_as_the_gated_filter_does():
    model, ys, mask = _lossy(runs=20, steps=40)
    det = CusumDetector(5.0, threshold=6.0)
    kf = df.kalman_filter(model, ys, mask=mask)
    g = df.fdi.normalized_innovation_squared(kf.innovations, kf.innovation_covs)
    scores, alarms = det.detect(kf.innovations, kf.innovation_covs, mask=mask)
    counted = g + (3 - mask.sum(-1)).double()
    torch.testing.assert_close(missing_entries_counted(g, mask), counted, rtol=0, atol=0)
    assert torch.equal(alarms, det.run(counted)[1])
    torch.testing.assert_close(scores, det.scores(counted), rtol=0, atol=0)
    gated = gated_gaussian_filter(model, ys, mask=mask, detector=det, filter=df.KalmanFilter(),
                                  gate=False)  # fmt: skip
    assert torch.equal(gated.detection.alarms, alarms)
    assert not torch.equal(alarms, det.detect(kf.innovations, kf.innovation_covs)[1])


def test_a_chi_square_detector_at_a_threshold_of_ones_own():
    tau = 14.0855
    det = ChiSquareDetector.at_threshold(4, tau)
    assert det.threshold == pytest.approx(tau, rel=1e-9)
    assert det.false_alarm_rate == pytest.approx(float(chi2.sf(tau, 4)), rel=1e-12)
    assert ChiSquareDetector.at_threshold(2, 20.0, window=3).threshold == pytest.approx(20.0)
    for bad, match in ((0.0, "threshold must be"), (float("nan"), "threshold must be"),
                       (1e5, r"beyond what χ²_4 reaches")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            ChiSquareDetector.at_threshold(4, bad)
    with pytest.raises(ValueError, match="window must be an integer"):
        ChiSquareDetector.at_threshold(4, 10.0, window=0)


def test_an_overflowed_statistic_stays_beyond_every_threshold_under_a_mask():
    """From the review: ``+inf`` (an overflowed νᵀS⁻¹ν, which the online step takes as an
    alarm) mapped to NaN, the lowest score for the calibration and the ROC."""
    g = torch.tensor([math.inf, 0.26, 3.0], dtype=F64, requires_grad=True)
    x = chi_square_equivalent(g, torch.tensor([1.0, 1.0, 3.0]), 3)
    assert x[0] == math.inf and not bool(x.isnan().any())
    (grad,) = torch.autograd.grad(x[1:].sum(), g)
    assert bool(grad.isfinite().all()) and grad[0] == 0
    det = ChiSquareDetector(3, 0.01, window=2)
    state = det.init((2,))
    mask = torch.tensor([[True, False, False], [True, True, True]])
    state, s, a = det.step(state, torch.tensor([math.inf, 1.0], dtype=F64), mask)
    assert s[0] == math.inf and bool(a[0]) and not bool(s.isnan().any())
    state, s, a = det.step(state, torch.tensor([1.0, 1.0], dtype=F64), mask)
    assert s[0] == math.inf and bool(a[0])  # the window still holds it
    with pytest.raises(ValueError, match=r"mask \[..., 3\] must be one row per run of g \(2,\)"):
        det.step(state, torch.ones(2, dtype=F64), torch.ones(4, 2, 3, dtype=torch.bool))


def test_a_detector_at_a_threshold_far_in_the_tail_keeps_it():
    """From the review: the quantiles were ``ppf(1 − α)``, and ``1 − α`` keeps no digit of
    α = 3e-17 (a threshold of 80 on χ²_3 raised "prob must lie in (0, 1)" at the first
    step) and few of α = 4e-13 (60 read back as 59.99986)."""
    for tau in (60.0, 80.0, 100.0):
        det = ChiSquareDetector.at_threshold(3, tau)
        assert det.threshold == pytest.approx(tau, rel=1e-12)
        _, score, alarm = det.step(det.init((3,)), torch.tensor([tau - 1e-6, tau + 1e-6, 1.0],
                                                                dtype=F64))  # fmt: skip
        assert alarm.tolist() == [False, True, False]


def test_a_state_made_before_masks_were_counted_still_steps():
    """A ``(past, count)`` state (what ``init`` returned before, e.g. a saved gated carry)
    steps as the state ``init`` makes now, with and without a mask."""
    det = ChiSquareDetector(3, 0.05, window=3)
    gen = torch.Generator().manual_seed(0)
    g = torch.rand(4, 6, dtype=F64, generator=gen) * 8
    mask = torch.rand(4, 6, 3, generator=gen) > 0.3
    for start in (0, 1, 2):  # the old state after 0, 1, 2 unmasked steps (slots still empty)
        new = det.init((4,))
        for t in range(start):
            new, _, _ = det.step(new, g[:, t])
        old = new[:2]
        for t in range(start, 6):
            m = None if t < 2 else mask[:, t]
            new, s_new, a_new = det.step(new, g[:, t], m)
            old, s_old, a_old = det.step(old, g[:, t], m)
            torch.testing.assert_close(s_old, s_new, rtol=0, atol=0)
            assert torch.equal(a_old, a_new)


def test_steps_without_a_mask_after_masked_ones_count_the_windows_losses():
    """From the whole-change review: an unmasked step whose window still held lost entries
    was judged against χ² of the full window (score 17.0, no alarm, where the all-True mask
    gave 23.88 and an alarm): it is the all-True mask's step."""
    model, ys, mask = _lossy(runs=40, steps=30)
    kf = df.kalman_filter(model, ys, mask=mask)
    g = df.fdi.normalized_innovation_squared(kf.innovations, kf.innovation_covs)
    given = [mask[:, t] if t % 3 else None for t in range(ys.shape[1])]  # every third unmasked
    full_mask = torch.stack([m if m is not None else torch.ones_like(mask[:, 0]) for m in given], 1)
    det = ChiSquareDetector(3, 0.05, window=4)
    scores, alarms = det.detect(kf.innovations, kf.innovation_covs, mask=full_mask)
    state = det.init((ys.shape[0],))
    for t, m in enumerate(given):
        state, s, a = det.step(state, g[:, t], m)
        torch.testing.assert_close(s, scores[:, t], rtol=1e-12, atol=1e-12)
        assert torch.equal(a, alarms[:, t])


def test_the_upper_quantile_keeps_a_rate_in_the_far_tail():
    from difffilter.fdi import chi_square_upper_quantile

    for dof, rate in ((1, 0.01), (3, 3e-17), (6, 1e-9)):
        assert chi_square_upper_quantile(dof, rate) == pytest.approx(
            float(chi2.isf(rate, dof)), rel=1e-12
        )
    with pytest.raises(ValueError, match=r"rate must lie in \(0, 1\)"):
        chi_square_upper_quantile(2, 0.0)


def test_detect_takes_one_mask_per_run_as_the_filters_do():
    """From a multi-rate trial: a [T, m] mask of one run was broadcast to every run
    (1.60 % alarms for 1.18 %); the filters refuse it, and now the detectors do."""
    model, ys, mask = _lossy(runs=5, steps=20)
    kf = df.kalman_filter(model, ys, mask=mask)
    for det in (ChiSquareDetector(3, 0.05), CusumDetector(5.0, threshold=6.0)):
        with pytest.raises(ValueError, match=r"mask must have the innovations' shape \(5, 20, 3\)"):
            det.detect(kf.innovations, kf.innovation_covs, mask=mask[0])
        det.detect(kf.innovations, kf.innovation_covs, mask=mask[0].expand(5, 20, 3))


def test_cusum_online_step_takes_the_mask_as_detect_does():
    """From a recorded-log trial: the online step had no mask (ChiSquareDetector.step has
    one), so a stream under packet loss fed the raw NIS and alarmed otherwise than detect."""
    model, ys, mask = _lossy(runs=20, steps=40)
    det = CusumDetector(5.0, threshold=6.0)
    kf = df.kalman_filter(model, ys, mask=mask)
    g = df.fdi.normalized_innovation_squared(kf.innovations, kf.innovation_covs)
    _, alarms = det.detect(kf.innovations, kf.innovation_covs, mask=mask)
    state, online = det.init((20,)), []
    for t in range(40):
        state, _, alarm = det.step(state, g[:, t], mask=mask[:, t])
        online.append(alarm)
    assert torch.equal(torch.stack(online, -1), alarms)
    state, raw = det.init((20,)), []
    for t in range(40):  # without it: the raw NIS, as before
        state, _, alarm = det.step(state, g[:, t])
        raw.append(alarm)
    assert not torch.equal(torch.stack(raw, -1), alarms)
    with pytest.raises(ValueError, match=r"mask must broadcast to \(20, 20\); got \(2, 20\)"):
        det.step(det.init((20,)), g[:, 0], mask=mask[:, 0, :2].T)
    # a whole [T, m] mask given to one run's step grew the state to [T] (a review)
    with pytest.raises(ValueError, match=r"must be one row per run of g \(\)"):
        det.step(det.init(()), g[0, 0], mask=mask[0])


def test_the_online_cusum_step_checks_its_mask_against_the_entries_measured():
    """A recorded-log trial: a 2-wide mask on a 3-sensor NIS was taken as m = 2 (g + 1 for
    one lost entry, where two were lost) without a word; ``dim=`` checks it."""
    cusum = CusumDetector(bias=4.0, threshold=10.0)
    state, g = cusum.init(), torch.tensor(2.0, dtype=F64)
    _, s3, _ = cusum.step(state, g, torch.tensor([True, False, False]), dim=3)
    assert float(s3) == 0.0  # g + 2 − b = 0
    with pytest.raises(ValueError, match=r"mask must broadcast to \(3,\); got \(2,\)"):
        cusum.step(state, g, torch.tensor([True, False]), dim=3)
    with pytest.raises(
        ValueError, match=r"mask must be \[\.\.\., 3\] \(dim = 3 measured entries\)"
    ):
        cusum.step(state, g, torch.tensor([True]), dim=3)
    _, s2, _ = cusum.step(state, g, torch.tensor([True, False]))  # no dim: its width is m
    assert float(s2) == 0.0  # max(0, 2 + 1 − 4)
    # a one-wide mask broadcast to the χ² test's 3 entries had counted 1 or 0 received
    chi = ChiSquareDetector(3, 0.01)
    with pytest.raises(
        ValueError, match=r"mask must be \[\.\.\., 3\] \(dim = 3 measured entries\)"
    ):
        chi.step(chi.init(()), g, torch.tensor([True]))


@pytest.mark.parametrize("window", [1, 3])
def test_an_online_step_takes_one_statistic_per_run_of_its_state(window):
    """A deployment trial passed one run's innovation vector where its NIS belonged: with a
    window of 1 the χ² step returned two scores for one run (its state grew), with 3 torch
    said "Tensors must have same number of dimensions"; CUSUM's state grew likewise. Now
    each says which ``g`` it wants; a scalar ``g`` still broadcasts to the state's runs, and
    a right one scores as the χ² quantile says."""
    det = ChiSquareDetector(2, 0.01, window=window)
    with pytest.raises(ValueError, match=r"g must be one statistic per run of the state, \(\)"):
        det.step(det.init((), dtype=F64), torch.tensor([6.0, 12.0], dtype=F64))
    runs = det.init((3,), dtype=F64)
    _, score, alarm = det.step(runs, torch.tensor(10.0, dtype=F64))  # one g for every run
    assert score.shape == (3,) and bool(alarm.all()) == (10.0 > chi2.ppf(0.99, 2))
    with pytest.raises(ValueError, match=r"state, \(3,\) .* got \(4,\)"):
        det.step(runs, torch.ones(4, dtype=F64))
    cusum = CusumDetector(3.0, threshold=5.0)
    with pytest.raises(ValueError, match=r"state, \(2,\) \(the batch_shape of CusumDetector"):
        cusum.step(cusum.init((2,)), torch.ones(5, dtype=F64))
    with pytest.raises(TypeError, match="state must be CusumDetector.init's tensor"):
        cusum.step(None, torch.ones(2, dtype=F64))


def test_the_online_chi_square_detector_has_its_thresholds_before_the_first_step(monkeypatch):
    """The quantiles (SciPy, imported on first use: 0.6–1.6 s in a deployment trial's first
    step) are computed at ``init``: after it, a step, masked or not, asks SciPy for none (a
    rate no other test uses, so no quantile of it is cached before ``init``)."""
    import scipy.stats

    det = ChiSquareDetector(3, 0.01234, window=2)
    state = det.init((2,), dtype=torch.float32)

    def refused(*args, **kwargs):
        raise AssertionError("a quantile computed at a step")

    monkeypatch.setattr(scipy.stats.chi2, "isf", refused)
    g = torch.tensor([2.0, 40.0])
    state, _, alarm = det.step(state, g)
    assert alarm.tolist() == [False, True]
    mask = torch.tensor([[True, False, True], [True, True, True]])
    _, _, alarm = det.step(state, g, mask)
    assert alarm.tolist() == [False, True]


def _redundant_pairs_masked(unit):
    """Two redundant pairs of precise sensors (float32, variances near ``unit² = 1e-6``: a
    received pair's ``S`` is singular in float32, so it is jittered), over 2 runs × 3 steps,
    run 0 losing the second pair and run 1 the first: ``(r', S', mask, the received
    sub-models' (r [2, 3, 2], S [2, 3, 2, 2]))``, ``S'`` made as the filters make it
    (:func:`~difffilter.linalg.masked_measurement`: unit placeholders where lost)."""
    f32 = torch.float32
    P = unit**2 * torch.eye(2, dtype=f32)
    H = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0]], dtype=f32)
    R = unit**2 * 1e-9 * torch.eye(4, dtype=f32)
    c = torch.tensor([1.0, 0.5, 2.0], dtype=f32)[:, None]  # each step's size
    r = unit * c * torch.tensor([1.0, 1.0, 0.3, 0.3], dtype=f32)  # [3, 4]
    r = r.expand(2, 3, 4)
    mask = torch.tensor([[True, True, False, False], [False, False, True, True]])
    mask = mask[:, None, :].expand(2, 3, 4).clone()
    rm, Hm, Rm, _ = df.linalg.masked_measurement(r, H, R, mask)
    S = Hm @ P @ Hm.transpose(-1, -2) + Rm
    keep = torch.tensor([[0, 1], [2, 3]])  # each run's received pair
    r_sub = torch.stack([r[i][:, keep[i]] for i in range(2)])
    S_sub = torch.stack([(H[keep[i]] @ P @ H[keep[i]].T + R[keep[i]][:, keep[i]]).expand(3, 2, 2)
                         for i in range(2)])  # fmt: skip
    return rm, S, mask, r_sub, S_sub


def test_the_nis_and_detectors_of_a_masked_result_are_the_received_sub_models():
    """The NIS of a masked result in small units: ``S`` of the received pair fails to
    factorise in float32 and is jittered; the jitter had been scaled by the mean diagonal
    over every entry, the lost ones' unit placeholders too (5e5 times the received
    entries' own), and ``g`` was 0.8 where the received sub-model's is 1. With the mask
    ``g`` is the sub-model's, and the float64 closed form ``2 c² / (2 + 1e-9)`` of each
    pair (``r = c·unit·(1, 1)``); so are the χ² detector's and CUSUM's scores."""
    unit = 1e-3
    r, S, mask, r_sub, S_sub = _redundant_pairs_masked(unit)
    g_sub = df.fdi.normalized_innovation_squared(r_sub, S_sub)
    c = torch.tensor([1.0, 0.5, 2.0], dtype=F64)
    closed = torch.stack([2 * c**2 / (2 + 1e-9), 2 * (0.3 * c) ** 2 / (2 + 1e-9)])
    torch.testing.assert_close(g_sub.double(), closed, rtol=1e-4, atol=0)
    scores, alarms = ChiSquareDetector(4).detect(r, S, mask)
    torch.testing.assert_close(scores, chi_square_equivalent(g_sub, 2, 4), rtol=1e-5, atol=0)
    assert torch.equal(alarms, g_sub > chi2.ppf(0.99, 2))
    cusum = CusumDetector(bias=4.0, threshold=100.0)
    torch.testing.assert_close(cusum.detect(r, S, mask)[0], cusum.scores(g_sub + 2.0),
                               rtol=1e-5, atol=0)  # fmt: skip
    g = df.fdi.normalized_innovation_squared(r, S, mask=mask)
    torch.testing.assert_close(g, g_sub, rtol=1e-5, atol=0)


def test_a_mask_of_every_entry_changes_no_nis_of_a_shared_s():
    """``normalized_innovation_squared`` with one ``S [m, m]`` for every step and a mask
    of all ``True``: the same numbers as without the mask, bit for bit, as the docstring
    says (S had been expanded to the mask's runs first, which took the batched product
    instead of the shared factor's: 1.9e-6 apart in float32)."""
    g = torch.Generator().manual_seed(3)
    A = torch.randn(4, 4, generator=g)
    S = A @ A.T + 0.5 * torch.eye(4)
    nu = torch.randn(6, 50, 4, generator=g)
    every = torch.ones(6, 50, 4, dtype=torch.bool)
    assert torch.equal(df.fdi.normalized_innovation_squared(nu, S, mask=every),
                       df.fdi.normalized_innovation_squared(nu, S))  # fmt: skip


def test_the_nis_and_the_detectors_refuse_innovations_and_s_of_two_dtypes():
    """float64 innovations with a float32 S (and the reverse): refused by name, as
    ``whiteness`` and ``nees`` refuse them (the NIS had come out float32, 1.5e-5 off the
    float64 statistic, and the χ² and CUSUM alarms were decided on it)."""
    g = torch.Generator().manual_seed(4)
    nu = torch.randn(3, 20, 2, generator=g, dtype=torch.float64)
    S = torch.eye(2, dtype=torch.float64).expand(3, 20, 2, 2) * 1.3
    calls = (lambda n, s: df.fdi.normalized_innovation_squared(n, s),
             lambda n, s: df.fdi.ChiSquareDetector(2, 0.01).detect(n, s),
             lambda n, s: df.fdi.CusumDetector(4.0, 5.0).detect(n, s))  # fmt: skip
    for call in calls:
        for n, s in ((nu, S.float()), (nu.float(), S)):
            with pytest.raises(ValueError, match="give them one dtype and device"):
                call(n, s)
        call(nu, S)  # one dtype: runs


@pytest.mark.parametrize("window", [1, 2])
def test_a_window_with_nothing_received_scores_zero_and_never_alarms(window):
    """A mutation trial: with the score of a window of no degrees of freedom left as the
    window's statistic, every test passed, and windows that received nothing scored 6.63
    and 9.21 (χ²₁'s and χ²₂'s 1 % thresholds: innovations left at lost entries) where they
    score 0."""
    det = ChiSquareDetector(1, window=window)
    innovations = torch.tensor([[[5.0], [0.3], [7.0], [0.1]]], dtype=torch.float64)
    covs = torch.ones(1, 4, 1, 1, dtype=torch.float64)
    mask = torch.tensor([[[False], [False], [True], [False]]])
    scores, alarms = det.detect(innovations, covs, mask)
    assert scores[0, :2].tolist() == [0.0, 0.0]
    assert alarms[0].tolist() == [False, False, True, window == 2]
    assert (scores[0, 3] > 0) == (window == 2)  # (the window still holds step 3's entry)
