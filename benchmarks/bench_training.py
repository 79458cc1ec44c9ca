"""``make bench`` section 11: one training step of the learned LFC estimator.

What one ``lfc.yaml`` training chunk costs (``difffilter-train fit --config
train/configs/lfc.yaml``: the Kalman observer in the closed loop, gating, the uncompensated
copy's innovation and its χ² restart, float32): the task's first training batch (32 runs),
one truncated-BPTT chunk of 100 steps, forward (the closed loop with the graph recorded and
the losses) and backward timed apart, best of three rounds, on the task's own estimator
(``FilterEstimatorTask.estimator_object(training=True)``: no density computed). The yardstick
for work on the training's speed: one seed is 30 epochs of 20 batches of ten such chunks,
plus validation.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]


def bench_lfc_training_step(steps: int = 100, repeats: int = 3) -> dict:
    """Seconds of the forward and the backward of one ``steps``-step chunk of the first
    training batch of ``train/configs/lfc.yaml`` (module docstring), the best of ``repeats``
    rounds after one warm-up, and run-steps per second."""
    from difffilter.train.task import FilterEstimatorTask, ScenarioDataModule

    config = yaml.safe_load((ROOT / "train/configs/lfc.yaml").read_text())
    task = FilterEstimatorTask(**config["model"]["init_args"])
    data = ScenarioDataModule(**config["data"]["init_args"])
    batch = data.train_batch(0, 0)
    estimator = task.estimator_object(training=True)
    forward, backward = [], []
    for _ in range(repeats + 1):  # the first round warms up
        task.zero_grad(set_to_none=True)
        start = time.perf_counter()
        out, truth, _ = task.run(task.scenario, batch, estimator, 0, steps=steps)
        loss = task._losses(out, truth)["loss"]
        middle = time.perf_counter()
        loss.backward()
        end = time.perf_counter()
        forward.append(middle - start)
        backward.append(end - middle)
    runs = out.means.shape[0]
    fwd, bwd = min(forward[1:]), min(backward[1:])
    return {"runs": runs, "steps": steps, "forward_s": fwd, "backward_s": bwd,
            "run_steps_per_s": runs * steps / (fwd + bwd), "backward_share": bwd / (fwd + bwd),
            "threads": torch.get_num_threads(), "load_average": os.getloadavg()[0]}  # fmt: skip


def print_training(figures: dict) -> None:
    print(
        "\n11. Training the learned LFC estimator (train/configs/lfc.yaml: Kalman observer in "
        "the closed loop, gating, plain innovation, restart, float32): one TBPTT chunk of the "
        "first batch, forward and backward"
    )
    r = bench_lfc_training_step()
    figures["lfc_training_step"] = r
    print(
        f"   {r['runs']} runs × {r['steps']} steps: forward {r['forward_s']:.2f} s, backward "
        f"{r['backward_s']:.2f} s ({100 * r['backward_share']:.0f} %), "
        f"{r['run_steps_per_s']:,.0f} run-steps/s ({r['threads']} thread(s), load "
        f"{r['load_average']:.1f}); a seed of lfc.yaml is 30 × 20 × 10 such chunks plus "
        "validation"
    )
