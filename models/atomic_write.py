"""Files that are replaced whole or not at all.

``calibrate --out checkpoints/<name>.ckpt --force`` rewrites a shipped checkpoint in place:
interrupted in the middle of a plain write, it would leave half a checkpoint (and a card
whose sha256 no longer matches). Each write here goes to a temporary file in the same
folder, which then replaces the target in one ``os.replace`` (atomic on one file system).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

__all__ = ["write_atomically", "write_json_atomically"]


def write_atomically(path: str | Path, write: Callable[[Path], object]) -> None:
    """``write(partial)`` writes the whole file to ``partial``, which then becomes ``path``;
    on any error or interrupt the partial file goes and ``path`` is left as it was."""
    path = Path(path)
    partial = path.with_name(f".{path.name}.{os.getpid()}.partial")
    try:
        write(partial)
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


def write_json_atomically(path: str | Path, document) -> None:
    """``document`` as indented JSON with a final newline, written atomically."""
    text = json.dumps(document, indent=2) + "\n"
    write_atomically(path, lambda partial: partial.write_text(text))
