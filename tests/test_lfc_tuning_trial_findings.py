"""An LFC-tuning trial's findings: a diverging grid point (``traditional_ad`` at lr = 1,
which the estimators' module says diverges from 0.3) stopped the whole grid with the loop's
"contains NaN or Inf", the scores before it lost, where the module says such settings score
``inf``; and an ``--out`` that is a folder or not JSON was found after every point was
scored."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from difffilter.models.lfc_estimators import LFCContext
from difffilter.train import lfc_tuning


def test_a_diverging_setting_scores_inf_and_a_converging_one_a_number():
    batch = lfc_tuning.validation_batch(1)

    def scored(lr):
        settings = {"init_scale": 0.01, "lr": lr, "luenberger_design": "modal"}
        est = lfc_tuning._estimator("traditional_ad", settings, LFCContext(dt=0.01), None)
        return lfc_tuning.score(est, batch)

    diverged = scored(1.0)
    assert diverged["attack_rmse"] == diverged["state5_rmse"] == math.inf
    assert math.isfinite(scored(0.01)["attack_rmse"])


@pytest.mark.parametrize("kind", ["folder", "not json", "a list"])
def test_a_bad_out_is_named_before_any_grid_point_is_scored(kind, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out.json"
    if kind == "folder":
        out.mkdir()
    else:
        out.write_text("not json" if kind == "not json" else "[1, 2]", encoding="utf-8")
    ran = []
    monkeypatch.setattr(lfc_tuning, "tune", lambda *a, **k: ran.append(1))
    with pytest.raises(SystemExit) as stop:
        lfc_tuning.main(["--runs", "1", "--out", str(out)])
    assert stop.value.code == 2 and ran == []
    assert "--out" in capsys.readouterr().err


def test_a_bad_ckpt_is_a_usage_error_before_any_grid_point(tmp_path, capsys):
    """``kf_nn_grad_ekf`` without ``--ckpt``, a path that does not exist, a checkpoint of
    another family: each had stopped with a traceback (a trial); now argparse's error
    (exit 2), naming ``--ckpt``, and nothing written."""
    from difffilter.train.lfc_tuning import main

    out = tmp_path / "t.json"
    four_tank = Path(__file__).resolve().parents[1] / "checkpoints" / "four_tank_nn_grad.ckpt"
    for extra, said in (([], "needs --ckpt"), (["--ckpt", str(tmp_path / "none.ckpt")],
                        "no checkpoint file"), (["--ckpt", str(four_tank)], "--ckpt")):  # fmt: skip
        with pytest.raises(SystemExit) as stop:
            main(["--estimators", "kf_nn_grad_ekf", "--runs", "1", "--out", str(out), *extra])
        assert stop.value.code == 2 and said in capsys.readouterr().err
    assert not out.exists()


def test_a_diverged_grid_is_written_as_strict_json_and_chooses_nothing(tmp_path, monkeypatch,
                                                                       capsys):  # fmt: skip
    """A trial of the JSON writers: a diverged point's inf score was written as bare
    ``Infinity`` (strict readers refuse the file), and a grid whose every point diverged
    "chose" one. Now the score is null with ``"diverged": true``, nothing is chosen for such
    a grid, and the file is written atomically."""
    import json

    monkeypatch.setitem(lfc_tuning.GRIDS, "traditional_ad",
                        {"init_scale": [0.01], "lr": [1.0, 2.0], "luenberger_design": ["modal"]})  # fmt: skip
    scores = {1.0: math.inf, 2.0: 0.5}
    monkeypatch.setattr(lfc_tuning, "_estimator", lambda name, setting, ctx, ckpt: setting["lr"])
    monkeypatch.setattr(lfc_tuning, "score", lambda lr, batch: {
        "attack_rmse": scores[lr], "attack_rmse_attacked": scores[lr],
        "state5_rmse": scores[lr], "wall_s": 0.0})  # fmt: skip
    monkeypatch.setattr(
        lfc_tuning, "validation_batch", lambda runs: {"attack": torch.zeros(1, 5, 10)}
    )

    def refuse(constant):
        raise ValueError(f"non-standard JSON constant {constant}")

    out = tmp_path / "tuning.json"
    assert (
        lfc_tuning.main(["--runs", "1", "--estimators", "traditional_ad", "--out", str(out)]) == 0
    )
    written = json.loads(out.read_text(), parse_constant=refuse)
    rows = written["grids"]["traditional_ad"]
    assert rows[0]["attack_rmse"] is None and rows[0]["diverged"] is True
    assert rows[1]["attack_rmse"] == 0.5 and "diverged" not in rows[1]
    assert written["chosen"]["traditional_ad"]["lr"] == 2.0
    scores[2.0] = math.inf  # every point diverged: nothing chosen, said on stderr, and the
    # choice of the file it merges into (the run before's) gone with its grid (a review)
    lfc_tuning.main(["--runs", "1", "--estimators", "traditional_ad", "--out", str(out)])
    assert "traditional_ad" not in json.loads(out.read_text(), parse_constant=refuse)["chosen"]
    assert "every point of the traditional_ad grid diverged" in capsys.readouterr().err
