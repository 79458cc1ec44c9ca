"""The notes a report prints for a variant describe that variant (a trial of the variants:
the robot's turning variants read u = (5 cm/s, 5 deg/s), and lfc_random_attacks a fixed
0.01 p.u. step of load in area 1, which it draws per run and area)."""

from __future__ import annotations

import pytest

from difffilter.models import registry


@pytest.mark.parametrize(
    ("name", "inputs"),
    [("robot_actuator_attack", "u = (5 cm/s, 5 deg/s)"),
     ("robot_actuator_attack_turning", "u = (5 cm/s, 10 deg/s)"),
     ("robot_actuator_attack_turn_rates", "u_r evenly spread over 0-15 deg/s")],
)  # fmt: skip
def test_a_robot_scenarios_note_names_its_commanded_inputs(name, inputs):
    scenario = registry.get(name)
    (note,) = [n for n in scenario.notes if n.startswith("[DEF] u = ")]
    assert inputs in note
    # and the scenario commands what its note says
    spread = scenario.turn_rate_range_deg
    assert (
        (spread == (0.0, 15.0))
        if "spread" in inputs
        else f"{scenario.turn_rate_deg:g} deg/s" in note
    )


def test_the_lfc_training_scenarios_note_says_its_load_is_drawn():
    drawn, fixed = registry.get("lfc_random_attacks"), registry.get("lfc_step")
    (note,) = [n for n in drawn.notes if n.startswith("[DEF] load:")]
    assert "U[-0.01, 0.01] p.u." in note and drawn.load_range == 0.02
    assert fixed.load_range is None
    assert any(n.startswith("[DEF] load: 0.01 p.u. step in area 1") for n in fixed.notes)
