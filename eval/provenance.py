"""Which code wrote a report: the ``software`` record of ``metrics.json`` and
``robustness.json``.

A run of the wrong copy of the library cannot be told from its numbers (a trial's console
script imported another checkout than the one it ran in, and nothing in the report said
so). The record names the ``difffilter`` package's folder, its version, and, where that
folder lies in a git work tree, the commit it was at and whether tracked files differed
from it; and the versions of Python and torch::

    {"difffilter": "0.1.0", "source": "/path/to/difffilter", "git_commit": "4889d61…",
     "git_dirty": false, "torch": "2.13.0", "python": "3.11.9"}

``git_commit`` and ``git_dirty`` are ``null`` outside a git work tree or without git.
"""

from __future__ import annotations

import functools
import os
import platform
import subprocess
from pathlib import Path

import torch

import difffilter

__all__ = ["software_record", "software_line"]


def _git(folder: Path, *args: str) -> str | None:
    """``git -C folder args`` stripped, or ``None`` where git or the work tree is missing."""
    # the folder alone says which repository: GIT_DIR or GIT_WORK_TREE exported by a script
    # driving another repository had recorded that one's commit (a provenance trial)
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}
    try:
        done = subprocess.run(["git", "-C", str(folder), *args], capture_output=True,
                              text=True, timeout=10, check=False, env=env)  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


@functools.cache
def software_record() -> dict:
    """The module docstring's record (once per process: a study's reports share it)."""
    source = Path(difffilter.__file__).resolve().parent
    # the commit of a tree that tracks these files: a copy inside another work tree (a
    # pip install into the repository's own .venv, a vendored copy) had been given that
    # tree's commit, as if the files that ran were the commit's
    tracked = _git(source, "ls-files", "--error-unmatch", "__init__.py") is not None
    commit = _git(source, "rev-parse", "HEAD") if tracked else None
    status = None if commit is None else _git(source, "status", "--porcelain",
                                                  "--untracked-files=no")  # fmt: skip
    return {
        "difffilter": difffilter.__version__,
        "source": str(source),
        "git_commit": commit,
        "git_dirty": None if status is None else bool(status),
        "torch": torch.__version__,
        "python": platform.python_version(),
    }


def software_line(record: dict | None) -> str:
    """One line of a report's summary: the version, the commit (``+ changes`` where tracked
    files differed from it) and the folder; ``""`` for a report written before the record."""
    if not record:
        return ""
    commit = record.get("git_commit")
    dirty = record.get("git_dirty")
    # (a git status that failed had read as a clean tree)
    changes = " + changes" if dirty else " + changes unknown" if dirty is None else ""
    at = "" if commit is None else f" at {commit[:12]}{changes}"
    return (f"\nCode: difffilter {record['difffilter']}{at} (`{record['source']}`), torch "
            f"{record['torch']}, Python {record['python']}.\n")  # fmt: skip
