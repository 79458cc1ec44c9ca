"""The training's monitors never draw the runs the evaluation scores (a seed-hygiene audit,
2026-12-04): ``monitor_seed=0`` computed the monitored scenarios' ``val/`` metrics, which a
checkpoint callback may select on, on exactly the runs ``difffilter-eval --seed 0`` scores."""

from __future__ import annotations

from types import SimpleNamespace as NS

import pytest
import torch

from difffilter.eval.cli import EVALUATION_SEED, build_parser
from difffilter.eval.suite import run_suite
from difffilter.models import registry
from difffilter.train.task import FilterEstimatorTask, evaluation_batch


def test_the_evaluations_default_seed_draws_the_runs_it_scores():
    """Why the guard: the monitor's batch of seed 0 is the evaluation's seed-0 runs."""
    scenario = registry.get("four_tank_bias")
    monitor = evaluation_batch(scenario, 2, EVALUATION_SEED, torch.float64)
    default = build_parser().parse_args(["four_tank_bias"]).seed  # the command's own default
    assert default == EVALUATION_SEED
    scored = run_suite(scenario, runs=2, seed=default, estimators=["chi_square_ekf"],
                       progress=False)  # fmt: skip
    assert torch.equal(monitor["y_recv"], scored.traj.y_recv)


def test_a_monitor_seed_of_the_scored_runs_is_refused():
    with pytest.raises(ValueError, match="monitor_seed must differ from 0, the seed of "
                                         "difffilter-eval's default runs"):  # fmt: skip
        FilterEstimatorTask(scenario="four_tank_bias", monitor_scenarios=["four_tank_bias"],
                            monitor_seed=0)  # fmt: skip
    FilterEstimatorTask(scenario="four_tank_bias", monitor_seed=0)  # no monitor: no monitor seed
    task = FilterEstimatorTask(scenario="four_tank_bias", monitor_scenarios=["four_tank_bias"],
                               monitor_seed=5)  # fmt: skip
    task._trainer = NS(datamodule=NS(hparams={"test_seed": 5}))  # a data module testing on 5
    with pytest.raises(ValueError, match="monitor_seed must differ from 5, the data module's "
                                         "test_seed"):  # fmt: skip
        task.on_fit_start()
    task._trainer = NS(datamodule=NS(hparams={"test_seed": 0}))
    task.on_fit_start()  # other seeds: trained
