"""The report's "Setting" section says what the study did, and only that."""

from __future__ import annotations

import types

from difffilter.eval.report import _summary_section

DOC = {"runs": 4, "steps": 10, "dt_s": 1.0, "seed": 0, "attacked_steps": 0,
       "attack_free_steps": 40, "notes": []}  # fmt: skip
FAR = {"target": 0.01, "calibration_runs": 100, "calibration_seed": 7}
SCENARIO = types.SimpleNamespace(paper="")


def test_the_calibrated_rate_is_described_only_where_a_detector_was_calibrated():
    """A scenario without detectors (four_tank_filters) said each threshold came from 100
    attack-free runs: its ``far`` record is there, with nothing measured on it."""
    none = _summary_section({**DOC, "far": {**FAR, "measured_on_calibration": {}}}, SCENARIO)
    assert "false-alarm rate" not in none.body
    some = {**FAR, "measured_on_calibration": {"chi_square_ekf": 0.01}}
    body = _summary_section({**DOC, "far": some}, SCENARIO).body
    assert "one false-alarm rate, 1 %" in body and "from 100 attack-free runs" in body
    # how far the threshold's rate may be from the target on fresh runs: 2√(α(1 − α)/n),
    # n = 100 runs × 10 steps (a user trial's 16 × 100 steps met 1.40 % for 1 %)
    assert "From 1,000 calibration steps" in body and "±0.63 points" in body
    trial = _summary_section({**DOC, "steps": 100, "far": {**some, "calibration_runs": 16}},
                             SCENARIO).body  # fmt: skip
    assert "From 1,600 calibration steps" in trial and "±0.5 points" in trial


def test_every_shipped_scenario_names_its_units():
    """Reports and the leaderboard print the scenario's units; four_tank_filters printed the
    placeholder "attack units"."""
    from difffilter.models import registry

    shipped = {"filters", "four_tank", "lfc", "robot", "tracking"}  # (not a test's own plants)
    for name in registry.names():
        sc = registry.get(name)
        if sc.family not in shipped:
            continue
        assert sc.state_unit != "state units" and sc.attack_unit != "attack units", name
