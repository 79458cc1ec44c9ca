"""A mutation review of eval/intervals.py, eval/acceptance.py and eval/report.py: each test
kills mutants that survived the suite, against a truth computed here by hand (a bootstrap
recomputed in numpy from the resample matrix, a verdict worked out from a small metrics
dict, a report table parsed back and compared to the metrics it came from)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from difffilter.eval import acceptance as ac
from difffilter.eval import intervals as iv

RUNS, RESAMPLES, SEED, FAR = 3, 400, 7, 0.1
LEARNED, ANALYTIC_A, ANALYTIC_C, ORACLE = "net", "a", "c", "oracle"
ROLE = {LEARNED: "learned", ANALYTIC_A: "analytic", ANALYTIC_C: "analytic", ORACLE: "oracle"}


def _t(*values):
    return torch.tensor(values, dtype=torch.float64)


#: Per-run totals of three runs, every number chosen by hand.
TOTALS = {
    # state: the learned error is exactly 1.05 x the analytic one's in every run (the bound)
    LEARNED: {"se": _t(1.1025, 1.1025, 1.1025), "n": _t(1, 1, 1),
              "attack_se": _t(0.5, 1.0, 2.2), "attack_n": _t(1, 1, 1),
              "hits": _t(9, 10, 8), "attacked": _t(10, 10, 10),
              "false": _t(1, 0, 5), "clear": _t(20, 20, 20)},
    ANALYTIC_A: {"se": _t(1, 1, 1), "n": _t(1, 1, 1),
                 "attack_se": _t(1, 1, 1), "attack_n": _t(1, 1, 1),
                 "hits": _t(10, 9, 10), "attacked": _t(10, 10, 10),
                 "false": _t(1, 1, 1), "clear": _t(20, 20, 20)},
    ANALYTIC_C: {"se": _t(1.5, 1.5, 1.5), "n": _t(1, 1, 1),
                 "attack_se": _t(1.2, 1.2, 1.2), "attack_n": _t(1, 1, 1),
                 "hits": _t(8, 10, 10), "attacked": _t(10, 10, 10),
                 "false": _t(1, 1, 1), "clear": _t(20, 20, 20)},
    # an oracle far better on every metric: never the best analytic
    ORACLE: {"se": _t(0.01, 0.01, 0.01), "n": _t(1, 1, 1),
             "attack_se": _t(0.01, 0.01, 0.01), "attack_n": _t(1, 1, 1),
             "hits": _t(10, 10, 10), "attacked": _t(10, 10, 10),
             "false": _t(1, 1, 1), "clear": _t(20, 20, 20)},
}  # fmt: skip


def _np(name, key):
    return TOTALS[name][key].numpy()


def _by_hand(weights: np.ndarray) -> dict[str, np.ndarray]:
    """Each check's statistic in every row of ``weights`` ``[1 + R, B]``, in numpy: pooled
    ratios of weighted sums, the best analytic (``a`` or ``c``, never the oracle) taken
    again in each row."""

    def rate(name, num, den):
        return (weights @ _np(name, num)) / (weights @ _np(name, den))

    best_tpr = np.maximum(
        rate(ANALYTIC_A, "hits", "attacked"), rate(ANALYTIC_C, "hits", "attacked")
    )
    best_state = np.minimum(
        np.sqrt(rate(ANALYTIC_A, "se", "n")), np.sqrt(rate(ANALYTIC_C, "se", "n"))
    )
    best_attack = np.minimum(np.sqrt(rate(ANALYTIC_A, "attack_se", "attack_n")),
                             np.sqrt(rate(ANALYTIC_C, "attack_se", "attack_n")))  # fmt: skip
    return {
        "tpr_at_far": rate(LEARNED, "hits", "attacked") - best_tpr,
        "state_rmse": np.sqrt(rate(LEARNED, "se", "n")) / best_state,
        "attack_rmse": np.sqrt(rate(LEARNED, "attack_se", "attack_n")) / best_attack,
        "fpr_at_far": rate(LEARNED, "false", "clear"),
    }


def test_the_resamples_of_three_runs_follow_the_multinomial_law():
    """The 10 multiplicity vectors of 3 runs drawn with replacement, against their exact
    probabilities 3!/(k1! k2! k3!) / 27 (a resampling of steps, or of fewer runs, gives
    other vectors or other frequencies)."""
    w = iv.resample_weights(RUNS, 20000, seed=SEED).numpy().astype(int)
    seen = {tuple(row): 0 for row in w}
    for row in w:
        seen[tuple(row)] += 1
    vectors = [v for v in itertools.product(range(4), repeat=3) if sum(v) == 3]
    assert set(seen) == set(vectors)
    for v in vectors:
        exact = math.factorial(3) / math.prod(math.factorial(k) for k in v) / 27
        assert seen[v] / 20000 == pytest.approx(exact, abs=0.012), v


def test_every_checks_interval_and_share_against_a_bootstrap_by_hand():
    """checks_intervals on hand-made totals against numpy on the same resample matrix:
    the study row, the 95 % percentile interval (numpy's linear quantile) and the share
    where the check holds: TPR difference ≥ −0.01, state ratio ≤ 1.05 (met exactly, every
    resample holds), attack ratio ≤ 1, FPR within [α/2, 2α]; the oracle is never the best."""
    got = iv.checks_intervals(TOTALS, ROLE, runs=RUNS, seed=SEED, far=FAR,
                              state_metric="state_rmse", resamples=RESAMPLES)  # fmt: skip
    weights = np.vstack([np.ones((1, RUNS)), iv.resample_weights(RUNS, RESAMPLES, SEED).numpy()])
    hand = _by_hand(weights)
    holds = {
        "tpr_at_far": lambda d: d >= -0.01 - 1e-12,
        "state_rmse": lambda r: r <= 1.05 + 1e-12,
        "attack_rmse": lambda r: r <= 1.0 + 1e-12,
        "fpr_at_far": lambda v: (v >= FAR / 2 - 1e-12) & (v <= 2 * FAR + 1e-12),
    }
    rows = got["estimators"][LEARNED]
    assert set(rows) == set(hand) and set(got["estimators"]) == {LEARNED}
    for metric, values in hand.items():
        low, high = np.quantile(values[1:], [0.025, 0.975])
        share = float(holds[metric](values[1:]).mean())
        assert rows[metric]["estimate"] == pytest.approx(values[0], rel=1e-12), metric
        assert (rows[metric]["low"], rows[metric]["high"]) == pytest.approx((low, high), rel=1e-12)
        assert rows[metric]["holds_share"] == pytest.approx(share, abs=1e-12), metric
    # the bound met exactly holds in every resample; the others hold in some but not all
    assert rows["state_rmse"]["holds_share"] == 1.0
    for metric in ("tpr_at_far", "attack_rmse", "fpr_at_far"):
        assert 0.0 < rows[metric]["holds_share"] < 1.0, metric
    # the FPR's share is not that of [α, 2α]: some resamples fall in [α/2, α)
    fpr = hand["fpr_at_far"][1:]
    assert ((fpr >= FAR / 2) & (fpr < FAR)).any()


# --- eval/acceptance.py and eval/report.py: a small study judged by hand --------------
#: A calibrated study (α = 1 %) with two analytic estimators, an oracle and an attack-free
#: reference better than both (never the best analytic), and two learned estimators.
EST = {
    "a": {"tpr_at_far": 0.95, "state_rmse": 0.2, "attack_rmse": 0.1, "fpr_at_far": 0.01},
    "c": {"tpr_at_far": 0.97, "state_rmse": 0.25, "attack_rmse": 0.08, "fpr_at_far": 0.012},
    "oracle": {"tpr_at_far": 1.0, "state_rmse": 0.01, "attack_rmse": 0.001, "fpr_at_far": 0.01},
    "ref": {"tpr_at_far": 0.999, "state_rmse": 0.02, "attack_rmse": 0.002, "fpr_at_far": 0.01},
    # TPR 0.0005 above the bound 0.96, state 1.05 x the best exactly, attack above 0.08,
    # FPR 0.0095 inside [0.005, 0.02] (a format rounding it to 0.01 misreports it)
    "net": {"tpr_at_far": 0.9605, "state_rmse": 0.21, "attack_rmse": 0.0801, "fpr_at_far": 0.0095},
    # TPR 0.9599 below 0.96, state 0.2101 above 0.21, attack 0.08 met, FPR 0.0049 below 0.005
    "net2": {"tpr_at_far": 0.9599, "state_rmse": 0.2101, "attack_rmse": 0.08, "fpr_at_far": 0.0049},
}
ROLES = {"a": "analytic", "c": "analytic", "oracle": "oracle", "ref": "reference",
         "net": "learned", "net2": "learned"}  # fmt: skip
#: The verdicts worked out by hand: best TPR 0.97 (c), best state 0.2 (a), best attack 0.08 (c).
BEST = {"tpr_at_far": (0.97, "c"), "state_rmse": (0.2, "a"), "attack_rmse": (0.08, "c")}
VERDICT = {
    "net": {"tpr_at_far": True, "state_rmse": True, "attack_rmse": False, "fpr_at_far": True},
    "net2": {"tpr_at_far": False, "state_rmse": False, "attack_rmse": True, "fpr_at_far": False},
}
#: Each learned check's interval, with shares that differ per check, and as printed: in
#: whole percent, with the decimals it takes not to read 100 or 0 where some resamples
#: differ (0.996 had read 100 %, 0.004 0 %).
SHARES = {"tpr_at_far": 0.996, "state_rmse": 0.42, "attack_rmse": 0.004, "fpr_at_far": 0.675}
SHARE_TEXT = {"tpr_at_far": "99.6", "state_rmse": "42", "attack_rmse": "0.4", "fpr_at_far": "68"}
STATISTIC = {"tpr_at_far": "difference", "state_rmse": "ratio", "attack_rmse": "ratio",
             "fpr_at_far": "value"}  # fmt: skip


def _doc():
    from difffilter.eval.report import study_metrics

    doc = study_metrics("s", runs=5, steps=10, seed=0, estimators=EST)
    intervals = {
        name: {m: {"statistic": STATISTIC[m], "estimate": 0.5 + i, "low": 0.25 + i,
                   "high": 0.75 + i, "holds_share": SHARES[m]}
               for i, m in enumerate(SHARES)}
        for name in ("net", "net2")
    }  # fmt: skip
    doc.update(estimator_roles=ROLES, far={"target": 0.01}, skipped={},
               estimator_descriptions={n: n for n in EST},
               acceptance_intervals={"level": 0.95, "runs": 5, "resamples": 2000,
                                     "estimators": intervals})  # fmt: skip
    return doc


def _table(text: str, first: str) -> list[list[str]]:
    """The cells of the markdown table whose header starts with ``| first``."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first}"))
    rows = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        if not line.startswith("|---"):
            rows.append([c.strip() for c in line.split("|")[1:-1]])
    # a markdown table: the separator line has one cell per header cell
    assert lines[start + 1] == "|---" * len(rows[0]) + "|"
    assert all(len(r) == len(rows[0]) for r in rows)
    return rows


def test_the_best_analytic_and_the_verdicts_of_a_small_study_by_hand():
    """best_analytic leaves out the oracle and the reference (better than all on every
    metric) and judge holds each check up to its bound, both against the hand verdicts."""
    best = ac.best_analytic(EST, ROLES)
    assert {m: best[m] for m in BEST} == BEST
    for name, verdict in VERDICT.items():
        checks = ac.judge(EST[name], best, far=0.01)
        assert {c.metric: c.holds for c in checks} == verdict, name


def test_the_reports_verdict_table_parsed_back_is_the_metrics_and_the_hand_verdicts():
    """report.md's "Learned against the best analytic": the best row names each best and its
    value, each learned cell is its metric (read back as a number equal to it: 0.0095 is
    not 0.01) with the hand verdict's mark, in the column its header names; then the
    intervals' table: estimate, [low, high] in that order and the share in %."""
    from difffilter.eval.report import _acceptance_section

    body = _acceptance_section(_doc()).body
    header, *rows = _table(body, "learned")
    metrics = [h.split(" ")[0] for h in header[1:-1]]
    assert metrics == ["tpr_at_far", "state_rmse", "attack_rmse", "fpr_at_far"]
    by_name = {r[0]: dict(zip(header, r, strict=True)) for r in rows}
    best_row = by_name["best analytic"]
    for metric, (value, who) in BEST.items():
        cell = best_row[header[1 + metrics.index(metric)]]
        assert cell == f"{value:g} (`{who}`)", metric
    for name, verdict in VERDICT.items():
        row = by_name[f"`{name}`"]
        for metric, holds in verdict.items():
            number, mark = row[header[1 + metrics.index(metric)]].split(" ")
            assert float(number) == EST[name][metric], (name, metric)
            assert mark == ("✓" if holds else "✗"), (name, metric)
        assert row["every check"] == ("holds" if all(verdict.values()) else "**fails**")
    header, *rows = _table(body.split("How sure each verdict is")[1], "learned")
    assert header[1:] == ["tpr_at_far − best", "state_rmse / best", "attack_rmse / best",
                          "fpr_at_far"]  # fmt: skip
    for row in rows:
        for i, metric in enumerate(SHARES):
            cell = row[1 + metrics.index(metric)]
            assert (
                cell == f"{0.5 + i:g} [{0.25 + i:g}, {0.75 + i:g}], holds in {SHARE_TEXT[metric]} %"
            )


def test_the_evaluations_summary_parsed_back_puts_each_check_in_its_column(tmp_path):
    """acceptance.md: each learned row's TPR, state, attack and false-alarm cells hold that
    metric's value, its hand verdict's mark and that check's own share rounded to the
    nearest percent, to a decimal where that would read 100 or 0 (0.996 is 99.6 %)."""
    from difffilter.eval.report import write_acceptance_summary

    text = write_acceptance_summary(tmp_path, {"s": _doc()}).read_text()
    header, *rows = _table(text.split("\n\n", 2)[2], "scenario")
    column = {"tpr_at_far": "TPR", "state_rmse": "state", "attack_rmse": "attack",
              "fpr_at_far": "false alarms"}  # fmt: skip
    assert {r[1] for r in rows} == {"`net`", "`net2`"}
    for row in rows:
        name, cells = row[1].strip("`"), dict(zip(header, row, strict=True))
        for metric, holds in VERDICT[name].items():
            mark = "✓" if holds else "✗"
            share = SHARE_TEXT[metric]
            assert cells[column[metric]] == f"{EST[name][metric]:g} {mark} ({share} %)"
        assert cells["every check"] == "**fails**"


def test_the_estimator_table_parsed_back_is_the_metrics_it_came_from():
    """report.md's estimator table: each column's header names the metric whose values
    fill it (read back, every number equals the metrics.json value to 3 digits)."""
    from difffilter.eval.report import _table_section

    doc = _doc()
    header, *rows = _table(_table_section(doc).body, "estimator")
    assert len(rows) == len(EST)
    for row in rows:
        values = doc["estimators"][row[0].strip("`")]
        for title, cell in zip(header[1:], row[1:], strict=True):
            metric = title.split(" ")[0]
            expected = values[metric]
            assert (cell == "—") if expected is None else float(cell) == float(f"{expected:.3g}")


@pytest.mark.parametrize(
    ("value", "text"),
    [(0.0095, "0.0095"), (0.001, "0.001"), (0.00095, "9.500e-04"), (0.99995, "0.99995"),
     (0.9999999, "0.9999999"), (1.0, "1"), (0.0, "0"), (12345.0, "1.234e+04")],
)  # fmt: skip
def test_format_number_at_its_edges(value, text):
    """format_number by hand: 4 significant digits from 1e-3, scientific below; a fraction
    just below 1 gets the digits that show it is not 1 (at most 8)."""
    from difffilter.eval.report import format_number

    assert format_number(value) == text


def test_a_best_analytic_that_is_not_finite_is_no_best():
    """An analytic estimator whose state error diverged (``inf``, as a suite's metrics hold
    it before metrics.json's cleaning) is no best: alone, the metric has no best and the
    learned estimator's state check does not hold (a best of ``inf`` passed any value)."""
    metrics = {"a": {"tpr_at_far": 0.9, "state_rmse": math.inf, "fpr_at_far": 0.01},
               "net": {"tpr_at_far": 0.95, "state_rmse": 0.3, "fpr_at_far": 0.01}}  # fmt: skip
    best = ac.best_analytic(metrics, {"a": "analytic", "net": "learned"})
    assert best == {"tpr_at_far": (0.9, "a")}
    checks = {c.metric: c.holds for c in ac.judge(metrics["net"], best, far=0.01)}
    assert checks == {"tpr_at_far": True, "state_rmse": False, "fpr_at_far": True}


def test_a_learned_estimator_that_broke_down_fails_every_check_in_the_report():
    """A learned estimator (the registry's ``pf_nn_grad``) that broke down on the study's
    data has no number: its row stays in the verdict table, every check ✗ and the row
    "**fails** (broke down)" (left out, it vanished while its rivals were judged)."""
    from difffilter.eval.report import _acceptance_section
    from difffilter.eval.suite import BROKE_DOWN

    doc = _doc()
    doc["skipped"] = {"pf_nn_grad": f"{BROKE_DOWN}: singular"}
    header, *rows = _table(_acceptance_section(doc).body, "learned")
    (row,) = [r for r in rows if r[0] == "`pf_nn_grad`"]
    assert row[1:-1] == ["— ✗"] * 4 and row[-1] == "**fails** (broke down)"


def test_a_learned_estimator_that_broke_down_under_a_threat_holds_in_no_resample():
    """robustness_intervals: where the learned estimator broke down under a threat it has
    no estimate, and its state check holds in no resample (a share of 0, not "not
    measured"); the other threat's ratio is the hand ratio 1.05 x in every resample."""
    totals = {"bias": {LEARNED: {"broke_down": True}, ANALYTIC_A: TOTALS[ANALYTIC_A]},
              "ramp": {LEARNED: TOTALS[LEARNED], ANALYTIC_A: TOTALS[ANALYTIC_A]}}  # fmt: skip
    got = iv.robustness_intervals(totals, ROLE, runs=RUNS, seed=SEED, resamples=50)[LEARNED]
    assert got["state"]["bias"] == {"estimate": None, "low": None, "high": None,
                                    "holds_share": 0.0}  # fmt: skip
    assert got["state"]["ramp"] == pytest.approx(
        {"estimate": 1.05, "low": 1.05, "high": 1.05, "holds_share": 1.0}
    )


def test_the_best_reading_estimator_is_held_to_the_robustness_factor():
    """judge_robustness with a blind best (an open-loop prediction): the learned state
    error 1.08 is 2.16 x the blind best 0.5 (fails) and 1.08 x the best reader's 1.0,
    within the robustness factor 1.1 (holds_reading), by hand."""
    cells = {"t": {"net": {"tpr_at_far": 0.9, "state_rmse": 1.08},
                   "open": {"state_rmse": 0.5},
                   "chi": {"tpr_at_far": 0.8, "state_rmse": 1.0}}}  # fmt: skip
    role_of = {"net": "learned", "open": "analytic", "chi": "analytic"}
    state = ac.judge_robustness(cells, role_of, 0.01, blind={"open"})["net"]["state"]["t"]
    assert state["best_estimator"] == "open" and state["holds"] is False
    assert state["best_reading_estimator"] == "chi" and state["best_reading"] == 1.0
    assert state["ratio_reading"] == pytest.approx(1.08) and state["holds_reading"] is True


def test_a_learned_estimator_without_a_detection_is_judged_and_fails_its_tpr():
    """A learned estimator that reports no detection (no tpr_at_far) gets a verdict row: its
    TPR check fails for want of a number, its state and attack errors are judged as
    anyone's (it had no row at all and escaped the verdicts without a word)."""
    from difffilter.eval.report import _acceptance_section

    doc = _doc()
    entry = dict(EST["net"])
    del entry["tpr_at_far"], entry["fpr_at_far"]
    doc["estimators"]["net"] = entry
    header, *rows = _table(_acceptance_section(doc).body, "learned")
    (row,) = [r for r in rows if r[0] == "`net`"]
    cells = dict(zip(header, row, strict=True))
    assert cells[header[1]] == "— ✗" and cells[header[4]] == "— ✗"
    assert cells[header[2]] == f"{entry['state_rmse']:g} " + (
        "✓" if VERDICT["net"]["state_rmse"] else "✗"
    )
    assert cells["every check"] == "**fails**"


def test_a_level_or_rate_given_in_percent_is_refused_by_name():
    """A trial: ``level=95`` failed in torch.quantile, ``level=-0.5`` gave intervals with
    low > high, and ``far=1`` (meant as 1 %) judged every rate against a band of [0.5, 2]."""
    from difffilter.eval import intervals as iv
    from difffilter.eval.acceptance import judge

    g = torch.Generator().manual_seed(0)

    def totals():
        return {"se": torch.rand(10, generator=g, dtype=torch.float64),
                "n": torch.ones(10, dtype=torch.float64),
                "false": torch.ones(10, dtype=torch.float64),
                "clear": torch.full((10,), 100.0, dtype=torch.float64)}  # fmt: skip

    t, role = {"A": totals(), "L": totals()}, {"A": "analytic", "L": "learned"}
    kw = dict(runs=10, seed=0, state_metric="state_rmse")
    for level in (95, -0.5, 1.0):
        with pytest.raises(ValueError, match="level must be a confidence level in"):
            iv.checks_intervals(t, role, far=0.01, level=level, **kw)
        with pytest.raises(ValueError, match="level must be a confidence level in"):
            iv.robustness_intervals({"bias": t}, role, runs=10, seed=0, level=level)
    with pytest.raises(ValueError, match="far must be a false-alarm rate in"):
        iv.checks_intervals(t, role, far=1, **kw)
    with pytest.raises(ValueError, match="far must be a false-alarm rate in"):
        judge({"fpr_at_far": 0.01}, {}, far=1)
    assert iv.checks_intervals(t, role, far=0.01, **kw)["estimators"]["L"]


def test_an_interval_failing_its_bar_by_a_hair_does_not_print_as_the_bar():
    """A trial: a state ratio of 1.0500012, which fails ≤ 1.05, read "1.05 [1.05, 1.05],
    holds in 0 %" in the report's intervals row (the verdict row printed 1.050001 ✗); a
    share of 999,999 in 10⁶ read "100.000"."""
    from difffilter.eval.report import _intervals_text, share_percent

    B, ratio = 20, 1.0500012
    n = torch.full((B,), 100.0, dtype=torch.float64)
    se = torch.full((B,), 100.0, dtype=torch.float64)
    totals = {"A": {"se": se, "n": n}, "L": {"se": se * ratio**2, "n": n}}
    out = iv.checks_intervals(totals, {"A": "analytic", "L": "learned"}, runs=B, seed=0,
                              far=0.01, state_metric="state_rmse")  # fmt: skip
    row = _intervals_text(out, ["state_rmse"]).strip().splitlines()[-1]
    assert "1.050001 [1.050001, 1.050001], holds in 0 %" in row
    assert share_percent(999_999 / 1_000_000) == "99.9999"
    assert share_percent(1999 / 2000) == "99.95" and share_percent(1.0) == "100"
