"""The Gaussian core: every Kalman-type prediction and update of the library, once.

One step ``k−1 → k`` of a Gaussian filter is three textbook blocks::

    predict   m⁻ = F m + B u                 P⁻ = F P Fᵀ + Q                 (linear_predict)
    gain      S  = C_yy + R                  K  = C_xy S⁻¹  (Cholesky solve)   (kalman_gain)
    update    m⁺ = m⁻ + K r                  P⁺ = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ
    evidence  log p(y_k | y_{1:k−1}) = log N(r; 0, S)                       (gaussian_update)

with ``C_xy = P⁻ Hᵀ`` and ``C_yy = H P⁻ Hᵀ`` for the KF and EKF (:func:`linear_update`;
:func:`linear_innovation` and :func:`innovation_log_prob` give ``r``, ``S`` and the evidence
alone, the same numbers, for a caller that reads them before it updates; the part that does
not read ``y_k``, :func:`measurement_moments`, can be computed once and updated from
several times, :func:`moments_update`; ``evidence=False`` skips the density where nobody
reads it) and their
sigma-point estimates for the UKF. Every Gaussian update of the library takes
its pieces from here: the Kalman filter (sequential, parallel-in-time and the
shared-covariance path), the gain schedule, the EKF and UKF, the Kalman proposal of the
particle filter, Zhang's adaptive Kalman filter and the MDPF's local filters, the attack
estimators and the EKF over a network's weights. Covariances are symmetrised after every
step; unreceived measurement entries are removed exactly
(:func:`difffilter.linalg.masked_measurement`). Shapes broadcast over leading batch
dimensions: vectors ``[..., d]``, matrices ``[..., d, d]``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .linalg import (
    INNOVATION_COV,
    cholesky_solve_right,
    gaussian_log_prob_chol,
    masked_measurement,
    matvec,
    safe_cholesky,
    symmetrize,
)

__all__ = [
    "kalman_gain",
    "joseph_covariance",
    "gaussian_update",
    "update_given",
    "predict_covariance",
    "linear_predict",
    "linear_innovation",
    "innovation_log_prob",
    "linear_update",
    "MeasurementMoments",
    "measurement_moments",
    "masked_residual",
    "moments_update",
]


def kalman_gain(
    cross_cov: Tensor, innovation_cov: Tensor, mask: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Gain ``K = C S⁻¹`` by a Cholesky solve (``S`` is never inverted).

    Shapes: ``cross_cov`` ``C = Cov(x, y)`` ``[..., dx, dy]``, ``innovation_cov`` ``S``
    ``[..., dy, dy]`` (symmetrised here) → ``(K [..., dx, dy], chol(S) [..., dy, dy])``.
    ``mask [..., dy]``: the received entries of an ``S`` masked by
    :func:`~difffilter.linalg.masked_measurement` (its jitter, if any, is the received
    entries' own: :func:`~difffilter.linalg.safe_cholesky`), or ``None``.
    """
    return _gain(cross_cov, symmetrize(innovation_cov), mask)


def _gain(cross_cov: Tensor, S: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """:func:`kalman_gain` of an ``S`` symmetrised already (symmetrising twice changes no bit)."""
    chol = safe_cholesky(S, name=INNOVATION_COV, mask=mask)
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
    *,
    evidence: bool = True,
    mask: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """Measurement update shared by every Gaussian filter.

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
        evidence: compute ``log N(r; 0, S)``; ``False`` returns ``None`` in its place (a
            caller that never reads the density saves its operations).
        mask: the received entries ``[..., dy]`` (bool) that ``residual`` and
            ``noise_cov`` were masked with, or ``None`` (then a jitter of ``S`` is scaled
            by all its entries, the unit placeholders of lost ones too:
            :func:`~difffilter.linalg.safe_cholesky`).

    Returns ``(m⁺, P⁺, S, log N(r; 0, S) or None)``.
    """
    S = symmetrize(pred_obs_cov + noise_cov)
    return update_given(pred_mean, pred_cov, residual, cross_cov, S, obs_matrix, noise_cov,
                         observed, evidence, mask)  # fmt: skip


def update_given(pred_mean, pred_cov, residual, cross_cov, S, obs_matrix, noise_cov, observed,
                  evidence, mask=None):  # fmt: skip
    """:func:`gaussian_update` from its innovation covariance ``S`` (symmetrised)."""
    gain, chol = _gain(cross_cov, S, mask)  # K = C S⁻¹  [..., dx, dy]
    mean = pred_mean + matvec(gain, residual)
    cov = joseph_covariance(pred_cov, gain, obs_matrix, noise_cov)
    log_lik = gaussian_log_prob_chol(residual, chol, observed) if evidence else None
    return mean, cov, S, log_lik


def predict_covariance(cov: Tensor, transition: Tensor, process_cov: Tensor) -> Tensor:
    """``P⁻ = F P Fᵀ + Q``, symmetrised: ``[..., dx, dx]`` each (``F`` may be a Jacobian)."""
    return symmetrize(transition @ cov @ transition.transpose(-1, -2) + process_cov)


def linear_predict(
    mean: Tensor,
    cov: Tensor,
    transition: Tensor,
    process_cov: Tensor,
    control: Tensor | None = None,
    u: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """``m⁻ = F m + B u``, ``P⁻ = F P Fᵀ + Q``: ``mean [..., dx]``, ``cov [..., dx, dx]``,
    ``F [..., dx, dx]``, ``Q [..., dx, dx]``, ``B [..., dx, du]`` and ``u [..., du]`` (either
    ``None``: no input) → ``([..., dx], [..., dx, dx])``.

    (The EKF's mean comes from the model; it shares :func:`predict_covariance`.)
    """
    pred_mean = matvec(transition, mean)
    if control is not None and u is not None:
        pred_mean = pred_mean + matvec(control, u)
    return pred_mean, predict_covariance(cov, transition, process_cov)


class MeasurementMoments(NamedTuple):
    """The part of a KF/EKF update that does not read ``y_k`` (:func:`measurement_moments`).

    Attributes: ``innovation_cov`` ``S = sym(H' C + R')`` ``[..., dy, dy]``, ``cross_cov``
    ``C = P⁻H'ᵀ`` ``[..., dx, dy]``, ``obs_matrix`` ``H'`` and ``noise_cov`` ``R'`` (masked,
    :func:`~difffilter.linalg.masked_measurement`), ``observed`` (received entries, an int or
    ``[...]``) and the ``mask`` ``[..., dy]`` (or ``None``) they were computed for.
    """

    innovation_cov: Tensor
    cross_cov: Tensor
    obs_matrix: Tensor
    noise_cov: Tensor
    observed: Tensor | int
    mask: Tensor | None


def measurement_moments(
    pred_cov: Tensor, obs_matrix: Tensor, noise_cov: Tensor, mask: Tensor | None = None
) -> MeasurementMoments:
    """``S``, ``C``, ``H'``, ``R'`` of the KF/EKF update of ``P⁻ [..., dx, dx]`` with ``H
    [..., dy, dx]``, ``R [..., dy, dy]`` and ``mask [..., dy]`` (bool) or ``None``: what
    every measurement under that prediction shares (a wrapper that reads the innovation of
    ``y_k`` and then updates with a compensated ``y_k`` computes them once)."""
    _, H, R, observed = masked_measurement(None, obs_matrix, noise_cov, mask)
    cross = pred_cov @ H.transpose(-1, -2)
    return MeasurementMoments(symmetrize(H @ cross + R), cross, H, R, observed, mask)


def masked_residual(residual: Tensor, mask: Tensor | None) -> Tensor:
    """``r' = M r``: the residual ``[..., dy]`` with unreceived entries zeroed (as
    :func:`~difffilter.linalg.masked_measurement` zeroes it: by selection, so that a lost
    entry's NaN or inf is dropped, where ``r · 0`` had kept it and made the update NaN)."""
    return residual if mask is None else torch.where(mask, residual, 0.0)


def linear_innovation(
    pred_cov: Tensor, residual: Tensor, obs_matrix: Tensor, noise_cov: Tensor, mask=None
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor | int]:
    """The KF/EKF innovation moments of ``r = y − ŷ⁻`` without the posterior:
    ``(r', S, C, H', R', observed)`` with ``r'``, ``H'``, ``R'`` the masked residual, matrix
    and noise (:func:`~difffilter.linalg.masked_measurement`), ``C = P⁻H'ᵀ`` and
    ``S = sym(H' C + R')`` (the numbers :func:`linear_update` computes them with:
    :func:`measurement_moments`). Shapes as there (``mask [..., dy]`` bool or ``None``);
    ``C [..., dx, dy]``."""
    m = measurement_moments(pred_cov, obs_matrix, noise_cov, mask)
    residual = masked_residual(residual, mask)
    return residual, m.innovation_cov, m.cross_cov, m.obs_matrix, m.noise_cov, m.observed


def innovation_log_prob(
    residual: Tensor, innovation_cov: Tensor, observed: Tensor | int, mask: Tensor | None = None
) -> Tensor:
    """``log N(r; 0, S)`` ``[...]`` as :func:`gaussian_update` computes it (the same Cholesky
    factor of ``sym(S)``, the same density, ``mask`` as there): for a caller that needs the
    evidence of a measurement without its update."""
    chol = safe_cholesky(symmetrize(innovation_cov), name=INNOVATION_COV, mask=mask)
    return gaussian_log_prob_chol(residual, chol, observed)


def linear_update(
    pred_mean: Tensor,
    pred_cov: Tensor,
    residual: Tensor,
    obs_matrix: Tensor,
    noise_cov: Tensor,
    mask: Tensor | None = None,
    *,
    evidence: bool = True,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None]:
    """The KF/EKF update from ``r = y − ŷ⁻`` with ``H`` (the matrix or the Jacobian at ``m⁻``).

    ``residual [..., dy]`` (unmasked), ``obs_matrix [..., dy, dx]``, ``noise_cov [..., dy, dy]``,
    ``mask [..., dy]`` (bool) or ``None``. Returns ``(m⁺, P⁺, r', S, log N(r'; 0, S))`` with
    ``r'`` the residual with unreceived entries zeroed (the density ``None`` with
    ``evidence=False``).
    """
    moments = measurement_moments(pred_cov, obs_matrix, noise_cov, mask)
    return moments_update(pred_mean, pred_cov, residual, moments, evidence=evidence)


def moments_update(
    pred_mean: Tensor,
    pred_cov: Tensor,
    residual: Tensor,
    moments: MeasurementMoments,
    *,
    evidence: bool = True,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None]:
    """:func:`linear_update` with its :func:`measurement_moments` computed before (for the
    same ``P⁻``, ``H``, ``R`` and mask): the same numbers, bit for bit. ``residual [..., dy]``
    unmasked; returns ``(m⁺, P⁺, r', S, log N(r'; 0, S) or None)``."""
    m = moments
    residual = masked_residual(residual, m.mask)
    mean, cov, S, log_lik = update_given(
        pred_mean, pred_cov, residual, m.cross_cov, m.innovation_cov, m.obs_matrix,
        m.noise_cov, m.observed, evidence, m.mask,
    )  # fmt: skip
    return mean, cov, residual, S, log_lik
