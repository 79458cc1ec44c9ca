"""The data-independent gains of a time-invariant linear model, shared by every run.

Without lost measurements the Kalman covariance recursion

    P⁻_k = F P_{k−1} Fᵀ + Q,   S_k = H P⁻_k Hᵀ + R,   K_k = P⁻_k Hᵀ S_k⁻¹,
    P_k  = (I − K_k H) P⁻_k (I − K_k H)ᵀ + K_k R K_kᵀ

does not depend on the data: :class:`GainSchedule` runs it once, with the Gaussian core
(:mod:`difffilter.gaussian`) on unbatched ``[dx, dx]`` matrices, and keeps every step's
moments. What remains per run is linear in the data,

    m⁻_k = F m_{k−1} + B u_{k−1}                                    (:meth:`GainSchedule.predict`)
    ν_k  = y_k − H m⁻_k,   m_k = m⁻_k + K_k ν_k                    (:meth:`GainSchedule.update`)

and is the Kalman filter's exactly (tested against :func:`difffilter.kalman_filter`), for
any batch of runs, differentiably with respect to ``m``, ``y`` and ``u``. The online
counterpart of the whole-sequence shared-covariance path of
:func:`difffilter.kalman_filter`: :class:`~difffilter.KalmanFilter` uses it by itself
for an unbatched time-invariant model, so a closed loop (where ``u_k`` depends on the
estimate) pays the covariance recursion once, not once per step of every loop. Once the
gain has converged (largest relative change of ``K`` at most ``tol``) the last moments
are reused for every later step.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .gaussian import joseph_covariance, kalman_gain, predict_covariance
from .linalg import LOG_2PI, matvec, symmetrize

__all__ = ["GainSchedule", "SharedMoments", "shared_gains_apply"]


class SharedMoments(NamedTuple):
    """The moments of measurement ``k`` shared by every run: ``pred_cov`` ``P⁻_k``, ``cov``
    ``P_k`` ``[dx, dx]``, ``gain`` ``K_k [dx, dy]``, ``innovation_cov`` ``S_k``, its
    Cholesky factor ``chol`` ``L_k``, the whitening ``whiten = L_k⁻¹`` ``[dy, dy]`` and
    ``log_norm = Σ log diag L_k + (dy/2) log 2π`` (so ``log N(ν; 0, S_k) =
    −½‖L_k⁻¹ν‖² − log_norm``: one product per step for all runs)."""

    pred_cov: Tensor
    cov: Tensor
    gain: Tensor
    innovation_cov: Tensor
    chol: Tensor
    whiten: Tensor
    log_norm: Tensor


def shared_gains_apply(model) -> bool:
    """Whether ``model`` is a time-invariant linear model whose matrices and prior carry no
    batch dimension (its gains are then the same for every run)."""
    needed = ("transition_matrix", "observation_matrix", "control_matrix", "process_cov")
    if not all(hasattr(model, name) for name in needed) or getattr(model, "time_varying", False):
        return False
    mats = (model.transition_matrix(0), model.observation_matrix(1), model.initial.cov)
    return all(m.dim() == 2 for m in mats) and model.initial.mean.dim() == 1


class GainSchedule:
    """The data-independent moments (:class:`SharedMoments`) of a linear model's Kalman
    filter, computed on first use and cached.

    Args:
        model: a time-invariant linear model (``transition_matrix``, ``observation_matrix``,
            ``process_cov``, ``measurement_cov``, ``control_matrix``; e.g.
            :class:`~difffilter.LinearGaussianModel`) whose matrices and prior carry no batch
            dimension.
        tol: relative change of ``K`` below which the gain counts as converged.
    """

    def __init__(self, model, *, tol: float = 1e-12):
        needed = ("transition_matrix", "observation_matrix", "control_matrix", "process_cov")
        missing = [name for name in needed if not hasattr(model, name)]
        if missing:
            raise ValueError(f"model must be linear (it lacks {', '.join(missing)})")
        if getattr(model, "time_varying", False):
            raise ValueError("model must be time-invariant (its gains are shared by every step)")
        if not shared_gains_apply(model):
            raise ValueError("model's matrices and prior must carry no batch dimension")
        if not tol >= 0:
            raise ValueError(f"tol must be >= 0; got {tol!r}")
        self.model, self.tol = model, float(tol)
        self.F, self.H, self.B = (
            model.transition_matrix(0),
            model.observation_matrix(1),
            model.control_matrix(0),
        )
        self.Q, self.R = model.process_cov(0), model.measurement_cov(1)
        dy, dx = self.H.shape
        eye = torch.eye(dx, dtype=self.H.dtype, device=self.H.device)
        # H = I (a fully measured state) saves a product per step
        self._identity_h = dx == dy and bool(torch.equal(self.H, eye))
        self._moments: list[SharedMoments] = []
        self._cov = model.initial.cov
        self.converged = False

    def moments(self, k: int) -> SharedMoments:
        """The :class:`SharedMoments` of measurement ``k ≥ 1``."""
        known = self._moments
        if type(k) is int and 1 <= k <= len(known):  # computed already: every step after the first
            return known[k - 1]
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueError(f"k must be an integer >= 1 (the measurement index); got {k!r}")
        with torch.no_grad():
            while len(self._moments) < k and not self.converged:
                self._extend()
        return self._moments[min(k, len(self._moments)) - 1]

    def _extend(self) -> None:
        pred_cov = predict_covariance(self._cov, self.F, self.Q)
        cross = pred_cov @ self.H.T
        S = symmetrize(self.H @ cross + self.R)
        K, chol = kalman_gain(cross, S)
        self._cov = joseph_covariance(pred_cov, K, self.H, self.R)
        if self._moments:
            prev = self._moments[-1].gain
            change = float((K - prev).abs().max())
            self.converged = change <= self.tol * float(prev.abs().max())
        eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
        whiten = torch.linalg.solve_triangular(chol, eye, upper=False)
        log_norm = torch.log(torch.diagonal(chol)).sum() + 0.5 * S.shape[-1] * LOG_2PI
        self._moments.append(SharedMoments(pred_cov, self._cov, K, S, chol, whiten, log_norm))

    def gain(self, k: int) -> tuple[Tensor, Tensor]:
        """``(K_k [dx, dy], S_k [dy, dy])`` of measurement ``k ≥ 1``."""
        m = self.moments(k)
        return m.gain, m.innovation_cov

    def predict(self, mean: Tensor, u: Tensor | None = None) -> Tensor:
        """``m⁻ = F m + B u``: ``mean [..., dx]``, ``u [..., du]`` or ``None`` → ``[..., dx]``."""
        pred = matvec(self.F, mean)
        if u is not None and self.B is not None:
            pred = pred + matvec(self.B, u)
        return pred

    def innovation(self, pred_mean: Tensor, y: Tensor) -> Tensor:
        """``ν = y − H m⁻`` ``[..., dy]``."""
        return y - (pred_mean if self._identity_h else matvec(self.H, pred_mean))

    def update(self, pred_mean: Tensor, y: Tensor, k: int) -> tuple[Tensor, Tensor, Tensor]:
        """``(m_k, ν_k, S_k)``: ``pred_mean [..., dx]``, ``y [..., dy]`` → ``[..., dx]``,
        ``[..., dy]``, ``[dy, dy]`` (shared by the runs)."""
        m = self.moments(k)
        innovation = self.innovation(pred_mean, y)
        return pred_mean + matvec(m.gain, innovation), innovation, m.innovation_cov
