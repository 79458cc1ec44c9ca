"""Kalman filter for many runs of one linear time-invariant model (shared covariances).

When the model's matrices ``F, H, Q, R, P_0`` (and ``B``) carry no batch dimension and
no entry is masked, the covariance recursion

    P⁻_t = F P_{t−1} Fᵀ + Q,   S_t = H P⁻_t Hᵀ + R,   K_t = P⁻_t Hᵀ S_t⁻¹,
    P_t  = (I − K_t H) P⁻_t (I − K_t H)ᵀ + K_t R K_tᵀ

does not depend on the measurements: it runs once, on ``[dx, dx]`` matrices (the
chunked recursion of :class:`difffilter.GainSchedule`, until the gain converges),
equal to :func:`difffilter.kalman.kalman_step`'s up to round-off. The covariances are returned
as expanded views ``[..., T, dx, dx]`` of one ``[T, dx, dx]`` tensor (no ``B`` copies).

What remains per run is linear in the data. Over a block of ``L`` steps starting after
``m_{s−1}``, with ``X = [m_{s−1}; y_s … y_{s+L−1}; u_s … u_{s+L−1}]``::

    m⁻_t = F m_{t−1} + B u_t,   r_t = y_t − H m⁻_t,   m_t = m⁻_t + K_t r_t,   z_t = L_t⁻¹ r_t

are all ``W X`` for one matrix ``W`` per block (built from the ``K_t``, ``L_t``
by running the recursion on coefficient matrices, batched over blocks), so each block
is one GEMM over all runs: ``[B, dx + (dy + du) L] × [·, (2 dx + 2 dy) L]``. The
log-likelihood increments are ``−½‖z_t‖² − Σ log diag L_t − (dy/2) log 2π``. The
results equal the step-by-step filter up to round-off (tests check 1e-10) on
well-conditioned models; the coefficients of ``W`` are formed ahead, and on a strongly
non-normal ``F`` their cancellation loses the means, which :func:`_means_hold` checks
(the filter then returns ``None`` and its caller steps through the sequence).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.nn.functional import pad as F_pad

from .gain_schedule import CovarianceChunks, half_log_det, riccati_steps
from .linalg import LOG_2PI
from .parallel_kalman import consistency_tolerance, scaled_gap
from .results import FilterResult

__all__ = ["shared_covariance_applies", "shared_covariance_kalman_filter"]

# Steps per GEMM block and runs per chunk (no-gradient path): the GEMM's cost per
# run-step grows with L (the block matrix is lower block-triangular but stored dense),
# the number of kernel launches falls with L and the chunk size; a chunk's block output
# should fit in cache. Measured on the 2-core CPU (CV model, T = 200, B = 1e5, best of
# 6): (L, chunk) = (8, 4096), (4, 4096), (4, 16384), (16, 2048) all gave 3.6e7–4.8e7
# run-steps/s (within the machine's noise); all runs at once with L = 4 gave 2.1e7.
BLOCK = 8
RUN_CHUNK = 4096
#: The covariance recursion without gradients stops where the gain changes by at most
#: this much, relative (0: down to round-off, CovarianceChunks' floor of 16 ε).
GAIN_TOL = 0.0


def shared_covariance_applies(model, mask: Tensor | None) -> bool:
    """Whether :func:`shared_covariance_kalman_filter` serves ``model`` (see module docstring)."""
    if mask is not None or getattr(model, "time_varying", False):
        return False
    needed = ("transition_matrix", "observation_matrix", "control_matrix")
    if not all(hasattr(model, name) for name in needed):
        return False
    mats = [
        model.transition_matrix(0),
        model.observation_matrix(1),
        model.process_cov(0),
        model.measurement_cov(1),
        model.initial.cov,
    ]
    B = model.control_matrix(0)
    if B is not None:
        mats.append(B)
    return all(isinstance(m, Tensor) and m.dim() == 2 for m in mats)


def _covariances(F, H, Q, R, P, T):
    """The data-independent recursion, ``T`` steps stacked: ``P⁻, P, S, K, L⁻¹`` (``[T, ·,
    ·]`` each) and the ``[T]`` half log-determinants of ``S``.

    Without gradients it runs a chunk of steps at a time
    (:class:`~difffilter.gain_schedule.CovarianceChunks`, what the online
    :class:`~difffilter.GainSchedule` runs) until the gain and every entry of the
    covariance change by round-off alone (16 ε relative, :data:`GAIN_TOL`; each entry of P
    against its own correlation scale, and tighter for a slowly contracting recursion:
    :meth:`~difffilter.gain_schedule.CovarianceChunks._steps_to_keep`), and the later steps
    repeat its moments: the step by step
    recursion's numbers up to round-off (2e-14 relative on the benchmark's
    constant-velocity model, about 150 of its 200 steps computed, 11 more than before the
    per-entry test of 2026-11-30; tests: 1e-12), in about 150
    operations on batches instead of 25 a step. With gradients (or on the meta device)
    every step is computed, one at a time (:func:`~difffilter.gain_schedule.riccati_step`,
    the Gaussian core's blocks written out).
    """
    grad = torch.is_grad_enabled() and any(t.requires_grad for t in (F, H, Q, R, P))
    if not grad and F.device.type != "meta":
        chunks = CovarianceChunks(F, H, Q, R, P, tol=GAIN_TOL)
        parts = []
        while chunks.steps < T and not chunks.converged:
            parts.append(chunks.next())
        stacked = [torch.cat(field)[:T] for field in zip(*parts)]
        if chunks.steps < T:  # converged: the remaining steps are the last one
            more = T - chunks.steps
            stacked = [torch.cat([m, m[-1:].expand((more, *m.shape[1:]))]) for m in stacked]
        pred, covs, gains, inn, _, whiten, half_logdet = stacked
        return pred, covs, inn, gains, whiten, half_logdet
    eye_x = torch.eye(F.shape[-1], dtype=F.dtype, device=F.device)
    eye_y = torch.eye(H.shape[-2], dtype=F.dtype, device=F.device)
    Ft, Ht = F.transpose(0, 1), H.transpose(0, 1)
    pred, covs, gains, inn, chols, whiten = riccati_steps(P, T, F, Ft, H, Ht, Q, R, eye_x, eye_y)
    return pred, covs, inn, gains, whiten, half_log_det(chols)


def _block_maps(F, H, Bm, gains, whiten, L, du):
    """``W [nb, (2dx + 2dy) L, dx + (dy + du) L]`` for every block (module docstring).

    Rows: ``m_{s..s+L−1}`` (dx each), ``m⁻`` (dx each), ``r`` (dy each), ``z`` (dy each);
    columns: ``m_{s−1}``, ``y_s … y_{s+L−1}``, ``u_s … u_{s+L−1}``. ``gains``/``whiten``
    are padded to ``nb·L`` steps.
    """
    T_pad, dx, dy = gains.shape[0], F.shape[-1], H.shape[-2]
    nb = T_pad // L
    nX = dx + (dy + du) * L
    K = gains.view(nb, L, dx, dy)
    Z = whiten.view(nb, L, dy, dy)
    Mm = torch.zeros(nb, dx, nX, dtype=F.dtype, device=F.device)
    Mm[:, :, :dx] = torch.eye(dx, dtype=F.dtype, device=F.device)
    eye_y = torch.eye(dy, dtype=F.dtype, device=F.device)
    means, preds, res, zs = [], [], [], []
    for j in range(L):
        Mp = F @ Mm
        if du:
            col = dx + dy * L + du * j
            Mp = Mp + torch.nn.functional.pad(Bm, (col, nX - col - du))
        col = dx + dy * j
        Mr = torch.nn.functional.pad(eye_y, (col, nX - col - dy)) - H @ Mp
        Mm = Mp + K[:, j] @ Mr
        means.append(Mm)
        preds.append(Mp)
        res.append(Mr)
        zs.append(Z[:, j] @ Mr)
    return torch.cat(means + preds + res + zs, dim=-2)


def _blocks_autograd(W, m_prev, Y, U, L, dims):
    """All runs at once, blocks concatenated (differentiable). Returns ``m, m⁻, r`` as
    ``[n, T·d]`` and ``‖z‖² [n, T]``."""
    dx, dy, du = dims
    n, T = Y.shape[0], Y.shape[1] // dy
    parts = []
    # the blocks, data and inputs split once: each W[b] or Y[:, s:e] alone had sent back a
    # zero-filled gradient the size of all of it (O(T²) in the backward pass: 317 s at
    # T = 100,000 for a gradient in Q, 30 s split; the same for one in the data)
    blocks = W.unbind(0)
    data = Y.split(L * dy, dim=1)
    inputs = None if U is None else U.split(L * du, dim=1)
    for b, Wb in enumerate(blocks):
        Lb = min(L, T - b * L)
        X = [m_prev, F_pad(data[b], (0, (L - Lb) * dy))]
        if inputs is not None:
            X.append(F_pad(inputs[b], (0, (L - Lb) * du)))
        out = torch.cat(X, dim=-1) @ Wb.transpose(0, 1)
        parts.append([out[:, row : row + Lb * w] for row, w in _row_groups(L, dx, dy)])
        m_prev = parts[-1][0][:, -dx:]
    means, pred, inn, z = (torch.cat(group, dim=1) for group in zip(*parts))
    return means, pred, inn, z.square().view(n, T, dy).sum(-1)


def _blocks_in_place(W, m_prev, Y, U, L, dims):
    """Same as :func:`_blocks_autograd` without gradients, faster at large ``n``.

    Runs go through in chunks of :data:`RUN_CHUNK` so that one block's GEMM output
    ``[chunk, (2dx + 2dy) L]`` stays in cache while it is copied into the outputs; over
    all runs at once it went to memory and back (1.5× slower at ``n = 1e5``).
    """
    dx, dy, du = dims
    n, T = Y.shape[0], Y.shape[1] // dy
    means, pred, inn = (Y.new_empty(n, T * d) for d in (dx, dx, dy))
    quad = Y.new_empty(n, T)
    Wt = W.transpose(1, 2).contiguous()  # [nb, nX, rows]: the GEMM's right operand
    groups = _row_groups(L, dx, dy)
    eye = torch.eye(L, dtype=Y.dtype, device=Y.device)
    summing = eye.repeat_interleave(dy, dim=0)  # [L dy, L]: sums each step's dy squares
    for c0 in range(0, n, RUN_CHUNK):
        rows = slice(c0, min(n, c0 + RUN_CHUNK))
        c = rows.stop - c0
        X = Y.new_zeros(c, W.shape[-1])  # [m_{s−1} | y_s … | u_s …], zero past T
        X[:, :dx] = m_prev[rows]
        out = Y.new_empty(c, W.shape[-2])
        for b in range(W.shape[0]):
            s, Lb = b * L, min(L, T - b * L)
            X[:, dx : dx + Lb * dy] = Y[rows, s * dy : (s + Lb) * dy]
            X[:, dx + Lb * dy : dx + L * dy] = 0
            if U is not None:
                X[:, dx + L * dy : dx + L * dy + Lb * du] = U[rows, s * du : (s + Lb) * du]
                X[:, dx + L * dy + Lb * du :] = 0
            torch.mm(X, Wt[b], out=out)
            for target, (row, w) in zip((means, pred, inn), groups):
                target[rows, s * w : (s + Lb) * w] = out[:, row : row + Lb * w]
            row = groups[3][0]
            z2 = out[:, row : row + Lb * dy].square_()
            # ‖z_t‖² by a GEMM with the block-summing matrix: a sum over the last
            # dimension of [chunk, L, dy] was the slowest op of the loop (dy = 2)
            quad[rows, s : s + Lb] = z2 @ summing[: Lb * dy, :Lb]
            X[:, :dx] = out[:, (Lb - 1) * dx : Lb * dx]
    return means, pred, inn, quad


#: How many runs :func:`_means_hold` checks: those of the largest data (the blocks'
#: round-off grows with the data's magnitude, in the shared covariances' units); all of
#: them had cost 1.7 times the filter at 1,000 and 100,000 runs.
CHECKED_RUNS = 32


def _means_hold(means, m_prev, Y, U, F, H, Bm, gains, covs, dims) -> bool:
    """Whether each step's filtered mean is one Kalman update of the step before,

        m̃_t = m⁻_t + K_t (y_t − H m⁻_t),   m⁻_t = F m_{t−1} + B u_t,

    within :data:`~difffilter.parallel_kalman.CONSISTENCY_TOLERANCE` posterior standard
    deviations (``√P_t,ii``), on the runs whose data (``y``, ``u``, ``m_0``) reach the
    largest magnitudes, entry by entry (:func:`_runs_to_check`). The blocks' ``W X`` sums coefficients such as
    ``F − K H F`` formed ahead: on a strongly non-normal ``F`` (‖F‖ up to 1e4, spectral
    radius below 1) their cancellation left the means 1e4 to 4e7 sd from a 40-digit
    filter, where the step-by-step filter (prediction, residual, update in turn) stayed
    within 3 sd. On well-conditioned models the gap is round-off (below 1e-9 sd in float64,
    1e-3 in float32). ``means`` ``[n, T·dx]``, ``m_prev`` ``[n, dx]``, ``Y`` ``[n, T·dy]``,
    ``U`` ``[n, T·du]`` or ``None``, ``gains`` ``[T, dx, dy]``, ``covs`` ``[T, dx, dx]``."""
    dx, dy, du = dims
    if means.device.type == "meta":
        return True
    n, T = Y.shape[0], Y.shape[1] // dy
    with torch.no_grad():
        rows = _runs_to_check(Y, U, m_prev, dims) if n > CHECKED_RUNS else slice(None)
        m = means[rows].view(-1, T, dx)
        prev = torch.cat([m_prev[rows].unsqueeze(1), m[:, :-1]], dim=1)
        pred = prev @ F.mT
        if U is not None and Bm is not None:
            pred = pred + U[rows].view(-1, T, du) @ Bm.mT
        res = Y[rows].view(-1, T, dy) - pred @ H.mT
        again = pred + torch.einsum("tij,ctj->cti", gains, res)
        scale = covs.diagonal(dim1=-2, dim2=-1).clamp_min(0.0).sqrt()  # [T, dx]
        gap = scaled_gap(again - m, scale + torch.finfo(m.dtype).tiny)
        return not bool(gap.max() > consistency_tolerance(m.dtype))


def _runs_to_check(Y: Tensor, U: Tensor | None, m_prev: Tensor, dims) -> Tensor:
    """The runs :func:`_means_hold` checks: for each entry of ``y``, ``u`` and ``m_0`` on
    its own, the :data:`CHECKED_RUNS` runs where it reaches its largest magnitude (at most
    ``CHECKED_RUNS·(dy + du + dx)`` runs). Each entry on its own, in its own units: ranked
    by the largest of all entries, runs of large inputs through a small ``B`` had crowded
    out a run whose measurements broke the blocks (0.47 posterior sd and 8.7 nats off,
    unchecked; a red-team trial)."""
    dx, dy, du = dims
    n = Y.shape[0]
    sizes = [_largest(Y.view(n, -1, dy)), _largest(m_prev.view(n, 1, dx))]
    if U is not None:
        sizes.append(_largest(U.view(n, -1, du)))
    top = torch.cat(sizes, dim=1).topk(CHECKED_RUNS, dim=0).indices  # [CHECKED_RUNS, entries]
    return top.flatten().unique()


def _largest(rows: Tensor) -> Tensor:
    """``max_t |rows_itj|`` ``[n, d]`` of ``[n, T, d]`` without an ``|rows|`` copy (half the
    time of ``abs().amax``: 150 against 315 ms at 100,000 × 400)."""
    low, high = torch.aminmax(rows, dim=1)
    return torch.maximum(high, low.neg())


def _row_groups(L, dx, dy):
    """(first row, width per step) of ``m``, ``m⁻``, ``r``, ``z`` in a block map ``W``."""
    return ((0, dx), (L * dx, dx), (2 * L * dx, dy), (2 * L * dx + L * dy, dy))


def shared_covariance_kalman_filter(
    model, ys: Tensor, us: Tensor | None = None
) -> FilterResult | None:
    """Kalman filter of ``ys [..., T, dy]`` (validated, no mask) for a shared LTI model,
    or ``None`` where its means fail :func:`_means_hold` (the caller then filters step by
    step).

    Same result as ``run_gaussian_filter(kalman_step, model, ys, us)`` up to round-off;
    see the module docstring for the method. Differentiable (with gradients enabled and
    an input that requires them, the blocks are concatenated instead of copied into
    preallocated outputs).
    """
    F, H = model.transition_matrix(0), model.observation_matrix(1)
    Q, R = model.process_cov(0), model.measurement_cov(1)
    Bm = model.control_matrix(0) if us is not None else None
    m0, P0 = model.initial.mean, model.initial.cov
    dx, dy = F.shape[-1], H.shape[-2]
    du = 0 if us is None else us.shape[-1]
    T = ys.shape[-2]
    batch = ys.shape[:-2]
    if us is not None:
        batch = torch.broadcast_shapes(batch, us.shape[:-2])
    batch = torch.broadcast_shapes(batch, m0.shape[:-1])
    n = math.prod(batch)
    dtype = ys.dtype

    pred_covs, covs, inn_covs, gains, whiten, half_logdet = _covariances(F, H, Q, R, P0, T)
    L = min(BLOCK, T)
    nb = -(-T // L)
    pad = nb * L - T
    if pad:  # the last block is shorter: pad the gains (their rows are never read)
        gains = torch.cat([gains, gains[-1:].expand(pad, dx, dy)])
        whiten = torch.cat([whiten, whiten[-1:].expand(pad, dy, dy)])
    W = _block_maps(F, H, Bm, gains, whiten, L, du)  # [nb, rows, nX]

    Y = ys.expand(batch + ys.shape[-2:]).reshape(n, T * dy)
    U = None if us is None else us.expand(batch + us.shape[-2:]).reshape(n, T * du)
    m_prev = m0.expand(batch + (dx,)).reshape(n, dx)
    tensors = [Y, U, F, H, Q, R, m0, P0, Bm]
    grad = torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)
    run_blocks = _blocks_autograd if grad else _blocks_in_place
    out_means, out_pred, out_inn, quad = run_blocks(W, m_prev, Y, U, L, (dx, dy, du))
    if not _means_hold(out_means, m_prev, Y, U, F, H, Bm, gains[:T], covs, (dx, dy, du)):
        return None  # the step-by-step filter, whose means a strongly non-normal F keeps
    norm = half_logdet + 0.5 * dy * LOG_2PI  # [T]
    # in place without gradients: a [B, T] temporary is 160 MB at B = 1e5
    increments = -0.5 * quad - norm if grad else quad.mul_(-0.5).sub_(norm)
    increments = increments.view(batch + (T,)).to(dtype)

    def shared(mats: Tensor) -> Tensor:  # [T, d, d] → a view [..., T, d, d]
        return mats.expand(batch + mats.shape)

    return FilterResult(
        means=out_means.view(batch + (T, dx)),
        covs=shared(covs),
        pred_means=out_pred.view(batch + (T, dx)),
        pred_covs=shared(pred_covs),
        innovations=out_inn.view(batch + (T, dy)),
        innovation_covs=shared(inn_covs),
        log_likelihood_increments=increments,
        log_likelihood=increments.sum(-1),
    )
