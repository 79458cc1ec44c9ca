"""Hand checks of the detection counts, the suite's scoring and what the closed loop hands on.

Confusion counts with a ``valid`` mask, ``score`` on a 2 × 4 case (time per step, RMSE,
false alarms with and without an attacked input, per-step RMSE, rates by attack size in
``(lo, hi]``), and the closed loop's views: the controller reads the received ỹ_k,
``KnownInputs`` gives u_k = us[:, k], ``ReplayedNoise`` measures at k = t + 1.
"""

from __future__ import annotations

import math

import pytest
import torch

import difffilter as df

F64 = torch.float64


def test_detection_counts_and_rates_by_hand_with_a_valid_mask():
    from difffilter import metrics

    alarms = torch.tensor([[1, 0, 1, 1], [0, 1, 0, 1]], dtype=torch.bool)
    flags = torch.tensor([[1, 1, 0, 0], [0, 0, 0, 1]], dtype=torch.bool)
    valid = torch.tensor([[1, 1, 1, 0], [1, 0, 1, 1]], dtype=torch.bool)
    # valid: TP (0,0), (1,3); FN (0,1); FP (0,2); TN (1,0), (1,2)
    assert metrics.detection_counts(alarms, flags, valid) == {"tp": 2, "fp": 1, "tn": 2, "fn": 1}
    rates = metrics.detection_rates(alarms, flags, valid)
    assert rates["tpr"] == pytest.approx(2 / 3)
    assert rates["fpr"] == pytest.approx(1 / 3)
    # all steps: FP (0,2), (0,3), (1,1); TN (1,0), (1,2)
    assert metrics.detection_rates(alarms, flags)["fpr"] == pytest.approx(3 / 5)


def _scored_case():
    from difffilter.estimator import Detection, EstimatorOutput
    from difffilter.loop import Trajectories

    B, T = 2, 4
    x = torch.zeros(B, T, 1, dtype=F64)
    means = torch.tensor([[[1.0], [0.0], [2.0], [0.0]], [[1.0], [0.0], [0.0], [2.0]]], dtype=F64)
    flags = torch.tensor([[0, 1, 1, 0], [0, 0, 0, 0]], dtype=torch.bool)
    alarms = torch.tensor([[1, 1, 0, 0], [0, 1, 0, 0]], dtype=torch.bool)
    traj = Trajectories(x, x, x, None, None, torch.zeros(B, T, 1, dtype=F64), flags, {})
    out = EstimatorOutput(means=means, detection=Detection(scores=alarms.double(), alarms=alarms))
    return out, traj, alarms, flags


def test_score_by_hand():
    from difffilter.eval import scoring

    out, traj, _, _ = _scored_case()
    row = scoring.score(out, traj, dt=0.5, wall_s=8.0)
    assert row["time_per_step_s"] == pytest.approx(8.0 / (2 * 4))
    assert row["state_rmse"] == pytest.approx(math.sqrt(10 / 8))
    assert row["false_alarms"] == 2 and row["fpr"] == pytest.approx(2 / 6)
    assert row["tpr"] == pytest.approx(0.5) and row["missed_attacks"] == 1
    assert (row["attack_episodes"], row["episodes_detected"], row["detection_delay_steps"]) == (
        1,
        1,
        0,
    )


def test_score_of_an_estimator_on_clean_input_counts_every_alarm_false():
    from difffilter.eval import scoring

    out, traj, _, _ = _scored_case()
    row = scoring.score(out, traj, dt=0.5, wall_s=8.0, attacked_input=False)
    assert row["false_alarms"] == 3 and row["fpr"] == pytest.approx(3 / 8)
    assert row["tpr"] is None and row["auc"] is None


def test_rmse_over_time_and_rates_by_size_by_hand():
    """Per step √(mean over runs and components e²); sizes binned in (lo, hi]."""
    from difffilter.eval import scoring

    out, traj, alarms, flags = _scored_case()
    torch.testing.assert_close(
        scoring.rmse_over_time(out.means, traj.x),
        torch.tensor([1.0, 0.0, math.sqrt(2), math.sqrt(2)], dtype=F64),
    )
    sizes = torch.tensor([[1.0, 1.0, 2.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    rows = scoring.rates_by_size(alarms, flags, sizes, [0.0, 1.0, 2.0])
    assert [(r["steps"], r["rate"]) for r in rows] == [(1, 1.0), (1, 0.0)]


def test_closed_loop_hands_the_controller_the_received_measurement():
    from difffilter.attack import TabulatedAttack
    from difffilter.loop import ReplayedNoise, closed_loop

    eye = torch.eye(2, dtype=F64)
    F = torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=F64)
    model = df.LinearGaussianModel(F, eye, 1e-3 * eye, 1e-2 * eye, torch.zeros(2, dtype=F64), eye,
                                   B=torch.tensor([[0.0], [0.1]], dtype=F64))  # fmt: skip

    class LateBias(TabulatedAttack):
        channel = "sensor"

        def sample(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
            b = (batch_shape,) if isinstance(batch_shape, int) else tuple(batch_shape)
            flags = torch.zeros(*b, num_steps, dtype=torch.bool)
            flags[..., 2:] = True
            return torch.full((*b, num_steps, dim), 5.0, dtype=dtype), flags

    class Recorder:
        def __init__(self):
            self.ys = []

        def init(self, batch, dtype, device):
            return torch.zeros(*batch, 1, dtype=dtype)

        def __call__(self, k, y, out):
            self.ys.append(y.clone())
            return torch.full((y.shape[0], 1), float(k), dtype=y.dtype)

    g = torch.Generator().manual_seed(0)
    noise = ReplayedNoise(*(torch.randn(2, 5, 2, generator=g, dtype=F64) for _ in range(2)))
    controller = Recorder()
    result = closed_loop(model, 5, noise=noise, x0=torch.zeros(2, 2, dtype=F64),
                         estimator=df.KalmanFilter(), controller=controller, attack=LateBias())  # fmt: skip
    traj = result.trajectories
    assert not torch.equal(traj.y_recv, traj.y_true)
    assert torch.equal(torch.stack(controller.ys, 1), traj.y_recv)


def test_known_inputs_and_replayed_noise_time_indices():
    """``KnownInputs(us)``: u_k = us[:, k]; ``ReplayedNoise.measure(t)``: h(x, t + 1) + v[:, t]."""
    from difffilter.loop import KnownInputs, ReplayedNoise

    us = torch.arange(10, dtype=F64).reshape(2, 5, 1)
    inputs = KnownInputs(us)
    assert torch.equal(inputs.init((2,), F64, None), us[:, 0])
    for k in range(1, 5):
        assert torch.equal(inputs(k, None, None), us[:, k])

    class TimeScaled:
        def observe(self, x, k):
            return x * k

    replayed = ReplayedNoise(torch.zeros(1, 3, 1), torch.zeros(1, 3, 1))
    assert [float(replayed.measure(TimeScaled(), torch.ones(1, 1), t)) for t in range(3)] == [
        1,
        2,
        3,
    ]
