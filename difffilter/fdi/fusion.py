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
  ``0.618^iterations`` (6e-7 for the default 30 iterations) in float64; in float32 the
  trace is too flat about its minimum for its round-off to tell the candidates apart
  (``ω`` within 5e-4 in a trial, the fused mean off by as much). Where ``ω = ½`` is as good
  (equal local covariances: every ``ω`` is), ``ω = ½``, so the rule is symmetric in its
  two locals (the search had drifted to ``ω = 1``: local 1 alone). Differentiable,
  ``ω`` included: the search runs on values, and ``ω``'s derivative is the implicit
  function theorem's at the minimiser, ``dω = −d(J′)/J″`` with ``J′ = −tr(P_f A P_f)``,
  ``J″ = 2 tr(P_f A P_f A P_f)``, ``A = P₁⁻¹ − P₂⁻¹`` (0 where the minimiser is a bound of
  ``[0, 1]``: ``J′(0) ≥ 0`` or ``J′(1) ≤ 0``; a fusion trial's chain KF → CI → loss had the
  wrong sign, ``ω`` held constant). First derivatives, reverse and forward mode.
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

from .._checks import Choice, _vmapped, check_symmetric, cholesky_fails
from ..linalg import matvec, symmetrize, under_transform
from . import _components as C

__all__ = ["covariance_intersection", "information_fusion", "FusionRule", "fuse"]

_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def _check_pair(means: Tensor, covs: Tensor) -> None:
    """Two local estimates: ``means [..., 2, d]`` finite, ``covs [..., 2, d, d]`` symmetric
    positive definite (a singular or NaN one gave NaN for d ≤ 3 and torch's own error,
    naming nothing, beyond)."""
    for name, t in (("means", means), ("covs", covs)):
        if not isinstance(t, Tensor) or not t.is_floating_point():
            raise TypeError(f"{name} must be a floating-point torch.Tensor; got "
                            f"{getattr(t, 'dtype', type(t).__name__)}")  # fmt: skip
    if means.dtype != covs.dtype or means.device != covs.device:
        # (torch had promoted silently: a float32 covariance fused in float64 with the means)
        raise ValueError(
            f"means and covs must share one dtype and device; got means {means.dtype} on "
            f"{means.device}, covs {covs.dtype} on {covs.device}"
        )
    if means.dim() < 2 or means.shape[-2] != 2:
        raise ValueError(
            f"means must have shape [..., 2, d] (two local estimates); got {tuple(means.shape)}"
        )
    d = means.shape[-1]
    if covs.shape[-3:] != (2, d, d):
        raise ValueError(f"covs must have shape [..., 2, {d}, {d}]; got {tuple(covs.shape)}")
    if under_transform(means, covs):  # (vmap and the like: their values cannot be read)
        return
    if not bool(torch.isfinite(means).all()) or not bool(torch.isfinite(covs).all()):
        raise ValueError("means and covs must be finite (a NaN or Inf local estimate)")
    check_symmetric(covs, "covs")
    if bool(cholesky_fails(covs).any()):  # (float32's alone is the CPU's: cholesky_fails)
        raise ValueError(
            "covs must be positive definite: a local covariance is singular or indefinite (a "
            "local estimate of no uncertainty in some direction cannot be fused by its inverse)"
        )


def _information(covs: Tensor) -> Tensor:
    """``covs⁻¹`` where the pair check's Cholesky passed: a float32 covariance of condition
    beyond 1/ε (≈ 1.7e7) can factorise and still fail to invert, and torch's error ("The
    diagonal element 2 is zero") named neither ``covs`` nor the dtype (a trial)."""
    info, status = torch.linalg.inv_ex(covs)
    if not under_transform(covs) and bool((status != 0).any()):
        raise ValueError(
            f"covs must be positive definite to fuse by their inverses: a local covariance "
            f"cannot be inverted in {str(covs.dtype).removeprefix('torch.')} (its condition "
            "number is beyond the dtype's precision; float64 may hold it)"
        )
    return info


def _fused(info: Tensor, means: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """``P_f = (Σ wᵢ Iᵢ)⁻¹``, ``x̂_f = P_f Σ wᵢ Iᵢ x̂ᵢ`` for ``info [..., 2, d, d]``, ``w [..., 2]``."""
    wi = w[..., None, None] * info
    total = symmetrize(wi.sum(-3))
    cov = symmetrize(torch.linalg.inv(total))
    mean = matvec(cov, matvec(wi, means).sum(-2))
    return mean, cov


# -- d ≤ 3 by hand ----------------------------------------------------------------------
# The locals' covariances are 3×3 (state) and 2×2 (attack): batched torch.linalg calls on
# such matrices cost ~100 ns per matrix plus a dispatch each, and the golden-section
# search makes 32 of them. Written entry by entry (difffilter.fdi._components) a trace
# evaluation is ~20 elementwise kernels: the same formulas, the same result up to
# round-off (tested against the torch.linalg route, which larger d still takes).

_HAND_MAX_DIM = 3

#: The adjugate's error grows as cond² ε where the LU route's grows as cond ε (2× at a
#: Hadamard ratio det P / Π P_ii of 1e-2, 15× at 3e-5; 1e4 in float32 gave 2e-3 against 2e-4,
#: and cond 1e12 in float64 a fused mean 103 % off: a trial): below this ratio, or where the
#: determinant leaves the dtype's range (float32 covariances of 1e13 or 1e-14 had fused to
#: NaN), the locals take the torch.linalg route.
_HAND_MIN_RATIO = 1e-2


def _by_hand(covs: Tensor, d: int) -> bool:
    """Whether the two locals' ``covs [..., 2, d, d]`` take the by-hand route: ``d ≤ 3``,
    each one's Hadamard ratio ``det P / Π P_ii`` at least :data:`_HAND_MIN_RATIO` and its
    determinant a normal number of the dtype (one read)."""
    if d > _HAND_MAX_DIM:
        return False
    if d == 1 or _vmapped(covs):
        return True  # (under vmap no value can choose a route: the by-hand one, as before)
    # under grad, jacrev or jacfwd the values can be read, and choose as the plain call does
    # (every torch.func level had taken the by-hand route: a fused mean 17–225 % off and its
    # gradient wrong for cond 1e10–1e12 in float64, where the plain call is right: a
    # red-team trial)
    with torch.no_grad():
        det = torch.linalg.det(covs.detach())
        ratio = det / covs.detach().diagonal(dim1=-2, dim2=-1).prod(-1)
        normal = det.abs() >= torch.finfo(det.dtype).tiny
        return bool((normal & torch.isfinite(det) & (ratio >= _HAND_MIN_RATIO)).all())


def _local_entries(covs: Tensor, d: int):
    """Upper-triangle component views of the two locals' ``covs [..., 2, d, d]``."""
    return [[[covs[..., n, i, j] if j >= i else None for j in range(d)] for i in range(d)]
            for n in range(2)]  # fmt: skip


def _weighted(info, w0, w1, d: int):
    """``w₀ I₀ + w₁ I₁`` (upper triangle) of the locals' information components."""
    return [[C.lin(((1.0, info[0][i][j], w0), (1.0, info[1][i][j], w1))) if j >= i else None
             for j in range(d)] for i in range(d)]  # fmt: skip


def _trace_inverse(a, d: int) -> Tensor:
    """``tr A⁻¹`` of a symmetric ``d × d`` component matrix (``d ≤ 3``, upper triangle
    read): the sum of the principal cofactors over the determinant."""
    cof, det = C.cofactors(a)
    return C.lin((1.0, cof[i][i], 1.0) for i in range(d)) / det


def _fused_by_hand(info, means: Tensor, w0, w1, d: int) -> tuple[Tensor, Tensor]:
    """:func:`_fused` on components: ``info`` the two locals' information matrices
    (component lists), ``w0``, ``w1`` the weights (``[...]`` tensors or numbers)."""
    cov, _ = C.sym_inverse(_weighted(info, w0, w1, d))
    ws = (w0, w1)
    # Σ wᵢ Iᵢ x̂ᵢ, then P_f times it
    ix = [[C.lin((1.0, info[n][r][c], means[..., n, c]) for c in range(d)) for r in range(d)]
          for n in range(2)]  # fmt: skip
    rhs = [C.lin((1.0, ix[n][r], ws[n]) for n in range(2)) for r in range(d)]
    mean = [C.lin((1.0, cov[r][c], rhs[c]) for c in range(d)) for r in range(d)]
    return torch.stack(mean, -1), C.from_components(cov)


def _local_information(covs: Tensor, d: int):
    """The two locals' ``Pᵢ⁻¹`` as full component matrices (``out[j][i] is out[i][j]``)."""
    return [C.sym_inverse(m)[0] for m in _local_entries(covs, d)]


def covariance_intersection(
    means: Tensor, covs: Tensor, *, iterations: int = 30
) -> tuple[Tensor, Tensor, Tensor]:
    """Covariance intersection of two estimates (module docstring) → ``(mean, cov, ω)``."""
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        # (-1 returned ω = 0.5 unsearched)
        raise ValueError(f"iterations must be an integer >= 1; got {iterations!r}")
    _check_pair(means, covs)
    d = means.shape[-1]
    hand = _by_hand(covs, d)
    if hand:
        info = _local_information(covs, d)

        def trace(omega):
            return _trace_inverse(_weighted(info, omega, 1.0 - omega, d), d)

    else:
        info = _information(covs)

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
    half = torch.full_like(omega, 0.5)
    omega = torch.where(trace(half) <= trace(omega), half, omega)  # flat: the symmetric ω
    if (covs.requires_grad and torch.is_grad_enabled()) or under_transform(covs):
        omega = _with_implicit_gradient(omega, covs)
    if hand:
        mean, cov = _fused_by_hand(info, means, omega, 1.0 - omega, d)
    else:
        mean, cov = _fused(info, means, torch.stack((omega, 1.0 - omega), -1))
    return mean, cov, omega


def _with_implicit_gradient(omega: Tensor, covs: Tensor) -> Tensor:
    """``ω`` (a value found by search) with the derivative the minimiser of ``J(ω) = tr P_f``
    has: ``ω − (s − s.detach())`` for the Newton step ``s = J′/J″``, whose derivative at
    ``J′ = 0`` is ``d(J′)/J″`` (module docstring); none at a bound."""
    # in float64: near-equal covariances leave J′ and J″ of the size of float32's round-off
    info = torch.linalg.inv(covs.to(torch.float64))
    A = info[..., 0, :, :] - info[..., 1, :, :]

    def trace(M):
        return M.diagonal(dim1=-2, dim2=-1).sum(-1)

    def slope(P):  # J′ = −tr(P A P)
        return -trace(P @ A @ P)

    w = omega.detach().to(torch.float64)[..., None, None]
    P = torch.linalg.inv(w * info[..., 0, :, :] + (1 - w) * info[..., 1, :, :])
    first, second = slope(P), 2 * trace(P @ A @ P @ A @ P)  # J′, J″
    # the minimiser is inside [0, 1] where J falls at 0 and rises at 1 (a search stopped
    # short of a bound, ω = 0.99997 after 20 iterations, is at the bound: no derivative)
    with torch.no_grad():
        inside = (slope(covs[..., 1, :, :].to(torch.float64)) < 0) & (
            slope(covs[..., 0, :, :].to(torch.float64)) > 0
        )
        scale = torch.linalg.matrix_norm(covs.to(torch.float64), ord=2).amax(-1)
        inside = inside & (second > 1e-12 * (A.abs().amax((-1, -2)) * scale) ** 2 * scale)
    step = torch.where(inside, first / torch.where(inside, second, 1.0), 0.0)
    return omega.detach() - (step - step.detach()).to(omega.dtype)


def information_fusion(means: Tensor, covs: Tensor) -> tuple[Tensor, Tensor]:
    """Naive information fusion ``P_f⁻¹ = P₁⁻¹ + P₂⁻¹`` (module docstring) → ``(mean, cov)``."""
    _check_pair(means, covs)
    d = means.shape[-1]
    if _by_hand(covs, d):
        return _fused_by_hand(_local_information(covs, d), means, 1.0, 1.0, d)
    info = _information(covs)
    return _fused(info, means, means.new_ones(means.shape[:-1]))


class FusionRule(Choice):
    """How two estimates are fused: covariance intersection or naive information fusion."""

    CI = "ci"
    NAIVE = "naive"


def fuse(
    means: Tensor, covs: Tensor, rule: FusionRule | str = FusionRule.CI
) -> tuple[Tensor, Tensor]:
    """``(mean, cov)`` of the two estimates by ``rule`` (:class:`FusionRule`)."""
    if FusionRule(rule) is FusionRule.CI:
        mean, cov, _ = covariance_intersection(means, covs)
        return mean, cov
    return information_fusion(means, covs)
