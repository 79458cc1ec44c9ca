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


def test_the_reports_are_shared_longest_first_and_rank_0_keeps_the_leaderboard():
    """``report_writers``: with the headline families and two processes, tracking's report
    (its equal-wall-time study: about 8 plain reports) goes to the second process, then
    four_tank's (7) to the first, which starts one report behind for the leaderboard; one
    process writes everything; with one family (the test above) the second process writes
    it, the first the leaderboard."""
    from difffilter.eval.cli import resolve_scenarios
    from difffilter.eval.report import report_writers
    from difffilter.models import registry

    families: dict = {}
    for name in resolve_scenarios("all"):
        families.setdefault(registry.get(name).family, []).append(name)
    two = report_writers(families, 2)
    assert sorted(two) == sorted(families)
    assert sorted(f for f, r in two.items() if r == 1) == ["lfc", "tracking"]
    assert set(report_writers(families, 1).values()) == {0}
    assert report_writers({"filters": ["four_tank_filters"]}, 2) == {"filters": 1}
    three = report_writers(families, 3)
    assert set(three.values()) == {0, 1, 2} and three["tracking"] == 2


def test_the_estimators_are_shared_by_their_measured_cost():
    """``shares``: untimed estimators go round robin (as before any suite has run); timed
    ones longest first onto the least loaded process, in registry order within each."""
    from types import SimpleNamespace

    from difffilter.eval.suite import shares

    specs = [SimpleNamespace(name=n) for n in "abcdef"]
    assert [[s.name for s in p] for p in shares(specs, 2, {}, 10)] == [["a", "c", "e"],
                                                                       ["b", "d", "f"]]  # fmt: skip
    seconds = {"a": 1.0, "b": 1.0, "c": 8.0, "d": 1.0, "e": 1.0, "f": 2.0}
    parts = shares(specs, 2, seconds, 10)
    assert [[s.name for s in p] for p in parts] == [["c"], ["a", "b", "d", "e", "f"]]
    # an untimed estimator counts as the mean of the timed ones (here 2 s per run): c (3)
    # first, then a, b (2 each) onto the other, d and e alternately, f (1) last
    parts = shares(specs, 2, {"c": 3.0, "f": 1.0}, 1)
    assert [[s.name for s in p] for p in parts] == [["c", "d", "f"], ["a", "b", "e"]]
    assert shares(specs, 1, seconds, 10) == [specs]


def test_an_estimator_goes_back_to_its_rank_where_the_balance_allows():
    """``shares(previous=...)``: an estimator returns to the rank of the earlier suites (what
    that process cached for it serves it only there) unless that rank's load would pass
    the largest load of the plain assignment; a rank the group no longer has is ignored."""
    from types import SimpleNamespace

    from difffilter.eval.suite import shares

    specs = [SimpleNamespace(name=n) for n in "abcd"]
    seconds = {"a": 3.0, "b": 3.0, "c": 2.0, "d": 2.0}

    def names(parts):
        return [[s.name for s in p] for p in parts]

    assert names(shares(specs, 2, seconds, 1)) == [["a", "c"], ["b", "d"]]  # loads 5 and 5
    assert names(shares(specs, 2, seconds, 1, {"c": 1, "d": 0})) == [["a", "d"], ["b", "c"]]
    # b back on rank 1 would load it 6 > 5: it goes to the least loaded instead
    assert names(shares(specs, 2, seconds, 1, {"a": 1, "b": 1})) == [["b", "c"], ["a", "d"]]
    assert names(shares(specs, 2, seconds, 1, {"c": 5})) == [["a", "c"], ["b", "d"]]
