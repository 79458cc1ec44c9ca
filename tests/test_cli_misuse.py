"""A hurried user's mistakes on the command lines (a CLI trial's 110 attempts; these are
the ones that had ended in a traceback, done something else without a word, or said
something misleading): each now fails early with one line that names the argument."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOUR_TANK = str(ROOT / "train" / "configs" / "four_tank.yaml")


def test_an_interrupted_evaluation_says_so_in_one_line(monkeypatch, capsys, tmp_path):
    """Ctrl-C had printed a traceback from wherever the study was (and two with --devices)."""
    import difffilter.eval.cli as cli

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "evaluate", interrupted)
    assert cli.main(["four_tank_bias", "--runs", "2", "--out", str(tmp_path)]) == 130
    assert capsys.readouterr().err == (
        "difffilter-eval: interrupted: the reports under --out may be incomplete; rerun the "
        "same command to evaluate again\n"
    )


def test_an_empty_checkpoint_path_and_all_among_threats_are_named(tmp_path):
    """``--ckpt ""`` had said "no checkpoint file at ." and ``--threats all,bias`` called
    ``all`` unknown and then offered it; an empty threat set "must map" (it was one)."""
    from difffilter.eval.cli import parse_checkpoints
    from difffilter.eval.robustness import load_threat_set
    from difffilter.models import registry

    for value in ("", "pf_nn_grad="):
        with pytest.raises(ValueError, match=rf"--ckpt '{value}': an empty path; give a "
                           r"checkpoint file \(PATH or NAME=PATH\)"):  # fmt: skip
            parse_checkpoints([value])
    scenario = registry.get("four_tank_bias")
    with pytest.raises(ValueError, match=r"--threats: all stands alone .*; got all,bias"):
        load_threat_set(scenario, ["all", "bias"])
    every = list(load_threat_set(scenario, "all").threats)
    assert list(load_threat_set(scenario, "all,").threats) == every  # (a review: "stands alone")
    assert list(load_threat_set(scenario, " all").threats) == every
    named_all = tmp_path / "named.yaml"  # a threat named all is still chosen by its name
    named_all.write_text(
        "threats:\n  all: {kind: bias, onset: 5}\n  ramp: {kind: ramp, onset: 5}\n"
    )
    assert list(load_threat_set(scenario, ["all"], path=named_all).threats) == ["all"]
    for nothing in ("", ",", []):  # (they had given an empty study)
        with pytest.raises(ValueError, match="--threats: no threat named; give names, or all"):
            load_threat_set(scenario, nothing)


def test_an_empty_threat_set_and_a_key_given_twice_are_named(tmp_path):
    """Two threats of one name: YAML kept the last without a word (a ramp vanished from a
    study); ``threats: {}`` was said not to be a mapping."""
    from difffilter.eval.robustness import load_threat_set
    from difffilter.models import registry

    scenario = registry.get("four_tank_bias")
    empty, twice = tmp_path / "empty.yaml", tmp_path / "twice.yaml"
    empty.write_text("threats: {}\n")
    with pytest.raises(ValueError, match=r"empty.yaml: 'threats' must be a non-empty mapping of "
                       r"threat names to their specs; got \{\}"):  # fmt: skip
        load_threat_set(scenario, path=empty)
    twice.write_text("threats:\n  r: {kind: ramp, slope: 0.005, onset: 21}\n"
                     "  r: {kind: bias, value: 0.5, onset: 21}\n")  # fmt: skip
    with pytest.raises(ValueError, match=r"twice.yaml: the key 'r' appears twice in one mapping "
                       r"\(lines 2 and 3\); YAML would keep the last alone: rename one"):  # fmt: skip
        load_threat_set(scenario, path=twice)


def test_the_check_of_keys_compares_them_as_yaml_builds_them():
    """Keys are one where PyYAML's dict makes them one (a review: two merge keys, and 1
    beside '1', had been refused; null beside ~ passed); nested, in sequences, aliases."""
    from difffilter.models.yaml_scenario import check_unique_keys

    for fine in ("a: &x {b: 1}\nc: *x\nd: [{e: 1}, {e: 2}]\n",  # distinct maps, an alias
                 "a: &a {x: 1}\nb: &b {y: 1}\nd:\n  <<: *a\n  <<: *b\n",  # both merged
                 "d: {<<: [{x: 1}, {y: 2}], x: 3}\n",
                 "m: {1: a, '1': b}\n", "m: {true: a, 'true': b}\n"):  # fmt: skip
        check_unique_keys(fine, "ok.yaml")
    with pytest.raises(ValueError, match=r"deep.yaml: the key 'e' appears twice .*lines 2 and 3"):
        check_unique_keys("d:\n- {e: 1,\n   e: 2}\n", "deep.yaml")
    for one, other in (("null", "~"), ("1", "0x1"), ("1", "1.0")):
        with pytest.raises(ValueError, match=rf"the keys '{one}' and '{other}' are one key"):
            check_unique_keys(f"m: {{{one}: a, {other}: b}}\n", "one.yaml")
    # the training command line tells keys apart as jsonargparse's loader does (1e3 a
    # number, where SafeLoader reads a string)
    from difffilter.train.common import jsonargparse_yaml_loader

    loader = jsonargparse_yaml_loader()
    check_unique_keys("m: {1e3: a, '1e3': b}\n", "cli", loader)
    with pytest.raises(ValueError, match=r"the keys '1e3' and '1000.0' are one key"):
        check_unique_keys("m: {1e3: a, 1000.0: b}\n", "cli", loader)


def test_a_training_config_or_value_with_a_key_twice_is_refused(tmp_path, capsys):
    """The same in a training config (the card recorded one threat where two were written)
    and in a value given on the command line; nothing is trained."""
    from difffilter.train.cli import main

    twice = tmp_path / "twice.yaml"
    twice.write_text("data:\n  init_args:\n    threats:\n"
                     "      r: {weight: 1, kind: ramp, slope: 0.005, onset: 21}\n"
                     "      r: {weight: 1, kind: bias, value: 0.5, onset: 21}\n")  # fmt: skip
    quick = ["--trainer.fast_dev_run=true", "--trainer.logger=false"]
    for option in ("--config", "-c"):
        assert main(["fit", "--config", FOUR_TANK, option, str(twice), *quick]) == 2
        assert (f"difffilter-train: error: {twice}: the key 'r' appears twice in one mapping "
                "(lines 4 and 5)") in capsys.readouterr().err  # fmt: skip
    inline = "--data.init_args.threats={r: {weight: 1, kind: bias}, r: {weight: 1, kind: ramp}}"
    assert main(["fit", "--config", FOUR_TANK, inline, *quick]) == 2
    assert "the key 'r' appears twice in one mapping" in capsys.readouterr().err


def test_checkpoint_folders_and_an_unwritable_run_folder_are_named(tmp_path, monkeypatch, capsys):
    """A folder as ``--ckpt_path`` ended in IsADirectoryError, a folder named like the
    export's ``--out`` named an internal temporary file, and a run folder that could not be
    made ended in a PermissionError traceback (fit's logs, a sweep's ``--out``)."""
    import difffilter.train.lightning_cli as lightning_cli
    from difffilter.train.common import check_checkpoint_out
    from difffilter.train.sweep import main as sweep_main

    with pytest.raises(ValueError, match=r"--ckpt_path: .*checkpoints is a folder; give a "
                       r"checkpoint file \(it holds .*\.ckpt"):  # fmt: skip
        lightning_cli._check_ckpt_path({"ckpt_path": str(ROOT / "checkpoints")}, None)
    folder = tmp_path / "d.ckpt"
    folder.mkdir()
    with pytest.raises(ValueError, match=r"--out: .*d.ckpt is a folder; give the name of a "):
        check_checkpoint_out(folder, force=True)

    class Denied(lightning_cli.DifffilterCLI):  # where Lightning makes the run's folder
        def __init__(self, *args, **kwargs):
            raise PermissionError(13, "Permission denied", "/root-owned/logs")

    monkeypatch.setattr(lightning_cli, "DifffilterCLI", Denied)
    assert lightning_cli.run(["fit", "--config", FOUR_TANK], ["fit"], "d") == 2
    assert capsys.readouterr().err.startswith(
        "difffilter-train: error: cannot write /root-owned/logs (Permission denied): run from a "
        "writable folder or give one with --trainer.logger.init_args.save_dir"
    )
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert sweep_main(["--config", FOUR_TANK, "--seeds", "0", "--out", str(blocker / "sw"),
                       "--validation-only"]) == 2  # fmt: skip
    assert "--out: cannot make the folder" in capsys.readouterr().err
    # a sweep refused for another reason makes no folder (a review: it left an empty one)
    assert sweep_main(["--config", FOUR_TANK, "--out", str(tmp_path / "sw"), "--runs", "0"]) == 2
    assert "--runs must be an integer >= 1" in capsys.readouterr().err
    assert not (tmp_path / "sw").exists()
    twice = tmp_path / "twice.yaml"  # said before the monitor check reads the config
    twice.write_text("a: 1\na: 2\n")
    assert sweep_main(["--config", str(twice), "--out", str(tmp_path / "sw")]) == 2
    assert "twice.yaml: the key 'a' appears twice" in capsys.readouterr().err
    broken = tmp_path / "broken.yaml"  # (the monitor check's parser traceback, a review)
    broken.write_text("model: [1, 2\n")
    assert sweep_main(["--config", str(broken), "--out", str(tmp_path / "sw")]) == 2
    assert f"--config: {broken} is not valid YAML" in capsys.readouterr().err


def test_a_start_from_nothing_and_a_checkpoint_of_another_family_are_named(capsys):
    """``init_from`` of a missing file was named "ckpt"; ``validate`` of the four-tank
    config with the LFC checkpoint printed two settings dicts and not the family."""
    from difffilter.train.cli import main

    quick = ["--trainer.fast_dev_run=true", "--trainer.logger=false"]
    assert main(["fit", "--config", FOUR_TANK, "--model.init_args.init_from=/no/such.ckpt",
                 *quick]) == 2  # fmt: skip
    assert ("difffilter-train: error: model.init_args.init_from: no checkpoint file at "
            "/no/such.ckpt") in capsys.readouterr().err  # fmt: skip
    lfc = str(ROOT / "checkpoints" / "lfc_nn_grad.ckpt")
    assert main(["validate", "--config", FOUR_TANK, "--ckpt_path", lfc,
                 "--trainer.logger=false"]) == 2  # fmt: skip
    assert (
        f"--ckpt_path: {lfc} is an estimator of the lfc family (trained on "
        "lfc_random_attacks); the config trains a four_tank one"
    ) in capsys.readouterr().err
    ours = str(ROOT / "checkpoints" / "four_tank_nn_grad.ckpt")
    assert main(["validate", "--config", FOUR_TANK, "--ckpt_path", ours,
                 "--model.init_args.hidden=8", "--trainer.logger=false"]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert (f"--ckpt_path: the network in {ours} has other settings than the configured "
            "model's (hidden 16 against 8)") in err and "trained by" not in err  # fmt: skip
    # the EKF-trained network on the gradient config: its own config named (a docs trial)
    ekf = str(ROOT / "checkpoints" / "four_tank_nn_ekf.ckpt")
    assert main(["validate", "--config", FOUR_TANK, "--ckpt_path", ekf,
                 "--trainer.logger=false"]) == 2  # fmt: skip
    assert ("(it was trained by 'ekf', the config trains by 'grad': its config is "
            "train/configs/four_tank_ekf.yaml)") in capsys.readouterr().err  # fmt: skip


def test_an_added_learned_estimator_that_does_not_fit_names_the_shipped_one_that_does(
    monkeypatch, tmp_path
):
    """``--add-estimators pf_nn_ekf`` on the four-tank scenario was skipped because the
    default checkpoint is gradient-trained, with ``four_tank_nn_ekf.ckpt`` shipped beside."""
    from difffilter.models.learned_estimator import _shipped_fitting

    monkeypatch.chdir(ROOT)
    assert _shipped_fitting("pf_nn_ekf", "four_tank") == "checkpoints/four_tank_nn_ekf.ckpt"
    assert _shipped_fitting("pf_nn_ekf", "lfc") is None
    monkeypatch.chdir(tmp_path)  # from elsewhere, a path that works there (a review)
    assert _shipped_fitting("pf_nn_ekf", "four_tank") == str(
        ROOT / "checkpoints" / "four_tank_nn_ekf.ckpt")  # fmt: skip


def test_an_abbreviated_option_is_refused_and_a_device_option_is_answered(tmp_path, capsys):
    """argparse took a prefix of an option for the option: `difffilter-eval --device cuda`
    was read as --devices and failed with "argument --devices: invalid int value: 'cuda'"
    (a course trial). Each command line now takes its options whole."""
    import difffilter.eval.cli as cli
    from difffilter.train import calibrate, export, lfc_tuning, sweep

    with pytest.raises(SystemExit) as stop:
        cli.main(["four_tank_bias", "--device", "cuda", "--out", str(tmp_path)])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert (
        "unrecognized arguments: --device cuda (the evaluation runs on the CPU; --devices N" in err
    )
    attempts = [
        (cli.main, ["four_tank_bias", "--run", "2", "--out", str(tmp_path)], "--run 2"),
        (calibrate.main, ["x.ckpt", "--out", str(tmp_path / "c.ckpt"), "--ru", "5"], "--ru 5"),
        (export.main, ["x.ckpt", "--out", str(tmp_path / "e.ckpt"), "--forc"], "--forc"),
        (sweep.main, ["--config", FOUR_TANK, "--out", str(tmp_path / "s"), "--seed", "0"],
         "--seed 0"),
        (lfc_tuning.main, ["--run", "2"], "--run 2"),
    ]  # fmt: skip
    for main, argv, named in attempts:
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code == 2, main
        assert f"unrecognized arguments: {named}" in capsys.readouterr().err, main


def test_list_with_a_name_lists_that_familys_scenarios_or_says_what_it_takes(capsys):
    """``--list extra`` printed every scenario, the name ignored without a word; a family
    lists its scenarios (headline or not), ``all`` the headline ones."""
    from difffilter.eval.cli import main
    from difffilter.models import registry

    def listed(*argv):
        assert main([*argv, "--list"]) == 0
        lines = capsys.readouterr().out.split("\n\n")[0].splitlines()
        return [line.split()[0] for line in lines]

    assert listed("robot") == registry.names("robot")
    assert "robot_actuator_attack_turn_rates" in listed("robot")  # a variant, not headline
    assert set(listed("all")) == set(registry.names(headline_only=True))
    assert len(listed()) == len(registry.all_scenarios())
    with pytest.raises(SystemExit) as exit_:
        main(["extra", "--list"])
    assert exit_.value.code == 2
    assert "--list extra: give a family (filters, four_tank" in capsys.readouterr().err


def test_a_training_command_without_a_config_points_to_the_configs(capsys):
    """A docs trial: ``difffilter-train fit`` alone said only "the following arguments are
    required: fit.data, fit.model"; it now says where the model and data come from. A
    command with a config keeps its own error, without the hint."""
    from difffilter.train.cli import main

    assert main(["fit"]) == 2
    err = capsys.readouterr().err
    # (jsonargparse's own words differ by version: "the following arguments are required:
    # fit.data, fit.model", at the lowest declared one 'Key "fit.data" is required', or
    # fit.model, whichever it meets first)
    assert "required" in err and ("fit.model" in err or "fit.data" in err)
    assert ("no --config given: start from a training config, e.g. difffilter-train fit "
            "--config train/configs/four_tank.yaml") in err  # fmt: skip
    assert main(["fit", "--config", FOUR_TANK, "--model.init_args.nosuch=1"]) == 2
    err = capsys.readouterr().err
    assert "nosuch" in err and "no --config given" not in err  # (its words: the version's)


def test_a_missing_ckpt_path_is_refused_before_a_run_folder_is_made(tmp_path, monkeypatch, capsys):
    """A docs trial: ``fit``/``validate``/``test --ckpt_path`` of a file that is not there
    was named by Lightning after the run folder had been made, an empty run in TensorBoard
    at every try. Refused first now, in both spellings; Lightning's own names stay its."""
    from difffilter.train import lightning_cli
    from difffilter.train.cli import main

    monkeypatch.chdir(tmp_path)
    missing = str(tmp_path / "nope.ckpt")
    for argv in (["fit", "--config", FOUR_TANK, "--ckpt_path", missing],
                 ["validate", "--config", FOUR_TANK, f"--ckpt_path={missing}"]):  # fmt: skip
        assert main([*argv, "--trainer.fast_dev_run=true"]) == 2
        assert f"--ckpt_path: no checkpoint file at {missing}" in capsys.readouterr().err
    # Lightning's "last" in a new run's folder: nothing behind it (it trained from scratch)
    assert main(["fit", "--config", FOUR_TANK, "--ckpt_path", "last",
                 "--trainer.fast_dev_run=true"]) == 2  # fmt: skip
    assert "--ckpt_path last: Lightning reads this name as" in capsys.readouterr().err
    assert not (tmp_path / "lightning_logs").exists()
    for name in ("last", "best", "hpc", "s3://bucket/run.ckpt"):
        assert lightning_cli._check_ckpt_path({"ckpt_path": name}, "fit") is None


def test_a_seed_everything_out_of_range_is_named_before_anything_runs(
    tmp_path, monkeypatch, capsys
):
    """A docs trial: ``fit --seed_everything -1`` said "-1 is not in bounds, numpy accepts
    from 0 to 4294967295", naming no option; the other commands say ``--seed must be an
    integer >= 0``."""
    from difffilter.train.cli import main

    monkeypatch.chdir(tmp_path)
    for seed in ("-1", str(2**32)):
        assert main(["fit", "--config", FOUR_TANK, "--seed_everything", seed,
                     "--trainer.fast_dev_run=true"]) == 2  # fmt: skip
        assert (f"difffilter-train: error: --seed_everything must be an integer from 0 to "
                f"4294967295 (or true: a random seed; false: none); got {seed}"
                ) in capsys.readouterr().err  # fmt: skip
    assert not (tmp_path / "lightning_logs").exists()


def test_a_worker_of_several_processes_takes_sigterm_as_an_interrupt(monkeypatch):
    """An interrupts trial: the launcher stops its workers with SIGTERM, which killed a
    worker on the spot (it ran ``_main``, not ``main``), and a report being written stayed
    as a stray ``.partial`` file. The worker now raises the interrupt that removes it."""
    import signal

    import torch.distributed as dist

    from difffilter.eval import cli
    from difffilter.interrupts import Terminated

    monkeypatch.setattr(dist, "init_process_group", lambda *a, **k: None)
    monkeypatch.setattr(dist, "destroy_process_group", lambda: None)

    def study(argv):
        signal.raise_signal(signal.SIGTERM)  # as the launcher's cleanup sends it
        raise AssertionError("SIGTERM did not interrupt the worker")

    monkeypatch.setattr(cli, "_main", study)
    # where the worker set no handler of its own, this one is hit (not the default, which
    # would end the test run)
    previous = signal.signal(signal.SIGTERM, lambda *_: None)
    try:
        with pytest.raises(SystemExit) as stopped:
            cli._worker(1, 2, "tcp://127.0.0.1:1", [])
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert stopped.value.code == 130 and issubclass(Terminated, KeyboardInterrupt)


def test_a_reader_that_leaves_early_is_no_failure(tmp_path):
    """An interrupts trial: ``difffilter-eval … | head -c 1`` ended a finished run with a
    BrokenPipeError traceback and exit 1, a failure under pipefail."""
    import subprocess
    import sys

    script = (
        "import sys\nfrom difffilter.eval import cli\n"
        "def study(argv):\n    raise BrokenPipeError(32, 'Broken pipe')\n"
        "cli._main = study\nsys.exit(cli.main([]))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0 and "Traceback" not in done.stderr
