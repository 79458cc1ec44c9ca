"""Mutation review of the learned estimator's cards: the checkpoint loader
(:mod:`difffilter.models.neural_estimator`), the estimator built from a card
(:func:`difffilter.models.learned_estimator.compose`) and ``difffilter-train calibrate``.

Each test checks against a truth of its own: a tiny checkpoint built here, a card read
back, an order statistic computed by hand, a file's bytes before and after."""

from __future__ import annotations

import json
import math
import shutil

import pytest
import torch

from difffilter.kalman import KalmanFilter
from difffilter.models.learned_estimator import compose
from difffilter.models.neural_estimator import (
    EstimatorCard,
    NeuralFDIEstimator,
    load_estimator_checkpoint,
    save_estimator_checkpoint,
)
from difffilter.train.calibrate import calibrate_checkpoint, main

LFC = "checkpoints/lfc_nn_grad.ckpt"


def _tiny(features=(), dim=2, **kw):
    """A one-area network of ``dim`` channels with a head, reading ``features``."""
    from difffilter.fdi.neural import feature_dim

    return NeuralFDIEstimator(num_areas=1, area_dim=dim, a=1, b=1, hidden=3,
                              extra_inputs=feature_dim(features, dim), seed=3, **kw)  # fmt: skip


def test_compose_runs_the_kalman_filter_with_every_option_its_card_names():
    """Every run option of a card reaches the step object: threshold, gating, compensation,
    restart, confirm and reject (three distinct rates, so a value read from the wrong key
    shows), standardize, features and residual. Truth: the card written here."""
    card = EstimatorCard(scenario_family="x", filter="kf", residual="lagged", standardize=False,
                         features=("mask",), threshold=0.123, gating=True,
                         compensation="detected", restart=0.01, confirm=0.02, reject=0.03)  # fmt: skip
    est = compose(_tiny(("mask",)), card)
    assert isinstance(est.inner, KalmanFilter)
    assert est.threshold == 0.123 and est.gating is True
    assert est.compensation.value == "detected"
    assert (est.restart, est.confirm, est.reject) == (0.01, 0.02, 0.03)
    assert est.core.standardize is False and est.core.features == ("mask",)
    assert est.core.residual.value == "lagged"
    plain = compose(_tiny(), EstimatorCard(filter="kf"))  # the card's defaults
    assert plain.threshold == 0.5 and plain.gating is False and plain.core.standardize is True
    assert (plain.restart, plain.confirm, plain.reject) == (None, None, None)
    # a particle filter's settings on a Gaussian card are named, not ignored (a docs trial)
    for kw, named in (({"num_particles": 100}, "num_particles"),
                      ({"resampler": object()}, "resampler"),
                      ({"ess_threshold": 0.5}, "ess_threshold")):  # fmt: skip
        with pytest.raises(
            ValueError,
            match=rf"^{named}: set a particle filter, and this "
            r"checkpoint's network runs in the kf filter",
        ):
            compose(_tiny(), EstimatorCard(filter="kf"), **kw)


def test_compose_gives_the_particle_filter_the_cards_size_unless_told_and_its_poa_eta():
    """A particle filter has the card's ``num_particles`` unless the caller gives another
    (the suite gives the scenario's), and the ``poa`` feature reads the card's ``η``."""
    card = EstimatorCard(filter="pf", num_particles=7, features=("poa",), poa_eta=0.25)
    net = _tiny(("poa",))
    assert compose(net, card).inner.num_particles == 7
    assert compose(net, card, num_particles=5).inner.num_particles == 5
    assert compose(net, card).core.poa_eta == 0.25


def _tampered(tmp_path, change):
    """A tiny exported checkpoint (no card beside it: no sha256 to match) whose stored
    blob ``change`` edits."""
    path = tmp_path / "tiny.ckpt"
    save_estimator_checkpoint(path, _tiny(), EstimatorCard(filter="kf"))
    blob = torch.load(path, weights_only=True)
    change(blob)
    torch.save(blob, path)
    return path


def test_a_checkpoint_missing_a_weight_or_holding_an_unknown_setting_is_refused(tmp_path):
    """The loader loads the state strictly: a file without the head's ``c`` must not load
    with the constructor's −4 in its place, nor one with a weight the network lacks; an
    estimator setting the network does not know is a ``ValueError`` naming it (not a bare
    ``KeyError``). Truth: the tiny checkpoint as saved here, edited by hand."""
    path = _tampered(tmp_path, lambda b: b["state_dict"].pop("c"))
    with pytest.raises(ValueError, match="does not match its own configuration"):
        load_estimator_checkpoint(path)
    path = _tampered(tmp_path, lambda b: b["state_dict"].update(Q=torch.zeros(2)))
    with pytest.raises(ValueError, match="does not match its own configuration"):
        load_estimator_checkpoint(path)
    path = _tampered(tmp_path, lambda b: b["estimator_config"].update(dropout=0.1))
    with pytest.raises(ValueError, match=r"unknown estimator settings \['dropout'\]"):
        load_estimator_checkpoint(path)
    net, _ = load_estimator_checkpoint(_tampered(tmp_path, lambda b: None))  # untouched: loads
    assert torch.equal(net.c, _tiny().c)


def _scores(path, seed, runs=1):
    from difffilter.eval.suite import run_suite
    from difffilter.models import registry

    scenario = registry.get("lfc_random_attacks").with_threat(None)
    result = run_suite(scenario, runs=runs, seed=seed, estimators=["kf_nn_grad"],
                       checkpoint={"kf_nn_grad": str(path)}, progress=False)  # fmt: skip
    return result.outputs["kf_nn_grad"].detection.scores


def test_calibrate_keeps_the_cards_restart_and_confirm_and_counts_strict_exceedances(tmp_path):
    """The shipped LFC card runs with restart 0.01 and confirm 0.01; calibrating it with the
    options left at ``keep`` keeps both. Its confirmed score is 0 wherever the copy's test
    is quiet (most steps), so at a 30 % target τ = 0 and only strict exceedances count as
    alarms: the measured rates are the fractions of scores ``> τ`` on the calibration and
    the check runs, recomputed here from the suite's scores on the seeds the entry records,
    and τ is the order statistic of eq. ``#{s > τ} ≤ ⌊α n⌋`` computed by hand."""
    out = tmp_path / "out.ckpt"
    shipped = load_estimator_checkpoint(LFC)[1]
    cal = calibrate_checkpoint(LFC, out, far=0.3, runs=1, progress=False)
    card = load_estimator_checkpoint(out)[1]
    assert (card.restart, card.confirm, card.reject) == (0.01, 0.01, None)
    assert (cal["restart"], cal["confirm"]) == (0.01, 0.01) and "reject" not in cal
    assert cal["previous_threshold"] == shipped.threshold != cal["threshold"]
    assert card.target_false_alarm_rate == 0.3 and card.threshold == cal["threshold"]
    fitted = _scores(LFC, cal["seed"]).flatten()
    allowed = math.floor(0.3 * fitted.numel())
    # τ by hand: the smallest score with at most ⌊α n⌋ scores above it
    tau = min(float(s) for s in fitted.unique() if int((fitted > s).sum()) <= allowed)
    assert cal["threshold"] == tau == 0.0
    assert cal["measured_on_calibration"] == float((fitted > tau).double().mean()) < 0.3
    checked = _scores(LFC, cal["check_seed"]).flatten()
    assert cal["check_seed"] != cal["seed"]
    assert cal["measured_on_check"] == float((checked > tau).double().mean()) < 0.3


def test_calibrate_off_on_the_command_line_removes_restart_and_confirm_and_spares_the_source(
    tmp_path, capsys
):
    """``--restart off --confirm off`` runs and writes the card without either (``off`` is
    not ``keep``, and ``--confirm`` is not read as ``--reject``); the source checkpoint and
    its card keep their bytes, the new card's check is the recomputed one, and ``--out``
    naming the source itself is refused without ``--force``. Truth: the card read back, the files' bytes before and after."""
    src = tmp_path / "lfc.ckpt"
    shutil.copy(LFC, src)
    shutil.copy(LFC.replace(".ckpt", ".json"), src.with_suffix(".json"))
    before = src.read_bytes(), src.with_suffix(".json").read_bytes()
    assert main([str(src), "--out", str(src), "--runs", "1", "--no-progress"]) == 2
    assert "is the source itself; pass --force" in capsys.readouterr().err
    out = tmp_path / "off.ckpt"
    argv = [str(src), "--out", str(out), "--runs", "1", "--far", "0.3", "--no-progress"]
    assert main([*argv, "--restart", "off", "--confirm", "off"]) == 0, capsys.readouterr().err
    card = load_estimator_checkpoint(out)[1]
    assert (card.restart, card.confirm, card.reject) == (None, None, None)
    document = json.loads(out.with_suffix(".json").read_text())
    assert not {"restart", "confirm", "reject"} & set(document["calibration"])
    assert document["observer"]["restart"] is None and document["observer"]["confirm"] is None
    # the card's check is recomputed for the estimator as it now runs
    note = document["check"]["note"]
    assert "calibrate with restart None, confirm None, reject None" in note
    assert (src.read_bytes(), src.with_suffix(".json").read_bytes()) == before


def test_a_card_keeps_what_it_does_not_know_in_extra_through_a_checkpoint(tmp_path):
    """Keys a card does not know (a newer writer's, a training note) are kept in ``extra``
    beside the card's own ``extra``, in the card read back from a checkpoint, not dropped.
    Truth: the observer dict written here."""
    observer = {
        **EstimatorCard(filter="kf", threshold=0.7).to_dict(),
        "note": "from a newer writer",
    }
    observer["extra"] = {"calibration": {"target": 0.01}}
    path = tmp_path / "tiny.ckpt"
    save_estimator_checkpoint(path, _tiny(), observer)
    card = load_estimator_checkpoint(path)[1]
    assert card.threshold == 0.7 and card.filter == "kf"
    assert card.extra == {"calibration": {"target": 0.01}, "note": "from a newer writer"}


def test_a_file_with_a_state_dict_but_no_lightning_version_is_not_read_as_lightning(tmp_path):
    """Only a file carrying ``pytorch-lightning_version`` is a training run's checkpoint: a
    bare ``{"state_dict": …}`` of ``estimator.*`` weights is neither kind and is refused,
    not loaded with the legacy LFC card. Truth: the file written here."""
    from difffilter.models.neural_estimator import checkpoint_kind

    state = {f"estimator.{k}": v for k, v in _tiny().state_dict().items()}
    path = tmp_path / "bare.ckpt"
    torch.save({"state_dict": state, "hyper_parameters": {}}, path)
    assert checkpoint_kind(torch.load(path, weights_only=True)) is None
    with pytest.raises(ValueError, match="is neither a"):
        load_estimator_checkpoint(path)


def test_a_non_finite_estimator_setting_is_refused(tmp_path):
    """``init_scale = inf`` in a checkpoint's settings passes the constructor (``inf > 0``)
    and the stored weights replace what it drew: the loader itself must refuse it. Truth:
    the tiny checkpoint edited here."""
    path = _tampered(tmp_path, lambda b: b["estimator_config"].update(init_scale=math.inf))
    with pytest.raises(ValueError, match="non-finite setting init_scale = inf"):
        load_estimator_checkpoint(path)


def test_a_lightning_checkpoint_without_its_observer_reads_the_papers_lag_of_one(tmp_path):
    """A Lightning checkpoint whose module stored neither a card nor ``residual_lag`` is an
    LFC module's: the Kalman filter, raw residuals lagged by the paper's ``ℓ = 1``
    (``"lagged"``), ``dt`` 0.01; its weights are the module's ``estimator.*``. Truth: the
    blob written here and the module docstring's ``ℓ = 1``."""
    net = _tiny()
    blob = {"pytorch-lightning_version": "2.0.0", "hyper_parameters": net.config(),
            "state_dict": {f"estimator.{k}": v for k, v in net.state_dict().items()}}  # fmt: skip
    path = tmp_path / "run.ckpt"
    torch.save(blob, path)
    loaded, card = load_estimator_checkpoint(path)
    assert (card.filter, card.residual, card.dt, card.standardize) == ("kf", "lagged", 0.01, False)
    assert card.scenario_family == "lfc"
    assert torch.equal(loaded.V, net.V)
    blob["hyper_parameters"] = {**net.config(), "residual_lag": 0}
    torch.save(blob, path)
    assert load_estimator_checkpoint(path)[1].residual == "predicted"


def test_an_expected_sha256_given_is_checked_without_a_card(tmp_path):
    """``expected_sha256=`` is compared with the file's digest even where no card lies
    beside it (a wrong one refused, the right one, in either case, accepted). Truth:
    ``hashlib`` over the file's bytes."""
    import hashlib

    path = tmp_path / "tiny.ckpt"
    save_estimator_checkpoint(path, _tiny(), EstimatorCard(filter="kf"))
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    with pytest.raises(ValueError, match="does not match the sha256"):
        load_estimator_checkpoint(path, expected_sha256="0" * 64)
    load_estimator_checkpoint(path, expected_sha256=digest.upper())


def test_compose_refuses_a_replacement_network_without_its_deception():
    """A replacement-channel card needs the density it assumes: no silent default."""
    card = EstimatorCard(filter="pf", channel="replacement", num_particles=4)
    with pytest.raises(ValueError, match="deception"):
        compose(_tiny(), card)


def test_the_registry_entries_take_each_checkpoint_by_its_own_card(tmp_path):
    """Within one study two entries read two checkpoints: each runs its own card's
    threshold (the loader's cache is per file), and an entry refuses a checkpoint of
    another trainer. Truth: the shipped cards read back; ``load_estimator``'s ``"float"``
    means float32."""
    from types import SimpleNamespace

    from difffilter.models import registry
    from difffilter.models.estimators import SkipEstimator
    from difffilter.models.learned_estimator import learned_step, load_estimator

    files = {"pf_nn_grad": "checkpoints/four_tank_nn_grad.ckpt",
             "pf_nn_ekf": "checkpoints/four_tank_nn_ekf.ckpt"}  # fmt: skip
    ctx = SimpleNamespace(checkpoint_for=files.get, cache={}, checkpoint_users=[],
                          scenario=registry.get("four_tank_bias"), dtype=torch.float64)  # fmt: skip
    for name, path in files.items():
        est, _ = learned_step(ctx, name)
        assert est.threshold == load_estimator_checkpoint(path)[1].threshold
    wrong = SimpleNamespace(
        **{**vars(ctx), "cache": {}, "checkpoint_for": lambda n: files["pf_nn_grad"]}
    )
    with pytest.raises(SkipEstimator, match="by grad"):
        learned_step(wrong, "pf_nn_ekf")
    net = load_estimator(files["pf_nn_grad"], dtype="float").estimator.network
    assert net.V.dtype == torch.float32
