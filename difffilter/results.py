"""Typed results of the filters: plain dataclasses of tensors, batch first."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import NamedTuple

from torch import Tensor

__all__ = ["GaussianState", "GaussianStepOutput", "FilterResult", "ParticleFilterResult"]


class GaussianState(NamedTuple):
    """Online state of a Gaussian filter: the posterior of ``x_k``.

    Attributes:
        mean: ``[..., dx]``.
        cov: ``[..., dx, dx]`` (may have fewer leading dimensions than ``mean`` when it
            is the same for every run, e.g. a linear time-invariant model without mask).
        k: time index of the state (0 for the prior of ``x_0``).
    """

    mean: Tensor
    cov: Tensor
    k: int = 0


class GaussianStepOutput(NamedTuple):
    """What one predict/update step of a Gaussian filter reports.

    Shapes: ``mean``/``pred_mean`` ``[..., dx]``, ``cov``/``pred_cov`` ``[..., dx, dx]``,
    ``innovation`` ``[..., dy]`` (``y − ŷ_{k|k−1}``, zero on unreceived entries),
    ``innovation_cov`` ``[..., dy, dy]`` (``S_k``), ``log_likelihood`` ``[...]``
    (``log p(y_k | y_{1:k−1})`` of the received entries).
    """

    mean: Tensor
    cov: Tensor
    pred_mean: Tensor
    pred_cov: Tensor
    innovation: Tensor
    innovation_cov: Tensor
    log_likelihood: Tensor


@dataclass
class FilterResult:
    """Whole-sequence output of a Gaussian filter (time index ``t`` ↔ ``x_{t+1}``, ``y_{t+1}``).

    Attributes:
        means: filtered means ``E[x_t | y_{1:t}]`` ``[..., T, dx]``.
        covs: filtered covariances ``[..., T, dx, dx]``.
        pred_means: one-step predictions ``E[x_t | y_{1:t−1}]`` ``[..., T, dx]``.
        pred_covs: ``[..., T, dx, dx]``.
        innovations: ``y_t − E[y_t | y_{1:t−1}]`` ``[..., T, dy]``.
        innovation_covs: ``S_t`` ``[..., T, dy, dy]``.
        log_likelihood_increments: ``log p(y_t | y_{1:t−1})`` ``[..., T]``.
        log_likelihood: ``log p(y_{1:T})`` ``[...]``.
        nonfinite_skipped: with ``nonfinite="skip"``, the number of non-finite received
            entries of ``ys`` treated as unreceived ``[...]`` (``None`` otherwise).
    """

    means: Tensor
    covs: Tensor
    pred_means: Tensor
    pred_covs: Tensor | None
    innovations: Tensor
    innovation_covs: Tensor
    log_likelihood_increments: Tensor
    log_likelihood: Tensor
    nonfinite_skipped: Tensor | None = None

    def to_dict(self) -> dict[str, Tensor | None]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class ParticleFilterResult(FilterResult):
    """Output of :func:`difffilter.particle_filter`.

    In addition to :class:`FilterResult` (weighted moments of the particles; the
    innovation covariance is the particle covariance of ``h(x)`` plus ``R``;
    ``pred_covs`` is ``None``):

    Attributes:
        ess: effective sample size after weighting ``[..., T]``.
        resampled: whether the particles were resampled before step ``t`` ``[..., T]``.
        degenerate: whether every weight of the run underflowed at step ``t`` and was
            reset to the predictive weights ``[..., T]`` (see :mod:`difffilter.particle`).
        particles: ``[..., T, N, dx]`` when requested (``return_particles=True``), else ``None``.
        log_weights: normalised log-weights ``[..., T, N]`` when requested, else ``None``.
        records: what the filter's step hooks recorded, ``{name: [..., T, ...]}``.
    """

    ess: Tensor | None = None
    resampled: Tensor | None = None
    degenerate: Tensor | None = None
    particles: Tensor | None = None
    log_weights: Tensor | None = None
    records: dict[str, Tensor] | None = None
