"""Findings of a red-team trial of a training run's export, card and figures (each failed
before its fix)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def _lightning_file(tmp_path: Path) -> Path:
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    net, card = load_estimator_checkpoint(ROOT / "checkpoints" / "four_tank_nn_grad.ckpt")
    src = tmp_path / "last.ckpt"
    torch.save({"pytorch-lightning_version": "2.5.0", "epoch": 3, "global_step": 48,
                "state_dict": {f"estimator.{k}": v for k, v in net.state_dict().items()},
                "hyper_parameters": {}, "difffilter_estimator_config": net.config(),
                "difffilter_observer": card.to_dict()}, src)  # fmt: skip
    return src


def test_an_export_of_a_lightning_file_names_its_estimator_and_family(tmp_path):
    """A fit's card names them; an export of a run's Lightning file had None for both, so
    the shipped-checkpoint hint (which matches cards on them) never offered it."""
    from difffilter.train.export import export

    export(_lightning_file(tmp_path), tmp_path / "out.ckpt")
    card = json.loads((tmp_path / "out.json").read_text())
    assert card["estimator"] == "pf_nn_grad" and card["scenario_family"] == "four_tank"


@pytest.mark.slow  # two processes, about 15 s
def test_an_exported_file_is_the_same_bytes_in_every_process(tmp_path):
    """torch.save named the archive inside the file after the partial file, whose name
    holds the process id: two identical exports had two file digests."""
    script = (
        "import sys; from pathlib import Path; from difffilter.train.export import export; "
        "export(Path(sys.argv[1]), Path(sys.argv[2]))"
    )
    src = _lightning_file(tmp_path)
    digests = []
    for name in ("a", "b"):
        out = tmp_path / name / "x.ckpt"
        subprocess.run([sys.executable, "-c", script, str(src), str(out)], check=True)
        digests.append(json.loads(out.with_suffix(".json").read_text())["sha256"])
    assert digests[0] == digests[1]


def test_an_actuator_attack_is_drawn_in_input_units():
    from difffilter.train.figures import attack_figure

    attack = torch.zeros(10, 2)
    attack[5:, 1] = 1.0
    fig = attack_figure(attack, attack, 0.1, actuator=True)
    ax = fig.axes[0]
    assert ax.get_ylabel() == "attack [input units]"
    assert "attack input2" in [t.get_text() for t in ax.get_legend().get_texts()]
    fig = attack_figure(attack, attack, 0.1)
    assert fig.axes[0].get_ylabel() == "attack [measurement units]"


def test_an_export_of_a_lightning_file_carries_the_calibration_record(tmp_path):
    """A fit's card has the observer's calibration record at its top level (README, "The
    card"); an export of the run's Lightning file (the same weights) had left it out."""
    from difffilter.models.neural_estimator import load_estimator_checkpoint
    from difffilter.train.export import export

    _, card = load_estimator_checkpoint(ROOT / "checkpoints" / "four_tank_nn_grad.ckpt")
    export(_lightning_file(tmp_path), tmp_path / "out.ckpt")
    exported = json.loads((tmp_path / "out.json").read_text())
    assert exported["calibration"] == card.extra["calibration"]
    assert exported["observer"]["extra"]["calibration"] == card.extra["calibration"]


def test_weights_stored_as_integers_are_refused_by_name(tmp_path):
    """A damaged file (no card beside it to compare the sha256 with) whose ``V`` was stored
    as int32 had loaded its integers as the weights (0 and ±1), without a word."""
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    blob = torch.load(ROOT / "checkpoints" / "four_tank_nn_grad.ckpt", weights_only=True)
    blob["state_dict"]["V"] = blob["state_dict"]["V"].to(torch.int32)
    torch.save(blob, tmp_path / "damaged.ckpt")
    with pytest.raises(ValueError, match=r"holds weights that are no floating-point tensors: V "
                                         r"\(torch.int32\)"):  # fmt: skip
        load_estimator_checkpoint(tmp_path / "damaged.ckpt")


def test_calibrate_refuses_scores_that_are_not_finite_where_the_threshold_falls(tmp_path,
                                                                                monkeypatch):  # fmt: skip
    """A trial of the cards: attack-free scores of +inf (an overflowed statistic) or NaN (no
    scored step) made a threshold of Infinity or -Infinity, written into the card as
    non-standard JSON; nothing is written now, and the error says why."""
    import math
    import shutil

    import difffilter.train.calibrate as calibrate

    for suffix in (".ckpt", ".json"):
        shutil.copy(ROOT / "checkpoints" / f"robot_nn_ekf{suffix}", tmp_path / f"src{suffix}")
    for fill in (math.inf, math.nan):
        monkeypatch.setattr(calibrate, "_scores", lambda scenario, name, path, runs, seed,
                            progress, fill=fill: (torch.full((runs, 50), fill), None))  # fmt: skip
        out = tmp_path / "out.ckpt"
        with pytest.raises(ValueError, match="are not finite where the threshold for 0.01 falls"):
            calibrate.calibrate_checkpoint(tmp_path / "src.ckpt", out, far=0.01, runs=2,
                                           force=True, progress=False)  # fmt: skip
        assert not out.exists() and not out.with_suffix(".json").exists()


def test_a_check_that_diverges_is_refused_not_written_as_nan(monkeypatch):
    """A trial of the cards: a check of NaN was written as bare NaN (and, never equal to
    itself, noted as moved at every calibration)."""
    import math
    from types import SimpleNamespace

    from difffilter.models import estimators
    from difffilter.train.export import check_metric

    nan_output = SimpleNamespace(factory=lambda ctx: lambda traj: SimpleNamespace(
        attack=torch.full_like(traj.attack, math.nan)))  # fmt: skip
    monkeypatch.setattr(estimators, "get", lambda name: nan_output)
    with pytest.raises(ValueError, match="the estimator diverges there"):
        check_metric(ROOT / "checkpoints" / "robot_nn_ekf.ckpt", runs=1)


@pytest.mark.parametrize(("field", "value"), [("dt", float("nan")), ("dt", float("inf")),
                                              ("dt", 0.0), ("poa_eta", float("nan")),
                                              ("poa_eta", -1.0), ("dt", True),
                                              ("poa_eta", True)])  # fmt: skip
def test_a_card_of_a_non_finite_dt_or_eta_is_refused_when_made(field, value):
    """A trial of the cards: a NaN ``dt`` or ``poa_eta`` was written, and the pair was then
    refused at every load ("dt = nan there, nan inside"); ``dt = inf`` was taken."""
    from difffilter.models.neural_estimator import EstimatorCard

    with pytest.raises(ValueError, match=f"{field} must be a finite number"):
        EstimatorCard(scenario_family="four_tank", scenario="four_tank_bias", threshold=0.5,
                      **{field: value})  # fmt: skip
    # η = 0 is a threshold the PoA detector takes (a mutation trial: > 0 was not caught)
    EstimatorCard(scenario_family="four_tank", scenario="four_tank_bias", threshold=0.5,
                  poa_eta=0.0)  # fmt: skip


def test_a_card_of_the_poa_feature_without_its_eta_is_refused_when_made():
    """A review: ``features: ["poa"]`` with ``poa_eta: null`` was taken by the card and
    refused only where the estimator was built."""
    from difffilter.models.neural_estimator import EstimatorCard

    with pytest.raises(ValueError, match="poa_eta must be a number >= 0 where features include"):
        EstimatorCard(scenario_family="four_tank", scenario="four_tank_bias", threshold=0.5,
                      features=("poa",))  # fmt: skip
    EstimatorCard(scenario_family="four_tank", scenario="four_tank_bias", threshold=0.5,
                  features=("poa",), poa_eta=0.233)  # fmt: skip
