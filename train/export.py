"""``difffilter-train export``: ship a trained estimator, explicitly.

``fit`` writes only inside its run folder (``lightning_logs/<name>/version_<n>/``, where
``ExportEstimator`` leaves ``<name>.ckpt`` and its card). Copying a result to the shipped
``checkpoints/`` is this command::

    difffilter-train export lightning_logs/lfc_nn_grad/version_3/lfc_nn_grad.ckpt \\
        --out checkpoints/lfc_nn_grad.ckpt --force

The source is an exported estimator file (checked against its card's sha256 and copied
byte for byte, with its card) or a Lightning checkpoint of a run (its estimator is
written in the exported format with a new card). An existing ``--out`` is only replaced
with ``--force``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import torch

from difffilter.models.neural_estimator import (
    checkpoint_sha256,
    load_estimator_checkpoint,
    save_estimator_checkpoint,
)

__all__ = ["export", "main"]


def export(src: str | Path, out: str | Path, *, force: bool = False) -> Path:
    """Write the estimator of ``src`` to ``out`` (and ``out`` with suffix ``.json``, its card).

    ``ValueError`` if ``out`` exists without ``force`` or ``src`` is not an estimator
    checkpoint (``FileNotFoundError`` if it does not exist). Returns ``out``.
    """
    src, out = Path(src), Path(out)
    if out.exists() and not force:
        raise ValueError(f"--out: {out} exists; pass --force to replace it")
    if out.resolve() == src.resolve():
        raise ValueError(f"--out: {out} is the source itself")
    estimator, observer = load_estimator_checkpoint(src, dtype=torch.float32)  # verifies it
    out.parent.mkdir(parents=True, exist_ok=True)
    card_src = src.with_suffix(".json")
    blob = torch.load(src, map_location="cpu", weights_only=True)
    if "pytorch-lightning_version" not in blob:  # already exported: the same bytes
        shutil.copyfile(src, out)
        card = json.loads(card_src.read_text()) if card_src.is_file() else {}
        digest = checkpoint_sha256(out)
    else:
        digest = save_estimator_checkpoint(out, estimator, observer)
        card = {
            "estimator_config": estimator.config(),
            "observer": observer,
            "epoch": blob.get("epoch"),
            "global_step": blob.get("global_step"),
            "torch_version": torch.__version__,
        }
    card.update(checkpoint=out.name, sha256=digest, exported_from=str(src))
    card.setdefault("name", out.stem)
    out.with_suffix(".json").write_text(json.dumps(card, indent=2) + "\n")
    load_estimator_checkpoint(out)  # the shipped pair loads and matches its card
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="difffilter-train export",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("src", type=Path, help="exported estimator (.ckpt) or Lightning checkpoint")
    p.add_argument("--out", type=Path, required=True, help="where to write it (and its card)")
    p.add_argument("--force", action="store_true", help="replace an existing --out")
    args = p.parse_args(argv)
    try:
        out = export(args.src, args.out, force=args.force)
    except (ValueError, FileNotFoundError) as exc:
        print(f"difffilter-train export: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out} and {out.with_suffix('.json')} (sha256 {checkpoint_sha256(out)})")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
