"""A command-line fuzzer's findings (a user trial of ~170 invocations): each input that was
accepted silently, dropped, or failed with a traceback or after minutes of work is refused
up front with one line naming the option."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from difffilter.eval import cli as eval_cli
from difffilter.train.cli import main as train_main

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "checkpoints" / "four_tank_nn_grad.ckpt"


def _eval_error(argv, capsys) -> str:
    assert eval_cli.main(argv) == 2
    return capsys.readouterr().err


def test_difffilter_eval_refuses_what_it_dropped_or_ran_without_a_word(
    tmp_path, monkeypatch, capsys
):
    out = ["--out", str(tmp_path / "o"), "--runs", "2", "--far", "off", "--no-progress"]
    # one estimator given two checkpoints: the first was dropped, metrics.json named the second
    err = _eval_error(["four_tank_bias", *out, "--ckpt", f"pf_nn_grad={SHIPPED}",
                       "--ckpt", f"pf_nn_grad={tmp_path / 'b.ckpt'}"], capsys)  # fmt: skip
    assert "pf_nn_grad is given twice" in err
    with pytest.raises(SystemExit):  # an empty --out wrote the reports into the current folder
        eval_cli.main(["four_tank_bias", "--out", ""])
    assert "--out: expected a folder" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # "" ran the scenario's own estimators
        eval_cli.main(["four_tank_bias", "--add-estimators", ""])
    assert "--add-estimators: expected estimator names" in capsys.readouterr().err
    monkeypatch.setattr(eval_cli.os, "cpu_count", lambda: 2)  # 100 processes sat silent
    assert "--devices 100: this machine has 2 CPU(s)" in _eval_error(
        ["four_tank_bias", *out, "--devices", "100"], capsys
    )
    # a typo gets a suggestion and the names beside the scenarios
    err = _eval_error(["four_tank_bia", *out], capsys)
    assert "did you mean four_tank_bias" in err and "also all, robustness" in err


def test_estimators_replaces_the_scenarios_own_and_the_family_tables_that_need_others_leave(
    tmp_path, capsys
):
    """``--estimators A,B`` runs those instead of the scenario's own (a user trial asked for
    it: only --add-estimators existed); the four-tank tables, which read ``modified_pf`` and
    others, are left out with the reason; a typo is named with the nearest name."""
    out = tmp_path / "o"
    argv = ["four_tank_bias", "--runs", "2", "--no-progress", "--out", str(out)]
    assert eval_cli.main([*argv, "--estimators", "chi_square_ekf"]) == 0
    doc = json.loads((out / "four_tank_bias" / "metrics.json").read_text())
    assert sorted(doc["estimators"]) == ["chi_square_ekf"]
    assert "`modified_pf` (not in this run)" in doc["family_report_skipped"]
    err = _eval_error([*argv, "--estimators", "chi_sqare_ekf"], capsys)
    assert "--estimators: unknown estimator 'chi_sqare_ekf' (did you mean 'chi_square_ekf'?)" in err


def test_family_options_are_checked_for_every_family_before_any_suite(
    tmp_path, monkeypatch, capsys
):
    """``all -o nosuch=true`` failed after the four-tank suites had run and written their
    reports; a sizing option without its study was ignored; a repeated key, the last won."""

    def no_suite(*args, **kwargs):
        raise AssertionError("a suite ran before the options were checked")

    monkeypatch.setattr("difffilter.eval.suite.run_suite", no_suite)
    out = ["--out", str(tmp_path / "o"), "--runs", "2", "--far", "off"]
    assert "unknown lfc option(s) ['nosuch']" in _eval_error(
        ["all", *out, "-o", "nosuch=1"], capsys
    )
    err = _eval_error(["lfc_step", *out, "-o", "per_channel_runs=5"], capsys)
    assert "per_channel_runs: sizes the per_channel study" in err
    err = _eval_error(["lfc_step", *out, "-o", "watermark=true", "-o", "watermark=false"], capsys)
    assert "--option watermark: given twice" in err
    err = _eval_error(["four_tank_bias", *out, "-o", "x=1"], capsys)
    assert "the families evaluated (four_tank) take no options; lfc does" in err
    assert not any((tmp_path / "o").rglob("*.md"))  # nothing written


def test_one_threat_set_is_refused_for_several_families(tmp_path, capsys):
    """``robustness --threat-set four_tank.yaml`` applied the four-tank set (a 0.005 cm
    ramp) to the LFC, robot and tracking plants without a word."""
    argv = ["robustness", "--threats", "ramp", "--threat-set",
            str(ROOT / "eval" / "threats" / "four_tank.yaml"), "--out", str(tmp_path)]  # fmt: skip
    assert "one file's threats for the scenarios of 5 families" in _eval_error(argv, capsys)


def test_a_threat_sets_runs_must_be_a_positive_integer_named_by_its_file(tmp_path):
    """``runs: 0`` read as "not given" (the scenario's 100 runs ran); -3 failed naming no file."""
    from difffilter.eval.robustness import load_threat_set
    from difffilter.models import registry

    for runs in (0, -3, "abc", True):
        path = tmp_path / f"set_{runs}.yaml"
        path.write_text(f"runs: {json.dumps(runs)}\nthreats:\n  b: {{kind: bias, value: 0.5}}\n")
        with pytest.raises(ValueError, match=rf"{path.name}: runs must be an integer >= 1"):
            load_threat_set(registry.get("four_tank_bias"), "all", path=path)


def _train_error(argv, capsys, tmp_path, monkeypatch) -> str:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    assert train_main(argv) == 2
    return capsys.readouterr().err


def test_difffilter_train_names_a_ckpt_path_that_is_no_checkpoint(tmp_path, monkeypatch, capsys):
    """A file torch cannot load with ``weights_only=True`` gave Lightning's traceback, whose
    advice was an unsafe load; a torch file of other keys a ``KeyError`` traceback; both left
    a run folder. ``validate``/``test``/``predict`` without one judged untrained weights."""
    config = ["--config", str(ROOT / "train" / "configs" / "robot.yaml")]
    (tmp_path / "garbage.ckpt").write_bytes(bytes(range(256)) * 4)
    torch.save({"a": torch.ones(2)}, tmp_path / "dict.ckpt")
    for command in ("fit", "validate"):
        err = _train_error([command, *config, "--ckpt_path", str(tmp_path / "garbage.ckpt")],
                           capsys, tmp_path, monkeypatch)  # fmt: skip
        assert "garbage.ckpt is no checkpoint torch can load with weights_only=True" in err
        assert "Traceback" not in err and "weights_only` set to `False`" not in err
    err = _train_error(["fit", *config, f"--ckpt_path={tmp_path / 'dict.ckpt'}"], capsys,
                       tmp_path, monkeypatch)  # fmt: skip
    assert "dict.ckpt is neither a training run's Lightning checkpoint" in err
    for command in ("validate", "test", "predict"):
        err = _train_error([command, *config], capsys, tmp_path, monkeypatch)
        assert f"--ckpt_path: {command} needs the weights" in err
    assert not (tmp_path / "lightning_logs").exists()


def test_a_sweep_forgets_a_seed_that_trained_nothing_and_keeps_its_out_to_one_sweep(
    tmp_path, monkeypatch, capsys
):
    """A misspelt option failed the fit but left the seed's settings, and the corrected
    command was refused as "trained with the options [...]"; a sweep of another config into
    the same --out replaced the first sweep's summary."""
    from difffilter.train import sweep as sweep_module

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    config = ROOT / "train" / "configs" / "robot.yaml"
    out = tmp_path / "sw"
    with pytest.raises(ValueError, match="seed 0: difffilter-train fit failed"):
        sweep_module._fit(config, 0, out / "runs", ["--nosuch.option=1"], progress=False)
    folder = sweep_module._seed_run(config, 0, out / "runs", [])[0]
    assert not (folder / sweep_module._SETTINGS).exists()
    sweep_module._check_same_settings(folder, sweep_module._settings(config, []), 0)  # accepted
    out.mkdir(exist_ok=True)
    (out / "sweep.json").write_text(json.dumps({"config": str(config), "options": []}))
    sweep_module._check_same_sweep(out, config, [])  # more seeds of the same sweep
    other = ROOT / "train" / "configs" / "four_tank_ekf.yaml"
    with pytest.raises(ValueError, match="holds the sweep of .*robot.yaml"):
        sweep_module._check_same_sweep(out, other, [])
    with pytest.raises(ValueError, match="give another --out"):
        sweep_module._check_same_sweep(out, config, ["--trainer.max_epochs=2"])


def test_fit_takes_no_progress_as_sweep_and_calibrate_do():
    """``fit`` had no ``--no-progress`` (``sweep`` and ``calibrate`` do): the trainer's
    option it stands for is set."""
    from difffilter.train.cli import _scenario_option

    assert _scenario_option(["fit", "--no-progress", "--scenario", "lfc_step"]) == [
        "fit", "--trainer.enable_progress_bar=false", "--model.init_args.scenario=lfc_step",
        "--data.init_args.scenario=lfc_step",
    ]  # fmt: skip


def test_an_out_folder_with_a_folder_where_a_report_goes_is_refused_first(tmp_path, capsys):
    """A folder named leaderboard.md, or a file named like a scenario, failed the
    evaluation with a traceback after its suites had run."""
    out = tmp_path / "o"
    (out / "leaderboard.md").mkdir(parents=True)
    argv = ["four_tank_bias", "--out", str(out), "--runs", "2", "--far", "off"]
    assert "leaderboard.md is a folder" in _eval_error(argv, capsys)
    (out / "leaderboard.md").rmdir()
    (out / "four_tank_bias").write_text("")
    assert "four_tank_bias is a file" in _eval_error(argv, capsys)
    # inside the scenario's folder too (a docs trial: a traceback after the whole suite)
    (out / "four_tank_bias").unlink()
    (out / "four_tank_bias" / "metrics.json").mkdir(parents=True)
    assert ("four_tank_bias/metrics.json is a folder; scenario four_tank_bias's report "
            "writes a file there") in _eval_error(argv, capsys)  # fmt: skip
    (out / "four_tank_bias" / "metrics.json").rmdir()
    (out / "four_tank_bias" / "tb").write_text("")
    assert ("four_tank_bias/tb is a file; scenario four_tank_bias's report writes a folder "
            "there") in _eval_error(argv, capsys)  # fmt: skip


def test_a_mask_on_another_device_than_the_measurements_is_named():
    """torch said "Tensor on device cpu is not on the expected device meta!", naming no
    argument (an auditor's trial; the meta device stands in for a GPU here)."""
    from conftest import constant_velocity

    import difffilter as df

    model = constant_velocity().to("meta")
    ys = torch.zeros(2, 5, model.dim_y, device="meta", dtype=torch.float64)
    mask = torch.ones(2, 5, model.dim_y, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"mask is on cpu and ys on meta: put mask on ys's device"):
        df.kalman_filter(model, ys, mask=mask)


def test_a_run_in_which_no_estimator_ran_prints_why_and_fails(tmp_path, capsys):
    """A docs trial: ``--estimators`` naming only estimators that do not fit the scenario
    (``chi_square_kf`` needs a linear model) wrote empty reports, printed "No estimator ran"
    without the reasons (they were in the scenario's report.md) and exited 0, so a script
    took it for a result. Now the console lists each reason and the command exits 1."""
    out = tmp_path / "o"
    argv = ["four_tank_bias", "--runs", "2", "--no-progress", "--out", str(out),
            "--estimators", "chi_square_kf"]  # fmt: skip
    assert eval_cli.main(argv) == 1
    printed = capsys.readouterr()
    assert "No estimator ran" in printed.out
    assert "- four_tank_bias: `chi_square_kf` (" in printed.out and "linear" in printed.out
    assert "difffilter-eval: error: no estimator ran" in printed.err
    assert "No artists with labels" not in printed.err


def test_an_uncalibrated_evaluation_says_why_it_has_no_acceptance_summary(tmp_path, capsys):
    """A docs trial: ``--far off`` wrote no acceptance.md and said nothing of it."""
    out = tmp_path / "o"
    argv = ["four_tank_bias", "--runs", "2", "--no-progress", "--out", str(out), "--far", "off",
            "--estimators", "chi_square_ekf"]  # fmt: skip
    assert eval_cli.main(argv) == 0
    printed = capsys.readouterr().out
    assert "note: --far off: nothing calibrated, so no acceptance.md" in printed
    assert "Nothing was calibrated (`--far off`)" in printed and "tpr_at_far [" not in printed
    assert not (out / "acceptance.md").exists()


def test_the_report_records_the_studys_dtype(tmp_path):
    """A docs trial: a ``run_suite(dtype=torch.float32)`` study's metrics.json read as a
    float64 one's; it records ``dtype`` now (schema-checked)."""
    import jsonschema

    from difffilter.eval.report import metrics_schema, write_report
    from difffilter.eval.suite import run_suite
    from difffilter.models import registry

    scenario = registry.get("four_tank_bias")
    for dtype, name in ((torch.float32, "float32"), (torch.float64, "float64")):
        result = run_suite(scenario, runs=2, estimators=["chi_square_ekf"], dtype=dtype,
                           progress=False)  # fmt: skip
        doc = write_report(tmp_path / name, result)
        assert doc["dtype"] == name
        jsonschema.validate(json.loads((tmp_path / name / "metrics.json").read_text()),
                            metrics_schema())  # fmt: skip
