"""Findings of a red-team trial of plant matching and estimator needs (2026-12-06)."""

from __future__ import annotations

import json

import pytest
import torch

import difffilter as df
from difffilter.models import registry
from difffilter.models.needs import LINEAR_MODEL
from difffilter.models.plant_match import (
    plant_difference,
    training_plant_notes,
    training_scenario_of,
)

D = torch.float64


def _carts(B):
    t = lambda a: torch.tensor(a, dtype=D)  # noqa: E731
    return df.LinearGaussianModel(t(((0.95, 0.04), (-0.02, 0.9))), torch.eye(2, dtype=D),
                                  1e-3 * torch.eye(2, dtype=D), 1e-2 * torch.eye(2, dtype=D),
                                  torch.zeros(2, dtype=D), 0.1 * torch.eye(2, dtype=D), B=t(B))  # fmt: skip


@pytest.mark.parametrize(
    "B",
    [((0.0, 1.0), (1.0, 0.0)), ((0.5, 0.5), (0.5, 0.5)), ((1.0, 0.0), (1.0, 0.0))],
    ids=["swapped", "mixed", "one actuator drives both"],
)
def test_input_matrices_of_equal_row_sums_are_other_plants(B):
    # u = 0.1 · 1 alone read these as B = I: at x = 0, u = e_1 the transitions differ by 0.5-1
    identity = _carts(((1.0, 0.0), (0.0, 1.0)))
    assert plant_difference(identity, _carts(B)) == "its transition differs about the prior mean"
    assert plant_difference(identity, _carts(((1.0, 0.0), (0.0, 1.0)))) is None


def test_the_tracking_model_is_not_linear_for_the_kalman_filters():
    # it has a transition matrix (its constant-velocity motion) but nonlinear measurements:
    # kf, chi_square_kf and cusum_kf had been run, not skipped, and died in the suite
    scenario = registry.get("tracking_rrp_deception_eta04")
    model = scenario.system(torch.float64)
    assert "needs a linear model" in LINEAR_MODEL.unmet(scenario, model)
    assert LINEAR_MODEL.unmet(registry.get("lfc_step"), registry.get("lfc_step").system(D)) is None


@pytest.mark.parametrize("config", ["oops", ["scenario", "x"]])
def test_a_card_whose_model_config_is_not_a_mapping_claims_nothing(tmp_path, config):
    path = tmp_path / "net.ckpt"
    path.write_bytes(b"not a torch file")
    path.with_suffix(".json").write_text(json.dumps({"model_config": config}))
    assert training_scenario_of(path) is None
    assert training_plant_notes([("net.ckpt", path)], ["lfc_step"]) == []


YAML = """\
name: NAME
family: carts
description: two carts
dt: 0.1
runs: 4
steps: 20
num_particles: 50
false_alarm_rate: 0.01
plant:
  F: FMAT
  H: [[1.0, 0.0], [0.0, 1.0]]
  Q: 1.0e-3
  R: 1.0e-2
  P0: 0.1
attack: {kind: bias, value: 0.3, entries: [0], onset: 8, share: 0.5}
"""


def test_a_lightning_checkpoint_names_the_scenario_file_it_was_trained_on(
    isolated_registry, tmp_path
):
    # a run's Lightning checkpoint has no card beside it: its YAML scenario's name alone
    # ("cart_a") cannot be built by another process, and the plant note went unsaid
    a, c = tmp_path / "a.yaml", tmp_path / "c.yaml"
    a.write_text(YAML.replace("NAME", "cart_a").replace("FMAT", "[[0.95, 0.04], [-0.02, 0.9]]"))
    c.write_text(YAML.replace("NAME", "cart_c").replace("FMAT", "[[0.5, 0.04], [-0.02, 0.3]]"))
    ckpt = tmp_path / "last.ckpt"
    torch.save({"pytorch-lightning_version": "2.5.0", "hyper_parameters": {"scenario": str(a)},
                "difffilter_observer": {"scenario": "cart_a"}}, ckpt)  # fmt: skip
    assert training_scenario_of(ckpt) == str(a)
    isolated_registry.get(str(c))
    notes = training_plant_notes([("last.ckpt", ckpt)], ["cart_c"])
    assert len(notes) == 1 and "trained on cart_a, whose plant is not cart_c's" in notes[0]
