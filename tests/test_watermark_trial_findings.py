"""The LFC watermark's arguments (a red-team trial of the watermark study, 2026-12-07; each
test failed before its fix). In a file of their own: test_watermark.py is in the slow group."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.models.lfc import LFCPlant, Watermarked, lfc_loop


@pytest.mark.parametrize("entries", [3, 4])
def test_the_watermark_never_marks_the_loads(entries):
    """A red-team trial: a std of 3 or 4 entries marked the loads, which ride along in the
    input and which the observer's model leaves out (a watermark it does not know)."""
    plant = LFCPlant()
    xi, theta = plant.sample_noise(2, 10, torch.Generator().manual_seed(0))
    load = torch.tensor([[0.01, 0.0]], dtype=torch.float64)
    gen = torch.Generator().manual_seed(1)
    mark = lambda c: Watermarked(c, torch.full((entries,), 0.1), gen)  # noqa: E731
    with pytest.raises(ValueError, match=f"std has {entries} entries and the controller 2"):
        lfc_loop(plant, df.KalmanFilter(), xi, theta, load, compensate=False, watermark=mark)


@pytest.mark.parametrize("generator", [None, 5])
def test_the_watermark_needs_a_generator(generator):
    """None drew from torch's global stream (two identical loops marked apart, 0.37 in
    the inputs), 5 failed at the first step on torch's "invalid combination of arguments"."""
    with pytest.raises(ValueError, match="generator must be a torch.Generator"):
        Watermarked(None, torch.full((2,), 0.1), generator)
