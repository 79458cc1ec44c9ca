"""A trial of the LFC plant and context: ``LFCContext.dt``/``dtype`` and ``LFCPlant.params``
assigned after construction had been stored beside the matrices and gains built from the
old values (the Luenberger gain then designed from the old plant's ``A_d`` with the new
``dt``: 1.8 off a context of that ``dt``; the LQR gain of the new parameters 8.05 off the
plant's). Each is read-only now, named."""

from __future__ import annotations

import pytest
import torch

from difffilter.models.lfc import LFCParameters, LFCPlant, lqr_gain
from difffilter.models.lfc_estimators import LFCContext


def test_a_contexts_sampling_time_and_dtype_are_read_only():
    ctx = LFCContext(dt=0.01)
    with pytest.raises(AttributeError, match=r"LFCContext.dt is its plant's: build a new"):
        ctx.dt = 0.001
    with pytest.raises(AttributeError, match=r"LFCContext.dtype is read-only"):
        ctx.dtype = torch.float32
    assert ctx.dt == ctx.plant.dt == 0.01 and ctx.dtype is torch.float64
    fine = LFCContext(dt=0.001, dtype=torch.float32)
    assert fine.dt == fine.plant.dt == 0.001 and fine.luenberger("modal").dtype is torch.float32
    # the gain is the one of a context built at its dt (the trial's mixed design is not made)
    torch.testing.assert_close(ctx.luenberger("modal"), LFCContext(dt=0.01).luenberger("modal"))


def test_a_plants_parameters_are_read_only():
    plant = LFCPlant(dt=0.01)
    other = LFCParameters(tie_stiffness=0.3)
    with pytest.raises(AttributeError, match=r"LFCPlant.params are built into its matrices"):
        plant.params = other
    assert plant.params == LFCParameters()
    built = LFCPlant(dt=0.01, params=other)
    assert built.params is other and not torch.equal(lqr_gain(built), lqr_gain(plant))


def test_a_scenarios_load_range_is_checked_when_built():
    """``load_range`` is the width of ``U[−range/2, range/2]``: a negative one had drawn the
    mirrored loads without a word, an infinite one failed only at simulate."""
    import dataclasses

    from difffilter.models.registry import get

    scenario = get("lfc_step")
    for bad in (-1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match=r"load_range \(the width of .*\) must be a finite"):
            dataclasses.replace(scenario, load_range=bad)
    with pytest.raises(TypeError, match="load_range"):
        dataclasses.replace(scenario, load_range="0.02")
    assert dataclasses.replace(scenario, load_range=0).load_range == 0.0
