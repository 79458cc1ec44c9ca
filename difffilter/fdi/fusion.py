"""Fusion of two local estimates: covariance intersection and naive information fusion.

The lidar-robot letter fuses the local estimates ``(x̂₁, P₁)``, ``(x̂₂, P₂)`` (and the
attack estimates ``(â₁, S₁)``, ``(â₂, S₂)``) by a rule stated in its main text, which is
not among our sources. Two rules are provided:

* **Covariance intersection** (Julier & Uhlmann 1997), consistent for any unknown
  cross-covariance of the two local errors (the locals share the process noise)::

      P_f⁻¹ = ω P₁⁻¹ + (1 − ω) P₂⁻¹,   x̂_f = P_f (ω P₁⁻¹ x̂₁ + (1 − ω) P₂⁻¹ x̂₂),
      ω = argmin_{ω ∈ [0, 1]} tr P_f(ω)

  ``tr P_f(ω)`` is convex in ``ω`` (the trace of the inverse of a positive-definite
  matrix affine in ``ω``); a batched golden-section search finds the minimiser to
  ``0.618^iterations`` (6e-7 for the default 30 iterations).
* **Naive information fusion** (the ablation), exact only for independent local errors::

      P_f⁻¹ = P₁⁻¹ + P₂⁻¹,   x̂_f = P_f (P₁⁻¹ x̂₁ + P₂⁻¹ x̂₂)

Shapes: ``means [..., 2, d]``, ``covs [..., 2, d, d]`` (the two locals on the
second-to-last batch dimension) → ``mean [..., d]``, ``cov [..., d, d]`` and, for CI,
``omega [...]``. Any leading dimensions (runs, time) are fused at once.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..linalg import matvec, symmetrize

__all__ = ["covariance_intersection", "information_fusion", "FUSION_RULES", "fuse"]

_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def _check_pair(means: Tensor, covs: Tensor) -> None:
    if means.dim() < 2 or means.shape[-2] != 2:
        raise ValueError(
            f"means must have shape [..., 2, d] (two local estimates); got {tuple(means.shape)}"
        )
    d = means.shape[-1]
    if covs.shape[-3:] != (2, d, d):
        raise ValueError(f"covs must have shape [..., 2, {d}, {d}]; got {tuple(covs.shape)}")


def _fused(info: Tensor, means: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """``P_f = (Σ wᵢ Iᵢ)⁻¹``, ``x̂_f = P_f Σ wᵢ Iᵢ x̂ᵢ`` for ``info [..., 2, d, d]``, ``w [..., 2]``."""
    wi = w[..., None, None] * info
    total = symmetrize(wi.sum(-3))
    cov = symmetrize(torch.linalg.inv(total))
    mean = matvec(cov, matvec(wi, means).sum(-2))
    return mean, cov


def covariance_intersection(
    means: Tensor, covs: Tensor, *, iterations: int = 30
) -> tuple[Tensor, Tensor, Tensor]:
    """Covariance intersection of two estimates (module docstring) → ``(mean, cov, ω)``."""
    _check_pair(means, covs)
    info = torch.linalg.inv(covs)

    def trace(omega):
        w = torch.stack((omega, 1.0 - omega), -1)
        total = (w[..., None, None] * info).sum(-3)
        return torch.linalg.inv(total).diagonal(dim1=-2, dim2=-1).sum(-1)

    lo = means.new_zeros(means.shape[:-2])
    hi = torch.ones_like(lo)
    a = hi - _GOLDEN * (hi - lo)
    b = lo + _GOLDEN * (hi - lo)
    fa, fb = trace(a), trace(b)
    for _ in range(iterations):  # one new evaluation per iteration and row
        left = fa < fb  # the minimum lies in [lo, b]: b ← a, a ← new; else a ← b, b ← new
        hi = torch.where(left, b, hi)
        lo = torch.where(left, lo, a)
        new = torch.where(left, hi - _GOLDEN * (hi - lo), lo + _GOLDEN * (hi - lo))
        f_new = trace(new)
        a, b = torch.where(left, new, b), torch.where(left, a, new)
        fa, fb = torch.where(left, f_new, fb), torch.where(left, fa, f_new)
    omega = 0.5 * (lo + hi)
    mean, cov = _fused(info, means, torch.stack((omega, 1.0 - omega), -1))
    return mean, cov, omega


def information_fusion(means: Tensor, covs: Tensor) -> tuple[Tensor, Tensor]:
    """Naive information fusion ``P_f⁻¹ = P₁⁻¹ + P₂⁻¹`` (module docstring) → ``(mean, cov)``."""
    _check_pair(means, covs)
    info = torch.linalg.inv(covs)
    return _fused(info, means, means.new_ones(means.shape[:-1]))


#: The fusion rules by name (what the estimators and tests select).
FUSION_RULES = ("ci", "naive")


def fuse(means: Tensor, covs: Tensor, rule: str = "ci") -> tuple[Tensor, Tensor]:
    """``(mean, cov)`` of the two estimates by ``rule`` (``"ci"`` or ``"naive"``)."""
    if rule == "ci":
        mean, cov, _ = covariance_intersection(means, covs)
        return mean, cov
    if rule == "naive":
        return information_fusion(means, covs)
    raise ValueError(f"rule must be one of {FUSION_RULES}; got {rule!r}")
