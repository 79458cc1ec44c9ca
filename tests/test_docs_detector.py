"""docs/adding-a-scenario.md's detector of one's own runs as written and is judged as the
page says: its scores are the NIS summed over the last five steps (checked step by step),
its own alarms at its own threshold, and its ``*_at_far`` figures at a threshold calibrated
on attack-free runs of another seed (a detector author's trial)."""

from __future__ import annotations

import re
from pathlib import Path

import torch

PAGE = Path(__file__).resolve().parents[1] / "docs" / "adding-a-scenario.md"


def _detector_block() -> str:
    section = PAGE.read_text().split("### A detector of your own", 1)[1]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)[0]


def test_the_pages_detector_is_calibrated_and_judged_on_other_runs(monkeypatch):
    import difffilter as df
    from difffilter.eval.calibration import calibrate
    from difffilter.eval.suite import run_suite
    from difffilter.models import estimators, registry

    estimators.names()  # the built-in ones loaded, then a copy that this test's leaves with it
    monkeypatch.setattr(estimators, "ESTIMATORS", dict(estimators.ESTIMATORS))
    exec(compile(_detector_block(), str(PAGE), "exec"), {})
    scenario = registry.get("lfc_step")
    names = ["nis_window_kf", "chi_square_kf"]
    calibration = calibrate(scenario, runs=4, far=0.01, estimators=names, progress=False)
    study = run_suite(scenario, runs=3, estimators=names, calibration=calibration,
                      progress=False)  # fmt: skip
    mine = study.metrics["nis_window_kf"]
    assert mine["threshold_at_far"] == calibration.thresholds["nis_window_kf"]
    assert 0 <= mine["tpr_at_far"] <= 1 and mine["tpr"] is not None

    # the scores by hand from the filter's innovations, one step at a time
    traj = study.traj_of("nis_window_kf")
    res = df.kalman_filter(scenario.system(), traj.y_recv, traj.us, mask=traj.mask)
    nu, S = res.innovations.double(), res.innovation_covs.double()
    nis = torch.stack([torch.einsum("bi,bij,bj->b", nu[:, k], torch.linalg.inv(S[:, k]), nu[:, k])
                       for k in range(nu.shape[1])], 1)  # fmt: skip
    window = torch.stack([nis[:, max(0, k - 4) : k + 1].sum(1) for k in range(nis.shape[1])], 1)
    window[:, :4] = float("nan")  # not yet five steps: no score
    detection = study.outputs["nis_window_kf"].detection
    torch.testing.assert_close(detection.scores.double(), window, rtol=1e-7, atol=1e-7,
                               equal_nan=True)  # fmt: skip
    # its own alarms at its own threshold give `tpr` / `fpr`; the calibrated one, `*_at_far`
    flags = traj.flags.bool()
    own = window > 25.0
    assert abs(mine["tpr"] - float(own[flags].double().mean())) < 1e-12
    assert abs(mine["fpr"] - float(own[~flags].double().mean())) < 1e-12
    at_far = window > mine["threshold_at_far"]
    assert abs(mine["tpr_at_far"] - float(at_far[flags].double().mean())) < 1e-12
    assert calibration.seed != 0  # attack-free runs of their own seed (calibration_seed(0))
