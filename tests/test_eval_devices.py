"""``difffilter-eval --devices 2``: two processes share the estimators, same metrics."""

from __future__ import annotations

import json

from difffilter.eval.cli import main


def _without_times(value):
    if isinstance(value, dict):
        return {k: _without_times(v) for k, v in value.items() if "time" not in k}
    if isinstance(value, list):
        return [_without_times(v) for v in value]
    return value


def test_two_processes_give_the_metrics_of_one(tmp_path):
    # the plain filters of four_tank_filters: five estimators (two particle filters on the
    # named random streams), no family studies, so the processes' start-up dominates
    args = ["four_tank_filters", "--runs", "3", "--seed", "3", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "one")]) == 0
    assert main([*args, "--out", str(tmp_path / "two"), "--devices", "2"]) == 0
    one, two = (
        json.loads((tmp_path / d / "four_tank_filters" / "metrics.json").read_text())
        for d in ("one", "two")
    )
    assert list(one["estimators"]) == list(two["estimators"])  # same order too
    assert _without_times(one) == _without_times(two)
    assert (tmp_path / "two" / "leaderboard.md").is_file()


def test_devices_must_be_positive(tmp_path, capsys):
    assert main(["four_tank_bias", "--devices", "0", "--out", str(tmp_path)]) == 2
    assert "--devices" in capsys.readouterr().err
