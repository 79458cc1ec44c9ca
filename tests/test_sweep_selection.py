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
    # an even count: the lower median counted from the best
    assert _median({0: 0.4, 1: 0.1, 2: 0.2, 3: 0.3}, higher_is_better=False) == 2
    assert _median({0: 0.4, 1: 0.1, 2: 0.2, 3: 0.3}, higher_is_better=True) == 3
    # a seed without a score is never the median of three scored ones
    assert _median({0: float("nan"), 1: 0.1, 2: 0.2, 3: 0.3}, higher_is_better=True) == 2


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
    with pytest.raises(ValueError, match="names no validation score.*--select-on test"):
        _validation_scores(cards, config)
