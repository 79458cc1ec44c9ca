"""Every family's metrics.json follows eval/metrics.schema.json (four-tank, LFC and a user's
plant are validated in their own tests; here the tracking, robot and plain-filter families)."""

from __future__ import annotations

import json
from dataclasses import replace

import jsonschema
import pytest

from difffilter.eval.report import metrics_schema, write_report
from difffilter.eval.suite import run_suite
from difffilter.models import registry

SMALL = {
    "tracking_rrp_deception": {"num_particles": 50, "steps": 30},
    "robot_actuator_attack": {"num_particles": 20, "steps": 60},  # its report reads k = 44
    "four_tank_filters": {"num_particles": 50, "steps": 20},
}


@pytest.mark.parametrize("name", sorted(SMALL))
def test_metrics_json_follows_the_schema(name, tmp_path):
    sc = replace(registry.get(name), **SMALL[name])
    doc = write_report(tmp_path, run_suite(sc, runs=3, progress=False))
    written = json.loads((tmp_path / "metrics.json").read_text())
    jsonschema.validate(written, metrics_schema())
    assert written["estimators"].keys() == doc["estimators"].keys() and doc["estimators"]
    assert (tmp_path / "report.md").stat().st_size > 500
