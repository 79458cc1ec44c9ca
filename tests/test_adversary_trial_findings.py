"""Adversarial training's bookkeeping and the prediction index (a red-team trial).

* ``Adversary.augment`` labelled the crafted attack on entries the mask says never arrived,
  where the network's estimate is zero by construction: a loss no weights could lower.
* Onsets after the scenario's last step were clamped to it (an attack of one row), and a
  crafting an epoch later failed naming no adversarial option.
* A crafting that kept no attack counted on the card as one the weights met.
* ``PredictionFiles`` reused by a second ``trainer.predict`` listed its batch files twice.
"""

import json

import pytest
import torch

from difffilter.models.streams import Streams
from difffilter.models.yaml_scenario import scenario_from_dict
from difffilter.stealthy import CraftedAttack
from difffilter.train.adversarial import Adversary
from difffilter.train.export import adversarial_craftings
from difffilter.train.task import FilterEstimatorTask, training_batch

F64 = torch.float64


def test_the_crafted_attack_is_labelled_on_received_entries_only():
    sc = scenario_from_dict({
        "name": "lossy_bias_trial", "steps": 40,
        "plant": {"F": [[0.95, 0.0], [0.0, 0.98]], "H": [[1.0, 0.0], [0.0, 1.0]],
                  "Q": 1.0e-4, "R": 1.0e-3, "P0": 1.0e-3},
        "attack": {"kind": "bias", "channel": "sensor", "value": 0.5, "onset": 10, "share": 0.5},
        "schedule": {"kind": "packet_loss", "rate": 0.3},
    })  # fmt: skip
    adversary = Adversary(runs=2)
    adversary.onset = 10
    adversary.attack = torch.zeros(sc.steps, 2, dtype=F64)
    adversary.attack[9:] = 0.5 * torch.randn(
        sc.steps - 9, 2, generator=torch.Generator().manual_seed(0), dtype=F64
    )
    out = adversary.augment(training_batch(sc, 2, 7, F64), sc, 5, F64)
    extra = {k: v[2:] for k, v in out.items()}
    truth = sc.with_threat(CraftedAttack(adversary.attack, adversary.onset)).simulate(
        2, Streams(5).simulation(), dtype=F64
    )
    assert bool((~extra["mask"]).any())
    torch.testing.assert_close(extra["attack"], truth.attack)  # was the attack on lost entries too
    assert torch.equal(extra["flags"], truth.flags)


def test_onsets_after_the_last_step_are_refused():
    with pytest.raises(ValueError, match=r"adversarial_onsets \[150, 200\].*last step \(100\)"):
        FilterEstimatorTask("four_tank_bias", filter="ekf", hidden=4, adversarial_runs=2,
                            adversarial_onsets=[150, 200])  # fmt: skip


def test_a_crafting_that_kept_no_attack_is_not_counted():
    adversary = Adversary(runs=2)
    adversary.history = [(16, 30, 0.0), (32, 40, 0.25)]
    assert adversary.kept_craftings() == 1
    assert adversarial_craftings({"difffilter_adversary": adversary.state_dict()}) == 1  # was 2


def test_a_prediction_writer_used_twice_indexes_each_prediction_once(tmp_path):
    import lightning.pytorch as pl

    from difffilter.train.predictions import PredictionFiles
    from difffilter.train.task import ScenarioDataModule

    dm = ScenarioDataModule(scenario="four_tank_bias", batch_size=2, batches_per_epoch=1,
                            val_runs=2, test_runs=3, steps=20, dtype="float32")  # fmt: skip
    task = FilterEstimatorTask(scenario="four_tank_bias", filter="pf", num_particles=20, hidden=4,
                               dtype="float32")  # fmt: skip
    writer = PredictionFiles(tmp_path / "predictions")
    trainer = pl.Trainer(accelerator="cpu", devices=1, logger=False, callbacks=[writer],
                         enable_progress_bar=False, enable_checkpointing=False,
                         default_root_dir=tmp_path / "root")  # fmt: skip
    for _ in range(2):
        trainer.predict(task, datamodule=dm, return_predictions=False)
    index = json.loads((tmp_path / "predictions" / "predictions.json").read_text())
    assert [f["file"] for f in index["files"]] == ["batch_00000.pt"]  # was listed twice
    assert sum(f["runs"] for f in index["files"]) == 3
