"""Hand checks of what the command lines, figures and files pass on: ``difffilter-eval``'s
options reaching the study and the calibration, the figures' time axes and spans, the
TensorBoard curves, the prediction files, resuming and loading exported weights, the LFC
tuning file, and the inputs' finiteness check under a mask.

Each value here is written down by hand (a tiny case) or is what the module's docstring
promises; every test failed on a mutant of mutation round 10 that the rest of the suite
let through.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace as NS

import pytest
import torch

import difffilter as df

# ---------------------------------------------------------------- difffilter-eval options


def test_a_plain_checkpoint_among_named_ones_is_the_others_default():
    from difffilter.eval.cli import parse_checkpoints
    from difffilter.models import registry

    registry.names()  # the estimators' names are known once the families are registered
    parsed = parse_checkpoints(["pf_nn_grad=a.ckpt", "b.ckpt"])
    assert parsed == {"pf_nn_grad": Path("a.ckpt"), "*": Path("b.ckpt")}


@pytest.mark.parametrize("text", ["0", "1", "-0.1", "nan", "1.5"])
def test_far_is_a_rate_strictly_between_zero_and_one(text):
    import argparse

    from difffilter.eval.cli import _far

    with pytest.raises(argparse.ArgumentTypeError, match="a rate in"):
        _far(text)
    assert _far("0.05") == 0.05 and _far("off") is None


def test_calibration_runs_and_the_checkpoint_reach_the_calibration(monkeypatch, tmp_path):
    """``evaluate``: the detectors are calibrated on ``calibration_runs`` runs (``runs``
    when not given), with the checkpoint the study ran (its detectors are those calibrated)."""
    from difffilter.eval import calibration, cli, leaderboard, report, suite

    seen = {"suite": [], "calibrate": []}
    monkeypatch.setattr(cli, "check_arguments", lambda **kw: None)
    monkeypatch.setattr(cli, "_write_family", lambda family, results, out, prep: {})
    monkeypatch.setattr(suite, "run_suite", lambda sc, **kw: seen["suite"].append(kw) or NS())
    monkeypatch.setattr(suite, "apply_calibration", lambda result, cal: None)
    monkeypatch.setattr(suite, "detectors", lambda result: ["chi_square_ekf"])
    monkeypatch.setattr(suite, "process_group", lambda: (0, 1))
    monkeypatch.setattr(calibration, "calibrate",
                        lambda sc, **kw: seen["calibrate"].append(kw))  # fmt: skip
    monkeypatch.setattr(report, "family_report", lambda f: NS(prepare=None, finish=None))
    monkeypatch.setattr(
        report, "report_writers", lambda families, world: dict.fromkeys(families, 0)
    )
    monkeypatch.setattr(report, "write_acceptance_summary", lambda out, docs: None)
    monkeypatch.setattr(leaderboard, "write_leaderboard", lambda out, docs: None)
    ckpt = Path("given.ckpt")
    for calibration_runs in (7, None):
        cli.evaluate(["four_tank_bias"], ckpt=ckpt, runs=3, out=tmp_path, seed=4,
                     progress=False, far=0.01, calibration_runs=calibration_runs)  # fmt: skip
    assert [c["runs"] for c in seen["calibrate"]] == [7, 3]
    assert [c["study_runs"] for c in seen["calibrate"]] == [3, 3]  # the study's detectors
    assert all(c["checkpoint"] == ckpt and c["far"] == 0.01 for c in seen["calibrate"])
    assert all(s["checkpoint"] == ckpt and s["runs"] == 3 for s in seen["suite"])


def test_the_scenario_robustness_runs_the_robustness_study_on_every_threat(monkeypatch, tmp_path):
    from difffilter.eval import cli

    called = {}
    monkeypatch.setattr(cli, "_robustness",
                        lambda names, threats, args: called.setdefault("robustness", threats) and 0)  # fmt: skip
    monkeypatch.setattr(cli, "evaluate", lambda *a, **kw: called.setdefault("evaluate", True))
    cli.main(["robustness", "--out", str(tmp_path / "out"), "--no-progress"])
    assert called == {"robustness": "all"}


# ---------------------------------------------------------------- figures and TensorBoard


def test_alarm_spans_are_consecutive_alarms_centred_on_their_steps():
    from difffilter.eval.plots import _alarm_spans

    dt = 0.1
    t = [dt * (k + 1) for k in range(5)]
    for alarms, want in (
        ([True, True, False, False, True], [(0.05, 0.2), (0.45, 0.1)]),
        ([False, True, True, True, False], [(0.15, 0.3)]),
    ):
        spans = _alarm_spans(torch.tensor(alarms), t, dt)
        assert len(spans) == len(want)
        for got, expected in zip(spans, want):
            assert got == pytest.approx(expected, abs=1e-12)


def test_the_attack_figure_shows_its_runs_attacked_channels_the_most_attacked_first():
    from difffilter.eval.plots import _attacked_channels, _entry_units

    attack = torch.zeros(2, 4, 3)
    attack[0, 2, 1], attack[0, 1, 0], attack[1, :, 2] = 5.0, -1.0, 9.0  # run 1 is not run 0
    assert _attacked_channels(attack, 0) == [1, 0] and _attacked_channels(attack, 1) == [2]
    attack[0, 3, 0] = -6.0  # by magnitude
    assert _attacked_channels(attack, 0) == [0, 1]
    assert _attacked_channels(torch.zeros(1, 4, 3), 0) == [0]  # none attacked: the first
    # one unit per entry where the scenario lists one per entry (the robot's)
    units = {"cm/s, rad/s": ["cm/s", "rad/s"], "p.u. (Δf in Hz)": ["p.u. (Δf in Hz)"] * 2}
    for unit, want in units.items():
        assert _entry_units(type("S", (), {"attack_unit": unit}), 2) == want


def test_the_rmse_figure_plots_step_k_at_time_k_dt():
    """Step ``t`` of a trajectory is measurement ``k = t + 1``, at time ``k · dt``."""
    from difffilter.eval.plots import standard_figures

    B, T = 2, 4
    x = torch.randn(B, T, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    traj = NS(flags=torch.zeros(B, T, dtype=torch.bool), attack=torch.zeros(B, T, 0), x=x)
    out = NS(means=x + 0.1, detection=None, attack=None)
    result = NS(traj=traj, outputs={"kf": out}, scenario=NS(dt=0.5, state_unit="m"),
                traj_of=lambda name: traj, metrics={"kf": {}})  # fmt: skip
    name, fig = standard_figures(result)[0]
    line = fig.axes[0].lines[0]
    assert name == "rmse_over_time.png"
    assert list(line.get_xdata()) == pytest.approx([0.5, 1.0, 1.5, 2.0])
    assert list(line.get_ydata()) == pytest.approx([0.1] * T)


def test_each_roc_curve_is_drawn_against_the_flags_its_estimator_ran_on():
    """In a closed loop each estimator has its own trajectories: its ROC curve (like its
    AUC in the legend) is against its own flags, not the study's."""
    from difffilter.eval.plots import _roc_figure
    from difffilter.eval.scoring import roc

    study = torch.tensor([[False, True, True, False]])
    own = torch.tensor([[True, False, False, True]])  # "loop"'s own closed loop
    scores = torch.tensor([[0.9, 0.1, 0.2, 0.8]])
    outputs = {n: NS(detection=NS(scores=scores)) for n in ("open", "loop")}
    flags = {"open": study, "loop": own}
    result = NS(traj=NS(flags=study), traj_of=lambda n: NS(flags=flags[n]),
                metrics={n: {"auc": 0.5} for n in outputs}, calibration=None)  # fmt: skip
    fig = _roc_figure(result, outputs, {"open": "C0", "loop": "C1"})
    curves = {line.get_label().split()[0]: line for line in fig.axes[0].lines}
    for name in outputs:
        fpr, tpr = roc(scores, flags[name])
        assert list(curves[name].get_ydata()) == pytest.approx(tpr.tolist())
    # the same scores: perfect against its own flags (every detection before the first
    # false alarm), inverted against the study's (none)
    for name, want in (("loop", 1.0), ("open", 0.0)):
        x, y = curves[name].get_xdata(), curves[name].get_ydata()
        assert max(yi for xi, yi in zip(x, y) if xi == x.min()) == want


def test_run_0s_alarm_rows_show_the_attack_each_detector_faced():
    """A detector of its own closed loop, attacked at other steps than the study's run 0,
    gets its own attacked steps as a grey band behind its alarms; one on the study's
    trajectories gets none (the top row is its truth)."""
    import matplotlib.pyplot as plt
    from matplotlib import colors as mcolors

    from difffilter.eval.plots import _alarm_figure

    study = torch.tensor([[False, True, True, False, False]])
    own = torch.tensor([[False, False, False, True, True]])
    alarms = torch.tensor([[False, False, True, True, False]])
    outputs = {n: NS(detection=NS(alarms=alarms)) for n in ("open", "loop")}
    flags = {"open": study, "loop": own}
    result = NS(
        traj=NS(flags=study), traj_of=lambda n: NS(flags=flags[n]), metrics={n: {} for n in outputs}
    )  # not calibrated: their own alarms
    t = [0.5 * (k + 1) for k in range(5)]
    fig = _alarm_figure(result, outputs, {"open": "C0", "loop": "C1"}, t, 0.5)
    bars = [(tuple(c.get_facecolor()[0][:3]), c.get_paths()) for c in fig.axes[0].collections]

    def spans(colour):
        rgb = mcolors.to_rgb(colour)
        return [[tuple(path.get_extents().intervalx) for path in paths]
                for face, paths in bars if face == pytest.approx(rgb)]  # fmt: skip

    # step k at time k·dt, its bar half a step either side
    assert spans("k") == [[(0.75, 1.75)]]  # the study's steps 2-3
    assert spans("0.85") == [[(1.75, 2.75)]]  # "loop"'s own steps 4-5, once (not "open")
    assert spans("C0") == spans("C1") == [[(1.25, 2.25)]]
    plt.close(fig)


def test_the_attack_figure_draws_the_attack_injected_in_an_estimators_own_loop():
    import matplotlib.pyplot as plt

    from difffilter.attack import Channel
    from difffilter.eval.plots import standard_figures

    B, T = 1, 4
    x = torch.zeros(B, T, 1, dtype=torch.float64)
    study_attack = torch.tensor([[[0.0], [1.0], [1.0], [1.0]]], dtype=torch.float64)
    own_attack = torch.tensor([[[0.0], [2.0], [3.0], [4.0]]], dtype=torch.float64)
    info = {"attack_channel": Channel.SENSOR}
    study = NS(flags=torch.zeros(B, T, dtype=torch.bool), attack=study_attack, x=x, info=info)
    own = NS(flags=study.flags, attack=own_attack, x=x, info=info)
    est = lambda a: NS(means=x + 0.1, detection=None, attack=a, attack_channel=Channel.SENSOR)  # noqa: E731
    outputs = {"open": est(study_attack + 0.1), "loop": est(own_attack - 0.1)}
    result = NS(
        traj=study,
        outputs=outputs,
        scenario=NS(dt=1.0, state_unit="m", attack_unit="V"),
        traj_of=lambda n: own if n == "loop" else study,
        metrics={n: {} for n in outputs},
    )
    figs = dict(standard_figures(result))
    lines = {
        line.get_label(): list(line.get_ydata())
        for line in figs["attack_estimates_run0.png"].axes[0].lines
    }
    assert lines == {"injected": [0.0, 1.0, 1.0, 1.0], "open": pytest.approx([0.1, 1.1, 1.1, 1.1]),
                     "injected in loop's loop": [0.0, 2.0, 3.0, 4.0],
                     "loop": pytest.approx([-0.1, 1.9, 2.9, 3.9])}  # fmt: skip
    assert figs["attack_estimates_run0.png"].axes[0].get_ylabel() == "attack, channel 1 [V]"
    # a scenario that names its entries: the channel by its name (a reviewer took the LFC's
    # turbine power, channel 3 in "p.u. (Δf in Hz)", for a frequency)
    result.scenario.attack_entry_names = ("dPtu_1",)
    named = dict(standard_figures(result))
    assert (
        named["attack_estimates_run0.png"].axes[0].get_ylabel() == "attack, channel 1, dPtu_1 [V]"
    )
    for fig in (*figs.values(), *named.values()):
        plt.close(fig)


def test_tensorboard_curves_are_means_over_runs_at_steps_from_one(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from difffilter.eval.tensorboard import log_suite

    alarms = torch.tensor([[1, 0, 0], [1, 1, 0], [0, 1, 0], [1, 1, 1]], dtype=torch.bool)
    x = torch.zeros(4, 3, 1, dtype=torch.float64)
    traj = NS(x=x, attack=torch.zeros(4, 3, 0))
    out = NS(means=x + 2.0, detection=NS(alarms=alarms), attack=None)
    result = NS(outputs={"chi": out}, traj_of=lambda name: traj, metrics={"chi": {}})
    log_suite(tmp_path, result, {"estimators": {"chi": {}}, "scenario": "s", "runs": 4, "seed": 0},
              [])  # fmt: skip
    events = EventAccumulator(str(tmp_path))
    events.Reload()
    curve = lambda tag: [(e.step, round(e.value, 6)) for e in events.Scalars(tag)]  # noqa: E731
    assert curve("alarm_rate_per_step/chi") == [(1, 0.75), (2, 0.75), (3, 0.25)]
    assert curve("state_rmse_per_step/chi") == [(1, 2.0), (2, 2.0), (3, 2.0)]
    # a second evaluation into the same folder replaces the first's events (a user trial:
    # TensorBoard drew both runs' points, two per step, beside one run's metrics.json)
    (tmp_path / "notes.txt").write_text("mine")
    result.outputs["chi"].means = x + 1.0
    log_suite(tmp_path, result, {"estimators": {"chi": {}}, "scenario": "s", "runs": 4, "seed": 0},
              [])  # fmt: skip
    events = EventAccumulator(str(tmp_path))
    events.Reload()
    assert curve("state_rmse_per_step/chi") == [(1, 1.0), (2, 1.0), (3, 1.0)]
    assert len(list(tmp_path.rglob("events.out.tfevents.*"))) == 2  # the curves' and hparams/chi
    assert (tmp_path / "notes.txt").read_text() == "mine"  # only event files go


def _hparams_experiment(logdir):
    """``(hparam names, metric tags)`` of the HPARAMS table TensorBoard's own backend builds
    for ``logdir`` (what its HPARAMS tab shows)."""
    import inspect

    from tensorboard import context
    from tensorboard.backend.event_processing import data_provider, plugin_event_multiplexer
    from tensorboard.plugins import base_plugin
    from tensorboard.plugins.hparams import backend_context

    mux = plugin_event_multiplexer.EventMultiplexer()
    mux.AddRunsFromDirectory(str(logdir))
    mux.Reload()
    provider = data_provider.MultiplexerDataProvider(mux, str(logdir))
    backend = backend_context.Context(
        base_plugin.TBContext(logdir=str(logdir), data_provider=provider, multiplexer=mux)
    )
    request = context.RequestContext()
    # (TensorBoard 2.14, the lowest declared, takes neither include_metrics nor limit)
    takes = lambda f, name: name in inspect.signature(f).parameters  # noqa: E731
    limit = (None,) if takes(backend.hparams_from_data_provider, "limit") else ()
    provided = backend.hparams_from_data_provider(request, "", *limit)
    include = (True,) if takes(backend.experiment_from_metadata, "include_metrics") else ()
    experiment = backend.experiment_from_metadata(
        request, "", *include, backend.hparams_metadata(request, ""), provided
    )
    return (sorted(h.name for h in experiment.hparam_infos),
            sorted(m.name.tag for m in experiment.metric_infos))  # fmt: skip


def test_the_hparams_table_has_every_estimators_columns_and_the_calibrated_curve(tmp_path):
    """TensorBoard's HPARAMS table of an evaluation and its leaderboard holds every column
    of every row (a trial: each row wrote an experiment summary of its own, and TensorBoard
    showed the first one's columns for all, hiding the network's holds_share and, under
    the leaderboard's, every scenario column); the calibrated metrics are columns, and the
    alarm rate at the calibrated threshold is a curve beside the one at the estimator's own
    (means over runs of score > τ by hand)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from difffilter.eval.leaderboard import _hparams
    from difffilter.eval.tensorboard import log_suite

    x = torch.zeros(4, 3, 1, dtype=torch.float64)
    scores = torch.tensor([[3.0, 0, 0], [3, 2, 0], [0, 2, float("nan")], [3, 2, 1]])
    alarms = scores > 2.5  # the estimator's own threshold
    out = NS(means=x + 2.0, detection=NS(alarms=alarms, scores=scores), attack=None)
    reference = NS(means=x + 1.0, detection=None, attack=None)
    traj = NS(x=x, attack=torch.zeros(4, 3, 0))
    result = NS(outputs={"chi": out, "ref": reference}, traj_of=lambda name: traj,
                metrics={"chi": {"threshold_at_far": 1.5}, "ref": {}})  # fmt: skip
    doc = {"estimators": {"chi": {"auc": 0.9, "threshold_at_far": 1.5, "tpr_at_far": 0.5},
                          "ref": {"state_rmse": 1.0}},
           "scenario": "s", "runs": 4, "seed": 0,
           "acceptance_intervals": {"estimators": {"chi": {"state_rmse": {"holds_share": 0.8}}}}}  # fmt: skip
    log_suite(tmp_path / "s" / "tb", result, doc, [])
    row = {"scenario": "s", "estimator": "chi", "checkpoint": None, "auc": 0.9}
    _hparams(tmp_path / "tb_leaderboard", [row])
    names, tags = _hparams_experiment(tmp_path)
    assert names == ["checkpoint", "estimator", "runs", "scenario", "seed"]
    # the leaderboard's rows name their study too (two seeds' rows had been told apart by
    # nothing but their metrics: a trial)
    assert _hparams_experiment(tmp_path / "tb_leaderboard")[0] == [
        "checkpoint",
        "estimator",
        "scenario",
    ]
    from difffilter.eval.leaderboard import leaderboard_rows

    (board,) = [r for r in leaderboard_rows({"s": doc}) if r["estimator"] == "chi"]
    assert (board["seed"], board["runs"]) == (0, 4)
    _hparams(tmp_path / "tb_leaderboard", [board])
    names = _hparams_experiment(tmp_path / "tb_leaderboard")[0]
    assert names == ["checkpoint", "estimator", "runs", "scenario", "seed"]
    assert tags == ["hparam/auc", "hparam/holds_share/state_rmse", "hparam/state_rmse",
                    "hparam/threshold_at_far", "hparam/tpr_at_far", "leaderboard/auc"]  # fmt: skip
    events = EventAccumulator(str(tmp_path / "s" / "tb"))
    events.Reload()
    curve = lambda tag: [(e.step, round(e.value, 6)) for e in events.Scalars(tag)]  # noqa: E731
    assert curve("alarm_rate_per_step/chi") == [(1, 0.75), (2, 0.0), (3, 0.0)]
    assert curve("alarm_rate_at_far_per_step/chi") == [(1, 0.75), (2, 0.75), (3, 0.0)]
    assert "alarm_rate_at_far_per_step/ref" not in events.Tags()["scalars"]


# ---------------------------------------------------------------- training's files


def test_predictions_write_one_file_per_batch_and_the_test_seed(tmp_path):
    from difffilter.train.predictions import PredictionFiles

    writer = PredictionFiles(tmp_path / "pred")
    trainer = NS(log_dir=str(tmp_path), datamodule=NS(hparams={"seed": 3, "test_seed": 11}))
    module = NS(scenario_of_data=lambda: NS(name="s", dt=0.1), alarm_threshold=0.5,
                channel=NS(value="sensor"))  # fmt: skip
    for i, runs in enumerate((2, 3)):
        prediction = {
            "means": torch.full((runs, 4, 2), float(i)),
            "attack_estimate": torch.zeros(runs, 4, 1),
            "attack_probability": torch.full((runs, 4), 0.1 * i),
            "alarms": torch.zeros(runs, 4, dtype=torch.bool),
        }
        writer.write_on_batch_end(trainer, module, prediction, None, None, i, 0)
    writer.on_predict_end(trainer, module)
    index = json.loads((tmp_path / "pred" / "predictions.json").read_text())
    files = sorted(p.name for p in (tmp_path / "pred").glob("batch_*.pt"))
    assert files == ["batch_00000.pt", "batch_00001.pt"]
    assert [(f["file"], f["runs"]) for f in index["files"]] == list(zip(files, (2, 3)))
    second = torch.load(tmp_path / "pred" / files[1], weights_only=True)
    assert second["means"].shape[0] == 3 and bool((second["means"] == 1.0).all())
    assert index["seed"] == 11


def test_resuming_another_runs_checkpoint_does_not_take_its_version(tmp_path, monkeypatch):
    """``fit --ckpt_path <save_dir>/<name>/version_3/checkpoints/last.ckpt`` logs into
    version 3 only when ``<name>`` is this run's logger name. (The path names no file: the
    check of the file itself, which refuses a missing one, is left out here.)"""
    from difffilter.train import lightning_cli
    from difffilter.train.lightning_cli import DifffilterCLI

    monkeypatch.setattr(lightning_cli, "_check_ckpt_path", lambda cfg, subcommand: "lightning")

    ckpt = str(tmp_path / "other" / "version_3" / "checkpoints" / "last.ckpt")
    for name, version in (("mine", None), ("other", 3)):
        logger = {"init_args": {"save_dir": str(tmp_path), "name": name}}
        cli = NS(
            subcommand="fit", config={"fit": {"ckpt_path": ckpt, "trainer": {"logger": logger}}}
        )
        DifffilterCLI.before_instantiate_classes(cli)
        assert logger["init_args"].get("version") == version, name


def test_an_exported_checkpoint_given_as_ckpt_path_loads_its_weights(capsys):
    from difffilter.models.neural_estimator import load_estimator_checkpoint
    from difffilter.train.lightning_cli import DifffilterCLI

    path = Path("checkpoints/four_tank_nn_ekf.ckpt")
    shipped, _ = load_estimator_checkpoint(path)
    mine, _ = load_estimator_checkpoint(path)
    with torch.no_grad():
        for p in mine.parameters():
            p.add_(1.0)
    from difffilter.models import registry

    # (the configured scenario: the checkpoint's own plant, so no note of another one)
    cli = NS(config_init={"predict": {"ckpt_path": str(path)}},
             model=NS(estimator=mine, check_exported=lambda card, path: None,
                      scenario=registry.get("four_tank_bias")))  # fmt: skip
    DifffilterCLI._load_exported(cli, "predict")
    for got, want in zip(mine.state_dict().values(), shipped.state_dict().values()):
        assert torch.equal(got, want)
    assert cli.config_init["predict"]["ckpt_path"] is None  # nothing left for Lightning
    said = capsys.readouterr()
    assert "loaded the exported estimator" in said.out and "note:" not in said.err


def test_the_attack_figure_draws_the_two_most_attacked_channels_from_time_dt():
    from difffilter.train.figures import attack_figure

    attack = torch.zeros(5, 4)
    attack[:, 2], attack[:, 0], attack[0, 3] = 3.0, 1.0, 0.5
    lines = attack_figure(attack, 0.9 * attack, 0.1).axes[0].lines
    labels = [line.get_label() for line in lines]
    assert labels[0] == "attack ch3" and labels[2] == "attack ch1"
    assert lines[0].get_xdata()[0] == pytest.approx(0.1)


def test_lfc_tuning_merges_into_an_existing_file(monkeypatch, tmp_path, capsys):
    from difffilter.train import lfc_tuning

    out = tmp_path / "tuning.json"
    out.write_text(json.dumps({"grids": {"kf_nn_ekf": [{"a": 1}]},
                               "chosen": {"kf_nn_ekf": {"init_scale": 0.1}}}))  # fmt: skip
    monkeypatch.setattr(lfc_tuning, "tune", lambda estimators, runs, ckpt: {
        "grids": {"traditional_ad": [{"b": 2}]}, "chosen": {"traditional_ad": {"lr": 0.01}},
        "validation": {"runs": runs},
    })  # fmt: skip
    lfc_tuning.main(["--runs", "2", "--out", str(out), "--estimators", "traditional_ad"])
    document = json.loads(out.read_text())
    assert document["chosen"] == {"kf_nn_ekf": {"init_scale": 0.1}, "traditional_ad": {"lr": 0.01}}
    assert set(document["grids"]) == {"kf_nn_ekf", "traditional_ad"}


def test_lfc_tuning_records_the_horizon_it_validated_on(monkeypatch):
    """The tuning's JSON recorded 1,000 validation steps whatever the batch held."""
    from difffilter.train import lfc_tuning

    monkeypatch.setattr(lfc_tuning, "validation_batch",
                        lambda runs: {"attack": torch.zeros(runs, 50, 10)})  # fmt: skip
    out = lfc_tuning.tune(estimators=(), runs=3, progress=False)
    assert out["validation"]["steps"] == 50 and out["validation"]["runs"] == 3


# ---------------------------------------------------------------- inputs under a mask


def test_a_non_finite_measurement_counts_only_where_it_is_received():
    from difffilter._checks import check_sequence_inputs

    d = torch.float64
    eye = torch.eye(2, dtype=d)
    model = df.LinearGaussianModel(eye, eye, eye, eye, torch.zeros(2, dtype=d), eye)
    ys = torch.zeros(2, 3, 2, dtype=d)
    mask = torch.ones(2, 3, 2, dtype=torch.bool)
    ys[0, 1, 0], mask[0, 1, 0] = float("nan"), False  # unreceived: never read
    clean, _, _, _ = check_sequence_inputs(model, ys, mask=mask)
    assert bool(torch.isfinite(clean).all())
    ys[1, 2, 1] = float("inf")  # received
    with pytest.raises(ValueError, match="ys"):
        check_sequence_inputs(model, ys, mask=mask)
    _, _, folded, skipped = check_sequence_inputs(model, ys, mask=mask, nonfinite="skip")
    assert skipped.tolist() == [0, 1] and not folded[1, 2, 1] and not folded[0, 1, 0]
    assert int(folded.sum()) == 12 - 2


def test_a_rate_may_be_any_real_number_in_the_open_unit_interval():
    import numpy as np

    from difffilter._checks import check_rate

    for value in (0.1, np.float32(0.1), np.float64(0.1), torch.tensor(0.1)):
        assert check_rate(value, "far") == pytest.approx(0.1)
    for bad in (0, 1, 0.0, 1.0, -0.5, 2, True, np.float32(1.0), torch.tensor(0.0), "0.1", None):
        with pytest.raises(ValueError, match=r"far must be a false-alarm rate in \(0, 1\); got"):
            check_rate(bad, "far")
    # a user trial: calibrate(far=None) said "… in (0, 1) or None; got None"
    with pytest.raises(ValueError, match=r"restart must be a false-alarm rate in \(0, 1\) or "
                       r"None; got 2"):  # fmt: skip
        check_rate(2, "restart", unset="None")


def test_an_added_estimator_that_does_not_run_is_named_on_stderr(tmp_path, capsys):
    """A user trial: ``--add-estimators kf`` on the (nonlinear) robot exited 0 with nothing
    said; the reason was only in report.md's "Skipped" line."""
    from difffilter.eval.cli import main

    args = ["robot_actuator_attack", "--runs", "2", "--add-estimators", "kf,zhang_akf",
            "--far", "off", "--no-progress", "--out", str(tmp_path)]  # fmt: skip
    assert main(args) == 0
    err = capsys.readouterr().err
    assert ("note: --add-estimators kf does not run on robot_actuator_attack: needs a linear "
            "model") in err and "zhang" not in err  # fmt: skip


def test_option_errors_name_the_option_and_what_it_takes(tmp_path, capsys):
    """A user trial: ``--seed -1`` said "seed must be …", a misspelled ``--add-estimators``
    listed 52 names without the option or the likely one, and ``--option foo=1`` on LFC did
    not say which keys exist."""
    from difffilter.eval.cli import main

    out = ["--out", str(tmp_path), "--no-progress"]
    assert main(["four_tank_bias", "--seed", "-1", *out]) == 2
    assert "error: --seed must be an integer >= 0; got -1" in capsys.readouterr().err
    assert main(["four_tank_bias", "--add-estimators", "chi_sqare_ekf", *out]) == 2
    assert ("error: --add-estimators: unknown estimator 'chi_sqare_ekf' (did you mean "
            "'chi_square_ekf'?)") in capsys.readouterr().err  # fmt: skip
    # a name like none known: one's own, without the module that registers it (a trial)
    assert main(["four_tank_bias", "--add-estimators", "glr_window_kf", *out]) == 2
    assert ("error: --add-estimators: unknown estimator 'glr_window_kf' (an estimator of your "
            "own is known once the module that registers it is imported: --import MODULE on "
            "the command line)") in capsys.readouterr().err  # fmt: skip
    assert main(["lfc_step", "--option", "foo=1", *out]) == 2
    assert ("unknown lfc option(s) ['foo']; valid: per_channel, per_channel_runs, "
            "per_channel_steps, watermark, watermark_std") in capsys.readouterr().err  # fmt: skip
    assert main(["--list"]) == 0
    assert "also: all (every headline scenario), robustness" in capsys.readouterr().out


def test_the_watermark_study_takes_its_runs_option_and_the_evaluations_rate(monkeypatch, tmp_path):
    """A user trial: the watermark study ran 20 runs at 1 % whatever ``--runs``/``--far``
    said, and no option sized it."""
    from difffilter.eval import watermark
    from difffilter.eval.families import lfc

    seen = []
    monkeypatch.setattr(watermark, "watermark_study", lambda sc, **kw: seen.append(kw))
    monkeypatch.setattr(watermark, "write_watermark", lambda out, study: None)
    common = dict(out=tmp_path, seed=3, checkpoint=None, progress=False)
    lfc._prepare(["lfc_step"], **common, options={"watermark": True, "watermark_runs": 7},
                 far=0.05)  # fmt: skip
    lfc._prepare(["lfc_step"], **common, options={"watermark": True}, far=None)
    assert [(kw["runs"], kw["far"], kw["seed"]) for kw in seen] == [(7, 0.05, 3), (20, 0.01, 3)]
    with pytest.raises(ValueError, match=r"--option watermark_runs: an integer >= 1; got 0"):
        lfc._prepare(["lfc_step"], **common, options={"watermark_runs": 0})
