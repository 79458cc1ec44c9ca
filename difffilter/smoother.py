"""The Rauch–Tung–Striebel smoother: ``p(x_k | y_{1:T})`` of a linear Gaussian model.

After the Kalman filter's forward pass (filtered ``m_k, P_k``, predicted ``m⁻_{k+1},
P⁻_{k+1}``), the backward recursion from ``m^s_T = m_T``, ``P^s_T = P_T``:

    G_k   = P_k F_kᵀ (P⁻_{k+1})⁻¹
    m^s_k = m_k + G_k (m^s_{k+1} − m⁻_{k+1})
    P^s_k = P_k + G_k (P^s_{k+1} − P⁻_{k+1}) G_kᵀ

with ``F_k`` the transition from step ``k`` to ``k + 1`` (``model.transition_matrix(k)``),
down to the prior ``x_0 ~ N(m0, P0)`` (``k = 0``), and the lag-one cross-covariance
``Cov(x_k, x_{k+1} | y_{1:T}) = G_k P^s_{k+1}``: with the smoothed ``x_0``, what an EM
update of ``F``, ``Q`` and the prior needs (docs/gradients.md). Inputs and lost measurements enter through the
forward pass alone. Batched over runs, differentiable (tested equal to the dense joint
Gaussian's conditional, and by ``gradcheck``). For a nonlinear model the same recursion
on the EKF's result with ``F_k = ∂f/∂x(m_k, u_k)`` is the extended RTS smoother
(:func:`extended_kalman_smoother`). On the UKF's result, the unscented RTS smoother
(Särkkä 2008, :func:`unscented_kalman_smoother`) replaces ``P_k F_kᵀ`` by the sigma
points' cross-covariance of ``x_k`` and ``x_{k+1}``:

    X_k = sigma points of N(m_k, P_k),   D_k = Σᵢ wᶜᵢ (X_k^i − m_k)(f(X_k^i, u_k) − m⁻_{k+1})ᵀ
    G_k = D_k (P⁻_{k+1})⁻¹

(the same recursion otherwise; on a linear model ``D_k = P_k F_kᵀ`` and it is the RTS
smoother). The backward loop over time is the only Python loop. For offline analysis of
a recorded log (docs/recorded-logs.md): the state at every step given the whole log, not
only its past.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import torch
from torch import Tensor

from ._checks import (
    _check_us,
    broadcast_or_none,
    check_filtered_dtype,
    check_finite_at,
    check_inputs_given,
    check_model_batch,
    check_positive_definite,
    check_same_result,
    check_semidefinite,
    check_symmetric,
    model_batch_shape,
    model_dtype_device,
    step_covariance,
)
from .kalman import _check_declared_time_varying, kalman_filter
from .linalg import symmetrize
from .results import FilterResult, ParticleFilterResult
from .ssm import inputs_per_point, inputs_per_row

__all__ = [
    "SmootherResult",
    "rts_smoother",
    "unscented_rts_smoother",
    "kalman_smoother",
    "extended_kalman_smoother",
    "unscented_kalman_smoother",
]


class SmootherResult(NamedTuple):
    """The smoothed distribution, every tensor with the runs' batch shape (views where the
    filter's covariances are shared by every run, so sums over runs count each run; they
    share memory across runs: ``.clone()`` before writing into one):

    * ``means [..., T, dx]`` ``E[x_k | y_{1:T}]`` and ``covs [..., T, dx, dx]`` for
      ``k = 1 … T`` (time index ``t`` ↔ ``k = t + 1``, as the filter's);
    * ``cross_covs [..., T − 1, dx, dx]`` ``Cov(x_k, x_{k+1} | y_{1:T})`` for ``k = 1 … T − 1``
      (the transpose of Shumway & Stoffer's ``P_{k+1,k}``);
    * ``gains [..., T − 1, dx, dx]`` the smoother gains ``G_k``, ``k = 1 … T − 1``;
    * the initial state: ``initial_mean [..., dx]`` ``E[x_0 | y_{1:T}]``, ``initial_cov``
      and ``initial_cross [..., dx, dx]`` ``Cov(x_0, x_1 | y_{1:T})`` (an EM update of the
      prior, and of ``F`` and ``Q`` through the first transition, needs them: without them
      EM stopped short of the maximum-likelihood estimate in an identification trial);
    * ``filtered``, the forward pass's :class:`~difffilter.results.FilterResult`.
    """

    means: Tensor
    covs: Tensor
    cross_covs: Tensor
    gains: Tensor
    initial_mean: Tensor
    initial_cov: Tensor
    initial_cross: Tensor
    filtered: FilterResult


def _of_k(model, name: str, steps: int) -> Tensor:
    """``model.name(k)`` for ``k = 0 … T − 1`` ``[(…,) T, d, d]`` (one, ``[(…,) 1, d, d]``,
    where the model is time-invariant)."""
    # a covariance as the filters read it (checked where a time-varying model overrides it)
    method = (
        partial(step_covariance, model, name) if name.endswith("_cov") else getattr(model, name)
    )
    if getattr(model, "time_varying", False):
        return torch.stack([method(k) for k in range(steps)], -3)
    return method(0).unsqueeze(-3)


def _jacobians(model, m0: Tensor, means: Tensor, us: Tensor | None) -> Tensor:
    """``∂f/∂x`` at ``m_k`` (``m_0`` the prior mean) with ``u_k`` for ``k = 0 … T − 1``
    ``[..., T, dx, dx]``: the transitions the EKF linearised."""
    at = [m0.expand(means.shape[:-2] + m0.shape[-1:])] + list(means[..., :-1, :].unbind(-2))
    return torch.stack([model.transition_jacobian(x, inputs_per_row(None if us is None
                                                                     else us[..., k, :], x), k)
                        for k, x in enumerate(at)], -3)  # fmt: skip


def _at(t: Tensor, k: int) -> Tensor:
    """Step ``k`` of a ``[…, T or 1, d, d]`` sequence (one matrix: every step)."""
    return t[..., k if t.shape[-3] > 1 else 0, :, :]


def _check_filtered_by(filtered: FilterResult, want: Tensor, pred: Tensor | None,
                       unscented: bool = False) -> None:  # fmt: skip
    """``filtered`` is ``model``'s filter result as far as step 1 shows it, where every path
    of the filter computes the same numbers: ``P⁻_1`` is ``want`` (``F_0 P0 F_0ᵀ + Q_0``, or
    the unscented transform's) and, where the first input is known (given, or a model
    without inputs), ``m⁻_1`` is ``pred`` (``f(m0, u_0)``, or the sigma points' mean; ``None``:
    not known) (a result of another model, or a stale one in an EM loop, had smoothed
    silently wrong: means 0.48 off). Per run and per matrix, to round-off of the dtype
    (later steps of the shared-covariance path differ from the plain recursion by more than
    that in float32). Not seen: a result filtered with another ``H`` or ``R``."""
    tol = 1e3 * torch.finfo(filtered.means.dtype).eps
    got = filtered.pred_covs[..., 0, :, :]
    scale = want.detach().abs().amax((-1, -2)).clamp_min(torch.finfo(want.dtype).tiny)
    bad = (got.detach() - want.detach()).abs().amax((-1, -2)) > tol * scale
    if pred is not None:
        spread = want.detach().diagonal(dim1=-2, dim2=-1).amax(-1).sqrt()
        size = pred.detach().abs().amax(-1) + spread
        gap = (filtered.pred_means[..., 0, :].detach() - pred.detach()).abs().amax(-1)
        bad = bad | (gap > tol * size)
    if bool(bad.any()) and unscented:
        raise ValueError(
            "filtered is not this model's unscented Kalman filter result with these sigma "
            "points: its prediction of step 1 is not the sigma points' of the prior; filter "
            "with this model and the same SigmaPoints, e.g. "
            "difffilter.unscented_kalman_smoother(model, ys, …, sigma_points=…)"
        )
    if bool(bad.any()):
        raise ValueError(
            "filtered is not this model's Kalman filter result: its prediction of step 1 is "
            "not the model's (F P0 Fᵀ + Q, F m0); filter with this model, e.g. "
            "difffilter.kalman_smoother(model, ys, …), after every change to it (a UKF's "
            "result: difffilter.unscented_rts_smoother)"
        )


def rts_smoother(model, filtered: FilterResult, us: Tensor | None = None) -> SmootherResult:
    """The Rauch–Tung–Striebel smoother (module docstring) of ``filtered``, from step ``T``
    back to the prior ``x_0``: for a linear model (``transition_matrix(k)``) the result of
    :func:`difffilter.kalman_filter`; for a nonlinear one the result of
    :func:`difffilter.extended_kalman_filter` on the same ``us``, with ``F_k`` the
    Jacobian ``∂f/∂x`` at the filtered mean ``m_k`` (the prior mean at ``k = 0``), as the
    EKF predicted with: the extended RTS smoother. ``us [..., T, du]``, the filter's inputs,
    also let the check of ``filtered`` read the first predicted mean; a nonlinear model with
    inputs needs them (``ValueError`` without: zero inputs are given as zeros). (The UKF's result:
    :func:`unscented_rts_smoother`.) The check sees a filter of another ``F``, ``Q`` or
    prior (the prior's mean, on a model with inputs, only where ``us`` is given), not one of
    another ``H``, ``R`` or ``B`` (the backward pass reads none of them): smooth with the
    model that filtered."""
    steps, dx = _check_arguments(model, filtered, us, "transition_jacobian")
    means = filtered.means
    if callable(getattr(model, "transition_matrix", None)):
        # read at step 0 alone unless declared time-varying, as the Kalman filter refuses it
        # (the EKF reads F_k at every step: its result had been smoothed with F_0, 0.8 off)
        _check_declared_time_varying(model)
        F = _of_k(model, "transition_matrix", steps)
    else:  # the EKF's linearisation: at the prior mean for k = 0, the filtered mean after
        check_inputs_given(model, us, "the extended RTS smoother", "its Jacobians ∂f/∂x at u_k")
        F = _jacobians(model, model.initial.mean, means, us)
    Q = _of_k(model, "process_cov", steps)
    if F.shape[-2:] != (dx, dx):
        raise ValueError(f"model's F is {tuple(F.shape[-2:])} and the filtered states have "
                         f"{dx} entries: smooth with the model that was filtered")  # fmt: skip
    m0, P0 = model.initial.mean, model.initial.cov
    if filtered.pred_covs is not None:
        F_0 = _at(F, 0)
        pred = None
        if us is not None or not getattr(model, "dim_u", 0):
            # the model's own transition (F_0 m0 was a nonlinear model's linearisation, not f)
            start = m0.expand(means.shape[:-2] + m0.shape[-1:])  # every run's
            pred = model.transition(start, inputs_per_row(None if us is None else us[..., 0, :],
                                                          start), 0)  # fmt: skip
        _check_filtered_by(filtered, F_0 @ P0 @ F_0.mT + _at(Q, 0), pred)

    def transition(k: int, mean: Tensor, cov: Tensor, predict: bool):
        F_k = _at(F, k)  # Cov(x_{k+1}, x_k | y_{1:k}) = F P, and P⁻ = F P Fᵀ + Q
        cross = F_k @ cov
        return cross, cross @ F_k.mT + _at(Q, k) if predict else None

    return _backward(model, filtered, transition)


def unscented_rts_smoother(
    model, filtered: FilterResult, us: Tensor | None = None, sigma_points=None
) -> SmootherResult:
    """The unscented RTS smoother (Särkkä 2008; module docstring) of ``filtered``, the
    result of :func:`difffilter.unscented_kalman_filter` on ``model`` with ``us
    [..., T, du]`` and the same ``sigma_points`` (a
    :class:`~difffilter.extended.SigmaPoints`; default ``SigmaPoints()``, the UKF's): the
    smoother gain from the cross-covariance of the sigma points of ``N(m_k, P_k)`` and
    their images under ``f``, with the UKF's weights (``us`` required on a model with
    inputs: ``ValueError`` without). On a linear model, the RTS smoother."""
    from .extended import SigmaPoints, _check_sigma_points, _moments

    _check_sigma_points(sigma_points)
    if model_batch_shape(model, matrices_only=True):  # (as the UKF refuses it)
        raise ValueError(
            "the unscented smoother evaluates f on sigma points, and this model's matrices "
            "have a batch shape (one per run): smooth its Kalman filter's result with "
            "difffilter.rts_smoother"
        )
    sp = sigma_points or SigmaPoints()
    steps, _ = _check_arguments(model, filtered, us, "transition")
    check_inputs_given(model, us, "the unscented RTS smoother", "f(X, u_k) at its sigma points")
    m0, P0 = model.initial.mean, model.initial.cov
    means = filtered.means
    wm, wc, scale = sp.weights(means.shape[-1], means.dtype, means.device)

    def predicted(k: int, mean: Tensor, cov: Tensor):
        """The sigma points ``X``, ``f(X)`` and the UKF's own prediction ``(m⁻, P⁻)``."""
        X = sp.points(mean, cov, scale)  # [..., 2n+1, n]
        # (one input row per point, as the UKF gives them: a transition that joins x and u
        # with torch.cat had failed here on [..., 1, du], the filter it smooths running it)
        FX = model.transition(X, inputs_per_point(None if us is None else us[..., k, :], X), k)
        pred_mean, pred_cov = _moments(FX, wm, wc)  # (the filter's sums, in its order)
        return X, FX, pred_mean, symmetrize(pred_cov + step_covariance(model, "process_cov", k))

    def transition(k: int, mean: Tensor, cov: Tensor, predict: bool):
        # Cov(x_{k+1}, x_k) = Σ wᶜ (f(X) − m⁻)(X − m)ᵀ
        X, FX, pred_mean, pred_cov = predicted(k, mean, cov)
        weighted = (wc[:, None] * (FX - pred_mean.unsqueeze(-2))).mT  # [..., n, 2n+1]
        return weighted @ (X - mean.unsqueeze(-2)), pred_cov if predict else None

    if filtered.pred_covs is not None:
        start = m0.expand(means.shape[:-2] + m0.shape[-1:])
        _, _, pred, want = predicted(0, start, P0)
        _check_filtered_by(filtered, want, pred, unscented=True)  # (us given where used)
    return _backward(model, filtered, transition)


def _check_arguments(model, filtered, us, needed: str) -> tuple[int, int]:
    """``(T, dx)`` of ``filtered`` after checking what every smoother takes."""
    if not isinstance(filtered, FilterResult) or isinstance(filtered, ParticleFilterResult):
        raise TypeError(
            "filtered must be the FilterResult of difffilter.kalman_filter(model, ys, …) (or "
            "extended_kalman_filter, unscented_kalman_filter for a nonlinear model); got "
            f"{type(filtered).__name__}"
        )
    for name in (needed, "process_cov"):
        if not callable(getattr(model, name, None)):
            raise TypeError(
                f"the RTS smoother needs a state-space model with {name} ({type(model).__name__} "
                "has none): e.g. difffilter.LinearGaussianModel"
            )
    steps, dx = filtered.means.shape[-2], filtered.means.shape[-1]
    if steps < 1:
        raise ValueError("filtered holds no step (T = 0)")
    check_filtered_dtype(model, filtered.means, "means")
    # (torch's "size of tensor a (4) must match" from the check of step 1 otherwise)
    check_model_batch(model, filtered.means.shape[:-2], "the filtered means")
    _check_fields(filtered, steps, dx)
    if us is not None:  # the filter's inputs, checked as the filters check them
        dtype, device = model_dtype_device(model)
        _check_us(model, us, filtered.means.shape[:-2], steps, dtype, device,
                  against="the filtered means'")  # fmt: skip
    return steps, dx


def _check_fields(filtered: FilterResult, steps: int, dx: int) -> None:
    """``filtered``'s ``means [..., T, dx]``, ``covs [..., T, dx, dx]``, ``pred_means`` and
    ``pred_covs`` (if any) as a filter hands them out: ``T`` steps each, runs that broadcast
    to the means', the means' dtype and device, finite values, symmetric covariances and
    positive-definite predicted ones (which the gain solves against). A result edited by
    hand had been read a step shifted (``covs`` one short: 0.14 off), truncated (integer
    ``pred_means``: 0.78 off), run to NaN means, or failed in torch (a Gaussian-smoother
    trial). Covariances shared by the runs (stride 0) are checked once."""
    means = filtered.means
    runs = means.shape[:-2]
    fields = [("means", means, 1), ("covs", filtered.covs, 2)]
    fields.append(("pred_means", filtered.pred_means, 1))
    if filtered.pred_covs is not None:
        fields.append(("pred_covs", filtered.pred_covs, 2))
    for name, t, event in fields:
        want = (steps, dx) if event == 1 else (steps, dx, dx)
        shape = "[..., T, dx]" if event == 1 else "[..., T, dx, dx]"
        if not isinstance(t, Tensor) or t.dim() < event + 1 or tuple(t.shape[-event - 1 :]) != want:
            got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(
                f"filtered.{name} must be {shape} with T = {steps}, dx = {dx} (as the means); "
                f"got {got}"
            )
        if broadcast_or_none(t.shape[: t.dim() - event - 1], runs) != runs:
            raise ValueError(
                f"filtered.{name} holds the runs {tuple(t.shape[: t.dim() - event - 1])}, and "
                f"the means {tuple(runs)}: one result of one filter"
            )
        check_same_result(t, f"filtered.{name}", means, "the means")
        values = _shared(t) if event == 2 else t
        check_finite_at(values, f"filtered.{name}")
        if event == 2:
            check_symmetric(values, f"filtered.{name}")
            check_semidefinite(values, f"filtered.{name}",
                               advice="smooth the result a filter returned")  # fmt: skip
    if filtered.pred_covs is not None:
        check_positive_definite(_shared(filtered.pred_covs), "filtered.pred_covs", resolved=False)


def _backward(model, filtered: FilterResult, transition) -> SmootherResult:
    """The backward recursion (module docstring) of ``filtered``, from step ``T`` to the
    prior, with ``transition(k, m_k, P_k, predict) → (Cov(x_{k+1}, x_k | y_{1:k})
    [..., dx, dx], P⁻_{k+1} or None)``, asked for ``P⁻_{k+1}`` (``predict``) only where
    ``filtered`` holds no predicted covariances."""
    means = filtered.means
    steps, dx = means.shape[-2], means.shape[-1]
    m0, P0 = model.initial.mean, model.initial.cov
    # the prior as step 0, then the filtered steps 1 … T (covariances shared by every run,
    # as the filter hands them out expanded, stride 0: narrowed to one, so the covariance
    # recursion runs once, not once per run: 2,000 runs × 300 steps took 2 s and 73 MiB)
    run_shape = means.shape[:-2]
    shared = _shared(filtered.covs)
    lead = torch.broadcast_shapes(shared.shape[:-3], P0.shape[:-2])
    covs = torch.cat([P0.unsqueeze(-3).expand(lead + (1, dx, dx)),
                      shared.expand(lead + shared.shape[-3:])], -3)  # fmt: skip
    mean_seq = torch.cat([m0.unsqueeze(-2).expand(run_shape + (1, dx)), means], -2)
    pred_covs = None if filtered.pred_covs is None else _shared(filtered.pred_covs)
    smooth_m, smooth_P = [mean_seq[..., -1, :]], [covs[..., -1, :, :]]
    gains, cross = [], []
    for k in range(steps - 1, -1, -1):  # backward from k = T − 1 to the prior, k = 0
        P_k = covs[..., k, :, :]
        ahead, P_pred = transition(k, mean_seq[..., k, :], P_k, pred_covs is None)
        if pred_covs is not None:  # index k: P⁻_{k+1}, as the filter predicted
            P_pred = pred_covs[..., k, :, :]
        # G = C (P⁻)⁻¹ with C = Cov(x_k, x_{k+1}) = aheadᵀ, by a solve: Gᵀ = (P⁻)⁻¹ ahead
        G = torch.linalg.solve(P_pred, ahead).mT
        m_next, P_next = smooth_m[-1], smooth_P[-1]
        step = (G @ (m_next - filtered.pred_means[..., k, :]).unsqueeze(-1)).squeeze(-1)
        smooth_m.append(mean_seq[..., k, :] + step)
        smooth_P.append(symmetrize(P_k + G @ (P_next - P_pred) @ G.mT))
        gains.append(G)
        cross.append(G @ P_next)
    for seq in (smooth_m, smooth_P, gains, cross):
        seq.reverse()  # index k: step k (the prior first)
    cov_shape = run_shape + (dx, dx)
    # the last step's covariance may be the filter's shared one ([1, dx, dx]) where a
    # transition evaluated per run made every earlier one per run (a UKF's or an EKF's
    # smoother given a Kalman filter's result: torch.stack had failed on the shapes)
    smooth_P, gains, cross = (list(torch.broadcast_tensors(*seq)) if seq else seq
                              for seq in (smooth_P, gains, cross))  # fmt: skip
    P = torch.stack(smooth_P, -3)
    empty = means.new_zeros(run_shape + (0, dx, dx))
    return SmootherResult(
        torch.stack(smooth_m[1:], -2),
        P[..., 1:, :, :].expand(run_shape + (steps, dx, dx)),
        torch.stack(cross[1:], -3).expand(run_shape + (steps - 1, dx, dx)) if steps > 1 else empty,
        torch.stack(gains[1:], -3).expand(run_shape + (steps - 1, dx, dx)) if steps > 1 else empty,
        smooth_m[0],
        P[..., 0, :, :].expand(cov_shape),
        cross[0].expand(cov_shape),
        filtered,
    )


def _shared(covs: Tensor) -> Tensor:
    """``covs [..., T, d, d]`` with every batch dimension that is an expansion (stride 0)
    narrowed to size 1: the same numbers, broadcasting as before."""
    for dim in range(covs.dim() - 3):
        if covs.stride(dim) == 0 and covs.shape[dim] > 1:
            covs = covs.narrow(dim, 0, 1)
    return covs


def extended_kalman_smoother(
    model, ys: Tensor, us: Tensor | None = None, **filter_options
) -> SmootherResult:
    """:func:`difffilter.extended_kalman_filter` on ``ys [..., T, dy]`` (``us``, and its
    options), then the extended :func:`rts_smoother` (Jacobians at the filtered means)."""
    from .extended import extended_kalman_filter

    return rts_smoother(model, extended_kalman_filter(model, ys, us, **filter_options), us)


def kalman_smoother(
    model, ys: Tensor, us: Tensor | None = None, **filter_options
) -> SmootherResult:
    """:func:`difffilter.kalman_filter` on ``ys [..., T, dy]`` (``us``, and its options:
    ``mask``, ``nonfinite``, …), then :func:`rts_smoother`."""
    return rts_smoother(model, kalman_filter(model, ys, us, **filter_options), us)


def unscented_kalman_smoother(
    model, ys: Tensor, us: Tensor | None = None, *, sigma_points=None, **filter_options
) -> SmootherResult:
    """:func:`difffilter.unscented_kalman_filter` on ``ys [..., T, dy]`` (``us``,
    ``sigma_points`` and its options), then :func:`unscented_rts_smoother` with the same
    sigma points."""
    from .extended import unscented_kalman_filter

    filtered = unscented_kalman_filter(model, ys, us, sigma_points=sigma_points,
                                       **filter_options)  # fmt: skip
    return unscented_rts_smoother(model, filtered, us, sigma_points)
