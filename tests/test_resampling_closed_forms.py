"""The resamplers against dense closed forms: the inverse CDF of their very uniforms (with
zero weights before, inside and after the positive ones, a uniform of 0, a float32 target
past the total), the soft resampler's mixture ``q`` and its weights ``w / q``, residual
resampling's counts, the transport plan's marginals (a mutation review of the
particle-filter core: ``right=False`` in the searches, a clamp to ``N − 1`` instead of the
last particle of positive weight, the soft resampler drawing from ``w`` or counting dead
particles, all passed the suite)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter import _pf_host_step, _pf_single_run
from difffilter import resampling as rs

D = torch.float64


def _dense_inverse_cdf(w, u):
    """a_j = min{i : u_j * W < cdf_i}, never past the last positive weight (numpy, float64)."""
    w = np.asarray(w, dtype=np.float64)
    cdf = np.cumsum(w)
    last = int(np.nonzero(w > 0)[0].max())
    return np.array(
        [
            min(int(np.argmax(uj * cdf[-1] < cdf)) if (uj * cdf[-1] < cdf).any() else last, last)
            for uj in np.asarray(u)
        ]
    )


@pytest.mark.parametrize("seed", range(5))
def test_systematic_ancestors_are_the_inverse_cdf_of_j_plus_u_over_n(seed):
    g = torch.Generator().manual_seed(seed)
    n = 37
    w = torch.rand(n, generator=g, dtype=D) ** 3
    w[[3, 4, 20]] = 0.0
    for off in (0.0, 0.137, 0.5, 0.9999):
        offset = torch.tensor([off], dtype=D)
        got = rs.systematic_ancestors(torch.cumsum(w, -1), offset)
        want = _dense_inverse_cdf(w.numpy(), (np.arange(n) + off) / n)
        assert got.tolist() == want.tolist()
        # the batched path (scatter) as well
        got2 = rs.systematic_ancestors(
            torch.cumsum(w, -1).expand(2, n).contiguous(), offset.expand(2, 1)
        )
        assert got2[1].tolist() == want.tolist()
        # and the one-run torch step's / host step's inverse CDF, with U fixed
        got3 = rs._inverse_cdf(w, (torch.arange(n, dtype=D) + off) / n)
        assert got3.tolist() == want.tolist()


class _FixedRand:
    """``torch.rand`` that returns ``value`` everywhere (a fixed systematic offset)."""

    def __init__(self, value):
        self.value = value

    def __call__(self, *shape, generator=None, dtype=None, device=None):
        return torch.full(*shape if len(shape) == 1 else (shape,), self.value, dtype=dtype)


@pytest.mark.parametrize("off", [0.0, 0.25, 0.999])
def test_one_run_systematic_fast_paths_are_the_dense_inverse_cdf(monkeypatch, off):
    g = torch.Generator().manual_seed(1)
    n = 29
    w = torch.rand(n, generator=g, dtype=D) ** 2
    w[[0, 7, n - 1, n - 2]] = 0.0
    want = _dense_inverse_cdf(w.numpy(), (np.arange(n) + off) / n)
    monkeypatch.setattr(torch, "rand", _FixedRand(off))
    assert _pf_single_run._systematic_ancestors(w, None).tolist() == want.tolist()
    assert _pf_host_step._systematic_ancestors(w.numpy(), None).tolist() == want.tolist()
    assert rs.Systematic()._draw_from(w, None).tolist() == want.tolist()


def test_top_target_past_the_total_is_clamped_to_last_positive_weight(monkeypatch):
    # weights whose float32 cumsum rounds so that (N-1+U)/N * W lands at or past cdf[last positive]
    w = torch.tensor([0.3, 0.3, 0.4, 0.0, 0.0], dtype=torch.float32)
    off = float(np.nextafter(np.float32(1.0), np.float32(0.0)))
    cdf = torch.cumsum(w, 0)
    # dense: targets beyond the last positive entry must be mapped to index 2
    got = rs.systematic_ancestors(cdf, torch.tensor([off]))
    assert int(got.max()) <= 2
    got = rs._inverse_cdf(w, torch.tensor([0.99999994] * 5))
    assert int(got.max()) == 2
    monkeypatch.setattr(torch, "rand", _FixedRand(off))
    assert int(_pf_single_run._systematic_ancestors(w, None).max()) <= 2


@pytest.mark.parametrize("name", ["Multinomial", "Stratified", "Systematic"])
def test_inverse_cdf_schemes_draw_exactly_through_their_uniforms(name):
    """Against the dense inverse CDF of the very uniforms the scheme draws."""
    n = 23
    w = torch.rand(3, n, generator=torch.Generator().manual_seed(5), dtype=D) ** 2
    w[:, 5] = 0.0
    res = getattr(rs, name)()
    got = res._draw_from(w, torch.Generator().manual_seed(11))
    g = torch.Generator().manual_seed(11)
    if name == "Multinomial":
        u = torch.rand(w.shape, generator=g, dtype=D)
    elif name == "Stratified":
        u = (torch.arange(n, dtype=D) + torch.rand(w.shape, generator=g, dtype=D)) / n
    else:
        u = (torch.arange(n, dtype=D) + torch.rand((3, 1), generator=g, dtype=D)) / n
    for r in range(3):
        assert got[r].tolist() == _dense_inverse_cdf(w[r].numpy(), u[r].numpy()).tolist()


def test_soft_log_q_and_weights_closed_form():
    alpha = 0.3
    lw = torch.log_softmax(torch.tensor([[0.1, -2.0, 1.5, -math.inf, 0.4]], dtype=D), -1)
    s = rs.Soft(alpha)
    q = s._log_q(lw).exp()
    w = lw.exp()
    alive = torch.isfinite(lw)
    want = torch.where(alive, alpha * w + (1 - alpha) / alive.sum(), torch.zeros_like(w))
    torch.testing.assert_close(q, want)
    torch.testing.assert_close(q.sum(-1), torch.ones(1, dtype=D))
    anc = torch.tensor([[2, 2, 0, 4, 1]])
    nl = s._new_log_weights(lw, anc)
    ratio = (w / q)[0, anc[0]]
    torch.testing.assert_close(nl.exp()[0], ratio / ratio.sum())


def test_residual_counts_are_floor_n_w_plus_residual_draws():
    n = 10
    w = torch.tensor([0.33, 0.27, 0.15, 0.11, 0.08, 0.06, 0.0, 0.0, 0.0, 0.0], dtype=D)
    lw = torch.log(w)
    for seed in range(20):
        a = rs.Residual()._draw(lw, torch.Generator().manual_seed(seed))
        counts = torch.bincount(a, minlength=n)
        floor = torch.floor(n * w).long()
        assert bool((counts >= floor).all())
        assert int(counts.sum()) == n
        assert bool((counts[6:] == 0).all())
        # the residual mass R = N - Σ floor is spread over particles with a positive residual
        extra = counts - floor
        assert int(extra.sum()) == n - int(floor.sum())
        assert bool((extra[(n * w - floor) == 0] == 0).all())


def test_residual_extra_draws_only_where_the_residual_is_positive():
    n = 10
    w = torch.tensor([0.2, 0.3, 0.15, 0.35, 0, 0, 0, 0, 0, 0], dtype=D)
    n = 10
    lw = torch.log(w)
    # N w = [2, 3, 1.5, 3.5]: deterministic 2, 3, 1, 3; the R = 1 remaining slot goes to 2 or 3
    for seed in range(30):
        a = rs.Residual()._draw(lw, torch.Generator().manual_seed(seed))
        counts = torch.bincount(a, minlength=10)
        assert bool((counts[4:] == 0).all())
        assert counts[0] == 2 and counts[1] == 3, counts
        assert int(counts.sum()) == n


def test_effective_sample_size_of_unnormalised_log_weights():
    lw = torch.tensor([[0.3, -1.0, 2.0, 0.5]], dtype=D)
    w = torch.softmax(lw, -1)
    torch.testing.assert_close(rs.effective_sample_size(lw + 7.0), 1.0 / (w * w).sum(-1))


@pytest.mark.parametrize("method", ["kernel", "log"])
def test_transport_plan_marginals_and_projection(method):
    g = torch.Generator().manual_seed(2)
    x = torch.randn(12, 2, generator=g, dtype=D)
    lw = torch.log_softmax(torch.randn(12, generator=g, dtype=D), -1)
    ot = rs.OptimalTransport(epsilon=0.5, tolerance=1e-10, max_iterations=5000, method=method)
    P = ot.transport_matrix(x, lw)
    torch.testing.assert_close(P.sum(0), torch.full((12,), 1 / 12, dtype=D))
    torch.testing.assert_close(P.sum(1), lw.exp(), atol=1e-8, rtol=0)
    torch.testing.assert_close(ot(x, lw).particles, 12 * P.T @ x, atol=1e-8, rtol=0)


def test_a_zero_uniform_never_picks_a_leading_zero_weight_particle(monkeypatch):
    w = torch.tensor([0.0, 0.0, 0.5, 0.25, 0.25], dtype=D)
    u = torch.tensor([0.0, 0.2, 0.4, 0.6, 0.8], dtype=D)
    assert rs._inverse_cdf(w, u).tolist() == [2, 2, 2, 3, 4]
    assert rs.systematic_ancestors(torch.cumsum(w, 0), torch.zeros(1, dtype=D)).tolist() == [
        2,
        2,
        2,
        3,
        4,
    ]
    monkeypatch.setattr(torch, "rand", _FixedRand(0.0))
    assert _pf_single_run._systematic_ancestors(w, None).tolist() == [2, 2, 2, 3, 4]
    assert _pf_host_step._systematic_ancestors(w.numpy(), None).tolist() == [2, 2, 2, 3, 4]
    for name in ("Multinomial", "Stratified", "Systematic"):
        assert 0 not in getattr(rs, name)()._draw_from(w, None).tolist()


@pytest.mark.parametrize("alpha", [0.3, 0.7])
def test_soft_draws_from_the_mixture_q(alpha):
    """Soft's ancestors are the base scheme's inverse CDF of q = α w + (1 − α)/N at the
    very uniforms the base draws (dense check)."""
    n = 20
    lw = torch.log_softmax(
        3 * torch.randn(n, generator=torch.Generator().manual_seed(8), dtype=D), -1
    )
    got = rs.Soft(alpha, rs.Multinomial()).ancestors(lw, torch.Generator().manual_seed(9))
    u = torch.rand(n, generator=torch.Generator().manual_seed(9), dtype=D)
    q = alpha * lw.exp() + (1 - alpha) / n
    assert got.tolist() == _dense_inverse_cdf(q.numpy(), u.numpy()).tolist()
