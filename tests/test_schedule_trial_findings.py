"""Findings of a red-team trial of the schedules and random streams (each failed before
its fix)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difffilter.input_loss import InputLossSchedule
from difffilter.models.calibration_cache import model_fingerprint
from difffilter.models.schedules import AllSensors, PacketLoss, RoundRobin


def test_nested_groups_are_fingerprinted_apart():
    """Nested tuples had flattened alike: two schedules of other groups got one cached
    CUSUM threshold (5.648 served where its own is 6.776)."""
    assert model_fingerprint(RoundRobin(((0, 1), (2,)))) != model_fingerprint(
        RoundRobin(((0,), (1, 2)))
    )
    assert model_fingerprint(PacketLoss(0.5, ((0, 1, 2),))) != model_fingerprint(
        PacketLoss(0.5, ((0,), (1,), (2,)))
    )
    assert model_fingerprint([[1], 2]) != model_fingerprint([1, [2]])
    assert model_fingerprint({"a": (1, 2)}) != model_fingerprint({"a": ((1,), 2)})
    shared = torch.ones(2)
    assert model_fingerprint((shared, shared)) != model_fingerprint((shared,))  # met again
    assert model_fingerprint(RoundRobin(((0, 1), (2,)))) == model_fingerprint(
        RoundRobin(((0, 1), (2,)))
    )


def test_an_input_loss_of_every_entry_arriving_is_no_loss():
    """InputLossSchedule(AllSensors()) was taken, then failed at every simulation on its
    None mask, naming neither."""
    loss = InputLossSchedule(AllSensors()).draw(3, 5, 2)
    assert loss.mask.shape == (3, 5, 2) and bool(loss.mask.all())


def test_round_robin_start_names_a_group():
    """start = 2 over two groups (a 1-based γ_ini) had wrapped to group 0 unsaid; numpy's
    integers were refused where groups take them."""
    with pytest.raises(ValueError, match=r"start must be the 0-based index of a group, 0 … 1"):
        RoundRobin(((0,), (1,)), start=2)
    rr = RoundRobin(((0,), (1,)), start=np.int64(1))
    assert rr.start == 1 and isinstance(rr.start, int)
    assert rr.scheduled(4).tolist() == [1, 0, 1, 0]
