"""Detectors, the gated filter and the replacement deception's cache (a red-team trial).

* ``ReplacementDeception.log_density`` kept its value keyed on ``y`` and ``mask`` alone: a
  density changed by ``load_state_dict`` answered with its old values (the mixture PF's
  log-likelihood 1 nat off), a learned one crashed the second ``backward``, and a value made
  under ``no_grad`` left the next training step without a gradient.
* Its dimension check ran only in ``__call__``, not on the paths that tabulate it.
* ``ChiSquareDetector`` kept the quantile table of its first use after ``false_alarm_rate``
  or ``window`` were set (235 alarms for 4, or an IndexError); a NaN ``CusumDetector``
  threshold assigned after ``__init__`` never alarmed.
* ``GatedFilter`` took a ``FixedGainFilter`` (no innovation covariance) and failed in torch.
"""

import math

import pytest
import torch
from scipy.stats import chi2

import difffilter as df
from difffilter.fdi.detectors import ChiSquareDetector, CusumDetector
from difffilter.fdi.gated import GatedFilter
from difffilter.fdi.mixture import (
    DeceptionMixtureLikelihood,
    ReplacementDeception,
    mixture_likelihood_particle_filter,
)
from difffilter.noise import Gaussian
from difffilter.observers import FixedGainFilter

d = torch.float64


def _model():
    one = torch.eye(1, dtype=d)
    return df.LinearGaussianModel(
        0.9 * one, one, 0.3 * one, 0.5 * one, torch.zeros(1, dtype=d), one
    )


def _ys():
    return _model().simulate(6, batch_shape=(2,), generator=torch.Generator().manual_seed(0))[1]


def _loglik(likelihood, ys):
    out = mixture_likelihood_particle_filter(_model(), ys, num_particles=200, likelihood=likelihood,
                                             generator=torch.Generator().manual_seed(1))  # fmt: skip
    return out.extras["log_likelihood"]


def test_a_reloaded_density_is_read_again():
    ys = _ys()
    density = Gaussian(torch.zeros(1, dtype=d), 4.0 * torch.eye(1, dtype=d))
    attack = ReplacementDeception(density)
    likelihood = DeceptionMixtureLikelihood(0.3, attack)
    attack.log_density(ys)
    state = density.state_dict()
    state["loc"] = state["loc"] + 3.0
    density.load_state_dict(state)
    torch.testing.assert_close(attack.log_density(ys), density.log_prob(ys))
    fresh = DeceptionMixtureLikelihood(0.3, ReplacementDeception(density))
    torch.testing.assert_close(_loglik(likelihood, ys), _loglik(fresh, ys))


def test_a_learned_density_trains_after_a_no_grad_pass_and_twice():
    ys = _ys()
    density = Gaussian(torch.nn.Parameter(torch.zeros(1, dtype=d)), 4.0 * torch.eye(1, dtype=d))
    likelihood = DeceptionMixtureLikelihood(0.3, ReplacementDeception(density))
    with torch.no_grad():
        _loglik(likelihood, ys)
    grads = [torch.autograd.grad(_loglik(likelihood, ys).sum(), density.loc)[0] for _ in range(2)]
    fresh = DeceptionMixtureLikelihood(0.3, ReplacementDeception(density))
    truth = torch.autograd.grad(_loglik(fresh, ys).sum(), density.loc)[0]
    for grad in grads:
        torch.testing.assert_close(grad, truth)
    assert truth.abs().item() > 1e-3


def test_a_density_of_another_dimension_is_named_on_every_path():
    one = torch.eye(1, dtype=d)
    two = torch.eye(2, dtype=d)
    model = df.LinearGaussianModel(
        0.9 * two, two, 0.3 * two, 0.5 * two, torch.zeros(2, dtype=d), two
    )
    ys = model.simulate(4, batch_shape=(2,), generator=torch.Generator().manual_seed(0))[1]
    likelihood = DeceptionMixtureLikelihood(
        0.3, ReplacementDeception(Gaussian(torch.zeros(1, dtype=d), one))
    )
    with pytest.raises(ValueError, match="density has dimension 1.*dim_y = 2"):
        mixture_likelihood_particle_filter(model, ys, num_particles=20, likelihood=likelihood,
                                           generator=torch.Generator().manual_seed(1))  # fmt: skip


def test_a_chi_square_detector_set_after_use_thresholds_at_its_new_setting():
    r = torch.randn(200, 20, 2, dtype=d, generator=torch.Generator().manual_seed(0))
    S = torch.eye(2, dtype=d).expand(200, 20, 2, 2)
    g = r.square().sum(-1)
    det = ChiSquareDetector(2, 0.05)
    det.detect(r, S)
    det.false_alarm_rate = 0.001
    assert int(det.detect(r, S)[1].sum()) == int((g > chi2.isf(0.001, 2)).sum())  # was 235
    det.window = 3
    fresh = ChiSquareDetector(2, 0.001, window=3)
    torch.testing.assert_close(det.detect(r, S)[1], fresh.detect(r, S)[1])
    with pytest.raises(ValueError, match="false_alarm_rate"):
        det.false_alarm_rate = math.nan
    with pytest.raises(ValueError, match="window must be an integer >= 1"):
        det.window = 0


def test_a_cusum_threshold_assigned_later_is_checked():
    det = CusumDetector(3.0, 1.0)
    with pytest.raises(ValueError, match="threshold must be a finite number"):
        det.threshold = math.nan
    with pytest.raises(ValueError, match="bias"):
        det.bias = -1.0
    det.threshold = None  # (uncalibrated: allowed, as at __init__)


def test_a_gated_filter_refuses_an_observer_without_innovation_covariance():
    with pytest.raises(TypeError, match="FixedGainFilter reports no innovation covariance"):
        GatedFilter(ChiSquareDetector(1), FixedGainFilter(torch.ones(1, 1, dtype=d)))


@pytest.mark.parametrize("dof", [math.inf, math.nan, 0.0, -1.0])
def test_the_chi_square_quantiles_refuse_a_dof_that_is_not_finite_and_positive(dof):
    """``chi_square_quantile(inf, p)`` had returned NaN (a threshold no score exceeds)."""
    from difffilter.fdi.detectors import chi_square_quantile, chi_square_upper_quantile

    for quantile in (chi_square_quantile, chi_square_upper_quantile):
        with pytest.raises(ValueError, match="dof must be a finite number > 0"):
            quantile(dof, 0.01)


def test_a_windowed_chi2_after_an_overflowed_statistic_sums_the_window_and_alarms():
    """A second trial: one reading whose NIS overflowed to +∞ made the running total +∞,
    and every window from W steps later NaN (∞ − ∞), which never alarms: an attack four
    steps later was missed. Truth: :meth:`ChiSquareDetector.step`, the last W values of g."""
    from difffilter.fdi.detectors import ChiSquareDetector, normalized_innovation_squared

    r = torch.full((8, 2), 0.5, dtype=torch.float32)
    r[2, 0], r[6] = 2e19, 4.0  # g_2 = +∞; g_6 = 32
    S = torch.eye(2, dtype=torch.float32).expand(8, 2, 2)
    det = ChiSquareDetector(2, 0.01, 3)
    g = normalized_innovation_squared(r, S)
    scores, alarms = det.detect(r, S)
    state, want = det.init((), dtype=torch.float32), []
    for k in range(8):
        state, s, _ = det.step(state, g[k])
        want.append(float(s))
    assert scores.tolist() == pytest.approx(want, rel=1e-6)
    assert scores[2:5].isinf().all() and alarms.tolist()[5:] == [False, True, True]


def test_the_mixture_attack_posterior_of_a_reading_no_hypothesis_explains_is_an_alarm():
    """A second trial: a float32 reading of 1e20 under a bias deception underflowed both
    densities, and ``−∞ − (−∞)`` scored NaN, no alarm; in float64 it scores 1 (the closed
    form ρᵀR⁻¹(y − h) − ρᵀR⁻¹ρ/2 ≈ 6e20: certainly attacked)."""
    from difffilter.fdi.mixture import (
        BiasDeception,
        DeceptionMixtureLikelihood,
        mixture_likelihood_particle_filter,
    )

    for dtype in (torch.float32, torch.float64):
        eye = torch.eye(2, dtype=dtype)
        model = df.LinearGaussianModel(
            eye, eye, 0.1 * eye, 0.5 * eye, torch.zeros(2, dtype=dtype), eye
        )
        ys = torch.zeros(1, 5, 2, dtype=dtype)
        ys[0, 2, 0] = 1e20
        lik = DeceptionMixtureLikelihood(0.1, BiasDeception(torch.tensor([3.0, 0.0], dtype=dtype)))
        out = mixture_likelihood_particle_filter(model, ys, num_particles=20, likelihood=lik,
                                                 generator=torch.Generator().manual_seed(0))  # fmt: skip
        assert float(out.detection.scores[0, 2]) == 1.0 and bool(out.detection.alarms[0, 2])
        assert not out.detection.scores.isnan().any()


# -- a second detector trial (2026-12-07) -----------------------------------------------


def _f64(x):
    return torch.tensor(x, dtype=torch.float64)


def test_a_cusum_over_a_whole_sequence_alarms_on_an_overflowed_statistic_as_its_step_does():
    # innovations of 1e200 (finite) give g = +inf: step() alarmed and reset, run() and
    # detect() raised about a g the caller never passed
    m, T = 2, 5
    r = torch.zeros(1, T, m, dtype=torch.float64)
    r[0, 2, 0] = 1e200
    S = torch.eye(m, dtype=torch.float64).expand(1, T, m, m)
    cusum = CusumDetector(bias=3.0, threshold=8.0)
    state, online = cusum.init((1,)), []
    for t in range(T):
        g = df.fdi.normalized_innovation_squared(r[:, t], S[:, t])
        state, _, alarm = cusum.step(state, g)
        online.append(bool(alarm))
    scores, alarms = cusum.detect(r, S)
    assert alarms[0].tolist() == online == [False, False, True, False, False]
    assert scores[0, :2].tolist() == [0.0, 0.0] and math.isinf(scores[0, 2])
    with pytest.raises(ValueError, match="NaN"):
        cusum.run(_f64([[1.0, math.nan]]))


def test_the_detectors_refuse_a_negative_statistic():
    # a g of −100 in the window silenced an alarming 30 two steps later
    chi = ChiSquareDetector(2, 0.01, window=3)
    with pytest.raises(ValueError, match="g must be >= 0"):
        chi.step(chi.init(), _f64(-100.0))
    cusum = CusumDetector(bias=4.0, threshold=5.0)
    for call in (
        lambda: cusum.step(cusum.init(), _f64(-1.0)),
        lambda: cusum.run(_f64([[1.0, -1.0]])),
        lambda: cusum.scores(_f64([[-1.0]])),
        lambda: cusum.calibrate(_f64([[3.0, -1.0, 2.0] * 40]), 0.05),
    ):
        with pytest.raises(ValueError, match="must be >= 0"):
            call()
    assert float(cusum.run(_f64([[0.0, 9.5]]))[0][0, 1]) == 5.5  # 0 is a NIS; 9.5 − 4 > 5 alarms


def test_a_chi_square_step_refuses_a_state_of_another_window_or_dim():
    # window 3 → 1 after init: the two held g = 5 stayed in every score (g + 10: 1 read 11 and
    # alarmed at every step); a state of a larger dim indexed past the quantile table
    chi = ChiSquareDetector(2, 0.01, window=3)
    state = chi.init(())
    for _ in range(2):
        state, _, _ = chi.step(state, _f64(5.0))
    chi.window = 1
    with pytest.raises(ValueError, match="another window: call init"):
        chi.step(state, _f64(1.0))
    state, score, alarm = chi.step(chi.init(), _f64(1.0))  # a new state: the W = 1 score is g
    assert float(score) == 1.0 and not bool(alarm)
    wide = ChiSquareDetector(3, 0.01, 2)
    state3, _, _ = wide.step(wide.init(), _f64(1.0))
    with pytest.raises(ValueError, match="another dim: call init"):
        ChiSquareDetector(2, 0.01, 2).step(state3, _f64(1.0))
    # the truth the checks leave alone: a state made for W = 2, m = 3 goes on as a sum of two
    state3, score, alarm = wide.step(state3, _f64(2.0))
    assert float(score) == 3.0 and bool(alarm) == (3.0 > chi2.ppf(0.99, 6))


@pytest.mark.parametrize("bad", [math.nan, 1.5, -0.1, "0.5", True])
def test_a_poa_detectors_zeta_or_eta_assigned_later_is_checked_as_at_init(bad):
    # ζ = NaN assigned after __init__ never alarmed (β > NaN is false), nor did the PFs that
    # read detector.zeta at every step
    detector = df.fdi.PoADetector(0.2, 0.5)
    with pytest.raises(ValueError, match="zeta must be a number in"):
        detector.zeta = bad
    with pytest.raises(ValueError, match="eta must be finite"):
        detector.eta = -1.0
    detector.zeta = torch.tensor(0.25, dtype=torch.float64)  # a one-entry tensor is a number
    assert detector.zeta == 0.25 and isinstance(detector.zeta, float)
    residuals = torch.tensor([[0.1], [0.3], [0.5], [0.05]])  # β = 0.5 of uniform weights
    beta, alarm = detector(residuals)
    assert float(beta) == pytest.approx(0.5) and bool(alarm)


def test_a_cusum_detector_for_refuses_a_bad_runs_by_name():
    one = torch.eye(1, dtype=torch.float64)
    model = df.LinearGaussianModel(one, one, one, one, torch.zeros(1, dtype=torch.float64), one)
    for runs in (0, -1, 2.5):
        with pytest.raises(ValueError, match="runs must be a positive integer"):
            df.fdi.cusum_detector_for(model, false_alarm_rate=0.05, runs=runs, steps=10)


@pytest.mark.parametrize("bad", [math.nan, -1e7])
def test_a_cusum_step_refuses_a_state_that_is_no_statistic(bad):
    """``S ≥ 0`` and never NaN: a NaN state had scored NaN and never alarmed again (g = 1e6),
    a negative one cancelled the attack's evidence; :meth:`CusumDetector.check_state` (which
    GatedFilter calls) refused both, a direct ``step`` took them (a trial). ``+inf`` (an
    overflowed statistic) is a state the steps keep."""
    det = CusumDetector(bias=4.0, threshold=5.0)
    g = torch.tensor([1e6], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"state \(the statistic S\) must be >= 0 and not NaN"):
        det.step(torch.tensor([bad], dtype=torch.float64), g)
    _, s, alarm = det.step(torch.tensor([math.inf], dtype=torch.float64), g)
    assert math.isinf(float(s)) and bool(alarm)


def test_a_chi_square_step_refuses_a_window_that_holds_no_statistics():
    """As the CUSUM's S: a NaN window value had scored NaN and never alarmed while it was in
    the window (g = 1e6 twice), a negative one lowered the score."""
    det = ChiSquareDetector(2, 0.01, window=3)
    past, count, received = det.init((1,), dtype=torch.float64)
    g = torch.tensor([1e6], dtype=torch.float64)
    for bad in (math.nan, -1e7):
        with pytest.raises(ValueError, match=r"state\[0\] \(the window's values\) must be >= 0"):
            det.step((torch.full_like(past, bad), count, received), g)
    assert bool(det.step((past, count, received), g)[2])
    # nor counts of entries received that are none (a review: -2 flipped the alarm, NaN
    # failed as torch's IndexError)
    for bad in (math.nan, -2.0):
        with pytest.raises(ValueError, match=r"state\[2\] \(the entries received\) must be >= 0"):
            det.step((past, count, torch.full_like(received, bad)), g)
