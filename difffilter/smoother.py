"""The Rauch–Tung–Striebel smoother: ``p(x_k | y_{1:T})`` of a linear Gaussian model.

After the Kalman filter's forward pass (filtered ``m_k, P_k``, predicted ``m⁻_{k+1},
P⁻_{k+1}``), the backward recursion from ``m^s_T = m_T``, ``P^s_T = P_T``:

    G_k   = P_k F_kᵀ (P⁻_{k+1})⁻¹
    m^s_k = m_k + G_k (m^s_{k+1} − m⁻_{k+1})
    P^s_k = P_k + G_k (P^s_{k+1} − P⁻_{k+1}) G_kᵀ

with ``F_k`` the transition from step ``k`` to ``k + 1`` (``model.transition_matrix(k)``),
and the lag-one cross-covariance ``Cov(x_k, x_{k+1} | y_{1:T}) = G_k P^s_{k+1}`` (what an
EM update of ``F`` and ``Q`` needs). Inputs and lost measurements enter through the
forward pass alone. Batched over runs, differentiable (tested equal to the dense joint
Gaussian's conditional, and by ``gradcheck``); the backward loop over time is the only
Python loop. For offline analysis of a recorded log (docs/recorded-logs.md): the state
at every step given the whole log, not only its past.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .kalman import kalman_filter
from .linalg import symmetrize
from .results import FilterResult

__all__ = ["SmootherResult", "rts_smoother", "kalman_smoother"]


class SmootherResult(NamedTuple):
    """``means [..., T, dx]`` ``E[x_k | y_{1:T}]``, ``covs [..., T, dx, dx]``, ``cross_covs
    [..., T − 1, dx, dx]`` ``Cov(x_k, x_{k+1} | y_{1:T})``, ``gains [..., T − 1, dx, dx]``
    the smoother gains ``G_k`` (time index ``t`` ↔ ``k = t + 1``, as the filter's), and
    ``filtered``, the forward pass's :class:`~difffilter.results.FilterResult`. Where the
    filter's covariances are shared by every run (an unbatched time-invariant model, every
    entry received), ``cross_covs`` and ``gains`` are too: size 1 in those batch
    dimensions, which broadcast (``gains[..., t, :, :]`` indexes time either way);
    ``covs`` is expanded to the runs (a view)."""

    means: Tensor
    covs: Tensor
    cross_covs: Tensor
    gains: Tensor
    filtered: FilterResult


def _transitions(model, steps: int) -> Tensor:
    """``F_k`` for ``k = 1 … T − 1`` ``[(…,) T − 1, dx, dx]`` (one matrix where the model is
    time-invariant)."""
    if getattr(model, "time_varying", False):
        return torch.stack([model.transition_matrix(k) for k in range(1, steps)], -3)
    return model.transition_matrix(1).unsqueeze(-3)


def rts_smoother(model, filtered: FilterResult) -> SmootherResult:
    """The Rauch–Tung–Striebel smoother (module docstring) of ``filtered``, the result of
    :func:`difffilter.kalman_filter` on ``model`` (a linear model: ``transition_matrix(k)``,
    ``process_cov(k)``)."""
    if not isinstance(filtered, FilterResult):
        raise TypeError(
            "filtered must be the FilterResult of difffilter.kalman_filter(model, ys, …); got "
            f"{type(filtered).__name__}"
        )
    for name in ("transition_matrix", "process_cov"):
        if not callable(getattr(model, name, None)):
            raise TypeError(
                f"the RTS smoother needs a linear model ({type(model).__name__} has no {name}): "
                "e.g. difffilter.LinearGaussianModel"
            )
    means, covs = filtered.means, filtered.covs
    steps, dx = means.shape[-2], means.shape[-1]
    if steps < 1:
        raise ValueError("filtered holds no step (T = 0)")
    empty = means.new_zeros(means.shape[:-2] + (0, dx, dx))
    if steps == 1:  # the last step is the filter's (no transition to read)
        return SmootherResult(means, covs.expand(means.shape + (dx,)), empty, empty, filtered)
    F = _transitions(model, steps)
    if F.shape[-2:] != (dx, dx):
        raise ValueError(f"model's F is {tuple(F.shape[-2:])} and the filtered states have "
                         f"{dx} entries: smooth with the model that was filtered")  # fmt: skip
    if filtered.pred_covs is not None:
        pred_covs = filtered.pred_covs
    else:  # P⁻_{k+1} = F_k P_k F_kᵀ + Q_k (the filter's prediction)
        Q = torch.stack([model.process_cov(k) for k in range(1, steps)], -3) if getattr(
            model, "time_varying", False) else model.process_cov(1).unsqueeze(-3)  # fmt: skip
        ahead = F @ covs[..., :-1, :, :] @ F.mT + Q  # P⁻_2 … P⁻_T (P⁻_1 is not read)
        pred_covs = torch.cat([covs[..., :1, :, :], ahead], -3)
    # covariances shared by every run (the filter hands them out expanded, stride 0): the
    # covariance recursion once, not once per run (2,000 runs × 300 steps took 2 s and
    # 73 MiB for each of covs, gains and cross_covs)
    covs, pred_covs = _shared(covs), _shared(pred_covs)
    smooth_m, smooth_P = [means[..., -1, :]], [covs[..., -1, :, :]]
    gains, cross = [], []
    for t in range(steps - 2, -1, -1):  # backward: index t ↔ k = t + 1
        F_t = F[..., t if F.shape[-3] > 1 else 0, :, :]
        P_t, P_next_pred = covs[..., t, :, :], pred_covs[..., t + 1, :, :]
        # G = P Fᵀ (P⁻)⁻¹, by a solve: Gᵀ = (P⁻)⁻¹ F P (P⁻ and P symmetric)
        G = torch.linalg.solve(P_next_pred, F_t @ P_t).mT
        m_next, P_next = smooth_m[-1], smooth_P[-1]
        m = means[..., t, :] + (
            G @ (m_next - filtered.pred_means[..., t + 1, :]).unsqueeze(-1)
        ).squeeze(-1)
        P = symmetrize(P_t + G @ (P_next - P_next_pred) @ G.mT)
        smooth_m.append(m)
        smooth_P.append(P)
        gains.append(G)
        cross.append(G @ P_next)
    smooth_m.reverse()
    smooth_P.reverse()
    gains.reverse()
    cross.reverse()
    P = torch.stack(smooth_P, -3)
    return SmootherResult(
        torch.stack(smooth_m, -2),
        P.expand(means.shape[:-1] + (dx, dx)),
        torch.stack(cross, -3),
        torch.stack(gains, -3),
        filtered,
    )


def _shared(covs: Tensor) -> Tensor:
    """``covs [..., T, d, d]`` with every batch dimension that is an expansion (stride 0)
    narrowed to size 1: the same numbers, broadcasting as before."""
    for dim in range(covs.dim() - 3):
        if covs.stride(dim) == 0 and covs.shape[dim] > 1:
            covs = covs.narrow(dim, 0, 1)
    return covs


def kalman_smoother(
    model, ys: Tensor, us: Tensor | None = None, **filter_options
) -> SmootherResult:
    """:func:`difffilter.kalman_filter` on ``ys [..., T, dy]`` (``us``, and its options:
    ``mask``, ``nonfinite``, …), then :func:`rts_smoother`."""
    return rts_smoother(model, kalman_filter(model, ys, us, **filter_options))
