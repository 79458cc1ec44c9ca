"""Findings of a new user's trial of the Python API and of a smoothers-and-gradients trial
(2026-12-04): a missing input to a nonlinear model with inputs, a smoother given a filter's
result of another dtype, a model object passed as its builder, a deception density's pair
passed whole, a hand-built indefinite covariance in a carry, and a calibration whose
spread went unsaid. Each test fails on the code before the fix."""

from __future__ import annotations

import json
import math

import pytest
import torch

import difffilter as df

F64 = torch.float64


def _nonlinear(dtype=F64, dim_u=1):
    eye = torch.eye(2, dtype=dtype)
    f = (lambda x, u: 0.9 * x + u) if dim_u else (lambda x: 0.9 * x)
    return df.NonlinearGaussianModel(
        f, lambda x: x[..., :1], 0.1 * eye, 0.2 * torch.eye(1, dtype=dtype),
        torch.ones(2, dtype=dtype), eye, dim_u=dim_u,
    )  # fmt: skip


def test_a_nonlinear_model_with_inputs_given_none_takes_the_input_as_zero():
    """docs/python-api.md: a step or sequence given no input on a model with inputs takes it
    as zero. ``f(x, u)`` had been handed ``None`` (a ``TypeError`` in the user's ``+``)."""
    model = _nonlinear()
    ys = torch.randn(3, 6, 1, generator=torch.Generator().manual_seed(0), dtype=F64)
    zeros = torch.zeros(3, 6, 1, dtype=F64)
    ekf = df.extended_kalman_filter(model, ys, zeros)
    for got in (df.extended_kalman_filter(model, ys), df.unscented_kalman_filter(model, ys)):
        torch.testing.assert_close(got.log_likelihood, ekf.log_likelihood, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(got.means, ekf.means, rtol=1e-12, atol=1e-12)
    # the smoother, whose Jacobians read the inputs, is given them, zeros as zeros (a later
    # trial: a smoother without the us its filter ran on had smoothed silently wrong)
    with pytest.raises(ValueError, match=r"us: the extended RTS smoother reads the inputs"):
        df.rts_smoother(model, ekf)
    df.rts_smoother(model, ekf, zeros)
    # one step of the online filter: the same as u = 0
    est = df.ExtendedKalmanFilter()
    c0 = est.init(model)
    (_, a), (_, b) = est.step(c0, ys[0, 0]), est.step(c0, ys[0, 0], torch.zeros(1, dtype=F64))
    torch.testing.assert_close(a.mean, b.mean, rtol=0, atol=0)
    # the zero input [..., du] follows x's batch (sigma points, runs): x + u of x's shape
    assert model.transition(torch.ones(5, 3, 2, dtype=F64), None, 0).shape == (5, 3, 2)
    torch.testing.assert_close(model.transition(torch.ones(2, dtype=F64), None, 0),
                               torch.full((2,), 0.9, dtype=F64))  # fmt: skip


def test_a_smoother_names_a_filter_result_of_another_dtype():
    """A float32 model given a float64 filter's result failed in torch ("expected scalar type
    Double but found Float"), naming neither."""
    m64, m32 = _nonlinear(F64, 0), _nonlinear(torch.float32, 0)
    ys = torch.randn(2, 5, 1, generator=torch.Generator().manual_seed(1), dtype=F64)
    ekf = df.extended_kalman_filter(m64, ys)
    pf = df.particle_filter(m64, ys, num_particles=20, return_particles=True,
                            generator=torch.Generator().manual_seed(0))  # fmt: skip
    for call, what in ((lambda: df.rts_smoother(m32, ekf), "means"),
                       (lambda: df.unscented_rts_smoother(m32, ekf), "means"),
                       (lambda: df.particle_smoother(m32, pf), "particles")):  # fmt: skip
        with pytest.raises(ValueError, match=f"filtered holds torch.float64 {what} and the model "
                                             "is torch.float32"):  # fmt: skip
            call()
    df.rts_smoother(m64, ekf), df.particle_smoother(m64, pf)  # the same dtype: smoothed


def test_a_custom_scenario_refuses_a_model_in_place_of_its_builder():
    """``model_fn=vdp(torch.float64)``: a model is callable (every ``nn.Module`` is) and took
    the dtype as its input: torch's "missing the required forward function"."""
    from difffilter.models.scenario import CustomScenario

    with pytest.raises(ValueError, match="got a NonlinearGaussianModel model itself: pass the "
                                         "function that builds it"):  # fmt: skip
        CustomScenario(name="c", family="custom", description="d", model_fn=_nonlinear())
    with pytest.raises(ValueError, match="model_fn must be a callable dtype -> StateSpaceModel"):
        CustomScenario(name="c", family="custom", description="d", model_fn=3)


def test_a_deception_density_must_be_callable_and_its_pair_is_named():
    """``deception=deception_of(...)`` without its ``[0]`` was accepted and failed at the
    first step: "'tuple' object is not callable"."""
    from difffilter.models import registry
    from difffilter.models.generic_estimators import deception_of

    scenario = registry.get("tracking_rrp_deception")
    pair = deception_of(scenario.attack_model(), F64)
    with pytest.raises(TypeError, match=r"not a tuple: deception_of\(...\) returns \(density, "
                                        r"rate\), give its \[0\]"):  # fmt: skip
        df.load_estimator("checkpoints/tracking_nn_grad.ckpt", deception=pair)
    with pytest.raises(TypeError, match="deception must be an object, not the string 'uniform'"):
        df.load_estimator("checkpoints/tracking_nn_grad.ckpt", deception="uniform")
    with pytest.raises(TypeError, match="deception must be an instance, not the class "
                                        "ReplacementDeception"):  # fmt: skip
        df.load_estimator("checkpoints/tracking_nn_grad.ckpt", deception=type(pair[0]))
    with pytest.raises(TypeError, match="deception"):  # too few arguments, named at load
        df.load_estimator("checkpoints/tracking_nn_grad.ckpt", deception=lambda model, y: y)
    df.load_estimator("checkpoints/tracking_nn_grad.ckpt", deception=pair[0])  # loads


def _linear():
    return df.LinearGaussianModel(
        torch.tensor([[0.95, 0.04], [-0.02, 0.8]], dtype=F64), torch.tensor([[1.0, 0.0]], dtype=F64),
        1e-4 * torch.eye(2, dtype=F64), 1e-3 * torch.eye(1, dtype=F64), torch.zeros(2, dtype=F64),
        1e-2 * torch.eye(2, dtype=F64),
    )  # fmt: skip


def test_a_rebuilt_carry_with_an_indefinite_covariance_is_refused():
    """Eigenvalues 3e-3 and −1e-3: the step returned a posterior of negative variance and a
    finite log-likelihood. A semi-definite one (a known state, ``P = 0``) and one a filter
    returned still step."""
    model, y = _linear(), torch.tensor([0.1], dtype=F64)
    indefinite = torch.tensor([[1e-3, 2e-3], [2e-3, 1e-3]], dtype=F64)
    assert float(torch.linalg.eigvalsh(indefinite)[0]) == pytest.approx(-1e-3)
    for est in (df.KalmanFilter(), df.ExtendedKalmanFilter(), df.UnscentedKalmanFilter()):
        carry = df.GaussianState(torch.zeros(2, dtype=F64), indefinite, 20, model)
        with pytest.raises(ValueError, match="carry.cov must be a covariance, positive "
                                             "semi-definite; its eigenvalues run from -0.001 to "
                                             "0.003"):  # fmt: skip
            est.step(carry, y)
        batch = torch.stack([torch.eye(2, dtype=F64), indefinite])  # the second run's
        with pytest.raises(ValueError, match=r"eigenvalues \(of a run\) run from -0.001"):
            est.step(
                df.GaussianState(torch.zeros(2, 2, dtype=F64), batch, 20, model), y.expand(2, 1)
            )
        for cov in (torch.zeros(2, 2, dtype=F64), est.step(est.init(model), y)[1].cov.clone()):
            est.step(df.GaussianState(torch.zeros(2, dtype=F64), cov, 1, model), y)
    # one check for every carry's covariance (the adaptive KF's attack_cov, the expected-
    # input filter's cov), float32 on torch's path's twin too
    from difffilter._checks import check_carry_tensor

    for t in (indefinite, indefinite.float()):
        with pytest.raises(ValueError, match="carry.attack_cov must be a covariance"):
            check_carry_tensor(t, "attack_cov", dim=2, covariance=True)
    check_carry_tensor(indefinite, "attack", dim=2)  # not a covariance: not asked


def test_calibrate_states_the_spread_of_a_threshold_on_few_alarms(tmp_path, capsys, monkeypatch):
    """A trial's plant: 5 % on 8 runs of 60 steps (24 alarms expected) gave 7 % on fresh
    runs and no note: the binomial standard deviation of the rate, √(0.05 · 0.95 / 480) =
    0.99 %, is now said, with the runs that expect about 100 alarms (⌈100 / 3⌉ = 34)."""
    from difffilter.train import calibrate as cal_mod

    gen = torch.Generator().manual_seed(0)
    scores = torch.rand(8, 60, generator=gen, dtype=F64)
    monkeypatch.setattr(cal_mod, "_scores", lambda *args: (scores, None))
    out = tmp_path / "x.ckpt"
    args = ["checkpoints/four_tank_nn_grad.ckpt", "--out", str(out), "--far", "0.05",
            "--runs", "8", "--no-progress"]  # fmt: skip
    assert cal_mod.main(args) == 0
    printed = capsys.readouterr().out
    assert math.sqrt(0.05 * 0.95 / 480) == pytest.approx(0.0099, abs=5e-5)
    assert (
        "note: 480 calibration steps at the 5 % target expect 24 alarms: the threshold's "
        "rate on fresh runs varies by about ±0.99 % between calibration draws"
    ) in printed
    assert "--runs 34 expects about 100" in printed
    assert json.loads(out.with_suffix(".json").read_text())["calibration"]["runs"] == 8
    # enough alarms (4,000 steps at 5 %: 200): nothing said
    monkeypatch.setattr(cal_mod, "_scores", lambda *args: (scores.repeat(9, 1)[:67], None))
    assert cal_mod.main([*args[:-3], "--runs", "67", "--no-progress", "--force"]) == 0
    assert "calibration steps at the" not in capsys.readouterr().out


def test_the_fused_modified_pf_equals_the_steps_with_one_generator_too():
    """``fused=True`` is "the same algorithm and random numbers" as the steps; with one
    generator for the propagation and the resampling the fused path drew the horizon's
    noise before any uniform (0.27 apart in the mean at N = 4, an alarm apart): it steps
    now, and with a ``resample_generator`` of its own it stays on the fast path."""
    import numpy as np

    from difffilter.fdi.modified_pf import modified_particle_filter
    from difffilter.fdi.poa import PoADetector
    from difffilter.models.four_tank import FourTankModel

    model, rng = FourTankModel(dtype=F64), np.random.default_rng(3)
    x0 = model.initial.mean.numpy()
    ys = torch.tensor(x0 + rng.normal(size=(1, 10, 4)) * 0.05
                      + (rng.random((1, 10, 1)) < 0.5) * 0.4)  # fmt: skip
    gamma = torch.full((1, 10, 4), 0.4, dtype=F64)

    def run(fused, **kw):
        return modified_particle_filter(
            model, ys, num_particles=4, detector=PoADetector(0.2333, 0.5), gamma_hat=gamma,
            fused=fused, generator=torch.Generator().manual_seed(7), **kw,
        )  # fmt: skip

    steps, one = run(False), run(True)
    torch.testing.assert_close(one.means, steps.means, rtol=0, atol=1e-12)
    assert torch.equal(one.detection.alarms, steps.detection.alarms)
    assert one.covs is not None  # stepped: the fused path returns no covariances
    fast = run(True, resample_generator=torch.Generator().manual_seed(9))
    stepped = run(False, resample_generator=torch.Generator().manual_seed(9))
    assert fast.covs is None  # the fused path, as before
    torch.testing.assert_close(fast.means, stepped.means, rtol=0, atol=1e-12)


def test_a_confidence_level_is_not_called_a_false_alarm_rate():
    """A confidence of 1.5 was refused as "a false-alarm rate in (0, 1)": its complement
    (a numerics check of the consistency tests)."""
    from difffilter.consistency import chi_square_bounds

    with pytest.raises(ValueError, match=r"confidence must be a confidence level in \(0, 1\)"):
        chi_square_bounds(2, 3, 1.5)
    lo, hi = chi_square_bounds(2, 3, 0.95)  # a level: accepted
    assert 0 < lo < 2 < hi
