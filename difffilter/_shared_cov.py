"""Kalman filter for many runs of one linear time-invariant model (shared covariances).

When the model's matrices ``F, H, Q, R, P_0`` (and ``B``) carry no batch dimension and
no entry is masked, the covariance recursion

    P⁻_t = F P_{t−1} Fᵀ + Q,   S_t = H P⁻_t Hᵀ + R,   K_t = P⁻_t Hᵀ S_t⁻¹,
    P_t  = (I − K_t H) P⁻_t (I − K_t H)ᵀ + K_t R K_tᵀ

does not depend on the measurements: it runs once, on ``[dx, dx]`` matrices, with the
same operations as :func:`difffilter.kalman.kalman_step`. The covariances are returned
as expanded views ``[..., T, dx, dx]`` of one ``[T, dx, dx]`` tensor (no ``B`` copies).

What remains per run is linear in the data. Over a block of ``L`` steps starting after
``m_{s−1}``, with ``X = [m_{s−1}; y_s … y_{s+L−1}; u_s … u_{s+L−1}]``::

    m⁻_t = F m_{t−1} + B u_t,   r_t = y_t − H m⁻_t,   m_t = m⁻_t + K_t r_t,   z_t = L_t⁻¹ r_t

are all ``W X`` for one matrix ``W`` per block (built from the ``K_t``, ``L_t``
by running the recursion on coefficient matrices, batched over blocks), so each block
is one GEMM over all runs: ``[B, dx + (dy + du) L] × [·, (2 dx + 2 dy) L]``. The
log-likelihood increments are ``−½‖z_t‖² − Σ log diag L_t − (dy/2) log 2π``. The
results equal the step-by-step filter up to round-off (tests check 1e-10).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .linalg import LOG_2PI, cholesky_solve_right, safe_cholesky, symmetrize
from .results import FilterResult

__all__ = ["shared_covariance_applies", "shared_covariance_kalman_filter"]

# Steps per GEMM block: the GEMM's cost per run-step grows with L (the block matrix is
# lower block-triangular but stored dense), the number of kernel launches falls with it.
# Measured on the 2-core CPU (CV model, T = 200, B = 1e5): L = 2, 4, 8, 16, 32 gave
# 1.8e7, 1.84e7, 1.37e7, 1.52e7, 1.2e7 run-steps/s.
BLOCK = 4


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
    """The data-independent recursion, the same operations as ``kalman_step``."""
    dx = F.shape[-1]
    eye = torch.eye(dx, dtype=F.dtype, device=F.device)
    eye_y = torch.eye(H.shape[-2], dtype=F.dtype, device=F.device)
    pred, covs, inn, gains, whiten, half_logdet = [], [], [], [], [], []
    for _ in range(T):
        Pp = symmetrize(F @ P @ F.transpose(-1, -2) + Q)
        cross = Pp @ H.transpose(-1, -2)
        S = symmetrize(H @ cross + R)
        chol = safe_cholesky(S, name="innovation covariance S")
        K = cholesky_solve_right(cross, chol)
        i_kh = eye - K @ H
        P = symmetrize(i_kh @ Pp @ i_kh.transpose(-1, -2) + K @ R @ K.transpose(-1, -2))
        pred.append(Pp)
        covs.append(P)
        inn.append(S)
        gains.append(K)
        whiten.append(torch.linalg.solve_triangular(chol, eye_y, upper=False))
        half_logdet.append(torch.log(torch.diagonal(chol)).sum())
    return (
        torch.stack(pred),
        torch.stack(covs),
        torch.stack(inn),
        torch.stack(gains),
        torch.stack(whiten),
        torch.stack(half_logdet),
    )


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


def shared_covariance_kalman_filter(model, ys: Tensor, us: Tensor | None = None) -> FilterResult:
    """Kalman filter of ``ys [..., T, dy]`` (validated, no mask) for a shared LTI model.

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
    parts = {"means": [], "pred": [], "inn": [], "quad": []}
    if not grad:
        out_means = ys.new_empty(n, T, dx)
        out_pred = ys.new_empty(n, T, dx)
        out_inn = ys.new_empty(n, T, dy)
        out_quad = ys.new_empty(n, T)
    for b in range(nb):
        s, Lb = b * L, min(L, T - b * L)
        rows = torch.cat(
            [torch.arange(k * L * dx + 0, k * L * dx + Lb * dx, device=W.device) for k in range(2)]
            + [
                torch.arange(
                    2 * L * dx + k * L * dy, 2 * L * dx + k * L * dy + Lb * dy, device=W.device
                )
                for k in range(2)
            ]
        )
        Wb = W[b].index_select(0, rows) if Lb < L else W[b]
        # one GEMM per input group: m_{s−1}, the block's y's, its u's
        out = torch.addmm(
            m_prev @ Wb[:, :dx].transpose(0, 1),
            Y[:, s * dy : (s + Lb) * dy],
            Wb[:, dx : dx + dy * Lb].transpose(0, 1),
        )
        if U is not None:
            col = dx + dy * L
            out = out.addmm(
                U[:, s * du : (s + Lb) * du], Wb[:, col : col + du * Lb].transpose(0, 1)
            )
        a, e = Lb * dx, Lb * dy
        means = out[:, :a].view(n, Lb, dx)
        pred = out[:, a : 2 * a].view(n, Lb, dx)
        inn = out[:, 2 * a : 2 * a + e].view(n, Lb, dy)
        quad = out[:, 2 * a + e :].square().view(n, Lb, dy).sum(-1)
        m_prev = out[:, a - dx : a]
        if grad:
            for key, val in zip(parts, (means, pred, inn, quad)):
                parts[key].append(val)
        else:
            out_means[:, s : s + Lb] = means
            out_pred[:, s : s + Lb] = pred
            out_inn[:, s : s + Lb] = inn
            out_quad[:, s : s + Lb] = quad
    if grad:
        out_means, out_pred, out_inn, out_quad = (torch.cat(parts[k], dim=1) for k in parts)
    increments = -0.5 * out_quad - half_logdet - 0.5 * dy * LOG_2PI
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
