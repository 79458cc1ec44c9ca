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

Where the actuators hold their last applied input instead (``on_loss="hold"``; Schenato,
"To zero or to hold control inputs with lossy links?", IEEE TAC 54(5), 2009, compares the
two), the applied input is a state of its own, ``z_{k−1} = N_k u_{k−1} + (I − N_k) z_{k−2}``
(``z_{−1} = 0``, the loop's ``ū``), so the filter runs on ``s_k = [x_k; z_{k−1}]``
(``[dx + du]``). With ``δ = N_k − E[N_k]`` independent of ``s``, ``s_k = Ā s_{k−1} + ν̄ G u
+ G δ (u − z) + [w; 0]`` for ``G = [B; I]`` and ``Ā = [[F, B(I − ν̄)], [0, I − ν̄]]``, so the
same linear minimum-mean-square-error predictor is::

    m_z⁻ = m_z + ν̄ ⊙ (u − m_z),             m_x⁻ = F m_x + B m_z⁻
    P⁻   = Ā P Āᵀ + blkdiag(Q, 0) + G V Gᵀ,  d = u − m_z
    V    = ν̄(1 − ν̄) (d dᵀ + P_zz)                     (one packet)
    V    = diag(ν̄ ⊙ (1 − ν̄) ⊙ (d ⊙ d + diag P_zz))    (one per actuator)

and the Kalman update with ``[H, 0]``. The steps report ``x``'s moments; the held input's
mean and covariance are in ``extras`` (``"held_input"``, ``"held_input_cov"``). Both
predictors take the arrivals independent from step to step (a Bernoulli channel); under
bursts of loss (:class:`~difffilter.models.schedules.BurstLoss`) they are a linear
estimator that ignores the bursts, not a consistent one (a review, the DC motor of
docs/your-own-plant.md under bursts at the stationary rate: NEES 3.5 for ``dx = 2`` at
input amplitude 1 and 37 at 10, where packet loss at that rate gives about 2; the
evaluation's registry leaves it out there).
"""

from __future__ import annotations

import numbers

import numpy as np
import torch
from torch import Tensor

from ._assignments import note_assignment
from ._checks import check_carry_fits_model, check_carry_tensor, step_covariance
from .gaussian import measurement_moments, predict_covariance
from .input_loss import OnLoss, on_loss_of
from .kalman import (
    KalmanFilter,
    Prediction,
    _check_declared_time_varying,
    _check_linear,
    _check_zero_mean_noise,
    gaussian_init,
)
from .linalg import matvec, symmetrize
from .results import GaussianState

__all__ = ["ExpectedInputKalmanFilter"]


class ExpectedInputKalmanFilter(KalmanFilter):
    """The Kalman filter that predicts with the expected applied input (module docstring).

    Args:
        arrival_rate: ``ν̄``, the probability that an input packet arrives: a number in
            ``(0, 1]``, or (``independent=True``) one per actuator, a sequence or tensor
            ``[du]``.
        independent: ``False`` (default): one packet carries every actuator's input;
            ``True``: each actuator's packet arrives on its own.
        on_loss: what the actuators apply when a packet is lost, as the loop's
            :class:`~difffilter.input_loss.InputLoss`: ``"zero"`` (default) or ``"hold"``
            (the held input estimated with the state: module docstring).

    Steps with the sent input ``u`` (``closed_loop``'s ``Trajectories.us`` under an
    unacknowledged :class:`~difffilter.input_loss.InputLoss`); ``arrival_rate=1`` is the
    Kalman filter. Give it the loop's ``on_loss``: a filter of zeroed inputs on a plant
    that holds them is not consistent (NEES 9.05 for ``dx = 2`` in a review, 2.00 with the
    matching filter). The rate is a number, not a parameter: no gradient reaches it.
    Carry: :class:`~difffilter.results.GaussianState`, of ``x`` (``"zero"``) or of
    ``[x; z]`` (``"hold"``: ``mean [..., dx + du]``); a Kalman filter's carry with a shared
    gain schedule is stepped without it (the schedule's covariances ignore the inputs).
    """

    def __init__(self, arrival_rate, *, independent: bool = False,
                 on_loss: OnLoss | str = OnLoss.ZERO):  # fmt: skip
        super().__init__()
        on_loss = on_loss_of(on_loss)
        independent = _independent(independent)
        rate = _arrival_rate(arrival_rate, independent)
        self.arrival_rate, self.independent, self.on_loss = rate, independent, on_loss

    #: Settings a carry is made for: one replaced after ``__init__`` is checked as
    #: ``__init__`` checks it, and the next step validates its carry against it in full (a
    #: lean step had broadcast one rate to two actuators, and stepped a ``"hold"`` carry
    #: ``[x; z]`` as ``"zero"``'s ``x`` into torch's shape error: a red-team trial).
    _CARRY_SETTINGS = frozenset({"arrival_rate", "independent", "on_loss"})

    def __setattr__(self, name, value):
        if name not in self._CARRY_SETTINGS or name not in self.__dict__:
            super().__setattr__(name, value)
            return
        if name == "arrival_rate":
            value = _arrival_rate(value, self.independent)
        elif name == "independent":  # the rates held, as __init__ takes them with it
            value = _independent(value)
            super().__setattr__("arrival_rate", _arrival_rate(self.arrival_rate, value))
        else:
            value = on_loss_of(value)
        super().__setattr__(name, value)
        note_assignment()

    @property
    def carry_is_state(self) -> bool:
        """``False`` under ``"hold"``: the carry holds ``[x; z]``."""
        return self.on_loss is OnLoss.ZERO

    def _init(self, model, batch_shape, generators):
        _check_linear(model)
        _check_declared_time_varying(model)
        self._check_rates(model)
        state = gaussian_init(model, batch_shape)  # (no shared gains: P⁻ reads the inputs)
        if self.on_loss is OnLoss.ZERO:
            return state
        # (a time-varying model's B_k may be None at some steps, B_0 among them: no input
        # acts there, and the actuators still hold theirs; a trial had it refused)
        if model.dim_u == 0 or (
            not getattr(model, "time_varying", False) and model.control_matrix(0) is None
        ):
            raise ValueError(
                "ExpectedInputKalmanFilter(on_loss='hold') estimates the input the actuators "
                "hold, and this model has no input (B is None): use on_loss='zero' or a "
                "KalmanFilter"
            )
        # s_0 = [x_0; z_{−1}] with z_{−1} = 0 known (the loop's actuators start at zero)
        mean, du = state.mean, model.dim_u
        held = mean.new_zeros(mean.shape[:-1] + (du,))
        return GaussianState(torch.cat([mean, held], -1), _padded(state.cov, du), 0, model)

    def _step(self, carry, y, u, mask):
        carry = _ungained(carry)
        return self.update(carry, self.predict(carry, u), y, mask)

    def update(self, carry, prediction, y, mask, *, evidence=True, moments=None):
        new, out = super().update(_ungained(carry), prediction, y, mask, evidence=evidence,
                                  moments=moments)  # fmt: skip
        if self.on_loss is OnLoss.ZERO:
            return new, out
        mean, cov, held = self.reported(carry.model, new.mean, new.cov)
        pred_mean, pred_cov, _ = self.reported(carry.model, out.pred_mean, out.pred_cov)
        return new, out._replace(mean=mean, cov=cov, pred_mean=pred_mean, pred_cov=pred_cov,
                                 extras={**(out.extras or {}), **held})  # fmt: skip

    def reported(self, model, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor, dict]:
        """Under ``"hold"``: ``x``'s moments of a carry's ``[x; z]`` and the held input's as
        extras ``"held_input"`` ``[..., du]``, ``"held_input_cov"`` ``[..., du, du]``."""
        if self.on_loss is OnLoss.ZERO:
            return mean, cov, {}
        dx = model.dim_x
        held = {"held_input": mean[..., dx:], "held_input_cov": cov[..., dx:, dx:]}
        return mean[..., :dx], cov[..., :dx, :dx], held

    def __repr__(self) -> str:
        rate = self.arrival_rate.tolist()
        return (f"ExpectedInputKalmanFilter({rate!r}, independent={self.independent}, "
                f"on_loss={self.on_loss.value!r})")  # fmt: skip

    def moments(self, carry, prediction, mask):
        carry = _ungained(carry)
        if self.on_loss is OnLoss.ZERO:
            return super().moments(carry, prediction, mask)
        model, k = carry.model, carry.k + 1
        H = model.observation_matrix(k)
        H = torch.cat([H, H.new_zeros(H.shape[:-1] + (model.dim_u,))], -1)  # [H, 0]
        return measurement_moments(
            prediction.cov, H, step_covariance(model, "measurement_cov", k), mask
        )

    def residual(self, carry, prediction, y):
        dx = carry.model.dim_x
        return y - matvec(carry.model.observation_matrix(carry.k + 1), prediction.mean[..., :dx])

    def innovation(self, carry, prediction, y, mask, *, evidence: bool = True, moments=None):
        return super().innovation(_ungained(carry), prediction, y, mask, evidence=evidence,
                                  moments=moments)  # fmt: skip

    def predict(self, carry, u):
        if self.on_loss is OnLoss.HOLD:
            return self._predict_held(carry, u)
        model, k = carry.model, carry.k
        F, Q = model.transition_matrix(k), step_covariance(model, "process_cov", k)
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

    def _predict_held(self, carry, u):
        """The prediction of ``s = [x; z]`` under held inputs (module docstring)."""
        if u is None:
            raise ValueError(
                "ExpectedInputKalmanFilter(on_loss='hold') steps with the sent input u [..., du]; "
                "got None"
            )
        model, k = carry.model, carry.k
        F, Q, B = (
            model.transition_matrix(k),
            step_covariance(model, "process_cov", k),
            model.control_matrix(k),
        )
        dx, du = model.dim_x, model.dim_u
        if B is None:  # no input acts at this step (a time-varying B_k): B_k = 0, z still held
            B = F.new_zeros(F.shape[:-2] + (dx, du))  # (an AttributeError in matvec before)
        rate = self.arrival_rate.to(dtype=u.dtype, device=u.device)
        keep, spread = 1.0 - rate, rate * (1.0 - rate)
        mean, cov = carry.mean, carry.cov
        held, held_cov = mean[..., dx:], cov[..., dx:, dx:]
        gap = u - held  # d = u − m_z
        new_held = held + rate * gap
        new_x = matvec(F, mean[..., :dx]) + matvec(B, new_held)
        # Ā = [[F, B(I − ν̄)], [0, I − ν̄]] and G = [B; I], batched as F and B are
        lead = torch.broadcast_shapes(F.shape[:-2], B.shape[:-2])
        F, B = F.expand(lead + F.shape[-2:]), B.expand(lead + B.shape[-2:])
        eye = torch.eye(du, dtype=u.dtype, device=u.device).expand(lead + (du, du))
        kept = eye * keep  # I − ν̄ (diag(1 − ν̄) per actuator)
        A = torch.cat([torch.cat([F, B @ kept], -1),
                       torch.cat([F.new_zeros(lead + (du, dx)), kept], -1)], -2)  # fmt: skip
        G = torch.cat([B, eye], -2)
        if self.independent:  # V = diag(ν̄(1 − ν̄)(d² + diag P_zz))
            variance = spread * (gap.square() + torch.diagonal(held_cov, dim1=-2, dim2=-1))
            V = torch.diag_embed(variance)
        else:  # V = ν̄(1 − ν̄)(d dᵀ + P_zz)
            V = spread * (gap.unsqueeze(-1) * gap.unsqueeze(-2) + held_cov)
        pred_cov = predict_covariance(cov, A, _padded(Q, du)) + G @ V @ G.transpose(-1, -2)
        # (a model of per-run matrices on an unbatched carry: x's mean takes F's runs first)
        runs = torch.broadcast_shapes(new_x.shape[:-1], new_held.shape[:-1])
        joint = torch.cat([new_x.expand(runs + (dx,)), new_held.expand(runs + (du,))], -1)
        return Prediction(joint, symmetrize(pred_cov))

    def _check_rates(self, model) -> None:
        """One rate per actuator of ``model`` where the rates are per actuator."""
        rate = self.arrival_rate
        if rate.dim() == 1 and rate.shape[0] != model.dim_u:
            raise ValueError(
                f"arrival_rate holds {rate.shape[0]} rates, and the model has {model.dim_u} "
                "input(s): one rate per actuator"
            )

    def _check_carry(self, carry):
        # (here too: a Kalman filter's carry, which this filter may step, never saw _init;
        # one rate for two inputs had been broadcast to both, three had failed in torch)
        self._check_rates(carry.model)
        if self.on_loss is OnLoss.ZERO:
            return super()._check_carry(carry)
        # what the Kalman filter's checks hold of the model, its noise means (a noise of
        # non-zero mean assigned between steps had been dropped here: a red-team trial)
        _check_zero_mean_noise(carry.model)
        _check_linear(carry.model)
        width = carry.model.dim_x + carry.model.dim_u
        for name, t in (("mean", carry.mean), ("cov", carry.cov)):
            if not isinstance(t, Tensor) or t.dim() < 1 or t.shape[-1] != width:
                got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
                raise ValueError(
                    f"carry.{name} of ExpectedInputKalmanFilter(on_loss='hold') holds [x; z], the "
                    f"state and the input the actuators hold: [..., dx + du] = [..., {width}]; "
                    f"got {got} (a Kalman filter's carry? start from this filter's init)"
                )
        check_carry_tensor(carry.mean, "mean", dim=width)
        check_carry_tensor(carry.cov, "cov", dim=width, covariance=True)
        check_carry_fits_model(carry.model, mean=carry.mean, cov=carry.cov)

    def _run(self, carry, ys, us, mask):
        return None  # step by step: the covariances read the inputs


def _independent(independent) -> bool:
    if not isinstance(independent, bool):
        raise ValueError(f"independent must be True or False; got {independent!r}")
    return independent


def _arrival_rate(arrival_rate, independent: bool) -> Tensor:
    """``ν̄`` as a float64 tensor, ``[]`` or (``independent``) ``[du]``, checked."""
    if isinstance(arrival_rate, Tensor) and arrival_rate.dtype == torch.bool:
        # (a 0-d one had gone through float() to a rate of 1, where True is refused)
        raise ValueError(f"arrival_rate must hold probabilities, not booleans; got "
                         f"{arrival_rate!r}")  # fmt: skip
    if isinstance(arrival_rate, Tensor) and arrival_rate.dim() == 0:
        arrival_rate = float(arrival_rate)
    if (
        isinstance(arrival_rate, np.ndarray)
        and arrival_rate.ndim == 0
        and (arrival_rate.dtype.kind in "fiu")
    ):  # (a 0-d numpy array had been refused where a 0-d tensor was taken: a trial)
        arrival_rate = arrival_rate.item()
    if isinstance(arrival_rate, numbers.Real) and not isinstance(arrival_rate, bool):
        rate = torch.tensor(float(arrival_rate), dtype=torch.float64)
    elif isinstance(arrival_rate, (Tensor, list, tuple, np.ndarray)) and independent:
        listed = arrival_rate if isinstance(arrival_rate, (list, tuple)) else ()
        if getattr(arrival_rate, "dtype", None) in (torch.bool, np.bool_) or any(
            isinstance(r, (bool, np.bool_)) for r in listed
        ):  # (True, True) had been taken as rates of 1
            raise ValueError(f"arrival_rate must hold probabilities, not booleans; got "
                             f"{arrival_rate!r}")  # fmt: skip
        # (float64 from the numbers given: a tuple through float32 moved 0.3 by 1e-8)
        rate = torch.as_tensor(arrival_rate, dtype=torch.float64).detach().clone()
        if rate.dim() != 1 or rate.numel() == 0:
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
    return rate


def _padded(a: Tensor, extra: int) -> Tensor:
    """``[[a, 0], [0, 0]]`` ``[..., n + extra, n + extra]`` of ``a [..., n, n]``: a covariance
    of ``x`` as one of ``[x; z]`` with ``z`` known (the prior's ``z_{−1} = 0``) or noiseless
    (``Q``)."""
    return torch.nn.functional.pad(a, (0, extra, 0, extra))


def _ungained(carry):
    """``carry`` without a Kalman filter's shared gain schedule (whose covariances ignore
    the inputs: a KF's carry given to this filter went on with the KF's covariances)."""
    return carry if carry.gains is None else carry._replace(gains=None)
