"""How the suite runs: the ``slow`` group names tests that exist (a renamed test would
otherwise leave the group silently and run in ``make test``), and ``make test``'s workers
keep to one intra-op thread."""

from __future__ import annotations

import ast
import os
from pathlib import Path

import pytest
import torch
from conftest import SLOW

TESTS = Path(__file__).resolve().parent


def _test_functions(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    return {node.name for node in ast.walk(tree) if isinstance(node, ast.FunctionDef)}


def test_every_slow_entry_names_a_test_file_or_function_that_exists():
    stale = []
    for entry in SLOW:
        file, _, test = entry.split("[")[0].partition("::")  # a parameter: conftest checks it
        path = TESTS / file
        if not path.is_file() or (test and test not in _test_functions(path)):
            stale.append(entry)
    assert not stale, f"tests/conftest.py SLOW names tests that do not exist: {stale}"


def test_a_worker_of_make_test_and_the_command_lines_it_starts_use_one_thread():
    """``make test`` runs pytest-xdist workers side by side: with torch's default threads in
    each, two workers on two cores wait on each other's threads (tens of times slower)."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        pytest.skip("not a pytest-xdist worker (make test TEST_JOBS=0 or plain pytest)")
    assert torch.get_num_threads() == 1
    assert os.environ["OMP_NUM_THREADS"] == "1"
