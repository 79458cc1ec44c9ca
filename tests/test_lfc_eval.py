"""LFC evaluation through the one pipeline: schema, family metrics, report, plots,
TensorBoard events, the per-channel validation and the summary."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math

import jsonschema
import pytest
import torch

import difffilter as df
from difffilter.eval.cli import evaluate
from difffilter.eval.report import metrics_schema, write_report
from difffilter.eval.scoring import METRICS
from difffilter.eval.suite import run_suite
from difffilter.models import registry
from difffilter.models.neural_estimator import NeuralFDIEstimator, save_estimator_checkpoint

MAIN = ("kf_nn_ekf", "traditional_ad", "kf_nn_grad", "kf_nn_grad_ekf")


@pytest.fixture(scope="module")
def short_scenario():
    """lfc_simultaneous cut to 3 s (its attack on both areas runs from 0.1 s to 5 s)."""
    sc = dataclasses.replace(
        registry.get("lfc_simultaneous"), name="lfc_simultaneous_3s", duration=3.0, headline=False
    )
    registry.register(sc)
    yield sc
    registry._REGISTRY.pop(sc.name)


@pytest.fixture(scope="module")
def smoke(tmp_path_factory, short_scenario):
    """2 runs with an untrained checkpoint, a 1-run-per-channel validation: plumbing only."""
    out = tmp_path_factory.mktemp("lfc_eval")
    ckpt = out / "net.ckpt"
    net = NeuralFDIEstimator(hidden=4, init="symmetric", init_scale=0.05, seed=1)
    save_estimator_checkpoint(ckpt, net, {"residual_lag": 0, "dt": 0.01})
    options = {"per_channel": True, "per_channel_runs": 1, "per_channel_steps": 150}
    result = evaluate(
        [short_scenario.name],
        ckpt=ckpt,
        runs=2,
        out=out,
        seed=5,
        progress=False,
        family_options=options,
    )
    return out, out / short_scenario.name, result[short_scenario.name]


def test_metrics_json_follows_the_schema_with_the_family_metrics(smoke):
    _, folder, result = smoke
    doc = json.loads((folder / "metrics.json").read_text())
    jsonschema.validate(doc, metrics_schema())
    assert doc["runs"] == 2 and doc["steps"] == 300 and doc["dt_s"] == 0.01
    assert doc["paper"]["proposed_ad"] == pytest.approx(0.133867)
    assert doc["reference"] == "kf_attack_free" and doc["skipped"] == {}
    est = doc["estimators"]
    assert set(registry.get("lfc_simultaneous").estimators) == set(est)
    for name, entry in est.items():
        assert set(METRICS) <= set(entry), name
        assert entry["state5_rmse"] > 0, name
    for name in MAIN:
        e = est[name]
        per_channel = e["attack_rmse_eq43_per_channel"]
        assert set(per_channel) == {"dPtu_1", "dPtu_2"}
        # Scenario III's paper metric: eq. (43) per attacked channel, summed (Table I).
        assert e["attack_rmse_eq43"] == pytest.approx(sum(per_channel.values()))
        # the shared, pooled definition: attacked steps × all ten channels
        assert 0 < e["attack_rmse"] < e["attack_rmse_eq43"]
        assert 0 <= e["tpr"] <= 1 and 0 <= e["fpr"] <= 1
        if name.startswith("kf_nn_grad") and e["detection_delay_steps"] is None:
            continue  # this smoke test's untrained head may never pass p = 0.5
        assert e["detection_delay_s"] == pytest.approx(0.01 * e["detection_delay_steps"])
    assert est["uncompensated"]["attack_rmse"] is None
    assert est["uncompensated"]["attack_rmse_eq43_zero_estimate"] > 0
    assert est["kf_nn_grad"]["auc_prob"] is not None  # the checkpoint's probability head
    assert 0 < est["chi_square_kf"]["tpr"] <= 1 and est["chi_square_kf"]["auc"] > 0.5
    assert result["estimators"]["kf_nn_grad"]["attack_rmse_eq43"] == pytest.approx(
        est["kf_nn_grad"]["attack_rmse_eq43"]
    )


def test_report_plots_tensorboard_and_summary(smoke):
    import PIL.Image
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out, folder, _ = smoke
    report = (folder / "report.md").read_text()
    assert "Table I" in report and "Table II" in report and "0.1339" in report  # paper beside ours
    assert "Per-channel validation" in report and "Hyperparameters chosen" in report
    for png in ("states.png", "rmse_over_time.png", "roc.png", "attack_estimates_run0.png"):
        assert (folder / png).read_bytes()[:4] == b"\x89PNG"
    acc = EventAccumulator(str(folder / "tb"), size_guidance={"scalars": 0, "images": 0})
    acc.Reload()
    assert "state_rmse_per_step/kf_nn_grad" in acc.Tags()["scalars"]
    for tag in ("rmse_over_time", "roc", "attack_estimates_run0"):  # the saved PNG, as saved
        (image,) = acc.Images(tag)
        saved = (folder / f"{tag}.png").read_bytes()
        assert image.encoded_image_string == saved
        assert (image.width, image.height) == PIL.Image.open(io.BytesIO(saved)).size
    assert len(acc.Scalars("state_rmse_per_step/kf_nn_grad")) == 300  # a curve, not a point
    assert len(acc.Scalars("attack_rmse_per_step/kf_nn_grad")) == 300
    summary = (out / "lfc_summary.md").read_text()
    assert "lfc_simultaneous_3s" in summary and "0.1526" in summary  # the paper's mean of I–IV


def test_the_summary_lists_scenarios_i_to_iv_in_the_papers_order(tmp_path):
    """A reviewer matched alphabetical rows to the paper's numerals by hand."""
    from difffilter.eval.families.lfc import _finish

    names = ["lfc_sawtooth", "lfc_simultaneous", "lfc_sine", "lfc_step", "mine"]
    results = {n: {"estimators": {"kf_nn_grad": {"attack_rmse_eq43": i + 1.0}}, "paper": {}}
               for i, n in enumerate(names)}  # fmt: skip
    _finish(results, tmp_path, None)
    rows = [line.split(" | ")[0].lstrip("| ") for line in
            (tmp_path / "lfc_summary.md").read_text().splitlines() if line.startswith("| ")][1:]  # fmt: skip
    assert rows == ["I: lfc_step", "II: lfc_sine", "III: lfc_simultaneous", "IV: lfc_sawtooth",
                    "mine", "mean of I–IV"]  # fmt: skip
    assert "| 2.5 |" in (tmp_path / "lfc_summary.md").read_text()  # (4 + 3 + 2 + 1) / 4


def test_per_channel_validation_files(smoke):
    out, _, _ = smoke
    doc = json.loads((out / "lfc_per_channel" / "metrics.json").read_text())
    jsonschema.validate(doc, metrics_schema())  # a study's own metrics.json follows it too
    table = doc["attack_rmse"]
    expected = {"kf_nn_ekf", "traditional_ad", "kf_nn_gd", "luenberger_nn_ekf", "kf_nn_grad"}
    assert expected | {"zero_estimate"} <= set(table)
    assert all(len(v) == 10 for v in table.values())
    assert (out / "lfc_per_channel" / "per_channel.png").is_file()
    assert "Lowest RMSE per channel" in (out / "lfc_per_channel" / "report.md").read_text()
    assert doc["wall_time_s"] > 0  # its cost, recorded beside its numbers


def test_per_channel_validation_is_opt_in_on_the_cli():
    from difffilter.eval.cli import build_parser

    assert build_parser().parse_args(["lfc_step"]).option == []
    args = build_parser().parse_args(
        ["lfc", "-o", "per_channel=true", "--option", "per_channel_runs=2"]
    )
    assert dict(args.option) == {"per_channel": True, "per_channel_runs": 2}
    with pytest.raises(SystemExit):
        build_parser().parse_args(["lfc", "--option", "per_channel"])
    with pytest.raises(SystemExit):  # a YAML syntax error: a usage error, not a traceback
        build_parser().parse_args(["lfc", "--option", "per_channel=["])


@pytest.mark.parametrize(
    "option, why",
    [
        ("per_channel=maybe", "--option per_channel: true or false"),
        ("per_channel_runs=abc", "--option per_channel_runs: an integer >= 1"),
        ("per_channel_runs=0", "--option per_channel_runs: an integer >= 1"),
        ("watermark_std=abc", "--option watermark_std: a number > 0"),
    ],
)
def test_a_bad_lfc_option_value_is_named_before_any_work(option, why, tmp_path, capsys):
    """Values were read where they were used: a TypeError traceback, "num_runs and steps
    must be >= 1" or "could not convert string to float" (and "maybe" read as true)."""
    from difffilter.eval.cli import main

    argv = ["lfc_step", "--runs", "1", "--out", str(tmp_path), "--no-progress", "--far", "off"]
    switch = [] if option.startswith("per_channel=") else ["-o", "per_channel=true"]
    assert main([*argv, *switch, "-o", option]) == 2
    assert why in capsys.readouterr().err


def test_without_ckpt_the_shipped_checkpoint_is_used_and_recorded(tmp_path):
    sc = dataclasses.replace(registry.get("lfc_step"), duration=0.6)
    result = run_suite(sc, runs=1, progress=False, estimators=("uncompensated", "kf_nn_grad"))
    ckpt = result.checkpoint
    assert ckpt["path"].endswith("checkpoints/lfc_nn_grad.ckpt") and ckpt["used_by"] == [
        "kf_nn_grad"
    ]
    assert ckpt["source"].startswith("shipped default")
    card = json.loads(
        (registry.get("lfc_step").shipped_checkpoint().with_suffix(".json")).read_text()
    )
    assert ckpt["sha256"] == card["sha256"]
    doc = write_report(tmp_path, result)
    assert doc["checkpoint"] == ckpt
    assert "shipped default" in (tmp_path / "report.md").read_text()
    # and on the console, one line per file (a user trial found it only in report.md)
    from difffilter.eval.cli import _say_shipped

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        _say_shipped({"lfc_step": doc, "lfc_sine": doc, "other": {"checkpoint": None}})
    assert out.getvalue() == ("no --ckpt: the shipped checkpoints/lfc_nn_grad.ckpt ran on "
                              "lfc_step (kf_nn_grad); lfc_sine (kf_nn_grad)\n")  # fmt: skip


def test_checkpoint_estimators_are_skipped_and_listed_without_any_checkpoint():
    sc = dataclasses.replace(registry.get("lfc_step"), duration=0.6, checkpoint=None)
    result = run_suite(sc, runs=1, progress=False)
    why = "no checkpoint given (--ckpt; checkpoint= in Python) and no shipped one"
    assert result.skipped == {"kf_nn_grad": why, "kf_nn_grad_ekf": why}
    assert "kf_nn_grad" not in result.outputs and "kf_nn_ekf" in result.outputs
    assert result.checkpoint is None


def test_closed_loops_replay_the_scenario_draws(short_scenario):
    """The uncompensated loop is the trajectory the suite simulated, and the plain Kalman
    filter on its received measurements and inputs is its observer (every residual
    detector reads those innovations)."""
    sc = dataclasses.replace(short_scenario, duration=2.0)
    result = run_suite(sc, runs=3, seed=1, estimators=("uncompensated",), progress=False)
    tr, out = result.traj, result.outputs["uncompensated"]
    own = result.traj_of("uncompensated")  # its own loop's trajectories: the suite's truth
    assert own is not tr and torch.equal(own.x, tr.x) and "x" not in out.extras
    kf = df.kalman_filter(sc.system(), tr.y_recv, tr.us)
    torch.testing.assert_close(kf.means, out.means, rtol=0, atol=1e-10)
    assert torch.equal(tr.flags, (tr.attack != 0).any(-1)) and bool(tr.flags.any())


def test_the_random_attack_scenario_calibrates_its_cusum_on_attack_free_runs():
    """lfc_random_attacks draws its attacks from the 'attack' stream; the CUSUM's calibration
    runs are attack-free and draw from 'plant' and 'schedule' only (it used to fail with a
    KeyError: 'attack'), and they carry no attack."""
    sc = dataclasses.replace(registry.get("lfc_random_attacks"), steps=60)
    gens = {k: torch.Generator().manual_seed(i) for i, k in enumerate(("plant", "schedule"))}
    tr = sc.simulate(3, gens, attack=None)
    assert not tr.flags.any() and torch.equal(tr.y_recv, tr.y_true)
    from difffilter.models.estimators import SuiteContext
    from difffilter.models.streams import Streams

    ctx = SuiteContext(sc, sc.system(), 3, Streams(0), sc.estimator_options())
    assert not ctx.calibration.flags.any()  # what the CUSUM calibrates on


def test_attacked_loops_run_from_the_fork_at_their_onset_are_the_whole_loops(monkeypatch):
    """lfc_step's attacked loops continue their loop without attack from the step before the
    onset (step 299, kept while that loop ran, or on demand for a threat after the loop
    without attack ran without forks): the same estimates and trajectories, bit for bit,
    as loops run from the start (an online learner's ρ, updated in place, included)."""
    import difffilter.models.lfc_estimators as lfc_estimators
    from difffilter.eval.robustness import load_threat_set

    scenario, names = registry.get("lfc_step"), ["kf_nn_ekf", "kf_nn_grad"]
    draws = scenario.exogenous(2, {"plant": torch.Generator().manual_seed(0)})
    assert lfc_estimators._fork_steps(scenario, draws) == [299] == [scenario.attack_onset(draws)]
    assert lfc_estimators._fork_steps(scenario.with_threat(None), draws) == []
    ramp = load_threat_set(scenario, ["ramp"]).threats["ramp"]  # a robustness study's threat

    def suites():  # the loops without attack first (no forks), then the threat's, then its own
        cache = {}
        run_suite(scenario.with_threat(None), runs=2, seed=4, progress=False, estimators=names,
                  cache=cache)  # fmt: skip
        return [run_suite(sc, runs=2, seed=4, progress=False, estimators=names, cache=cache)
                for sc in (scenario.with_threat(ramp), scenario)]  # fmt: skip

    forked = suites()
    monkeypatch.setattr(lfc_estimators, "_least_onset", lambda scenario: math.inf)  # no forks
    whole = suites()
    for a, b in zip(forked, whole):
        for name in names:
            x, y = a.outputs[name], b.outputs[name]
            assert torch.equal(x.means, y.means) and torch.equal(x.attack, y.attack)
            assert torch.equal(x.detection.scores, y.detection.scores)
            for field in ("x", "y_recv", "attack", "flags"):
                assert torch.equal(getattr(a.traj_of(name), field), getattr(b.traj_of(name), field))


class _Watching(df.attack.Attack):
    """0.05 p.u. on the first frequency sensor from step 10; records per loop whether each
    view it got had a score and an alarm (``reads_view`` as given: a plain bias when it
    does not read)."""

    channel = df.attack.Channel.SENSOR

    def __init__(self, reads_view: bool):
        self.reads_view, self.loops = reads_view, []

    def init(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        self.loops.append([])
        return None

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        if view is not None:
            self.loops[-1].append((view.score is not None, view.alarm is not None))
        value = torch.zeros_like(y)
        value[..., 0] = 0.05
        return state, value, torch.full(y.shape[:-1], k >= 10)


def test_an_adaptive_attack_meets_the_gated_filters_in_their_own_loops():
    """A user trial: on LFC the χ²/CUSUM-gated filters were scored on the shared loop, where
    an adaptive attack had read a plain Kalman filter's output (no score, no alarm; an attack
    reading view.score crashed there). Now each runs in a loop of its own: the same numbers
    as on the shared loop when the attack ignores what it reads, and the views of every
    loop hold a score and an alarm. An estimator with no loop of its own is skipped."""
    scenario = registry.get("lfc_step").with_steps(40)
    names = ["chi_square_kf", "cusum_kf", "kf"]
    plain = run_suite(scenario.with_threat(_Watching(False)), runs=2, estimators=names,
                      progress=False)  # fmt: skip
    watching = _Watching(True)
    adaptive = run_suite(scenario.with_threat(watching), runs=2, estimators=names,
                         progress=False)  # fmt: skip
    assert "reads_view" in adaptive.skipped["kf"] and "kf" in plain.outputs
    assert len(watching.loops) == 3  # the shared loop, then each gated filter's own
    assert all(seen == [(True, True)] * 39 for seen in watching.loops)
    for name in ("chi_square_kf", "cusum_kf"):
        mine, shared = adaptive.outputs[name], plain.outputs[name]
        torch.testing.assert_close(mine.means, shared.means, rtol=0, atol=1e-9)
        torch.testing.assert_close(mine.detection.scores, shared.detection.scores, rtol=0,
                                   atol=1e-9)  # fmt: skip
        assert torch.equal(mine.detection.alarms, shared.detection.alarms)
        assert adaptive.metrics[name]["tpr"] == plain.metrics[name]["tpr"]


def test_the_shipped_checkpoint_beside_a_named_one_is_not_said_to_run_without_ckpt():
    """``--ckpt NAME=PATH`` for one estimator leaves the others the shipped checkpoint: the
    console said "no --ckpt: the shipped … ran", though a --ckpt was given (a review)."""
    import contextlib
    import io

    from difffilter.eval.cli import _say_shipped

    sc = dataclasses.replace(registry.get("lfc_step"), duration=0.6)
    shipped = str(sc.shipped_checkpoint())
    result = run_suite(sc, runs=1, progress=False, estimators=("kf_nn_grad",),
                       checkpoint={"kf_nn_grad_ekf": shipped})  # fmt: skip
    assert result.checkpoint["source"] == "shipped default (--ckpt named other estimators only)"
    assert result.checkpoint["used_by"] == ["kf_nn_grad"]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        _say_shipped({"lfc_step": {"checkpoint": result.checkpoint}})
    assert out.getvalue() == ("not named by --ckpt: the shipped checkpoints/lfc_nn_grad.ckpt "
                              "ran on lfc_step (kf_nn_grad)\n")  # fmt: skip


def test_lfc_variants_of_another_rate_or_network_share_no_calibration_or_loop(monkeypatch):
    """A trial: a variant of lfc_step with its own false-alarm rate was handed lfc_step's
    calibration (a CUSUM's τ 16.7 where its own is 12.6), and one with another network
    lfc_step's attack-free loop of ``kf_nn_grad``. The four built-in scenarios still share
    one key (their loops and calibrations), and a loop is kept per checkpoint."""
    import dataclasses
    from types import SimpleNamespace

    from difffilter.models import lfc_estimators, registry

    built_in = {registry.get(n).attack_free_key()
                for n in ("lfc_step", "lfc_sine", "lfc_simultaneous", "lfc_sawtooth")}  # fmt: skip
    assert len(built_in) == 1
    step = registry.get("lfc_step")
    rate = dataclasses.replace(step, name="lfc_step_5pct", false_alarm_rate=0.05)
    net = dataclasses.replace(step, name="lfc_step_other_net", checkpoint="/tmp/other.ckpt")
    assert len({step.attack_free_key(), rate.attack_free_key(), net.attack_free_key()}) == 3

    calls = []

    def fake_loop(ctx, estimator, tr, compensate, attack=None, forks=None, **kw):
        calls.append(ctx.checkpoint)
        return object()

    tr = SimpleNamespace(x=torch.zeros(2, 5, 10), info={})
    cache = {}
    monkeypatch.setattr(lfc_estimators, "_loop", fake_loop)
    monkeypatch.setattr(lfc_estimators, "_fork_steps", lambda scenario, draws: [])
    for name in ("kf_nn_grad", "uncompensated"):
        for ckpt in ("a.ckpt", "b.ckpt", "a.ckpt"):
            ctx = SimpleNamespace(scenario=step, streams=SimpleNamespace(seed=0), cache=cache,
                                  checkpoint=ckpt, checkpoint_for=lambda name, c=ckpt: c,
                                  checkpoint_users=["kf_nn_grad"])  # fmt: skip
            lfc_estimators._attack_free(ctx, name, None, tr, True)
    # the checkpoint's estimator: a loop per network (the third reuses the first's); one
    # that reads none: one loop for all
    assert calls == ["a.ckpt", "b.ckpt", "a.ckpt"]


def test_the_states_figure_names_each_states_own_unit(tmp_path, monkeypatch):
    """The integral of the area control error ACE = β Δf + ΔP_tie (p.u.) is in p.u.·s, not
    p.u. as the figure had it; the unit follows from the model's own row (d x5/dt = β x1 + x4)."""
    from types import SimpleNamespace

    from difffilter.eval.families import lfc as family
    from difffilter.models.lfc import STATE_NAMES, STATE_UNITS, continuous_model

    A, _, _ = continuous_model()
    assert A[4].nonzero().flatten().tolist() == [0, 3]  # ∫ACE: Δf (Hz) × β (p.u./Hz) + ΔP_tie
    assert STATE_NAMES[4] == "ace_int_1" and STATE_UNITS[4] == "p.u.·s"
    assert STATE_UNITS[0] == "Hz" and STATE_UNITS[5:] == STATE_UNITS[:5]
    steps, sc = 20, registry.get("lfc_step")
    run = SimpleNamespace(x=torch.zeros(1, steps, 10), flags=torch.zeros(1, steps, 10, dtype=bool))
    result = SimpleNamespace(outputs=["kf_nn_grad"], scenario=sc, traj=run, traj_of=lambda n: run)
    labels = []
    monkeypatch.setattr(
        family,
        "save_figure",
        lambda fig, *a, **k: labels.extend(ax.get_ylabel() for ax in fig.axes),
    )
    family._states_figure(result, tmp_path)
    assert labels == ["X3: dPtu_1 [p.u.]", "X5: ace_int_1 [p.u.·s]"]
