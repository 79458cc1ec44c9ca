"""The library's filters as registered estimators (``kf``, ``ekf``, ``ukf``, ``bootstrap_pf``,
``kalman_proposal_pf``) and the ``four_tank_filters`` scenario that `make demo` runs."""

from __future__ import annotations

import torch

import difffilter as df
from difffilter.eval.suite import run_suite
from difffilter.models import registry
from difffilter.models.scenario import CustomScenario

PLAIN = ("kf", "ekf", "ukf", "bootstrap_pf", "kalman_proposal_pf")


def _linear(dtype):
    return df.LinearGaussianModel(
        torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=dtype),
        torch.tensor([[1.0, 0.0]], dtype=dtype),
        0.01 * torch.eye(2, dtype=dtype),
        0.04 * torch.eye(1, dtype=dtype),
        torch.zeros(2, dtype=dtype),
        torch.eye(2, dtype=dtype),
    )


def test_plain_filters_agree_on_a_linear_plant():
    """EKF and UKF equal the KF on a linear model; the PFs converge to it (N = 4000)."""
    sc = CustomScenario(
        name="linear_plain", family="test", description="", model_fn=_linear, steps=25,
        num_particles=4000,
    )  # fmt: skip
    res = run_suite(sc, runs=6, estimators=PLAIN, progress=False)
    kf = res.outputs["kf"].means
    for name in ("ekf", "ukf"):
        torch.testing.assert_close(res.outputs[name].means, kf, rtol=0, atol=1e-10)
    sd = res.outputs["kf"].covs.diagonal(dim1=-2, dim2=-1).sqrt()
    for name in ("bootstrap_pf", "kalman_proposal_pf"):
        err = (res.outputs[name].means - kf).abs() / sd
        assert float(err.max()) < 0.3, name  # Monte Carlo error ~ 1/√N of a posterior sd
    for name in PLAIN:
        assert res.outputs[name].detection is None and res.metrics[name]["auc"] is None


def test_four_tank_filters_scenario_runs_every_filter_without_attack():
    sc = registry.get("four_tank_filters")
    assert sc.headline and sc.attack_model() is None
    res = run_suite(sc, runs=3, progress=False)
    assert list(res.outputs) == list(sc.estimators)
    assert not bool(res.traj.flags.any())
    rmse = {n: m["state_rmse"] for n, m in res.metrics.items()}
    # near the fixed point the linearised KF, the EKF and the UKF agree to a few per cent
    assert abs(rmse["kf_linearised"] / rmse["ekf"] - 1) < 0.05
    assert abs(rmse["ukf"] / rmse["ekf"] - 1) < 0.05
    assert all(0 < v < 0.05 for v in rmse.values()), rmse
