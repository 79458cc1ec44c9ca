"""A mutation review of ``difffilter-train sweep`` (train/sweep.py): the seeds' fit options,
the resume and the refusal of other settings, the summary statistics, the median seed on
validation and on the test, the baselines' cache key and the acceptance, each held against
values worked out by hand from the module docstring on small dicts and folders. Fast: no
training and no evaluation (``_fit``, ``_evaluate`` and the baselines are stand-ins)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import yaml

from difffilter.models import estimators
from difffilter.train import sweep

ROOT = Path(__file__).resolve().parents[1]
MONITORED = (
    "trainer:\n  logger:\n    class_path: lightning.pytorch.loggers.CSVLogger\n"
    "    init_args: {name: net}\n"
    "  callbacks:\n  - class_path: lightning.pytorch.callbacks.EarlyStopping\n"
    "    init_args: {monitor: val/loss}\n"
    "  - class_path: lightning.pytorch.callbacks.ModelCheckpoint\n"
    "    init_args: {monitor: val/auc, mode: max}\n"
)


def _config(tmp_path, text=MONITORED, name="c.yaml"):
    config = tmp_path / name
    config.write_text(text)
    return config


# ---------------------------------------------------------------- one seed's fit


def test_the_training_seed_is_one_plus_ten_times_the_seed():
    """``train_seed = 1 + 10 s`` (the docstring), written out: seed 0 gives the default 1."""
    assert [sweep.train_seed_of(s) for s in range(5)] == [1, 11, 21, 31, 41]


def _fake_fit(monkeypatch, code=0, export=True, checkpoints=False):
    """``cli.main`` replaced: records its arguments and whether the seed's settings were
    written before it ran, and exports ``net.ckpt`` (with its card) into the seed's folder."""
    calls = []

    def fit(args):
        save_dir = Path(next(a for a in args if "save_dir=" in a).split("=", 1)[1])
        folder = save_dir / "net" / "seed_3"
        calls.append({"args": list(args), "settings": (folder / sweep._SETTINGS).is_file()})
        if checkpoints:
            (folder / "checkpoints").mkdir(parents=True, exist_ok=True)
        if export:
            (folder / "net.ckpt").write_bytes(b"")
            (folder / "net.json").write_text("{}")
        return code

    monkeypatch.setattr("difffilter.train.cli.main", fit)
    return calls


def test_a_seeds_fit_gets_its_three_seeds_its_folder_and_the_options(tmp_path, monkeypatch):
    """Seed 3: ``--seed_everything 3``, ``model_seed 3``, ``train_seed 31``, logged into
    ``<runs>/<name>/seed_3``, ``{seed}`` filled in, no progress bar when asked, and the
    settings written (as :func:`_settings` gives them) before the fit runs."""
    calls = _fake_fit(monkeypatch)
    config, runs = _config(tmp_path), tmp_path / "runs"
    extra = ["--model.init_args.init_from=s1/seed_{seed}/e.ckpt"]
    done = sweep._fit(config, 3, runs, extra, progress=False)
    assert done == runs / "net" / "seed_3" / "net.ckpt"
    args = calls[0]["args"]
    for expected in ("--seed_everything=3", "--model.init_args.model_seed=3",
                     "--data.init_args.train_seed=31", f"--trainer.logger.init_args.save_dir={runs}",
                     "--trainer.logger.init_args.version=seed_3",
                     "--trainer.enable_progress_bar=false",
                     "--model.init_args.init_from=s1/seed_3/e.ckpt"):  # fmt: skip
        assert expected in args
    assert "--ckpt_path" not in args and calls[0]["settings"]
    written = json.loads((runs / "net" / "seed_3" / sweep._SETTINGS).read_text())
    assert written["options"] == ["--model.init_args.init_from=s1/seed_3/e.ckpt"]
    assert written["config"] == yaml.safe_load(MONITORED)  # the config's values, read
    assert written["config_file"] == str(config)
    # with progress bars: the option is left out
    (runs / "net" / "seed_3" / "net.ckpt").unlink()
    sweep._fit(config, 3, runs, extra, progress=True)
    assert "--trainer.enable_progress_bar=false" not in calls[1]["args"]


def test_an_interrupted_seed_resumes_from_its_last_checkpoint(tmp_path, monkeypatch):
    """A seed folder with ``checkpoints/last.ckpt`` and no export: fit is given
    ``--ckpt_path <last.ckpt>`` (the docstring's resume)."""
    calls = _fake_fit(monkeypatch)
    config, runs = _config(tmp_path), tmp_path / "runs"
    last = runs / "net" / "seed_3" / "checkpoints" / "last.ckpt"
    last.parent.mkdir(parents=True)
    last.write_bytes(b"")
    sweep._fit(config, 3, runs, [], progress=False)
    args = calls[0]["args"]
    assert args[args.index("--ckpt_path") + 1] == str(last)


def test_a_failed_fit_that_saved_checkpoints_keeps_its_settings(tmp_path, monkeypatch):
    """A fit that failed after saving a checkpoint is a run to resume: its settings stay
    (only a fit that trained nothing forgets them)."""
    _fake_fit(monkeypatch, code=1, export=False, checkpoints=True)
    config, runs = _config(tmp_path), tmp_path / "runs"
    with pytest.raises(ValueError, match="seed 3: difffilter-train fit failed"):
        sweep._fit(config, 3, runs, [], progress=False)
    assert (runs / "net" / "seed_3" / sweep._SETTINGS).is_file()


def test_an_export_is_a_checkpoint_with_its_card(tmp_path):
    """``_exported``: a ``.ckpt`` without its ``.json`` card beside it is no export."""
    (tmp_path / "a.ckpt").write_bytes(b"")
    assert sweep._exported(tmp_path) is None
    (tmp_path / "b.ckpt").write_bytes(b"")
    (tmp_path / "b.json").write_text("{}")
    assert sweep._exported(tmp_path) == tmp_path / "b.ckpt"


# ---------------------------------------------------------------- settings


def test_the_settings_name_every_scenario_file_of_the_config_and_the_options(tmp_path, monkeypatch):
    """The YAML files named in the config (in a list too) and in the options after ``--``."""
    monkeypatch.chdir(tmp_path)
    for name in ("a.yaml", "b.yaml", "c.yaml"):
        (tmp_path / name).write_text(f"{name}: 1\n")
    config = _config(tmp_path, "data:\n  init_args:\n    scenarios: [a.yaml, b.yaml]\n")
    found = sweep._settings(config, ["--model.init_args.scenario=c.yaml"])
    assert set(found["scenario_files"]) == {"a.yaml", "b.yaml", "c.yaml"}


def test_a_seed_folder_of_other_config_values_or_options_is_refused(tmp_path):
    """A folder trained with other config values, or other options, is refused; a comment
    edited in the config is no change."""
    config = _config(tmp_path, "trainer:\n  max_epochs: 2\n")
    folder = tmp_path / "seed_0"
    folder.mkdir()
    (folder / sweep._SETTINGS).write_text(json.dumps(sweep._settings(config, ["--x=1"])))
    config.write_text("# a comment\ntrainer:\n  max_epochs: 2\n")
    sweep._check_same_settings(folder, sweep._settings(config, ["--x=1"]), 0)
    with pytest.raises(ValueError, match=r"trained with the options \['--x=1'\]"):
        sweep._check_same_settings(folder, sweep._settings(config, ["--x=2"]), 0)
    config.write_text("trainer:\n  max_epochs: 3\n")
    with pytest.raises(ValueError, match=r"trained with the config .*c.yaml's values"):
        sweep._check_same_settings(folder, sweep._settings(config, ["--x=1"]), 0)


def test_the_same_config_by_another_path_is_the_same_sweep(tmp_path, monkeypatch):
    """``--out``'s sweep.json names the config by a relative path; the same file by its
    absolute path is the same sweep (more seeds are welcome)."""
    monkeypatch.chdir(tmp_path)
    config = _config(tmp_path)
    (tmp_path / "sweep.json").write_text(json.dumps({"config": "c.yaml", "options": []}))
    sweep._check_same_sweep(tmp_path, config.resolve(), [])


def test_the_monitor_is_the_model_checkpoints_not_another_callbacks(tmp_path):
    """An EarlyStopping callback's monitor before the ModelCheckpoint is not the score the
    weights were chosen by."""
    assert sweep._config_monitor(_config(tmp_path)) == {"metric": "val/auc", "mode": "max"}


def test_a_scenario_override_or_the_validation_only_run_skips_the_family_check(tmp_path):
    """``--scenarios`` of another family are refused before training, unless the options
    set the training scenario, or nothing is run on the test (``--validation-only``)."""
    config = ROOT / "train" / "configs" / "four_tank.yaml"
    check = sweep._check_before_training
    with pytest.raises(ValueError, match="lfc_step is a lfc scenario"):
        check(config, tmp_path / "o", ["lfc_step"], None, True, [])
    check(config, tmp_path / "o", ["lfc_step"], None, True, ["--model.init_args.scenario=lfc_step"])
    check(config, tmp_path / "o", ["lfc_step"], None, False, [])
    with pytest.raises(ValueError, match="--runs must be an integer >= 1; got True"):
        check(config, tmp_path / "o", None, True, True, [])


# ---------------------------------------------------------------- statistics


def test_the_summary_is_mean_min_max_and_spread_over_the_seeds_that_have_the_metric():
    """By hand: auc 0.5, 0.9, 0.6 give mean 2/3, min 0.5, max 0.9, spread 0.4; fpr 0.02,
    None, 0.04 give mean 0.03 and spread 0.02 over the two seeds that have it; a metric no
    seed has (attack_rmse, listed first) is left out and the metrics after it are kept."""
    rows = [{"attack_rmse": None, "auc": 0.5, "fpr": 0.02},
            {"attack_rmse": None, "auc": 0.9, "fpr": None},
            {"attack_rmse": None, "auc": 0.6, "fpr": 0.04}]  # fmt: skip
    per_seed = {s: {"scenarios": {"sc": row}} for s, row in enumerate(rows)}
    summary = sweep._summary(per_seed)["sc"]
    assert set(summary) == {"auc", "fpr"}
    auc, fpr = summary["auc"], summary["fpr"]
    assert math.isclose(auc["mean"], 2 / 3, rel_tol=1e-12)
    assert (auc["min"], auc["max"]) == (0.5, 0.9)
    assert math.isclose(auc["spread"], 0.4, rel_tol=1e-12)
    assert math.isclose(fpr["mean"], 0.03, rel_tol=1e-12)
    assert (fpr["min"], fpr["max"]) == (0.02, 0.04)
    assert math.isclose(fpr["spread"], 0.02, rel_tol=1e-12)


def test_the_test_score_is_the_mean_over_the_scenarios_that_have_it():
    """Seed 0: (0.6 + 0.8) / 2 = 0.7 over two scenarios; seed 1: 0.9, its second None."""
    per_seed = {0: {"scenarios": {"a": {"tpr_at_far": 0.6}, "b": {"tpr_at_far": 0.8}}},
                1: {"scenarios": {"a": {"tpr_at_far": 0.9}, "b": {"tpr_at_far": None}}}}  # fmt: skip
    scores = sweep._test_scores(per_seed, "tpr_at_far")
    assert math.isclose(scores[0], 0.7, rel_tol=1e-12) and scores[1] == 0.9


def test_a_seed_without_a_score_is_never_ranked_among_scored_ones():
    """{0: 0.1, 1: NaN, 2: 0.2}: only seeds 0 and 2 are ranked; of two the worse middle is
    seed 0 when higher is better (2, 0) and seed 2 when lower is (0, 2): never the NaN one."""
    scores = {0: 0.1, 1: float("nan"), 2: 0.2}
    assert sweep._median(scores, higher_is_better=True) == 0
    assert sweep._median(scores, higher_is_better=False) == 2


# ---------------------------------------------------------------- the sweep, stand-ins


def _stubbed(monkeypatch, tmp_path, val, metric_of=None):
    """``_fit`` exports ``s<seed>.ckpt`` with a card of best_val_score ``val[seed]`` (the
    val/auc monitor, max); ``_evaluate`` gives ``metric_of(seed)`` on one scenario ``s``."""
    fits = []

    def fit(config, seed, runs_dir, extra, progress=True):
        fits.append(seed)
        path = tmp_path / f"s{seed}.ckpt"
        path.write_text("x")
        card = {"best_val_score": val[seed], "monitor": {"metric": "val/auc", "mode": "max"}}
        path.with_suffix(".json").write_text(json.dumps(card))
        return path

    def evaluate(path, scenarios, runs, far, progress):
        seed = int(path.stem[1:])
        row = dict.fromkeys(sweep.METRICS, 0.5) | (metric_of(seed) if metric_of else {})
        return {"estimator": "e", "scenarios": {"s": row}}, {"s": {}}

    monkeypatch.setattr(sweep, "_fit", fit)
    monkeypatch.setattr(sweep, "_evaluate", evaluate)
    monkeypatch.setattr(sweep, "_scenarios_of", lambda path, scenarios: ("e", ["s"]))
    monkeypatch.setattr(sweep, "_baseline", lambda *a, **k: ({}, {}))
    monkeypatch.setattr(sweep, "_acceptance", lambda *a, **k: {})
    return fits


def test_the_median_on_validation_of_four_seeds_is_the_worse_middle_one(tmp_path, monkeypatch):
    """val/auc (max) 0.9, 0.6, 0.8, 0.7 for seeds 0..3: best first 0, 2, 3, 1; the worse of
    the two middle ones is seed 3 (0.7), and its checkpoint is the one named."""
    _stubbed(monkeypatch, tmp_path, {0: 0.9, 1: 0.6, 2: 0.8, 3: 0.7})
    doc = sweep.sweep(_config(tmp_path), seeds=(0, 1, 2, 3), out=tmp_path / "out",
                      progress=False, test=False)  # fmt: skip
    assert doc["median_seed"] == 3
    assert doc["median_checkpoint"] == str(tmp_path / "s3.ckpt")
    assert doc["selection"]["scores"] == {"0": 0.9, "1": 0.6, "2": 0.8, "3": 0.7}


def test_the_median_on_the_test_follows_the_metrics_direction(tmp_path, monkeypatch):
    """--select-on test by fpr_at_far_after_attack (lower is better): 0.1 and 0.3 rank
    seed 0 then seed 1, and the worse middle of two is seed 1; by tpr_at_far (higher is
    better) 0.1 and 0.3 name seed 0."""
    rate = {0: 0.1, 1: 0.3}
    _stubbed(monkeypatch, tmp_path, {0: 0.5, 1: 0.5},
             lambda s: {"fpr_at_far_after_attack": rate[s], "tpr_at_far": rate[s]})  # fmt: skip
    config = _config(tmp_path)
    doc = sweep.sweep(config, seeds=(0, 1), out=tmp_path / "a", select_on="test",
                      rank_by="fpr_at_far_after_attack", progress=False)  # fmt: skip
    assert doc["median_seed"] == 1
    doc = sweep.sweep(config, seeds=(0, 1), out=tmp_path / "b", select_on="test",
                      rank_by="tpr_at_far", progress=False)  # fmt: skip
    assert doc["median_seed"] == 0


def test_the_sweeps_options_are_checked_before_any_training(tmp_path, monkeypatch):
    """Seeds must be distinct integers >= 0 (0 allowed), --far in (0, 1) open, a config
    without a monitor is accepted when the options add callbacks, and a seed folder of
    other settings is refused before the first seed trains, whichever seed it is."""
    fits = _stubbed(monkeypatch, tmp_path, {0: 0.5, 1: 0.5, 2: 0.5})
    config = _config(tmp_path)
    with pytest.raises(ValueError, match="--seeds must be distinct integers >= 0"):
        sweep.sweep(config, seeds=(-1, 1), out=tmp_path / "o", progress=False, test=False)
    for far in (0.0, 1.0):
        with pytest.raises(ValueError, match="--far must lie in"):
            sweep.sweep(config, seeds=(0,), out=tmp_path / "o", far=far, progress=False)
    assert not fits
    bare = _config(tmp_path, "trainer:\n  max_epochs: 1\n", "bare.yaml")
    doc = sweep.sweep(bare, seeds=(0, 1, 2), out=tmp_path / "bare", progress=False, test=False,
                      extra=["--trainer.callbacks+=ModelCheckpoint"])  # fmt: skip
    assert doc["median_seed"] in (0, 1, 2) and fits == [0, 1, 2]
    # seed 1's folder holds another option's run: refused before seed 0 trains
    out = tmp_path / "held"
    folder, _, settings = sweep._seed_run(config, 1, out / "runs", ["--x=1"])
    folder.mkdir(parents=True)
    (folder / sweep._SETTINGS).write_text(json.dumps({**settings, "options": ["--x=2"]}))
    fits.clear()
    with pytest.raises(ValueError, match="seed 1: .*seed_1 was trained with the options"):
        sweep.sweep(config, seeds=(0, 1), out=out, progress=False, test=False, extra=["--x=1"])
    assert not fits


def test_the_command_passes_only_the_options_after_the_double_dash(tmp_path, monkeypatch):
    """``main``: what follows ``--`` goes to every seed's fit, without the ``--`` itself."""
    seen = {}

    def fake_sweep(config, seeds, out, **kwargs):
        seen.update(kwargs, seeds=seeds)
        Path(out).mkdir()
        (Path(out) / "sweep.md").write_text("")
        return {"median_seed": 0, "median_checkpoint": "x"}

    monkeypatch.setattr(sweep, "sweep", fake_sweep)
    args = ["--config", "c.yaml", "--seeds", "4", "5", "--out", str(tmp_path / "o"), "--",
            "--trainer.max_epochs=1"]  # fmt: skip
    assert sweep.main(args) == 0
    assert seen["extra"] == ["--trainer.max_epochs=1"] and seen["seeds"] == [4, 5]


def test_a_seeds_estimator_must_run_on_every_scenario_it_is_judged_on(monkeypatch):
    """``_evaluate`` asks each scenario's study for the checkpoint with ``required=True`` (a
    learned checkpoint that did not run is an error naming why, never a row left out)."""
    seen = []

    def calibrated_metrics(scenario, names, runs, far, progress, checkpoint=None, required=False):
        seen.append((scenario.name, names, required, checkpoint))
        return {names[0]: {"auc": 0.5}}, {names[0]: {"x": 0}}

    monkeypatch.setattr(sweep, "_calibrated_metrics", calibrated_metrics)
    monkeypatch.setattr(sweep, "_scenarios_of", lambda path, sc: ("e", ["four_tank_bias"]))
    table, totals = sweep._evaluate(Path("s.ckpt"), None, 2, 0.01, False)
    assert seen == [("four_tank_bias", ["e"], True, {"e": "s.ckpt"})]
    assert table == {"estimator": "e", "scenarios": {"four_tank_bias": {"auc": 0.5}}}
    assert totals == {"four_tank_bias": {"x": 0}}


# ---------------------------------------------------------------- baselines


def test_the_baselines_are_cached_per_run_count_and_rerun_without_their_totals(
    tmp_path, monkeypatch
):
    """The cache key holds the runs: 3 then 5 runs compute twice, 3 again reads back; a
    cached table whose ``.totals.pt`` is gone is computed again, not half read."""
    computed = []

    def calibrated_metrics(scenario, names, runs, far, progress, checkpoint=None):
        assert names and all(estimators.get(n).role == "analytic" for n in names)
        computed.append(runs)
        return {"kf": {"runs_seen": runs}}, {}

    monkeypatch.setattr(sweep, "_calibrated_metrics", calibrated_metrics)
    folder = tmp_path / "baselines"
    assert sweep._baseline("four_tank_bias", 3, 0.01, False, folder)[0] == {"kf": {"runs_seen": 3}}
    assert sweep._baseline("four_tank_bias", 5, 0.01, False, folder)[0] == {"kf": {"runs_seen": 5}}
    assert sweep._baseline("four_tank_bias", 5, 0.01, False, folder)[0] == {"kf": {"runs_seen": 5}}
    assert computed == [3, 5]
    (folder / "four_tank_bias.totals.pt").unlink()
    assert sweep._baseline("four_tank_bias", 5, 0.01, False, folder)[0] == {"kf": {"runs_seen": 5}}
    assert computed == [3, 5, 5]


def test_two_plant_files_of_one_name_keep_their_own_baselines(tmp_path, monkeypatch):
    """``plant.yaml`` in two folders, named by the same relative path from each: each keeps
    its own cached baselines (the stem's digest is of the absolute path), so going back to
    the first reads its numbers again instead of computing them a third time."""
    computed = []

    def calibrated_metrics(scenario, names, runs, far, progress, checkpoint=None):
        computed.append(Path("plant.yaml").read_text())
        return {"kf": {"n": len(computed)}}, {}

    monkeypatch.setattr(sweep, "_calibrated_metrics", calibrated_metrics)
    monkeypatch.setattr(
        "difffilter.models.registry.get", lambda name: type("S", (), {"estimators": ["cusum_kf"]})
    )
    folder = tmp_path / "baselines"
    for where in ("a", "b"):
        (tmp_path / where).mkdir()
        (tmp_path / where / "plant.yaml").write_text(f"R: {where}\n")
    found = []
    for where in ("a", "b", "a"):
        monkeypatch.chdir(tmp_path / where)
        found.append(sweep._baseline("plant.yaml", 3, 0.01, False, folder)[0])
    assert computed == ["R: a\n", "R: b\n"] and found[0] == found[2] == {"kf": {"n": 1}}


# ---------------------------------------------------------------- acceptance


def test_each_seed_is_held_against_the_best_analytic_by_hand(monkeypatch):
    """Analytic cusum_kf (TPR 0.90, state 1.0) and cusum_ekf (TPR 0.80, state 0.8), no
    rmse_p: the state metric is state_rmse, the best TPR 0.90 (cusum_kf), the best state 0.8
    (cusum_ekf), no attack check (no analytic attack estimate). Seed 0
    (TPR 0.895 >= 0.89, state 0.82 <= 0.84, false alarms 1 % in [0.5 %, 2 %]) holds every
    check; seed 1 (state 0.9 > 0.84) fails one, so it does not hold."""
    import torch

    seen = []

    def intervals(totals, role, *, far, seed, runs, state_metric):
        seen.append((runs, state_metric, role))
        return {"estimators": {"learned": {"tpr_at_far": {"holds_share": 1.0}}}}

    monkeypatch.setattr("difffilter.eval.intervals.checks_intervals", intervals)
    table = {"cusum_kf": {"tpr_at_far": 0.90, "state_rmse": 1.0},
             "cusum_ekf": {"tpr_at_far": 0.80, "state_rmse": 0.8}}  # fmt: skip
    per_seed = {0: {"scenarios": {"sc": {"tpr_at_far": 0.895, "state_rmse": 0.82,
                                         "fpr_at_far": 0.01}}},
                1: {"scenarios": {"sc": {"tpr_at_far": 0.95, "state_rmse": 0.9,
                                         "fpr_at_far": 0.01}}}}  # fmt: skip
    totals = {"cusum_kf": {"x": torch.zeros(6, 3)}, "cusum_ekf": {"x": torch.zeros(6, 3)}}
    seed_totals = {s: {"sc": {"x": torch.zeros(6, 3)}} for s in (0, 1)}
    out = sweep._acceptance(per_seed, {"sc": (table, totals)}, 0.01, seed_totals)["sc"]
    assert out["state_metric"] == "state_rmse"
    assert out["best_analytic"]["tpr_at_far"] == {"value": 0.90, "estimator": "cusum_kf"}
    assert out["best_analytic"]["state_rmse"] == {"value": 0.8, "estimator": "cusum_ekf"}
    held = {s: {c["metric"]: c["holds"] for c in cs} for s, cs in out["checks"].items()}
    assert held == {"0": {"tpr_at_far": True, "state_rmse": True, "fpr_at_far": True},
                    "1": {"tpr_at_far": True, "state_rmse": False, "fpr_at_far": True}}  # fmt: skip
    assert out["holds"] == {"0": True, "1": False}
    role = {"cusum_kf": "analytic", "cusum_ekf": "analytic", "learned": "learned"}
    assert seen == [(6, "state_rmse", role)] * 2  # runs: the totals' first dimension
    assert out["intervals"]["0"] == {"tpr_at_far": {"holds_share": 1.0}}
    # analytic rows reporting rmse_p where a seed's row does not: the state metric is
    # state_rmse over every row, and the best analytic is taken on it too (the analytic rows
    # alone chose rmse_p: no best state, and every seed's state check failed; a review)
    for row, p in zip(table.values(), (0.5, 0.6)):
        row["rmse_p"] = p
    out = sweep._acceptance(per_seed, {"sc": (table, totals)}, 0.01, seed_totals)["sc"]
    assert out["state_metric"] == "state_rmse"
    assert out["best_analytic"]["state_rmse"] == {"value": 0.8, "estimator": "cusum_ekf"}
    assert out["holds"] == {"0": True, "1": False}


# ---------------------------------------------------------------- sweep.md


def _doc():
    per_seed = {"0": {"checkpoint": "s0.ckpt", "scenarios": {"sc": {"auc": 0.5}}},
                "1": {"checkpoint": "s1.ckpt", "scenarios": {"sc": {"auc": 0.9}}}}  # fmt: skip
    check = {"metric": "tpr_at_far", "value": 0.9, "bound": "≥", "best": 0.9,
             "best_estimator": "kf", "holds": True}  # fmt: skip
    accept = {"a": {"checks": {"0": [check], "1": [check]}, "holds": {"0": True, "1": True}},
              "b": {"checks": {"0": [check], "1": [check]}, "holds": {"0": True, "1": False}}}  # fmt: skip
    return {
        "config": "c.yaml", "seeds": [0, 1], "eval_seed": 0, "far": 0.01, "rank_by": "auc",
        "select_on": "validation", "median_seed": 1, "median_checkpoint": "s1.ckpt",
        "selection": {"monitor": {"metric": "val/auc", "mode": "max"},
                      "scores": {"0": 0.9, "1": 0.8}, "median_seed_by_test": 0},
        "per_seed": per_seed, "acceptance": accept,
        "summary": {"sc": {"auc": {"mean": 0.7, "min": 0.5, "max": 0.9, "spread": 0.4}}},
    }  # fmt: skip


def test_the_markdown_says_the_spread_the_direction_the_tests_choice_and_the_verdict():
    """The row's last cell is the spread (0.4, not the max 0.9); val/auc with mode max is
    "higher is better"; the test's seed 0 differs from the median 1, so it is named; the
    median seed fails scenario b, so it "does not hold every row"."""
    text = sweep._markdown(_doc())
    assert "| sc | auc | 0.5 | 0.9 | 0.7 | 0.4 |" in text
    assert "(val/auc, higher is better;" in text
    assert "would name seed 0." in text
    assert "The median seed 1 does not hold every row." in text


def test_a_seeds_folder_is_where_lightnings_logger_writes_for_every_run_name(tmp_path):
    """The sweep's ``<runs>/<name>/seed_<s>`` against TensorBoardLogger's own ``log_dir``:
    a name given, the config's, Lightning's default, and a name of ``""`` or ``null`` (the
    review's case: read as the config's name, the sweep wrote its settings into one folder
    while the fit logged into ``<runs>/seed_<s>``, then said it exported nothing)."""
    from lightning.pytorch.loggers import TensorBoardLogger

    def config(logger) -> Path:
        path = tmp_path / f"c{len(list(tmp_path.iterdir()))}.yaml"
        path.write_text(yaml.safe_dump({"trainer": {} if logger is None else {"logger": logger}}))
        return path

    named = config({"class_path": "x", "init_args": {"name": "mine"}})
    null = config({"class_path": "x", "init_args": {"name": None}})
    cases = [
        (named, [], "mine"),
        (named, ["--trainer.logger.init_args.name=other"], "other"),
        (named, ["--trainer.logger.init_args.name="], ""),
        (named, ["--trainer.logger.init_args.name=null"], None),
        (null, [], None),
        (config({"class_path": "x", "init_args": {}}), [], "lightning_logs"),
        (config(None), [], "lightning_logs"),
    ]
    runs = tmp_path / "runs"
    for path, extra, lightning_name in cases:
        want = TensorBoardLogger(save_dir=str(runs), name=lightning_name, version="seed_3").log_dir
        assert runs / sweep._run_name(path, extra) / "seed_3" == Path(want), (path, extra)


# ---------------------------------------------------------------- a config among the options


def _print_config(args: list[str]) -> dict:
    """The settings ``difffilter-train`` itself makes of ``args`` (``--print_config``)."""
    import contextlib
    import io

    from difffilter.train.cli import main as cli_main

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed), pytest.raises(SystemExit):
        cli_main([*args, "--print_config"])
    return yaml.safe_load(printed.getvalue())


def test_a_config_among_the_options_names_the_folder_the_fit_logs_into(tmp_path, monkeypatch):
    """``-- --config second.yaml`` whose logger has a name of its own: the seed's folder the
    sweep looks in is the one the fit logs into, as the training CLI itself reads the
    arguments the sweep gives it (``--print_config``, then TensorBoardLogger's ``log_dir``).
    Read from the sweep's config alone, the sweep had looked in ``four_tank_nn_grad/`` and
    said the fit exported nothing; the space-separated form of an option too."""
    from lightning.pytorch.loggers import TensorBoardLogger

    config = ROOT / "train" / "configs" / "four_tank.yaml"
    second = _config(
        tmp_path, "trainer:\n  logger:\n    init_args: {name: second_name}\n", "s.yaml"
    )
    renamed = ["--trainer.logger.init_args.name", "third_name"]
    runs, calls = tmp_path / "runs", []
    for extra, name in (([], "four_tank_nn_grad"), (["--config", str(second)], "second_name"),
                        ([f"--config={second}", *renamed], "third_name"),
                        ([*renamed, "--config", str(second)], "second_name")):  # fmt: skip
        monkeypatch.setattr("difffilter.train.cli.main", lambda args: calls.append(args) or 1)
        with pytest.raises(ValueError, match="fit failed"):
            sweep._fit(config, 3, runs, extra, progress=False)
        monkeypatch.undo()
        logger = _print_config(calls[-1])["trainer"]["logger"]["init_args"]
        fit_dir = TensorBoardLogger(logger["save_dir"], logger["name"], logger["version"]).log_dir
        assert logger["name"] == name
        assert sweep._seed_run(config, 3, runs, extra)[0] == Path(fit_dir), extra


def test_an_edited_config_among_the_options_is_other_settings(tmp_path):
    """A threat distribution given as ``-- --config threats.yaml`` and edited since a seed
    was trained is other settings (the seed is not taken as trained already); the same
    file unedited, or by the ``--config=`` spelling, is the same; a folder recorded before
    the option configs were is judged on the rest."""
    config = _config(tmp_path, "trainer:\n  max_epochs: 2\n")
    threats = _config(tmp_path, "data:\n  init_args: {threats: {own: 1.0}}\n", "threats.yaml")
    folder = tmp_path / "seed_0"
    folder.mkdir()
    options = ["--config", str(threats)]
    (folder / sweep._SETTINGS).write_text(json.dumps(sweep._settings(config, options)))
    sweep._check_same_settings(folder, sweep._settings(config, options), 0)
    threats.write_text("data:\n  init_args: {threats: {own: 0.5, none: 0.5}}\n")
    for now in (options, [f"--config={threats}"]):
        with pytest.raises(ValueError, match=r"threats.yaml' values as they were"):
            sweep._check_same_settings(folder, sweep._settings(config, now), 0)
    recorded = sweep._settings(config, options)
    del recorded["option_configs"]
    (folder / sweep._SETTINGS).write_text(json.dumps(recorded))
    sweep._check_same_settings(folder, sweep._settings(config, options), 0)


def test_the_family_check_reads_the_training_scenario_a_config_among_the_options_sets(tmp_path):
    """``--scenarios`` are held against the scenario the fit will train on: one a second
    config sets (a config of the LFC family after four_tank.yaml accepts LFC scenarios and
    refuses the four-tank's), and the ``--scenario`` shortcut and the space-separated form
    as well; an option on a scenario it cannot read skips the check."""
    config = ROOT / "train" / "configs" / "four_tank.yaml"
    lfc = _config(tmp_path, "model:\n  init_args: {scenario: lfc_step}\n", "lfc.yaml")
    check = sweep._check_before_training
    out = tmp_path / "o"
    for extra in (["--config", str(lfc)], ["--scenario", "lfc_step"],
                  ["--model.init_args.scenario", "lfc_sine"]):  # fmt: skip
        check(config, out, ["lfc_step"], None, True, extra)
        with pytest.raises(ValueError, match="four_tank_bias is a four_tank scenario"):
            check(config, out, ["four_tank_bias"], None, True, extra)
    with pytest.raises(ValueError, match="lfc_step is a lfc scenario"):
        check(config, out, ["lfc_step"], None, True, ["--config", str(config)])
    check(config, out, ["lfc_step"], None, True, ["--data.init_args.scenario_weights=1"])


def test_a_config_among_the_options_may_bring_the_checkpoint_monitor(tmp_path):
    """A config without a ModelCheckpoint monitor is refused for ``--select-on validation``
    before training, unless a config among the options brings callbacks of its own (the
    run gets past that check to the next, ``--runs``, here)."""
    bare = _config(tmp_path, "trainer:\n  max_epochs: 1\n", "bare.yaml")
    monitored = _config(tmp_path)
    out = tmp_path / "sw"
    with pytest.raises(ValueError, match="has no ModelCheckpoint monitor"):
        sweep.sweep(bare, [0], out, runs=0)
    with pytest.raises(ValueError, match="--runs must be an integer >= 1"):
        sweep.sweep(bare, [0], out, runs=0, extra=["--config", str(monitored)])
    assert not out.exists()


def test_an_infinite_metric_makes_the_summary_unknown_and_names_its_seeds():
    """Two seeds at inf had made the spread NaN (inf − inf), named no seed, and written bare
    ``Infinity`` and ``NaN`` into sweep.json (a trial of the sweep's statistics)."""
    per_seed = {seed: {"scenarios": {"sc": {"state_rmse": value}}}
                for seed, value in ((0, math.inf), (1, math.inf), (2, 0.11))}  # fmt: skip
    entry = sweep._summary(per_seed)["sc"]["state_rmse"]
    assert entry == {"mean": None, "min": None, "max": None, "spread": None, "not_a_number": [0, 1]}
    json.dumps(entry, allow_nan=False)
