"""Findings of a red-team trial of the reproducibility records (each failed before its fix)."""

from __future__ import annotations

from pathlib import Path


def test_the_library_fingerprint_covers_the_evaluation_code(monkeypatch):
    """In a development checkout eval/ lies outside difffilter/: a fix of a metric left
    the sweep's cached baselines (keyed by this fingerprint) of before in use."""
    import difffilter.eval.scoring as scoring
    from difffilter.models import calibration_cache as cc

    monkeypatch.setattr(cc, "_LIBRARY_FINGERPRINT", None)
    before = cc.library_fingerprint()
    edited = Path(scoring.__file__).resolve()
    read = Path.read_bytes

    def read_edited(path):
        data = read(path)
        return data + b"\n# edited\n" if Path(path).resolve() == edited else data

    monkeypatch.setattr(Path, "read_bytes", read_edited)
    monkeypatch.setattr(cc, "_LIBRARY_FINGERPRINT", None)
    assert cc.library_fingerprint() != before


def test_a_copy_inside_another_work_tree_gets_no_commit_and_an_unknown_status_is_said(
    tmp_path, monkeypatch
):
    """A copy of difffilter/ inside an unrelated repository (a pip install into its .venv)
    had been given that repository's commit; a git status that failed read as clean."""
    import shutil
    import subprocess

    import difffilter
    from difffilter.eval import provenance

    repo = tmp_path / "other"
    repo.mkdir()
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git[:3], "init", "-q"], check=True)
    (repo / "README").write_text("x")
    subprocess.run([*git, "add", "README"], check=True)
    subprocess.run([*git, "commit", "-qm", "x"], check=True)
    copy = repo / "site" / "difffilter"
    shutil.copytree(Path(difffilter.__file__).parent, copy,
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    monkeypatch.setattr(difffilter, "__file__", str(copy / "__init__.py"))
    provenance.software_record.cache_clear()
    try:
        record = provenance.software_record()
    finally:
        provenance.software_record.cache_clear()
    assert record["git_commit"] is None and record["git_dirty"] is None
    line = provenance.software_line({**record, "git_commit": "0123456789abcdef", "git_dirty": None})
    assert "at 0123456789ab + changes unknown" in line
