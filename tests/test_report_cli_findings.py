"""A mutation review of eval/report.py and eval/cli.py: mutants of the report and the
command line that the fast tests let through, and two command-line errors found with them."""

from __future__ import annotations

import json
import types

import pytest
import torch

from difffilter.eval.report import _network_line, _summary_section, _table_section, network_of

DOC = {"runs": 4, "steps": 10, "dt_s": 1.0, "seed": 0, "attacked_steps": 12,
       "attack_free_steps": 28, "notes": []}  # fmt: skip
SCENARIO = types.SimpleNamespace(paper="")


def _table_doc(state_unit: str, attack_unit: str) -> dict:
    entry = {"state_rmse": 0.5, "attack_rmse": 0.25}
    return {
        "estimators": {"kf": entry},
        "units": {"state_rmse": "state units", "attack_rmse": "attack units"},
        "scenario_units": {"state": state_unit, "attack": attack_unit},
        "estimator_roles": {"kf": "analytic"},
        "estimator_descriptions": {"kf": "a Kalman filter"},
    }


def test_the_estimator_table_heads_each_column_with_its_own_scenario_unit():
    """The robot's state is in cm and rad, its actuator attack in cm/s and rad/s: a header
    that read the attack's unit for the state (or the generic "state units") survived every
    fast test (the shipped four-tank scenario has cm for both)."""
    text = _table_section(_table_doc("cm, rad", "cm/s, rad/s")).body
    header = text.splitlines()[0]
    assert "state_rmse [cm, rad]" in header
    assert "attack_rmse [cm/s, rad/s]" in header


def test_the_estimator_table_shows_the_metrics_it_has_without_raw_counts_and_marks_roles():
    """The columns: every metric some estimator has, but the raw counts (they are in
    metrics.json); definitions for those columns alone; a role beside each name that is
    not analytic. Each of the three survived the fast tests when dropped."""
    doc = _table_doc("cm", "cm")
    doc["estimators"] = {"kf": {"state_rmse": 0.5, "false_alarms": 3, "attack_episodes": 2},
                         "net": {"state_rmse": 0.4, "attack_rmse": 0.25}}  # fmt: skip
    doc["estimator_roles"] = {"kf": "analytic", "net": "learned"}
    doc["estimator_descriptions"] = {"kf": "a Kalman filter", "net": "a network"}
    text = _table_section(doc).body
    header = text.splitlines()[0]
    assert header == "| estimator | state_rmse [cm] | attack_rmse [cm] |"
    assert "| `kf` | 0.5 | — |" in text and "| `net` | 0.4 | 0.25 |" in text
    assert "- `kf`: a Kalman filter" in text and "- `net` (learned): a network" in text
    definitions = text.split("Definitions:")[1]
    assert "`state_rmse`" in definitions and "`attack_rmse`" in definitions
    assert "`auc`" not in definitions and "`false_alarms`" not in definitions


def test_the_report_counts_the_attacked_steps_from_the_flags_and_records_the_seed(
    tmp_path, monkeypatch
):
    """metrics.json's attacked_steps / attack_free_steps and seed, and the Setting line:
    counted from the study's flags, the seed the study ran with (mutants that counted ~flags
    as attacked, or wrote seed 0 whatever --seed, survived the fast tests)."""
    from difffilter.eval.report import write_report
    from difffilter.eval.suite import run_suite
    from difffilter.models.yaml_scenario import scenario_from_dict

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    sc = scenario_from_dict({
        "name": "motor_review159", "runs": 4, "steps": 40, "dt": 0.01,
        "plant": {"F": [[0.95, 0.04], [-0.02, 0.8]], "B": [[0.0], [0.2]], "H": [[1.0, 0.0]],
                  "Q": 1.0e-4, "R": 1.0e-3},
        "inputs": {"kind": "constant", "value": 1.0},
        "attack": {"kind": "bias", "channel": "actuator", "value": 0.5, "onset": 30,
                   "share": 1.0},
        "estimators": ["kf"],
    }, "motor.yaml")  # fmt: skip
    result = run_suite(sc, runs=4, seed=3, progress=False)
    attacked = int(result.traj.flags.sum())
    assert 0 < attacked < 4 * 40 / 2  # the two counts differ, so a swap shows
    doc = write_report(tmp_path / "out", result)
    written = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert written["attacked_steps"] == doc["attacked_steps"] == attacked
    assert written["attack_free_steps"] == 4 * 40 - attacked
    assert written["seed"] == 3
    report = (tmp_path / "out" / "report.md").read_text()
    assert f"seed 3; {attacked} attacked and {4 * 40 - attacked} attack-free steps" in report


def test_a_step_that_received_some_entries_is_not_a_step_without_data():
    """``steps_without_data``: the share of (run, step) that received no entry at all; a
    step that lost one of two entries received data (``mask.all`` for ``mask.any`` survived:
    the fast tests' plant has one sensor)."""
    mask = torch.tensor([[[True, True], [True, False], [False, False], [False, True]]])
    traj = types.SimpleNamespace(mask=mask)
    sc = types.SimpleNamespace(input_loss_schedule=lambda: None, schedule=lambda: "every")
    assert network_of(sc, traj)["steps_without_data"] == 0.25


def test_the_network_line_says_whether_the_actuators_hold_or_zero_a_lost_input():
    def line(on_loss):
        inputs = {"schedule": "PacketLoss(rate=0.3)", "on_loss": on_loss, "acknowledged": True}
        return _network_line({"sensors": "AllSensors()", "inputs": inputs})

    assert "holding their last input where one is lost" in line("hold")
    assert "applying zero where one is lost" in line("zero")
    assert "acknowledged (TCP-like" in line("hold")


def test_the_setting_names_an_unused_checkpoint_and_each_estimators_own():
    ckpt = {"path": "a.ckpt", "source": "--ckpt", "sha256": "0" * 64, "used_by": []}
    own = {"pf_nn_ekf": {"path": "b.ckpt", "sha256": "1" * 64, "training_scenario": "s"}}
    body = _summary_section({**DOC, "checkpoint": ckpt, "checkpoints": own}, SCENARIO).body
    assert "), used by no estimator (ignored)." in body
    assert "Checkpoint of `pf_nn_ekf`: `b.ckpt` (sha256 1111111111111111…; trained on `s`)" in body


def test_an_output_folder_with_a_file_where_the_leaderboards_events_go_is_refused_first(
    tmp_path,
):
    """``<out>/tb_leaderboard`` a file: the evaluation ran every suite, wrote the reports and
    the leaderboard, then failed with a FileExistsError traceback (SummaryWriter's
    makedirs); check_output_folder refuses it before any work, as it does a folder where a
    file goes."""
    from difffilter.eval.cli import check_output_folder

    (tmp_path / "tb_leaderboard").write_text("")
    with pytest.raises(ValueError, match="--out: .*tb_leaderboard"):
        check_output_folder(tmp_path, ["four_tank_bias"])


@pytest.mark.parametrize("kind", ["file", "folder"])
def test_what_a_family_writes_beside_the_scenarios_is_checked_first(tmp_path, kind):
    """The LFC family writes ``lfc_summary.md`` and the folders ``lfc_per_channel`` and
    ``lfc_watermark`` in ``--out``: a folder named ``lfc_summary.md`` passed the check and
    the evaluation failed at its very end, in the family's summary. Another family's
    scenarios do not claim those names."""
    from difffilter.eval.cli import check_output_folder

    taken = tmp_path / ("lfc_summary.md" if kind == "folder" else "lfc_watermark")
    taken.mkdir() if kind == "folder" else taken.write_text("")
    with pytest.raises(ValueError, match=rf"--out: .*{taken.name} is a {kind}; the lfc family"):
        check_output_folder(tmp_path, ["lfc_step"])
    check_output_folder(tmp_path, ["four_tank_bias"])


def test_a_refused_run_leaves_no_output_folder(tmp_path, capsys):
    """An argument the evaluation refuses (here ``--runs 0``) is refused before ``--out`` is
    made: the output folder check, which creates it, ran first and left an empty folder."""
    from difffilter.eval import cli

    out = tmp_path / "never"
    assert cli.main(["four_tank_bias", "--runs", "0", "--out", str(out)]) == 2
    assert "--runs" in capsys.readouterr().err
    assert not out.exists()


def test_an_option_with_threats_is_refused_not_dropped(tmp_path, monkeypatch, capsys):
    """``--threats`` runs the robustness study instead of the scenario's report, and
    ``--option`` configures that report: ``lfc_step --threats bias -o watermark=true`` was
    checked, accepted and never used (run_robustness takes no options)."""
    from difffilter.eval import cli, robustness

    def reached(*args, **kwargs):
        raise AssertionError("the robustness study ran; --option was dropped without a word")

    monkeypatch.setattr(robustness, "run_robustness", reached)
    code = cli.main(["lfc_step", "--threats", "bias", "-o", "watermark=true", "--runs", "2",
                     "--no-progress", "--out", str(tmp_path)])  # fmt: skip
    assert code == 2
    assert "--option" in capsys.readouterr().err


def test_a_negative_statistic_prints_as_a_positive_one_does():
    """The intervals' ``tpr_at_far − best`` is negative where the network detects less: a
    range test on ``value`` instead of ``abs(value)`` printed it in scientific notation."""
    from difffilter.eval.report import format_number

    assert format_number(-0.004098) == "-0.004098"
    assert format_number(-0.5, 3) == "-0.5" and format_number(-1234.5) == "-1234"


def test_a_network_given_its_own_checkpoint_is_a_checkpoints_in_the_summary(tmp_path):
    """``--ckpt pf_nn_ekf=b.ckpt``: its checkpoint is in metrics.json's ``checkpoints``, not
    ``checkpoint.used_by``; acceptance.md must still say "checkpoint" (the library's claim)
    and list it first (reading ``used_by`` alone survived the fast tests)."""
    from difffilter.eval.report import write_acceptance_summary
    from difffilter.eval.scoring import METRICS

    def entry(tpr, state):
        return {**dict.fromkeys(METRICS), "tpr_at_far": tpr, "state_rmse": state,
                "fpr_at_far": 0.01}  # fmt: skip

    doc = {"estimators": {"kf": entry(0.9, 1.0), "online_net": entry(0.9, 1.0),
                          "pf_nn_ekf": entry(0.95, 1.0)},
           "estimator_roles": {"kf": "analytic", "online_net": "learned", "pf_nn_ekf": "learned"},
           "far": {"target": 0.01}, "checkpoint": None,
           "checkpoints": {"pf_nn_ekf": {"path": "b.ckpt", "sha256": "1" * 64}}}  # fmt: skip
    path = write_acceptance_summary(tmp_path, {"s": doc})
    rows = [
        line.split("|")[2:4] for line in path.read_text().splitlines() if line.startswith("| s |")
    ]
    assert rows == [[" `pf_nn_ekf` ", " checkpoint "], [" `online_net` ", " online "]]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--runs", "0"], "--runs must be an integer >= 1; got 0"),
        (["--calibration-runs", "0"], "--calibration-runs must be an integer >= 1; got 0"),
        (["--far", "off", "--calibration-runs", "5"], "--calibration-runs with --far off"),
        (["--threat-set", "threats.yaml"], "--threat-set names the threats of --threats"),
        (["--threats", "all", "--far", "off"], "--far off: the robustness study"),
        (["--threats", "all", "--devices", "2"], "--devices: the robustness study runs in one"),
        (["--threats", "all", "--threat-set", "missing.yaml"], "--threat-set: no file"),
    ],
)  # fmt: skip
def test_each_misuse_of_the_command_line_is_refused_before_any_work(
    argv, message, tmp_path, monkeypatch, capsys
):
    """Each of these error paths survived the fast tests when switched off (the study then
    ran, or took the option without a word); here each fails first, naming the option."""
    from difffilter.eval import cli, robustness, suite

    def ran(*args, **kwargs):
        raise AssertionError("a study ran")

    monkeypatch.setattr(robustness, "run_robustness", ran)
    monkeypatch.setattr(suite, "run_suite", ran)
    monkeypatch.chdir(tmp_path)
    code = cli.main(["four_tank_bias", "--runs", "2", "--no-progress", "--out", "out", *argv])
    assert code == 2
    assert message in capsys.readouterr().err


def test_a_file_where_a_scenarios_folder_goes_is_refused_before_any_work(tmp_path, capsys):
    from difffilter.eval import cli

    (tmp_path / "four_tank_bias").write_text("")
    code = cli.main(["four_tank_bias", "--runs", "2", "--out", str(tmp_path)])
    assert code == 2
    assert f"--out: {tmp_path / 'four_tank_bias'} is a file" in capsys.readouterr().err


def test_an_option_without_a_key_is_a_usage_error(capsys):
    from difffilter.eval import cli

    with pytest.raises(SystemExit) as stop:
        cli.main(["four_tank_bias", "-o", "=true"])
    assert stop.value.code == 2
    assert "expected KEY=VALUE; got '=true'" in capsys.readouterr().err


def test_a_checkpoint_no_estimator_used_is_said_after_the_leaderboard(
    tmp_path, monkeypatch, capsys
):
    """``--ckpt FILE`` that no estimator of a scenario read: a note names it (switched off,
    no test noticed)."""
    from difffilter.eval import cli

    def evaluate(names, **kwargs):
        (tmp_path / "leaderboard.md").write_text("# Leaderboard\n")
        return {
            "four_tank_bias": {
                "checkpoint": {"used_by": [], "source": "--ckpt"},
                "estimators": {"chi_square_ekf": {}},
            }
        }  # (one ran)

    monkeypatch.setattr(cli, "evaluate", evaluate)
    code = cli.main(["four_tank_bias", "--ckpt", "checkpoints/four_tank_nn_grad.ckpt",
                     "--no-progress", "--out", str(tmp_path)])  # fmt: skip
    assert code == 0
    out = capsys.readouterr().out
    assert "note: --ckpt checkpoints/four_tank_nn_grad.ckpt is used by no estimator of " \
           "four_tank_bias" in out  # fmt: skip


def test_a_value_that_fails_its_bound_is_printed_apart_from_it():
    """A check printed at four digits showed an FPR of 0.020004 above the band's 0.02 as
    "0.02 ✗", and a TPR of 0.97999 below best − 0.01 = 0.98 as "0.98 ✗": the digits grow
    until the value no longer prints as its bound. A value equal to its bound, or far from
    it, keeps four digits."""
    from difffilter.eval.acceptance import judge
    from difffilter.eval.report import _acceptance_section, format_number

    assert format_number(0.020004, 4, (0.005, 0.02)) == "0.020004"
    assert format_number(0.02, 4, (0.005, 0.02)) == "0.02"
    assert format_number(0.0123456, 4, (0.005, 0.02)) == "0.01235"
    assert format_number(2.00004e-5, 4, (2e-5,)) == "2.00004e-05"
    learned = {"tpr_at_far": 0.97999, "state_rmse": 1.05, "fpr_at_far": 0.020004}
    checks = judge(learned, {"tpr_at_far": (0.99, "kf"), "state_rmse": (1.0, "kf")}, 0.01)
    assert [c.limits for c in checks] == [(pytest.approx(0.98),), (1.05,), (0.005, 0.02)]
    assert "limits" not in checks[0].as_dict()
    doc = {"estimators": {"kf": {"tpr_at_far": 0.99, "state_rmse": 1.0, "fpr_at_far": 0.01},
                          "net": learned},
           "estimator_roles": {"kf": "analytic", "net": "learned"},
           "far": {"target": 0.01}}  # fmt: skip
    row = next(r for r in _acceptance_section(doc).body.splitlines() if "`net`" in r)
    assert "0.97999 ✗" in row and "1.05 ✓" in row and "0.020004 ✗" in row, row


def _one_tank_spec(name: str, estimators: list[str]) -> dict:
    """A one-tank YAML scenario (4 runs of 30 steps, a bias of 1 from step 15)."""
    return {
        "name": name, "runs": 4, "steps": 30, "dt": 1.0,
        "plant": {"F": [[0.9]], "H": [[1.0]], "Q": 1.0e-3, "R": 1.0e-2},
        "attack": {"kind": "bias", "value": 1.0, "onset": 15},
        "estimators": estimators,
    }  # fmt: skip


def test_a_rerun_into_the_same_folder_leaves_none_of_the_earlier_runs_figures(
    tmp_path, monkeypatch
):
    """The README: "a scenario's folder always shows one run". A rerun without detectors
    left the earlier run's roc.png and alarms_run0.png beside its own report, which shows
    neither. A PNG the earlier report did not show (a user's) stays."""
    from difffilter.eval.report import write_report
    from difffilter.eval.suite import run_suite
    from difffilter.models.yaml_scenario import scenario_from_dict

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    sc = scenario_from_dict(_one_tank_spec("tank_rerun", ["kf"]), "tank.yaml")
    out = tmp_path / "out"
    write_report(out, run_suite(sc, runs=4, seed=0, progress=False, add=["chi_square_kf"]))
    assert (out / "roc.png").is_file() and (out / "alarms_run0.png").is_file()
    (out / "mine.png").write_bytes(b"")
    write_report(out, run_suite(sc, runs=4, seed=0, progress=False))
    report = (out / "report.md").read_text()
    assert "roc.png" not in report and "rmse_over_time.png" in report
    assert not (out / "roc.png").exists() and not (out / "alarms_run0.png").exists()
    assert (out / "rmse_over_time.png").is_file() and (out / "mine.png").is_file()


def test_a_rerun_after_a_stopped_evaluation_leaves_none_of_the_stopped_runs_figures(
    tmp_path, monkeypatch, isolated_registry
):
    """An evaluation stopped after its PNGs, before its report.md, left roc.png and
    alarms_run0.png, which the earlier report.md (the one a rerun reads) does not list: the
    rerun kept them and removed INCOMPLETE.md, a folder that looked whole with a figure of
    another run. Truth: the same runs with no stop between them (README: "a scenario's
    folder always shows one run of each kind"); a PNG that was there before (a user's)
    stays, and so does the record through a second stop."""
    from pathlib import Path

    from difffilter.eval import report as report_module
    from difffilter.eval.report import INCOMPLETE, _figures_of, write_report
    from difffilter.eval.suite import run_suite
    from difffilter.models.yaml_scenario import scenario_from_dict

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    sc = scenario_from_dict(_one_tank_spec("tank_stopped", ["kf"]), "tank.yaml")
    plain = run_suite(sc, runs=4, seed=0, progress=False)  # draws no ROC, no alarms
    detecting = run_suite(sc, runs=4, seed=1, progress=False, add=["chi_square_kf"])
    real = report_module.write_atomically

    def stopped(folder: Path, result) -> None:  # stopped as report.md is about to be written
        def write(path, content):
            if Path(path).name == "report.md":
                raise KeyboardInterrupt
            return real(path, content)

        with monkeypatch.context() as m:
            m.setattr(report_module, "write_atomically", write)
            with pytest.raises(KeyboardInterrupt):
                write_report(folder, result)
        assert (folder / INCOMPLETE).is_file()

    def pngs(folder: Path) -> set[str]:
        return {p.name for p in folder.glob("*.png")}

    expected = tmp_path / "expected"  # the same runs, none stopped
    write_report(expected, plain)
    (expected / "mine.png").write_bytes(b"")
    write_report(expected, plain)

    out = tmp_path / "out"
    write_report(out, plain)
    (out / "mine.png").write_bytes(b"")
    stopped(out, detecting)
    assert {"roc.png", "alarms_run0.png"} <= pngs(out)  # the stopped run's, listed nowhere
    stopped(out, plain)  # a rerun stopped too: the record carries the stopped run's figures
    write_report(out, plain)
    assert pngs(out) == pngs(expected)
    assert "roc.png" not in pngs(out) and "mine.png" in pngs(out)
    assert _figures_of(out / "report.md") == pngs(out) - {"mine.png"}
    assert not (out / INCOMPLETE).exists()


def _one_tank(tmp_path, monkeypatch):
    """The one-tank scenario of the test above, its YAML file and a threat set of one bias."""
    from difffilter.models.yaml_scenario import scenario_from_dict

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    spec = _one_tank_spec("tank_stopped", ["kf", "chi_square_kf"])
    (tmp_path / "tank.yaml").write_text(json.dumps(spec))  # (JSON is YAML)
    (tmp_path / "threats.yaml").write_text(
        "threats:\n  bias: {kind: bias, value: 1.0, onset: 15}\n"
    )
    return scenario_from_dict(spec, "tank.yaml"), tmp_path / "tank.yaml", tmp_path / "threats.yaml"


def _kinds_marked(folder) -> list[str]:
    """The kinds of run whose section ``<folder>/INCOMPLETE.md`` holds ([] where none)."""
    from difffilter.eval.report import INCOMPLETE

    marker = folder / INCOMPLETE
    lines = marker.read_text().splitlines() if marker.is_file() else []
    return [kind for kind in ("evaluation", "robustness study") if f"## {kind}" in lines]


def _interrupted(*args, **kwargs):
    raise KeyboardInterrupt


def _stop_writing(monkeypatch, module, name: str, write, stop=_interrupted) -> None:
    """``write()`` stopped by a KeyboardInterrupt where ``stop`` in place of ``module.name``
    raises one (at its first call by default)."""
    with monkeypatch.context() as m:
        m.setattr(module, name, stop)
        with pytest.raises(KeyboardInterrupt):
            write()


def test_a_robustness_study_to_its_end_keeps_a_stopped_evaluations_marker_and_record(
    tmp_path, monkeypatch, isolated_registry
):
    """An evaluation and a robustness study marked a scenario's folder with the same
    INCOMPLETE.md, and each removed it at its end: a study run to its end after a stopped
    evaluation removed the evaluation's marker (the stopped run's metrics.json and figures
    unflagged), and with it the record of the PNGs there before the evaluation's write.
    Truth: the README ("an INCOMPLETE.md left in a scenario's folder says that an evaluation
    stopped there midway", until rerun to its end) and the same runs with no stop between
    them, the study's robustness.png included."""
    from pathlib import Path

    from difffilter.eval import report as report_module
    from difffilter.eval.report import INCOMPLETE, _figures_before, write_report
    from difffilter.eval.robustness import load_threat_set, run_robustness, write_robustness
    from difffilter.eval.suite import run_suite

    sc, _, threats = _one_tank(tmp_path, monkeypatch)
    plain = run_suite(sc, runs=4, seed=0, progress=False)  # draws no ROC, no alarms
    detecting = run_suite(sc, runs=4, seed=1, progress=False, add=["chi_square_kf"])
    study = run_robustness(sc, load_threat_set(sc, path=threats), runs=4, progress=False)

    def pngs(folder) -> set[str]:
        return {p.name for p in folder.glob("*.png")}

    expected = tmp_path / "expected"  # the same runs, none stopped
    write_report(expected, plain)
    write_robustness(expected, study)
    write_report(expected, plain)

    out = tmp_path / "out"
    write_report(out, plain)
    real = report_module.write_atomically

    def write(path, content):  # stopped as report.md is about to be written: no report
        if Path(path).name == "report.md":  # lists the stopped run's figures, its record does
            raise KeyboardInterrupt
        return real(path, content)

    _stop_writing(monkeypatch, report_module, "write_atomically",
                  lambda: write_report(out, detecting), stop=write)  # fmt: skip
    record = _figures_before(out)
    assert record == pngs(expected) - {"robustness.png"}
    assert {"roc.png", "alarms_run0.png"} <= pngs(out)  # the stopped run's, listed nowhere
    write_robustness(out, study)  # to its end
    assert (out / INCOMPLETE).is_file()
    assert _kinds_marked(out) == ["evaluation"]  # the stopped evaluation's still flagged
    assert _figures_before(out) == record  # ... with its record whole
    write_report(out, plain)  # the evaluation run again to its end
    assert pngs(out) == pngs(expected)  # the study's heat map kept, the stopped run's gone
    assert not (out / INCOMPLETE).exists()


def test_an_evaluation_to_its_end_keeps_a_stopped_robustness_studys_marker(
    tmp_path, monkeypatch, isolated_registry
):
    """The other way round: an evaluation run to its end removed the INCOMPLETE.md of a
    robustness study stopped in the folder before its heat map (its robustness.json and .md
    of this study beside the earlier heat map, unflagged). Truth: the README (the marker says
    so until that run is repeated to its end)."""
    from difffilter.eval import robustness
    from difffilter.eval.report import INCOMPLETE, write_report
    from difffilter.eval.suite import run_suite

    sc, _, threats = _one_tank(tmp_path, monkeypatch)
    plain = run_suite(sc, runs=4, seed=0, progress=False)
    study = robustness.run_robustness(sc, robustness.load_threat_set(sc, path=threats), runs=4,
                                      progress=False)  # fmt: skip
    out = tmp_path / "out"
    _stop_writing(
        monkeypatch, robustness, "_heatmap", lambda: robustness.write_robustness(out, study)
    )
    assert (out / INCOMPLETE).is_file()  # the stopped study's
    write_report(out, plain)  # to its end
    assert (out / INCOMPLETE).is_file()
    assert _kinds_marked(out) == ["robustness study"]
    assert "Writing the robustness study of tank_stopped" in (out / INCOMPLETE).read_text()
    robustness.write_robustness(out, study)  # the study run again to its end
    assert not (out / INCOMPLETE).exists()


def test_each_kind_of_run_into_out_clears_only_its_own_incomplete_md(
    tmp_path, monkeypatch, isolated_registry
):
    """``difffilter-eval``: an evaluation and a robustness study (--threats) into one --out,
    each stopped and then the other run to its end, the stopped one's INCOMPLETE.md stays in
    <out> and in the scenario's folder until it is run again to its end (README); both had
    been removed by the other kind's run."""
    from difffilter.eval import cli, robustness, tensorboard
    from difffilter.eval.report import INCOMPLETE

    _, scenario, threats = _one_tank(tmp_path, monkeypatch)
    out = tmp_path / "out"
    evaluation = [str(scenario), "--runs", "4", "--no-progress", "--out", str(out)]
    study = [*evaluation, "--threats", "all", "--threat-set", str(threats)]
    folders = (out, out / "tank_stopped")

    def stopped(module, name, args) -> None:
        with monkeypatch.context() as m:
            m.setattr(module, name, _interrupted)
            assert cli.main(args) == 130

    for (module, name, kind, run), other in (
        ((tensorboard, "log_suite", "evaluation", evaluation), study),
        ((robustness, "_heatmap", "robustness study", study), evaluation),
    ):
        stopped(module, name, run)
        assert cli.main(other) == 0  # the other kind to its end: the marker stays
        assert [_kinds_marked(f) for f in folders] == [[kind]] * 2
        assert cli.main(run) == 0  # its own kind to its end: gone
        assert not list(out.rglob(INCOMPLETE))


def test_a_marker_of_the_earlier_version_is_cleared_by_its_own_kind_alone(tmp_path):
    """An INCOMPLETE.md written before the markers had sections (no kind's heading) is read as
    the kind its text names: an evaluation's clear leaves a stopped study's, the study's own
    removes it; an unknown kind is refused by name."""
    from difffilter.eval.report import INCOMPLETE, clear_incomplete, mark_incomplete

    marker = tmp_path / INCOMPLETE
    marker.write_text("# Incomplete\n\nWriting the robustness study of tank into this folder "
                      "began at 2024-01-01 00:00:00 (process 1) and has not ended.\n")  # fmt: skip
    clear_incomplete(tmp_path)  # an evaluation to its end
    assert marker.is_file()
    mark_incomplete(tmp_path, "An evaluation into this folder")
    assert _kinds_marked(tmp_path) == ["evaluation", "robustness study"]
    clear_incomplete(tmp_path, "robustness study")
    assert _kinds_marked(tmp_path) == ["evaluation"]
    clear_incomplete(tmp_path)
    assert not marker.exists()
    with pytest.raises(ValueError, match="kind: 'robustness'"):
        mark_incomplete(tmp_path, "A study", kind="robustness")
