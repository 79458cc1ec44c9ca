"""The physical watermark against replay on the LFC loop (Mo & Sinopoli 2009): the
watermark reaches the plant and the observer alike, and the windowed χ² sees a replay that
it cannot see without it, for a control cost the study states."""

from __future__ import annotations

import json

import jsonschema
import pytest
import torch

import difffilter as df
from difffilter.eval.report import metrics_schema
from difffilter.eval.watermark import watermark_study, write_watermark
from difffilter.models import registry
from difffilter.models.lfc import LFCPlant, Watermarked, lfc_loop


def test_the_watermark_is_what_the_controller_sent_to_plant_and_observer():
    plant = LFCPlant()
    xi, theta = plant.sample_noise(2, 30, torch.Generator().manual_seed(0))
    load = torch.tensor([[0.01, 0.0]], dtype=torch.float64)
    gen = torch.Generator().manual_seed(1)
    mark = lambda c: Watermarked(c, torch.full((2,), 0.1), gen)  # noqa: E731
    marked = lfc_loop(plant, df.KalmanFilter(), xi, theta, load, compensate=False, watermark=mark)
    plain = lfc_loop(plant, df.KalmanFilter(), xi, theta, load, compensate=False)
    us, base = marked.trajectories.us, plain.trajectories.us
    assert torch.equal(us[..., 2:], base[..., 2:])  # the load carries no watermark
    assert not torch.equal(us[:, 1:, :2], base[:, 1:, :2])
    # the first input is the controller's init (nothing measured yet): no watermark
    assert torch.equal(us[:, 0], base[:, 0])
    with pytest.raises(ValueError, match="std must be"):
        Watermarked(None, torch.tensor([-1.0]), gen)
    wide = lambda c: Watermarked(c, torch.full((5,), 0.1), gen)  # noqa: E731
    with pytest.raises(ValueError, match="Watermarked: std has 5 entries and the controller 2"):
        lfc_loop(plant, df.KalmanFilter(), xi, theta, load, compensate=False, watermark=wide)


def test_the_watermark_exposes_a_replay_at_a_stated_control_cost(tmp_path):
    doc = watermark_study(registry.get("lfc_step"))
    rows = doc["rows"]
    plain = rows["plain replay, without watermark"]
    seamless = rows["seamless replay, without watermark"]
    # measured (seed 0): plain 0.64 (its splice shows), 0.57 after it; seamless 0.55
    assert plain["auc"] > seamless["auc"] + 0.05
    assert seamless["auc"] <= 0.6 and plain["auc_after_splice"] <= 0.6
    for label in ("plain replay, with watermark", "seamless replay, with watermark"):
        assert rows[label]["auc"] >= 0.9 and rows[label]["auc_after_splice"] >= 0.9  # 0.94–0.97
    assert 0.005 <= plain["fpr_at_far"] <= 0.02  # calibrated at 1 % on other runs: 0.52 %
    assert 0.0 < doc["control_cost_increase"] <= 0.10  # measured +7.4 %
    folder = write_watermark(tmp_path, doc)
    written = json.loads((folder / "metrics.json").read_text())
    jsonschema.validate(written, metrics_schema())
    assert written["rows"]["seamless replay, with watermark"]["std"] == 0.08
    assert "control cost" in (folder / "report.md").read_text()


@pytest.mark.parametrize("kw, match", [
    (dict(onset=400, delay=100), r"onset must be a step of the scenario's 1 … 300"),
    (dict(onset=0), r"onset must be a step"),
    (dict(onset=200, delay=100, window=200), r"window must be an integer in 1 … onset − 1 = 199"),
])  # fmt: skip
def test_a_replay_or_window_outside_the_run_is_refused(kw, match):
    """A trial: a replay from step 400 of a 300-step run had returned an AUC of None and a
    TPR of NaN (which metrics.json cannot hold), without a word."""
    scenario = registry.get("lfc_step").with_steps(300)
    with pytest.raises(ValueError, match=match):
        watermark_study(scenario, runs=2, **kw)
