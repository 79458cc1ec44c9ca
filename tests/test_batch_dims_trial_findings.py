"""Findings of a red-team trial of batch shapes: runs of several axes, and no runs at all,
through the filters, detectors and metrics. Each test failed on the code before its fix."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter import metrics
from difffilter.consistency import whiteness
from difffilter.fdi.detectors import CusumDetector
from difffilter.fdi.gated import cusum_detector_for

F64 = dict(dtype=torch.float64)


def _nonlinear() -> df.NonlinearGaussianModel:
    def f(x, u, k):
        return torch.stack(
            [x[..., 0] + 0.1 * torch.sin(x[..., 1]) + u[..., 0], 0.9 * x[..., 1]], -1
        )

    def h(x, k):
        return torch.stack([0.5 * x[..., 0] ** 2 + x[..., 1], torch.sin(x[..., 0])], -1)

    eye = torch.eye(2, **F64)
    return df.NonlinearGaussianModel(
        f, h, 0.1 * eye, 0.2 * eye, torch.zeros(2, **F64), eye, dim_u=1
    )


@pytest.mark.parametrize("run", ["ekf", "eks", "jacobian"])
def test_no_runs_of_a_nonlinear_model_give_empty_outputs(run):
    # torch.func.vmap over no rows had handed the model's own h a view of no entries:
    # IndexError in x[..., 0] (the UKF and the PF return the empty outputs below)
    model = _nonlinear()
    ys, us = torch.zeros(0, 5, 2, **F64), torch.zeros(0, 5, 1, **F64)
    if run == "jacobian":
        jac = model.observation_jacobian(torch.zeros(0, 2, **F64), 1)
        assert jac.shape == (0, 2, 2) and jac.dtype == torch.float64
        return
    filt = df.extended_kalman_filter if run == "ekf" else df.extended_kalman_smoother
    out = filt(model, ys, us)
    assert out.means.shape == (0, 5, 2)
    assert df.unscented_kalman_filter(model, ys, us).means.shape == (0, 5, 2)


def test_the_jacobian_of_some_runs_is_unchanged_by_the_empty_case():
    model = _nonlinear()
    x = torch.tensor([[0.3, -1.2], [2.0, 0.5]], **F64)
    jac = model.observation_jacobian(x, 1)
    want = torch.stack([torch.tensor([[xi[0], 1.0], [torch.cos(xi[0]), 0.0]], **F64) for xi in x])
    torch.testing.assert_close(jac, want, rtol=0, atol=1e-15)


@pytest.mark.parametrize("shape", [(0, 10), (2, 0, 10)])
def test_cusum_calibration_on_no_runs_is_named(shape):
    # (torch's "max(): Expected reduction dim" had been all it said)
    with pytest.raises(ValueError, match="g_attack_free has no runs to calibrate on"):
        CusumDetector(4.0).calibrate(torch.rand(shape, **F64), 0.01)


def test_cusum_detector_for_names_the_empty_measurements():
    eye = torch.eye(2, **F64)
    model = df.LinearGaussianModel(0.9 * eye, eye, 0.1 * eye, 0.1 * eye, torch.zeros(2, **F64), eye)
    with pytest.raises(ValueError, match="ys has no runs or no steps"):
        cusum_detector_for(model, false_alarm_rate=0.01, ys=torch.zeros(0, 6, 2, **F64))


@pytest.mark.parametrize("masked", [False, True])
def test_whiteness_of_no_runs_is_named(masked):
    # (torch's amax on a dimension of size 0 had been all it said)
    nu = torch.zeros(0, 6, 2, **F64)
    covs = torch.eye(2, **F64).expand(0, 6, 2, 2)
    mask = torch.ones(0, 6, 2, dtype=torch.bool) if masked else None
    with pytest.raises(ValueError, match="innovations has no runs or no entries"):
        whiteness(nu, covs, mask=mask)


def test_since_the_attack_reads_runs_of_several_axes_with_time_dim():
    # flags [2, 3, T] had been read as 2 runs of 3 steps with T areas (the three functions
    # take time on dim 1): time_dim=-1 reads them as the flattened [6, T] batch does
    g = torch.Generator().manual_seed(0)
    alarms = torch.rand(2, 3, 6, generator=g) > 0.5
    flags = torch.rand(2, 3, 6, generator=g) > 0.5
    flat_a, flat_f = alarms.reshape(6, 6), flags.reshape(6, 6)
    since = metrics.steps_since_attack(flags, time_dim=-1)
    assert torch.equal(since, metrics.steps_since_attack(flat_f).reshape(2, 3, 6))
    after = metrics.after_attack(flags, 2, time_dim=-1)
    assert torch.equal(after, metrics.after_attack(flat_f, 2).reshape(2, 3, 6))
    rates, counts = metrics.alarm_rate_since_attack(alarms, flags, (1, 2, 3), time_dim=-1)
    flat_rates, flat_counts = metrics.alarm_rate_since_attack(flat_a, flat_f, (1, 2, 3))
    assert torch.equal(counts, flat_counts)
    torch.testing.assert_close(rates, flat_rates, equal_nan=True)
    # a hand count of run (0, 0): last attacked step before each step, by hand
    row = flags[0, 0].tolist()
    last, want = -1, []
    for k, hit in enumerate(row):
        last = k if hit else last
        want.append(-1 if last < 0 else k - last)
    assert since[0, 0].tolist() == want


@pytest.mark.parametrize("bad", [3, -4, 1.0, True])
def test_a_time_dim_out_of_range_or_not_an_int_is_named(bad):
    flags = torch.zeros(2, 5, dtype=torch.bool)
    with pytest.raises((ValueError, TypeError), match="time_dim"):
        metrics.steps_since_attack(flags, time_dim=bad)
