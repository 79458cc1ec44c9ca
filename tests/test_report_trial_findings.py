"""Findings of a trial of the written reports: a number is never printed as the bar its
check compares it with unless it is that bar."""

from __future__ import annotations

from difffilter.eval.report import _acceptance_section
from difffilter.eval.robustness import _acceptance_section as _robustness_section


def test_an_fpr_interval_is_printed_apart_from_the_band():
    """The verdict printed ``0.0200004 ✗``; the interval beside it ``0.02 [0.015, 0.02]``,
    which reads as the band's edge (where it holds) beside "holds in 0 %"."""
    v = 0.0200004
    doc = {
        "estimators": {"a": {"tpr_at_far": 0.9, "state_rmse": 1.0, "fpr_at_far": 0.01},
                       "L": {"tpr_at_far": 0.9, "state_rmse": 1.0, "fpr_at_far": v}},
        "estimator_roles": {"a": "analytic", "L": "learned"}, "far": {"target": 0.01},
        "skipped": {},
        "acceptance_intervals": {"level": 0.95, "runs": 20, "resamples": 2000, "estimators": {
            "L": {"fpr_at_far": {"statistic": "value", "estimate": v, "low": 0.015, "high": v,
                                 "holds_share": 0.0}}}},
    }  # fmt: skip
    rows = [r for r in _acceptance_section(doc).body.splitlines() if r.startswith("| `L`")]
    assert "0.0200004 ✗" in rows[0]
    assert "0.0200004 [0.015, 0.0200004], holds in 0 %" in rows[1]


def _robustness_row(ratio: float) -> str:
    check = {"value": ratio, "best": 1.0, "best_estimator": "a", "ratio": ratio,
             "holds": ratio <= 1.1, "interval": {"low": ratio - 0.0003, "high": ratio + 0.0003,
                                                "holds_share": 0.5, "estimate": ratio}}  # fmt: skip
    a = {"worst_tpr": (0.035208, "t"), "best_analytic_worst_tpr": (0.035214, "a", "t"),
         "tpr_holds": False, "worst_threat_undetected": False, "state_holds": ratio <= 1.1,
         "state": {"t": check}, "training": None}  # fmt: skip
    return _robustness_section("L", a)


def test_a_robustness_ratio_is_printed_apart_from_its_bar():
    """A state ratio of 1.1004 (fails ≤ 1.1) and one of 1.0996 (holds) had both printed
    "1.1", beside opposite verdicts; the worst TPRs 0.035208 and 0.035214 both "0.03521"."""
    failing, holding = _robustness_row(1.1004), _robustness_row(1.0996)
    row = next(r for r in failing.splitlines() if r.startswith("| t |"))
    assert "| 1.1004 |" in row and "**no**" in row
    row = next(r for r in holding.splitlines() if r.startswith("| t |"))
    assert "| 1.0996 |" in row and "yes" in row
    assert "0.035208" in failing and "0.035214" in failing
