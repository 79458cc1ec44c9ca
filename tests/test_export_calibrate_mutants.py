"""Mutation review of ``train/export.py`` (``difffilter-train export``, the export card) and
``train/calibrate.py`` (``difffilter-train calibrate``): the threshold against an empirical
quantile computed by hand in numpy, the measured rates against numpy counts, the seeds and
digests against ``hashlib``, the card's fields against the module docstrings and
docs/architecture.md. The attack-free scores are stubbed (``_scores``) so that every
calibration here is instant and its scores known."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import shutil
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from difffilter.models.neural_estimator import (
    load_estimator_checkpoint,
    save_estimator_checkpoint,
    weights_sha256,
)
from difffilter.train import calibrate as calibrate_module
from difffilter.train import export as export_module
from difffilter.train.calibrate import calibrate_checkpoint
from difffilter.train.export import ExportEstimator, _whole_epochs, export

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "checkpoints" / "four_tank_nn_grad.ckpt"


def _sha256(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _stream_seed(master: int, name: str) -> int:
    """``Streams(master).seed_of(name)`` as its docstring defines it: the first 8 bytes of
    sha256("<master>/<name>"), little-endian, shifted right by one."""
    digest = hashlib.sha256(f"{master}/{name}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def _by_hand_threshold(scores: np.ndarray, far: float) -> float:
    """τ_α = the smallest τ with #{s > τ} ≤ ⌊α n⌋, by brute force over the candidate values
    (every score, and −∞), float64."""
    s = scores.ravel().astype(np.float64)
    allowed = math.floor(far * s.size + 1e-9)
    candidates = sorted(set(s.tolist()) | {-math.inf})
    return next(t for t in candidates if int((s > t).sum()) <= allowed)


class Calls(list):
    continuous = False  # integer multiples of 1/4 (ties), else uniform draws (no ties)
    check_value = 0.0123456789  # what the stubbed check_metric gives (_source's card's)


def _stub_values(seed: int, runs: int, continuous: bool) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed % (2**31))
    if continuous:
        return torch.rand((runs, 25), generator=gen, dtype=torch.float64)
    return torch.randint(0, 12, (runs, 25), generator=gen).double() / 4


@pytest.fixture
def stub_scores(monkeypatch):
    """Replace the attack-free scoring by integer-valued scores (ties on purpose) of a
    generator seeded by the stream seed; records every call's arguments."""
    calls = Calls()

    def scores(scenario, name, path, runs, seed, progress):
        calls.append(SimpleNamespace(scenario=scenario.name, name=name, path=Path(path),
                                     card=load_estimator_checkpoint(path)[1], runs=runs,
                                     seed=seed, progress=progress))  # fmt: skip
        return _stub_values(seed, runs, calls.continuous), "stub statistic"

    def check_metric(path, *, seed, runs, scenario=None):  # (calibrate recomputes the card's check)
        return {"metric": "attack_rmse", "seed": seed, "runs": runs, "value": calls.check_value}

    monkeypatch.setattr(calibrate_module, "_scores", scores)
    monkeypatch.setattr(export_module, "check_metric", check_metric)
    return calls


def _source(tmp_path, **changes):
    """A copy of the shipped four-tank checkpoint and its JSON card (``changes``: to the card
    inside, the JSON card's sha256 updated)."""
    src = tmp_path / "src" / "net.ckpt"
    src.parent.mkdir(parents=True)
    net, card = load_estimator_checkpoint(SHIPPED, dtype=None)
    card = dataclasses.replace(card, **changes)
    save_estimator_checkpoint(src, net, card)
    document = json.loads(SHIPPED.with_suffix(".json").read_text())
    # (the JSON card says what the card inside says, as export and calibrate write it)
    document["sha256"], document["observer"] = _sha256(src), card.to_dict()
    document["check"] = {"metric": "attack_rmse", "seed": 31, "runs": 3, "value": 0.0123456789}
    src.with_suffix(".json").write_text(json.dumps(document))
    return src, document


def test_the_threshold_and_rates_are_the_hand_computed_quantile_and_counts(tmp_path, stub_scores):
    """τ is the empirical quantile of the calibration scores computed by brute force in
    numpy; the measured rates are numpy's fractions of strict exceedances on each set; the
    two sets come from the seeds sha256 gives the two streams of the master seed; every
    field of the ``calibration`` entry is the module docstring's."""
    src, document = _source(tmp_path, threshold=0.7)
    out = tmp_path / "out" / "cal.ckpt"
    cal = calibrate_checkpoint(src, out, far=0.1, runs=3, seed=7, progress=False)
    fit_seed = _stream_seed(7, "checkpoint-calibration")
    check_seed = _stream_seed(7, "checkpoint-calibration/check")
    assert [c.seed for c in stub_scores] == [fit_seed, check_seed]
    assert [c.runs for c in stub_scores] == [3, 3]
    assert all(c.path == src and c.scenario == "four_tank_bias" for c in stub_scores)
    assert all(c.name == "pf_nn_grad" and c.progress is False for c in stub_scores)
    fitted = _stub_values(fit_seed, 3, False).numpy()
    checked = _stub_values(check_seed, 3, False).numpy()
    tau = _by_hand_threshold(fitted, 0.1)
    assert cal["threshold"] == tau
    assert (fitted > tau).sum() <= math.floor(0.1 * fitted.size) < (fitted >= tau).sum()
    assert cal["measured_on_calibration"] == pytest.approx(np.mean(fitted > tau), abs=1e-15)
    assert cal["measured_on_check"] == pytest.approx(np.mean(checked > tau), abs=1e-15)
    assert cal["measured_on_calibration"] != np.mean(fitted >= tau)  # ties matter here
    expected = {"target": 0.1, "estimator": "pf_nn_grad", "scenario": "four_tank_bias",
                "runs": 3, "score": "stub statistic", "steps": 25, "master_seed": 7,
                "seed": fit_seed, "check_seed": check_seed, "threshold": tau,
                "previous_threshold": 0.7, "num_particles": 100}  # fmt: skip
    assert {k: cal[k] for k in expected} == expected
    assert set(cal) == {*expected, "measured_on_calibration", "measured_on_check", "time_s"}
    assert 0.0 <= cal["time_s"] < 60.0
    # the checkpoint's card and the JSON card beside it
    net, card = load_estimator_checkpoint(out)
    assert card.threshold == tau and card.target_false_alarm_rate == 0.1
    assert card.estimator == "pf_nn_grad" and card.extra["calibration"] == cal
    doc = json.loads(out.with_suffix(".json").read_text())
    assert doc["sha256"] == _sha256(out) and doc["checkpoint"] == "cal.ckpt"
    assert doc["name"] == document["name"] == "four_tank_nn_grad"  # kept from the source
    assert doc["weights_sha256"] == weights_sha256(SHIPPED)  # the weights unchanged
    assert doc["observer"] == card.to_dict() and doc["calibration"] == cal
    assert doc["check"] == document["check"]  # the same figure: kept as it was
    assert doc["model_config"] == document["model_config"]
    src_net, _ = load_estimator_checkpoint(SHIPPED, dtype=None)
    for a, b in zip(net.state_dict().values(), src_net.state_dict().values(), strict=True):
        assert torch.equal(a, b)


def test_a_check_the_library_no_longer_gives_is_recomputed_with_the_value_before(
    tmp_path, stub_scores
):
    """A calibration that changes nothing of how the estimator runs recomputes the card's
    check too: the tracking card's had kept its export's figure after the particle filter's
    numbers moved (a trial). The new value comes with the one before."""
    src, document = _source(tmp_path)
    stub_scores.check_value = 0.5
    calibrate_checkpoint(src, tmp_path / "cal.ckpt", far=0.1, runs=3, progress=False)
    check = json.loads((tmp_path / "cal.json").read_text())["check"]
    assert check == {**document["check"], "value": 0.5,
                     "note": "recomputed by difffilter-train calibrate (before: 0.0123457)"}  # fmt: skip


def test_a_check_on_a_plant_this_process_cannot_load_is_kept_or_left_out(
    tmp_path, stub_scores, capsys
):
    """A card trained on a plant of one's own, calibrated on a built-in plant of its family
    (``--scenario four_tank_bias``, the documented route): the check, made on that plant,
    cannot be recomputed here. Kept as it was where nothing changed how the estimator runs
    (a review: the calibration had failed after its scoring, writing nothing), left out
    where its restart changed; said on stderr either way."""
    for restart in (None, 0.05):
        src, document = _source(tmp_path / str(restart), scenario="my_own_tanks", restart=None,
                                reject=None, confirm=None, filter="ekf")  # fmt: skip
        document["check"]["scenario"] = "my_own_tanks"
        src.with_suffix(".json").write_text(json.dumps(document))
        out = tmp_path / str(restart) / "cal.ckpt"
        calibrate_checkpoint(src, out, far=0.1, runs=3, progress=False,
                             scenario="four_tank_bias", restart=restart)  # fmt: skip
        doc = json.loads(out.with_suffix(".json").read_text())
        if restart is None:
            assert doc["check"] == document["check"]
            assert "'my_own_tanks', which is not registered here: kept as it was" in (
                capsys.readouterr().err)  # fmt: skip
        else:
            assert "check" not in doc
            assert "not registered here: left out (the estimator runs otherwise now)" in (
                capsys.readouterr().err)  # fmt: skip


@pytest.mark.parametrize("far", [0.04, 0.5, 0.29])
def test_the_threshold_is_the_quantile_at_other_rates_and_the_default_runs(
    far, tmp_path, stub_scores
):
    """At other rates (0.29 · n: the floor of a product with round-off) τ is the brute-force
    quantile; without ``runs`` the scenario's own number of runs is used (four_tank_bias:
    its registered ``runs``); a source without a JSON card gets a card named after --out."""
    from difffilter.models import registry

    src = tmp_path / "plain.ckpt"
    shutil.copyfile(SHIPPED, src)  # no card beside it
    out = tmp_path / "named.ckpt"
    cal = calibrate_checkpoint(src, out, far=far, seed=3, progress=False)
    runs = registry.get("four_tank_bias").runs
    assert cal["runs"] == runs and [c.runs for c in stub_scores] == [runs, runs]
    fitted = _stub_values(_stream_seed(3, "checkpoint-calibration"), runs, False).numpy()
    assert cal["threshold"] == _by_hand_threshold(fitted, far)
    doc = json.loads(out.with_suffix(".json").read_text())
    assert doc["name"] == "named" and "check" not in doc
    assert doc["sha256"] == _sha256(out)


@pytest.mark.parametrize("far", [0.1, 0.29, 0.01])
def test_the_threshold_of_distinct_scores_lets_exactly_floor_alpha_n_through(
    far, tmp_path, stub_scores
):
    """Distinct scores, α n an integer (4 runs × 25 steps: 10, 29 — 0.29 · 100 is
    28.999999999999996 in floating point — and 1): exactly ⌊α n⌋ calibration scores exceed
    τ, which is the (⌊α n⌋ + 1)-th largest (numpy's sort), and the measured rate is α."""
    stub_scores.continuous = True
    cal = calibrate_checkpoint(SHIPPED, tmp_path / "d.ckpt", far=far, runs=4, progress=False)
    fitted = _stub_values(_stream_seed(5, "checkpoint-calibration"), 4, True).numpy()
    k = round(far * 100)
    assert cal["threshold"] == np.sort(fitted.ravel())[::-1][k] == _by_hand_threshold(fitted, far)
    assert cal["measured_on_calibration"] == pytest.approx(k / 100, abs=1e-15)


def test_a_changed_restart_scores_a_file_so_configured_and_recomputes_the_check(
    tmp_path, stub_scores, monkeypatch
):
    """``restart``/``reject`` given: the scores are those of a temporary file whose card
    carries them (not the source), the calibration records them, and the check is
    recomputed on that file with the source card's seed and runs."""
    checked = []

    def check_metric(path, *, seed, runs, scenario=None):
        checked.append((load_estimator_checkpoint(path)[1].restart, seed, runs))
        return {"metric": "attack_rmse", "seed": seed, "runs": runs, "value": 0.25}

    monkeypatch.setattr(export_module, "check_metric", check_metric)
    # (a card of a Gaussian filter: calibrate refuses a restart of a particle filter's network)
    src, document = _source(tmp_path, restart=None, reject=None, confirm=None, filter="ekf")
    out = tmp_path / "r.ckpt"
    cal = calibrate_checkpoint(src, out, far=0.2, runs=2, progress=False, restart=0.05,
                               reject=0.1)  # fmt: skip
    assert all(c.path != src for c in stub_scores)
    assert [(c.card.restart, c.card.reject) for c in stub_scores] == [(0.05, 0.1)] * 2
    assert cal["restart"] == 0.05 and cal["reject"] == 0.1 and "confirm" not in cal
    old = document["check"]
    assert checked == [(0.05, old["seed"], old["runs"])]
    doc = json.loads(out.with_suffix(".json").read_text())
    assert doc["check"]["value"] == 0.25
    assert doc["check"]["note"].endswith(f"(before: {old['value']:.6g})")
    card = load_estimator_checkpoint(out)[1]
    assert (card.restart, card.reject, card.confirm) == (0.05, 0.1, None)


@pytest.mark.parametrize("far", [0.0, 1.0, -0.1, 1.5])
def test_a_rate_outside_the_open_interval_is_refused(far, tmp_path, stub_scores):
    """``far`` must lie in (0, 1): both ends are refused before any scoring."""
    with pytest.raises(ValueError, match=r"--far must lie in \(0, 1\)"):
        calibrate_checkpoint(SHIPPED, tmp_path / "x.ckpt", far=far, runs=1, progress=False)
    assert stub_scores == []


@pytest.mark.parametrize("runs", [0, -1, True, 2.0])
def test_runs_must_be_a_positive_integer(runs, tmp_path, stub_scores):
    """``runs`` 0, negative, a bool or a float is refused; 1 is accepted."""
    with pytest.raises(ValueError, match="--runs must be a positive integer"):
        calibrate_checkpoint(SHIPPED, tmp_path / "x.ckpt", runs=runs, progress=False)
    cal = calibrate_checkpoint(SHIPPED, tmp_path / "x.ckpt", far=0.5, runs=1, progress=False)
    assert cal["runs"] == 1


def test_calibrate_refuses_an_existing_out_and_a_confirm_without_restart(tmp_path, stub_scores):
    """An existing --out (or its card alone) is refused without ``force`` and replaced with
    it; the source itself needs ``force``; ``confirm`` without a restart rate is refused."""
    src, _ = _source(tmp_path, restart=None, confirm=None)
    out = tmp_path / "o.ckpt"
    out.with_suffix(".json").write_text("{}")
    with pytest.raises(ValueError, match="exists; pass --force"):
        calibrate_checkpoint(src, out, far=0.5, runs=1, progress=False)
    calibrate_checkpoint(src, out, far=0.5, runs=1, progress=False, force=True)
    assert json.loads(out.with_suffix(".json").read_text())["sha256"] == _sha256(out)
    with pytest.raises(ValueError, match="is the source itself"):
        calibrate_checkpoint(src, src, far=0.5, runs=1, progress=False)
    with pytest.raises(ValueError, match="needs a restart rate too"):
        calibrate_checkpoint(src, tmp_path / "c.ckpt", confirm=0.1, runs=1, progress=False)
    # a card without a training scenario
    src2, _ = _source(tmp_path / "b", scenario=None)
    with pytest.raises(ValueError, match="names no training scenario"):
        calibrate_checkpoint(src2, tmp_path / "d.ckpt", runs=1, progress=False)


def test_calibrate_main_reports_the_rates_and_the_resolution_note(tmp_path, stub_scores, capsys):
    """The command line prints the threshold, the rates in % and the runs; at a target with
    fewer than the resolved number of expected alarms it adds the note."""
    from difffilter.train.calibrate import main

    out = tmp_path / "m.ckpt"
    assert main([str(SHIPPED), "--out", str(out), "--far", "0.2", "--runs", "1",
                 "--seed", "4", "--no-progress"]) == 0  # fmt: skip
    text = capsys.readouterr().out
    cal = json.loads(out.with_suffix(".json").read_text())["calibration"]
    assert cal["master_seed"] == 4 and cal["target"] == 0.2 and cal["runs"] == 1
    assert stub_scores[0].progress is False
    assert f"alarms above {cal['threshold']:.6g} (stub statistic)" in text
    assert f"{100 * cal['measured_on_calibration']:.2f} % on the calibration runs" in text
    assert "on 1 other attack-free run of four_tank_bias (target 20 %)" in text
    assert "note:" in text  # 0.2 × 25 = 5 expected alarms: too few


def test_calibrate_main_maps_rate_options(tmp_path, stub_scores):
    """``off`` is ``None``, ``keep`` the card's, a number the rate."""
    from difffilter.train.calibrate import KEEP, _rate_option

    assert _rate_option("off", "restart") is None
    assert _rate_option(KEEP, "restart") == KEEP
    assert _rate_option("0.25", "restart") == 0.25
    with pytest.raises(ValueError, match="--confirm must be a rate"):
        _rate_option("often", "confirm")


# ------------------------------------------------------------------------------ export


def test_exporting_an_export_copies_its_bytes_and_updates_its_card(tmp_path, capsys):
    """An exported file is copied byte for byte (sha256 by hashlib the same); its card is
    the source's with ``checkpoint``, ``sha256``, ``weights_sha256`` and ``exported_from``
    set and its ``name`` kept; an existing --out is refused without --force."""
    from difffilter.train.export import main

    out = tmp_path / "ship" / "copy.ckpt"
    assert main([str(SHIPPED), "--out", str(out)]) == 0
    assert out.read_bytes() == SHIPPED.read_bytes()
    source_card = json.loads(SHIPPED.with_suffix(".json").read_text())
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["sha256"] == _sha256(SHIPPED) == _sha256(out)
    assert card["checkpoint"] == "copy.ckpt" and card["exported_from"] == str(SHIPPED)
    assert card["name"] == source_card["name"] and card["weights_sha256"] == weights_sha256(out)
    changed = {"checkpoint", "exported_from"}
    assert {k: v for k, v in card.items() if k not in changed} == {
        k: v for k, v in source_card.items() if k not in changed
    }
    assert f"sha256 {_sha256(out)}" in capsys.readouterr().out
    before = out.read_bytes()
    other = ROOT / "checkpoints" / "four_tank_nn_ekf.ckpt"
    assert main([str(other), "--out", str(out)]) == 2
    assert "exists; pass --force" in capsys.readouterr().err and out.read_bytes() == before
    assert main([str(other), "--out", str(out), "--force"]) == 0
    assert _sha256(out) == _sha256(other)
    with pytest.raises(ValueError, match="is the source itself"):
        export(out, out, force=True)


def test_an_export_without_a_card_beside_it_is_named_after_out(tmp_path):
    src = tmp_path / "bare.ckpt"
    shutil.copyfile(SHIPPED, src)
    out = export(src, tmp_path / "dest.ckpt")
    card = json.loads(out.with_suffix(".json").read_text())
    assert card == {"checkpoint": "dest.ckpt", "sha256": _sha256(src), "name": "dest",
                    "weights_sha256": weights_sha256(SHIPPED), "exported_from": str(src)}  # fmt: skip


def _lightning_blob(callbacks, **more):
    net, card = load_estimator_checkpoint(SHIPPED, dtype=None)
    return {"pytorch-lightning_version": "2.6.6", "epoch": 0, "global_step": 7,
            "state_dict": {f"estimator.{k}": v for k, v in net.state_dict().items()},
            "hyper_parameters": {"hidden": 16, "sizes": (3, 4), "_private": 1},
            "datamodule_hyper_parameters": {"batch": (1, 2), "_x": 0},
            "difffilter_estimator_config": net.config(), "difffilter_observer": card.to_dict(),
            "callbacks": callbacks, **more}  # fmt: skip


def test_a_lightning_export_records_the_first_monitor_min_mode_and_its_own_best(tmp_path):
    """The card of a Lightning checkpoint: epochs = epoch index + 1, the configs without
    private keys and tuples as lists, ``min`` where the callback's key says no ``max``, the
    first ModelCheckpoint's score only, ``best_val_score`` only where the callback's best
    file is this one; the new file's sha256 by hashlib; the card named after --out."""
    first = "ModelCheckpoint{'monitor': 'val/loss', 'mode': 'min'}"
    second = "ModelCheckpoint{'monitor': 'val/auc', 'mode': 'max'}"
    callbacks = {
        "Other": {"train_time_s": None},
        first: {"monitor": "val/loss", "current_score": torch.tensor(0.5),
                "best_model_score": torch.tensor(0.25), "best_model_path": "/x/best.ckpt"},
        second: {"monitor": "val/auc", "current_score": torch.tensor(0.9),
                 "best_model_score": torch.tensor(0.95), "best_model_path": "/x/best.ckpt"},
        "ExportEstimator": {"train_time_s": 3.5},
    }  # fmt: skip
    torch.save(_lightning_blob(callbacks), tmp_path / "best.ckpt")
    torch.save(_lightning_blob({first: {**callbacks[first], "best_model_path": "/x/o.ckpt"}},
                               epoch=None), tmp_path / "last.ckpt")  # fmt: skip
    out = export(tmp_path / "best.ckpt", tmp_path / "e" / "best_out.ckpt")
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["sha256"] == _sha256(out) and card["name"] == "best_out"
    assert card["checkpoint"] == "best_out.ckpt"
    assert card["weights_sha256"] == weights_sha256(SHIPPED)
    assert card["model_config"] == {"hidden": 16, "sizes": [3, 4]}
    assert card["data_config"] == {"batch": [1, 2]}
    assert card["epochs"] == 1 and card["global_step"] == 7
    assert card["lightning_version"] == "2.6.6" and card["torch_version"] == torch.__version__
    assert card["selected_checkpoint"] == "best.ckpt" and card["train_time_s"] == 3.5
    assert card["monitor"] == {"metric": "val/loss", "mode": "min"}
    assert card["val_score"] == 0.5 and card["best_val_score"] == 0.25
    _, est_card = load_estimator_checkpoint(SHIPPED)
    assert card["observer"] == est_card.to_dict()
    last = json.loads(export(tmp_path / "last.ckpt", tmp_path / "l.ckpt")
                      .with_suffix(".json").read_text())  # fmt: skip
    assert last["epochs"] is None and "best_val_score" not in last and "train_time_s" not in last
    # not the callback's best file: its current_score is the last improvement's, not these
    # weights' (a trial: an export of last.ckpt reported the best epoch's score)
    assert last["val_score"] is None
    # the task's record of the validation of the epoch the file was written at: these weights'
    other = {first: {**callbacks[first], "best_model_path": "/x/o.ckpt"}}
    for epoch, want in ((0, 0.7), (1, None)):  # (a record of another epoch is no record)
        torch.save(_lightning_blob(other, difffilter_validation={
            "epoch": epoch, "metrics": {"val/loss": 0.7, "val/auc": 0.8}}), tmp_path / "own.ckpt")  # fmt: skip
        own = json.loads(export(tmp_path / "own.ckpt", tmp_path / f"o{epoch}.ckpt")
                         .with_suffix(".json").read_text())  # fmt: skip
        assert own["val_score"] == want


def test_whole_epochs_drops_only_a_cut_epoch():
    """``current_epoch`` less one exactly where the last epoch ran some but not all of its
    batches (0 < ready < total) and an epoch was counted."""

    def trainer(epoch, ready, total):
        progress = SimpleNamespace(current=SimpleNamespace(ready=ready))
        loop = SimpleNamespace(epoch_loop=SimpleNamespace(batch_progress=progress))
        return SimpleNamespace(current_epoch=epoch, fit_loop=loop, num_training_batches=total)

    assert _whole_epochs(trainer(3, 2, 5)) == 2
    assert _whole_epochs(trainer(3, 5, 5)) == 3  # the epoch ended whole
    assert _whole_epochs(trainer(3, 0, 5)) == 3
    assert _whole_epochs(trainer(3, 1, 5)) == 2
    assert _whole_epochs(trainer(3, 4, 5)) == 2
    assert _whole_epochs(trainer(0, 2, 5)) == 0
    assert _whole_epochs(trainer(1, 2, 5)) == 0
    assert _whole_epochs(trainer(2, 2, float("inf"))) == 2


def test_the_callback_counts_the_training_time_across_a_resume(tmp_path, capsys):
    """``train_time_s`` is the seconds before the resume plus those since this fit started;
    ``None`` before a fit; Ctrl-C while exporting removes a file without its card only."""
    cb = ExportEstimator()
    assert cb.state_dict() == {"train_time_s": None}
    cb.load_state_dict({"train_time_s": 100.0})
    cb._start = time.time() - 2.0
    assert 102.0 <= cb.state_dict()["train_time_s"] < 110.0
    cb.load_state_dict({})
    assert 2.0 <= cb._train_time() < 10.0
    lone, paired = tmp_path / "lone.ckpt", tmp_path / "paired.ckpt"
    for path in (lone, paired):
        path.write_bytes(b"x")
    paired.with_suffix(".json").write_text("{}")
    cb._exporting = (lone, "src.ckpt")
    cb.on_exception(None, None, RuntimeError())
    assert lone.exists()  # not a Ctrl-C
    cb.on_exception(None, None, KeyboardInterrupt())
    assert not lone.exists() and cb._exporting is None
    assert "export it with: difffilter-train export src.ckpt --out" in capsys.readouterr().out
    cb._exporting = (paired, "src.ckpt")
    cb.on_exception(None, None, KeyboardInterrupt())
    assert paired.exists()


def test_the_entry_is_the_cards_own_else_named_from_its_filter_and_trainer(tmp_path, stub_scores):
    """``estimator_name`` (docstring): the card's ``estimator`` where it has one (here one
    that the filter and trainer would not give), else ``pf_nn_<trainer>`` for a particle
    filter and ``gaussian_nn_<trainer>`` otherwise; the calibration scores that entry, on a
    scenario of the card's family only."""
    from difffilter.train.calibrate import estimator_name

    _, card = load_estimator_checkpoint(SHIPPED)
    assert estimator_name(dataclasses.replace(card, estimator="my_entry")) == "my_entry"
    assert estimator_name(dataclasses.replace(card, estimator=None)) == "pf_nn_grad"
    assert estimator_name(dataclasses.replace(card, estimator=None, filter="ekf",
                                              trainer="ekf")) == "gaussian_nn_ekf"  # fmt: skip
    src, _ = _source(tmp_path, estimator="gaussian_nn_grad")
    cal = calibrate_checkpoint(src, tmp_path / "g.ckpt", far=0.5, runs=1, progress=False)
    assert cal["estimator"] == "gaussian_nn_grad" == stub_scores[0].name
    with pytest.raises(ValueError, match="trained on 'four_tank' scenarios"):
        calibrate_checkpoint(src, tmp_path / "h.ckpt", runs=1, progress=False,
                             scenario="lfc_step")  # fmt: skip


def test_a_plugin_scenario_named_in_the_json_card_is_the_one_calibrated_on(
    tmp_path, stub_scores, monkeypatch, isolated_registry
):
    """The JSON card's ``model_config.scenario`` naming a plug-in (``module:object``) is
    loaded and calibrated on (module docstring of ``_fit_scenario``), not the card's
    registered name: the stub sees the plug-in scenario's name and default runs."""
    (tmp_path / "r137_tank_plugin.py").write_text(
        "import dataclasses\n"
        "from difffilter.models import registry\n"
        "tanks = dataclasses.replace(registry.get('four_tank_bias'), name='r137_tanks',"
        " runs=3)\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    src, document = _source(tmp_path)
    document["model_config"] = {"scenario": "r137_tank_plugin:tanks"}
    src.with_suffix(".json").write_text(json.dumps(document))
    cal = calibrate_checkpoint(src, tmp_path / "p.ckpt", far=0.5, progress=False)
    assert cal["scenario"] == "r137_tanks" and cal["runs"] == 3
    assert [c.scenario for c in stub_scores] == ["r137_tanks"] * 2


def test_a_fits_export_takes_the_best_checkpoints_weights_and_score(tmp_path, monkeypatch):
    """``ExportEstimator.on_fit_end`` (a stub trainer and module, a real ``ModelCheckpoint``
    whose best file holds the shipped weights, without ``save_last``): the
    exported weights are the best file's (the shipped card's recorded ``weights_sha256``),
    the card names that file, its score and monitor, the file's sha256 (hashlib) and the
    whole epochs (2 counted, the last cut after 2 of 4 batches: 1); ``enabled=False``
    writes nothing."""
    import lightning.pytorch as pl

    monkeypatch.setattr(export_module, "check_metric", lambda path: {"value": 0.5})
    net, card = load_estimator_checkpoint(SHIPPED, dtype=None)
    best = tmp_path / "best.ckpt"
    state = net.state_dict()
    torch.save({"state_dict": {f"estimator.{k}": v for k, v in state.items()}}, best)
    net.load_state_dict({k: v - 1 for k, v in state.items()})  # where training ended

    class Module:
        estimator, hparams = net, {"hidden": 16, "_x": 1}

        def export_name(self):
            return "stub"

        def card(self):
            return card

        def load_state_dict(self, sd):
            net.load_state_dict({k.removeprefix("estimator."): v for k, v in sd.items()})

        def export_card(self, trainer, estimator):
            return {}

    mc = pl.callbacks.ModelCheckpoint(dirpath=tmp_path, monitor="val/auc", mode="max")
    mc.best_model_path, mc.best_model_score = str(best), 0.93
    mc.last_model_path = ""  # save_last off: no last.ckpt written
    progress = SimpleNamespace(current=SimpleNamespace(ready=2))
    trainer = SimpleNamespace(
        fast_dev_run=False, ckpt_path=None, log_dir=str(tmp_path / "run"),
        is_global_zero=True, callbacks=[mc], datamodule=None, global_step=9,
        callback_metrics={"val/auc": torch.tensor(0.9), "train/loss": torch.tensor(1.0)},
        current_epoch=2, num_training_batches=4,
        fit_loop=SimpleNamespace(epoch_loop=SimpleNamespace(batch_progress=progress)),
    )  # fmt: skip
    (tmp_path / "run").mkdir()
    out = tmp_path / "run" / "stub.ckpt"
    ExportEstimator(enabled=False).on_fit_end(trainer, Module())
    assert not out.exists()  # turned off: nothing written
    ExportEstimator().on_fit_end(trainer, Module())
    doc = json.loads(out.with_suffix(".json").read_text())
    shipped = json.loads(SHIPPED.with_suffix(".json").read_text())
    assert doc["weights_sha256"] == shipped["weights_sha256"]
    assert doc["sha256"] == _sha256(out) and doc["checkpoint"] == "stub.ckpt"
    assert doc["selected_checkpoint"] == "best.ckpt" and doc["best_val_score"] == 0.93
    assert doc["monitor"] == {"metric": "val/auc", "mode": "max"}
    assert doc["metrics_last_validation"] == {"val/auc": pytest.approx(0.9)}
    assert doc["model_config"] == {"hidden": 16} and doc["epochs"] == 1
    assert doc["global_step"] == 9 and doc["check"] == {"value": 0.5}


def test_calibrating_a_lightning_checkpoint_keeps_what_its_export_records(tmp_path, stub_scores):
    """A training run's Lightning checkpoint calibrated directly (``calibrate`` takes one) had
    a card of six keys: the configs, epochs and the plant's fingerprint were lost (a training
    trial). Its card is the export's, with the calibration."""
    from difffilter.models.plant_match import PLANT_FINGERPRINT, _recorded_plant

    blob = _lightning_blob({}, **{PLANT_FINGERPRINT: "ab" * 32})
    torch.save(blob, tmp_path / "last.ckpt")
    exported = export(tmp_path / "last.ckpt", tmp_path / "exp.ckpt")
    calibrate_checkpoint(exported, tmp_path / "a.ckpt", far=0.05, runs=4, progress=False)
    calibrate_checkpoint(tmp_path / "last.ckpt", tmp_path / "b.ckpt", far=0.05, runs=4,
                         progress=False)  # fmt: skip
    via_export = json.loads((tmp_path / "a.json").read_text())
    direct = json.loads((tmp_path / "b.json").read_text())
    assert sorted(direct) == sorted(via_export)
    for key in ("model_config", "data_config", "epochs", "global_step", "scenario_plant_sha256",
                "weights_sha256"):  # fmt: skip
        assert direct[key] == via_export[key], key
    assert {**direct["observer"], "extra": None} == {**via_export["observer"], "extra": None}
    assert direct["exported_from"] == str(tmp_path / "last.ckpt")
    assert direct["calibration"]["threshold"] == via_export["calibration"]["threshold"]
    assert _recorded_plant(tmp_path / "b.ckpt") == "ab" * 32
