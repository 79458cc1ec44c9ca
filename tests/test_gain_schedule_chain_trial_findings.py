"""Findings of a trial of the gain schedule (each failed before its fix)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter.gain_schedule import GainSchedule

D = torch.float64


def test_a_chunk_whose_covariances_drift_past_round_off_runs_step_by_step():
    """Three random walks seen through their sum (a state and sensor biases): the chunked
    recursion's covariances were 2.5e-8 off, within the chain test's 1.5e-7, and cancelling
    in ``P⁻Hᵀ`` they gave gains 2.4 % off the textbook recursion (means 2.7e-4 off)."""
    dx, T = 3, 400
    F, H, Q, R, P0 = np.eye(dx), np.ones((1, dx)), 1e-9 * np.eye(dx), 1e-6 * np.eye(1), np.eye(dx)
    P, gains = P0, []
    for _ in range(T):  # the textbook recursion, Joseph form
        Pm = F @ P @ F.T + Q
        K = Pm @ H.T @ np.linalg.inv(H @ Pm @ H.T + R)
        A = np.eye(dx) - K @ H
        P = A @ Pm @ A.T + K @ R @ K.T
        P = (P + P.T) / 2
        gains.append(K)
    model = df.LinearGaussianModel(
        *(torch.tensor(a) for a in (F, H, Q, R)), torch.zeros(dx, dtype=D), torch.tensor(P0)
    )
    schedule = GainSchedule(model)
    got = np.array([schedule.moments(k).gain.numpy() for k in range(1, T + 1)])
    relative = np.abs(got - np.array(gains)).max((1, 2)) / np.abs(np.array(gains)).max((1, 2))
    assert relative.max() < 1e-6


def test_a_schedule_update_refuses_a_measurement_of_another_width():
    """``update`` broadcast a ``y [1]`` over ``dy = 2`` and returned an estimate."""
    eye = torch.eye(2, dtype=D)
    schedule = GainSchedule(
        df.LinearGaussianModel(eye, eye, 0.1 * eye, 0.1 * eye, torch.zeros(2, dtype=D), eye)
    )
    with pytest.raises(ValueError, match=r"y must have shape \[\.\.\., 2\]; got \(1,\)"):
        schedule.update(torch.zeros(2, dtype=D), torch.ones(1, dtype=D), 1)
