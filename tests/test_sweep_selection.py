"""How ``difffilter-train sweep`` chooses the seed to ship: the median of the validation
scores the trainings chose their weights by (or of the test's metric under ``--select-on
test``). Fast: no training (the sweep's end-to-end test is in the slow group)."""

from __future__ import annotations

from pathlib import Path

import pytest

from difffilter.train.sweep import _config_monitor, _median, _validation_scores

ROOT = Path(__file__).resolve().parents[1]


def test_the_median_seed_ranks_best_first_and_nan_last():
    assert _median({0: 0.3, 1: 0.1, 2: 0.2}, higher_is_better=False) == 2
    assert _median({0: 0.3, 1: 0.1, 2: 0.2}, higher_is_better=True) == 2
    # an even count: the worse of the two middle seeds, never the best (two seeds shipped
    # the better one)
    assert _median({0: 0.4, 1: 0.1, 2: 0.2, 3: 0.3}, higher_is_better=False) == 3
    assert _median({0: 0.4, 1: 0.1, 2: 0.2, 3: 0.3}, higher_is_better=True) == 2
    assert _median({0: 0.1, 1: 0.2}, higher_is_better=False) == 1
    assert _median({0: 0.1, 1: 0.2}, higher_is_better=True) == 0
    # a seed without a score is never the median of three scored ones
    assert _median({0: float("nan"), 1: 0.1, 2: 0.2, 3: 0.3}, higher_is_better=True) == 2
    assert _median({0: float("nan"), 1: float("nan")}, higher_is_better=True) == 1


def test_the_validation_scores_come_from_the_cards_or_their_config():
    config = ROOT / "train" / "configs" / "lfc.yaml"
    assert _config_monitor(config) == {"metric": "val/attack_rmse", "mode": "min"}
    # cards from before cards recorded their monitor: the config's
    cards = {0: {"best_val_score": 0.5}, 1: {"best_val_score": 0.25}}
    scores, monitor = _validation_scores(cards, config)
    assert scores == {0: 0.5, 1: 0.25} and monitor == {"metric": "val/attack_rmse", "mode": "min"}
    # a card's own monitor wins over the config's
    cards[0] = {"best_val_score": 0.9, "monitor": {"metric": "val/auc", "mode": "max"}}
    with pytest.raises(ValueError, match="chosen by different validation scores"):
        _validation_scores(cards, config)
    cards[0] = {"best_val_score": None}
    # a user trial: with max_epochs 0 the message blamed a monitor the config has
    with pytest.raises(ValueError, match=r"names no validation score .*\(no validation ran "
                       r"before its training stopped .*--select-on test"):  # fmt: skip
        _validation_scores(cards, config)


def test_a_config_without_a_monitored_checkpoint_is_named_as_the_reason(tmp_path):
    bare = tmp_path / "bare.yaml"
    bare.write_text("trainer:\n  max_epochs: 1\n")
    with pytest.raises(ValueError, match=r"ModelCheckpoint has no monitor"):
        _validation_scores({0: {"best_val_score": None}}, bare)


def test_a_sweep_takes_only_its_own_configs_finished_run(tmp_path, monkeypatch):
    """Another config's finished seed in the same --out (a grad network beside the EKF
    config's) was taken as "trained already" and its network reported."""
    from difffilter.train import sweep

    runs = tmp_path / "runs"

    def export_into(name):
        folder = runs / name / "seed_0"
        folder.mkdir(parents=True, exist_ok=True)  # (the sweep made it, for its settings)
        (folder / f"{name}.ckpt").write_bytes(b"")
        (folder / f"{name}.json").write_text("{}")
        return folder / f"{name}.ckpt"

    export_into("four_tank_nn_grad")
    fits = []

    def fake_fit(args):
        fits.append(args)
        export_into("four_tank_nn_ekf")
        return 0

    monkeypatch.setattr("difffilter.train.cli.main", fake_fit)
    ekf = ROOT / "train" / "configs" / "four_tank_ekf.yaml"
    done = sweep._fit(ekf, 0, runs, [], progress=False)
    assert done == runs / "four_tank_nn_ekf" / "seed_0" / "four_tank_nn_ekf.ckpt" and fits
    assert sweep._fit(ekf, 0, runs, [], progress=False) == done and len(fits) == 1  # reused
    renamed = ["--trainer.logger.init_args.name=mine"]
    assert sweep._run_name(ekf, renamed) == "mine"
    assert sweep._run_name(ROOT / "train" / "configs" / "four_tank.yaml", []) == (
        "four_tank_nn_grad"
    )


def test_a_scenario_files_baselines_stay_in_the_folder_and_follow_its_contents(
    tmp_path, monkeypatch
):
    """A training trial: with an absolute scenario path the baselines landed beside the plant
    file (the path replaced the folder), keyed by the path alone, and a later sweep of the
    edited plant, into a new --out, was judged against the old plant's numbers."""
    import torch

    from difffilter.train import sweep

    plant = tmp_path / "plants" / "plant.yaml"
    plant.parent.mkdir()
    plant.write_text("R: 0.1\n")
    computed = []

    def fake(scenario, names, runs, far, progress, **kwargs):
        computed.append(plant.read_text())
        return {"cusum_kf": {"tpr_at_far": len(computed)}}, {"cusum_kf": torch.zeros(2)}

    monkeypatch.setattr(sweep, "_calibrated_metrics", fake)
    monkeypatch.setattr(
        "difffilter.models.registry.get", lambda name: type("S", (), {"estimators": ["cusum_kf"]})
    )
    folder = tmp_path / "out" / "baselines"
    first, _ = sweep._baseline(str(plant), 4, 0.01, False, folder)
    assert sorted(p.name for p in plant.parent.iterdir()) == ["plant.yaml"]  # nothing beside it
    assert (
        len(list(folder.glob("plant-*.json"))) == 1
        and len(list(folder.glob("plant-*.totals.pt"))) == 1
    )
    again, _ = sweep._baseline(str(plant), 4, 0.01, False, folder)
    assert again == first and len(computed) == 1  # the same file: read back
    plant.write_text("R: 0.01\n")
    edited, _ = sweep._baseline(str(plant), 4, 0.01, False, folder)
    assert edited != first and computed == ["R: 0.1\n", "R: 0.01\n"]  # the edited plant: run
    assert sweep._cache_stem("pkg.mod:obj") == "pkg.mod_obj"


def test_a_seed_trained_on_a_scenario_file_is_not_reused_after_the_file_changed(
    tmp_path, monkeypatch
):
    """The same trial: after R was edited in the plant's YAML a sweep into the same --out said
    "seed 0: trained already" and reported the network trained on the old plant; a resume
    across the edit was accepted too."""
    import json

    import torch

    from difffilter.train.lightning_cli import _check_resumed_settings
    from difffilter.train.sweep import _SETTINGS, _check_same_settings, _settings
    from difffilter.train.task import SCENARIO_FILE_DIGEST

    monkeypatch.chdir(tmp_path)
    (tmp_path / "plant.yaml").write_text("R: 0.1\n")
    config = tmp_path / "cfg.yaml"
    config.write_text("model:\n  init_args:\n    scenario: plant.yaml\n")
    folder = tmp_path / "seed_0"
    folder.mkdir()
    before = _settings(config, [])
    assert set(before["scenario_files"]) == {"plant.yaml"}
    (folder / _SETTINGS).write_text(json.dumps(before))
    _check_same_settings(folder, _settings(config, []), 0)  # unchanged: reused
    (tmp_path / "plant.yaml").write_text("R: 0.01\n")
    with pytest.raises(ValueError, match=r"was trained with the scenario file\(s\) plant.yaml as "
                       r"they were \(their contents, or the Python code they name, "
                       r"changed since\)"):  # fmt: skip
        _check_same_settings(folder, _settings(config, []), 0)
    old = {k: v for k, v in before.items() if k != "scenario_files"}  # a sweep before the record
    (folder / _SETTINGS).write_text(json.dumps(old))
    _check_same_settings(folder, _settings(config, []), 0)
    # a file naming Python code, recorded before its digest covered that code (its bytes'
    # sha256): the same file, so reused (a review: every such seed had read as changed)
    import hashlib

    (tmp_path / "sweepplant.py").write_text("def f(x):\n    return x\n")
    (tmp_path / "plant.yaml").write_text("plant:\n  transition: sweepplant:f\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    legacy = {**before, "scenario_files": {
        "plant.yaml": hashlib.sha256((tmp_path / "plant.yaml").read_bytes()).hexdigest()}}  # fmt: skip
    assert legacy["scenario_files"] != _settings(config, [])["scenario_files"]
    (folder / _SETTINGS).write_text(json.dumps(legacy))
    _check_same_settings(folder, _settings(config, []), 0)

    from types import SimpleNamespace

    from difffilter.models.yaml_scenario import scenario_file_digest

    ckpt = tmp_path / "last.ckpt"
    torch.save({"hyper_parameters": {"scenario": "plant.yaml"},
                SCENARIO_FILE_DIGEST: scenario_file_digest("plant.yaml")}, ckpt)  # fmt: skip
    model = SimpleNamespace(hparams={"scenario": "plant.yaml"})
    _check_resumed_settings(str(ckpt), model, None)  # the same bytes: resumes
    (tmp_path / "plant.yaml").write_text("R: 0.001\n")
    with pytest.raises(ValueError, match=r"the scenario file plant.yaml \(its contents changed "
                       r"since the run began\)"):  # fmt: skip
        _check_resumed_settings(str(ckpt), model, None)


def test_a_seed_that_saved_no_last_checkpoint_resumes_from_its_newest(tmp_path):
    """From a review: a seed whose run saved a checkpoint but no last.ckpt (a config without
    save_last, or cut between Lightning's two saves) was refused on every rerun (a new fit
    into a folder holding a run); it resumes from its newest checkpoint."""
    import os

    from difffilter.train.sweep import _newest_checkpoint

    seed = tmp_path / "seed_0"
    assert _newest_checkpoint(seed) is None
    (seed / "checkpoints").mkdir(parents=True)
    older, newer = seed / "checkpoints" / "epoch=1.ckpt", seed / "checkpoints" / "best.ckpt"
    older.write_bytes(b"")
    newer.write_bytes(b"")
    os.utime(older, ns=(1_000_000_000, 1_000_000_000))
    assert _newest_checkpoint(seed) == newer
    (seed / "checkpoints" / "last.ckpt").write_bytes(b"")
    assert _newest_checkpoint(seed) == seed / "checkpoints" / "last.ckpt"
