"""docs/plugins.md runs as written: its Python blocks in order in one namespace (each
example asserts its own numbers against the Kalman filter)."""

from __future__ import annotations

import re
from pathlib import Path

PAGE = Path(__file__).resolve().parents[1] / "docs" / "plugins.md"


def test_every_python_block_of_the_page_runs():
    blocks = re.findall(r"```python\n(.*?)```", PAGE.read_text(), flags=re.S)
    assert len(blocks) == 5
    namespace: dict = {}
    for block in blocks:
        exec(compile(block, str(PAGE), "exec"), namespace)
    assert namespace["out"].mean.shape == (4, 2)
