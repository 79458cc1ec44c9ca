"""Every shipped card's ``check`` (the reproducibility figure its export wrote: the attack
RMSE over every step of ``runs`` runs of ``seed``, ``train.export.check_metric``) is what the
checkpoint gives today: the tracking card's had kept 0.73555 from its export after the
particle filter's wrapped-bearing averaging moved it to 0.73457 (a trial), and nothing had
recomputed it. The robot card's figure reproduced bit for bit; the tolerance allows the
last digits of another BLAS."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from difffilter.train.export import check_metric

CARDS = sorted(Path("checkpoints").glob("*.json"))
CHECKED = [c for c in CARDS if "check" in json.loads(c.read_text(encoding="utf-8"))]
#: (the LFC card's, 100 s of closed loops, is test_lfc_train.py's)
RECOMPUTED = [c for c in CHECKED if c.stem != "lfc_nn_grad"]


def test_the_cards_with_a_check_are_found():
    assert {c.stem for c in CHECKED} >= {"robot_nn_ekf", "tracking_nn_grad", "lfc_nn_grad"}


@pytest.mark.parametrize("card", RECOMPUTED, ids=lambda c: c.stem)
def test_a_shipped_cards_check_is_what_its_checkpoint_gives(card):
    check = json.loads(card.read_text(encoding="utf-8"))["check"]
    now = check_metric(card.with_suffix(".ckpt"), seed=check["seed"], runs=check["runs"])
    assert now["metric"] == check["metric"] and now["scenario"] == check["scenario"]
    assert now["value"] == pytest.approx(check["value"], rel=1e-9)
