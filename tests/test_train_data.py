"""The training task's data: test runs are the evaluation's runs, in any training dtype."""

from __future__ import annotations

import pytest
import torch

from difffilter.models import registry
from difffilter.models.streams import Streams
from difffilter.train.task import ScenarioDataModule


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_the_test_runs_are_the_runs_difffilter_eval_scores(dtype):
    """``difffilter-eval --seed s`` draws in float64; a float32 task drew its own float32
    numbers (torch's randn differs by dtype from 16 draws on): other runs, 0.42 apart."""
    scenario = registry.get("four_tank_bias")
    dm = ScenarioDataModule("four_tank_bias", dtype=dtype, test_runs=20, test_seed=3)
    test = next(iter(dm.test_dataloader()))
    streams = Streams(3)
    gens = {k: streams(k) for k in ("plant", "attack", "schedule")}
    ev = scenario.simulate(20, gens, dtype=torch.float64, model=scenario.system(torch.float64))
    wanted = getattr(torch, dtype)
    for key in ("x", "y_recv", "attack"):
        assert test[key].dtype == wanted
        assert torch.equal(test[key], getattr(ev, key).to(wanted)), key
    assert torch.equal(test["flags"], ev.flags)
