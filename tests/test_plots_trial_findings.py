"""Findings of a red-team trial of the figures (each failed before its fix)."""

from __future__ import annotations

from types import SimpleNamespace

import torch

from difffilter.eval.plots import _roc_figure


def test_a_false_alarm_rate_of_zero_is_drawn_apart_from_one_false_alarm():
    """The ROC's false-alarm floor was the smallest non-zero rate itself (one alarm in n
    attack-free steps): a detector with no false alarm and one with one were drawn at the
    same x, and nothing said the edge meant 0 (a trial)."""
    gen = torch.Generator().manual_seed(0)
    flags = torch.zeros(4, 50, dtype=torch.bool)
    flags[:, 25:] = True  # 100 attack-free steps, 100 attacked
    clean = torch.rand(4, 50, generator=gen, dtype=torch.float64) + 2.0 * flags
    one = clean.clone()
    one[0, 3] = 10.0  # one attack-free step above every other: one false alarm
    outputs, metrics = {}, {}
    for name, scores in (("none", clean), ("one", one)):
        alarms = scores > 1.5
        outputs[name] = SimpleNamespace(detection=SimpleNamespace(scores=scores, alarms=alarms))
        metrics[name] = {"auc": 0.99, "fpr_at_far": float(alarms[~flags].double().mean()),
                         "tpr_at_far": float(alarms[flags].double().mean())}  # fmt: skip
    traj = SimpleNamespace(flags=flags)
    result = SimpleNamespace(traj=traj, outputs=outputs, metrics=metrics,
                             traj_of=lambda name: traj, calibration=SimpleNamespace(far=0.01))  # fmt: skip
    fig = _roc_figure(result, outputs, {"none": "#ff0000", "one": "#0000ff"},
                      {"none": "-", "one": "--"})  # fmt: skip
    dots = [line for line in fig.axes[0].get_lines() if line.get_marker() == "o"]
    x_none, x_one = (float(dot.get_xdata()[0]) for dot in dots)
    assert x_one == metrics["one"]["fpr_at_far"] == 0.01 and x_none < x_one
    floors = [line for line in fig.axes[0].get_lines()
              if line.get_label().startswith("no false alarm at all")]  # fmt: skip
    assert len(floors) == 1 and float(floors[0].get_xdata()[0]) == x_none
    assert fig.axes[0].get_xlim()[0] < x_none
