"""Findings of a red-team trial of long horizons: the χ² detector's window sums after one
large statistic, and the adaptive filters' attack covariance over a long outage. Each test
failed on the code before its fix."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter import LinearGaussianModel
from difffilter.fdi import ChiSquareDetector, adaptive_kalman_filter, adaptive_particle_filter
from difffilter.linalg import NumericalBreakdown


def _spiked(T: int = 600) -> torch.Tensor:
    g = torch.rand(T, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 4.0
    g[100] = 1e16  # one finite but huge statistic (a saturated sensor)
    return g


def _as_innovations(g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Innovations of one entry and unit variance whose NIS is ``g``."""
    return g.sqrt().unsqueeze(-1), torch.ones(g.shape + (1, 1), dtype=g.dtype)


def test_window_sums_after_one_huge_statistic_are_the_exact_sums():
    # a difference of running totals had been off by up to 4.2 on every later window
    g = _spiked()
    det = ChiSquareDetector(1, 0.01, window=5)
    scores, alarms = det.detect(*_as_innovations(g))
    exact = [math.fsum(g[max(0, k - 4) : k + 1].tolist()) for k in range(len(g))]
    later = slice(106, None)  # (windows without the spike)
    np.testing.assert_allclose(scores[later].numpy(), np.array(exact)[later], rtol=0, atol=1e-12)
    state, online = det.init(()), []
    for value in g:
        state, _, alarm = det.step(state, value)
        online.append(bool(alarm))
    assert alarms.tolist() == online


def test_ordinary_window_sums_keep_their_running_totals_bit_for_bit():
    # the direct sums are for totals whose round-off could matter: other runs' numbers stay
    g = torch.rand(3, 400, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 4.0
    from difffilter.fdi.detectors import _window_sums

    c = torch.cumsum(g, -1)
    want = c - torch.cat([torch.zeros(3, 5, dtype=torch.float64), c[..., :-5]], -1)
    assert torch.equal(_window_sums(g, 5), want)


def _outage_model(dtype):
    t = lambda a: torch.tensor(a, dtype=dtype)  # noqa: E731
    eye = np.eye(2)
    return LinearGaussianModel(t([[0.9, 0.1], [0.0, 0.8]]), t(eye), t(0.01 * eye), t(0.1 * eye),
                               t([0.0, 0.0]), t(eye), B=t(eye))  # fmt: skip


def _outage(dtype, T: int, gap: int):
    ys = 0.3 * torch.randn(1, T, 2, generator=torch.Generator().manual_seed(0), dtype=dtype)
    mask = torch.ones(1, T, 2, dtype=torch.bool)
    mask[:, 20 : 20 + gap] = False
    return ys, mask


def test_the_adaptive_kf_names_its_forgetting_after_a_long_outage():
    # S grows as S/λ per lost step: float32 had failed in torch's "matrix is singular"
    ys, mask = _outage(torch.float32, 300, 260)
    with pytest.raises(
        NumericalBreakdown, match="forgetting λ = 0.7 the attack covariance S grows"
    ):
        adaptive_kalman_filter(_outage_model(torch.float32), ys, mask=mask)
    # λ = 1 keeps S from growing: the same outage runs
    out = adaptive_kalman_filter(_outage_model(torch.float32), ys, mask=mask, forgetting=1.0)
    assert torch.isfinite(out.means).all()


def test_the_adaptive_pf_names_its_forgetting_after_a_long_outage():
    ys, mask = _outage(torch.float32, 300, 260)
    with pytest.raises(ValueError, match="forgetting λ = 0.7"):
        adaptive_particle_filter(_outage_model(torch.float32), ys, mask=mask, num_particles=10,
                                 generator=torch.Generator().manual_seed(0))  # fmt: skip
