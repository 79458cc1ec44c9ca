"""docs/python-api.md: the snippet runs as written and gives difffilter-eval's metrics on
the same runs; the loader names what it needs."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

import difffilter
from difffilter.eval.suite import run_suite
from difffilter.models import registry

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "python-api.md"
COMPARED = ("state_rmse", "attack_rmse", "auc", "tpr", "fpr", "tpr_at_1pct_fpr",
            "detection_delay_steps")  # fmt: skip


def test_the_documented_snippet_gives_the_metrics_of_difffilter_eval(monkeypatch):
    monkeypatch.chdir(ROOT)  # the snippet's paths are the repository's
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)
    assert len(blocks) == 2
    namespace: dict = {}
    exec(compile(blocks[0], str(DOC), "exec"), namespace)  # noqa: S102
    out, metrics = namespace["out"], namespace["metrics"]
    assert not out.means.requires_grad and out.detection.alarms.dtype == torch.bool
    assert "ekf filter, actuator channel" in repr(namespace["estimator"])
    sc = registry.get("robot_actuator_attack")
    suite = run_suite(sc, runs=8, seed=0, estimators=["gaussian_nn_ekf"], progress=False)
    expected = suite.metrics["gaussian_nn_ekf"]
    for key in COMPARED:
        if expected.get(key) is None:
            assert metrics.get(key) is None, key
        else:
            assert metrics[key] == pytest.approx(expected[key], rel=1e-12, abs=1e-12), key
    torch.testing.assert_close(out.means, suite.outputs["gaussian_nn_ekf"].means, rtol=0, atol=0)


def test_a_trained_estimator_steps_like_any_estimator_and_can_give_gradients():
    sc = registry.get("robot_actuator_attack")
    est = difffilter.load_estimator(sc.shipped_checkpoint())
    model = sc.system()
    gens = {k: torch.Generator().manual_seed(i) for i, k in enumerate(("plant", "attack"))}
    tr = sc.simulate(2, gens)
    whole = est.run(model, tr.y_recv, tr.us, mask=tr.mask)
    carry, means = est.init(model, (2,)), []
    for t in range(5):
        mask = None if tr.mask is None else tr.mask[:, t]
        carry, step = est.step(carry, tr.y_recv[:, t], tr.us[:, t], mask)
        means.append(step.mean)
    torch.testing.assert_close(torch.stack(means, 1), whole.means[:, :5])
    ys = tr.y_recv.clone().requires_grad_(True)
    est.run(model, ys, tr.us, mask=tr.mask, grad=True).means.sum().backward()
    assert ys.grad is not None and bool(ys.grad.abs().sum() > 0)


def test_the_loader_names_what_it_needs():
    lfc = registry.get("lfc_step").shipped_checkpoint()
    with pytest.raises(ValueError, match="LFC closed loop"):
        difffilter.load_estimator(lfc)
    tracking = registry.get("tracking_rrp_deception").shipped_checkpoint()
    with pytest.raises(ValueError, match="deception"):
        difffilter.load_estimator(tracking)
    with pytest.raises(FileNotFoundError):
        difffilter.load_estimator("no/such.ckpt")


def test_the_documented_judgement_and_its_intervals(monkeypatch):
    monkeypatch.chdir(ROOT)
    block = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)[1]
    namespace: dict = {}
    exec(compile(block, str(DOC), "exec"), namespace)  # noqa: S102
    study, checks, sure = namespace["study"], namespace["checks"], namespace["sure"]
    m = study.metrics
    analytic = [n for n, r in namespace["role"].items() if r == "analytic"]
    best = min(m[n]["state_rmse"] for n in analytic)
    state = next(c for c in checks if c.metric == "state_rmse")
    assert state.holds == (m["gaussian_nn_ekf"]["state_rmse"] <= 1.05 * best)
    mine = sure["estimators"]["gaussian_nn_ekf"]["state_rmse"]
    assert mine["estimate"] == pytest.approx(m["gaussian_nn_ekf"]["state_rmse"] / best, rel=1e-9)
    assert mine["low"] <= mine["high"] and 0.0 <= mine["holds_share"] <= 1.0
