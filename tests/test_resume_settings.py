"""A Lightning checkpoint runs with the model settings it was trained with: a command that
gives others is refused, naming each. Lightning (from 2.5.5) reads the checkpoint's
settings into the config before any hook, so a training trial's resumed fit with ``hidden
32``, ``lr 0.001`` and ``filter ukf`` trained on with 16, 0.01 and ekf, and a ``test``
with ``restart 0.01`` scored the network without it, both without a word (the settings
check compared the checkpoint with itself). Older releases (2.2, test-min) build the
module from the command's settings."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch
from conftest import small_four_tank_fit
from lightning.pytorch.cli import LightningCLI

from difffilter.train.cli import main
from difffilter.train.lightning_cli import DifffilterCLI

ROOT = Path(__file__).resolve().parents[1]
#: Whether this Lightning reads a --ckpt_path's settings into the config (2.5.5 on: our
#: DifffilterCLI._parse_ckpt_path compares them); before, the command's settings build the
#: module and a fit's resume check (_check_resumed_settings) compares them with the file's.
MERGES = hasattr(LightningCLI, "_parse_ckpt_path")
REFUSED = ("this command's model settings are not the checkpoint's" if MERGES
           else "this command changes settings the run was trained with")  # fmt: skip


def test_a_checkpoint_given_other_model_settings_is_refused_and_its_own_resume(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    base = ["--config", str(ROOT / "train" / "configs" / "robot.yaml"),
            "--data.init_args.batches_per_epoch=2", "--data.init_args.batch_size=2",
            "--data.init_args.val_runs=4", "--data.init_args.calibration_runs=4",
            "--trainer.enable_progress_bar=false", "--trainer.logger=false",
            f"--trainer.default_root_dir={tmp_path / 'run'}"]  # fmt: skip
    assert main(["fit", *base, "--trainer.max_epochs=1"]) == 0
    ckpt = f"--ckpt_path={tmp_path / 'run' / 'checkpoints' / 'last.ckpt'}"
    capsys.readouterr()
    seeded = ("--seed_everything 3: the run's network was seeded 0" if MERGES
              else "--data.init_args.train_seed: 1 → 31")  # fmt: skip
    for command, given, named in (
        ("fit", ["--model.init_args.hidden=32", "--model.init_args.filter=ukf"],
         "--model.init_args.filter: 'ekf' → 'ukf'; --model.init_args.hidden: 16 → 32"),
        # a class default spelled where the run had another (robot.yaml's ekf_lr is 1.0)
        ("fit", ["--model.init_args.ekf_lr=0.5"], "--model.init_args.ekf_lr: 1.0 → 0.5"),
        ("fit", ["--seed_everything=3"], seeded),
    ):  # fmt: skip
        assert main([command, *base, "--trainer.max_epochs=2", *given, ckpt]) == 2, command
        err = capsys.readouterr().err
        assert REFUSED in err and named in err
    # a test with another setting: refused where Lightning would run the checkpoint's; an
    # older Lightning runs the command's own, as asked
    ran_with = []  # the setting the tested module holds (a spy: the exit code alone
    # could not tell the command's 0.05 from the checkpoint's 0.01)
    before_test = DifffilterCLI.before_test

    def spy(cli):
        ran_with.append(cli.model.hparams["target_false_alarm_rate"])
        before_test(cli)

    monkeypatch.setattr(DifffilterCLI, "before_test", spy)
    rate = ["test", *base, "--model.init_args.target_false_alarm_rate=0.05", ckpt]
    assert main(rate) == (2 if MERGES else 0)
    assert ran_with == ([] if MERGES else [0.05])
    if MERGES:
        assert "--model.init_args.target_false_alarm_rate: 0.01 → 0.05" in capsys.readouterr().err
    assert main(["fit", *base, "--trainer.max_epochs=2", ckpt]) == 0  # its own: resumes
    # last.ckpt carries its epoch's own validation scores: its export's val_score is these
    # weights', not the best epoch's (a trial: an export of last.ckpt had been given those)
    from difffilter.train.export import _lightning_record

    last = tmp_path / "run" / "checkpoints" / "last.ckpt"
    blob = torch.load(last, map_location="cpu", weights_only=False)
    assert blob["epoch"] == 1 and blob["difffilter_validation"]["epoch"] == 1
    record = _lightning_record(blob, last)
    metric = record["monitor"]["metric"]
    assert record["val_score"] == blob["difffilter_validation"]["metrics"][metric]
    assert main(["test", *base, ckpt]) == 0
    # a test draws from its own seed: another --seed_everything scores the same network
    assert main(["test", *base, "--seed_everything=3", ckpt]) == 0


def test_a_run_with_a_setting_of_its_own_resumes_only_with_it(tmp_path, monkeypatch, capsys):
    """The run's settings are the checkpoint's: a command that leaves one out describes
    another run (the class's default), and is refused naming it; with it, or with the
    run's config.yaml, it resumes."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    base = ["--config", str(ROOT / "train" / "configs" / "robot.yaml"),
            "--data.init_args.batches_per_epoch=2", "--data.init_args.batch_size=2",
            "--data.init_args.val_runs=4", "--data.init_args.calibration_runs=4",
            "--trainer.enable_progress_bar=false"]  # fmt: skip
    own = "--model.init_args.adversarial_onsets=[10, 50]"
    assert main(["fit", *base, own, "--trainer.max_epochs=1"]) == 0
    run = tmp_path / "lightning_logs" / "robot_nn_ekf" / "version_0"
    ckpt = f"--ckpt_path={run / 'checkpoints' / 'last.ckpt'}"
    capsys.readouterr()
    assert main(["fit", *base, "--trainer.max_epochs=2", ckpt]) == 2
    err = capsys.readouterr().err
    assert REFUSED in err
    onsets = r"--model.init_args.adversarial_onsets: [\[(]10, 50[\])] → [\[(]5, 60[\])]"
    assert re.search(onsets, err)  # (an older Lightning's check writes tuples)
    assert main(["fit", *base, own, "--trainer.max_epochs=2", ckpt]) == 0
    # a test of the run's best checkpoint writes config_test.yaml, not over the run's
    best = next((run / "checkpoints").glob("best*.ckpt"))
    assert main(["test", "--config", str(run / "config.yaml"), f"--ckpt_path={best}"]) == 0
    # (in a folder of its own: the resumed run's config.yaml pins the run's version, and a
    # test had logged into the run, a trial)
    (tested,) = [p.parent for p in run.parent.glob("version_*/config_test.yaml")]
    assert tested != run and not (tested / "checkpoints").exists()
    assert not re.search(r"^verbose:", (run / "config.yaml").read_text(), flags=re.M)
    assert main(["fit", "--config", str(run / "config.yaml"), "--trainer.max_epochs=3", ckpt]) == 0


def test_a_threat_distribution_in_another_order_is_another_run(tmp_path, monkeypatch, capsys):
    """A threat distribution draws a threat by its entry's place (and an entry's random
    fields in their order): a trial resumed its run with the YAML's entries reversed, the
    check compared them as equal dicts, and the run trained on other data (53 of 64 runs
    drawn otherwise) and chose its best checkpoint between two validation sets. Refused,
    naming the setting; the run's own config.yaml resumes."""
    import yaml

    from difffilter.threat_distribution import ThreatDistribution

    source = yaml.safe_load((ROOT / "train" / "configs" / "four_tank_threats.yaml").read_text())
    threats = source["data"]["init_args"]["threats"]
    reverse = dict(reversed(list(threats.items())))
    first = [
        ThreatDistribution(threats).sample(torch.Generator().manual_seed(s))[0] for s in range(20)
    ]
    other = [
        ThreatDistribution(reverse).sample(torch.Generator().manual_seed(s))[0] for s in range(20)
    ]
    assert first != other  # the premise: the same entries in another order draw other threats
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    (tmp_path / "a.yaml").write_text(yaml.safe_dump(source, sort_keys=False))
    source["data"]["init_args"]["threats"] = reverse
    (tmp_path / "b.yaml").write_text(yaml.safe_dump(source, sort_keys=False))
    small = ["--data.init_args.batch_size=2", "--data.init_args.batches_per_epoch=1",
             "--data.init_args.val_runs=8", "--data.init_args.calibration_runs=4",
             "--model.init_args.hidden=4", "--trainer.enable_progress_bar=false"]  # fmt: skip
    assert main(["fit", "--config", "a.yaml", *small, "--trainer.max_epochs=1"]) == 0
    run = tmp_path / "lightning_logs" / "four_tank_threats_nn_grad" / "version_0"
    ckpt = f"--ckpt_path={run / 'checkpoints' / 'last.ckpt'}"
    capsys.readouterr()
    assert main(["fit", "--config", "b.yaml", *small, "--trainer.max_epochs=2", ckpt]) == 2
    err = capsys.readouterr().err
    assert "this command changes settings the run was trained with" in err
    order = ", ".join(threats)  # named as the order of the keys, not two whole dicts
    assert (f"--data.init_args.threats: the same keys in another order ({order} → "
            f"{', '.join(reverse)})") in err  # fmt: skip
    assert main(["fit", "--config", str(run / "config.yaml"), "--trainer.max_epochs=2", ckpt]) == 0


@pytest.mark.parametrize(
    "value, expected",
    [({"a": (1, 2)}, {"a": [1, 2]}), ({"a": [(1, {"b": (3,)})]}, {"a": [[1, {"b": [3]}]]})],
)
def test_settings_compare_as_plain_values(value, expected):
    from difffilter.train.lightning_cli import _plain

    assert _plain(value) == expected


def test_the_training_scenario_is_read_from_every_kind_of_checkpoint(tmp_path, monkeypatch):
    """From a review: a Lightning checkpoint (its card under ``difffilter_observer``) and an
    export in torch's legacy format (which cannot be mapped) gave none."""
    import torch

    from difffilter.models.neural_estimator import checkpoint_training_scenario

    shipped = ROOT / "checkpoints" / "robot_nn_ekf.ckpt"
    assert checkpoint_training_scenario(shipped) == "robot_actuator_attack_turn_rates"
    blob = torch.load(shipped, map_location="cpu", weights_only=True)
    legacy = tmp_path / "legacy.ckpt"
    torch.save(blob, legacy, _use_new_zipfile_serialization=False)
    assert checkpoint_training_scenario(legacy) == "robot_actuator_attack_turn_rates"
    lightning = tmp_path / "run.ckpt"
    torch.save({"state_dict": {}, "difffilter_observer": {**blob["observer"], "scenario": "mine"}},
               lightning)  # fmt: skip
    assert checkpoint_training_scenario(lightning) == "mine"
    (tmp_path / "junk.ckpt").write_bytes(b"not a checkpoint")
    assert checkpoint_training_scenario(tmp_path / "junk.ckpt") is None


def test_a_refused_setting_is_shown_where_it_differs():
    """A trial's refusal printed two whole threat distributions of 600 characters that
    differed in one entry's order of fields: the first place of difference is named, and a
    short setting is shown whole."""
    from difffilter.train.lightning_cli import _changed_text

    big = {"kind": "bias", "weight": 1, "value": {"uniform": [0.5, 1.5]}}
    a = {"own": {"weight": 1}, "big": big, "ramp": {"kind": "ramp", "slope": 0.1}}
    fields = {"own": {"weight": 1}, "big": dict(reversed(list(big.items()))),
              "ramp": {"kind": "ramp", "slope": 0.1}}  # fmt: skip
    assert _changed_text("--t", a, fields) == (
        "--t.big: the same keys in another order (kind, weight, value → value, weight, kind)"
    )
    slope = {**a, "ramp": {"kind": "ramp", "slope": 0.2}}
    assert _changed_text("--t", a, slope) == "--t.ramp.slope: 0.1 → 0.2"
    assert _changed_text("--t", [a], [slope]) == "--t[0].ramp.slope: 0.1 → 0.2"
    assert _changed_text("--o", (10, 50), [5, 60]) == "--o: (10, 50) → [5, 60]"
    assert _changed_text("--t", a, None).startswith("--t: {'own': {'weight': 1}")


def test_a_run_resumed_after_an_interrupted_epoch_draws_each_point_once(tmp_path, monkeypatch):
    """Interrupted in its second epoch (after that epoch's first batch was logged) and
    resumed from the first epoch's last.ckpt, the run logs the cut epoch again: its curves
    hold each step once (the interrupted process's points from the checkpoint's step on are
    purged; TensorBoard had drawn them twice, a trial), every epoch's validation kept."""
    import signal

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from difffilter.train.task import FilterEstimatorTask

    def interrupt(self, outputs, batch, batch_idx):
        if self.current_epoch == 1 and batch_idx == 1:
            raise KeyboardInterrupt

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    small = small_four_tank_fit(max_epochs=3)
    monkeypatch.setattr(FilterEstimatorTask, "on_train_batch_end", interrupt, raising=False)
    handler = signal.getsignal(signal.SIGINT)  # Lightning ignores SIGINT after an interrupt
    try:
        try:
            got = main(["fit", *small])
        except SystemExit as exit_:
            got = exit_.code
    finally:
        signal.signal(signal.SIGINT, handler)
    assert got == 130  # Ctrl-C: as difffilter-eval
    run = tmp_path / "lightning_logs" / "four_tank_nn_grad" / "version_0"
    interrupted = EventAccumulator(str(run)).Reload()
    assert [e.step for e in interrupted.Scalars("train/loss")] == [0, 1, 2, 3]  # cut at 3
    monkeypatch.delattr(FilterEstimatorTask, "on_train_batch_end")
    assert main(["fit", *small, f"--ckpt_path={run / 'checkpoints' / 'last.ckpt'}"]) == 0
    events = EventAccumulator(str(run)).Reload()
    assert [e.step for e in events.Scalars("train/loss")] == list(range(9))
    assert [e.step for e in events.Scalars("val/threshold")] == [2, 5, 8]
