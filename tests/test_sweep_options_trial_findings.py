"""A sweep's options compared as the command line reads them, and the calibration cache's
key (red-team trials of the command lines and of the evaluation's data, 2026-12-07; each
test failed before its fix)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ORIGINAL = ["--trainer.max_epochs=1", "--data.init_args.batches_per_epoch=2",
            "--data.init_args.val_runs=16"]  # fmt: skip


@pytest.mark.parametrize("now", [
    list(reversed(ORIGINAL)),
    ["--trainer.max_epochs", "1", "--data.init_args.batches_per_epoch", "2",
     "--data.init_args.val_runs=16"],
    ["--trainer.max_epochs=3", *ORIGINAL],  # (the last of a key's settings counts)
])  # fmt: skip
def test_more_seeds_of_the_same_sweep_with_its_options_reordered_or_respelt(tmp_path, now):
    """The same options in another order, or ``--key value`` for ``--key=value``, had been
    refused as another sweep's (exit 2), though ``fit --print_config`` prints the same
    configuration for both."""
    from difffilter.train import sweep

    config = ROOT / "train" / "configs" / "robot.yaml"
    (tmp_path / "sweep.json").write_text(json.dumps({"config": str(config), "options": ORIGINAL}))
    sweep._check_same_sweep(tmp_path, config, now)
    with pytest.raises(ValueError, match="give another --out"):
        sweep._check_same_sweep(tmp_path, config, [*ORIGINAL, "--trainer.max_epochs=2"])
    folder = tmp_path / "seed"
    folder.mkdir()
    (folder / sweep._SETTINGS).write_text(json.dumps(sweep._settings(config, ORIGINAL)))
    sweep._check_same_settings(folder, sweep._settings(config, now), 0)


def test_options_around_a_config_are_compared_as_written():
    """Where a ``--config`` is among the options, what follows it overrides it: its place
    matters, and the lists are compared as written."""
    from difffilter.train.sweep import _same_options

    a = ["--config=x.yaml", "--trainer.max_epochs=1"]
    assert _same_options(a, list(a)) and not _same_options(a, list(reversed(a)))


def test_the_calibration_caches_key_tells_the_scenarios_estimators_from_none(monkeypatch):
    """``estimators=None`` (the scenario's own) and ``[]`` (``add``'s alone) shared a key: one
    calibration answered for the other (1 threshold where there are 11)."""
    from difffilter.eval import calibration as cal

    seen = []

    def fake_run_suite(scenario, **kw):
        seen.append(kw["estimators"])
        raise RuntimeError("stop")  # (the key is made before any work)

    monkeypatch.setattr("difffilter.eval.suite.run_suite", fake_run_suite)
    from difffilter.models import registry

    scenario = registry.get("four_tank_bias")
    cache = {}
    made = cal.Calibration(0.05, 4, 1, {"cusum_ekf": 1.0}, scenario=scenario.attack_free_key())
    key_empty = ("far-calibration", scenario.attack_free_key(), 4, 0, 0.05, (), ("cusum_ekf",),
                 "None", 4)  # fmt: skip
    cache[key_empty] = made
    assert cal.calibrate(scenario, far=0.05, runs=4, seed=0, estimators=[], add=["cusum_ekf"],
                         cache=cache, progress=False) is made  # fmt: skip
    with pytest.raises(RuntimeError, match="stop"):
        cal.calibrate(scenario, far=0.05, runs=4, seed=0, estimators=None, add=["cusum_ekf"],
                      cache=cache, progress=False)  # fmt: skip
    assert seen == [None]


def test_a_run_name_with_the_seed_placeholder_is_the_folder_the_fit_writes(tmp_path):
    # a sweep trial: -- --trainer.logger.init_args.name=net_{seed} trained into net_0/seed_0,
    # and the sweep looked in net_{seed}/seed_0, said the fit exported nothing, and the rerun
    # was refused as a run folder holding a run
    from difffilter.train.sweep import _seed_run

    config = Path(__file__).resolve().parents[1] / "train" / "configs" / "four_tank.yaml"
    folder, options, _ = _seed_run(config, 3, tmp_path / "runs",
                                   ["--trainer.logger.init_args.name=net_{seed}"])  # fmt: skip
    assert folder == tmp_path / "runs" / "net_3" / "seed_3"
    assert options == ["--trainer.logger.init_args.name=net_3"]
