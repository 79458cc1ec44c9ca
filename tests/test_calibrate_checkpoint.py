"""``difffilter-train calibrate``: a checkpoint's threshold chosen on attack-free runs for a
false-alarm rate, checked on others, carried by the card and used by the estimator."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from difffilter.eval.suite import run_suite
from difffilter.models import registry
from difffilter.models.lfc_estimators import PROBABILITY, confirmed_statistic
from difffilter.models.neural_estimator import (
    checkpoint_sha256,
    load_estimator_checkpoint,
    save_estimator_checkpoint,
    weights_sha256,
)
from difffilter.models.streams import Streams
from difffilter.train.calibrate import calibrate_checkpoint, estimator_name, main

SHIPPED = "checkpoints/four_tank_nn_grad.ckpt"


def _free_scores(scenario, name, path, runs, seed):
    result = run_suite(scenario.with_threat(None), runs=runs, seed=seed, estimators=[name],
                       checkpoint={name: str(path)}, progress=False)  # fmt: skip
    return result.outputs[name].detection


def test_the_threshold_meets_the_rate_on_its_runs_and_the_estimator_alarms_above_it(tmp_path):
    out = tmp_path / "calibrated.ckpt"
    cal = calibrate_checkpoint(SHIPPED, out, far=0.05, runs=6, progress=False)
    net, card = load_estimator_checkpoint(out)
    assert card.threshold == cal["threshold"] and card.target_false_alarm_rate == 0.05
    document = json.loads(out.with_suffix(".json").read_text())
    assert document["weights_sha256"] == weights_sha256(SHIPPED)  # the same weights
    assert card.estimator == "pf_nn_grad" == cal["estimator"]
    scenario = registry.get("four_tank_bias")
    # the particles it was scored with (the scenario's), which load_estimator then runs
    assert cal["num_particles"] == scenario.num_particles
    # recomputed from the calibration runs: at most ⌊α n⌋ exceed τ, and τ is tight (a lower
    # threshold would let more through)
    fitted = _free_scores(scenario, "pf_nn_grad", SHIPPED, 6, cal["seed"]).scores
    above, allowed = int((fitted > cal["threshold"]).sum()), math.floor(0.05 * fitted.numel())
    assert above <= allowed < int((fitted >= cal["threshold"]).sum())
    assert cal["measured_on_calibration"] == pytest.approx(above / fitted.numel())
    # the check runs are others (their own seed), and the new file alarms at τ on them
    assert cal["check_seed"] != cal["seed"] == Streams(5).seed_of("checkpoint-calibration")
    assert cal["master_seed"] == 5
    assert cal["check_seed"] == Streams(5).seed_of("checkpoint-calibration/check")
    det = _free_scores(scenario, "pf_nn_grad", out, 6, cal["check_seed"])
    assert torch.equal(det.alarms, det.scores > cal["threshold"])
    assert cal["measured_on_check"] == pytest.approx(float(det.alarms.double().mean()))
    assert 0.0 < cal["measured_on_check"] < 0.15  # 6 runs × 100 steps around 5 %
    # the weights are the source's; the card keeps its history and records the calibration
    src_net, _ = load_estimator_checkpoint(SHIPPED)
    for a, b in zip(net.state_dict().values(), src_net.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    doc = json.loads(out.with_suffix(".json").read_text())
    assert doc["calibration"] == cal and doc["model_config"]["scenario"] == "four_tank_bias"


def _uncalibrated(path, out):
    """A copy of the checkpoint at ``path`` whose card carries no calibration and no
    confirmation (the head's default threshold, as ``export`` writes it by default)."""
    net, card = load_estimator_checkpoint(path)
    extra = {k: v for k, v in card.extra.items() if k != "calibration"}
    card = dataclasses.replace(card, threshold=0.5, confirm=None, extra=extra)
    save_estimator_checkpoint(out, net, card)
    return out


def test_a_calibrated_lfc_checkpoint_alarms_at_its_threshold_on_its_head(tmp_path):
    """The LFC checkpoint's network has a detection head: its entry scores the head's
    probability, at the card's threshold where the card was calibrated for this entry and
    this statistic, else at p = 0.5 (a card calibrated for the standardised estimate, as
    before the statistic was recorded, does not apply to the probability)."""
    plain = _uncalibrated("checkpoints/lfc_nn_grad.ckpt", tmp_path / "plain.ckpt")
    out = tmp_path / "lfc.ckpt"
    cal = calibrate_checkpoint(plain, out, far=0.02, runs=2, progress=False)
    assert cal["estimator"] == "kf_nn_grad" and cal["scenario"] == "lfc_random_attacks"
    assert cal["score"] == "attack probability" and 0.0 < cal["threshold"] < 1.0
    net, card = load_estimator_checkpoint(out)
    old_cal = {k: v for k, v in cal.items() if k != "score"}
    old = tmp_path / "old.ckpt"
    save_estimator_checkpoint(old, net, dataclasses.replace(
        card, threshold=3.3, extra={**card.extra, "calibration": old_cal}))  # fmt: skip
    scenario = registry.get("lfc_step").with_steps(300)
    shipped = load_estimator_checkpoint("checkpoints/lfc_nn_grad.ckpt")[1]
    confirmed = confirmed_statistic(PROBABILITY, shipped.confirm)
    assert shipped.extra["calibration"]["estimator"] == "kf_nn_grad"  # the shipped one is,
    assert shipped.extra["calibration"]["score"] == confirmed  # for its confirmed probability
    # the online fine-tuning of the same network is another entry: it keeps p = 0.5
    cases = (("checkpoints/lfc_nn_grad.ckpt", "kf_nn_grad", shipped.threshold, confirmed),
             (plain, "kf_nn_grad", 0.5, PROBABILITY),
             (out, "kf_nn_grad", cal["threshold"], PROBABILITY),
             (old, "kf_nn_grad", 0.5, PROBABILITY), (out, "kf_nn_grad_ekf", 0.5, PROBABILITY))  # fmt: skip
    for path, name, threshold, statistic in cases:
        result = run_suite(scenario, runs=2, estimators=[name], checkpoint={name: str(path)},
                           progress=False)  # fmt: skip
        output = result.outputs[name]
        det, logit = output.detection, output.extras["attack_logit"]
        assert det.threshold == threshold and det.statistic == statistic
        probability = torch.sigmoid(logit)
        if statistic == confirmed:  # the probability where the copy's test alarmed, else 0
            probability = torch.where(output.extras["confirmed"], probability, 0.0)
        assert torch.allclose(det.scores, probability)
        assert torch.equal(det.alarms, det.scores > threshold)


def test_the_paper_networks_score_their_standardised_estimate():
    """Without a detection head (the paper's networks) an LFC entry scores ``max_c |α̂_c| /
    σ_c`` at 3σ."""
    result = run_suite(registry.get("lfc_step").with_steps(300), runs=2,
                       estimators=["kf_nn_gd"], progress=False)  # fmt: skip
    out = result.outputs["kf_nn_gd"]
    assert "attack_logit" not in out.extras
    det = out.detection
    assert det.statistic == "standardised attack estimate" and det.threshold == 3.0
    assert torch.equal(det.alarms, det.scores > 3.0)


def test_calibrate_refuses_what_it_cannot_do(tmp_path, capsys):
    out = tmp_path / "x.ckpt"
    assert main([SHIPPED, "--out", str(out), "--far", "1.5"]) == 2
    assert "--far must lie in (0, 1)" in capsys.readouterr().err
    assert main([SHIPPED, "--out", str(out), "--runs", "0"]) == 2
    assert "--runs must be a positive integer" in capsys.readouterr().err
    out.write_bytes(b"")
    assert main([SHIPPED, "--out", str(out)]) == 2
    assert "exists; pass --force" in capsys.readouterr().err
    assert main([str(tmp_path / "missing.ckpt"), "--out", str(tmp_path / "y.ckpt")]) == 2
    assert "missing.ckpt" in capsys.readouterr().err
    # --scenario: where a card's training scenario is not registered (a plant of your own)
    out.unlink()
    assert main([SHIPPED, "--out", str(out), "--scenario", "lfc_step"]) == 2
    assert "trained on 'four_tank' scenarios" in capsys.readouterr().err
    assert main([SHIPPED, "--out", str(out), "--scenario", "no_such_plant"]) == 2
    assert "--scenario: unknown scenario 'no_such_plant'" in capsys.readouterr().err
    # a CLI fuzzer: --seed -1 was refused as "seed must be …", naming no option
    with pytest.raises(SystemExit):
        main([SHIPPED, "--out", str(out), "--seed", "-1"])
    assert "--seed must be an integer >= 0; got -1" in capsys.readouterr().err
    # a docs trial: the restart on a particle filter's network was refused in internal names
    assert main([SHIPPED, "--out", str(out), "--restart", "0.01"]) == 2
    assert (
        "--restart: the restart runs an uncompensated copy of a Gaussian filter against "
        "sensor attacks; this network runs in the pf filter"
    ) in capsys.readouterr().err


def test_calibrate_says_when_its_runs_are_too_few_for_the_target(tmp_path, capsys):
    """``--runs 1 --far 1e-6`` succeeded without a word: 2 runs × 100 steps expect 2 alarms
    at 1 %, and the threshold rests on a handful of scores."""
    assert main([SHIPPED, "--out", str(tmp_path / "x.ckpt"), "--runs", "2", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "on 2 other attack-free runs" in out
    assert "note: Few calibration steps for the 1 % target (200 steps: 2 alarms " in out
    assert "about 1.5 % in expectation" in out and "give more --runs" in out


def test_calibrate_says_when_its_alarms_cluster_in_a_few_runs(tmp_path, capsys, monkeypatch):
    """Scores whose 20 calibration alarms at 1 % all fall in one of 20 runs (the other runs'
    scores below every one of them): the dispersion of the per-run counts, (R − 1) D =
    19² + 19 = 380 with c̄ = 1, far above χ²₁₉'s 1 − 1e-4 quantile, worth 20 · 19 / 380 = 1
    independent alarm. The card records it and the command says to give more runs (a trial
    met 0.35 % on the check runs, 1.39 % on 2,000 fresh ones, without a word)."""
    import json

    from difffilter.train import calibrate as cal_mod

    gen = torch.Generator().manual_seed(0)
    scores = torch.rand(20, 100, generator=gen, dtype=torch.float64)
    scores[0, :50] = 2.0 + torch.arange(50, dtype=torch.float64)  # one run's burst
    monkeypatch.setattr(cal_mod, "_scores", lambda *args: (scores, None))
    out = tmp_path / "x.ckpt"
    assert main([SHIPPED, "--out", str(out), "--runs", "20", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "note: the 20 alarms on the calibration runs cluster in a few of the 20 runs" in printed
    assert "(worth 1.0 independent ones)" in printed and "give more --runs" in printed
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["calibration"]["clustered"] == {"alarms": 20, "effective_alarms": 1.0}
    # alarms spread over the runs: nothing said, nothing recorded
    monkeypatch.setattr(cal_mod, "_scores", lambda *args: (scores[1:].repeat(2, 1), None))
    assert main([SHIPPED, "--out", str(out), "--runs", "38", "--no-progress", "--force"]) == 0
    assert "cluster" not in capsys.readouterr().out
    assert "clustered" not in json.loads(out.with_suffix(".json").read_text())["calibration"]


def test_calibrate_says_when_the_check_runs_miss_the_rate(tmp_path, capsys, monkeypatch):
    """A trial's own plant (8 runs × 60 steps at 5 %): 5.00 % on the calibration runs, 13.3 %
    on the check runs and 9.8 % on fresh ones, and no note (24 alarms expected, none
    clustered). The check runs' rate outside the acceptance's band [α/2, 2α] now says so.
    Scripted: uniform calibration scores; check scores from the same law (inside the band:
    nothing said), then shifted up by half the threshold's tail (3 % at a 1 % target)."""
    from difffilter.train import calibrate as cal_mod

    gen = torch.Generator().manual_seed(0)
    fitted = torch.rand(40, 100, generator=gen, dtype=torch.float64)
    same = torch.rand(40, 100, generator=gen, dtype=torch.float64)
    for checked, said in ((same, False), (same + 0.02, True)):
        draws = iter([(fitted, None), (checked, None)])
        monkeypatch.setattr(cal_mod, "_scores", lambda *args, d=draws: next(d))
        out = tmp_path / "x.ckpt"
        assert main([SHIPPED, "--out", str(out), "--runs", "40", "--no-progress", "--force"]) == 0
        printed = capsys.readouterr().out
        rate = json.loads(out.with_suffix(".json").read_text())["calibration"]["measured_on_check"]
        assert (rate > 0.02) is said, rate
        assert ("outside [0.5 %, 2 %]" in printed) is said, printed
        assert (
            "does not keep its rate on other runs of this size; give more --runs" in printed
        ) is said


def test_a_card_of_an_unregistered_scenario_is_calibrated_on_the_scenario_named(
    tmp_path, capsys, monkeypatch, isolated_registry
):
    """A checkpoint trained on a plant of one's own records the scenario's registered name,
    which a new process does not know: it said 'unknown scenario' with no way round it."""
    import dataclasses

    from difffilter.models.neural_estimator import (
        load_estimator_checkpoint,
        save_estimator_checkpoint,
    )

    net, card = load_estimator_checkpoint(SHIPPED, dtype=None)
    renamed = tmp_path / "own.ckpt"
    save_estimator_checkpoint(renamed, net, dataclasses.replace(card, scenario="my_own_tanks"))
    out = tmp_path / "calibrated.ckpt"
    assert main([str(renamed), "--out", str(out), "--runs", "2", "--no-progress"]) == 2
    assert (
        "--scenario package.module:object, or the YAML file's path from this folder"
        in capsys.readouterr().err
    )
    argv = [str(renamed), "--out", str(out), "--runs", "2", "--no-progress"]
    assert main([*argv, "--scenario", "four_tank_bias"]) == 0
    assert "of four_tank_bias" in capsys.readouterr().out
    # the JSON card beside it names the scenario as fit was given it (a user trial had to
    # name it again): a YAML file here, which a new process loads
    (tmp_path / "my_tank_plant.py").write_text(
        "from difffilter.models.four_tank import FourTankModel\n"
        "def tanks(dtype):\n    return FourTankModel(dtype=dtype)\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    plant = tmp_path / "my_tanks.yaml"
    plant.write_text("name: my_own_tanks\nfamily: four_tank\nplant: {model: my_tank_plant:tanks}\n")
    from difffilter.models.neural_estimator import checkpoint_sha256

    card_json = {"sha256": checkpoint_sha256(renamed), "model_config": {"scenario": str(plant)}}
    renamed.with_suffix(".json").write_text(json.dumps(card_json))
    out.unlink()
    out.with_suffix(".json").unlink()
    code = main(argv)
    assert code == 0, capsys.readouterr().err
    assert "of my_own_tanks" in capsys.readouterr().out


def test_old_cards_name_the_entry_that_evaluates_them():
    _, grad = load_estimator_checkpoint(SHIPPED)
    _, ekf = load_estimator_checkpoint("checkpoints/robot_nn_ekf.ckpt")
    _, pf_ekf = load_estimator_checkpoint("checkpoints/four_tank_nn_ekf.ckpt")
    assert [estimator_name(c) for c in (grad, ekf, pf_ekf)] == [
        "pf_nn_grad", "gaussian_nn_ekf", "pf_nn_ekf"
    ]  # fmt: skip


def test_calibrate_sets_the_restart_it_runs_and_chooses_the_threshold_with(
    tmp_path, capsys, monkeypatch
):
    """``--restart α`` (and ``--reject ρ``) are in the card before the scores are taken: the
    threshold is the one the estimator so run meets, the card's check is recomputed for it
    (on the file so configured, with the card's seed and runs), and ``off`` removes them."""
    from difffilter.models.lfc_estimators import build_estimator
    from difffilter.train import export

    checked = []  # (the file's card, seed, runs) of every recomputed check

    def check_metric(
        path, *, seed, runs, scenario=None
    ):  # the real one is tested on the shipped files
        checked.append((load_estimator_checkpoint(path)[1], seed, runs))
        return {"metric": "attack_rmse", "seed": seed, "runs": runs, "value": 0.125}

    monkeypatch.setattr(export, "check_metric", check_metric)

    plain = _uncalibrated("checkpoints/lfc_nn_grad.ckpt", tmp_path / "plain.ckpt")
    net, card = load_estimator_checkpoint(plain)
    card = dataclasses.replace(card, restart=None)
    save_estimator_checkpoint(plain, net, card)
    shipped_json = Path("checkpoints/lfc_nn_grad.json").read_text()
    # (its JSON card says what the card inside says, as export and calibrate write it)
    document = {**json.loads(shipped_json), "sha256": checkpoint_sha256(plain),
                "observer": card.to_dict()}  # fmt: skip
    plain.with_suffix(".json").write_text(json.dumps(document))  # its check, to be recomputed
    on, off = tmp_path / "on.ckpt", tmp_path / "off.ckpt"
    cal_on = calibrate_checkpoint(plain, on, far=0.05, runs=2, progress=False, restart=0.01,
                                  reject=0.02)  # fmt: skip
    cal_off = calibrate_checkpoint(on, off, far=0.05, runs=2, progress=False, restart=None,
                                   reject=None)  # fmt: skip
    on_card, off_card = load_estimator_checkpoint(on)[1], load_estimator_checkpoint(off)[1]
    assert on_card.restart == 0.01 == cal_on["restart"]
    assert on_card.reject == 0.02 == cal_on["reject"]
    assert off_card.restart is None and "restart" not in cal_off
    assert off_card.reject is None and "reject" not in cal_off
    check = json.loads(on.with_suffix(".json").read_text())["check"]
    assert "restart 0.01, confirm None, reject 0.02" in check["note"] and check["value"] == 0.125
    seed, runs = document["check"]["seed"], document["check"]["runs"]
    assert [(c.restart, c.reject, s, r) for c, s, r in checked] == [
        (0.01, 0.02, seed, runs), (None, None, seed, runs)
    ]  # fmt: skip
    assert cal_on["threshold"] != cal_off["threshold"]  # other scores, another threshold
    # the threshold is the one the restarted estimator's scores give on the calibration runs
    scenario = registry.get("lfc_random_attacks")
    fitted = _free_scores(scenario, "kf_nn_grad", on, 2, cal_on["seed"]).scores
    above, allowed = int((fitted > cal_on["threshold"]).sum()), math.floor(0.05 * fitted.numel())
    assert above <= allowed < int((fitted >= cal_on["threshold"]).sum())
    # the entry runs the card's restart
    ctx = SimpleNamespace(checkpoint_for=lambda name: on, cache={}, scenario=scenario,
                          checkpoint_users=[])  # fmt: skip
    built = build_estimator("kf_nn_grad", ctx)
    assert (built.restart, built.reject) == (0.01, 0.02)
    assert main(["checkpoints/lfc_nn_grad.ckpt", "--out", str(tmp_path / "x.ckpt"),
                 "--restart", "sometimes"]) == 2  # fmt: skip
    assert "--restart must be a rate in (0, 1) or off" in capsys.readouterr().err
    assert main(["checkpoints/lfc_nn_grad.ckpt", "--out", str(tmp_path / "x.ckpt"),
                 "--reject", "2"]) == 2  # fmt: skip
    assert "--reject must be a false-alarm rate in" in capsys.readouterr().err


def test_calibrate_to_a_place_it_cannot_write_says_so_before_scoring(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert main([SHIPPED, "--out", str(blocker / "x.ckpt"), "--runs", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out: cannot make the folder" in err[0]
    assert main([SHIPPED, "--out", str(tmp_path / "x.json")]) == 2
    assert "--out must name a .ckpt file" in capsys.readouterr().err


@pytest.mark.parametrize("writes", [False, True])
def test_an_interrupted_calibration_says_whether_out_was_written(
    tmp_path, monkeypatch, capsys, writes
):
    """Ctrl-C in ``difffilter-train calibrate`` printed a 22-frame traceback (a training
    trial); it now says what stands at ``--out``: nothing (rerun), or a file being written,
    checkpoint and card possibly unmatched (rerun with ``--force``)."""
    from difffilter.train import calibrate as calibrate_module

    out = tmp_path / "cal.ckpt"

    def interrupted(src, dst, **kwargs):
        if writes:
            dst.write_bytes(b"part")
        raise KeyboardInterrupt

    monkeypatch.setattr(calibrate_module, "calibrate_checkpoint", interrupted)
    assert calibrate_module.main([str(tmp_path / "src.ckpt"), "--out", str(out)]) == 130
    err = capsys.readouterr().err
    if writes:
        assert f"interrupted: {out} was being written; rerun the same command with --force" in err
    else:
        assert f"interrupted: nothing was written to {out}; rerun the same command" in err


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(p.stem for p in Path("checkpoints").glob("*.ckpt")))
def test_every_shipped_threshold_is_what_its_cards_calibration_computes_today(name, tmp_path):
    """Calibrating a shipped checkpoint again, on the runs and seed its card records, gives
    the threshold it carries (a checkpoint trial: the tracking card's 0.119265 had been
    chosen before the particle filter averaged wrapped bearings as residuals about one point,
    6bc5bba; the same runs now give 0.118682, recalibrated)."""
    src = Path("checkpoints") / f"{name}.ckpt"
    recorded = json.loads(src.with_suffix(".json").read_text())["calibration"]
    entry = calibrate_checkpoint(src, tmp_path / "again.ckpt", far=recorded["target"],
                                 runs=recorded["runs"], seed=recorded.get("master_seed", 5),
                                 progress=False)  # fmt: skip
    assert entry["seed"] == recorded["seed"] and entry["check_seed"] == recorded["check_seed"]
    assert entry["threshold"] == pytest.approx(recorded["threshold"], rel=1e-9, abs=1e-12)
    assert entry["measured_on_check"] == pytest.approx(recorded["measured_on_check"], abs=1e-12)
