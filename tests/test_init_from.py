"""Training from another estimator's weights (``FilterEstimatorTask(init_from=...)``) and
the sweep's ``{seed}`` placeholder that chains two stages seed by seed."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from difffilter.models.neural_estimator import load_estimator_checkpoint
from difffilter.train.task import FilterEstimatorTask

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = str(ROOT / "checkpoints" / "four_tank_nn_grad.ckpt")


def test_a_training_starts_from_the_weights_of_an_exported_estimator():
    task = FilterEstimatorTask("four_tank_bias", num_particles=20, init_from=SHIPPED)
    shipped, _ = load_estimator_checkpoint(SHIPPED, dtype=torch.float32)
    mine, theirs = task.estimator.state_dict(), shipped.state_dict()
    assert mine.keys() == theirs.keys()
    for key in mine:
        torch.testing.assert_close(mine[key], theirs[key], rtol=0, atol=0)
    fresh = FilterEstimatorTask("four_tank_bias", num_particles=20)
    assert not torch.equal(fresh.estimator.W, task.estimator.W)
    assert task.hparams.init_from == SHIPPED  # the export writes it in the card (model_config)


def test_a_network_of_other_settings_is_refused_by_name():
    with pytest.raises(ValueError, match=r"init_from: the network of .* does not match"):
        FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=8, init_from=SHIPPED)
    with pytest.raises(FileNotFoundError, match="no checkpoint file"):
        FilterEstimatorTask("four_tank_bias", init_from=str(ROOT / "no.ckpt"))


def test_the_sweep_puts_each_seed_in_the_options_that_name_it(tmp_path, monkeypatch):
    from difffilter.train import sweep

    seen = []
    monkeypatch.setattr("difffilter.train.cli.main", lambda args: seen.append(args) or 1)
    with pytest.raises(ValueError, match="seed 2: difffilter-train fit failed"):
        sweep._fit(tmp_path / "c.yaml", 2, tmp_path / "runs",
                   ["--model.init_args.init_from=s1/seed_{seed}/e.ckpt", "--trainer.max_epochs=3"])  # fmt: skip
    assert "--model.init_args.init_from=s1/seed_2/e.ckpt" in seen[0]
    assert "--trainer.max_epochs=3" in seen[0]
