"""What a non-editable install carries: the scenarios find the shipped networks and the LFC
tuning table beside ``models/`` (``difffilter/checkpoints`` once installed). A user trial's
``pip install .`` had none, and every learned estimator was skipped with "no shipped
checkpoint"."""

from __future__ import annotations

import fnmatch
from pathlib import Path

import pytest

from difffilter.eval.families import lfc
from difffilter.models import registry

ROOT = Path(__file__).resolve().parents[1]


def test_the_shipped_files_are_package_data_where_the_scenarios_look():
    tomllib = pytest.importorskip("tomllib")  # (Python 3.11)
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert tool["package-dir"]["difffilter.models"] == "models"
    assert tool["package-dir"]["difffilter.checkpoints"] == "checkpoints"
    assert "difffilter.checkpoints" in tool["packages"]
    patterns = tool["package-data"]["difffilter.checkpoints"]
    shipped = [p for p in (ROOT / "checkpoints").iterdir() if p.name != ".gitkeep"]
    assert shipped and all(any(fnmatch.fnmatch(p.name, pat) for pat in patterns) for p in shipped)
    # the lookups: beside the models/ package (difffilter/ once installed)
    for name in ("four_tank_bias", "lfc_step", "robot_actuator_attack", "tracking_rrp_deception"):
        path = registry.get(name).shipped_checkpoint()
        assert path is not None and path.parent == ROOT / "checkpoints", name
    assert lfc.TUNING == ROOT / "checkpoints" / "lfc_tuning.json" and lfc.TUNING.is_file()
