"""The ``slow`` group names tests that exist: a renamed test would otherwise leave the group
silently and run in ``make test``."""

from __future__ import annotations

import ast
from pathlib import Path

from conftest import SLOW

TESTS = Path(__file__).resolve().parent


def _test_functions(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    return {node.name for node in ast.walk(tree) if isinstance(node, ast.FunctionDef)}


def test_every_slow_entry_names_a_test_file_or_function_that_exists():
    stale = []
    for entry in SLOW:
        file, _, test = entry.partition("::")
        path = TESTS / file
        if not path.is_file() or (test and test not in _test_functions(path)):
            stale.append(entry)
    assert not stale, f"tests/conftest.py SLOW names tests that do not exist: {stale}"
