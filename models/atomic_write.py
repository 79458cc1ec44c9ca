"""Files that are replaced whole or not at all.

``calibrate --out checkpoints/<name>.ckpt --force`` rewrites a shipped checkpoint in place:
interrupted in the middle of a plain write, it would leave half a checkpoint (and a card
whose sha256 no longer matches). Each write here goes to a temporary file in the same
folder, which then replaces the target in one ``os.replace`` (atomic on one file system).
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Callable
from pathlib import Path

__all__ = ["write_atomically", "write_json_atomically"]


def write_atomically(path: str | Path, content: str | bytes | Callable[[Path], object]) -> None:
    """``content`` (text, bytes, or a function that writes the whole file to the path it is
    given) goes to a partial file, which then becomes ``path``; on any error or interrupt
    the partial file goes and ``path`` is left as it was. An ``OSError`` names ``path``
    (a full disk's names no file, a failed rename the partial one: a report writer's error
    line had to say which file was not written)."""
    path = Path(path)
    # a partial file of this process and thread: two threads writing one path had shared
    # it, and the first to finish moved the other's half-written file into place
    partial = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.partial")
    try:
        if isinstance(content, str):
            partial.write_text(content)
        elif isinstance(content, bytes):
            partial.write_bytes(content)
        else:
            content(partial)
        os.replace(partial, path)
    except BaseException as exc:
        partial.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            exc.filename, exc.filename2 = str(path), None
        raise


def save_torch_atomically(path: str | Path, obj) -> None:
    """``torch.save(obj)`` to ``path``, whole or not at all (:func:`write_atomically`), its
    bytes the same in every process: saved to a buffer first, torch names the archive
    inside the file "archive"; saved to the partial file, it named it after that file's
    name, which holds the process id, so two identical exports had two file digests (a
    trial: a resumed fit's card differed from the uninterrupted one's in its sha256)."""
    import io

    import torch

    buffer = io.BytesIO()
    torch.save(obj, buffer)
    write_atomically(path, buffer.getvalue())


def write_json_atomically(path: str | Path, document) -> None:
    """``document`` as indented JSON with a final newline, written atomically."""
    write_atomically(path, json.dumps(document, indent=2) + "\n")
