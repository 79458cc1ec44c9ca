"""``difffilter-train``: the Lightning command line of difffilter's trainable estimators.

Usage::

    difffilter-train fit --config train/configs/lfc.yaml
    difffilter-train fit --config train/configs/lfc.yaml --trainer.fast_dev_run=1
    difffilter-train fit --config train/configs/lfc.yaml --ckpt_path <run>/checkpoints/last.ckpt
    difffilter-train export <run>/lfc_nn_grad.ckpt --out checkpoints/lfc_nn_grad.ckpt --force

The YAML files in ``train/configs/`` hold every setting (model, data, trainer, callbacks);
``--print_config`` shows the resolved configuration. TensorBoard logs go under the
logger's ``save_dir`` (``tensorboard --logdir lightning_logs``). ``fit`` writes only
inside its run folder; ``export`` (:mod:`difffilter.train.export`) ships a result.
"""

from __future__ import annotations

import os
import sys

import torch
from lightning.pytorch.cli import LightningCLI

from difffilter.runtime import tune_cpu_allocator

from .lfc import LFCDataModule, LFCGradModule

__all__ = ["main"]


def main(args: list[str] | None = None) -> int:
    """Entry point of the ``difffilter-train`` console script (``args`` for tests).

    Training simulates closed loops step by step: a long chain of tiny tensor operations,
    for which intra-op threads only add synchronisation (and stall badly when another
    process holds a core). One thread is the default; ``DIFFFILTER_THREADS`` overrides it.
    """
    argv = sys.argv[1:] if args is None else list(args)
    if argv[:1] == ["export"]:
        from .export import main as export_main

        return export_main(argv[1:])
    torch.set_num_threads(int(os.environ.get("DIFFFILTER_THREADS", "1")))
    tune_cpu_allocator()
    try:
        LightningCLI(
            LFCGradModule,
            LFCDataModule,
            args=args,
            save_config_kwargs={"overwrite": True},
            auto_configure_optimizers=False,
        )
    except (ValueError, FileNotFoundError) as exc:
        # a user error (a setting out of range, a missing file): one line, no traceback
        print(f"difffilter-train: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
