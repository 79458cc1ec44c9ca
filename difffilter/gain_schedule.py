"""Online Kalman filtering of many runs of one time-invariant linear model with a shared gain.

Without lost measurements the Kalman covariance recursion of :func:`difffilter.kalman_step`

    P⁻_k = F P_{k−1} Fᵀ + Q,   S_k = H P⁻_k Hᵀ + R,   K_k = P⁻_k Hᵀ S_k⁻¹,
    P_k  = (I − K_k H) P⁻_k (I − K_k H)ᵀ + K_k R K_kᵀ

does not depend on the data: :class:`GainSchedule` runs it once, by
:func:`difffilter.kalman_step` itself on a single unbatched state (no gradient), and keeps
``K_k`` and ``S_k``. What remains per run is linear in the data,

    m⁻_k = F m_{k−1} + B u_{k−1}                                    (:meth:`GainSchedule.predict`)
    ν_k  = y_k − H m⁻_k,   m_k = m⁻_k + K_k ν_k                    (:meth:`GainSchedule.update`)

and is the Kalman filter's exactly (tested against :func:`difffilter.kalman_filter`), for
any batch of runs, differentiably with respect to ``m``, ``y`` and ``u``. This is the
online counterpart of the whole-sequence shared-covariance path of
:func:`difffilter.kalman_filter`: for closed loops, where ``u_k`` depends on ``m_k`` and
the sequence is not known in advance (the LFC secure controller feeds the compensated
estimate back). Once the gain has converged (largest relative change of ``K`` at most
``tol``) the last one is reused for every later step.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .kalman import gaussian_init, kalman_gain, kalman_step
from .linalg import matvec

__all__ = ["GainSchedule"]


class GainSchedule:
    """The data-independent gains ``K_k [dx, dy]`` and innovation covariances ``S_k [dy, dy]``
    of a linear model's Kalman filter, computed on first use and cached.

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
        mats = (model.transition_matrix(0), model.observation_matrix(1), model.initial.cov)
        if any(m.dim() != 2 for m in mats) or model.initial.mean.dim() != 1:
            raise ValueError("model's matrices and prior must carry no batch dimension")
        if not tol >= 0:
            raise ValueError(f"tol must be >= 0; got {tol!r}")
        self.model, self.tol = model, float(tol)
        self.F, self.H, self.B = mats[0], mats[1], model.control_matrix(0)
        dy, dx = self.H.shape
        eye = torch.eye(dx, dtype=self.H.dtype, device=self.H.device)
        # H = I (a fully measured state) saves a product per step
        self._identity_h = dx == dy and bool(torch.equal(self.H, eye))
        self._gains: list[Tensor] = []
        self._covs: list[Tensor] = []
        self._state = gaussian_init(model)
        self.converged = False

    def gain(self, k: int) -> tuple[Tensor, Tensor]:
        """``(K_k [dx, dy], S_k [dy, dy])`` of measurement ``k ≥ 1``."""
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueError(f"k must be an integer >= 1 (the measurement index); got {k!r}")
        while len(self._gains) < k and not self.converged:
            dy = self.H.shape[0]
            y0 = self.H.new_zeros(dy)  # the covariances do not depend on the data
            u0 = None if self.B is None else self.B.new_zeros(self.B.shape[-1])
            with torch.no_grad():
                self._state, out = kalman_step(self.model, self._state, y0, u0)
            K, _ = kalman_gain(out.pred_cov @ self.H.T, out.innovation_cov)
            if self._gains:
                prev = self._gains[-1]
                change = float((K - prev).abs().max())
                self.converged = change <= self.tol * float(prev.abs().max())
            self._gains.append(K)
            self._covs.append(out.innovation_cov)
        i = min(k, len(self._gains)) - 1
        return self._gains[i], self._covs[i]

    def predict(self, mean: Tensor, u: Tensor | None = None) -> Tensor:
        """``m⁻ = F m + B u``: ``mean [..., dx]``, ``u [..., du]`` or ``None`` → ``[..., dx]``."""
        pred = matvec(self.F, mean)
        if u is not None and self.B is not None:
            pred = pred + matvec(self.B, u)
        return pred

    def update(self, pred_mean: Tensor, y: Tensor, k: int) -> tuple[Tensor, Tensor, Tensor]:
        """``(m_k, ν_k, S_k)``: ``pred_mean [..., dx]``, ``y [..., dy]`` → ``[..., dx]``,
        ``[..., dy]``, ``[dy, dy]`` (shared by the runs)."""
        K, S = self.gain(k)
        innovation = y - (pred_mean if self._identity_h else matvec(self.H, pred_mean))
        return pred_mean + matvec(K, innovation), innovation, S
