"""Filter consistency: does a filter's reported covariance match its actual error?

For a consistent filter over ``R`` independent Monte Carlo runs (Bar-Shalom, Li &
Kirubarajan 2001, §5.4):

* **NEES** ``ε_k = e_kᵀ P_k⁻¹ e_k`` with ``e_k = x_k − x̂_k`` is ``χ²_n`` (``n = dim x``);
  its average over the runs at one step, ``ε̄_k``, lies in
  ``[χ²_{Rn}(α/2), χ²_{Rn}(1 − α/2)] / R`` with probability ``1 − α``
  (:func:`chi_square_bounds`).
* **NIS** ``ν_kᵀ S_k⁻¹ ν_k`` (:func:`difffilter.fdi.normalized_innovation_squared`) is
  ``χ²_m`` likewise.
* **Whiteness**: the innovations of different steps are uncorrelated. With whitened
  innovations ``w_k = L_k⁻¹ ν_k`` (``S_k = L_k L_kᵀ``), the run-averaged correlation

      ρ̄_k(j) = Σ_r w_{r,k}ᵀ w_{r,k+j} / √(Σ_r |w_{r,k}|² Σ_r |w_{r,k+j}|²)

  has variance ``1 / (R m)`` for a consistent filter (``ρ̄² ~ Beta(½, (Rm − 1)/2)``): outside
  its 95 % bound (about ``±1.96/√(Rm)``) at about 5 % of the steps.

Average over the **runs** at each step, not over the steps of one run: one run's errors
are correlated in time, so its time average is no χ² of ``Tn`` degrees of freedom (a
consistency trial: 42 % of the runs of a matched Kalman filter fell "outside" by that
reading). :func:`ensemble_test` does the averaging and counts the steps outside the
bounds: about ``α`` of them for a consistent filter.
"""

from __future__ import annotations

import math
import numbers
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ._checks import (
    broadcast_or_none,
    check_one_dtype_device,
    check_rate,
    check_semidefinite,
    check_symmetric,
)
from .linalg import safe_cholesky

__all__ = ["nees", "chi_square_bounds", "ensemble_test", "ConsistencyTest", "whiteness"]


def nees(errors: Tensor, covs: Tensor) -> Tensor:
    """``eᵀ P⁻¹ e``: ``errors [..., n]`` (``x − x̂``), ``covs [..., n, n]`` → ``[...]``.

    By a linear solve, not a Cholesky factor: a particle filter's collapsed covariance
    (an eigenvalue of 1e-26) gives the huge NEES it deserves rather than an error, and an
    exactly singular one ``+inf`` (``0`` where the error is exactly ``0``). So does one
    singular to round-off, whose solve comes back negative or NaN (a cloud of two particles
    has a rank-one covariance, its other eigenvalue a round-off of either sign: −4.6e22,
    and NaN where the solve overflowed, had been returned, and a mean over runs and steps
    read NaN: a red-team trial). A covariance that is indefinite beyond round-off is
    refused."""
    if not isinstance(errors, Tensor) or errors.dim() < 1:
        raise ValueError(
            f"errors must be a tensor [..., n]; got {getattr(errors, 'shape', errors)!r}"
        )
    n = errors.shape[-1]
    if not isinstance(covs, Tensor) or covs.shape[-2:] != (n, n):
        raise ValueError(
            f"covs must be [..., {n}, {n}] (the filter's covariances); got "
            f"{tuple(covs.shape) if isinstance(covs, Tensor) else covs!r}"
        )
    check_one_dtype_device(errors, "errors", covs, "covs")
    if broadcast_or_none(covs.shape[:-2], errors.shape[:-1]) is None:
        raise ValueError(
            f"covs [..., {n}, {n}] must have the errors' batch {tuple(errors.shape[:-1])} (or "
            f"broadcast to it); got {tuple(covs.shape)}"
        )
    # every finite covariance, symmetric and semidefinite (the carries' check, whose jitter
    # passes round-off, down to a cloud collapsed to 1e-323); only those whose solve came
    # back negative had been checked: diag(1, −1) gave 0.99 for e = (1, 0.1), and an
    # asymmetric one a number (a consistency trial)
    _check_covariances(covs, "covs")
    e = errors.unsqueeze(-1)
    solved, info = torch.linalg.solve_ex(covs, e)
    value = (e.mT @ solved).squeeze(-1).squeeze(-1)
    # an exactly singular covariance (a cloud collapsed onto one particle), or one singular
    # to round-off (a negative or NaN solve of finite numbers): +inf, or 0 for an error of
    # exactly 0 (it had raised torch's LinAlgError for the whole batch: a trial)
    finite = torch.isfinite(errors).all(-1) & torch.isfinite(covs).all(-1).all(-1)
    singular = (info != 0) | (~(value >= 0) & finite)
    if not bool(singular.any()):
        return value
    value, singular = torch.broadcast_tensors(value, singular)
    off = (errors != 0).any(-1).expand(value.shape)
    worst = torch.where(off, torch.full_like(value, math.inf), torch.zeros_like(value))
    return torch.where(singular, worst, value)


def _check_covariances(covs: Tensor, name: str) -> None:
    """Every finite covariance of ``covs [..., n, n]`` symmetric (:func:`check_symmetric`,
    skipped where exactly so, as a filter's are) and semidefinite to round-off
    (:func:`check_semidefinite`, on the few a plain Cholesky factor refuses): the full
    checks of every matrix had made ``nees`` of ``[100, 200, 4, 4]`` 5–25× slower (a
    review)."""
    finite = torch.isfinite(covs).all(-1).all(-1)
    known = covs if bool(finite.all()) else covs[finite]
    if not torch.equal(known, known.mT):
        check_symmetric(known, name)
    _, info = torch.linalg.cholesky_ex(known)
    if bool((info != 0).any()):
        check_semidefinite(known[info != 0], name, advice="give the filter's covariances")


def chi_square_bounds(dof: int, runs: int, confidence: float = 0.95) -> tuple[float, float]:
    """The two-sided ``confidence`` interval of the average of ``runs`` independent ``χ²_dof``
    values: ``(χ²_{R·dof}((1 − c)/2), χ²_{R·dof}((1 + c)/2)) / R``."""
    from scipy.stats import chi2

    for name, value in (("dof", dof), ("runs", runs)):  # (numpy's integers too)
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
            raise ValueError(f"{name} must be an integer >= 1; got {value!r}")
    alpha = 1.0 - check_rate(confidence, "confidence", kind="a confidence level")
    low, high = chi2.ppf([alpha / 2, 1 - alpha / 2], int(runs) * int(dof)) / int(runs)
    return float(low), float(high)


class ConsistencyTest(NamedTuple):
    """``mean [T]`` the run average of a statistic at each step, ``(low, high)`` its bounds
    (numbers, or ``[T]`` where the degrees of freedom vary), ``outside`` the share of steps
    outside them, a non-finite average included (about ``1 − confidence`` if consistent),
    of the steps where some run has data (``dof`` of ``[R, T]``: a step where every run's is
    0 tests nothing; NaN where none has any), and ``expected`` that share."""

    mean: Tensor
    low: float | Tensor
    high: float | Tensor
    outside: float
    expected: float


def ensemble_test(statistic: Tensor, dof, confidence: float = 0.95) -> ConsistencyTest:
    """The run-averaged ``χ²_dof`` statistic ``[R, T]`` (NEES with ``dof = n``, NIS with
    ``dof = m``) against :func:`chi_square_bounds` at every step (module docstring).

    ``dof`` may be a tensor ``[R, T]`` of each value's degrees of freedom: the NIS under
    packet loss has as many as entries received (``dof = mask.sum(-1)``; with ``m`` a
    matched filter under 30 % loss read as inconsistent at 98 % of the steps). The sum over
    the runs is then ``χ²`` of ``D_t = Σ_r dof_{r,t}``, and the bounds are ``[χ²_{D_t}(α/2),
    χ²_{D_t}(1 − α/2)] / R``."""
    if not isinstance(statistic, Tensor) or statistic.dim() != 2:
        raise ValueError(
            "statistic must be [R, T] (runs, steps) of NEES or NIS values; got "
            f"{tuple(statistic.shape) if isinstance(statistic, Tensor) else statistic!r}"
        )
    runs = statistic.shape[0]
    if runs == 0 or statistic.shape[1] == 0:
        raise ValueError(f"statistic has no runs or no steps: {tuple(statistic.shape)}")
    if bool((statistic < 0).any()):  # (a negative one, of a covariance that is no
        # covariance, had been averaged with the others and could land inside the bounds)
        raise ValueError(
            f"statistic must be >= 0 (NEES and NIS are squared norms); got "
            f"{float(statistic.min()):g} (a covariance that is not positive definite?)"
        )
    mean = statistic.double().mean(0)
    if isinstance(dof, (np.ndarray, list, tuple)):
        dof = torch.as_tensor(np.asarray(dof))
    if isinstance(dof, Tensor) and dof.dim() == 0:  # one number (refused as no [R, T])
        dof = dof.item()
    if isinstance(dof, Tensor):
        from scipy.stats import chi2

        alpha = 1.0 - check_rate(confidence, "confidence", kind="a confidence level")
        if (
            dof.shape != statistic.shape
            or bool((dof < 0).any())
            or not bool(torch.isfinite(dof).all())
        ):  # (an infinite dof had given NaN bounds, counted as outside without a word)
            raise ValueError(f"dof must be a number or [R, T] like statistic "
                             f"{tuple(statistic.shape)}, finite and >= 0; got "
                             f"{tuple(dof.shape)}")  # fmt: skip
        if dof.is_floating_point() and bool((dof != dof.round()).any()):
            # counts of entries received (the scalar dof is checked so too): 2.5 had passed
            raise ValueError(
                f"dof must be whole numbers of degrees of freedom (counts of entries "
                f"received); got {dof[dof != dof.round()].flatten()[0].item():g}"
            )
        total = dof.double().sum(0).cpu().numpy()
        # a step where no run received anything has statistic 0 and bounds [0, 0] (chi2 of
        # 0 degrees of freedom is NaN in scipy: such steps had counted as outside)
        low, high = (torch.as_tensor(np.where(total > 0, chi2.ppf(p, np.maximum(total, 1)), 0.0)
                                     / runs, device=mean.device)
                     for p in (alpha / 2, 1 - alpha / 2))  # fmt: skip
        # ... and tests nothing: the share outside is of the steps with data (counted as
        # inside, a sensor read every 10th step diluted it tenfold: a filter whose S was 25 %
        # too small, 32–47 % outside where it was tested, read 3–5 %, as a consistent one)
        tested = torch.as_tensor(total > 0, device=mean.device)
    else:
        low, high = chi_square_bounds(dof, runs, confidence)
        tested = torch.ones_like(mean, dtype=torch.bool)
    # a non-finite average (a run that diverged) is outside, never inside
    out = ~((mean >= low) & (mean <= high))
    outside = float(out[tested].double().mean()) if bool(tested.any()) else math.nan
    return ConsistencyTest(mean, low, high, outside, 1.0 - confidence)


def whiteness(
    innovations: Tensor, innovation_covs: Tensor, lag: int = 1, mask: Tensor | None = None
) -> tuple[Tensor, float | Tensor]:
    """``(ρ̄ [T − lag], bound)``: the run-averaged correlation of the whitened innovations
    ``lag`` steps apart (module docstring) and its two-sided 95 % bound, for
    ``innovations [R, T, m]`` and ``innovation_covs [R, T, m, m]`` (or broadcasting).

    For white Gaussian innovations ``ρ̄²`` is ``Beta(½, (Rm − 1)/2)`` (the squared cosine of
    the angle between two independent ``Rm``-vectors), so the bound is
    ``√(Beta⁻¹(0.95; ½, (Rm − 1)/2))``, about ``1.96/√(Rm)`` for large ``Rm`` (that
    approximation alone never rejected at ``Rm ≤ 3``, as ``|ρ̄| ≤ 1``); ``1`` where
    ``Rm = 1`` (one scalar run: no test).

    Under packet loss pass the filter's ``mask [R, T, m]`` (bool, ``True`` where an entry
    arrived; the innovations and covariances of a difffilter filter run with it, whose lost
    entries have a zero innovation and a unit, uncorrelated variance, so their whitened
    entries are 0 and the received ones are the received block's own): ``ρ̄`` then sums the
    pairs whose both entries arrived (an entry and the same entry ``lag`` steps later:
    under round-robin scheduling of ``n`` groups only multiples of ``n`` pair anything),
    ``n_k`` of them at step ``k``, and the bound is a ``[T − lag]`` tensor of
    ``√(Beta⁻¹(0.95; ½, (n_k − 1)/2))`` (``1`` where ``n_k ≤ 1``, ``ρ̄`` NaN where
    ``n_k = 0``). Without it every entry counts as received: a lost entry's
    0 then dilutes ``ρ̄`` below the bound's ``Rm`` (7.8 % of a matched filter's steps
    rejected for 5 % with 4 runs, 2 entries, half of them lost; with it 4.6 % of the steps
    it tests, those with ``n_k ≥ 2``)."""
    if not isinstance(innovations, Tensor) or innovations.dim() != 3:
        raise ValueError(
            "innovations must be [R, T, m] (runs, steps, entries); got "
            f"{tuple(innovations.shape) if isinstance(innovations, Tensor) else innovations!r}"
        )
    runs, steps, m = innovations.shape
    if runs == 0 or m == 0:  # (torch's amax had failed on no runs: a batch-dims trial)
        raise ValueError(f"innovations has no runs or no entries: {tuple(innovations.shape)}")
    # numbers.Integral: numpy's integers too (np.int64(1) had been refused as no integer)
    if isinstance(lag, bool) or not isinstance(lag, numbers.Integral) or not 1 <= lag < steps:
        raise ValueError(f"lag must be an integer in [1, T − 1 = {steps - 1}]; got {lag!r}")
    if mask is not None and (
        not isinstance(mask, Tensor) or mask.dtype != torch.bool or mask.shape != innovations.shape
    ):
        got = f"{mask.dtype} {tuple(mask.shape)}" if isinstance(mask, Tensor) else repr(mask)
        raise ValueError(f"mask must be a bool tensor of the innovations' shape "
                         f"{tuple(innovations.shape)} (the filter's mask); got {got}")  # fmt: skip
    if (
        not isinstance(innovation_covs, Tensor)
        or innovation_covs.shape[-2:] != (m, m)
        or (broadcast_or_none(innovation_covs.shape[:-2], (runs, steps)) != (runs, steps))
    ):
        got = (
            tuple(innovation_covs.shape) if isinstance(innovation_covs, Tensor) else innovation_covs
        )
        raise ValueError(f"innovation_covs must be [R, T, {m}, {m}] like the innovations (or "
                         f"broadcast to it); got {got!r}")  # fmt: skip
    check_one_dtype_device(innovations, "innovations", innovation_covs, "innovation_covs")
    if not bool(torch.isfinite(innovations).all()):
        # (a diverged run's NaN made ρ̄ NaN at the steps it reached, and NaN > bound is
        # false: a set of correlated innovations rejected at 100 % of the steps read 5 %,
        # "white": a red-team trial; the NIS refuses them too)
        raise ValueError(
            "innovations contains NaN or Inf values: a diverged run has no whiteness to test "
            "(leave it out, or pass mask= with its lost entries False and innovations 0)"
        )
    # (eigvalsh and the Cholesky factor read one triangle: an asymmetric S, which the NIS
    # refuses, had been read as its lower triangle: a consistency trial)
    if not torch.equal(innovation_covs, innovation_covs.mT):
        check_symmetric(innovation_covs, "innovation_covs")
    if bool((torch.linalg.eigvalsh(innovation_covs.double()) <= 0).any()):
        # (a zero S had been taken, its Cholesky jittered, and a normal-looking ρ̄ returned)
        raise ValueError("innovation_covs must be positive definite (a filter's S)")
    # (with the mask, a jittered S takes the received entries' own jitter: scaled by the
    # lost entries' unit placeholders too, the received block's whitening was off)
    chol = safe_cholesky(innovation_covs.expand(runs, steps, m, m), name="innovation_covs",
                         mask=mask)  # fmt: skip
    w = torch.linalg.solve_triangular(chol, innovations.unsqueeze(-1), upper=False).squeeze(-1)
    w = w.double()
    now, later = w[:, :-lag], w[:, lag:]
    if mask is not None:  # the pairs whose both entries arrived
        both = (mask[:, :-lag] & mask[:, lag:]).to(w.device)
        now, later = now * both, later * both
    # each step's pair of vectors scaled to a largest entry of 1 (the cosine does not
    # change): innovations of 1e160 overflowed the sums of squares, inf/inf = NaN
    now, later = _unit_max(now), _unit_max(later)
    cross = (now * later).sum((-1, 0))
    scale = now.square().sum((-1, 0)).sqrt() * later.square().sum((-1, 0)).sqrt()
    # a cosine: |ρ̄| ≤ 1, which round-off exceeded by an ulp (ρ̄ = 1 + 1e-16 "rejected" at a
    # bound of 1, the steps the docstring calls untested: 10 % of the one-pair steps)
    rho = (cross / scale).clamp(-1.0, 1.0)
    if mask is None:
        return rho, _white_bound(runs * m)
    counts, where = torch.unique(both.sum((-1, 0)).cpu(), return_inverse=True)
    bounds = torch.tensor([_white_bound(int(n)) for n in counts], dtype=torch.float64)
    return rho, bounds[where].to(cross.device)  # (one quantile per distinct n_k)


def _unit_max(v: Tensor) -> Tensor:
    """``v [R, T', m]`` divided by its largest magnitude at each step (steps of zeros kept)."""
    top = v.abs().amax((-1, 0), keepdim=True)
    return v / torch.where(top > 0, top, torch.ones_like(top))


def _white_bound(n: int) -> float:
    """The 95 % two-sided bound of the cosine of two independent Gaussian ``n``-vectors."""
    if n < 2:
        return 1.0
    from scipy.stats import beta

    return math.sqrt(float(beta.ppf(0.95, 0.5, (n - 1) / 2)))
