"""``difffilter-train predict`` writes its predictions in the documented format
(train/predictions.py) and says where."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from difffilter.models.neural_estimator import load_estimator_checkpoint
from difffilter.train.cli import main
from difffilter.train.predictions import FIELDS

ROOT = Path(__file__).resolve().parents[1]


def test_predict_writes_every_batch_and_an_index(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    shipped = ROOT / "checkpoints" / "four_tank_nn_grad.ckpt"
    argv = ["predict", "--config", str(ROOT / "train" / "configs" / "four_tank.yaml"),
            "--data.init_args.test_runs=3", "--model.init_args.num_particles=20",
            "--ckpt_path", str(shipped)]  # fmt: skip
    assert main(argv) == 0
    out = capsys.readouterr().out
    index_files = list(tmp_path.rglob("predictions.json"))
    assert len(index_files) == 1
    assert f"{index_files[0].parent.relative_to(tmp_path)}/ (predictions.json" in out
    index = json.loads(index_files[0].read_text())
    card = load_estimator_checkpoint(shipped)[1]
    assert index["scenario"] == "four_tank_bias" and index["threshold"] == card.threshold
    assert index["fields"] == FIELDS and index["files"][0]["runs"] == 3
    batch = torch.load(index_files[0].parent / index["files"][0]["file"], weights_only=True)
    assert set(batch) == set(FIELDS)
    steps = index["files"][0]["steps"]
    assert batch["means"].shape == (3, steps, 4) and batch["attack_estimate"].shape == (3, steps, 4)
    assert torch.equal(batch["alarms"], batch["attack_probability"] > index["threshold"])
    assert not (ROOT / "predictions").exists()  # nothing beside the shipped files
