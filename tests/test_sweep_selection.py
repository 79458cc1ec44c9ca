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
