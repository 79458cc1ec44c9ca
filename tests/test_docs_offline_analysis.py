"""docs/offline-analysis.md: the snippet runs as written and prints what the page says, and
what it computes holds against independent truths: the smoother agrees with the filter at
the last step and is nowhere wider, the particle smoother lands near the RTS smoother, and
the PCRB of a linear-Gaussian model is the Kalman filter's covariance."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import torch

import difffilter as df

DOC = Path(__file__).resolve().parents[1] / "docs" / "offline-analysis.md"


NUMBER = r"\d+\.?\d*(?:e-?\d+)?"


def _numbers(text: str) -> list[float]:
    return [float(x) for x in re.findall(NUMBER, text)]


def _words(text: str) -> str:
    return re.sub(NUMBER, "#", text)


def test_the_offline_analysis_snippet_prints_and_computes_what_the_page_says():
    text = DOC.read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    printed = re.findall(r"```text\n(.*?)```", text, flags=re.S)
    assert len(blocks) == 1 and len(printed) == 1
    ns: dict = {}
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(blocks[0], str(DOC), "exec"), ns)  # noqa: S102
    assert _words(out.getvalue()) == _words(printed[0])
    for got, said in zip(_numbers(out.getvalue()), _numbers(printed[0]), strict=True):
        # the PCRB's distance to the filter is round-off (its digits vary with the BLAS)
        assert got == said or (said < 1e-9 and got < 1e-9), (got, said)

    filtered, smoothed, ps, bound = ns["filtered"], ns["smoothed"], ns["ps"], ns["bound"]
    assert torch.equal(smoothed.means[:, -1], filtered.means[:, -1])
    diag = lambda c: c.diagonal(dim1=-2, dim2=-1)  # noqa: E731
    assert bool((diag(smoothed.covs) <= diag(filtered.covs) + 1e-15).all())
    # the same smoother in one call
    once = df.kalman_smoother(ns["model"], ns["ys"], mask=ns["mask"])
    torch.testing.assert_close(once.means, smoothed.means, rtol=0, atol=0)
    # the particle smoother a quarter of a posterior sd from the RTS means (the page), where
    # the 200 particles' filtering means are 1.6 away
    sd = diag(smoothed.covs)[..., 0].sqrt()
    assert float(((ps.means - smoothed.means)[..., 0].abs() / sd).mean()) < 0.35
    particles = ns["particles"]
    assert float(((particles.means - smoothed.means)[..., 0].abs() / sd).mean()) > 1.0
    # the floor: on a linear-Gaussian model J_k⁻¹ is the Kalman filter's P_k|k (mask included)
    torch.testing.assert_close(bound, filtered.covs[0], rtol=1e-9, atol=1e-12)
    gap = ns["gap"]
    assert bool((diag(bound)[gap, 0].diff() > 0).all())  # the outage: the floor rises
