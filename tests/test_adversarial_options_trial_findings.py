"""An adversarial-training trial's findings: the crafting ran from the second epoch whether
or not a threshold had been chosen for the network (without calibration runs and with a
validation every second epoch, under the placeholder 0.5, at which the network alarmed on
none of the crafting runs' steps: the alarm budget bounded nothing); onsets past the data's
shorter horizon were refused only at the first crafting, an epoch later; one crafting run
with onsets reaching the last step died at a random crafting; onsets of the wrong length
failed on Python's unpacking; and with ``adversarial_runs=0`` the other options went
unchecked and unread without a word."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import pytest

from difffilter.train.adversarial import Adversary
from difffilter.train.cli import main
from difffilter.train.task import FilterEstimatorTask

CONFIG = str(Path(__file__).resolve().parents[1] / "train" / "configs" / "four_tank.yaml")
SMALL = ["--data.init_args.batch_size=2", "--data.init_args.batches_per_epoch=2",
         "--data.init_args.val_runs=4", "--model.init_args.num_particles=20",
         "--model.init_args.hidden=4", "--trainer.enable_progress_bar=false",
         "--model.init_args.adversarial_runs=2", "--model.init_args.adversarial_iterations=2",
         "--model.init_args.adversarial_every=1"]  # fmt: skip


@pytest.mark.parametrize("onsets", [(5, 60, 70), (5,), 5, "5,60"])
def test_onsets_of_the_wrong_length_or_type_are_named(onsets):
    with pytest.raises(ValueError, match="adversarial_onsets must be \\[first, last\\]"):
        FilterEstimatorTask("four_tank_bias", filter="ekf", hidden=4, adversarial_runs=2,
                            adversarial_onsets=onsets)  # fmt: skip


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [("adversarial_iterations", 0, "adversarial_iterations must be an integer >= 1"),
     ("adversarial_onsets", (9, 3), "adversarial_onsets must be"),
     ("adversarial_resample", "yes", "adversarial_resample must be true or false")],
)  # fmt: skip
def test_adversarial_options_are_checked_with_adversarial_training_off(option, value, message):
    with pytest.raises(ValueError, match=message):
        FilterEstimatorTask("four_tank_bias", filter="ekf", hidden=4, **{option: value})


def test_adversarial_options_set_with_adversarial_training_off_are_named():
    with pytest.warns(UserWarning, match="adversarial_every, adversarial_resample set while "
                                         "adversarial_runs is 0"):  # fmt: skip
        FilterEstimatorTask("four_tank_bias", filter="ekf", hidden=4, adversarial_resample=True,
                            adversarial_every=4)  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the defaults (onsets as YAML gives them): no warning
        task = FilterEstimatorTask("four_tank_bias", filter="ekf", hidden=4,
                                   adversarial_onsets=[5, 60])  # fmt: skip
    assert task.adversary is None


def test_one_crafting_run_with_onsets_reaching_the_last_step_is_refused_when_built():
    with pytest.raises(ValueError, match="with adversarial_crafting_runs 1 an attack drawn there"):
        FilterEstimatorTask("four_tank_bias", filter="ekf", hidden=4, adversarial_runs=2,
                            adversarial_crafting_runs=1, adversarial_onsets=(5, 100))  # fmt: skip
    # one run whose onsets end before the last step, or two runs reaching it: built
    for runs, onsets in ((1, (5, 99)), (2, (5, 100))):
        task = FilterEstimatorTask("four_tank_bias", filter="ekf", hidden=4,
                                   adversarial_runs=2, adversarial_crafting_runs=runs,
                                   adversarial_onsets=onsets)  # fmt: skip
        assert task.adversary.onsets == onsets


def test_onsets_past_the_datas_shorter_horizon_are_refused_before_any_training_step(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    trained = []
    monkeypatch.setattr(FilterEstimatorTask, "training_step",
                        lambda self, batch, i: trained.append(i))  # fmt: skip
    rc = main(["fit", "--config", CONFIG, "--data.init_args.steps=4", "--trainer.max_epochs=1",
               *SMALL])  # fmt: skip
    assert rc == 2 and trained == []
    assert "the first onset is after the scenario's last step (4)" in capsys.readouterr().err


def test_no_crafting_runs_under_a_threshold_no_one_chose(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    seen, craft = [], Adversary.craft

    def recording(self, task, step):
        seen.append((task.current_epoch, float(task.alarm_threshold_rate)))
        return craft(self, task, step)

    monkeypatch.setattr(Adversary, "craft", recording)
    rc = main(["fit", "--config", CONFIG, "--data.init_args.calibration_runs=0",
               "--trainer.max_epochs=3", "--trainer.check_val_every_n_epoch=2", *SMALL])  # fmt: skip
    assert rc == 0
    # no validation until the end of epoch 1: the craftings wait for it (epoch 2)
    assert seen and all(epoch == 2 and math.isfinite(rate) for epoch, rate in seen)
