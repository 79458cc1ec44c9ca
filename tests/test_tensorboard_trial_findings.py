"""What TensorBoard shows against the study's own numbers (a red-team trial, 2026-12-07;
each test failed before its fix)."""

from __future__ import annotations

from types import SimpleNamespace as NS

import pytest
import torch
from conftest import session_scalars

D = torch.float64


def _study(threshold):
    """Two runs, three steps, one detector whose calibrated threshold is ``threshold``."""
    x = torch.zeros(2, 3, 1, dtype=D)
    scores = torch.tensor([[1e-300, 0.5, 2.0], [1e-250, 1e-200, 3.0]], dtype=D)
    det = NS(alarms=scores > 1.0, scores=scores)
    traj = NS(x=x, attack=torch.zeros(2, 3, 0, dtype=D))
    result = NS(outputs={"pf": NS(means=x, detection=det, attack=None)},
                traj_of=lambda name: traj, metrics={"pf": {"threshold_at_far": threshold}})  # fmt: skip
    return result, scores


def test_the_hparams_rows_keep_a_threshold_below_float32s_range(tmp_path):
    """A particle filter's attack probability goes down to 1e-323, and its calibrated
    threshold with it: the session's scalars were float32, and 3.6e-234 was shown as 0 (a
    detector alarming at 87 % of the attack-free steps for the study's 1 %)."""
    from difffilter.eval.tensorboard import log_suite

    result, _ = _study(3.6e-234)
    doc = {"estimators": {"pf": {"threshold_at_far": 3.6e-234, "fpr_at_far": 0.0101}},
           "scenario": "s", "runs": 2, "seed": 0}  # fmt: skip
    log_suite(tmp_path, result, doc, [])
    got = session_scalars(tmp_path / "hparams" / "pf")
    assert got["hparam/threshold_at_far"] == [3.6e-234]
    assert got["hparam/fpr_at_far"] == [0.0101]  # (exactly: no float32 round-off either)


@pytest.mark.parametrize("threshold", [float("-inf"), 1e-260])
def test_the_alarm_rate_at_the_calibrated_threshold_is_drawn_for_every_calibrated_detector(
    tmp_path, threshold
):
    """A calibrated threshold of −∞ (calibrated so on purpose where no finite one meets the
    rate) is null in the report's JSON, and the curve had been left out (that case failed
    before the fix); the curve follows the study's threshold in double precision (1e-260
    splits these scores)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from difffilter.eval.tensorboard import log_suite

    result, scores = _study(threshold)
    doc = {"estimators": {"pf": {"threshold_at_far": None if threshold < 0 else threshold}},
           "scenario": "s", "runs": 2, "seed": 0}  # fmt: skip
    log_suite(tmp_path, result, doc, [])
    events = EventAccumulator(str(tmp_path))
    events.Reload()
    curve = [e.value for e in events.Scalars("alarm_rate_at_far_per_step/pf")]
    assert curve == pytest.approx((scores > threshold).double().mean(0).tolist())
    assert curve == ([1.0, 1.0, 1.0] if threshold < 0 else [0.5, 1.0, 1.0])
