"""Findings of a trial of the training workflow on two processes (``--trainer.strategy ddp
--trainer.devices 2``):

* the tracking network, whose loss leaves its attack head unused (``attack_weight: 0``),
  had died at its second step in Lightning's "parameters that were not used" error, the
  first step unaveraged: an unused parameter is now left out of the average;
* the EKF over the weights (``trainer: ekf``) has no gradient for DDP to average: the two
  processes had trained two networks, the export process 0's. Refused now.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from lightning.pytorch.strategies import DDPStrategy

from difffilter.train.lightning_cli import _check_processes

ROOT = Path(__file__).resolve().parents[1]


def _trainer(world, strategy):
    return SimpleNamespace(world_size=world, strategy=strategy)


def _task(trainer_kind):
    return SimpleNamespace(hparams={"trainer": trainer_kind})


def test_several_processes_leave_an_unused_parameter_out_of_the_average():
    ddp = DDPStrategy()
    _check_processes(_trainer(2, ddp), _task("grad"))
    assert ddp._ddp_kwargs["find_unused_parameters"] is True
    chosen = DDPStrategy(find_unused_parameters=False)  # a user's own choice is kept
    _check_processes(_trainer(2, chosen), _task("grad"))
    assert chosen._ddp_kwargs["find_unused_parameters"] is False
    alone = DDPStrategy()
    _check_processes(_trainer(1, alone), _task("ekf"))  # one process: nothing to do
    assert "find_unused_parameters" not in alone._ddp_kwargs


def test_the_ekf_over_the_weights_is_refused_on_several_processes():
    with pytest.raises(ValueError, match=r"--trainer.devices: the EKF over the weights "
                                         r"\(trainer: ekf\) trains on one process \(2 asked\)"):  # fmt: skip
        _check_processes(_trainer(2, DDPStrategy()), _task("ekf"))


_DIGESTS = '''
import hashlib, os
import lightning.pytorch as pl


class Digests(pl.Callback):
    """Each process's weights digest at the end of every training epoch."""

    def __init__(self, out: str = "digests"):
        self.out = out

    def on_train_epoch_end(self, trainer, pl_module):
        h = hashlib.sha256()
        for name, value in sorted(pl_module.state_dict().items()):
            h.update(name.encode()); h.update(value.detach().cpu().numpy().tobytes())
        os.makedirs(self.out, exist_ok=True)
        with open(os.path.join(self.out, f"rank{trainer.global_rank}"), "a") as f:
            f.write(h.hexdigest() + "\\n")
'''


@pytest.mark.slow
def test_the_tracking_network_trains_as_one_network_on_two_processes(tmp_path):
    (tmp_path / "digests_callback.py").write_text(_DIGESTS)
    cmd = [sys.executable, "-m", "difffilter.train.cli", "fit",
           "--config", str(ROOT / "train" / "configs" / "tracking.yaml"),
           "--trainer.max_epochs=2", "--trainer.strategy=ddp", "--trainer.devices=2",
           "--data.init_args.batches_per_epoch=2", "--data.init_args.batch_size=4",
           "--data.init_args.val_runs=4", "--model.init_args.num_particles=50", "--no-progress",
           "--trainer.callbacks+=digests_callback.Digests",
           f"--trainer.callbacks.out={tmp_path / 'digests'}"]  # fmt: skip
    env = {**__import__("os").environ, "PYTHONPATH": str(tmp_path)}
    done = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    ranks = [(tmp_path / "digests" / f"rank{r}").read_text().split() for r in (0, 1)]
    assert len(ranks[0]) == 2 and ranks[0] == ranks[1]  # one network after every epoch
