"""The ``software`` record of a report (``eval/provenance.py``): which copy of the library
wrote it. A trial's console script imported another checkout than the one it ran in, and
no report said so. Checked against git run here, independently, and against the package
Python imported."""

from __future__ import annotations

import subprocess
from pathlib import Path

import torch

import difffilter
from difffilter.eval import provenance
from difffilter.eval.provenance import software_line, software_record


def _git_here(*args: str) -> str | None:
    folder = Path(difffilter.__file__).resolve().parent
    try:
        done = subprocess.run(["git", "-C", str(folder), *args], capture_output=True, text=True)
    except OSError:
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def test_the_record_names_the_imported_package_and_its_commit():
    """``source`` is the folder of the ``difffilter`` Python imported; ``git_commit`` is that
    folder's ``git rev-parse HEAD`` (``null`` outside a work tree) and ``git_dirty`` whether
    ``git status`` lists a changed tracked file; the versions are the running ones."""
    record = software_record()
    assert record["source"] == str(Path(difffilter.__file__).resolve().parent)
    assert record["difffilter"] == difffilter.__version__
    assert record["torch"] == torch.__version__
    commit = _git_here("rev-parse", "HEAD")
    assert record["git_commit"] == commit
    if commit is None:
        assert record["git_dirty"] is None
    else:
        assert len(commit) == 40
        status = _git_here("status", "--porcelain", "--untracked-files=no")
        assert record["git_dirty"] is bool(status)


def test_outside_a_work_tree_or_without_git_there_is_no_commit(tmp_path, monkeypatch):
    """A folder outside any git work tree, and a machine without git, give ``None`` (never
    an error: a report must be written without git)."""
    assert provenance._git(tmp_path, "rev-parse", "HEAD") is None

    def no_git(*args, **kwargs):
        raise FileNotFoundError("git")

    monkeypatch.setattr(provenance.subprocess, "run", no_git)
    assert provenance._git(Path(difffilter.__file__).parent, "rev-parse", "HEAD") is None


def test_the_reports_line_says_the_commit_and_whether_files_had_changed():
    """Twelve digits of the commit, "+ changes" only where tracked files differed, nothing
    of a commit outside a work tree, and no line for a report written before the record."""
    record = {"difffilter": "0.1.0", "source": "/x/difffilter", "git_commit": "a" * 40,
              "git_dirty": False, "torch": "2.13.0", "python": "3.11.7"}  # fmt: skip
    line = software_line(record)
    assert "difffilter 0.1.0 at aaaaaaaaaaaa (`/x/difffilter`)" in line
    assert "+ changes" not in line and "a" * 13 not in line
    assert "at aaaaaaaaaaaa + changes" in software_line({**record, "git_dirty": True})
    bare = software_line({**record, "git_commit": None, "git_dirty": None})
    assert "difffilter 0.1.0 (`/x/difffilter`), torch 2.13.0, Python 3.11.7" in bare
    assert software_line(None) == "" and software_line({}) == ""
