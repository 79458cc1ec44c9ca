"""LFC evaluation: report schema, plots, TensorBoard events, per-channel validation."""

from __future__ import annotations

import json

import jsonschema
import pytest
import torch

from difffilter.eval.lfc import run_lfc
from difffilter.eval.report import REQUIRED_KEYS, metrics_schema
from difffilter.models.neural_estimator import NeuralFDIEstimator, save_estimator_checkpoint


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    """A short evaluation (2 runs, 150 steps) with an untrained checkpoint: plumbing only."""
    out = tmp_path_factory.mktemp("lfc_eval")
    ckpt = out / "net.ckpt"
    net = NeuralFDIEstimator(hidden=4, init="symmetric", init_scale=0.05, seed=1)
    save_estimator_checkpoint(ckpt, net, {"residual_lag": 0, "dt": 0.01})
    result = run_lfc(
        ["lfc_simultaneous"],
        ckpt=ckpt,
        runs=2,
        out=out,
        seed=5,
        progress=False,
        per_channel_runs=1,
        max_steps=150,
    )
    return out, result


def test_metrics_json_follows_the_schema(smoke):
    out, result = smoke
    doc = json.loads((out / "lfc_simultaneous" / "metrics.json").read_text())
    jsonschema.validate(doc, metrics_schema())
    assert doc["scenario"] == "lfc_simultaneous" and doc["runs"] == 2 and doc["steps"] == 150
    assert doc["paper"]["proposed_ad"] == pytest.approx(0.133867)
    est = doc["estimators"]
    expected = {
        "uncompensated",
        "kf_nn_ekf",
        "traditional_ad",
        "kf_nn_grad",
        "kf_nn_grad_ekf",
        "chi_square_kf",
        "cusum_kf",
    }
    assert expected <= set(est)
    for name, entry in est.items():
        assert set(REQUIRED_KEYS) <= set(entry), name
        assert entry["state5_rmse"] > 0, name
    for name in ("kf_nn_ekf", "traditional_ad", "kf_nn_grad", "kf_nn_grad_ekf"):
        e = est[name]
        per_channel = e["attack_rmse_eq43_per_channel"]
        assert e["attack_rmse_eq43"] > 0 and set(per_channel) == {"dPtu_1", "dPtu_2"}
        # Scenario III's paper metric is the sum over the two attacked channels (eq. 43, Table I).
        assert e["attack_rmse_eq43"] == pytest.approx(sum(per_channel.values()), rel=0.05)
        # the shared, pooled definition: attacked steps × all ten channels
        assert 0 < e["attack_rmse"] < e["attack_rmse_eq43"]
        assert 0 <= e["tpr"] <= 1 and 0 <= e["fpr"] <= 1
    assert est["uncompensated"]["attack_rmse"] is None
    assert 0 < est["chi_square_kf"]["tpr"] <= 1 and est["chi_square_kf"]["auc"] > 0.5
    assert result["lfc_simultaneous"]["estimators"]["kf_nn_grad"][
        "attack_rmse_eq43"
    ] == pytest.approx(est["kf_nn_grad"]["attack_rmse_eq43"])


def test_report_plots_and_tensorboard(smoke):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out, _ = smoke
    folder = out / "lfc_simultaneous"
    report = (folder / "report.md").read_text()
    assert "Table I" in report and "Table II" in report and "0.1339" in report  # paper beside ours
    assert "Per-channel validation" in report
    for png in ("attack_estimates.png", "states.png"):
        assert (folder / png).read_bytes()[:4] == b"\x89PNG"
    acc = EventAccumulator(str(folder / "tb"), size_guidance={"images": 0, "scalars": 0})
    acc.Reload()
    assert "kf_nn_grad/attack_rmse" in acc.Tags()["scalars"]
    assert "kf_nn_ekf/state5_rmse" in acc.Tags()["scalars"]
    assert {"attack_estimates", "states"} <= set(acc.Tags()["images"])
    assert (out / "lfc_summary.md").is_file()


def test_per_channel_validation_files(smoke):
    out, _ = smoke
    doc = json.loads((out / "lfc_per_channel" / "metrics.json").read_text())
    table = doc["attack_rmse"]
    assert {
        "kf_nn_ekf",
        "traditional_ad",
        "kf_nn_gd",
        "luenberger_nn_ekf",
        "kf_nn_grad",
        "zero_estimate",
    } <= set(table)
    assert all(len(v) == 10 for v in table.values())
    assert (out / "lfc_per_channel" / "per_channel.png").is_file()
    assert "Lowest RMSE per channel" in (out / "lfc_per_channel" / "report.md").read_text()
    assert doc["wall_time_s"] > 0  # its cost, recorded beside its numbers


def test_per_channel_validation_is_opt_in_on_the_cli():
    from difffilter.eval.cli import build_parser

    assert build_parser().parse_args(["lfc_step"]).per_channel is False
    assert build_parser().parse_args(["lfc", "--per-channel"]).per_channel is True


def test_run_lfc_rejects_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="runs"):
        run_lfc(["lfc_step"], ckpt=None, runs=0, out=tmp_path)
    with pytest.raises(ValueError, match="unknown scenario"):
        run_lfc(["lfc_nope"], ckpt=None, runs=1, out=tmp_path)
    with pytest.raises(FileNotFoundError):
        run_lfc(["lfc_step"], ckpt=tmp_path / "missing.ckpt", runs=1, out=tmp_path)


def test_uncompensated_and_skipped_without_checkpoint(tmp_path):
    res = run_lfc(
        ["lfc_step"],
        ckpt=None,
        runs=1,
        out=tmp_path,
        progress=False,
        per_channel_runs=0,
        max_steps=60,
    )["lfc_step"]
    assert "kf_nn_grad" not in res["estimators"] and "kf_nn_grad" in res["skipped"]
    # Without an attack estimate the secure and the traditional loop coincide; the attack
    # (0.4 from t = 3 s) is outside 60 steps, so the uncompensated loop is attack-free here.
    unc = res["estimators"]["uncompensated"]
    assert unc["state5_rmse"] == pytest.approx(unc["state5_rmse_attack_free"])
    assert torch.isfinite(torch.tensor(res["estimators"]["kf_nn_ekf"]["attack_rmse_eq43"]))
