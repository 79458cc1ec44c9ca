"""eval/metrics.schema.json bounds the metrics by their units (a trial of the reports'
JSON: a TPR of 5, an FPR of −0.3, an AUC of 1.7, a false-alarm count of −4 or an RMSE of
−1 had validated): fractions in [0, 1]; counts, errors, delays and times ≥ 0."""

from __future__ import annotations

import copy

import jsonschema
import pytest
from conftest import registry_copy

from difffilter.eval.report import metrics_schema

YAML = """\
name: schema_bounds
steps: 30
runs: 2
plant: {F: [[0.95, 0.04], [-0.02, 0.8]], H: [[1.0, 0.0]], Q: 1.0e-4, R: 1.0e-3}
attack: {kind: bias, value: 0.5, onset: 15}
estimators: [kf_attack_free, kf, chi_square_kf]
"""


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    from difffilter.eval.report import write_report
    from difffilter.eval.suite import run_suite

    folder = tmp_path_factory.mktemp("schema_bounds")
    (folder / "plant.yaml").write_text(YAML)
    with registry_copy() as registry:
        scenario = registry.get(str(folder / "plant.yaml"))
        yield write_report(folder / "out", run_suite(scenario, runs=2, progress=False))


@pytest.mark.parametrize(
    ("metric", "value"),
    [("tpr", 5.0), ("fpr", -0.3), ("auc", 1.7), ("tpr_at_far", 1.01), ("false_alarms", -4),
     ("state_rmse", -1.0), ("attack_rmse", -0.1), ("detection_delay_steps", -2.0)],
)  # fmt: skip
def test_a_metric_outside_its_units_range_is_refused(written, metric, value):
    schema = metrics_schema()
    jsonschema.validate(written, schema)  # the real report: valid
    broken = copy.deepcopy(written)
    broken["estimators"]["chi_square_kf"][metric] = value
    with pytest.raises(jsonschema.ValidationError, match="(less|greater) than the m"):
        jsonschema.validate(broken, schema)
