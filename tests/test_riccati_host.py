"""The chunked covariance recursion on host arrays (:mod:`difffilter._riccati_host`)
against the torch recursion it stands in for (:mod:`difffilter.gain_schedule`): the same
maps, chunks and convergence step, and the torch recursion wherever the host cannot serve.
"""

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter import _riccati_host as host
from difffilter.gain_schedule import CovarianceChunks, riccati_chunk, riccati_steps

TOL = {torch.float64: dict(rtol=1e-12, atol=1e-13), torch.float32: dict(rtol=2e-4, atol=2e-5)}


def _matrices(seed: int, dx: int = 4, dy: int = 2, dtype=torch.float64, radius: float = 0.95):
    """``(F, H, Q, R, P0)`` of a random stable model with spectral radius ``radius``."""
    g = torch.Generator().manual_seed(seed)
    F = torch.randn(dx, dx, generator=g, dtype=torch.float64)
    F = F * radius / torch.linalg.eigvals(F).abs().max()
    H = torch.randn(dy, dx, generator=g, dtype=torch.float64)
    A = torch.randn(dx, dx, generator=g, dtype=torch.float64)
    Q = 0.1 * A @ A.T + 0.01 * torch.eye(dx, dtype=torch.float64)
    R = torch.diag(torch.rand(dy, generator=g, dtype=torch.float64) + 0.1)
    P0 = torch.eye(dx, dtype=torch.float64)
    return tuple(m.to(dtype) for m in (F, H, Q, R, P0))


def _torch_chunks(F, H, Q, R, P0, tol=1e-12) -> CovarianceChunks:
    chunks = CovarianceChunks(F, H, Q, R, P0, tol)
    chunks._host = None  # the torch recursion, as on another device
    return chunks


def _assert_close(actual, expected, dtype):
    for a, e in zip(actual, expected, strict=True):
        a = torch.from_numpy(np.ascontiguousarray(a)) if isinstance(a, np.ndarray) else a
        torch.testing.assert_close(a, e, **TOL[dtype])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_step_maps_equal_the_torch_doubling(seed, dtype):
    F, H, Q, R, P0 = _matrices(seed, dtype=dtype)
    expected = _torch_chunks(F, H, Q, R, P0)._step_maps()
    maps = host.host_step_maps(*host.host_arrays(F, H, Q, R), CovarianceChunks.BLOCK)
    assert all(m.shape == (16, 4, 4) and m.dtype == F.numpy().dtype for m in maps)
    _assert_close(maps, expected, dtype)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("blocks", [1, 3, 8])
def test_chunk_equals_riccati_chunk(blocks, dtype):
    F, H, Q, R, P0 = _matrices(3, dx=3, dy=2, dtype=dtype)
    torch_chunks = _torch_chunks(F, H, Q, R, P0)
    mats = torch_chunks._mats
    expected = riccati_chunk(P0, torch_chunks._step_maps(), blocks, *mats)
    arrays = host.host_arrays(F, H, Q, R)
    maps = host.host_step_maps(*arrays, CovarianceChunks.BLOCK)
    moments = host.host_chunk(P0.numpy(), maps, blocks, *arrays)
    assert [m.shape[0] for m in moments] == [16 * blocks] * 6
    _assert_close(moments, expected, dtype)
    # and the recursion itself, step by step (riccati_steps: no maps)
    _assert_close(moments, riccati_steps(P0, 16 * blocks, *mats), dtype)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize(("seed", "radius"), [(0, 0.5), (1, 0.95), (2, 0.999), (4, 1.02)])
def test_chunks_converge_at_the_torch_recursions_step(seed, radius, dtype):
    """The same chunks, the same first converged step (a slow mode and an unstable, observed
    one included: its filter converges) and the same moments as the torch recursion's."""
    F, H, Q, R, P0 = _matrices(seed, dtype=dtype, radius=radius)
    on_host, in_torch = CovarianceChunks(F, H, Q, R, P0, 1e-12), _torch_chunks(F, H, Q, R, P0)
    assert on_host._host is not None
    for _ in range(4):
        a, b = on_host.next(), in_torch.next()
        assert on_host.converged == in_torch.converged
        if dtype == torch.float64:
            assert on_host.steps == in_torch.steps
        else:  # float32: round-off 16 ε from the test's floor may move the step by one
            assert abs(on_host.steps - in_torch.steps) <= 1
        n = min(len(a[0]), len(b[0]))
        _assert_close([m[:n] for m in a], [m[:n] for m in b], dtype)
        if on_host.converged:
            break
    assert on_host._host is not None  # served by the host throughout
    assert on_host.converged


def test_an_unobserved_random_walk_never_converges_on_either():
    """A random walk no measurement reaches: its variance grows by q a step, every chunk is
    kept whole (the gain settles, the covariance does not), on the host as in torch."""
    F = torch.diag(torch.tensor([0.9, 1.0], dtype=torch.float64))
    H = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    Q, R = 0.1 * torch.eye(2, dtype=torch.float64), torch.eye(1, dtype=torch.float64)
    P0 = torch.eye(2, dtype=torch.float64)
    on_host, in_torch = CovarianceChunks(F, H, Q, R, P0, 1e-12), _torch_chunks(F, H, Q, R, P0)
    for _ in range(3):
        _assert_close(on_host.next(), in_torch.next(), torch.float64)
    assert on_host.steps == in_torch.steps == 16 + 112 + 128
    assert not on_host.converged and not in_torch.converged
    assert on_host._host is not None


def test_keep_is_the_first_steady_step():
    """The host convergence test on a constructed sequence: gains and covariances that stop
    moving at a known step."""
    n, dx, dy = 6, 2, 1
    K = np.ones((n, dx, dy))
    P = np.tile(np.eye(dx), (n, 1, 1))
    K[:3] += np.arange(3)[:, None, None]  # 1, 2, 3, then 1 from index 3 on
    F, H = 0.5 * np.eye(dx), np.ones((dy, dx))  # (I − K H) F: eigenvalues ±0.5, ρ² = 0.25
    # index 4 is the first equal to its predecessor: keep steps 0 … 4
    assert host.steps_to_keep(K, P, None, None, F, H, 1e-12) == 5
    # the previous chunk's last gain, different from the first: the same step
    assert host.steps_to_keep(K, P, 5 * K[0], P[0], F, H, 1e-12) == 5
    # ... and equal to it: the chunk's first step is steady
    assert host.steps_to_keep(K[3:], P[3:], K[3], P[3], F, H, 1e-12) == 1
    still = K + np.arange(n)[:, None, None]  # never steady
    assert host.steps_to_keep(still, P, None, None, F, H, 1e-12) is None


def test_singular_innovation_covariance_goes_to_the_torch_steps():
    """``H Q Hᵀ + R`` singular (a noiseless measurement of an undriven state): no maps on
    the host or in torch, the step-by-step torch recursion, whose ``S_k`` is definite
    through ``P⁻``."""
    F = torch.tensor([[0.9, 0.1], [0.0, 0.8]], dtype=torch.float64)
    H = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    Q, R = torch.diag(torch.tensor([0.0, 1.0], dtype=torch.float64)), torch.zeros(1, 1).double()
    P0 = torch.eye(2, dtype=torch.float64)
    assert host.host_step_maps(*host.host_arrays(F, H, Q, R), 16) is None
    chunks = CovarianceChunks(F, H, Q, R, P0, 1e-12)
    moments = chunks.next()
    assert chunks._host is None  # from then on, the torch recursion
    steps = riccati_steps(P0, 16, *chunks._mats)
    _assert_close(moments[:6], [m[: chunks.steps] for m in steps], torch.float64)


def test_a_chunk_the_host_cannot_factorise_is_the_torch_recursions(monkeypatch):
    """A chunk whose factorisation fails on the host: the torch recursion computes it
    (its jitter or its clear error decides) and every later chunk."""
    F, H, Q, R, P0 = _matrices(5)
    expected = _torch_chunks(F, H, Q, R, P0).next()
    monkeypatch.setattr("difffilter.gain_schedule.host_chunk", lambda *args: None, raising=True)
    chunks = CovarianceChunks(F, H, Q, R, P0, 1e-12)
    _assert_close(chunks.next(), expected, torch.float64)
    assert chunks._host is None


def test_host_arrays_are_views_of_cpu_float_tensors_only():
    a = torch.eye(3, dtype=torch.float64, requires_grad=True)
    (view,) = host.host_arrays(a)
    assert np.shares_memory(view, a.detach().numpy())
    assert host.host_arrays(a, torch.eye(3, dtype=torch.float16)) is None
    assert host.host_arrays(torch.eye(3, device="meta")) is None
    assert host.host_arrays(torch.eye(3, dtype=torch.int64)) is None
    with torch.inference_mode():
        inference = torch.eye(2)
    assert host.host_arrays(inference)[0].shape == (2, 2)


def test_gain_schedule_on_the_host_is_the_kalman_filter():
    """The public path end to end: the online filter's cold start (the host recursion)
    equal to the whole-sequence filter with gradients on (the step-by-step torch
    recursion) on a random model, 300 steps."""
    F, H, Q, R, P0 = _matrices(6)
    model = df.LinearGaussianModel(F, H, Q, R, torch.zeros(4, dtype=torch.float64), P0)
    with torch.no_grad():
        _, ys, _ = model.simulate(300, (), generator=torch.Generator().manual_seed(0))
    kf = df.KalmanFilter()
    carry, means, covs, lls = kf.init(model), [], [], []
    with torch.no_grad():
        for y in ys:
            carry, out = kf.step(carry, y)
            means.append(out.mean), covs.append(out.cov), lls.append(out.log_likelihood)
    assert carry.gains is not None and carry.gains._chunks._host is not None
    traced = df.LinearGaussianModel(F.clone().requires_grad_(), H, Q, R,
                                    torch.zeros(4, dtype=torch.float64), P0)  # fmt: skip
    reference = df.kalman_filter(traced, ys)
    torch.testing.assert_close(torch.stack(means), reference.means.detach(), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(torch.stack(covs), reference.covs.detach(), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(
        torch.stack(lls).sum(), reference.log_likelihood.detach(), rtol=1e-12, atol=1e-10
    )


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_host_chunk_tests_equal_the_torch_ones(dtype):
    """The finite and chain tests a host chunk passes on its arrays (one pass before they
    become tensors) cut where the torch tests cut: a chunk that holds, one broken by a step
    off the chain, one with an overflowed step."""
    F, H, Q, R, P0 = _matrices(4, dtype=dtype)
    chunks = CovarianceChunks(F, H, Q, R, P0, 1e-12)
    arrays = host.host_arrays(F, H, Q, R)
    maps = host.host_step_maps(*arrays, CovarianceChunks.BLOCK)
    pred, post = (m.copy() for m in host.host_chunk(P0.numpy(), maps, 2, *arrays)[:2])
    broken_pred = pred.copy()
    broken_pred[9, 1, 2] *= 1.1  # step 10 off the chain
    overflowed = post.copy()
    overflowed[5, 0, 0] = np.inf
    for p, c, n_finite, n_chained in [(pred, post, 32, 32), (broken_pred, post, 32, 9),
                                      (pred, overflowed, 5, 6)]:  # fmt: skip
        tp, tc = torch.from_numpy(p), torch.from_numpy(c)
        assert host.finite_steps(p, c) == chunks._finite_steps(tp, tc) == n_finite
        chained = host.chained_steps(
            p, c, arrays[0], arrays[2], CovarianceChunks.chain_tol(torch.float64)
        )
        assert chained == chunks._chained_steps(tp, tc) == n_chained
