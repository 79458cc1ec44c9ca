"""Consoles and locales as users' machines have them (an I/O trial): under a locale of
another encoding (Python's UTF-8 mode off) a finished evaluation had stopped writing
report.md (``write_text`` without an encoding: 'ascii' codec can't encode '×'), and then
at its last print; ``difffilter-train --help | head -1`` had ended in a BrokenPipeError
traceback and exit 1."""

import ast
import os
import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
ASCII_LOCALE = {"LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}


def test_every_text_file_the_package_reads_or_writes_names_its_encoding():
    calls = []
    for folder in ("difffilter", "models", "eval", "train"):
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
                if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                        and node.func.attr in ("read_text", "write_text")
                        and not any(k.arg == "encoding" for k in node.keywords)):  # fmt: skip
                    calls.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert calls == []


def _under_ascii_locale(code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, **ASCII_LOCALE, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          encoding="utf-8", errors="replace", timeout=120)  # fmt: skip


def test_reports_are_written_and_printed_under_an_ascii_locale(tmp_path):
    target = tmp_path / "report.md"
    code = (
        "import sys, locale\n"
        "assert locale.getpreferredencoding(False).lower() != 'utf-8', 'UTF-8 locale'\n"
        "from difffilter.models.atomic_write import write_atomically\n"
        "from difffilter.interrupts import console_output_tolerant\n"
        "from difffilter.eval.report import metrics_schema\n"
        f"write_atomically({str(target)!r}, 'TPR \\u2265 0.99 \\u2713 \\u00d7')\n"
        "metrics_schema()\n"
        "console_output_tolerant()\n"
        "print('TPR \\u2265 0.99 \\u2713')\n"
    )
    done = _under_ascii_locale(code)
    assert done.returncode == 0, done.stderr
    assert target.read_text(encoding="utf-8") == "TPR ≥ 0.99 ✓ ×"
    assert "TPR \\u2265 0.99 \\u2713" in done.stdout


def test_train_help_into_a_closed_pipe_ends_quietly():
    read, write = os.pipe()
    os.close(read)  # the reader (`head -1`) has left
    try:
        done = subprocess.run([sys.executable, "-m", "difffilter.train.cli", "--help"],
                              stdout=write, stderr=subprocess.PIPE, text=True, timeout=120,
                              env={**os.environ, "PYTHONPATH": str(ROOT)})  # fmt: skip
    finally:
        os.close(write)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
