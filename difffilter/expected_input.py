"""The Kalman filter of a plant whose input packets may be lost, unacknowledged (UDP-like).

Where the actuators apply zero when a packet is lost and nothing tells the estimator
which packets arrived (:class:`~difffilter.input_loss.InputLoss` with ``on_loss="zero"``,
``acknowledged=False``), the plant moves as ``x_k = F x_{k−1} + B N_k u_{k−1} + w_k`` with
``N_k`` the arrivals, unknown, independent of everything else, with mean ``ν̄``. The
linear minimum-mean-square-error predictor given the sent ``u`` (Schenato, Sinopoli,
Franceschetti, Poolla & Sastry, Proc. IEEE 95(1), 2007, the UDP-like estimator; one
packet for every actuator, ``N_k = ν_k I``)::

    m⁻ = F m + ν̄ B u
    P⁻ = F P Fᵀ + Q + ν̄ (1 − ν̄) (B u)(B u)ᵀ

and, with one packet per actuator (``independent=True``, ``N_k = diag(ν_k)``, rates ``ν̄``
``[du]``)::

    m⁻ = F m + B (ν̄ ⊙ u)
    P⁻ = F P Fᵀ + Q + B diag(ν̄ ⊙ (1 − ν̄) ⊙ u ⊙ u) Bᵀ

then the Kalman update. The input-dependent term is the variance of ``B N_k u`` about its
mean: the filter is consistent (its ``P`` the mean squared error over the arrivals) where
a Kalman filter given the sent input is not. Its covariances depend on the inputs, so
there is no shared gain schedule: every run keeps its own.
"""

from __future__ import annotations

import numbers

import torch
from torch import Tensor

from .gaussian import predict_covariance
from .kalman import (
    KalmanFilter,
    Prediction,
    _check_declared_time_varying,
    _check_linear,
    gaussian_init,
)
from .linalg import matvec, symmetrize

__all__ = ["ExpectedInputKalmanFilter"]


class ExpectedInputKalmanFilter(KalmanFilter):
    """The Kalman filter that predicts with the expected applied input (module docstring).

    Args:
        arrival_rate: ``ν̄``, the probability that an input packet arrives: a number in
            ``(0, 1]``, or (``independent=True``) one per actuator, a sequence or tensor
            ``[du]``.
        independent: ``False`` (default): one packet carries every actuator's input;
            ``True``: each actuator's packet arrives on its own.

    Steps with the sent input ``u`` (``closed_loop``'s ``Trajectories.us`` under an
    unacknowledged :class:`~difffilter.input_loss.InputLoss`); ``arrival_rate=1`` is the
    Kalman filter. Its model of the loss is the actuators' ``"zero"``: where they hold
    their last input the plant moves otherwise, and the filter is not consistent (a review:
    NEES 9.05 for ``dx = 2`` under ``"hold"``, 2.00 under ``"zero"``). The rate is a number,
    not a parameter: no gradient reaches it. Carry:
    :class:`~difffilter.results.GaussianState`; a Kalman filter's carry with a shared gain
    schedule is stepped without it (the schedule's covariances ignore the inputs).
    """

    def __init__(self, arrival_rate, *, independent: bool = False):
        super().__init__()
        if not isinstance(independent, bool):
            raise ValueError(f"independent must be True or False; got {independent!r}")
        if isinstance(arrival_rate, Tensor) and arrival_rate.dim() == 0:
            arrival_rate = float(arrival_rate)
        if isinstance(arrival_rate, numbers.Real) and not isinstance(arrival_rate, bool):
            rate = torch.tensor(float(arrival_rate), dtype=torch.float64)
        elif isinstance(arrival_rate, (Tensor, list, tuple)) and independent:
            rate = torch.as_tensor(arrival_rate, dtype=torch.float64).detach().clone()
            if rate.dim() != 1:
                raise ValueError(
                    f"arrival_rate must be a number or, with independent=True, one rate per "
                    f"actuator [du]; got shape {tuple(rate.shape)}"
                )
        else:
            raise ValueError(
                "arrival_rate must be a number in (0, 1] (or, with independent=True, one per "
                f"actuator [du]); got {arrival_rate!r}"
            )
        if not bool(((rate > 0) & (rate <= 1)).all()):
            raise ValueError(f"arrival_rate must lie in (0, 1]; got {arrival_rate!r}")
        self.arrival_rate, self.independent = rate, independent

    def _init(self, model, batch_shape, generators):
        _check_linear(model)
        _check_declared_time_varying(model)
        rate = self.arrival_rate
        if rate.dim() == 1 and rate.shape[0] != model.dim_u:
            raise ValueError(
                f"arrival_rate holds {rate.shape[0]} rates, and the model has {model.dim_u} "
                "input(s): one rate per actuator"
            )
        return gaussian_init(model, batch_shape)  # (no shared gains: P⁻ reads the inputs)

    def _step(self, carry, y, u, mask):
        carry = _ungained(carry)
        return self.update(carry, self.predict(carry, u), y, mask)

    def update(self, carry, prediction, y, mask, *, evidence=True, moments=None):
        return super().update(_ungained(carry), prediction, y, mask, evidence=evidence,
                              moments=moments)  # fmt: skip

    def moments(self, carry, prediction, mask):
        return super().moments(_ungained(carry), prediction, mask)

    def innovation(self, carry, prediction, y, mask, *, evidence: bool = True, moments=None):
        return super().innovation(_ungained(carry), prediction, y, mask, evidence=evidence,
                                  moments=moments)  # fmt: skip

    def predict(self, carry, u):
        model, k = carry.model, carry.k
        F, Q = model.transition_matrix(k), model.process_cov(k)
        mean, cov = matvec(F, carry.mean), predict_covariance(carry.cov, F, Q)
        B = model.control_matrix(k)
        if u is None or B is None:
            return Prediction(mean, cov)
        rate = self.arrival_rate.to(dtype=u.dtype, device=u.device)
        spread = rate * (1.0 - rate)
        if self.independent:  # B diag(ν̄(1 − ν̄) u²) Bᵀ
            mean = mean + matvec(B, rate * u)
            scaled = B * (spread * u.square()).unsqueeze(-2)
            extra = scaled @ B.transpose(-1, -2)
        else:  # ν̄(1 − ν̄) (Bu)(Bu)ᵀ
            Bu = matvec(B, u)
            mean = mean + rate * Bu
            extra = spread * Bu.unsqueeze(-1) * Bu.unsqueeze(-2)
        return Prediction(mean, symmetrize(cov + extra))

    def _run(self, carry, ys, us, mask):
        return None  # step by step: the covariances read the inputs


def _ungained(carry):
    """``carry`` without a Kalman filter's shared gain schedule (whose covariances ignore
    the inputs: a KF's carry given to this filter went on with the KF's covariances)."""
    return carry if carry.gains is None else carry._replace(gains=None)
