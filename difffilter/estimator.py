"""The estimator contract: what every attack-aware filter and detector returns.

Every FDI estimator of :mod:`difffilter.fdi` is a function
``(model, ys, us=None, *, mask=None, ...) -> EstimatorOutput`` over a batch of runs:

* ``ys [B, T, dy]`` — received measurements ``ỹ_1 … ỹ_T`` (possibly attacked);
* ``us [B, T, du]`` or ``None`` — the inputs ``u_0 … u_{T−1}`` the estimator knows;
* ``mask [B, T, dy]`` (bool) or ``None`` — which entries were received (Round-Robin
  scheduling, packet loss); unreceived entries carry no information.

and returns the state estimate, optionally its covariance, optionally an estimate of the
injected attack signal, and optionally a per-step detection. Evaluation, training and
reports consume this one type, whatever the algorithm behind it; what a filter records
beyond it (the PF's ESS, the modified PF's ``ζ_k``, the NIS of a gated EKF) goes into
``extras`` under documented keys.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import torch
from torch import Tensor

__all__ = ["Detection", "EstimatorOutput"]


@dataclass
class Detection:
    """A per-step attack decision.

    Attributes:
        scores: ``[..., T]`` real; higher means "more likely attacked" (the statistic the
            detector thresholds: NIS, CUSUM sum, probability of attack, …). Used for ROC
            curves, so it must be comparable across steps.
        alarms: ``[..., T]`` bool, the decision ``l̂_k``.
        threshold: the threshold the alarms came from: a number, or ``[..., T]`` when it
            changes with the step (windowed χ², Remark 6's running ``ζ_k``). ``None``
            when the decision is not a threshold of ``scores``.
    """

    scores: Tensor
    alarms: Tensor
    threshold: Tensor | float | None = None

    def __post_init__(self):
        if self.scores.shape != self.alarms.shape:
            raise ValueError(
                f"scores and alarms must have the same shape [..., T]; got "
                f"{tuple(self.scores.shape)} and {tuple(self.alarms.shape)}"
            )
        if self.alarms.dtype != torch.bool:
            raise ValueError(f"alarms must be a bool tensor; got {self.alarms.dtype}")


@dataclass
class EstimatorOutput:
    """Output of an estimator over ``T`` steps of a batch of runs (time index ``t`` ↔ ``k = t + 1``).

    Attributes:
        means: state estimates ``x̂_k`` ``[..., T, dx]`` (after attack compensation where
            the estimator compensates).
        covs: their covariances ``[..., T, dx, dx]`` or ``None``.
        attack: estimate of the injected attack signal ``[..., T, da]`` (zero where the
            estimator believes there is none) or ``None`` for estimators that do not
            estimate it.
        detection: a :class:`Detection` or ``None`` for plain filters.
        extras: named per-run or per-step records of the algorithm (documented by each
            estimator), for example ``"ess" [..., T]``.
    """

    means: Tensor
    covs: Tensor | None = None
    attack: Tensor | None = None
    detection: Detection | None = None
    extras: dict[str, Tensor] = field(default_factory=dict)

    def __post_init__(self):
        if self.means.dim() < 2:
            raise ValueError(f"means must have shape [..., T, dx]; got {tuple(self.means.shape)}")
        lead = self.means.shape[:-1]
        if self.attack is not None and self.attack.shape[:-1] != lead:
            raise ValueError(
                f"attack must have shape [{', '.join(map(str, lead))}, da] like means; "
                f"got {tuple(self.attack.shape)}"
            )
        if self.detection is not None and self.detection.scores.shape != lead:
            raise ValueError(
                f"detection scores must have shape {tuple(lead)} (means without dx); "
                f"got {tuple(self.detection.scores.shape)}"
            )

    @property
    def alarms(self) -> Tensor | None:
        """Shortcut for ``detection.alarms`` (``None`` without a detection)."""
        return None if self.detection is None else self.detection.alarms

    @property
    def scores(self) -> Tensor | None:
        """Shortcut for ``detection.scores`` (``None`` without a detection)."""
        return None if self.detection is None else self.detection.scores

    def detach(self) -> EstimatorOutput:
        """A copy whose tensors are detached from the autograd graph."""

        def d(v):
            return v.detach() if isinstance(v, Tensor) else v

        det = self.detection
        if det is not None:
            det = Detection(d(det.scores), d(det.alarms), d(det.threshold))
        values = {f.name: d(getattr(self, f.name)) for f in fields(self)}
        values.update(detection=det, extras={k: d(v) for k, v in self.extras.items()})
        return replace(self, **values)
