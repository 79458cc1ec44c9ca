"""docs/gradients.md: its fit runs as written and reaches the maximum of the likelihood."""

from __future__ import annotations

import re
from pathlib import Path

import torch

DOC = Path(__file__).resolve().parents[1] / "docs" / "gradients.md"


def test_the_documented_fit_reaches_the_maximum_likelihood():
    (block,) = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)
    namespace: dict = {}
    exec(compile(block, str(DOC), "exec"), namespace)  # noqa: S102
    q, r = namespace["q"], namespace["r"]
    # the numbers the page quotes, and near the truth (1e-3, 1e-2; 0.05)
    assert [round(float(v), 4) for v in q] == [0.0008, 0.0096] and round(float(r), 3) == 0.052
    log_q, log_r = namespace["log_q"], namespace["log_r"]
    log_q.grad = log_r.grad = None
    loss = namespace["negative_log_likelihood"]()
    loss.backward()  # at the optimum: no gradient left (relative to the likelihood's size)
    grad = torch.cat([log_q.grad, log_r.grad])
    assert float(grad.abs().max()) < 1e-4 * float(loss.detach().abs())
