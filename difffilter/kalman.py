"""The Kalman filter and the pieces every Gaussian filter shares.

Equations (one step, ``k−1 → k``)::

    predict   m⁻ = F m + B u                 P⁻ = F P Fᵀ + Q
    innovate  r  = y − H m⁻                  S  = H P⁻ Hᵀ + R
    gain      K  = P⁻ Hᵀ S⁻¹                 (Cholesky solve, S never inverted)
    update    m⁺ = m⁻ + K r                  P⁺ = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ   (Joseph)
    evidence  log p(y_k | y_{1:k−1}) = log N(r; 0, S)

Covariances are symmetrised after every step. Unreceived measurement entries (``mask``)
are removed exactly (:func:`difffilter.linalg.masked_measurement`). Every function is
differentiable with respect to the model's tensors and broadcasts over leading batch
dimensions. When the model's matrices carry no batch dimension and there is no mask,
the covariance recursion runs once for all runs (it does not depend on the data).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from ._checks import check_sequence_inputs, check_step_inputs
from ._shared_cov import shared_covariance_applies, shared_covariance_kalman_filter
from .linalg import (
    cholesky_solve_right,
    gaussian_log_prob_chol,
    masked_measurement,
    matvec,
    safe_cholesky,
    symmetrize,
)
from .results import FilterResult, GaussianState, GaussianStepOutput
from .ssm import StateSpaceModel

__all__ = [
    "gaussian_init",
    "gaussian_update",
    "kalman_gain",
    "joseph_covariance",
    "kalman_predict",
    "kalman_step",
    "kalman_filter",
    "run_gaussian_filter",
]


def gaussian_init(model: StateSpaceModel, batch_shape=()) -> GaussianState:
    """Prior state ``(m_0, P_0)`` of a Gaussian filter.

    ``mean`` is ``[*batch_shape, dx]``; ``cov`` keeps the prior's own shape
    ``[*, dx, dx]`` (broadcast lazily).
    """
    mean = model.initial.mean
    batch_shape = torch.Size(batch_shape)
    mean = mean.expand(torch.broadcast_shapes(batch_shape, mean.shape[:-1]) + mean.shape[-1:])
    return GaussianState(mean, model.initial.cov, 0)


def kalman_gain(cross_cov: Tensor, innovation_cov: Tensor) -> tuple[Tensor, Tensor]:
    """Gain ``K = C S⁻¹`` by a Cholesky solve (``S`` is never inverted).

    Shapes: ``cross_cov`` ``C = Cov(x, y)`` ``[..., dx, dy]``, ``innovation_cov`` ``S``
    ``[..., dy, dy]`` (symmetrised here) → ``(K [..., dx, dy], chol(S) [..., dy, dy])``.
    Every Gaussian update of the library (KF, EKF, UKF, the Kalman proposal of the PF,
    the modified PF's eq. 35, the attack estimators) takes its gain from here.
    """
    chol = safe_cholesky(symmetrize(innovation_cov), name="innovation covariance S")
    return cholesky_solve_right(cross_cov, chol), chol


def joseph_covariance(
    pred_cov: Tensor, gain: Tensor, obs_matrix: Tensor, noise_cov: Tensor
) -> Tensor:
    """Joseph-form posterior covariance ``(I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ``, symmetrised.

    Shapes: ``pred_cov [..., dx, dx]``, ``gain [..., dx, dy]``, ``obs_matrix [..., dy, dx]``,
    ``noise_cov [..., dy, dy]`` → ``[..., dx, dx]``. Positive semidefinite for any gain.
    """
    eye = torch.eye(pred_cov.shape[-1], dtype=pred_cov.dtype, device=pred_cov.device)
    i_kh = eye - gain @ obs_matrix
    cov = i_kh @ pred_cov @ i_kh.transpose(-1, -2) + gain @ noise_cov @ gain.transpose(-1, -2)
    return symmetrize(cov)


def gaussian_update(
    pred_mean: Tensor,
    pred_cov: Tensor,
    residual: Tensor,
    cross_cov: Tensor,
    pred_obs_cov: Tensor,
    obs_matrix: Tensor,
    noise_cov: Tensor,
    observed: Tensor | int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Measurement update shared by the KF, EKF and UKF.

    Args:
        pred_mean: ``m⁻`` ``[..., dx]``.
        pred_cov: ``P⁻`` ``[..., dx, dx]``.
        residual: ``r = y − ŷ`` ``[..., dy]`` (already masked).
        cross_cov: ``C = Cov(x, y)`` ``[..., dx, dy]`` (``P⁻Hᵀ`` for the KF/EKF).
        pred_obs_cov: covariance of the predicted measurement without noise
            ``[..., dy, dy]`` (``H P⁻ Hᵀ`` for the KF/EKF).
        obs_matrix: ``H`` ``[..., dy, dx]`` used by the Joseph form (the UKF passes its
            statistical linearisation ``Cᵀ P⁻⁻¹``).
        noise_cov: ``R`` ``[..., dy, dy]`` (already masked).
        observed: number of received entries (scalar or ``[...]``).

    Returns ``(m⁺, P⁺, S, log N(r; 0, S))``.
    """
    S = symmetrize(pred_obs_cov + noise_cov)
    gain, chol = kalman_gain(cross_cov, S)  # K = C S⁻¹  [..., dx, dy]
    mean = pred_mean + matvec(gain, residual)
    cov = joseph_covariance(pred_cov, gain, obs_matrix, noise_cov)
    log_lik = gaussian_log_prob_chol(residual, chol, observed)
    return mean, cov, S, log_lik


def kalman_predict(model, state: GaussianState, u: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``m⁻ = F m + B u``, ``P⁻ = F P Fᵀ + Q`` for a linear model → ``([..., dx], [..., dx, dx])``.

    ``model`` must provide ``transition_matrix(k)``, ``control_matrix(k)`` and
    ``process_cov(k)`` (as :class:`~difffilter.LinearGaussianModel` does).
    """
    k = state.k
    F = model.transition_matrix(k)
    mean = matvec(F, state.mean)
    B = model.control_matrix(k)
    if B is not None and u is not None:
        mean = mean + matvec(B, u)
    cov = symmetrize(F @ state.cov @ F.transpose(-1, -2) + model.process_cov(k))
    return mean, cov


def kalman_step(
    model, state: GaussianState, y: Tensor, u: Tensor | None = None, mask: Tensor | None = None
) -> tuple[GaussianState, GaussianStepOutput]:
    """One Kalman-filter step ``x_{k−1} → x_k`` with measurement ``y_k``.

    Args:
        model: a linear model (``transition_matrix``, ``observation_matrix``,
            ``control_matrix``, ``process_cov``, ``measurement_cov``).
        state: posterior of ``x_{k−1}`` (mean ``[..., dx]``, cov ``[..., dx, dx]``).
        y: ``[..., dy]``; u: ``[..., du]`` or ``None``; mask: ``[..., dy]`` bool or ``None``.

    The inputs are validated (:func:`difffilter._checks.check_step_inputs`): a NaN or Inf
    in a received entry of ``y`` raises ``ValueError`` instead of poisoning every later
    state. Returns the posterior of ``x_k`` and a :class:`GaussianStepOutput`.
    """
    y, u, mask = check_step_inputs(model, state.mean, y, u, mask)
    return _kalman_step(model, state, y, u, mask)


def _kalman_step(model, state, y, u=None, mask=None):
    """:func:`kalman_step` without input validation (the filters validate whole sequences)."""
    pred_mean, pred_cov = kalman_predict(model, state, u)
    k = state.k + 1
    H = model.observation_matrix(k)
    residual = y - matvec(H, pred_mean)
    residual, H, R, observed = masked_measurement(residual, H, model.measurement_cov(k), mask)
    cross = pred_cov @ H.transpose(-1, -2)
    mean, cov, S, log_lik = gaussian_update(
        pred_mean, pred_cov, residual, cross, H @ cross, H, R, observed
    )
    out = GaussianStepOutput(mean, cov, pred_mean, pred_cov, residual, S, log_lik)
    return GaussianState(mean, cov, k), out


def _validate_inputs(model, ys, us, mask, nonfinite="raise"):
    """The shared sequence checks (:func:`difffilter._checks.check_sequence_inputs`)."""
    return check_sequence_inputs(model, ys, us, mask, nonfinite=nonfinite)


def run_gaussian_filter(
    step: Callable[..., tuple[GaussianState, GaussianStepOutput]],
    model: StateSpaceModel,
    ys: Tensor,
    us: Tensor | None = None,
    mask: Tensor | None = None,
    state: GaussianState | None = None,
    *,
    nonfinite: str = "raise",
) -> FilterResult:
    """Run an online ``step`` over a whole sequence and stack its outputs.

    ``ys [..., T, dy]``, ``us [..., T, du]``, ``mask [..., T, dy]``; returns a
    :class:`FilterResult` with every field batch first. The Python loop over time is
    the only loop. ``nonfinite`` as in :func:`kalman_filter`.
    """
    ys, us, mask, skipped = _validate_inputs(model, ys, us, mask, nonfinite)
    result = _run_validated(step, model, ys, us, mask, state)
    result.nonfinite_skipped = skipped
    return result


def _run_validated(step, model, ys, us, mask, state=None) -> FilterResult:
    num_steps = ys.shape[-2]
    batch = ys.shape[:-2]
    if us is not None:
        batch = torch.broadcast_shapes(batch, us.shape[:-2])
    if mask is not None:
        batch = torch.broadcast_shapes(batch, mask.shape[:-2])
    if state is None:
        state = gaussian_init(model, batch)
    outs = []
    for t in range(num_steps):
        u = None if us is None else us[..., t, :]
        m = None if mask is None else mask[..., t, :]
        state, out = step(model, state, ys[..., t, :], u, m)
        outs.append(out)
    return _stack_outputs(outs, batch)


def _stack_outputs(outs: list[GaussianStepOutput], batch: torch.Size) -> FilterResult:
    def vec(name):
        vals = [getattr(o, name) for o in outs]
        shape = torch.broadcast_shapes(batch, *(v.shape[:-1] for v in vals))
        return torch.stack([v.expand(shape + v.shape[-1:]) for v in vals], dim=-2)

    def mat(name):
        vals = [getattr(o, name) for o in outs]
        shape = torch.broadcast_shapes(*(v.shape[:-2] for v in vals))
        stacked = torch.stack([v.expand(shape + v.shape[-2:]) for v in vals], dim=-3)
        full = torch.broadcast_shapes(batch, stacked.shape[:-3])
        return stacked.expand(full + stacked.shape[-3:])

    incs = [o.log_likelihood for o in outs]
    lshape = torch.broadcast_shapes(batch, *(v.shape for v in incs))
    increments = torch.stack([v.expand(lshape) for v in incs], dim=-1)
    return FilterResult(
        means=vec("mean"),
        covs=mat("cov"),
        pred_means=vec("pred_mean"),
        pred_covs=mat("pred_cov"),
        innovations=vec("innovation"),
        innovation_covs=mat("innovation_cov"),
        log_likelihood_increments=increments,
        log_likelihood=increments.sum(-1),
    )


def kalman_filter(
    model,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    mask: Tensor | None = None,
    method: str = "sequential",
    nonfinite: str = "raise",
) -> FilterResult:
    """Kalman filter of a linear-Gaussian model over a whole sequence.

    Args:
        model: :class:`~difffilter.LinearGaussianModel` (or any model with its matrix
            methods).
        ys: measurements ``y_1 … y_T`` ``[..., T, dy]``.
        us: inputs ``u_0 … u_{T−1}`` ``[..., T, du]`` or ``None``.
        mask: received entries ``[..., T, dy]`` (bool) or ``None`` (all received).
            Unreceived entries may be NaN.
        method: ``"sequential"`` (the online step in a loop; Joseph form) or
            ``"parallel"`` (the associative-scan filter of Särkkä & García-Fernández,
            IEEE TAC 2021: ``O(log T)`` batched operations instead of ``T`` small
            ones, fastest for a few long runs; equal to the sequential filter up to
            round-off). The sequential filter picks the shared-covariance fast path
            (:mod:`difffilter._shared_cov`) by itself when the model's matrices have no
            batch dimension, the model is time-invariant and nothing is masked: the
            covariance recursion runs once for all runs and the covariances come back
            as expanded views ``[..., T, dx, dx]`` of one ``[T, dx, dx]`` tensor.
        nonfinite: ``"raise"`` (default): a NaN or ±Inf in a received entry of ``ys``
            raises ``ValueError``; ``"skip"``: such entries are treated as unreceived
            (folded into ``mask``) and counted per run in
            ``result.nonfinite_skipped [...]``.

    Every input is validated first (shape, dtype, finiteness, mask dtype and shape,
    ``us`` batch; :func:`difffilter._checks.check_sequence_inputs`).

    Returns:
        :class:`~difffilter.results.FilterResult` (means ``[..., T, dx]``, covs
        ``[..., T, dx, dx]``, innovations, innovation covariances, log-likelihood ``[...]``).
    """
    if method not in ("sequential", "parallel"):
        raise ValueError(f"method must be 'sequential' or 'parallel'; got {method!r}")
    ys, us, mask, skipped = _validate_inputs(model, ys, us, mask, nonfinite)
    if method == "parallel":
        from .parallel_kalman import parallel_kalman_filter

        result = parallel_kalman_filter(model, ys, us, mask)
    elif shared_covariance_applies(model, mask):
        # one unbatched LTI model, nothing masked: covariances once for all runs
        result = shared_covariance_kalman_filter(model, ys, us)
    else:
        result = _run_validated(_kalman_step, model, ys, us, mask)
    result.nonfinite_skipped = skipped
    return result
