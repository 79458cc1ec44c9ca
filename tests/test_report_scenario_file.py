"""A report of a scenario read from a YAML file records the file: its absolute path and its
digest as the report was written (a trial: the report named the scenario alone, so an
edited file's numbers could not be told from the old one's)."""

from __future__ import annotations

import json

from difffilter.models.yaml_scenario import scenario_file_digest

YAML = """\
name: file_recorded
steps: 30
runs: 2
plant: {F: [[0.95, 0.04], [-0.02, 0.8]], H: [[1.0, 0.0]], Q: 1.0e-4, R: 1.0e-3}
attack: {kind: bias, value: 0.5, onset: 15}
estimators: [kf_attack_free, kf]
"""


def test_a_yaml_scenarios_report_records_its_file_and_digest(tmp_path, monkeypatch,
                                                             isolated_registry):  # fmt: skip
    import jsonschema

    from difffilter.eval.report import metrics_schema, write_report
    from difffilter.eval.suite import run_suite

    (tmp_path / "plant.yaml").write_text(YAML)
    monkeypatch.chdir(tmp_path)
    scenario = isolated_registry.get("plant.yaml")  # (a relative path, as typed)
    read = scenario_file_digest(tmp_path / "plant.yaml")
    assert isolated_registry.source_file("file_recorded") == (tmp_path / "plant.yaml", read)
    doc = write_report(tmp_path / "out", run_suite(scenario, runs=2, progress=False))
    written = json.loads((tmp_path / "out" / "metrics.json").read_text())
    recorded = {"path": str(tmp_path / "plant.yaml"),
                "sha256": scenario_file_digest(tmp_path / "plant.yaml")}  # fmt: skip
    assert doc["scenario_file"] == written["scenario_file"] == recorded
    assert len(recorded["sha256"]) == 64
    jsonschema.validate(written, metrics_schema())
    assert "sha256_now" not in doc["scenario_file"]
    # a built-in scenario's report has none
    assert isolated_registry.source_file("four_tank_bias") is None


def test_a_file_edited_during_the_study_is_recorded_as_read_with_its_digest_now(
    tmp_path, monkeypatch, isolated_registry
):
    """A review: the digest was taken as the report was written, so an edit during the study
    put the edited file's digest on the numbers of the file before it."""
    import pytest

    from difffilter.eval.report import write_report
    from difffilter.eval.suite import run_suite

    path = tmp_path / "plant.yaml"
    path.write_text(YAML)
    read = scenario_file_digest(path)
    result = run_suite(isolated_registry.get(str(path)), runs=2, progress=False)
    path.write_text(YAML.replace("Q: 1.0e-4", "Q: 1.0e-1"))
    with pytest.warns(UserWarning, match="changed during the study of file_recorded"):
        doc = write_report(tmp_path / "out", result)
    assert doc["scenario_file"] == {"path": str(path), "sha256": read,
                                    "sha256_now": scenario_file_digest(path)}  # fmt: skip
    assert read != scenario_file_digest(path)
