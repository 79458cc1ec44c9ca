"""Findings of a second red-team trial of documented shapes (the filters' carries and one-step
functions, the loop's replayed noise) and of a property-based fuzzing trial (a numpy integer
detector size). Each test failed on the code before its fix."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter import loop
from difffilter.fdi import ChiSquareDetector
from difffilter.results import GaussianState

D = torch.float64


def _model() -> df.LinearGaussianModel:
    eye = torch.eye(2, dtype=D)
    F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=D)
    return df.LinearGaussianModel(F, eye, 0.1 * eye, 0.5 * eye, torch.zeros(2, dtype=D), eye)


@pytest.mark.parametrize("k", [0.5, -3, True])
def test_a_hand_built_carry_of_no_step_index_is_refused(k):
    # k = 0.5 or -3 had read a time-varying model at that step without a word
    state = GaussianState(torch.zeros(2, dtype=D), torch.eye(2, dtype=D), k, None)
    with pytest.raises(ValueError, match="carry.k must be an integer step index >= 0"):
        df.kalman_step(_model(), state, torch.zeros(2, dtype=D))


def test_a_carry_of_covariances_for_other_runs_is_named():
    # a mean of 3 runs with covariances of 2 had failed inside torch
    state = GaussianState(
        torch.zeros(3, 2, dtype=D), torch.eye(2, dtype=D).expand(2, 2, 2), 0, None
    )
    with pytest.raises(ValueError, match="carry.cov .* must hold runs that broadcast"):
        df.kalman_step(_model(), state, torch.zeros(3, 2, dtype=D))


def test_one_mean_for_a_batch_of_covariances_steps_those_runs():
    # its runs are the covariances': measurements of 3 runs had been refused as not fitting
    # "the carry's runs ()", while one measurement was taken for 3
    covs = torch.stack([s * torch.eye(2, dtype=D) for s in (1.0, 2.0, 3.0)])
    state = GaussianState(torch.zeros(2, dtype=D), covs, 0, None)
    y = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], dtype=D)
    new, _ = df.kalman_step(_model(), state, y)
    for i in range(3):
        one, _ = df.kalman_step(
            _model(), GaussianState(torch.zeros(2, dtype=D), covs[i], 0, None), y[i]
        )
        torch.testing.assert_close(new.mean[i], one.mean, rtol=0, atol=1e-15)


@pytest.mark.parametrize(
    "u,match",
    [
        (torch.zeros(2, 1), "u must have the model.s dtype"),
        (np.zeros((2, 3)), "u must be a torch.Tensor"),
    ],
)
def test_kalman_predict_names_a_wrong_input(u, match):
    # (raw torch errors: "expected m1 and m2 to have the same dtype", "mat1 and mat2")
    eye = torch.eye(2, dtype=D)
    model = df.LinearGaussianModel(
        eye, eye, 0.1 * eye, 0.5 * eye, torch.zeros(2, dtype=D), eye, B=eye
    )
    state = GaussianState(torch.zeros(2, 2, dtype=D), eye, 0, None)
    with pytest.raises((ValueError, TypeError), match=match):
        df.kalman_predict(model, state, u)
    mean, cov = df.kalman_predict(model, state, torch.ones(2, 2, dtype=D))
    torch.testing.assert_close(mean, torch.ones(2, 2, dtype=D))
    torch.testing.assert_close(cov, 1.1 * eye)


def test_replayed_noise_refuses_nan_draws_by_name():
    # NaN draws had run to NaN states (no estimator) or been blamed on the plant
    w = torch.zeros(3, 5, 2, dtype=D)
    w[1, 2, 0] = float("nan")
    with pytest.raises(ValueError, match="ReplayedNoise: process noise contains NaN"):
        loop.ReplayedNoise(w, torch.zeros(3, 5, 2, dtype=D))


def test_a_numpy_integer_detector_size_runs_as_an_int():
    # np.int64 had been kept, and a mask broadcast over runs failed inside torch
    # ("Expected bool, got numpy.bool")
    got = []
    for dim in (2, np.int64(2)):
        det = ChiSquareDetector(dim, 0.01)
        _, score, alarm = det.step(
            det.init((3,)), torch.ones(3, dtype=D), torch.tensor([True, False])
        )
        got.append(score)
    torch.testing.assert_close(got[1], got[0], rtol=0, atol=0)
    assert type(ChiSquareDetector(np.int64(2), window=np.int64(3)).window) is int
