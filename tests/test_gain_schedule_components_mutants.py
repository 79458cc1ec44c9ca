"""Mutation review of the shared gain schedule and the component-list algebra.

``difffilter.gain_schedule`` (the data-independent Kalman moments of an unbatched
time-invariant model, computed a chunk of 16-step blocks at a time through the doubled
parallel-in-time maps ``E(j)``) is checked against a plain numpy float64 Joseph-form
Riccati recursion written from its module docstring, step by step, across chunk and block
boundaries (T = 15, 16, 17, 33, 100), with ``dx != dy`` both ways, a square non-identity
``H``, a control input, and against central differences for the gradients of the per-run
step. ``difffilter.fdi._components`` (matrices as lists of per-entry tensors) is checked
against numpy's dense linear algebra on random symmetric positive-definite matrices.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter.fdi import _components as C
from difffilter.gain_schedule import GainSchedule

F64 = torch.float64


def _t(a, dtype=F64):
    return torch.as_tensor(np.asarray(a), dtype=dtype)


def _model(F, H, Q, R, P0, B=None, dtype=F64):
    dx = F.shape[0]
    return df.LinearGaussianModel(
        _t(F, dtype), _t(H, dtype), _t(Q, dtype), _t(R, dtype),
        torch.zeros(dx, dtype=dtype), _t(P0, dtype),
        B=None if B is None else _t(B, dtype),
    )  # fmt: skip


def _random_model(seed, dx, dy, du=1):
    g = np.random.default_rng(seed)
    F = 0.95 * np.eye(dx) + 0.15 * g.standard_normal((dx, dx))
    H = g.standard_normal((dy, dx))
    a, b, c = (g.standard_normal((d, d)) for d in (dy, dx, dx))
    R = 0.3 * a @ a.T + 0.2 * np.eye(dy)
    Q = 0.05 * b @ b.T + 0.02 * np.eye(dx)
    P0 = c @ c.T + 0.5 * np.eye(dx)  # not the identity: the first step is not special
    B = g.standard_normal((dx, du))
    return F, H, Q, R, P0, B


def _np_riccati(F, H, Q, R, P0, T):
    """The module docstring's recursion in numpy float64, Joseph form:
    ``[(P⁻_k, P_k, K_k, S_k)]`` for ``k = 1 … T``."""
    P, out, eye = P0, [], np.eye(F.shape[0])
    for _ in range(T):
        Pp = F @ P @ F.T + Q
        S = H @ Pp @ H.T + R
        K = Pp @ H.T @ np.linalg.inv(S)
        IKH = eye - K @ H
        P = IKH @ Pp @ IKH.T + K @ R @ K.T
        out.append((Pp, P, K, S))
    return out


def _close(a, b, rtol=1e-9, atol=1e-11):
    np.testing.assert_allclose(np.asarray(a.detach()), b, rtol=rtol, atol=atol)


@pytest.mark.parametrize("T", [15, 16, 17, 33, 100])
@pytest.mark.parametrize("dims", [(3, 2), (2, 3), (4, 1)])
def test_schedule_moments_equal_a_numpy_joseph_recursion(T, dims):
    """Every step's ``P⁻, P, K, S``, the Cholesky factor, the whitening ``L⁻¹`` and
    ``log_norm = Σ log diag L + (dy/2) log 2π`` equal a numpy float64 Joseph recursion
    (and ``np.linalg.cholesky``/``inv``) up to step ``T``: chunk and block boundaries of
    the doubled maps (16-step blocks), ``dx > dy`` and ``dx < dy``."""
    dx, dy = dims
    F, H, Q, R, P0, _ = _random_model(10 * dx + dy, dx, dy)
    schedule = GainSchedule(_model(F, H, Q, R, P0))
    truth = _np_riccati(F, H, Q, R, P0, T)
    for k, (Pp, P, K, S) in enumerate(truth, start=1):
        m = schedule.moments(k)
        _close(m.pred_cov, Pp)
        _close(m.cov, P)
        _close(m.gain, K)
        _close(m.innovation_cov, S)
        L = np.linalg.cholesky(S)
        _close(m.chol, L)
        _close(m.whiten, np.linalg.inv(L))
        log_norm = np.log(np.diag(L)).sum() + 0.5 * dy * math.log(2 * math.pi)
        _close(m.log_norm, log_norm)


def _np_filter(F, B, H, Q, R, P0, m0, ys, us):
    """Posterior means and ``log N(ν; 0, S)`` of a numpy Kalman filter with an input."""
    m, P, means, lls = m0, P0, [], []
    for y, u in zip(ys, us):
        pm, pP = F @ m + B @ u, F @ P @ F.T + Q
        S = H @ pP @ H.T + R
        K = pP @ H.T @ np.linalg.inv(S)
        nu = y - H @ pm
        m = pm + K @ nu
        P = (np.eye(len(m)) - K @ H) @ pP
        _, logdet = np.linalg.slogdet(S)
        lls.append(-0.5 * (nu @ np.linalg.solve(S, nu) + logdet + len(y) * math.log(2 * math.pi)))
        means.append(m)
    return np.array(means), np.array(lls)


@pytest.mark.parametrize("batch", [None, 3])
@pytest.mark.parametrize("square_h", [False, True])
def test_filter_step_predict_update_equal_a_numpy_filter_with_an_input(batch, square_h):
    """``filter_step`` (one run: matrix-vector products; a batch: row GEMMs) and
    ``predict``/``update`` give the posterior means and the evidence of a numpy Kalman
    filter with a control input over 40 steps (three chunks' worth of blocks), with
    ``dx != dy`` or a square ``H`` that is not the identity."""
    dx, dy = (3, 3) if square_h else (3, 2)
    F, H, Q, R, P0, B = _random_model(5, dx, dy, du=2)
    schedule = GainSchedule(_model(F, H, Q, R, P0, B))
    g = np.random.default_rng(11)
    T, n = 40, batch or 1
    ys, us = g.standard_normal((n, T, dy)), g.standard_normal((n, T, 2))
    m0s = g.standard_normal((n, dx))
    for i in range(n):
        means, lls = _np_filter(F, B, H, Q, R, P0, m0s[i], ys[i], us[i])
        if batch is None:
            mean = _t(m0s[i])
            for k in range(T):
                mean, pred, _, ll, _ = schedule.filter_step(mean, _t(ys[i, k]), _t(us[i, k]), k + 1)
                _close(mean, means[k])
                _close(ll, lls[k])
            mean = _t(m0s[i])
            for k in range(T):
                pred = schedule.predict(mean, _t(us[i, k]))
                mean, _, S = schedule.update(pred, _t(ys[i, k]), k + 1)
                _close(mean, means[k])
    if batch is not None:
        mean = _t(m0s)
        for k in range(T):
            mean, _, _, ll, _ = schedule.filter_step(mean, _t(ys[:, k]), _t(us[:, k]), k + 1)
            for i in range(n):
                means, lls = _np_filter(F, B, H, Q, R, P0, m0s[i], ys[i, : k + 1], us[i, : k + 1])
                _close(mean[i], means[k])
                _close(ll[i], lls[k])


def _slow_unmeasured_model():
    """A measured fast state and an unmeasured slow one (``ρ ≈ 0.999``): the gain settles at
    once, the second variance creeps towards ``q / (1 − a²)`` for thousands of steps."""
    F = np.diag([0.3, 0.999])
    H = np.array([[1.0, 0.0]])
    Q = np.diag([0.5, 1e-3])
    R = np.array([[0.2]])
    P0 = np.diag([1.0, 0.01])
    return F, H, Q, R, P0


@pytest.mark.parametrize("k", [200, 3000])
def test_a_slow_unmeasured_variance_is_followed_to_its_fixed_point(k):
    """The schedule's covariance at step ``k`` equals the numpy recursion there even though
    the gain converged at the first steps: the unmeasured variance (a scalar recursion,
    ``p_k = a² p_{k−1} + q``, closed form ``q/(1−a²) + a^{2k}(p_0 − q/(1−a²))``) must not be
    frozen when the gain stops moving, nor by a convergence test that ignores the slow
    contraction."""
    F, H, Q, R, P0 = _slow_unmeasured_model()
    schedule = GainSchedule(_model(F, H, Q, R, P0))
    a2, q, p0 = 0.999**2, 1e-3, 0.01
    closed = q / (1 - a2) + a2**k * (p0 - q / (1 - a2))
    P = schedule.moments(k).cov
    assert abs(float(P[1, 1]) - closed) <= 1e-8 * closed


def _np_vector_gain_model():
    """A random-walk-like model with a slowly contracting mode that IS measured: ``ρ`` of
    ``(I − K H) F`` is near 1, so a step's change of ``P`` understates what remains."""
    F = np.array([[0.9995, 0.01], [0.0, 0.98]])
    H = np.array([[1.0, 0.0]])
    Q = np.diag([1e-6, 1e-2])
    R = np.array([[50.0]])
    P0 = np.diag([10.0, 1.0])
    return F, H, Q, R, P0


def test_a_slowly_contracting_measured_mode_is_not_cut_early():
    """With a measured mode that contracts slowly, the covariance and gain at step 4000
    equal the numpy Joseph recursion to 1e-9 relative (a convergence test without the
    ``(1 − ρ²)/ρ²`` factor stops early and reuses moments still far from the fixed point)."""
    F, H, Q, R, P0 = _np_vector_gain_model()
    schedule = GainSchedule(_model(F, H, Q, R, P0))
    truth = _np_riccati(F, H, Q, R, P0, 4000)
    for k in (50, 500, 4000):
        _, P, K, _ = truth[k - 1]
        _close(schedule.moments(k).cov, P, rtol=1e-9, atol=0)
        _close(schedule.moments(k).gain, K, rtol=1e-9, atol=0)


def test_a_float32_schedule_converges_with_the_default_tolerance():
    """In float32 the default ``tol = 1e-12`` is raised to ``16 ε`` (class docstring): a
    well-damped model's schedule converges (every later step reuses the last moments) and
    its gain is the numpy float64 steady-state gain to float32 accuracy."""
    F, H, Q, R, P0, _ = _random_model(3, 2, 1)
    F = 0.5 * F / max(abs(np.linalg.eigvals(F)))
    schedule = GainSchedule(_model(F, H, Q, R, P0, dtype=torch.float32))
    m = schedule.moments(2000)
    assert schedule.converged
    K = _np_riccati(F, H, Q, R, P0, 200)[-1][2]
    _close(m.gain, K, rtol=1e-4, atol=1e-6)


def test_a_nan_tolerance_is_refused():
    """``tol`` must be a number ``>= 0``: NaN is not one."""
    F, H, Q, R, P0, _ = _random_model(1, 2, 1)
    with pytest.raises(ValueError, match="tol"):
        GainSchedule(_model(F, H, Q, R, P0), tol=float("nan"))


def test_the_fused_step_gradients_equal_central_differences():
    """The gradients of the posterior mean and the evidence of ``filter_step`` with respect
    to ``m``, ``y`` and ``u`` (one run and a batch of two) equal float64 central
    differences (``torch.autograd.gradcheck``)."""
    F, H, Q, R, P0, B = _random_model(8, 3, 2, du=2)
    schedule = GainSchedule(_model(F, H, Q, R, P0, B))
    g = torch.Generator().manual_seed(0)
    for shape in ((), (2,)):
        m = torch.randn(*shape, 3, generator=g, dtype=F64, requires_grad=True)
        y = torch.randn(*shape, 2, generator=g, dtype=F64, requires_grad=True)
        u = torch.randn(*shape, 2, generator=g, dtype=F64, requires_grad=True)

        def f(m, y, u):
            mean, pred, nu, ll, _ = schedule.filter_step(m, y, u, 5)
            return mean, pred, nu, ll

        assert torch.autograd.gradcheck(f, (m, y, u))


# ---------------------------------------------------------------- component lists


def _spd(seed, d, batch=(4,)):
    g = np.random.default_rng(seed)
    a = g.standard_normal((*batch, d, d))
    return a @ np.swapaxes(a, -1, -2) + 0.5 * np.eye(d)


def _dense(m, n=4):
    """A component matrix whose entries may be Python numbers → ``[n, d, e]`` numpy."""
    rows = [[torch.as_tensor(e, dtype=F64).expand(n) for e in row] for row in m]
    return C.from_components(rows).numpy()


def test_to_and_from_components_are_the_entry_layout():
    """``to_components`` of ``[..., d, e]`` gives ``c[i][j] = A[..., i, j]`` (a non-square
    matrix: a transposed layout would show) and ``from_components`` inverts it."""
    a = np.random.default_rng(0).standard_normal((5, 2, 3))
    c = C.to_components(_t(a))
    assert len(c) == 2 and len(c[0]) == 3
    for i in range(2):
        for j in range(3):
            np.testing.assert_array_equal(c[i][j].numpy(), a[:, i, j])
    np.testing.assert_array_equal(C.from_components(c).numpy(), a)


def test_lin_sums_coefficients_products_and_constants_without_touching_its_inputs():
    """``lin`` is ``Σ c·a·b`` with numbers and tensors mixed (several constant terms,
    coefficients ≠ 1 on products and single tensors), equal to the literal float64 sum, and
    never writes into an input tensor (autograd's saved tensors)."""
    g = np.random.default_rng(1)
    x, y, z = (g.standard_normal(4) for _ in range(3))
    tx, ty, tz = _t(x), _t(y), _t(z)
    keep = [t.clone() for t in (tx, ty, tz)]
    terms = [(2.0, 3.0, 0.5), (1.0, tx, 1.0), (-2.5, ty, tz), (0.7, tz, 1.0), (-1.0, 4.0, 1.0),
             (3.0, tx, ty), (0.0, tz, tz)]  # fmt: skip
    want = 3.0 + x - 2.5 * y * z + 0.7 * z - 4.0 + 3.0 * x * y
    np.testing.assert_allclose(C.lin(terms).numpy(), want, rtol=1e-14, atol=1e-14)
    # a first product with coefficient ≠ 1, then a constant only
    np.testing.assert_allclose(C.lin([(-2.0, tx, ty), (1.0, 2.0, 1.5)]).numpy(), -2 * x * y + 3.0)
    # a single tensor term then more: the input tensor is the first accumulator
    np.testing.assert_allclose(C.lin([(1.0, tx, 1.0), (1.0, ty, tz)]).numpy(), x + y * z)
    np.testing.assert_allclose(C.lin([(1.0, tx, 1.0), (1.0, 2.0, 1.0)]).numpy(), x + 2.0)
    assert C.lin([(2.0, 3.0, 1.0), (1.0, 1.0, 1.0)]) == 7.0
    for t, k in zip((tx, ty, tz), keep):
        assert torch.equal(t, k)


def test_mm_mv_add_and_the_upper_product_equal_numpy():
    """``mm`` (full and ``upper``: the diagonal and above kept), ``mv``, ``mt`` and ``add``
    with ``α ≠ 1`` equal numpy's products on a batch of random matrices."""
    g = np.random.default_rng(2)
    a, b, v = g.standard_normal((3, 2, 3)), g.standard_normal((3, 3, 2)), g.standard_normal((3, 3))
    ca, cb = C.to_components(_t(a)), C.to_components(_t(b))
    ab = a @ b
    np.testing.assert_allclose(C.from_components(C.mm(ca, cb)).numpy(), ab, rtol=1e-13)
    up = C.mm(ca, cb, upper=True)
    for i in range(2):
        for j in range(2):
            if j >= i:
                np.testing.assert_allclose(up[i][j].numpy(), ab[:, i, j], rtol=1e-13)
            else:
                assert up[i][j] is None
    av = C.mv(ca, list(_t(v).unbind(-1)))
    np.testing.assert_allclose(
        torch.stack(av, -1).numpy(), np.einsum("nij,nj->ni", a, v), rtol=1e-13
    )
    np.testing.assert_array_equal(C.from_components(C.mt(ca)).numpy(), np.swapaxes(a, 1, 2))
    bt = np.swapaxes(b, 1, 2)
    s = C.add(ca, C.to_components(_t(bt)), alpha=-0.3)
    np.testing.assert_allclose(C.from_components(s).numpy(), a - 0.3 * bt, rtol=1e-13)


def test_gram_with_number_and_masked_tensor_weights_equals_numpy():
    """``gram`` is ``base + Hᵀ diag(w) H`` (upper triangle) with numeric weights and with
    tensor weights ``[..., 1]`` that mask rows per batch element, against numpy."""
    g = np.random.default_rng(3)
    h, base = g.standard_normal((3, 2)), _spd(4, 2, batch=(5,))
    ch, cbase = C.to_components(_t(h)), C.to_components(_t(base))
    w = [0.5, 2.0, 1.5]
    masks = (g.random((5, 3)) > 0.4).astype(float) * np.array(w)
    cases = [(w, np.tile(w, (5, 1))), ([_t(masks[:, i]) for i in range(3)], masks)]
    for weights, wn in cases:
        out = C.gram([[e for e in row] for row in ch], weights, cbase)
        want = base + np.einsum("ij,ni,ik->njk", h, wn, h)
        for j in range(2):
            for m in range(j, 2):
                np.testing.assert_allclose(
                    np.broadcast_to(np.asarray(out[j][m]), (5,)), want[:, j, m], rtol=1e-13
                )


@pytest.mark.parametrize("d", [1, 2, 3, 4, 5])
def test_cholesky_inverses_and_log_determinants_equal_numpy(d):
    """``cholesky`` equals ``np.linalg.cholesky``; ``spd_inverse`` and ``sym_inverse`` (the
    adjugate for ``d ≤ 3``, Cholesky above) equal ``np.linalg.inv`` and ``slogdet``; the
    ``cofactors`` for ``d = 3`` are ``det · A⁻¹`` (and for ``d = 2`` the stored off-diagonal
    is ``a₀₁``, the cofactor's negative, as documented)."""
    a = _spd(10 + d, d)
    ca = C.to_components(_t(a))
    inv, logdet = np.linalg.inv(a), np.linalg.slogdet(a)[1]
    low = C.cholesky(ca)
    np.testing.assert_allclose(_dense(low), np.linalg.cholesky(a), rtol=1e-12, atol=1e-13)
    out, ld = C.spd_inverse(ca)
    np.testing.assert_allclose(_dense(out), inv, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(ld.numpy(), logdet, rtol=1e-12)
    out, ld = C.sym_inverse(ca, logdet=True)
    np.testing.assert_allclose(_dense(out), inv, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.broadcast_to(ld.numpy(), (4,)), logdet, rtol=1e-12)
    if d in (2, 3):
        cof, det = C.cofactors(ca)
        np.testing.assert_allclose(det.numpy(), np.linalg.det(a), rtol=1e-12)
        adj = inv * np.linalg.det(a)[:, None, None]
        for i in range(d):
            for j in range(i, d):
                sign = -1.0 if (d == 2 and i != j) else 1.0
                np.testing.assert_allclose(sign * np.asarray(cof[i][j]), adj[:, i, j], rtol=1e-10)


@pytest.mark.parametrize("d", [4, 2])
def test_a_constant_entry_keeps_the_matrixs_float64(d):
    """A review: a number entry (the docstring's constant matrices) whose square root or
    log is taken was made a float32 tensor, so a float64 matrix with a constant leading
    diagonal entry came out 1e-7 off numpy (d = 4: the Cholesky route); an all-constant
    ``d = 2`` matrix's log-determinant was float32. Both equal numpy to float64 round-off."""
    a = _spd(30 + d, d)[0]
    a[0, 0] = float(a[0, 0]) + 0.3  # still positive definite
    batch = np.broadcast_to(a, (2, d, d)).copy()
    ca = C.to_components(_t(batch))
    ca[0][0] = float(a[0, 0])  # a number, not a tensor
    out, ld = C.spd_inverse(ca)
    dense = C.from_components(
        [[torch.as_tensor(e, dtype=F64).expand(2) for e in row] for row in out]
    )
    np.testing.assert_allclose(dense.numpy(), np.linalg.inv(batch), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(ld.numpy(), np.linalg.slogdet(batch)[1], rtol=1e-13)
    const = [[float(a[i, j]) for j in range(d)] for i in range(d)]
    _, ld = C.sym_inverse(const, logdet=True)
    assert ld.dtype == torch.float64
    assert float(ld) == pytest.approx(np.linalg.slogdet(a)[1], rel=1e-14)


def test_cholesky_of_a_semidefinite_matrix_is_finite():
    """A positive-semidefinite (rank-one) input gives a finite factor: the diagonal is
    clamped at the dtype's smallest normal number before the square root (docstring)."""
    v = np.array([1.0, 2.0, -1.0])
    low = C.cholesky(C.to_components(_t(np.outer(v, v))[None]))
    assert all(bool(torch.isfinite(torch.as_tensor(e)).all()) for row in low for e in row)
    np.testing.assert_allclose(low[1][0].numpy(), [2.0])


def test_a_never_converging_recursion_comes_in_chunks_of_at_most_max_blocks():
    """An unmeasured random walk never converges (its variance grows as ``p₀ + k q``, the
    closed form checked at every step): ``CovarianceChunks.next`` hands it out in chunks of
    at most ``MAX_BLOCKS`` blocks of ``BLOCK`` steps (class docstring), never converged."""
    from difffilter.gain_schedule import CovarianceChunks

    F, H = np.eye(2), np.array([[1.0, 0.0]])
    Q, R, P0 = np.diag([0.1, 0.05]), np.array([[0.3]]), np.diag([1.0, 2.0])
    chunks = CovarianceChunks(_t(F), _t(H), _t(Q), _t(R), _t(P0), 1e-12)
    cap, k = CovarianceChunks.BLOCK * CovarianceChunks.MAX_BLOCKS, 0
    for _ in range(4):
        P = chunks.next()[1]
        assert 1 <= len(P) <= cap
        k += len(P)
        np.testing.assert_allclose(P[:, 1, 1].numpy(), 2.0 + 0.05 * np.arange(k - len(P) + 1, k + 1),
                                   rtol=1e-12)  # fmt: skip
    assert not chunks.converged and k > 2 * cap


def test_held_is_exactly_the_steps_whose_moments_can_be_read(monkeypatch):
    """In a schedule that never converges and drops its oldest steps (``KEEP = TRIM = 4``),
    ``held(k)`` is true exactly where ``moments(k)`` answers (a dropped step raises), at
    every ``k`` including the boundary ``k = dropped``; the held ones still equal the
    numpy recursion (an unmeasured random walk: ``P₁₁ = p₀ + k q``)."""
    monkeypatch.setattr(GainSchedule, "KEEP", 4)
    monkeypatch.setattr(GainSchedule, "TRIM", 4)
    F, H = np.eye(2), np.array([[1.0, 0.0]])
    Q, R, P0 = np.diag([0.1, 0.05]), np.array([[0.3]]), np.diag([1.0, 2.0])
    schedule = GainSchedule(_model(F, H, Q, R, P0))
    truth = _np_riccati(F, H, Q, R, P0, 40)
    _close(schedule.moments(40).cov, truth[39][1])
    assert not schedule.converged
    seen = []
    for k in range(1, 41):
        try:
            cov = schedule.moments(k).cov
        except ValueError:
            seen.append(False)
        else:
            seen.append(True)
            _close(cov, truth[k - 1][1])
            assert float(cov[1, 1]) == pytest.approx(2.0 + 0.05 * k, rel=1e-12)
        assert schedule.held(k) == seen[-1], k
    assert not seen[0] and seen[-1]


def test_the_tolerance_given_is_the_one_the_recursion_stops_at():
    """``tol`` is the schedule's: with ``tol = 1e-3`` the slow unmeasured variance
    (``ρ² = 0.998``, closed form ``q/(1 − a²)`` at the fixed point) is frozen once a step's
    change leaves at most about ``tol`` of it to go: converged within 9000 steps (the
    default 1e-12 needs about 17,000), within ``2 tol`` of the fixed point, and every later
    step reuses it."""
    F, H, Q, R, P0 = _slow_unmeasured_model()
    schedule = GainSchedule(_model(F, H, Q, R, P0), tol=1e-3)
    fixed = 1e-3 / (1 - 0.999**2)
    p = float(schedule.moments(9000).cov[1, 1])
    assert schedule.converged
    assert abs(p - fixed) <= 2e-3 * fixed
    assert float(schedule.moments(30000).cov[1, 1]) == p


def test_an_input_without_an_input_map_is_ignored():
    """A model without ``B``: ``predict(m, u)`` is ``F m`` (the input has nowhere to go),
    as is the one-run and the batched fused step's prediction."""
    F, H, Q, R, P0, _ = _random_model(6, 2, 1)
    schedule = GainSchedule(_model(F, H, Q, R, P0))
    m, u = np.array([0.3, -1.2]), np.array([5.0])
    _close(schedule.predict(_t(m), _t(u)), F @ m)
    _close(schedule.filter_step(_t(m), _t([0.1]), _t(u), 1)[1], F @ m)
    _close(schedule.filter_step(_t(m)[None], _t([[0.1]]), _t(u)[None], 1)[1][0], F @ m)


def test_a_prior_mean_with_a_batch_dimension_takes_no_schedule():
    """``shared_gains_apply`` is false for a prior mean with a batch dimension (its
    docstring: matrices and prior carry none), and ``GainSchedule`` refuses such a model."""
    from difffilter.gain_schedule import shared_gains_apply

    F, H, Q, R, P0, _ = _random_model(7, 2, 1)
    model = _model(F, H, Q, R, P0)
    assert shared_gains_apply(model)
    model.initial = type(model.initial)(torch.zeros(3, 2, dtype=F64), _t(P0))
    assert not shared_gains_apply(model)
    with pytest.raises(ValueError, match="batch dimension"):
        GainSchedule(model)
