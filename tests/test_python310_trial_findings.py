"""Python 3.10, which pyproject.toml supports, has no ``BaseException.add_note``: an
estimator's own error raised through ``run_suite`` had come out as an ``AttributeError``
there (a packaging trial). Every note goes through ``difffilter._checks.add_note``."""

import ast
import pathlib
import re

import pytest

from difffilter._checks import add_note

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_the_package_still_claims_python_310():
    # (read as text: tomllib is no module of Python 3.10)
    text = (ROOT / "pyproject.toml").read_text()
    assert re.search(r'^requires-python = ">=3.10"$', text, re.M)


def test_no_module_calls_add_note_on_an_exception_itself():
    calls = []
    for folder in ("difffilter", "models", "eval", "train"):
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                        and node.func.attr == "add_note"):  # fmt: skip
                    calls.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    # the helper's own call alone
    assert [c.split(":")[0] for c in calls] == ["difffilter/_checks.py"]


class _Py310Error(RuntimeError):
    """An error as Python 3.10 makes it: no add_note."""

    def __getattribute__(self, name):
        if name == "add_note":
            raise AttributeError(name)
        return super().__getattribute__(name)


def test_add_note_keeps_the_error_where_python_has_no_notes():
    error = _Py310Error("shape mismatch in my estimator")
    add_note(error, "(raised by estimator 'mine')")
    with pytest.raises(_Py310Error, match="shape mismatch"):
        raise error
    noted = RuntimeError("x")
    add_note(noted, "(raised by estimator 'mine')")
    assert noted.__notes__ == ["(raised by estimator 'mine')"]
