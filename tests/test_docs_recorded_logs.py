"""docs/recorded-logs.md: the snippet runs as written, and what it computes is what it says:
the NaN entries are the explicit mask's, the threshold allows ⌊α n⌋ alarms on the
attack-free stretch, the gated filter alarms at that threshold from the attack's onset."""

from __future__ import annotations

import math
import re
from pathlib import Path

import torch

import difffilter as df

DOC = Path(__file__).resolve().parents[1] / "docs" / "recorded-logs.md"


def test_the_recorded_log_snippet_computes_what_the_page_says():
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)
    assert len(blocks) == 1
    ns: dict = {}
    exec(compile(blocks[0], str(DOC), "exec"), ns)  # noqa: S102
    model, y, us = ns["model"], ns["y"], ns["us"]
    mask = torch.isfinite(y)
    assert int((~mask).sum()) == 4
    masked = df.kalman_filter(model, torch.nan_to_num(y), us, mask=mask)
    torch.testing.assert_close(ns["est"].means, masked.means, rtol=0, atol=0)
    free = ns["free"].detection.scores
    assert int((free > ns["tau"]).sum()) <= math.floor(0.01 * 350)
    assert math.isclose(ns["detector"].threshold, ns["tau"], rel_tol=1e-9)
    assert ns["first_alarm"] == 400  # the attack's onset
    scores, alarms = ns["gated"].detection.scores, ns["gated"].detection.alarms
    assert torch.equal(alarms[mask.all(-1)], (scores > ns["tau"] * (1 + 1e-12))[mask.all(-1)])
    assert ns["table"].shape == (600, 6)
    smoothed = ns["smoothed"]  # the filter's at the last step, no wider anywhere
    torch.testing.assert_close(smoothed.means[-1], ns["est"].means[-1], rtol=0, atol=0)
    assert bool(
        (
            smoothed.covs.diagonal(dim1=-2, dim2=-1)
            <= ns["est"].covs.diagonal(dim1=-2, dim2=-1) + 1e-15
        ).all()
    )
