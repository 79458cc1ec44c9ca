"""Fixed-gain (Luenberger) observers as estimator objects.

A Luenberger observer in filter form with a gain ``L`` chosen beforehand (pole
placement; the LFC paper's "traditional" observer)::

    m⁻_k = F m_{k−1} + B u_{k−1}        r_k = y_k − H m⁻_k        m_k = m⁻_k + L r_k

It carries no covariance: the step output's ``cov``, ``pred_cov``, ``innovation_cov`` and
``log_likelihood`` are ``None``. It plugs into the attack-aware wrappers like the
Gaussian filters (:class:`~difffilter.kalman.GaussianFilter`'s ``predict``/``update``).
"""

from __future__ import annotations

from torch import Tensor

from ._checks import check_carry_fits_model, check_carry_tensor, check_finite
from .kalman import GaussianFilter, Prediction, _check_linear, gaussian_init
from .linalg import matvec
from .results import GaussianState, StepOutput

__all__ = ["FixedGainFilter"]


class FixedGainFilter(GaussianFilter):
    """The observer ``m_k = m⁻_k + L (y_k − H m⁻_k)`` of a linear model (module docstring).

    Args:
        gain: ``L [dx, dy]`` (filter form).

    Carry: :class:`~difffilter.results.GaussianState` (its ``cov`` is the prior's and
    never changes).
    """

    reports_innovation_cov = False  # a fixed gain, no S_k

    def __init__(self, gain: Tensor):
        self.gain = gain

    def __setattr__(self, name, value):
        # checked whenever set: a NaN gain had run, every estimate NaN from its first step
        # on (a trial), and one assigned after construction still did (a red-team trial)
        if name == "gain":
            if not isinstance(value, Tensor) or value.dim() != 2:
                raise ValueError(
                    f"gain must be a tensor [dx, dy]; got {getattr(value, 'shape', value)!r}"
                )
            # a complex gain (a modal design without .real) had run as its real part, an
            # integer or bool one cast without a word (an observers trial)
            if not value.is_floating_point():
                raise ValueError(f"gain must be a real floating tensor [dx, dy]; got {value.dtype}")
            check_finite(value, "gain")
        super().__setattr__(name, value)

    def _init(self, model, batch_shape, generators):
        _check_linear(model)
        self._check_gain_fits(model)
        return gaussian_init(model, batch_shape)

    def _check_gain_fits(self, model) -> None:
        # (at init and every update: a [1, 1] gain assigned between steps on a 2-state
        # model had added one correction to both states: an options trial)
        if self.gain.shape != (model.dim_x, model.dim_y):
            raise ValueError(
                f"gain must have shape [{model.dim_x}, {model.dim_y}]; got {tuple(self.gain.shape)}"
            )

    def _check_carry(self, carry):
        check_carry_tensor(carry.mean, "mean", dim=carry.model.dim_x)
        check_carry_fits_model(carry.model, mean=carry.mean)

    def predict(self, carry, u):
        model, k = carry.model, carry.k
        mean = matvec(model.transition_matrix(k), carry.mean)
        B = model.control_matrix(k)
        if B is not None and u is not None:
            mean = mean + matvec(B, u)
        return Prediction(mean, None)

    def update(self, carry, prediction, y, mask, *, evidence=True, moments=None):
        # (an observer reports no density; it has no moments to share)
        model, k = carry.model, carry.k + 1
        self._check_gain_fits(model)
        residual = y - matvec(model.observation_matrix(k), prediction.mean)
        if mask is not None:
            residual = residual * mask.to(residual.dtype)
        mean = prediction.mean + matvec(self.gain.to(residual.dtype), residual)
        out = StepOutput(mean, pred_mean=prediction.mean, innovation=residual)
        return GaussianState(mean, carry.cov, k, model), out
