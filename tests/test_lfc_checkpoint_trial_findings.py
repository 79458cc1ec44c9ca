"""The LFC learned estimators' checkpoint paths (a red-team trial).

* ``build_estimator("kf_nn_grad")`` alarmed at the step's default 0.5, not at the card's
  calibrated threshold its entry uses.
* A card re-saved with another ``restart`` or ``reject`` kept the threshold calibrated for
  the options of before (the calibration record names them).
* The online tuning built ``kf_nn_grad_ekf`` from two of the card's options and scored an
  observer without the card's restart.
* A Luenberger observer with ``restart``/``reject``/``standardize`` failed at its first step.
"""

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import pytest

from difffilter.models import registry
from difffilter.models.lfc_estimators import (
    LFCContext,
    build_estimator,
    card_options,
    lfc_estimator,
    paper_network,
)
from difffilter.models.neural_estimator import load_estimator_checkpoint, save_estimator_checkpoint

SHIPPED = Path(__file__).resolve().parents[1] / "checkpoints" / "lfc_nn_grad.ckpt"


def _context(path):
    return SimpleNamespace(checkpoint_for=lambda name: path, cache={},
                           scenario=registry.get("lfc_step"), checkpoint_users=[])  # fmt: skip


def test_build_estimator_alarms_at_the_cards_calibrated_threshold():
    _, card = load_estimator_checkpoint(SHIPPED)
    estimator = build_estimator("kf_nn_grad", _context(SHIPPED))
    assert estimator.threshold == pytest.approx(card.threshold)  # was 0.5
    assert card.threshold != 0.5


@pytest.mark.parametrize(("change", "calibrated"),
                         [({}, True), ({"restart": 0.2}, False), ({"reject": 0.01}, False)])  # fmt: skip
def test_a_threshold_is_kept_only_for_the_options_it_was_calibrated_with(
    tmp_path, change, calibrated
):
    net, card = load_estimator_checkpoint(SHIPPED)
    path = tmp_path / "changed.ckpt"
    save_estimator_checkpoint(path, net, dataclasses.replace(card, **change))
    estimator = build_estimator("kf_nn_grad", _context(path))
    assert estimator.threshold == (pytest.approx(card.threshold) if calibrated else 0.5)


def test_the_tuning_builds_the_entrys_observer():
    from difffilter.models.lfc_estimators import FINETUNE_DEFAULTS
    from difffilter.param_ekf import EKFRule
    from difffilter.train import lfc_tuning

    net, card = load_estimator_checkpoint(SHIPPED)
    tuned = lfc_tuning._estimator("kf_nn_grad_ekf", {}, LFCContext(0.01), (net, card))
    entry = lfc_estimator(LFCContext(0.01), network=net, rule=EKFRule(**FINETUNE_DEFAULTS, donate=True),
                          **card_options(card))  # fmt: skip
    for option in ("restart", "confirm", "reject", "gating", "compensation"):
        assert getattr(tuned, option) == getattr(entry, option)
    assert tuned.core.standardize == entry.core.standardize
    assert tuned.core.features == entry.core.features
    assert tuned.restart == card.restart is not None  # was None


@pytest.mark.parametrize("option", [{"restart": 0.01}, {"reject": 0.01}, {"standardize": True}])
def test_a_luenberger_observer_refuses_what_reads_the_innovation_covariance(option):
    with pytest.raises(
        ValueError, match="FixedGainFilter \\(a Luenberger observer\\) does not report"
    ):
        lfc_estimator(LFCContext(0.01), luenberger="modal", network=paper_network(0.01),
                      init_scale=0.01, **option)  # fmt: skip
    lfc_estimator(
        LFCContext(0.01), luenberger="modal", network=paper_network(0.01), init_scale=0.01
    )


def test_a_tuning_of_one_grid_keeps_the_others_validation(tmp_path, monkeypatch):
    import json

    from difffilter.train import lfc_tuning

    def tune(estimators, runs, ckpt):
        validation = {"runs": runs, "seed": 1}
        return {"grids": {e: [] for e in estimators}, "chosen": {}, "validation": validation,
                "validated_on": dict.fromkeys(estimators, validation)}  # fmt: skip

    monkeypatch.setattr(lfc_tuning, "tune", tune)
    out = tmp_path / "tuning.json"
    lfc_tuning.main(["--runs", "12", "--estimators", "kf_nn_ekf", "--out", str(out)])
    lfc_tuning.main(["--runs", "1", "--estimators", "traditional_ad", "--out", str(out)])
    record = json.loads(out.read_text())
    assert record["validated_on"]["kf_nn_ekf"]["runs"] == 12  # the last run's 1 had relabelled it
    assert record["validated_on"]["traditional_ad"]["runs"] == 1
