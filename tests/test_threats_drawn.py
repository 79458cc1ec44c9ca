"""What a training across threats drew, counted for the card: runs per threat component of
the training batches the selected weights met (a trial could not tell which threats a
training drew without re-drawing them through internal helpers)."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from difffilter.threat_distribution import ThreatDistribution

ROOT = Path(__file__).resolve().parents[1]
# the drawing rule written out (train/task.py's docstrings): batch i of epoch e has seed
# (train_seed, e, i); each of its runs draws a component by weight, then the component's
# random fields, from the generator of stream "threats" of that seed
MIX = {"own": {"weight": 0.3},
       "ramp": {"weight": 0.5, "kind": "ramp", "slope": {"uniform": [0.002, 0.01]},
                "onset": {"randint": [5, 40]}},
       "none": {"weight": 0.2},
       "rare": {"weight": 1e-9, "kind": "bias", "value": 0.5}}  # fmt: skip


def _replayed(batches: list[tuple[int, int]], runs: int, train_seed: int = 1) -> dict[str, int]:
    """Counts of a replay of the draws, batch by batch in the documented streams, through
    the distribution's sampler alone (no data module, no simulation, no Lightning): what
    is under test is the counting in training, its split across batches and processes,
    and its travel through checkpoints, resumes and exports."""
    from difffilter.models import registry
    from difffilter.models.streams import Streams
    from difffilter.train.common import mix_seed

    sc = registry.get("four_tank_bias")
    dist = ThreatDistribution(MIX, model=sc.system(), own=sc.threat)
    counts: dict[str, int] = {}
    for epoch, index in batches:
        g = Streams(mix_seed(train_seed, epoch, index))("threats")
        for _ in range(runs):
            name, _ = dist.sample(g)
            counts[name] = counts.get(name, 0) + 1
    return counts


def _fit(tmp_path: Path, monkeypatch, epochs: int, *more: str) -> Path:
    from difffilter.train.cli import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    argv = [
        "fit", "--config", str(ROOT / "train" / "configs" / "four_tank_threats.yaml"),
        f"--data.init_args.threats={json.dumps(MIX)}",
        "--data.init_args.batch_size=5", "--data.init_args.batches_per_epoch=2",
        "--data.init_args.val_runs=4", "--data.init_args.calibration_runs=4",
        "--model.init_args.num_particles=16", "--model.init_args.hidden=4",
        "--model.init_args.adversarial_runs=0", f"--trainer.max_epochs={epochs}",
        "--trainer.logger.init_args.version=run", *more,
    ]  # fmt: skip
    assert main(argv) == 0
    return tmp_path / "lightning_logs" / "four_tank_threats_nn_grad" / "run"


def test_the_card_counts_the_threats_the_selected_weights_met_and_a_resume_counts_on(
    tmp_path, monkeypatch
):
    """Two epochs of two batches of five runs: last.ckpt's count is the replay of the four
    batches; the fit's card counts the batches up to its selected checkpoint; a fit cut
    after epoch 0 and resumed to two epochs counts as the uninterrupted one (the count
    travels in the checkpoint); a component of weight 1e-9 is counted 0 and coverage holds
    it out, while a threat of a drawn component's kind is within."""
    from difffilter.eval.coverage import training_coverage
    from difffilter.train.cli import main

    (tmp_path / "whole").mkdir()
    whole = _fit(tmp_path / "whole", monkeypatch, 2)
    four = [(0, 0), (0, 1), (1, 0), (1, 1)]
    want = _replayed(four, 5)
    assert sum(want.values()) == 20 and want.get("rare", 0) == 0 and len(want) >= 2
    last = torch.load(whole / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
    from difffilter.train.export import threats_drawn

    assert threats_drawn(last) == want
    card = json.loads((whole / "four_tank_nn_grad.json").read_text())
    selected = torch.load(whole / "checkpoints" / card["selected_checkpoint"], weights_only=True)
    met = four[: 2 * (selected["epoch"] + 1)]
    assert card["threats_drawn"] == _replayed(met, 5)
    # an export of last.ckpt: every batch
    assert main(["export", str(whole / "checkpoints" / "last.ckpt"), "--out",
                 str(tmp_path / "last_export.ckpt")]) == 0  # fmt: skip
    assert json.loads((tmp_path / "last_export.json").read_text())["threats_drawn"] == want
    # cut after epoch 0, resumed to epoch 2 from last.ckpt: the same count as uninterrupted
    (tmp_path / "cut").mkdir()
    cut = _fit(tmp_path / "cut", monkeypatch, 1)
    first = torch.load(cut / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
    assert threats_drawn(first) == _replayed(four[:2], 5)
    resumed = _fit(tmp_path / "cut", monkeypatch, 2, "--ckpt_path",
                   str(cut / "checkpoints" / "last.ckpt"))  # fmt: skip
    again = torch.load(resumed / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
    assert threats_drawn(again) == want
    # coverage: the rare bias (never drawn) does not make a bias "kind only" (it did before the
    # count: its component has the study's value); a ramp is (own: unplaced, not given)
    study = {"bias": {"kind": "bias", "value": 0.5, "onset": 21},
             "ramp": {"kind": "ramp", "slope": 0.005, "onset": 21}}  # fmt: skip
    labels = training_coverage(tmp_path / "last_export.ckpt", study)["threats"]
    assert labels["ramp"] == "within"
    assert labels["bias"] == "held out"
