"""The Kalman filter's general step for one run on host arrays, where nothing is recorded.

An unbatched Kalman filter steps with its gain schedule (:class:`~difffilter.GainSchedule`:
about eight tensor operations) wherever every entry of ``y_k`` arrives. A step with a
``mask`` (a lost packet, a sensor out), and every step after one, takes the general update
instead: some sixty torch operations on ``[4, 4]`` matrices, each a few microseconds of
dispatch for well under a microsecond of arithmetic (a recorded-log trial: 166–236 µs a
step against 19 µs scheduled). When autograd records nothing (no input, carry tensor or
model matrix requires a gradient, no ``torch.func`` transform or forward-mode level is
active) and the run lives in CPU memory in float32 or float64, :func:`host_step`
computes the same update on numpy views of the same memory (no copies in, one
``torch.from_numpy`` per output)::

    predict    m⁻ = F m + B u,            P⁻ = sym(F P Fᵀ + Q)
    mask       H' = M H,  R' = M R M + (I − M),  r' = M (y − H m⁻)   (M = diag(mask))
    moments    C = P⁻ H'ᵀ,  S = sym(H' C + R'),  S = L Lᵀ
    update     K = C S⁻¹,  m⁺ = m⁻ + K r',  P⁺ = sym((I − K H') P⁻ (I − K H')ᵀ + K R' Kᵀ)
    evidence   log N(r'; 0, S) = −½ |L⁻¹ r'|² − Σ log L_ii − (m_k/2) log 2π

(:func:`~difffilter.linalg.masked_measurement`, :func:`~difffilter.gaussian.linear_update`:
the same equations, the same outputs; tests compare the two to round-off in float64 and
float32.) The inverse of ``S`` is formed from its triangular factor, ``S⁻¹ = L⁻ᵀ L⁻¹``,
where the torch update solves with it: the same numbers up to round-off at these sizes.
Left to the torch update: an ``S`` that is not positive definite, nearly singular (a
Cholesky pivot ``L_ii² ≤ 1000 ε S_ii``, where the two factorisations may decide apart)
or not finite (its jitter and its :class:`~difffilter.NumericalBreakdown`), models whose matrices are batched
or of another dtype, half precision, other devices, a batched carry, and any step that
could record a gradient.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ._checks import step_covariance
from .linalg import LOG_2PI, under_transform
from .results import GaussianState, StepOutput

__all__ = ["host_step"]

_HOST_DTYPES = (torch.float32, torch.float64)

#: A Cholesky pivot ``L_ii²`` at or below this share of ``S_ii`` (a thousand machine
#: epsilons) leaves the step to the torch update.
_NEAR_SINGULAR = {np.float32: 1e3 * np.finfo(np.float32).eps,
                  np.float64: 1e3 * np.finfo(np.float64).eps}  # fmt: skip


# an overflow or a NaN (a diverging carry, a far-off y) is the torch update's to name, as
# its NumericalBreakdown: numpy's RuntimeWarning had escaped before it (a review)
@np.errstate(over="ignore", invalid="ignore", divide="ignore")
def host_step(
    carry: GaussianState, y: Tensor, u: Tensor | None, mask: Tensor | None
) -> tuple[GaussianState, StepOutput] | None:
    """The general Kalman step of one run from ``carry`` on host arrays (module docstring):
    ``(GaussianState, StepOutput)`` as :meth:`KalmanFilter.update` returns them, or
    ``None`` where the torch update must take the step (the module docstring's list).

    Shapes: ``carry.mean [dx]``, ``carry.cov [dx, dx]``, ``y [dy]`` (zero where unreceived,
    as the step's checks leave it), ``u [du]`` or ``None``, ``mask [dy]`` bool or ``None``.
    """
    mean_t, cov_t = carry.mean, carry.cov
    if torch.is_grad_enabled() and (
        mean_t.requires_grad or cov_t.requires_grad or y.requires_grad
        or (u is not None and u.requires_grad)
    ):  # fmt: skip
        return None
    if mean_t.dim() != 1 or mean_t.dtype not in _HOST_DTYPES or mean_t.device.type != "cpu":
        return None
    if cov_t.dim() != 2 or y.dim() != 1:  # (a carry of one mean and a batch of covariances)
        return None
    if mask is not None and mask.dim() != 1:
        return None
    model, k = carry.model, carry.k
    F, Q, B = (
        model.transition_matrix(k),
        step_covariance(model, "process_cov", k),
        model.control_matrix(k),
    )
    H, R = model.observation_matrix(k + 1), step_covariance(model, "measurement_cov", k + 1)
    matrices = (F, Q, H, R) if B is None or u is None else (F, Q, H, R, B)
    dtype = mean_t.dtype
    for m in matrices:
        if not isinstance(m, Tensor) or m.dim() != 2 or m.dtype != dtype or m.device.type != "cpu":
            return None
        if m.requires_grad and torch.is_grad_enabled():
            return None
    if under_transform():  # (wrapped or dual tensors report requires_grad=False)
        return None
    try:
        arrays = [t.detach().numpy() if t.requires_grad else t.numpy()
                  for t in (mean_t, cov_t, y, *matrices)]  # fmt: skip
        u_np = None if u is None or B is None else u.detach().numpy()
    except (TypeError, RuntimeError):  # sparse or otherwise not a plain strided array
        return None
    m0, P, y_np, F, Q, H, R = arrays[:7]
    half = m0.dtype.type(0.5)

    pred_mean = F @ m0
    if u_np is not None:
        pred_mean = pred_mean + arrays[7] @ u_np
    pred_cov = F @ P @ F.T + Q
    pred_cov = (pred_cov + pred_cov.T) * half

    residual = y_np - H @ pred_mean
    if mask is None:
        observed = H.shape[0]
    elif (keep := mask.numpy()).all():  # every entry: M = I changes no number
        observed = m0.dtype.type(keep.shape[0])
    else:
        keep = keep.astype(m0.dtype)
        residual = residual * keep
        H = H * keep[:, None]
        R = R * np.multiply.outer(keep, keep) + np.diag(1.0 - keep)
        observed = keep.sum()
    cross = pred_cov @ H.T
    S = H @ cross + R
    S = (S + S.T) * half
    if not np.isfinite(S).all():
        return None
    try:
        chol = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:  # the torch update jitters it, or names the breakdown
        return None
    # nearly singular: numpy's and torch's factorisations may decide it differently (a
    # review: numpy factored 12 % of random rank-deficient S that torch refuses); the torch
    # update's decision, jitter or breakdown, is the step's
    pivots = np.diagonal(chol)
    if (pivots * pivots <= _NEAR_SINGULAR[m0.dtype.type] * np.diagonal(S)).any():
        return None
    chol_inv = np.linalg.inv(chol)
    gain = cross @ (chol_inv.T @ chol_inv)
    mean = pred_mean + gain @ residual
    i_kh = np.eye(m0.shape[0], dtype=m0.dtype) - gain @ H
    cov = i_kh @ pred_cov @ i_kh.T + gain @ R @ gain.T
    cov = (cov + cov.T) * half
    white = chol_inv @ residual
    log_lik = -half * (white @ white) - np.log(np.diagonal(chol)).sum() - half * observed * LOG_2PI

    mean_t, cov_t = torch.from_numpy(mean), torch.from_numpy(cov)
    out = StepOutput(
        mean_t, cov_t, torch.from_numpy(pred_mean), torch.from_numpy(pred_cov),
        torch.from_numpy(residual), torch.from_numpy(S),
        torch.from_numpy(np.asarray(log_lik, dtype=m0.dtype)),
    )  # fmt: skip
    return GaussianState(mean_t, cov_t, k + 1, model), out
