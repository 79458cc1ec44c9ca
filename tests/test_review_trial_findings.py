"""Findings of a review of this session's own changes: the staged names of an in-place
recalibration, and the χ² detector's choice of direct window sums. Each test failed on the
code before its fix (the commit it reviews)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def test_a_long_out_name_keeps_its_checkpoint_and_card_apart(tmp_path):
    # both staged names had been cut to 64 characters alike: the card was written over the
    # checkpoint, and --out SRC --force destroyed the source
    import difffilter.train.calibrate as calibrate
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    src = tmp_path / ("c" * 70 + ".ckpt")
    shutil.copy(ROOT / "checkpoints" / "four_tank_nn_grad.ckpt", src)
    shutil.copy(ROOT / "checkpoints" / "four_tank_nn_grad.json", src.with_suffix(".json"))
    assert calibrate._staged_name(src) != calibrate._staged_name(src.with_suffix(".json"))
    estimator, card = load_estimator_checkpoint(src, dtype=None, expected_sha256=None)
    document = json.loads(src.with_suffix(".json").read_text())
    calibrate._write_pair(src, estimator, card, document, {"threshold": 0.5}, None)
    assert src.read_bytes()[:2] == b"PK"  # (a zip archive: torch's, not the JSON card)
    load_estimator_checkpoint(src)  # (verified against the card beside it)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [src.name, src.with_suffix(".json").name]
    )


def test_a_runs_window_sums_do_not_hang_on_its_batch():
    # the direct sums had been chosen on the whole batch's largest total: a run's scores
    # differed by 1.4e-9 with another run beside it
    from difffilter.fdi.detectors import _window_sums

    g = torch.rand(3000, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 2000.0
    other = torch.zeros(3000, dtype=torch.float64)
    other[10] = 1e7
    alone = _window_sums(g, 5)
    batched = _window_sums(torch.stack([g, other]), 5)[0]
    assert torch.equal(alone, batched)
    exact = torch.tensor(
        [float(sum(g[max(0, k - 4) : k + 1].tolist())) for k in range(3000)], dtype=torch.float64
    )
    assert (alone - exact).abs().max() < 1e-9


def test_a_computed_time_varying_matrix_is_checked_at_its_read():
    # a second review: the table memo had left matrices computed afresh unchecked (a NaN B_5
    # ran to NaN means again)
    import pytest

    import difffilter as df

    D = torch.float64

    class Computed(df.LinearGaussianModel):
        time_varying = True

        def control_matrix(self, k):
            return self.B * (float("nan") if k == 5 else 1.0)

    eye = torch.eye(2, dtype=D)
    model = Computed(0.9 * eye, eye, 0.1 * eye, 0.2 * eye, torch.zeros(2, dtype=D), eye, B=eye)
    with pytest.raises(ValueError, match=r"Computed.control_matrix\(5\) contains NaN"):
        df.kalman_filter(model, torch.zeros(2, 8, 2, dtype=D), torch.ones(2, 8, 2, dtype=D))


def test_a_copied_models_table_written_nan_is_still_caught():
    # the memo (version stamps) came along with a deepcopy, whose tables start their versions
    # again: a table written NaN after the copy matched the old stamp
    import copy

    import pytest

    import difffilter as df

    D = torch.float64

    class Table(df.LinearGaussianModel):
        time_varying = True

        def __init__(self):
            eye = torch.eye(2, dtype=D)
            super().__init__(0.9 * eye, eye, 0.1 * eye, 0.2 * eye, torch.zeros(2, dtype=D), eye)
            self.register_buffer("Fs", (0.9 * eye).expand(10, 2, 2).clone())

        def transition_matrix(self, k):
            return self.Fs[k]

    model = Table()
    with torch.no_grad():
        model.Fs.mul_(1.0)  # (version 1)
    ys = torch.zeros(2, 6, 2, dtype=D)
    df.kalman_filter(model, ys)  # (checked and remembered at version 1)
    with torch.no_grad():
        model.Fs[3, 0, 0] = float("nan")  # (version 2)
    copied = copy.deepcopy(model)  # (its table's version starts again: 1, the memo's)
    with pytest.raises(ValueError, match=r"Table.transition_matrix\(3\) contains NaN"):
        df.kalman_filter(copied, ys)


def test_an_overflowed_chi_square_window_is_a_valid_gated_state():
    # the new state check had refused the +inf the χ² step keeps for an overflowed statistic
    import difffilter as df
    from difffilter.fdi import ChiSquareDetector, GatedFilter

    D = torch.float64
    eye = torch.eye(2, dtype=D)
    model = df.LinearGaussianModel(
        0.9 * eye, eye, 0.1 * eye, 0.2 * eye, torch.zeros(2, dtype=D), eye
    )
    gated = GatedFilter(ChiSquareDetector(2, 0.01, window=3), df.KalmanFilter())
    gated.full_checks = True
    carry = gated.init(model, ())
    carry, out = gated.step(carry, torch.tensor([1e200, 0.0], dtype=D))
    assert bool(out.alarm)
    carry, out = gated.step(carry, torch.zeros(2, dtype=D))
    assert bool(out.alarm)  # (the overflowed value still in the window)


def test_both_held_signals_are_delivered():
    # a SIGINT held first had raised KeyboardInterrupt before a held SIGTERM was delivered
    import os
    import signal

    import pytest

    from difffilter.interrupts import Terminated, signals_deferred, sigterm_as_interrupt

    with sigterm_as_interrupt():
        with pytest.raises(Terminated):
            with signals_deferred():
                os.kill(os.getpid(), signal.SIGINT)
                os.kill(os.getpid(), signal.SIGTERM)


def test_a_staged_name_stays_within_the_name_limit_in_bytes():
    from difffilter.train.calibrate import _staged_name

    path = Path("/tmp") / ("\N{GRINNING FACE}" * 62 + ".ckpt")  # 253 bytes
    assert len(_staged_name(path).name.encode()) <= 255


def test_a_held_sigterm_is_delivered_where_the_block_raised():
    # (a third review: an OSError in the block had dropped a held SIGTERM)
    import os
    import signal

    import pytest

    from difffilter.interrupts import Terminated, signals_deferred, sigterm_as_interrupt

    with sigterm_as_interrupt():
        with pytest.raises(Terminated) as caught:
            with signals_deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                raise OSError("a rename failed")
    assert isinstance(caught.value.__context__, OSError)
