"""Findings of a red-team trial of the fixed-gain observers and their designs: the learned
estimator's options around a Luenberger observer, its settings assigned later, and the
observer gain's input checks. Each test failed on the code before its fix."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difffilter import KalmanFilter, LinearGaussianModel
from difffilter.control import luenberger_gain, observer_poles
from difffilter.fdi.neural import NeuralCompensation
from difffilter.loop import open_loop
from difffilter.models.neural_estimator import NeuralFDIEstimator
from difffilter.observers import FixedGainFilter

F64 = torch.float64
EYE = torch.eye(2, dtype=F64)


def _model() -> LinearGaussianModel:
    return LinearGaussianModel(0.9 * EYE, EYE, 0.1 * EYE, 0.1 * EYE, torch.zeros(2, dtype=F64), EYE)


def _net() -> NeuralFDIEstimator:
    torch.manual_seed(0)
    return NeuralFDIEstimator(num_areas=1, area_dim=2, init_scale=0.5).double()


@pytest.mark.parametrize("feature", ["plain_innovation", "log_likelihood"])
def test_features_reading_what_an_observer_never_reports_are_refused_at_construction(feature):
    # (plain_innovation had failed at the first step in torch.diagonal(None); the
    # log-likelihood feature was refused only there, without naming the observer)
    from difffilter.fdi.neural import feature_dim

    net = NeuralFDIEstimator(num_areas=1, area_dim=2, init_scale=0.5,
                             extra_inputs=feature_dim((feature,), 2)).double()  # fmt: skip
    with pytest.raises(ValueError, match=f"{feature}: it reads the innovation covariance"):
        NeuralCompensation(net, FixedGainFilter(0.5 * EYE), standardize=False, features=(feature,))


@pytest.mark.parametrize("name", ["restart", "inner", "reject", "gating", "network"])
def test_options_built_by_the_constructor_are_not_reassignable(name):
    # restart assigned later had run as no restart (the copy it reads is made by the
    # constructor's choice): the means of restart=0.5 in the constructor differ by 2.6
    est = NeuralCompensation(_net(), KalmanFilter())
    value = {"restart": 0.5, "inner": FixedGainFilter(0.5 * EYE), "reject": 0.01,
             "gating": True, "network": _net()}[name]  # fmt: skip
    with pytest.raises(AttributeError, match=f"{name} is checked with the other options"):
        setattr(est, name, value)
    est.threshold = 0.7  # (the LFC entries set the threshold later: still checked and kept)
    assert est.threshold == 0.7


def test_restart_given_to_the_constructor_moves_the_estimates():
    # the option the refusal above points to works (the truth the ignored one missed)
    g = torch.Generator().manual_seed(0)
    ys = torch.randn(3, 30, 2, dtype=F64, generator=g)
    ys[:, 10:, 0] += 3.0
    net = _net()
    with_restart = open_loop(NeuralCompensation(net, KalmanFilter(), restart=0.5), _model(), ys)
    without = open_loop(NeuralCompensation(net, KalmanFilter()), _model(), ys)
    assert (with_restart.means - without.means).abs().max() > 0.1


@pytest.mark.parametrize("dtype", [torch.complex128, torch.int64, torch.bool])
def test_a_gain_not_real_floating_is_refused(dtype):
    # a complex gain had run as its real part (means equal to it to 0), int and bool cast
    gain = torch.ones(2, 2, dtype=dtype)
    with pytest.raises(ValueError, match=f"real floating tensor .*{dtype}"):
        FixedGainFilter(gain)
    obs = FixedGainFilter(0.5 * EYE)
    with pytest.raises(ValueError, match="real floating"):
        obs.gain = gain


@pytest.mark.parametrize("A", [[[0.0, 2.0], [-2.0, 0.0]], [[0.5, 0.0], [0.0, -1.0]]])
@pytest.mark.parametrize("design", ["modal", "robust", "diagonal"])
def test_a_closed_loop_with_a_mode_that_never_decays_is_refused(A, design):
    # an undamped pair ±2i gave error poles on the unit circle (spectral radius 1.000000),
    # an unstable +0.5 outside it (1.1618): an observer that never converges, unsaid
    A = torch.tensor(A, dtype=F64)
    Ad = torch.matrix_exp(0.1 * A)
    with pytest.raises(ValueError, match="A_closed must be stable but for zero eigenvalues"):
        luenberger_gain(Ad, A, 0.1, design=design)
    with pytest.raises(ValueError, match="real part ≥ 0"):
        observer_poles(A, 0.1)


def test_a_stable_closed_loop_still_gets_its_poles():
    # the refusal leaves the designs of stable loops alone: poles exp(3 λ dt) placed exactly
    A = torch.tensor([[-1.0, 0.5], [0.0, -2.0]], dtype=F64)
    Ad = torch.matrix_exp(0.1 * A)
    for design in ("modal", "robust", "diagonal"):
        L = luenberger_gain(Ad, A, 0.1, design=design)
        poles = np.sort(np.linalg.eigvals(Ad.numpy() @ (np.eye(2) - L.numpy())).real)
        np.testing.assert_allclose(poles, np.sort(np.exp(3 * 0.1 * np.array([-2.0, -1.0]))),
                                   rtol=1e-10)  # fmt: skip


def test_a_singular_ad_is_named():
    # numpy's bare "Singular matrix" had named neither Ad nor why it must be invertible
    Ad = torch.tensor([[0.0, 1.0], [0.0, 0.5]], dtype=F64)
    A = torch.diag(torch.tensor([-1.0, -2.0], dtype=F64))
    with pytest.raises(ValueError, match="Ad must be invertible"):
        luenberger_gain(Ad, A, 0.1)
