"""Findings of a trial of float32 studies: the side studies of a family's report run in the
study's dtype."""

from __future__ import annotations

import torch

from difffilter.eval.report import write_report
from difffilter.eval.suite import run_suite
from difffilter.models import registry


def _report_dtype(tmp_path, name: str, estimators: list[str], steps: int | None = None) -> str:
    scenario = registry.get(name)
    scenario = scenario.with_steps(steps) if steps else scenario
    result = run_suite(scenario, runs=2, seed=0, dtype=torch.float32, progress=False,
                       estimators=estimators)  # fmt: skip
    return write_report(tmp_path, result)["dtype"]


def test_a_float32_robot_study_is_reported(tmp_path):
    """The robot family's attack-free runs were simulated in float64 beside the float32
    model: ``write_report`` failed ("KnownInputs.init returned an input of dtype float64")."""
    assert _report_dtype(tmp_path, "robot_actuator_attack",
                         ["mdpf_fused_ci", "mdpf_fused_ci_compensated"], 50) == "float32"  # fmt: skip


def test_a_float32_tracking_study_is_reported(tmp_path):
    """The tracking family's η̄ sweep simulated float64 measurements for the float32 model:
    ``write_report`` failed ("ys must have the model's dtype")."""
    assert _report_dtype(tmp_path, "tracking_rrp_deception", ["rrp_pf_da"], 20) == "float32"


def test_a_float32_four_tank_studys_high_noise_runs_are_float32(monkeypatch):
    """The four-tank report's high-noise section was computed in float64 whatever the
    study's dtype, under a report that says float32."""
    from difffilter.eval.families import four_tank as family

    scenario = registry.get("four_tank_bias").with_steps(30)
    result = run_suite(scenario, runs=2, seed=0, dtype=torch.float32, progress=False,
                       estimators=["chi_square_ekf"])  # fmt: skip
    seen, score = [], family.score

    def spy(out, traj, **kw):
        seen.append((out.means.dtype, traj.y_recv.dtype))
        return score(out, traj, **kw)

    monkeypatch.setattr(family, "score", spy)
    family._high_noise(result)
    assert seen and all(dtypes == (torch.float32, torch.float32) for dtypes in seen)


def test_a_scenario_simulates_in_its_models_dtype_unless_told():
    scenario = registry.get("four_tank_bias").with_steps(5)
    gens = {k: torch.Generator().manual_seed(0) for k in ("plant", "attack")}
    model32 = scenario.system(torch.float32)
    assert scenario.simulate(2, gens, model=model32).y_recv.dtype == torch.float32
    assert scenario.simulate(2, gens).y_recv.dtype == torch.float64
