"""Findings of a red-team trial of the attack tables, ``inject`` and the expected-input
filter's arguments (2026-12-06), each against numbers written out by hand."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.attack import Channel, TabulatedAttack, inject


class _SharedTable(TabulatedAttack):
    """One value table for every run (``[T, dim]``, not expanded) beside per-run flags."""

    def sample(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        values = torch.full((num_steps, dim), 5.0, dtype=dtype)
        flags = torch.zeros(*batch_shape, num_steps, dtype=torch.bool)
        flags[0] = True  # run 0 attacked at every step
        return values, flags


def test_a_table_of_other_runs_than_its_batch_is_refused_by_name():
    # B = T = 4: the flags' rows had been read as the steps (every run flagged at step 1
    # only, where run 0 was attacked at every step)
    with pytest.raises(
        ValueError,
        match=r"_SharedTable.sample must return values \[\*batch, T, dim\] = \[4, 4, 1\]",
    ):
        _SharedTable().init((4,), 4, 1, dtype=torch.float64)


class _FlagsOfOneRun(TabulatedAttack):
    def sample(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        values = torch.ones(*batch_shape, num_steps, dim, dtype=dtype)
        return values, torch.ones(num_steps, dtype=torch.bool)


def test_flags_without_the_runs_are_refused_by_name():
    with pytest.raises(ValueError, match=r"flags \[\*batch, T\] = \[3, 6\]"):
        _FlagsOfOneRun().init((3,), 6, 2, dtype=torch.float32)


@pytest.mark.parametrize("channel", [Channel.SENSOR, Channel.REPLACEMENT])
def test_a_shared_value_with_per_run_flags_acts_on_the_flagged_runs(channel):
    # signal [2, 2], value [2] (one for every run), flag [2] per run (B = d): run 0 only
    signal = torch.tensor([[0.0, 0.0], [0.0, 0.0]])
    value = torch.tensor([1.0, 2.0])
    received, recorded = inject(channel, signal, value, torch.tensor([True, False]))
    expected = torch.tensor([[1.0, 2.0], [0.0, 0.0]])
    assert torch.equal(received, expected)
    assert torch.equal(recorded, expected)


def test_a_flag_per_entry_for_every_run_still_reads_per_entry():
    signal = torch.zeros(3, 2)
    received, _ = inject(
        Channel.SENSOR, signal, torch.tensor([1.0, 2.0]), torch.tensor([[True, False]])
    )
    assert torch.equal(received, torch.tensor([[1.0, 0.0]] * 3))


def test_a_boolean_tensor_is_not_an_arrival_rate():
    with pytest.raises(ValueError, match="not booleans"):
        df.ExpectedInputKalmanFilter(torch.tensor(True))


def _two_input_model():
    dt = torch.float64
    eye = torch.eye(2, dtype=dt)
    return df.LinearGaussianModel(
        torch.tensor([[0.98, 0.1], [0.0, 0.9]], dtype=dt), torch.tensor([[1.0, 0.0]], dtype=dt),
        1e-3 * eye, 1e-2 * torch.eye(1, dtype=dt), torch.zeros(2, dtype=dt), 0.1 * eye,
        B=torch.tensor([[0.0, 0.05], [0.3, 0.1]], dtype=dt),
    )  # fmt: skip


@pytest.mark.parametrize("rates", [(0.5,), (0.5, 0.5, 0.5)])
def test_the_rate_count_is_checked_on_a_kalman_filters_carry_too(rates):
    # init refused one rate for two inputs; a KF's carry (a documented use) had it broadcast
    # to both (one rate) or failed in torch (three)
    model = _two_input_model()
    est = df.ExpectedInputKalmanFilter(rates, independent=True)
    y, u = torch.zeros(2, 1, dtype=torch.float64), torch.ones(2, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match=f"holds {len(rates)} rates, and the model has 2"):
        est.step(df.KalmanFilter().init(model, (2,)), y, u)
