"""A checkpoint or card rewritten in place is replaced whole or not at all
(``calibrate --out checkpoints/<name>.ckpt --force`` interrupted mid-write)."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from difffilter.models.atomic_write import write_json_atomically
from difffilter.models.neural_estimator import (
    checkpoint_sha256,
    load_estimator_checkpoint,
    save_estimator_checkpoint,
)

SHIPPED = "checkpoints/four_tank_nn_grad.ckpt"


def test_an_interrupted_save_leaves_the_checkpoint_it_was_replacing(tmp_path, monkeypatch):
    path = tmp_path / "net.ckpt"
    shutil.copyfile(SHIPPED, path)
    before = path.read_bytes()
    estimator, card = load_estimator_checkpoint(path)

    def half_then_interrupt(obj, f):  # what Ctrl-C in the middle of torch.save leaves
        if hasattr(f, "write"):  # (saved to a buffer first: the same bytes in every process)
            f.write(before[: len(before) // 2])
        else:
            with open(f, "wb") as out:
                out.write(before[: len(before) // 2])
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", half_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        save_estimator_checkpoint(path, estimator, card)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [
        "net.ckpt"
    ]
    monkeypatch.undo()
    digest = save_estimator_checkpoint(path, estimator, card)  # an uninterrupted one lands
    assert digest == checkpoint_sha256(path) and load_estimator_checkpoint(path)[1] == card


def test_an_interrupted_card_write_leaves_the_card(tmp_path, monkeypatch):
    path = tmp_path / "net.json"
    write_json_atomically(path, {"sha256": "old"})
    real = type(path).write_text

    def interrupt(self, text, *args, **kwargs):
        real(self, text[:3], *args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(type(path), "write_text", interrupt)
    with pytest.raises(KeyboardInterrupt):
        write_json_atomically(path, {"sha256": "new"})
    monkeypatch.undo()
    assert json.loads(path.read_text()) == {"sha256": "old"} and len(list(tmp_path.iterdir())) == 1
