"""Files that are replaced whole or not at all.

``calibrate --out checkpoints/<name>.ckpt --force`` rewrites a shipped checkpoint in place:
interrupted in the middle of a plain write, it would leave half a checkpoint (and a card
whose sha256 no longer matches). Each write here goes to a temporary file in the same
folder, which then replaces the target in one ``os.replace`` (atomic on one file system).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import threading
from collections.abc import Callable
from pathlib import Path

__all__ = ["sibling_name", "write_atomically", "write_json_atomically"]


def write_atomically(path: str | Path, content: str | bytes | Callable[[Path], object]) -> None:
    """``content`` (text, bytes, or a function that writes the whole file to the path it is
    given) goes to a partial file, which then becomes ``path``; on any error or interrupt
    the partial file goes and ``path`` is left as it was. An ``OSError`` names ``path``
    (a full disk's names no file, a failed rename the partial one: a report writer's error
    line had to say which file was not written)."""
    path = Path(path)
    # a partial file of this process and thread: two threads writing one path had shared
    # it, and the first to finish moved the other's half-written file into place. Its name
    # is the target's cut to a prefix (with a digest of the whole): a legal name of 240
    # bytes had made a partial one past the file system's 255 (an interrupts trial)
    partial = sibling_name(path, f"{os.getpid()}.{threading.get_ident()}.partial")
    try:
        if isinstance(content, str):
            partial.write_text(content, encoding="utf-8")
        elif isinstance(content, bytes):
            partial.write_bytes(content)
        else:
            content(partial)
        os.replace(partial, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):  # (its own error had hidden the first)
            partial.unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.errno is not None and _about(exc, partial, path):
            # named after the target: "-> None" had ended every such line (filename2 set to
            # None is printed), and an error about another file a writer read is left alone
            raise type(exc)(exc.errno, exc.strerror, str(path)) from exc
        raise


def sibling_name(path: Path, tag: str) -> Path:
    """A hidden file beside ``path`` for writing it first: ``path``'s name cut to 64 bytes
    (a legal long name stays legal: a 240-byte one had made a partial name past the file
    system's 255; cut by characters, 62 emoji had), a digest of the whole name (two names
    cut alike stay apart: a checkpoint and its card had shared one) and ``tag``."""
    digest = hashlib.sha256(path.name.encode()).hexdigest()[:12]
    prefix = path.name.encode()[:64].decode(errors="ignore")
    return path.with_name(f".{prefix}.{digest}.{tag}")


def _about(exc: OSError, partial: Path, path: Path) -> bool:
    """Whether ``exc`` is about the write itself: no file named, or the partial file or
    the target (not another file the writer function read)."""
    named = {exc.filename, exc.filename2} - {None}
    return not named or all(str(name) in (str(partial), str(path)) for name in named)


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
