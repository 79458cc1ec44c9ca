"""Estimation and control over lossy links: the modified Riccati equations.

**Measurements lost** (Sinopoli, Schenato, Franceschetti, Poolla, Jordan & Sastry, "Kalman
filtering with intermittent observations", IEEE TAC 49(9), 2004): each measurement arrives
with probability ``λ``, independently, and the Kalman filter skips the update of a lost one
(:func:`difffilter.kalman_filter` with a ``mask``). Its prediction covariance ``P⁻_k`` is
then random; for ``λ`` above a critical ``λ_c`` its mean stays bounded, between the fixed
points of (Theorem 4 and 5)::

    S = (1 − λ) F S Fᵀ + Q                                    (lower bound S̄)
    V = F V Fᵀ + Q − λ F V Hᵀ (H V Hᵀ + R)⁻¹ H V Fᵀ           (upper bound V̄: the MARE)

with ``λ_c`` between ``1 − 1/ρ(F)²`` and the ``λ̄`` below which the MARE has no fixed point
(equal where ``H`` is invertible, as in the scalar case).

**Inputs lost, acknowledged** (Schenato et al., Proc. IEEE 95(1), 2007, TCP-like; the
actuators apply zero where a packet is lost, :class:`~difffilter.input_loss.InputLoss` with
``on_loss="zero"``): each input arrives with probability ``ν̄``, and the optimal controller
of ``Σ xᵀ Q x + (ν u)ᵀ R (ν u)`` is ``u_k = −K x̂_k`` with::

    S = Fᵀ S F + Q − ν̄ Fᵀ S B (Bᵀ S B + R)⁻¹ Bᵀ S F           (the control MARE)
    K = (Bᵀ S B + R)⁻¹ Bᵀ S F

(with the state known, the expected cost per step tends to ``tr(S W)``, ``W`` the process
noise covariance). Every fixed point is found by iterating its map (convergent where it
exists: Sinopoli et al., Lemma 1) in float64 numpy, from ``Q``; a singular ``Q`` can hold
the iteration at the fixed point 0 of an unstable mode it does not excite (an API trial: an
LQR gain that left an unstable mode alone, a zero upper bound where the filter's covariance
settles at ``a² − 1``), so where the fixed point leaves an unstable mode unestimated it
starts again from ``Q + c Π``, ``Π`` the projector onto those modes and ``c`` the
problem's scale (:func:`_scale`), and reaches the stabilising solution, as the filter from
a positive ``P₀`` does and as :func:`difffilter.control.dlqr` returns it.
Detached, no gradient, like :func:`difffilter.control.dlqr`.
"""

from __future__ import annotations

import math
import numbers
from typing import NamedTuple

import numpy as np
import scipy.linalg as sla
import torch
from torch import Tensor

from .control import _check_pair, _np, _weights, check_weight_values

__all__ = [
    "intermittent_kalman_bounds",
    "lossy_dlqr",
    "critical_arrival_rate",
    "CriticalRate",
]


def _rate(rate, name: str) -> float:
    if isinstance(rate, Tensor) and rate.dim() == 0 and not rate.dtype == torch.bool:
        rate = rate.item()
    if isinstance(rate, bool) or not isinstance(rate, numbers.Real) or not 0.0 < rate <= 1.0:
        raise ValueError(f"{name} must be a probability in (0, 1]; got {rate!r}")
    return float(rate)


def _arrays(F: Tensor, G: Tensor, Q: Tensor, R: Tensor, names: tuple[str, ...]):
    """``F``, ``G`` (``[p, n]``), ``Q``, ``R`` as float64 numpy arrays after checking their
    values: finite, ``Q`` symmetric positive semidefinite, ``R`` symmetric positive definite
    (a NaN had been reported as a rate below the critical one, an indefinite ``Q`` accepted,
    a negative ``R`` iterated for seconds)."""
    arrays = [_np(t.detach()) for t in (F, G, Q, R)]
    if arrays[0].shape[0] == 0:
        raise ValueError(f"{names[0]} has no state (n = 0): nothing to estimate or control")
    for name, a in zip(names[:2], arrays[:2]):
        if not np.isfinite(a).all():
            raise ValueError(f"{name} contains NaN or Inf values")
    check_weight_values(arrays[2], arrays[3], names[2:])
    return arrays


def _scale(F: np.ndarray, G: np.ndarray, Q: np.ndarray, R: np.ndarray) -> float:
    """The size of the MARE's solutions: ``(tr Q + tr R ‖G⁺‖²) · max(1, ρ(F)²)`` (``R`` in
    the state's units through ``G``'s pseudo-inverse; an unstable ``F`` multiplies the
    noise). Where the iterate passes ``10¹⁵`` times it, it diverges: measured against ``Q``
    alone, a tiny ``Q`` with a large ``R`` (``1e-12`` and ``1e6``, a fixed point of 3e5) was
    called divergent, and ``F = 1e8`` undetectable."""
    radius = float(np.abs(np.linalg.eigvals(F)).max())
    gain = float(np.linalg.norm(np.linalg.pinv(G), 2)) ** 2 if G.size else 0.0
    return (float(np.trace(Q)) + float(np.trace(R)) * gain) * max(1.0, radius**2) or 1.0


#: Why :func:`_mare` gave no fixed point: its iteration grew without bound, or had not
#: settled after ``max_iter`` steps (near the critical rate it moves slowly either way).
DIVERGED, UNSETTLED = "diverged", "unsettled"


def _mare(F: np.ndarray, G: np.ndarray, Q: np.ndarray, R: np.ndarray, rate: float,
          tol: float = 1e-12, max_iter: int = 100_000) -> np.ndarray | str:  # fmt: skip
    """The fixed point of ``X = F X Fᵀ + Q − rate · F X Gᵀ (G X Gᵀ + R)⁻¹ G X Fᵀ`` (the
    filtering form; the control form is its dual, ``F → Fᵀ``, ``G → Bᵀ``), or why there is
    none: :data:`DIVERGED` where the iteration grows without bound, :data:`UNSETTLED` where
    it has not settled after ``max_iter`` steps.

    From ``Q`` first; where that fixed point leaves an unstable mode unestimated
    (``ρ(F − F K G) > 1``, ``K = X Gᵀ (G X Gᵀ + R)⁻¹``: a mode ``Q`` does not excite, held
    at 0), again from ``Q + c Π``, ``Π`` the projector onto those modes
    (:func:`_unestimated`), which reaches the stabilising solution. Not from ``Q + c I``:
    on a marginal mode ``Q`` does not excite (a constant bias state) the covariance from a
    positive start shrinks like ``1/k`` and never settles (a review), where from ``Q`` it is
    0 at once, the limit either way."""
    # no fixed point where (1 − rate) ρ(F)² ≥ 1 (Sinopoli et al. 2004: λ_c ≥ 1 − 1/ρ(F)²);
    # said at once, not after the iterate has grown 10¹⁵-fold
    if (1.0 - rate) * float(np.abs(np.linalg.eigvals(F)).max()) ** 2 >= 1.0:
        return DIVERGED
    X = _mare_from(F, G, Q, R, rate, Q.copy(), tol, max_iter)
    n, restarts = F.shape[0], 0
    while _found(X):
        unstable = _unestimated(F, G, R, X)
        if unstable is None:
            return X
        if restarts == 3:  # (a stabilising solution the restarts do not reach: none found)
            return UNSETTLED
        restarts += 1
        start = Q + (_scale(F, G, Q, R) / n) * unstable
        X = _mare_from(F, G, Q, R, rate, start, tol, max_iter)
    return X


def _unestimated(F: np.ndarray, G: np.ndarray, R: np.ndarray, X: np.ndarray):
    """The orthogonal projector ``[n, n]`` onto the invariant subspace of the modes of ``F − F K G``
    (``K = X Gᵀ (G X Gᵀ + R)⁻¹``) outside the unit circle, or ``None`` where there is none:
    the unstable modes the fixed point ``X`` leaves unestimated. The restart adds them alone
    (along all of ``I`` a constant-bias mode beside them shrank like ``1/k`` again and never
    settled: a review, F = diag(1, 2), Q = 0)."""
    K = np.linalg.solve(G @ X @ G.T + R, G @ X).T
    # the invariant subspace of the modes outside the unit circle, from the ordered real
    # Schur form (its eigenvectors alone miss a Jordan block's other directions: a review,
    # F = [[1.2, 1], [0, 1.2]], a fixed point that left the loop at 1.2)
    _, Z, count = sla.schur(F - F @ K @ G, output="real",
                            sort=lambda re, im: math.hypot(re, im) > 1.0 + 1e-9)  # fmt: skip
    if count == 0:
        return None
    Zu = Z[:, :count]
    return Zu @ Zu.T  # orthonormal columns: the orthogonal projector


def _mare_from(F, G, Q, R, rate: float, X: np.ndarray, tol: float, max_iter: int):
    """:func:`_mare`'s iteration from ``X``, settled where every entry has:
    ``|X⁺ᵢⱼ − Xᵢⱼ| ≤ tol · √(X⁺ᵢᵢ X⁺ⱼⱼ)``, a test a change of the state's units leaves
    as it is (``X → D X D``). Against the largest entry of ``X`` a state in units 10⁶ times
    smaller stopped unconverged (8× low), and an unstable one below the critical rate
    passed for settled (a red-team trial)."""
    scale = _scale(F, G, Q, R)
    for _ in range(max_iter):
        S = G @ X @ G.T + R
        try:
            # F((1 − rate) X + rate P⁺)Fᵀ + Q with P⁺ = (I − KG) X (I − KG)ᵀ + K R Kᵀ (the
            # Joseph form): the same map without subtracting two products of F X Fᵀ's size
            # (F = 1e8: 1e32 each, their difference 1e16, round-off as large: never settled)
            K = np.linalg.solve(S, G @ X).T
        except np.linalg.LinAlgError:
            raise ValueError(
                "the modified Riccati iteration met a singular G X Gᵀ + R (R, or its control "
                "weight, singular along a direction the noise Q does not reach): give R > 0"
            ) from None
        IKG = np.eye(X.shape[0]) - K @ G
        posterior = IKG @ X @ IKG.T + K @ R @ K.T
        nxt = F @ ((1.0 - rate) * X + rate * posterior) @ F.T + Q
        nxt = 0.5 * (nxt + nxt.T)
        if not np.isfinite(nxt).all() or np.trace(nxt) > 1e15 * scale:
            return DIVERGED
        root = np.sqrt(np.abs(np.diagonal(nxt)))
        if (np.abs(nxt - X) <= tol * np.outer(root, root)).all():
            return nxt
        X = nxt
    return UNSETTLED


_UNDETECTABLE = ("(F, H) is not detectable (an unstable mode the measurements do not see): "
                 "no arrival rate keeps the Kalman filter's covariance bounded")  # fmt: skip


def _found(X) -> bool:
    return not isinstance(X, str)


def _diverged(X) -> bool:
    return isinstance(X, str) and X == DIVERGED


def _no_fixed_point(why: str, rate: float, what: str, mode: str = "undetectable") -> ValueError:
    """The error of a Riccati iteration without a fixed point; ``mode``: what a pair's
    mode on (or very near) the unit circle is called in that problem (a filter's ``undetectable``, a
    controller's ``uncontrollable``)."""
    if why == UNSETTLED:
        # at rate 1 nothing is lost: no critical rate to be near (a trial on the LFC plant,
        # whose conserved tie-line sum is an uncontrollable mode at 1, read that it was)
        cause = (f"the pair has an {mode} mode on (or very near) the unit circle" if rate == 1.0 else
                 "the rate is near (or below) the critical rate (critical_arrival_rate gives "
                 f"it), or the pair has an {mode} mode on (or very near) the unit circle")  # fmt: skip
        return ValueError(
            f"{what}: the modified Riccati iteration at rate {rate} had not settled after "
            f"100,000 steps: {cause}"
        )
    return ValueError(
        f"{what}: rate {rate} is at or below the critical rate: the modified Riccati equation "
        "has no fixed point and the mean covariance may grow without bound "
        "(critical_arrival_rate gives the rates)"
    )


def _as(X: np.ndarray, like: Tensor) -> Tensor:
    return torch.as_tensor(X, dtype=like.dtype, device=like.device)


def intermittent_kalman_bounds(F: Tensor, H: Tensor, Q: Tensor, R: Tensor,
                               arrival_rate: float) -> tuple[Tensor, Tensor]:  # fmt: skip
    """``(S̄, V̄)`` ``[n, n]``: the lower and upper bounds on the limit of the Kalman filter's
    mean prediction covariance ``E[P⁻_k]`` when each measurement arrives with probability
    ``arrival_rate`` (module docstring, Sinopoli et al. 2004): ``S̄`` the Lyapunov equation's
    solution (scipy), ``V̄`` the MARE's fixed point. At rate 1 both are the Kalman limit
    (the filter's covariance is then deterministic; the formula's ``S̄ = Q`` bounds it
    too, loosely). ``ValueError`` where ``V̄`` does not exist or the iteration has not
    settled (a rate at or just above the critical rate: :func:`critical_arrival_rate`)."""
    n, p = _check_pair(F, H.T if isinstance(H, Tensor) else H, ("F", "Hᵀ"))
    lam = _rate(arrival_rate, "arrival_rate")
    if Q is None or R is None:  # (the identity had been taken for them without a word)
        raise ValueError("Q and R (the process and measurement noise covariances) are needed")
    Q, R = _weights(Q, R, n, p, F)
    Fn, Hn, Qn, Rn = _arrays(F, H, Q, R, ("F", "H", "Q", "R"))
    upper = _mare(Fn, Hn, Qn, Rn, lam)
    if not _found(upper):
        # (at rate 1 the iteration just run is the one to read: a review's undetectable
        # pair at rate 1 was told the rate lay below the critical rate)
        if _diverged(upper if lam == 1.0 else _mare(Fn, Hn, Qn, Rn, 1.0)):
            raise ValueError(f"intermittent_kalman_bounds: {_UNDETECTABLE}")
        raise _no_fixed_point(upper, lam, "intermittent_kalman_bounds")
    if lam == 1.0:
        return _as(upper, F), _as(upper, F)
    # S = (1 − λ) F S Fᵀ + Q (exists: V̄ does, so (1 − λ) ρ(F)² < 1)
    lower = sla.solve_discrete_lyapunov(np.sqrt(1.0 - lam) * Fn, Qn)
    return _as(0.5 * (lower + lower.T), F), _as(upper, F)


def lossy_dlqr(F: Tensor, B: Tensor, Q: Tensor | None = None, R: Tensor | None = None, *,
               arrival_rate: float) -> tuple[Tensor, Tensor]:  # fmt: skip
    """``(K [m, n], S [n, n])``: the optimal state feedback ``u_k = −K x̂_k`` when each input
    packet arrives with probability ``arrival_rate``, acknowledged, and a lost one is zero
    at the actuators (module docstring, Schenato et al. 2007, TCP-like). ``arrival_rate=1``
    is :func:`difffilter.control.dlqr`. ``Q``, ``R`` default to ``I``; ``ValueError`` where
    the control MARE has no fixed point (the rate too low for ``(F, B)``)."""
    n, m = _check_pair(F, B, ("F", "B"))
    rate = _rate(arrival_rate, "arrival_rate")
    Q, R = _weights(Q, R, n, m, F)
    Fn, Bn, Qn, Rn = _arrays(F, B, Q, R, ("F", "B", "Q", "R"))
    S = _mare(Fn.T, Bn.T, Qn, Rn, rate)
    if not _found(S):
        if _diverged(S if rate == 1.0 else _mare(Fn.T, Bn.T, Qn, Rn, 1.0)):
            raise ValueError(
                "lossy_dlqr: (F, B) is not stabilizable (an unstable mode the inputs do not "
                "reach): no arrival rate makes the cost finite"
            )
        raise _no_fixed_point(S, rate, "lossy_dlqr (the control Riccati equation of (F, B) "
                                       "with lost inputs; the rates: critical_arrival_rate(F.T, B.T))",
                              mode="uncontrollable")  # fmt: skip
    K = np.linalg.solve(Bn.T @ S @ Bn + Rn, Bn.T @ S @ Fn)
    return _as(K, F), _as(S, F)


class CriticalRate(NamedTuple):
    """``(lower, upper)``: the critical arrival rate lies in ``[lower, upper]`` (module
    docstring): ``lower = 1 − 1/ρ(F)²`` (0 for a stable ``F``), ``upper`` the rate below which
    the modified Riccati equation has no fixed point (to ``tol``)."""

    lower: float
    upper: float


#: Iterations of the MARE per bisection step of :func:`critical_arrival_rate`: near ``λ̄``
#: its iteration converges (or grows) slowly, so a rate still undecided after them counts
#: as having no fixed point, and ``λ̄`` comes out a little high (scalar ``a = 1.2``: 7.6e-4
#: with 20,000 iterations, 1.7e-4 with 100,000 at five times the time).
BISECTION_ITERATIONS = 20_000


def critical_arrival_rate(F: Tensor, H: Tensor, Q: Tensor | None = None, R: Tensor | None = None,
                          *, tol: float = 1e-3) -> CriticalRate:  # fmt: skip
    """The critical arrival rate of measurements for the Kalman filter of ``(F, H)``
    (Sinopoli et al. 2004: ``E[P⁻_k]`` is bounded for every start above it and not below),
    as the interval :class:`CriticalRate` ``(1 − 1/ρ(F)², λ̄)`` with ``λ̄`` found by
    bisection on the existence of the MARE's fixed point, to ``tol`` and a little high
    (:data:`BISECTION_ITERATIONS`: right above ``λ̄`` the MARE's iteration settles so slowly
    that a rate may count as without a fixed point, and for a slowly unstable ``F`` the
    error can exceed ``tol``); equal ends, exact and without bisection, where ``H`` is
    square and invertible (Sinopoli et al. 2004: ``λ_c = 1 − 1/ρ(F)²`` there; a review's
    ``a = 1.01`` had bisected for 9.5 s to 1.9e-3 above it). For inputs
    (:func:`lossy_dlqr`), the dual: ``critical_arrival_rate(F.T, B.T, Q, R)``. ``Q``, ``R``
    default to ``I`` (``λ̄`` does not depend on them where ``(F, Q^{1/2})`` is
    controllable)."""
    n, p = _check_pair(F, H.T if isinstance(H, Tensor) else H, ("F", "Hᵀ"))
    if isinstance(tol, bool) or not isinstance(tol, numbers.Real) or not 0.0 < tol < 0.5:
        # (0 or less bisected forever; NaN or 2 returned an upper end of 1 unsearched)
        raise ValueError(f"tol must be a number in (0, 0.5); got {tol!r}")
    Q, R = _weights(Q, R, n, p, F)
    Fn, Hn, Qn, Rn = _arrays(F, H, Q, R, ("F", "H", "Q", "R"))
    radius = float(np.abs(np.linalg.eigvals(Fn)).max())
    at_one = _mare(Fn, Hn, Qn, Rn, 1.0)
    if _diverged(at_one):
        raise ValueError(_UNDETECTABLE)
    if not _found(at_one):
        raise _no_fixed_point(at_one, 1.0, "critical_arrival_rate")
    if radius <= 1.0 + 1e-12:  # stable (or marginal, detectable): bounded at every rate
        return CriticalRate(0.0, 0.0)
    lower = 1.0 - 1.0 / radius**2
    if p == n and np.linalg.matrix_rank(Hn) == n:
        return CriticalRate(lower, lower)
    lo, hi = lower, 1.0  # the MARE has no fixed point at or below lo (ρ² (1 − λ) ≥ 1)
    cap = BISECTION_ITERATIONS
    if lo > 0 and _found(_mare(Fn, Hn, Qn, Rn, min(1.0, lo + tol), max_iter=cap)):
        return CriticalRate(lower, min(1.0, lo + tol))
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        if not _found(_mare(Fn, Hn, Qn, Rn, mid, max_iter=cap)):
            lo = mid
        else:
            hi = mid
    return CriticalRate(lower, hi)
