"""Confirmed alarms: with ``NeuralCompensation(restart=α, confirm=β)`` the network's score
counts only where the χ²-gated copy's test at the rate β alarms as well."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import pytest
import torch
from test_learned_estimator import _data, _linear, _net, neural_gaussian_filter
from test_restart import gated_copy_by_hand

import difffilter as df
from difffilter.fdi.detectors import chi_square_quantile
from difffilter.models import registry
from difffilter.models.learned_estimator import NeuralCompensation
from difffilter.models.neural_estimator import (
    EstimatorCard,
    NeuralFDIEstimator,
    load_estimator_checkpoint,
    save_estimator_checkpoint,
)
from difffilter.train.calibrate import calibrate_checkpoint, main


def _head_net() -> NeuralFDIEstimator:
    """A one-area network with a detection head (its score: the head's probability)."""
    return NeuralFDIEstimator(num_areas=1, area_dim=2, a=2, b=2, hidden=5, init="symmetric",
                              init_scale=0.5, resid_scale=3.0, seed=1, dtype=torch.float64,
                              detection_head=True)  # fmt: skip


@pytest.mark.parametrize("head", [False, True])
def test_the_score_is_the_networks_where_the_copys_test_at_beta_alarms_and_zero_elsewhere(head):
    """Against the copy written out: ``s_k = s⁰_k · 1[q°_k > F⁻¹(1 − β)]`` with ``s⁰`` the
    score without confirmation; every estimate (means, covariances, attack) is the same
    bit for bit, and the alarms follow the new score."""
    model = _linear()
    _, ys = _data(model, runs=4, steps=14)
    alpha, beta = 0.05, 0.3
    net = _head_net() if head else _net()
    kwargs = dict(network=net, filter=df.KalmanFilter(), restart=alpha, threshold=1e-3)
    alone = neural_gaussian_filter(model, ys, **kwargs)
    confirmed = neural_gaussian_filter(model, ys, confirm=beta, **kwargs)
    for name in ("means", "covs", "attack"):
        assert torch.equal(getattr(alone, name), getattr(confirmed, name)), name
    nis = torch.stack([nis for nis, _, _ in gated_copy_by_hand(model, ys, alpha)], 1)
    loud = nis > chi_square_quantile(2, 1 - beta)
    assert loud.any() and (~loud).any()  # both branches exercised (the bias from step 5)
    want = torch.where(loud, alone.detection.scores, torch.zeros_like(alone.detection.scores))
    assert torch.equal(confirmed.detection.scores, want)
    assert torch.equal(confirmed.detection.alarms, want > 1e-3)
    assert (alone.detection.scores[~loud] > 0).any()  # the confirmation removed some score


def test_confirm_needs_a_rate_and_the_restarts_gated_copy():
    with pytest.raises(ValueError, match="confirm must be a false-alarm rate in"):
        NeuralCompensation(_net(), df.KalmanFilter(), restart=0.01, confirm=1.0)
    with pytest.raises(ValueError, match="confirm must be a false-alarm rate in"):
        NeuralCompensation(_net(), df.KalmanFilter(), restart=0.01, confirm=True)
    with pytest.raises(ValueError, match="confirm reads the χ² test .* give restart too"):
        NeuralCompensation(_net(), df.KalmanFilter(), confirm=0.1)


def test_the_card_carries_confirm_the_entry_runs_it_and_calibrate_sets_it(tmp_path, capsys):
    """The card round-trips ``confirm`` (older cards: ``None``); the LFC entry builds its
    estimator with the card's; ``calibrate`` refuses a confirmation without a restart
    before running anything, and a rate it cannot read, naming the option."""
    from difffilter.models.lfc_estimators import build_estimator

    card = EstimatorCard(filter="kf", restart=0.01, confirm=0.1)
    assert EstimatorCard.from_dict(card.to_dict()).confirm == 0.1
    assert EstimatorCard.from_dict({"filter": "kf"}).confirm is None
    net, shipped = load_estimator_checkpoint("checkpoints/lfc_nn_grad.ckpt")
    with_confirm, without_restart = tmp_path / "confirm.ckpt", tmp_path / "plain.ckpt"
    save_estimator_checkpoint(with_confirm, net, dataclasses.replace(shipped, confirm=0.1))
    save_estimator_checkpoint(without_restart, net, dataclasses.replace(shipped, restart=None))
    ctx = SimpleNamespace(checkpoint_for=lambda name: with_confirm, cache={},
                          scenario=registry.get("lfc_random_attacks"), checkpoint_users=[])  # fmt: skip
    est = build_estimator("kf_nn_grad", ctx)
    assert (est.restart, est.confirm) == (shipped.restart, 0.1)
    with pytest.raises(ValueError, match="--confirm reads the χ² test of the restart"):
        calibrate_checkpoint(without_restart, tmp_path / "x.ckpt", confirm=0.1, progress=False)
    with pytest.raises(ValueError, match="--confirm must be a false-alarm rate in"):
        calibrate_checkpoint(with_confirm, tmp_path / "x.ckpt", confirm=2.0, progress=False)
    assert main([str(with_confirm), "--out", str(tmp_path / "y.ckpt"),
                 "--confirm", "sometimes"]) == 2  # fmt: skip
    assert "--confirm must be a rate in (0, 1) or off" in capsys.readouterr().err
    assert not (tmp_path / "x.ckpt").exists() and not (tmp_path / "y.ckpt").exists()


def test_the_lfc_entry_scores_the_confirmed_probability_under_its_own_name(tmp_path):
    """The registered ``kf_nn_grad`` with a card's ``confirm``: its scores are the
    unconfirmed entry's where the copy's test alarmed, ``0`` elsewhere, under a statistic
    named for the confirmation; its estimates are the unconfirmed entry's."""
    from difffilter.eval.suite import run_suite
    from difffilter.models.lfc_estimators import PROBABILITY, confirmed_statistic

    net, shipped = load_estimator_checkpoint("checkpoints/lfc_nn_grad.ckpt")
    path, plain = tmp_path / "confirm.ckpt", tmp_path / "plain.ckpt"
    save_estimator_checkpoint(path, net, dataclasses.replace(shipped, confirm=0.2))
    save_estimator_checkpoint(plain, net, dataclasses.replace(shipped, confirm=None))
    scenario = registry.get("lfc_step")

    def run(ckpt):
        return run_suite(scenario, runs=2, estimators=["kf_nn_grad"],
                         checkpoint={"kf_nn_grad": ckpt}, progress=False).outputs["kf_nn_grad"]  # fmt: skip

    alone, confirmed = run(plain), run(path)
    assert torch.equal(alone.means, confirmed.means) and torch.equal(alone.attack, confirmed.attack)
    loud = confirmed.extras["confirmed"]
    assert loud.any() and (~loud).any()
    want = torch.where(loud, alone.detection.scores, torch.zeros_like(alone.detection.scores))
    assert torch.equal(confirmed.detection.scores, want)
    assert confirmed.detection.statistic == confirmed_statistic(PROBABILITY, 0.2) != PROBABILITY
    assert alone.detection.statistic == PROBABILITY


def test_the_training_task_runs_and_exports_its_confirm():
    """``--model.init_args.confirm=β`` reaches the task's estimator and its exported card;
    without ``restart`` the task refuses it by name."""
    from pathlib import Path

    import yaml

    from difffilter.train.task import FilterEstimatorTask

    config = yaml.safe_load((Path(__file__).parents[1] / "train/configs/lfc.yaml").read_text())
    options = {**config["model"]["init_args"], "restart": 0.01, "confirm": 0.05}
    task = FilterEstimatorTask(**options)
    assert task.estimator_object(training=True).confirm == 0.05
    assert task.card().confirm == 0.05 and task.card().restart == 0.01
    with pytest.raises(ValueError, match="confirm reads the χ² test"):
        FilterEstimatorTask(**{**options, "restart": None})
