"""Adversarial training: attacks crafted against the current network join its batches."""

from __future__ import annotations

import pytest
import torch

from difffilter.models import registry
from difffilter.train.adversarial import Adversary
from difffilter.train.task import FilterEstimatorTask, training_batch

F32 = torch.float32


def test_the_adversarys_runs_receive_its_attack_on_fresh_attack_free_runs():
    scenario = registry.get("four_tank_bias")
    adversary = Adversary(runs=3)
    adversary.attack = torch.zeros(100, 4)
    adversary.attack[29:] = torch.tensor([0.1, -0.2, 0.0, 0.3])
    adversary.onset = 30
    batch = training_batch(scenario, 2, 7, F32)
    out = adversary.augment(batch, scenario, 5, F32)
    free = training_batch(scenario.with_threat(None), 3, 5, F32)
    for k in batch:
        assert torch.equal(out[k][:2], batch[k])
    torch.testing.assert_close(
        out["y_recv"][2:] - free["y_recv"], adversary.attack.expand(3, 100, 4)
    )
    assert torch.equal(out["x"][2:], free["x"]) and torch.equal(
        out["attack"][2:, 29:, 1], torch.full((3, 71), -0.2)
    )
    assert not out["flags"][2:, :29].any() and out["flags"][2:, 29:].all()


def test_crafting_starts_at_its_onset_and_leaves_the_network_untouched():
    task = FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=4, adversarial_runs=2,
                               adversarial_iterations=4, adversarial_crafting_runs=4)  # fmt: skip
    task.alarm_threshold.fill_(0.3)
    before = [p.detach().clone() for p in task.estimator.parameters()]
    logs = task.adversary.craft(task, step=0)
    a, onset = task.adversary.attack, task.adversary.onset
    assert 5 <= onset <= 60 and a.shape == (100, 4)
    assert not a[: onset - 1].any() and a[onset - 1 :].abs().sum() > 0  # it attacks
    assert logs["adversarial_error"] > 0.0
    assert all(p.grad is None for p in task.estimator.parameters())  # nothing leaked in
    assert all(p.requires_grad for p in task.estimator.parameters())  # and restored
    assert all(torch.equal(p, q) for p, q in zip(before, task.estimator.parameters(), strict=True))
    assert task.adversary.due(16) and not task.adversary.due(3)


@pytest.mark.parametrize(
    ("kwargs", "why"),
    [
        ({"trainer": "ekf"}, "adversarial_runs needs the gradient trainer"),
        ({"adversarial_iterations": 0}, "adversarial_iterations must be an integer >= 1"),
        ({"adversarial_onsets": (9, 3)}, "adversarial_onsets must be"),
        ({"adversarial_selection_runs": -1}, "adversarial_selection_runs must be an integer >= 0"),
        ({"adversarial_resample": "yes"}, "adversarial_resample must be true or false"),
    ],
)
def test_adversarial_options_are_checked(kwargs, why):
    with pytest.raises(ValueError, match=why):
        FilterEstimatorTask("four_tank_bias", adversarial_runs=2, **kwargs)
    with pytest.raises(ValueError, match="open-loop scenario with a sensor attack"):
        FilterEstimatorTask("robot_actuator_attack", filter="ekf", adversarial_runs=2)


def _small_adversarial_fit(tmp_path, monkeypatch, *more: str) -> list[str]:
    """A tiny four-tank fit in ``tmp_path``, crafting at every step from epoch 1 on."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    return [
        "fit", "--config", str(root / "train" / "configs" / "four_tank.yaml"),
        "--data.init_args.batch_size=2", "--data.init_args.batches_per_epoch=2",
        "--data.init_args.val_runs=4", "--model.init_args.num_particles=20",
        "--model.init_args.hidden=4", "--trainer.max_epochs=2",
        "--model.init_args.adversarial_runs=2", "--model.init_args.adversarial_iterations=2",
        "--model.init_args.adversarial_every=1", *more,
    ]  # fmt: skip


def test_an_adversarial_fit_crafts_after_the_first_validation_and_logs_it(tmp_path, monkeypatch):

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from difffilter.train.cli import main

    assert main(_small_adversarial_fit(tmp_path, monkeypatch, "--trainer.log_every_n_steps=1")) == 0
    run = tmp_path / "lightning_logs" / "four_tank_nn_grad" / "version_0"
    events = EventAccumulator(str(run)).Reload()
    crafted = events.Scalars("train/adversarial_error")
    assert [e.step for e in crafted] == [2, 3]  # epoch 1's two steps, none before validation
    # once per crafting, whatever the logging interval: crafting every second step of 4
    # steps an epoch (steps 4 and 6 of epoch 1) with a point logged every 3 steps, the
    # craftings are at 4 and 6 alone (self.log had repeated a crafting's value at every
    # later logging step of its epoch: a trial's one crafting read as two)
    again = tmp_path / "again"
    again.mkdir()
    argv = _small_adversarial_fit(again, monkeypatch, "--trainer.log_every_n_steps=3",
                                  "--data.init_args.batches_per_epoch=4",
                                  "--model.init_args.adversarial_every=2")  # fmt: skip
    assert main(argv) == 0
    events = EventAccumulator(str(again / "lightning_logs" / "four_tank_nn_grad" / "version_0"))
    assert [e.step for e in events.Reload().Scalars("train/adversarial_onset")] == [4, 6]
    # the card counts the craftings the selected weights met (a trial's card credited
    # adversarial training to weights chosen at epoch 0, before any crafting): 0 for the
    # weights of epoch 0, 2 for those of epoch 1 (the steps above); an export of last.ckpt
    # (epoch 1) says 2, and the coverage calls a crafted threat "kind only" only then
    import json

    import torch

    from difffilter.eval.coverage import training_coverage

    card = json.loads((run / "four_tank_nn_grad.json").read_text())
    selected = torch.load(run / "checkpoints" / card["selected_checkpoint"], weights_only=True)
    assert card["adversarial_craftings"] == (0 if selected["epoch"] == 0 else 2)
    stealthy = {"crafted": {"kind": "stealthy", "against": "pf_nn_grad", "onset": 21}}
    label = training_coverage(run / "four_tank_nn_grad.ckpt", stealthy)["threats"]["crafted"]
    assert label == ("held out" if selected["epoch"] == 0 else "kind only")
    assert main(["export", str(run / "checkpoints" / "last.ckpt"), "--out",
                 str(tmp_path / "last_export.ckpt")]) == 0  # fmt: skip
    exported = json.loads((tmp_path / "last_export.json").read_text())
    assert exported["adversarial_craftings"] == 2
    assert training_coverage(tmp_path / "last_export.ckpt", stealthy)["adversarial"] is True


def test_a_crafting_that_keeps_no_attack_adds_no_runs_and_logs_zero(monkeypatch):
    """Where every iterate broke the alarm budget the crafting returns zeros: its runs would
    be attack-free runs flagged as attacked (the BCE taught to flag clean data), and the
    logged error was the largest over the iterates over budget."""
    import difffilter.train.adversarial as adversarial
    from difffilter.stealthy import CraftedAttack

    def over_budget(estimator, model, ys, xs, threshold, *, onset, **kw):
        T, dy = ys.shape[-2:]
        history = [(0, 5.0, 0.1, 0.30), (1, 7.0, 0.2, 0.40)]  # (it, J, excess, alarm rate)
        return CraftedAttack(torch.zeros(T, dy), onset, history, None, budget=0.02)

    monkeypatch.setattr(adversarial, "craft_stealthy_attack", over_budget)
    task = FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=4, adversarial_runs=2)
    logs = task.adversary.craft(task, step=0)
    assert logs["adversarial_error"] == 0.0
    scenario = registry.get("four_tank_bias")
    batch = training_batch(scenario, 2, 7, F32)
    out = task.adversary.augment(batch, scenario, 5, F32)
    assert all(torch.equal(out[k], batch[k]) for k in batch)


def test_a_crafting_logs_its_attack_free_rate_instead_of_warning_about_it(monkeypatch):
    """The crafting warns where its runs' attack-free rate is far from the target; the
    adversary logs that rate (the first batch's budget less ε) at every crafting instead,
    and silences that warning only: a warning a crafting would repeat all through a run."""
    import warnings

    import difffilter.train.adversarial as adversarial
    from difffilter.stealthy import CraftedAttack, StealthySettings

    def far_off(estimator, model, ys, xs, threshold, *, onset, **kw):
        if kw.get("warn_far_off", True):  # (as the crafting does)
            warnings.warn(
                "craft_stealthy_attack: the detector alarms on 7 % of …", RuntimeWarning,
                stacklevel=2,
            )  # fmt: skip
        warnings.warn("something else", RuntimeWarning, stacklevel=2)
        T, dy = ys.shape[-2:]
        return CraftedAttack(torch.zeros(T, dy), onset, [(0, 5.0, 0.0, 0.06, 0.073)], None,
                             budget=0.073)  # fmt: skip

    monkeypatch.setattr(adversarial, "craft_stealthy_attack", far_off)
    task = FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=4, adversarial_runs=2)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        logs = task.adversary.craft(task, step=0)
    assert [str(w.message) for w in seen] == ["something else"]
    slack = StealthySettings().slack
    assert logs["adversarial_attack_free_alarm_rate"] == pytest.approx(0.073 - slack, abs=1e-15)
    assert logs["adversarial_error"] == 5.0


def test_the_crafting_draws_particles_and_proposals_one_after_the_other(monkeypatch):
    """The prior particles and the first proposal noise are independent draws (two
    generators of one stream drew the same numbers: correlation 1)."""
    import difffilter.train.adversarial as adversarial
    from difffilter.stealthy import CraftedAttack

    seen = {}

    def capture(estimator, model, ys, xs, threshold, *, onset, generator, **kw):
        gens = generator()
        seen["init"] = torch.randn(1000, generator=gens.init)
        seen["propagate"] = torch.randn(1000, generator=gens.propagate)
        return CraftedAttack(torch.zeros(ys.shape[-2:]), onset, [], None, budget=0.02)

    monkeypatch.setattr(adversarial, "craft_stealthy_attack", capture)
    task = FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=4, adversarial_runs=2)
    task.adversary.craft(task, step=0)
    r = torch.corrcoef(torch.stack([seen["init"], seen["propagate"]]))[0, 1]
    assert abs(float(r)) < 0.2


def test_the_crafting_gets_the_receptions_the_training_batches_get(monkeypatch):
    """Training steps its filter with the sensor schedule's mask (task.py); the adversary
    crafted without it, on measurements the filter never gets (a session's note). A
    schedule that loses every fourth step of sensor 0 reaches the crafting as its mask."""

    import difffilter.train.adversarial as adversarial
    from difffilter.stealthy import CraftedAttack

    seen = {}

    def capture(estimator, model, ys, xs, threshold, *, onset, mask=None, **kw):
        seen["mask"] = mask
        return CraftedAttack(torch.zeros(ys.shape[-2:]), onset, [], None, budget=0.02)

    monkeypatch.setattr(adversarial, "craft_stealthy_attack", capture)
    task = FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=4, adversarial_runs=2)
    scenario = task.scenario_of_data()
    free = scenario.with_threat(None)
    lossy = torch.ones(100, 4, dtype=torch.bool)
    lossy[::4, 0] = False

    class Lossy:  # the scenario's attack-free runs, with a mask of lost entries
        def simulate(self, runs, gens, **kw):
            tr = free.simulate(runs, gens, **kw)
            return tr._replace(mask=lossy.expand(runs, 100, 4).clone())

    monkeypatch.setattr(type(scenario), "with_threat", lambda self, threat: Lossy())
    task.adversary.craft(task, step=0)
    runs = task.adversary.crafting_runs
    assert seen["mask"] is not None and torch.equal(seen["mask"], lossy.expand(runs, 100, 4))


def test_the_crafting_resamples_and_selects_as_the_evaluations_attacker(monkeypatch):
    """With ``resample`` every iteration gets fresh attack-free runs of its own (iteration 0
    the first batch), with ``selection_runs`` the attack is chosen on that many held-out
    runs; without them the crafting gets neither (the behaviour of before)."""
    import difffilter.train.adversarial as adversarial
    from difffilter.stealthy import CraftedAttack

    seen = {}

    def capture(estimator, model, ys, xs, threshold, *, onset, resample=None, select=None, **kw):
        seen.update(ys=ys, xs=xs, resample=resample, select=select)
        return CraftedAttack(torch.zeros(ys.shape[-2:]), onset, [], None, budget=0.02,
                             selection={"runs": 5, "budget": 0.02, "judged": [],
                                        "iteration": None})  # fmt: skip

    monkeypatch.setattr(adversarial, "craft_stealthy_attack", capture)
    plain = FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=4, adversarial_runs=2,
                                adversarial_crafting_runs=3)  # fmt: skip
    plain.adversary.craft(plain, step=0)
    assert seen["resample"] is None and seen["select"] is None
    first = seen["ys"]
    task = FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=4, adversarial_runs=2,
                               adversarial_crafting_runs=3, adversarial_resample=True,
                               adversarial_selection_runs=5)  # fmt: skip
    logs = task.adversary.craft(task, step=0)
    assert torch.equal(seen["ys"], first)  # the first batch as before
    one, two = seen["resample"](1), seen["resample"](2)
    for batch in (one, two):
        assert batch[0].shape == first.shape and batch[1].shape == seen["xs"].shape
        assert batch[2] is None and batch[3] is None  # four-tank: no inputs, every entry
    assert not torch.equal(one[0], first) and not torch.equal(one[0], two[0])
    assert torch.equal(seen["resample"](1)[0], one[0])  # drawn from the seed, reproducible
    held_out = seen["select"]
    assert held_out[0].shape == (5, 100, 4) and not torch.equal(held_out[0][:3], first)
    assert logs["adversarial_error"] == 0.0  # nothing kept on the held-out runs


def test_a_selected_crafting_logs_the_chosen_attacks_held_out_error(monkeypatch):
    import difffilter.train.adversarial as adversarial

    real, returned = adversarial.craft_stealthy_attack, []

    def spy(*args, **kw):
        returned.append(real(*args, **kw))
        return returned[-1]

    monkeypatch.setattr(adversarial, "craft_stealthy_attack", spy)
    task = FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=4, adversarial_runs=2,
                               adversarial_iterations=4, adversarial_crafting_runs=4,
                               adversarial_resample=True, adversarial_selection_runs=6)  # fmt: skip
    task.alarm_threshold.fill_(0.3)
    logs = task.adversary.craft(task, step=0)
    selection = returned[0].selection
    assert selection["runs"] == 6 and selection["judged"]
    chosen = selection["iteration"]
    assert chosen is not None  # a loose threshold: the first candidate keeps the budget
    judged = dict((it, j) for it, j, _ in selection["judged"])
    assert logs["adversarial_error"] == judged[chosen] > 0.0
    assert task.adversary.history[-1] == (0, task.adversary.onset, judged[chosen])
    assert torch.equal(task.adversary.attack, returned[0].values)


def test_the_adversarys_attack_survives_a_checkpoint(tmp_path):
    """A resumed run goes on with the attack it had (it crafted a new one at once, at other
    steps than the uninterrupted run: weights 1.5e-3 apart)."""
    task = FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=4, adversarial_runs=2)
    task.adversary.attack = torch.arange(400.0).reshape(100, 4)
    task.adversary.onset, task.adversary.history = 30, [(16, 30, 0.5)]
    checkpoint = {}
    task.on_save_checkpoint(checkpoint)
    torch.save(checkpoint, tmp_path / "c.ckpt")
    loaded = torch.load(tmp_path / "c.ckpt", weights_only=True)
    fresh = FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=4, adversarial_runs=2)
    fresh.on_load_checkpoint(loaded)
    assert torch.equal(fresh.adversary.attack, task.adversary.attack)
    assert fresh.adversary.onset == 30 and fresh.adversary.history == [(16, 30, 0.5)]
    assert not fresh.adversary.due(17) and fresh.adversary.due(32)


def test_a_crafting_between_validations_crafts_under_the_current_networks_threshold(
    tmp_path, monkeypatch
):  # fmt: skip
    """A user trial crafted every 3 steps of 4-batch epochs: between validations the
    adversary read the threshold of older weights, at which the current network alarmed on
    100 % of the attack-free crafting runs, so the alarm budget constrained nothing."""

    from difffilter.metrics import finite_scores, threshold_for
    from difffilter.train import adversarial
    from difffilter.train.cli import main

    seen = []
    real = adversarial.craft_stealthy_attack

    def recording(estimator, system, *args, **kwargs):
        task = recording.task
        free, _ = task._evaluate(*task.trainer.datamodule.calibration_data())
        fresh = threshold_for(finite_scores(free.detection.scores), task.false_alarm_rate)
        seen.append((task.global_step, args[2], fresh, float(task.alarm_threshold)))
        return real(estimator, system, *args, **kwargs)

    original_craft = adversarial.Adversary.craft

    def craft(self, task, step):
        recording.task = task
        return original_craft(self, task, step)

    monkeypatch.setattr(adversarial, "craft_stealthy_attack", recording)
    monkeypatch.setattr(adversarial.Adversary, "craft", craft)
    assert main(_small_adversarial_fit(tmp_path, monkeypatch)) == 0
    assert [s[0] for s in seen] == [2, 3]
    for _, used, fresh, _ in seen:
        assert used == fresh  # the threshold of the weights the attack is crafted against
    (_, _, _, validated), (_, used_later, _, stale) = seen
    assert seen[0][1] == validated  # right after the validation: its own threshold
    assert used_later != stale  # a step later, the weights moved: chosen again
