"""Attack-value estimation γ̂_k for the modified PF's estimation mode (Table 2, step 3-0).

The paper defers to the observer of its ref. [39]; here a Kalman filter on the attack
model of eq. (4) plays that role. With the augmented state ``θ_k = [γ_k; γ̄]``::

    θ_{k+1} = [[τ I, (1 − τ) I], [0, I]] θ_k + ω_k,     ω_k ~ N(0, diag(q_γ I, q_γ̄ I))
    r_k     = [I 0] θ_k + e_k,                          e_k ~ N(0, S_k)      (only when l̂_k = 1)

where the "measurement" is the flagged residual ``r_k = ỹ_k − ŷ_{k|k−1}`` of the
attack-compensated filter (its predicted measurement), whose noise covariance ``S_k`` is
that filter's predictive measurement covariance (particle covariance of ``G x`` plus
``R``). Unflagged steps only predict. The prior is ``γ_0 = 0`` (eq. 4) and ``γ̄ ~ N(0,
v I)`` ([DEF] ``v = 1``); ``τ`` is assumed known (part of the attack model, eq. 4).
"""

from __future__ import annotations

import numbers

import torch
from torch import Tensor

from .._checks import broadcast_or_none, check_covariance, check_integer
from ..gaussian import gaussian_update
from ..kalman import _kalman_predict
from ..linalg import masked_measurement, matvec
from ..results import GaussianState
from ..ssm import LinearGaussianModel

__all__ = ["BiasAttackEstimator"]


class BiasAttackEstimator:
    """Kalman filter on ``[γ_k; γ̄]`` (eq. 4) fed by the residuals of flagged steps.

    Args:
        dim: measurement dimension ``dy``.
        tau: ``τ`` of eq. (4), in ``(0, 1)``.
        gamma_bar_var: prior variance ``v`` of each entry of ``γ̄`` [DEF 1.0].
        process_var: ``(q_γ, q_γ̄)`` random-walk variances that let the estimate follow a
            model mismatch [DEF 1e-6 each].
        dtype, device: of the filter's tensors.

    Usage (batched over runs ``[...]``)::

        est = BiasAttackEstimator(4, 0.9)
        state = est.init((B,))
        state, gamma_hat, gamma_cov = est.step(state, residual, residual_cov, flag)
    """

    def __init__(
        self,
        dim: int,
        tau: float,
        *,
        gamma_bar_var: float = 1.0,
        process_var: tuple[float, float] = (1e-6, 1e-6),
        dtype: torch.dtype = torch.float64,
        device=None,
    ):
        dim = check_integer(dim, "dim", 1)
        if not gamma_bar_var > 0:
            raise ValueError(f"gamma_bar_var must be > 0; got {gamma_bar_var!r}")
        q_g, q_b = process_var
        if not (q_g > 0 and q_b > 0):
            raise ValueError(f"process_var must be two numbers > 0; got {process_var!r}")
        object.__setattr__(self, "dim", dim)
        self._settings = (float(gamma_bar_var), float(q_g), float(q_b), dtype, device)
        self.tau = tau  # (checked, and the model built, by __setattr__)

    def __setattr__(self, name, value):
        # τ is built into F: assigned after construction it had been stored and never read
        # (γ̂ of τ = 0.9 after tau = 0.1; and tau = 5 accepted): checked and the model built
        # again, as the constructor builds it. dim is the states' size: not reassignable.
        if name == "dim":
            raise AttributeError(
                "dim is the size of this estimator's states: build a new BiasAttackEstimator"
            )
        if name == "tau":
            tau = value
            if isinstance(tau, bool) or not isinstance(tau, numbers.Real) or not 0.0 < tau < 1.0:
                raise ValueError(f"tau must lie in (0, 1) (eq. 4); got {tau!r}")
            value = float(tau)
            super().__setattr__("model", self._model(value))
        elif name == "model" and "model" in self.__dict__:
            raise AttributeError("model follows tau: assign tau instead")
        super().__setattr__(name, value)

    def _model(self, tau: float) -> LinearGaussianModel:
        """Eq. (4)'s augmented model for ``τ`` and this estimator's other settings."""
        dim = self.dim
        gamma_bar_var, q_g, q_b, dtype, device = self._settings
        kw = {"dtype": dtype, "device": device}
        eye, zero = torch.eye(dim, **kw), torch.zeros(dim, dim, **kw)
        F = torch.cat([torch.cat([tau * eye, (1.0 - tau) * eye], 1), torch.cat([zero, eye], 1)], 0)
        H = torch.cat([eye, zero], 1)
        Q = torch.block_diag(q_g * eye, q_b * eye)
        # γ_0 = 0 is known (eq. 4): a tiny variance keeps P0 positive definite
        P0 = torch.block_diag(1e-12 * eye, gamma_bar_var * eye)
        return LinearGaussianModel(F, H, Q, eye, torch.zeros(2 * dim, **kw), P0)

    def init(self, batch_shape=()) -> GaussianState:
        """Prior of ``θ_0``: mean ``[*batch, 2 dy]`` (zeros), covariance ``[2 dy, 2 dy]``."""
        mean = self.model.initial.mean.expand(torch.Size(batch_shape) + (2 * self.dim,))
        # own tensors (as gaussian_init's): views of the prior had been written through by a
        # state written in place, moving every run's start and every later init (a review)
        return GaussianState(mean.clone(), self.model.initial.cov.clone(), 0)

    def step(
        self, state: GaussianState, residual: Tensor, residual_cov: Tensor, flag: Tensor
    ) -> tuple[GaussianState, Tensor, Tensor]:
        """Predict ``θ_k`` and, where ``flag [...]`` is set, update with ``residual [..., dy]``.

        ``flag`` is ``[...]`` or, per entry, ``[..., dy]``; ``residual_cov [..., dy, dy]`` is
        ``S_k``. Returns the new state, ``γ̂_k = E[γ_k]``
        ``[..., dy]`` and its covariance ``[..., dy, dy]``.
        """
        d = self.dim
        for name, value in (("residual", residual), ("residual_cov", residual_cov), ("flag", flag)):
            if not isinstance(value, Tensor):
                raise TypeError(f"{name} must be a torch.Tensor; got {type(value).__name__}")
        own = self.model.initial.mean
        for name, value in (("residual", residual), ("residual_cov", residual_cov)):
            if (value.dtype, value.device) != (own.dtype, own.device):
                # (torch's "expected scalar type Float but found Double" had named neither;
                # the other way round, γ̂ came back in the residual's dtype, silently)
                raise ValueError(
                    f"{name} is {value.dtype} on {value.device} and this estimator "
                    f"{own.dtype} on {own.device}: give the residuals in the estimator's dtype, "
                    f"or build it with BiasAttackEstimator(..., dtype={value.dtype})"
                )
        if residual.shape[-1] != d or residual_cov.shape[-2:] != (d, d):
            raise ValueError(
                f"residual must be [..., {d}] and residual_cov [..., {d}, {d}]; "
                f"got {tuple(residual.shape)}, {tuple(residual_cov.shape)}"
            )
        runs = residual.shape[:-1]
        target = residual.shape if flag.dim() == residual.dim() else runs  # (_flagged's reading)
        if flag.dim() > residual.dim() or broadcast_or_none(flag.shape, target) != target:
            # (a raw expand error had come from _flagged)
            raise ValueError(
                f"flag must be one per run {list(runs)} or one per entry {list(residual.shape)} "
                f"(or broadcast to one of them); got {list(flag.shape)}"
            )
        if flag.dtype != torch.bool and not bool(((flag == 0) | (flag == 1)).all()):
            # (.bool() had read a probability of 0.3 as an attacked step, silently)
            raise ValueError("flag must be bool or 0/1 (True = the step, or entry, is attacked)")
        mask = self._flagged(flag, residual)
        # a NaN residual on a flagged entry had made γ̂ NaN at that step and every later one;
        # an entry not flagged is never read (zeroed: 0 · NaN would still be NaN)
        residual = residual.where(mask, 0.0)
        if not bool(torch.isfinite(residual.detach()).all()):
            raise ValueError("residual contains NaN or Inf values on flagged entries")
        check_covariance(
            residual_cov, "residual_cov", advice="give S_k of the filter whose residual it is"
        )
        return self._update(state, residual, residual_cov, mask)

    @staticmethod
    def _flagged(flag: Tensor, residual: Tensor) -> Tensor:
        """``flag`` as the ``[..., dy]`` bool mask of the updated entries: one flag per run,
        or one per entry (an attacked step's received entries)."""
        mask = flag.bool()
        return (mask if mask.dim() == residual.dim() else mask.unsqueeze(-1)).expand(residual.shape)

    def _update(
        self, state: GaussianState, residual: Tensor, residual_cov: Tensor, mask: Tensor
    ) -> tuple[GaussianState, Tensor, Tensor]:
        """:meth:`step` on checked inputs (``mask``: :meth:`_flagged`), as a filter that
        feeds it its own residuals calls it."""
        d = self.dim
        pred_mean, pred_cov = _kalman_predict(self.model, state)
        H = self.model.H
        innov = residual - matvec(H, pred_mean)
        innov, Hm, Rm, observed = masked_measurement(innov, H, residual_cov, mask)
        cross = pred_cov @ Hm.transpose(-1, -2)
        mean, cov, _, _ = gaussian_update(
            pred_mean,
            pred_cov,
            innov,
            cross,
            Hm @ cross,
            Hm,
            Rm,
            observed,
            evidence=False,
            mask=mask,
        )
        return GaussianState(mean, cov, state.k + 1), mean[..., :d], cov[..., :d, :d]
