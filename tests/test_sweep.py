"""``difffilter-train sweep``: every seed trained, judged as the evaluation judges it, the
spread reported and the median seed named; a finished seed is not trained again."""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import pytest

from difffilter.eval.calibration import calibrate
from difffilter.eval.suite import run_suite
from difffilter.models import estimators, registry
from difffilter.train.sweep import main, train_seed_of
from difffilter.train.sweep import sweep as sweep_fn

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "--data.init_args.batch_size=2", "--data.init_args.batches_per_epoch=1",
    "--data.init_args.val_runs=4", "--model.init_args.num_particles=20",
    "--model.init_args.hidden=4", "--trainer.max_epochs=1",
]  # fmt: skip


def test_a_sweep_reports_every_seed_the_spread_and_the_median_seed(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    config = str(ROOT / "train" / "configs" / "four_tank.yaml")
    args = ["--config", config, "--seeds", "0", "3", "1", "--out", "sw", "--runs", "4",
            "--scenarios", "four_tank_bias", "--no-progress", "--", *TINY]  # fmt: skip
    # first the trainings alone, the median named on validation and the test held back
    split = args.index("--")
    assert main([*args[:split], "--validation-only", *args[split:]]) == 0
    held = json.loads((tmp_path / "sw" / "sweep.json").read_text())
    assert held["test"] == "held back" and held["selection"]["median_seed_by_test"] is None
    assert all(set(v) == {"checkpoint", "train_time_s"} for v in held["per_seed"].values())
    assert "acceptance" not in held and not (tmp_path / "sw" / "baselines").exists()
    assert "The test evaluation is held back" in (tmp_path / "sw" / "sweep.md").read_text()
    trained = {s: Path(v["checkpoint"]).stat().st_mtime_ns for s, v in held["per_seed"].items()}
    # then the test: the same seeds evaluated, none trained again, the same median
    assert main(args) == 0
    doc = json.loads((tmp_path / "sw" / "sweep.json").read_text())
    assert doc["seeds"] == [0, 3, 1] and doc["rank_by"] == "tpr_at_far"
    assert doc["select_on"] == "validation"
    seeds = doc["per_seed"]
    cards = {s: json.loads(Path(v["checkpoint"]).with_suffix(".json").read_text())
             for s, v in seeds.items()}  # fmt: skip
    for s, card in cards.items():  # each seed trained with its own seeds
        assert card["model_config"]["model_seed"] == int(s)
        assert card["data_config"]["train_seed"] == train_seed_of(int(s))
    # seed 3's numbers are what the evaluation's calibrated suite gives its checkpoint
    sc, path = registry.get("four_tank_bias"), seeds["3"]["checkpoint"]
    cal = calibrate(sc, runs=4, estimators=["pf_nn_grad"], checkpoint={"pf_nn_grad": path},
                    progress=False)  # fmt: skip
    res = run_suite(sc, runs=4, estimators=["pf_nn_grad"], checkpoint={"pf_nn_grad": path},
                    calibration=cal, progress=False)  # fmt: skip
    mine = seeds["3"]["scenarios"]["four_tank_bias"]
    for metric, value in mine.items():
        expected = (cal.measured["pf_nn_grad"] if metric == "far_measured_on_calibration"
                    else res.metrics["pf_nn_grad"][metric])  # fmt: skip
        assert value == pytest.approx(expected)
    # the spread and the median seed from the per-seed numbers
    values = {s: v["scenarios"]["four_tank_bias"]["tpr_at_far"] for s, v in seeds.items()}
    stats = doc["summary"]["four_tank_bias"]["tpr_at_far"]
    assert stats["mean"] == pytest.approx(statistics.fmean(values.values()))
    assert stats["spread"] == pytest.approx(max(values.values()) - min(values.values()))
    assert values[str(doc["selection"]["median_seed_by_test"])] == sorted(values.values())[1]
    # the seed that ships is the median of the validation scores the trainings chose their
    # weights by (four_tank.yaml: val/auc, higher is better), never of the reported draws
    val = {s: card["best_val_score"] for s, card in cards.items()}
    assert len(set(val.values())) == 3  # distinct: the check below picks one seed
    assert doc["selection"]["monitor"] == {"metric": "val/auc", "mode": "max"}
    assert doc["selection"]["scores"] == pytest.approx(val)
    assert val[str(doc["median_seed"])] == sorted(val.values())[1]
    assert doc["median_checkpoint"] == seeds[str(doc["median_seed"])]["checkpoint"]
    assert doc["median_seed"] == held["median_seed"]
    assert held["selection"]["scores"] == doc["selection"]["scores"]
    assert {s: Path(v["checkpoint"]).stat().st_mtime_ns for s, v in seeds.items()} == trained
    text = (tmp_path / "sw" / "sweep.md").read_text()
    assert "spread (max − min)" in text and "Median seed on validation" in text
    # the acceptance: the best of the scenario's analytic estimators on the same runs,
    # calibrated the same way, and seed 3 held against it
    analytic = [n for n in sc.estimators if estimators.get(n).role == "analytic"]
    assert "modified_pf_unknown_pl" not in analytic and "cusum_ekf" in analytic
    cal = calibrate(sc, runs=4, estimators=analytic, progress=False)
    base = run_suite(sc, runs=4, estimators=analytic, calibration=cal, progress=False).metrics
    accept = doc["acceptance"]["four_tank_bias"]
    best = accept["best_analytic"]
    assert best["state_rmse"]["value"] == pytest.approx(min(m["state_rmse"] for m in base.values()))
    tprs = {n: m["tpr_at_far"] for n, m in base.items() if m["tpr_at_far"] is not None}
    assert best["tpr_at_far"]["value"] == pytest.approx(max(tprs.values()))
    assert best["tpr_at_far"]["estimator"] == max(tprs, key=tprs.get)
    checks = {c["metric"]: c["holds"] for c in accept["checks"]["3"]}
    assert checks["state_rmse"] == (mine["state_rmse"] <= 1.05 * best["state_rmse"]["value"])
    assert checks["fpr_at_far"] == (0.005 <= mine["fpr_at_far"] <= 0.02)
    assert accept["holds"]["3"] == all(checks.values())
    # how sure: the same checks over resamples of the runs, the seed paired with the baselines
    sure = accept["intervals"]["3"]
    ratio = mine["state_rmse"] / best["state_rmse"]["value"]
    assert sure["state_rmse"]["estimate"] == pytest.approx(ratio, rel=1e-9)
    assert sure["fpr_at_far"]["estimate"] == pytest.approx(mine["fpr_at_far"])
    assert all(0.0 <= c["holds_share"] <= 1.0 for c in sure.values() if c["low"] is not None)
    assert "## Against the best analytic estimator" in (tmp_path / "sw" / "sweep.md").read_text()
    # a second call trains nothing again
    stamps = {s: Path(v["checkpoint"]).stat().st_mtime_ns for s, v in seeds.items()}
    baseline = tmp_path / "sw" / "baselines" / "four_tank_bias.json"
    stamps["baseline"] = baseline.stat().st_mtime_ns
    stamps["totals"] = baseline.with_suffix(".totals.pt").stat().st_mtime_ns
    assert main([*args[: args.index("--")], "--select-on", "test", *args[args.index("--") :]]) == 0
    again = json.loads((tmp_path / "sw" / "sweep.json").read_text())
    assert again["select_on"] == "test" and again["selection"]["monitor"] is None
    assert values[str(again["median_seed"])] == sorted(values.values())[1]
    assert {s: Path(v["checkpoint"]).stat().st_mtime_ns for s, v in again["per_seed"].items()
            } | {"baseline": baseline.stat().st_mtime_ns,
                 "totals": baseline.with_suffix(".totals.pt").stat().st_mtime_ns} == stamps  # fmt: skip
    assert again["acceptance"] == doc["acceptance"]
    assert again["options"] == TINY  # what the seeds were trained with, recorded
    # other settings into the same --out: refused, before anything is trained (a user trial:
    # the first sweep's networks were reported as the hidden=8 ones)
    other = [*args, "--model.init_args.hidden=8"]
    with pytest.raises(ValueError, match=r"--out sw holds the sweep of .*four_tank.yaml with "
                       r"the options .*hidden=4.*; this one is .*hidden=8.*give another --out"):  # fmt: skip
        sweep_fn(ROOT / "train" / "configs" / "four_tank.yaml", seeds=(0,), out="sw",
                 extra=other[other.index("--") + 1:])  # fmt: skip
    (tmp_path / "sw" / "sweep.json").unlink()  # a sweep stopped before its summary: the seeds'
    with pytest.raises(ValueError, match=r"seed 0: .*seed_0 was trained with the options .*"
                       r"hidden=4.* \(now .*hidden=8.*\); give another --out"):  # fmt: skip
        sweep_fn(ROOT / "train" / "configs" / "four_tank.yaml", seeds=(0,), out="sw",
                 extra=other[other.index("--") + 1:])  # fmt: skip
    assert {s: Path(v["checkpoint"]).stat().st_mtime_ns for s, v in seeds.items()} == {
        k: v for k, v in stamps.items() if k in seeds}  # fmt: skip


def test_a_sweep_refuses_bad_options(tmp_path, capsys):
    config = str(ROOT / "train" / "configs" / "four_tank.yaml")
    assert main(["--config", config, "--seeds", "1", "1", "--out", str(tmp_path)]) == 2
    assert "--seeds must be distinct" in capsys.readouterr().err
    assert main(["--config", config, "--rank-by", "speed", "--out", str(tmp_path)]) == 2
    assert "--rank-by must be one of" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--config", config, "--select-on", "best", "--out", str(tmp_path)])
    assert "--select-on: invalid choice: 'best'" in capsys.readouterr().err
    # a config whose training chooses its weights by no validation score: said before training
    bare = tmp_path / "bare.yaml"
    bare.write_text("trainer:\n  max_epochs: 1\n")
    assert main(["--config", str(bare), "--out", str(tmp_path / "sw")]) == 2
    assert "has no ModelCheckpoint monitor; add one, or --select-on test" in capsys.readouterr().err
    args = ["--config", config, "--out", str(tmp_path / "sw"), "--validation-only"]
    assert main([*args, "--select-on", "test"]) == 2
    assert "--validation-only chooses the median seed on validation" in capsys.readouterr().err
    assert not (tmp_path / "sw").exists()
    assert main(["--config", str(tmp_path / "no.yaml"), "--out", str(tmp_path)]) == 2
    assert "no.yaml does not exist" in capsys.readouterr().err
    # what the evaluation after each training would refuse, said before the first one
    file = tmp_path / "sw.log"
    file.write_text("")
    assert main(["--config", config, "--out", str(file)]) == 2
    assert "sw.log is a file; a sweep writes a folder" in capsys.readouterr().err
    out = ["--config", config, "--out", str(tmp_path / "sw2")]
    assert main([*out, "--runs", "0"]) == 2
    assert "--runs must be an integer >= 1" in capsys.readouterr().err
    assert main([*out, "--scenarios", "nope"]) == 2
    assert "unknown scenario 'nope'" in capsys.readouterr().err
    assert main([*out, "--scenarios", "lfc_step"]) == 2
    assert "--scenarios: lfc_step is a lfc scenario" in capsys.readouterr().err
    assert not (tmp_path / "sw2").exists()
