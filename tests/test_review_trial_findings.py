"""Findings of a review of this session's own changes: the staged names of an in-place
recalibration, and the χ² detector's choice of direct window sums. Each test failed on the
code before its fix (the commit it reviews)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def test_a_long_out_name_keeps_its_checkpoint_and_card_apart(tmp_path):
    # both staged names had been cut to 64 characters alike: the card was written over the
    # checkpoint, and --out SRC --force destroyed the source
    import difffilter.train.calibrate as calibrate
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    src = tmp_path / ("c" * 70 + ".ckpt")
    shutil.copy(ROOT / "checkpoints" / "four_tank_nn_grad.ckpt", src)
    shutil.copy(ROOT / "checkpoints" / "four_tank_nn_grad.json", src.with_suffix(".json"))
    assert calibrate._staged_name(src) != calibrate._staged_name(src.with_suffix(".json"))
    estimator, card = load_estimator_checkpoint(src, dtype=None, expected_sha256=None)
    document = json.loads(src.with_suffix(".json").read_text())
    calibrate._write_pair(src, estimator, card, document, {"threshold": 0.5}, None)
    assert src.read_bytes()[:2] == b"PK"  # (a zip archive: torch's, not the JSON card)
    load_estimator_checkpoint(src)  # (verified against the card beside it)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [src.name, src.with_suffix(".json").name]
    )


def test_a_runs_window_sums_do_not_hang_on_its_batch():
    # the direct sums had been chosen on the whole batch's largest total: a run's scores
    # differed by 1.4e-9 with another run beside it
    from difffilter.fdi.detectors import _window_sums

    g = torch.rand(3000, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 2000.0
    other = torch.zeros(3000, dtype=torch.float64)
    other[10] = 1e7
    alone = _window_sums(g, 5)
    batched = _window_sums(torch.stack([g, other]), 5)[0]
    assert torch.equal(alone, batched)
    exact = torch.tensor(
        [float(sum(g[max(0, k - 4) : k + 1].tolist())) for k in range(3000)], dtype=torch.float64
    )
    assert (alone - exact).abs().max() < 1e-9
