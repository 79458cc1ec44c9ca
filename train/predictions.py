"""``difffilter-train predict`` writes what the estimator predicted, batch by batch.

:class:`PredictionFiles` (a Lightning :class:`~lightning.pytorch.callbacks.BasePredictionWriter`)
saves every prediction batch as ``batch_<i>.pt`` in ``<run folder>/predictions/`` and an
index, ``predictions.json``, beside them. A batch file is a dict of tensors (load it with
``torch.load(path, weights_only=True)``)::

    means               [B, T, dx]  state estimates x̂_k
    attack_estimate     [B, T, da]  estimates of the injected signal (channel in the index)
    attack_probability  [B, T]      the detection score the threshold applies to: the
                                    head's probability of attack, or, for a network without
                                    a head (the EKF-trained ones), its squared standardised
                                    estimate Σ (â/√S)² (not a probability: above 1 too)
    alarms              [B, T]      bool, attack_probability > threshold

``B`` runs of the predict data (the data module's ``test_runs`` drawn from ``test_seed``),
``T`` steps; step ``t`` is measurement ``k = t + 1`` at time ``k·dt``. The index holds the
scenario, ``dt``, the alarm threshold, the channel, the seed, and per file its runs and
steps.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from lightning.pytorch.callbacks import BasePredictionWriter

__all__ = ["PredictionFiles", "FIELDS"]

#: The tensors of a batch file and their shapes (module docstring).
FIELDS = {
    "means": "[B, T, dx] state estimates",
    "attack_estimate": "[B, T, da] estimates of the injected signal",
    "attack_probability": "[B, T] the detection score: the head's probability of attack, or "
    "without a head the squared standardised estimate",
    "alarms": "[B, T] bool: attack_probability > threshold",
}


class PredictionFiles(BasePredictionWriter):
    """Write each prediction batch and the index (module docstring) under ``folder``
    (default ``<trainer.log_dir>/predictions``, else ``./predictions``)."""

    def __init__(self, folder: str | Path | None = None):
        super().__init__(write_interval="batch")
        self._given = None if folder is None else Path(folder)
        self.folder = self._given
        self.files: list[dict] = []

    def on_predict_start(self, trainer, pl_module):
        # one index per prediction: a second trainer.predict with this callback had listed
        # its batch files twice (6 runs counted for 3) and written into the first trainer's
        # folder (a red-team trial)
        self.files, self.folder = [], self._given

    def _target(self, trainer) -> Path:
        if self.folder is None:
            self.folder = Path(trainer.log_dir or ".") / "predictions"
        self.folder.mkdir(parents=True, exist_ok=True)
        return self.folder

    def write_on_batch_end(self, trainer, pl_module, prediction, batch_indices, batch,
                           batch_idx, dataloader_idx):  # fmt: skip
        folder = self._target(trainer)
        name = f"batch_{batch_idx:05d}.pt"
        tensors = {k: v.detach().cpu() for k, v in prediction.items() if k in FIELDS}
        torch.save(tensors, folder / name)
        B, T = tensors["alarms"].shape
        self.files.append({"file": name, "runs": int(B), "steps": int(T)})

    def on_predict_end(self, trainer, pl_module):
        if not self.files:
            return
        folder = self._target(trainer)
        dm = getattr(trainer, "datamodule", None)
        scenario = pl_module.scenario_of_data()
        index = {
            "scenario": scenario.name, "dt_s": float(scenario.dt),
            "threshold": float(pl_module.alarm_threshold),
            "channel": pl_module.channel.value,
            "seed": None if dm is None else dm.hparams.get("test_seed"),
            "fields": FIELDS, "files": self.files,
        }  # fmt: skip
        (folder / "predictions.json").write_text(
            json.dumps(index, indent=2) + "\n", encoding="utf-8"
        )
        runs = sum(f["runs"] for f in self.files)
        print(f"predictions of {runs} runs written to {folder}/ (predictions.json, "
              f"{len(self.files)} batch file(s); train/predictions.py says the format)")  # fmt: skip
