"""Typed results of the filters: plain dataclasses of tensors, batch first."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, NamedTuple

from torch import Tensor

__all__ = [
    "GaussianState",
    "StepOutput",
    "GaussianStepOutput",
    "FilterResult",
    "ParticleFilterResult",
]


class GaussianState(NamedTuple):
    """Online state (the carry) of a Gaussian filter: the posterior of ``x_k``.

    Attributes:
        mean: ``[..., dx]``.
        cov: ``[..., dx, dx]`` (may have fewer leading dimensions than ``mean`` when it
            is the same for every run, e.g. a linear time-invariant model without mask).
        k: time index of the state (0 for the prior of ``x_0``).
        model: the model being filtered (set by the estimators' ``init``).
        gains: the :class:`~difffilter.GainSchedule` whose shared covariances ``cov`` is
            (a Kalman filter of an unbatched time-invariant model), or ``None``.
    """

    mean: Tensor
    cov: Tensor
    k: int = 0
    model: Any = None
    gains: Any = None


class StepOutput(NamedTuple):
    """What one step ``k−1 → k`` of any estimator reports: the one step-output type.

    Every estimator of the library (plain filters, the papers' attack-aware filters, the
    learned estimator) returns it from ``step``; the open-loop driver stacks it over time
    into an :class:`~difffilter.EstimatorOutput`. Fields an estimator does not compute are
    ``None``.

    Attributes:
        mean: ``x̂_k`` ``[..., dx]`` (after compensation, where the estimator compensates).
        cov: its covariance ``[..., dx, dx]`` (may lack the batch dimensions when it is
            the same for every run).
        pred_mean, pred_cov: the prediction ``E[x_k | y_{1:k−1}]`` and its covariance.
        innovation: ``y_k − E[h(x_k) | y_{1:k−1}]`` ``[..., dy]`` (zero on unreceived entries).
        innovation_cov: its covariance ``S_k`` ``[..., dy, dy]``.
        log_likelihood: ``log p(y_k | y_{1:k−1})`` of the received entries ``[...]``.
        attack: the attack estimate ``â_k`` ``[..., da]``.
        score, alarm: the detection statistic ``[...]`` (higher = more likely attacked) and
            the decision ``l̂_k`` ``[...]`` (bool).
        threshold: what ``score`` was compared with: a number or ``[...]``.
        extras: what an estimator records beyond this, ``{name: tensor [..., ·]}`` (the
            particle filter's ``"ess"``, ``"resampled"``, ``"prior_log_weights"``,
            ``"degenerate"``; a detector's running statistic; …), or ``None``.
    """

    mean: Tensor
    cov: Tensor | None = None
    pred_mean: Tensor | None = None
    pred_cov: Tensor | None = None
    innovation: Tensor | None = None
    innovation_cov: Tensor | None = None
    log_likelihood: Tensor | None = None
    attack: Tensor | None = None
    score: Tensor | None = None
    alarm: Tensor | None = None
    threshold: Tensor | float | None = None
    extras: dict[str, Tensor] | None = None


#: The step output of the Gaussian filters (the same type, kept as a name of the API).
GaussianStepOutput = StepOutput


@dataclass
class FilterResult:
    """Whole-sequence output of a Gaussian filter (time index ``t`` ↔ ``x_{t+1}``, ``y_{t+1}``).

    Attributes:
        means: filtered means ``E[x_t | y_{1:t}]`` ``[..., T, dx]``.
        covs: filtered covariances ``[..., T, dx, dx]``.
        pred_means: one-step predictions ``E[x_t | y_{1:t−1}]`` ``[..., T, dx]``.
        pred_covs: ``[..., T, dx, dx]``.
        innovations: ``y_t − E[y_t | y_{1:t−1}]`` ``[..., T, dy]`` (0 on an entry not
            received: :func:`~difffilter.linalg.masked_measurement`).
        innovation_covs: ``S_t`` ``[..., T, dy, dy]`` (an entry not received has the row
            and column of the identity: unit variance, uncorrelated).
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

    @classmethod
    def from_output(cls, out, **more) -> FilterResult:
        """The result held by an :class:`~difffilter.EstimatorOutput` of a filter (its
        ``extras`` carry the statistics that :func:`~difffilter.estimator.stack_steps`
        stacks); ``more``: the subclass's own fields."""
        x = out.extras
        return cls(
            means=out.means,
            covs=out.covs,
            pred_means=x.get("pred_means"),
            pred_covs=x.get("pred_covs"),
            innovations=x.get("innovations"),
            innovation_covs=x.get("innovation_covs"),
            log_likelihood_increments=x.get("log_likelihood_increments"),
            log_likelihood=x.get("log_likelihood"),
            nonfinite_skipped=x.get("nonfinite_skipped"),
            **more,
        )


@dataclass
class ParticleFilterResult(FilterResult):
    """Output of :func:`difffilter.particle_filter`.

    In addition to :class:`FilterResult` (weighted moments of the particles; the
    innovation covariance is the particle covariance of ``h(x)`` plus ``R``;
    ``pred_covs`` is ``None``):

    Attributes:
        ess: effective sample size after weighting ``[..., T]``.
        resampled: whether the particles were resampled before step ``t`` ``[..., T]``:
            the ESS fell below the threshold and the resampler was called (a resampler of
            your own that decides for itself, from ``__call__``, may have kept them).
        degenerate: whether every weight of the run underflowed at step ``t`` and was
            reset to the predictive weights ``[..., T]`` (see :mod:`difffilter.particle`).
        particles: ``[..., T, N, dx]`` when requested (``return_particles=True``), else ``None``.
        log_weights: normalised log-weights ``[..., T, N]`` when requested, else ``None``.
        records: what the filter's step hooks recorded, ``{name: [..., T, ...]}``.
        start: the step ``k`` the filter started from (its ``initial_state``'s; 0 from the
            prior), which :func:`difffilter.particle_smoother` reads a time-varying model at;
            ``None`` where the result was not made by :func:`difffilter.particle_filter`.
    """

    ess: Tensor | None = None
    resampled: Tensor | None = None
    degenerate: Tensor | None = None
    particles: Tensor | None = None
    log_weights: Tensor | None = None
    records: dict[str, Tensor] | None = None
    start: int | None = None
