"""The chunked covariance recursion of :class:`~difffilter.gain_schedule.CovarianceChunks`
on host arrays.

The recursion of an unbatched time-invariant model runs outside autograd (a
:class:`~difffilter.GainSchedule` holds plain tensors; the whole-sequence path computes it
this way only where nothing records a gradient), on ``[d, d]`` matrices and ``[n, d, d]``
batches of them with ``d`` a few units. A torch operation on such a matrix costs a few
microseconds of dispatch for a fraction of a microsecond of arithmetic, a numpy one about
one. Where the matrices live in CPU memory in float32 or float64 the same equations run
here, on numpy views of them (no copies), with the torch recursion's grouping of products:
the same numbers up to round-off (tests: 1e-12 in float64)::

    element   S = H Q Hᵀ + R,  K = Q Hᵀ S⁻¹,  A = (I − K H) F,
              C = (I − K H) Q (I − K H)ᵀ + K R Kᵀ,  J = (H F)ᵀ S⁻¹ H F
    doubling  E(i + m) = E(i) ⊗ E(m):  X = (I + C_i J_m)⁻¹,  A = A_m X A_i,
              C = A_m X C_i A_mᵀ + C_m,  J = (X A_i)ᵀ J_m A_i + J_i
    map       E(j)(P) = A_j (I + P J_j)⁻¹ P A_jᵀ + C_j
    step      P⁻ = F P Fᵀ + Q,  S = H P⁻ Hᵀ + R = L Lᵀ,  K = P⁻ Hᵀ L⁻ᵀ L⁻¹,
              P = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ          (each covariance symmetrised)

and the tests a chunk passes before it is handed out, on its arrays before they become
tensors (:meth:`~difffilter.gain_schedule.CovarianceChunks._checked_host`; in torch, on
``[n, d, d]`` batches, they took about 1.3 ms of the online cold start below, which is
1.05× faster so): finite
covariances (:func:`finite_steps`), one chain of the recursion (:func:`chained_steps`) and
the convergence test (:func:`steps_to_keep`), each that of
:class:`~difffilter.gain_schedule.CovarianceChunks` with the same tolerances.
On the benchmark's four-state model (``make bench``'s section 1c) the recursion to its
converged step, 123 steps in two chunks, takes 0.9 ms here against 1.8 ms in torch, and
the online filter's cold start (``init`` and 200 steps) gains about 15 %.

Whatever the host cannot factorise (an ``S`` not numerically positive definite, a singular
``I + P J``) returns ``None``: the torch recursion then computes that chunk, with its
jittered factorisation or its clear error, as before.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "chained_steps",
    "finite_steps",
    "host_arrays",
    "host_chunk",
    "host_step_maps",
    "steps_to_keep",
]

_HOST_DTYPES = (torch.float32, torch.float64)


def host_arrays(*mats: Tensor) -> tuple[np.ndarray, ...] | None:
    """Numpy views of ``mats`` (no copies; their values, without autograd) where every one
    lives in CPU memory in float32 or float64, else ``None`` (the torch recursion)."""
    views = []
    for m in mats:
        if m.device.type != "cpu" or m.dtype not in _HOST_DTYPES:
            return None
        try:
            views.append(m.detach().numpy())
        except (RuntimeError, TypeError):  # a tensor numpy cannot view (a traced one)
            return None
    return tuple(views)


def host_step_maps(F, H, Q, R, block: int) -> tuple[np.ndarray, ...] | None:
    """``(A, C, J)``, each ``[block, dx, dx]``: the ``j``-step maps ``E(1 … block)`` of one
    step's scan element, by doubling (module docstring), or ``None`` where ``H Q Hᵀ + R``
    or a doubling's ``I + C J`` cannot be factorised on the host."""
    eye = np.eye(F.shape[-1], dtype=F.dtype)
    try:
        cross = Q @ H.T
        s_inv = _inverse_of_factor(np.linalg.cholesky(_sym(H @ cross + R)))
        K = cross @ s_inv
        i_kh = eye - K @ H
        HF = H @ F
        maps = (
            (i_kh @ F)[None],
            _sym(i_kh @ Q @ i_kh.T + K @ R @ K.T)[None],
            _sym(HF.T @ (s_inv @ HF))[None],
        )
        while maps[0].shape[0] < block:  # E(i + m) = E(i) ⊗ E(m), i = 1 … m
            A_i, C_i, J_i = maps
            A_m, C_m, J_m = (m[-1] for m in maps)
            x_inv = np.linalg.inv(eye + C_i @ J_m)
            xa = x_inv @ A_i
            more = (A_m @ xa, _sym(A_m @ x_inv @ C_i @ A_m.T + C_m), _sym(_t(xa) @ J_m @ A_i + J_i))
            maps = tuple(np.concatenate(pair) for pair in zip(maps, more))
    except np.linalg.LinAlgError:
        return None
    return tuple(m[:block] for m in maps)


def host_chunk(cov, maps, blocks: int, F, H, Q, R) -> tuple[np.ndarray, ...] | None:
    """``n = blocks · m`` steps of the recursion from ``P_s`` (``cov [dx, dx]``) with the
    maps ``E(1 … m)`` of :func:`host_step_maps`: ``(P⁻, P, K, S, L, L⁻¹)``, each ``[n, ·,
    ·]``, as :func:`~difffilter.gain_schedule.riccati_chunk` returns them; ``None`` where a
    factorisation fails (module docstring)."""
    A, C, J = maps
    eye_x = np.eye(F.shape[-1], dtype=F.dtype)
    try:
        starts = [cov]
        for _ in range(blocks - 1):  # the blocks' first covariances, one map of m steps each
            starts.append(_apply_map(starts[-1], A[-1], C[-1], J[-1], eye_x))
        starts = np.stack(starts)[:, None]  # [blocks, 1, dx, dx]
        inner = _apply_map(starts, A[:-1], C[:-1], J[:-1], eye_x)
        previous = np.concatenate([starts, inner], 1).reshape(-1, *cov.shape)
        # one step from each: P⁻, S = L Lᵀ, K = P⁻ Hᵀ L⁻ᵀ L⁻¹ and the Joseph-form P
        pred_cov = _sym(F @ previous @ F.T + Q)
        cross = pred_cov @ H.T
        S = _sym(H @ cross + R)
        chol = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return None
    whiten = np.linalg.inv(chol)
    K = (cross @ _t(whiten)) @ whiten
    i_kh = eye_x - K @ H
    post = _sym((K @ R) @ _t(K) + i_kh @ pred_cov @ _t(i_kh))
    return pred_cov, post, K, S, chol, whiten


def finite_steps(*moments) -> int:
    """How many of a chunk's first steps have finite moments (``P⁻, P [n, dx, dx]``, and
    ``S``, ``L`` where given: an ``S`` overflowed beside a finite ``P⁻`` had been taken, the
    means 0.047 s off and the log-likelihood −inf at scale s; a trial), the test of
    :meth:`~difffilter.gain_schedule.CovarianceChunks._finite_steps` on host arrays; what
    to do with a first step that has none is the caller's."""
    n = moments[0].shape[0]
    ok = np.ones(n, dtype=bool)
    for m in moments:
        ok &= np.isfinite(m.reshape(n, -1)).all(1)
    return n if ok.all() else int(ok.argmin())


def chained_steps(pred_cov, cov, F, Q, chain_tol: float) -> int:
    """How many of a chunk's first steps form one chain of the recursion, ``P⁻_t = F
    P_{t−1} Fᵀ + Q`` per entry within ``chain_tol · √ε · √(P⁻ᵢᵢ P⁻ⱼⱼ)`` plus ``64 ε`` of the
    step's largest entry: the test of
    :meth:`~difffilter.gain_schedule.CovarianceChunks._chained_steps` on host arrays."""
    n = pred_cov.shape[0]
    if n < 2:
        return n
    again = F @ cov[:-1] @ F.T + Q
    pred = pred_cov[1:]
    root = np.sqrt(np.diagonal(pred, axis1=-2, axis2=-1).clip(min=0))
    eps = float(np.finfo(pred.dtype).eps)
    bound = (chain_tol * eps**0.5) * (root[:, :, None] * root[:, None, :])
    bound += 64 * eps * np.abs(pred).max(axis=(-2, -1), keepdims=True)
    broken = (np.abs(again - pred) > bound).reshape(n - 1, -1).any(1)
    return n if not broken.any() else int(broken.argmax()) + 1


def steps_to_keep(K, P, last_gain, last_cov, F, H, tol: float) -> int | None:
    """How many of a chunk's steps (gains ``K [n, dx, dy]``, covariances ``P [n, dx, dx]``;
    the previous chunk's last ``last_gain``, ``last_cov`` or ``None``) to keep: the index
    after the first step whose gain and covariance both converged, or ``None`` where none
    did (keep all). The test
    :meth:`~difffilter.gain_schedule.CovarianceChunks._steps_to_keep` states, for the host
    and the torch recursion alike."""
    n, dx = K.shape[0], P.shape[-1]
    gains, covs = K.reshape(n, -1), P.reshape(n, -1)
    if last_gain is not None:
        gains = np.concatenate([last_gain.reshape(1, -1), gains])
        covs = np.concatenate([last_cov.reshape(1, -1), covs])
    if gains.shape[0] < 2:  # one step and nothing before it (a chunk cut short): no test
        return None
    first = n + 1 - gains.shape[0]  # the chunk's first tested step
    gain_scale = np.abs(gains[:-1]).max(-1)
    gain_change = np.abs(gains[1:] - gains[:-1]).max(-1)
    var = np.diagonal(covs[:-1].reshape(-1, dx, dx), axis1=-2, axis2=-1).clip(min=0)
    cov_scale = np.sqrt(var[:, :, None] * var[:, None, :]).reshape(var.shape[0], -1)
    cov_change = np.abs(covs[1:] - covs[:-1])

    def first_steady(tol: float, window: int = 1) -> int | None:
        # the last step of the first `window` consecutive steady steps
        steady = (gain_change <= tol * gain_scale) & (cov_change <= tol * cov_scale).all(-1)
        if window > 1:
            runs = np.convolve(steady.astype(np.int64), np.ones(window, np.int64), "valid")
            hits = np.flatnonzero(runs == window) + window - 1
        else:
            hits = np.flatnonzero(steady)
        return int(hits[0]) if hits.size else None

    hit = first_steady(tol)
    if hit is None:
        return None
    gain = gains[hit + 1].reshape(dx, -1)
    closed = (np.eye(dx, dtype=F.dtype) - gain @ H) @ F
    rho2 = float(np.abs(np.linalg.eigvals(closed.astype(np.float64))).max()) ** 2
    if rho2 >= 1.0:  # not contracting: never settles
        return None
    if rho2 > 0.5:  # (1 − ρ²)/ρ² < 1: a stricter test
        strict = tol * (1.0 - rho2) / rho2
        # in float32 the stricter test asks for a change below the dtype's resolution: a
        # step's change is a few ulp or, rounded, exactly 0, and one such step had passed (a
        # schedule of a slow mode froze its gain 2.3e-5 off, 12× the tolerance: a
        # gain-schedule trial); there it must hold STEADY_WINDOW steps in a row. float64
        # is left as it was: its early stops measured within 1e-12 of the fixed point
        # (7e-16 for the benchmark's constant-velocity model), and later stops cost the
        # one-run cold start
        eps = float(np.finfo(K.dtype).eps)
        fine = eps > 1e-10 and strict < 16 * eps
        hit = first_steady(strict, STEADY_WINDOW if fine else 1)
        if hit is None:
            return None
    return first + hit + 1


#: Consecutive steps the stricter convergence test must hold where its tolerance is below the
#: dtype's resolution (:func:`steps_to_keep`).
STEADY_WINDOW = 16


def _apply_map(cov, A, C, J, eye_x):
    """``E(P) = A (I + P J)⁻¹ P Aᵀ + C``, symmetrised (broadcasting ``[..., d, d]``)."""
    lhs = eye_x + cov @ J
    rhs = cov if cov.shape == lhs.shape else np.broadcast_to(cov, lhs.shape)
    return _sym(A @ np.linalg.solve(lhs, rhs) @ _t(A) + C)


def _inverse_of_factor(chol: np.ndarray) -> np.ndarray:
    """``S⁻¹ = L⁻ᵀ L⁻¹`` from the Cholesky factor ``L`` of ``S``."""
    whiten = np.linalg.inv(chol)
    return whiten.T @ whiten


def _sym(a: np.ndarray) -> np.ndarray:
    """``(A + Aᵀ)/2`` over the last two axes (the product by ½ in place, as the torch
    recursion's)."""
    out = a + _t(a)
    out *= out.dtype.type(0.5)
    return out


def _t(a: np.ndarray) -> np.ndarray:
    return np.swapaxes(a, -1, -2)
