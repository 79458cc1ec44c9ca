"""Extended and unscented Kalman filters: estimator objects and their whole-sequence runs.

EKF (first-order linearisation about the current estimate)::

    m⁻ = f(m, u, k)             P⁻ = F P Fᵀ + Q,        F = ∂f/∂x (m)
    r  = y − h(m⁻, k+1)         H = ∂h/∂x (m⁻)
    then the shared Joseph-form update (:func:`difffilter.kalman.gaussian_update`).

UKF (additive noise, scaled sigma points of Julier/van der Merwe): with
``λ = α²(n + κ) − n``, points ``X₀ = m``, ``X_{±i} = m ± √(n+λ) Lᵢ`` (``L`` the Cholesky
factor of ``P``), mean weights ``w₀ = λ/(n+λ)``, ``wᵢ = 1/(2(n+λ))`` and covariance
weight ``w₀ᶜ = w₀ + 1 − α² + β``::

    m⁻ = Σ w f(X)                P⁻ = Σ wᶜ (f(X) − m⁻)(·)ᵀ + Q
    ŷ  = Σ w h(X⁻)               Pyy = Σ wᶜ (h(X⁻) − ŷ)(·)ᵀ,  Pxy = Σ wᶜ (X⁻ − m⁻)(h(X⁻) − ŷ)ᵀ

where ``X⁻`` are sigma points redrawn from ``(m⁻, P⁻)``. The update uses ``K = Pxy S⁻¹``,
``S = Pyy + R`` and the Joseph form with the statistical linearisation
``H̃ = Pxyᵀ P⁻⁻¹`` and the noise ``R + Ω``, ``Ω = Pyy − H̃ P⁻ H̃ᵀ`` the linearisation's
error: ``P = P⁻ − K S Kᵀ``, the UKF's posterior, in a form that stays symmetric positive
semi-definite (``Ω`` formed as ``Σ wᶜ e eᵀ`` with ``e = h(X⁻) − ŷ − H̃ (X⁻ − m⁻)``, each
point's departure from the linearisation: the same matrix, never negative for
non-negative weights, where the difference lost that to round-off). On a linear model
``H̃ = H``, ``Ω = 0`` and both filters equal the KF exactly.
"""

from __future__ import annotations

import math
import warnings

import torch
from torch import Tensor

from ._checks import (
    NonFinite,
    broadcast_shapes,
    check_finite_number,
    method_matrices_batch,
    model_batch_shape,
    step_covariance,
)
from .gaussian import measurement_moments, predict_covariance, update_given
from .kalman import GaussianFilter, Prediction
from .linalg import NumericalBreakdown, masked_measurement, outer, safe_cholesky, symmetrize
from .loop import open_loop
from .results import FilterResult, GaussianState, StepOutput
from .ssm import StateSpaceModel, inputs_per_point, inputs_per_row, plain_residual, wrapped_spread

__all__ = [
    "ExtendedKalmanFilter",
    "UnscentedKalmanFilter",
    "extended_kalman_step",
    "extended_kalman_filter",
    "unscented_kalman_step",
    "unscented_kalman_filter",
    "SigmaPoints",
]


class ExtendedKalmanFilter(GaussianFilter):
    """The EKF as an estimator object (first-order linearisation about the estimate).

    ``predict``: ``F = ∂f/∂x(m)``, ``m⁻ = f(m, u)``, ``P⁻ = F P Fᵀ + Q``; ``update``: ``H =
    ∂h/∂x(m⁻)`` and the shared Joseph-form update with the model's residual (a wrapped
    angle stays wrapped). Jacobians from ``torch.func`` unless the model has closed forms.
    Carry: :class:`~difffilter.results.GaussianState`.
    """

    def predict(self, carry, u):
        model, k = carry.model, carry.k
        if torch.is_grad_enabled() and carry.mean.is_inference():
            # a carry stepped under torch.inference_mode() (inference tensors), now stepped
            # with gradients on: autograd cannot save its tensors for a model with
            # parameters, so step from their values (as the UKF's sigma points do; the
            # error had blamed the user's transition: a serialisation trial)
            carry = carry._replace(mean=carry.mean.clone(), cov=carry.cov.clone())
        # A torch.func Jacobian can come back in another dtype than the state (a model
        # function that builds a float64 constant from a Python float promotes it): cast, so
        # a float32 model stays float32 (and the products below do not mix dtypes).
        u = inputs_per_row(u, carry.mean)
        F = model.transition_jacobian(carry.mean, u, k).to(carry.mean.dtype)
        pred_mean = model.transition(carry.mean, u, k)
        return Prediction(
            pred_mean, predict_covariance(carry.cov, F, step_covariance(model, "process_cov", k))
        )

    def moments(self, carry, prediction, mask):
        model, k = carry.model, carry.k + 1
        H = model.observation_jacobian(prediction.mean, k).to(prediction.mean.dtype)
        return measurement_moments(
            prediction.cov, H, step_covariance(model, "measurement_cov", k), mask
        )

    def residual(self, carry, prediction, y):
        # the model's residual: a wrapped angle stays wrapped
        model, k = carry.model, carry.k + 1
        return model.measurement_residual(y, model.observe(prediction.mean, k))

    def update(self, carry, prediction, y, mask, *, evidence=True, moments=None):
        try:
            return self._moments_update(carry, prediction, y, mask, evidence, moments)
        except ValueError as exc:  # S failed: name the Jacobian where it is the cause
            k = carry.k + 1
            if not bool(torch.isfinite(prediction.mean).all()):  # (h was blamed for f's NaN)
                raise NumericalBreakdown(
                    f"the EKF's predicted mean at step {k} is NaN or inf: the transition f (or "
                    "its Jacobian) gave it from the previous estimate (e.g. a square root of a "
                    "negative level), so nothing could be linearised there"
                ) from exc
            if not bool(torch.isfinite(prediction.cov).all()) and bool(
                torch.isfinite(carry.cov).all()
            ):  # P⁻ = F P Fᵀ + Q from a finite P (the message had blamed S's Q, R and P0)
                raise NumericalBreakdown(
                    f"the EKF's predicted covariance F P Fᵀ + Q at step {k} is NaN or inf from a "
                    "finite P: the transition Jacobian ∂f/∂x is not finite at the previous "
                    "estimate (f not differentiable there, e.g. a square root of a level at 0: "
                    "the UKF or a particle filter can run), or the covariance overflowed (an "
                    "unstable plant run long without measurements)"
                ) from exc
            H = carry.model.observation_jacobian(prediction.mean, k)
            if bool(torch.isfinite(H).all()):
                raise
            raise NumericalBreakdown(
                f"the observation Jacobian ∂h/∂x at step {k} holds NaN or inf at the predicted "
                "mean: h is not differentiable there (e.g. a range or bearing measured at the "
                "sensor's own position), so the EKF cannot linearise it (the UKF or a "
                "particle filter can run)"
            ) from exc


def extended_kalman_step(
    model: StateSpaceModel,
    state: GaussianState,
    y: Tensor,
    u: Tensor | None = None,
    mask: Tensor | None = None,
) -> tuple[GaussianState, StepOutput]:
    """One EKF step ``x_{k−1} → x_k``; shapes and input checks as in :func:`difffilter.kalman_step`."""
    return ExtendedKalmanFilter().step(state._replace(model=model), y, u, mask)


def extended_kalman_filter(
    model: StateSpaceModel,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    mask: Tensor | None = None,
    nonfinite: NonFinite | str = NonFinite.RAISE,
) -> FilterResult:
    """EKF over a whole sequence: ``ys [..., T, dy]``, ``us [..., T, du]``, ``mask [..., T, dy]``.

    Jacobians come from ``model.transition_jacobian``/``observation_jacobian``
    (``torch.func`` by default). Input checks and ``nonfinite`` as in
    :func:`difffilter.kalman_filter`. Returns a :class:`~difffilter.results.FilterResult`.
    """
    out = open_loop(ExtendedKalmanFilter(), model, ys, us, mask=mask, nonfinite=nonfinite)
    return FilterResult.from_output(out)


class SigmaPoints:
    """Scaled symmetric sigma points (van der Merwe 2004) for dimension ``n``.

    Defaults ``α = 1, β = 2, κ = 0`` keep every weight non-negative (the centre point's mean
    weight ``w₀ᵐ = 0``, its covariance weight ``w₀ᶜ = 1 − α² + β = 2``) so covariances stay
    positive semidefinite; a small ``α`` (e.g. 1e-3) concentrates the
    points but makes ``w₀`` large and negative.

    Precision: the moments are weighted sums whose weights reach ``|w₀| ≈ 1/α²`` and sum to
    1, so they lose about ``Σ|wᵢ| ≈ 2/α²`` of the dtype's precision relative to the
    points' magnitude. In float64 that is harmless down to ``α ≈ 1e-6``; in float32 a
    ``α = 1e-2`` gives means about 0.05 posterior standard deviations off on a linear
    model and ``α = 1e-3`` about 10 (a numerics trial, against the float64 Kalman filter;
    centring the sums on ``X₀`` does not help: the points' own differences carry the
    round-off). A UserWarning says so once per object where ``Σ|wᵢ| · ε > 1e-3``.
    """

    #: The precision lost to the weights' magnitude (``Σ|wᵢ| · ε``) above which
    #: :meth:`weights` warns.
    PRECISION_WARNING = 1e-3

    def __init__(self, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0):
        self.alpha, self.beta, self.kappa = alpha, beta, kappa  # (checked by __setattr__)

    def __setattr__(self, name, value):
        # finite numbers: a NaN or inf made a NaN covariance, blamed on P at the first step;
        # checked whenever set (assigned later, NaN had been blamed on the transition f, and
        # alpha = -0.5 ran: a trial of the sigma-point filters)
        if name in ("alpha", "beta", "kappa"):
            value = check_finite_number(value, name, positive=name == "alpha")
        super().__setattr__(name, value)

    def weights(self, n: int, dtype, device) -> tuple[Tensor, Tensor, float]:
        """Mean weights ``[2n+1]``, covariance weights ``[2n+1]`` and the scale ``√(n+λ)``."""
        try:
            lam = self.alpha**2 * (n + self.kappa) - n
        except OverflowError:  # (a bare "Numerical result out of range" for alpha = 1e160)
            lam = math.inf
        if not math.isfinite(lam):
            raise ValueError(
                f"sigma-point scaling alpha² (n + kappa) overflows for alpha = {self.alpha!r}, "
                f"kappa = {self.kappa!r}: give alpha of order 1 (the points spread as alpha·√n)"
            )
        if n + lam <= 0:
            raise ValueError(
                f"sigma-point scaling gives n + λ = {n + lam} ≤ 0; raise alpha or kappa"
            )
        wm = torch.full((2 * n + 1,), 0.5 / (n + lam), dtype=dtype, device=device)
        wm[0] = lam / (n + lam)
        wc = wm.clone()
        wc[0] = wm[0] + 1.0 - self.alpha**2 + self.beta
        if dtype.is_floating_point:
            self._warn_precision(n, lam, dtype)
        return wm, wc, (n + lam) ** 0.5

    def _warn_precision(self, n: int, lam: float, dtype) -> None:
        """Warn, once per ``(n, dtype)``, where the weights' magnitude costs more than
        :attr:`PRECISION_WARNING` of ``dtype``'s precision (class docstring)."""
        lost = (abs(lam) + n) / (n + lam) * torch.finfo(dtype).eps
        # (a memo: ``*_cache``, which a settings fingerprint leaves out)
        warned = self.__dict__.setdefault("_warning_cache", set())
        if lost <= self.PRECISION_WARNING or (n, dtype) in warned:
            return
        warned.add((n, dtype))
        name = str(dtype).removeprefix("torch.")
        warnings.warn(
            f"SigmaPoints(alpha={self.alpha:g}) in {name}: the sigma-point weights reach "
            f"{abs(lam) / (n + lam):.3g} in magnitude, so the unscented moments carry {name} "
            f"round-off of about {lost:.1g} × the points' magnitude (a linear model's "
            "UKF then differs visibly from its Kalman filter); use float64 or a larger "
            "alpha (e.g. the default 1)",
            UserWarning,
            stacklevel=3,
        )

    def points(self, mean: Tensor, cov: Tensor, scale: float) -> Tensor:
        """Sigma points ``[..., 2n+1, n]`` of ``N(mean [..., n], cov [..., n, n])``."""
        L = safe_cholesky(cov, name="state covariance P") * scale
        cols = L.transpose(-1, -2)  # row i = i-th column of L
        batch = broadcast_shapes(mean.shape[:-1], cols.shape[:-2])
        mean = mean.expand(batch + mean.shape[-1:]).unsqueeze(-2)
        cols = cols.expand(batch + cols.shape[-2:])
        return torch.cat([mean, mean + cols, mean - cols], dim=-2)


def _moments(points: Tensor, wm: Tensor, wc: Tensor) -> tuple[Tensor, Tensor]:
    mean = (wm[:, None] * points).sum(-2)
    dev = points - mean.unsqueeze(-2)
    return mean, (wc[:, None, None] * outer(dev, dev)).sum(-3)


class UnscentedKalmanFilter(GaussianFilter):
    """The UKF as an estimator object (module docstring).

    Args:
        sigma_points: :class:`SigmaPoints` ``(α, β, κ)`` (default ``SigmaPoints(1, 2, 0)``).

    Carry: :class:`~difffilter.results.GaussianState`.
    """

    def __init__(self, sigma_points: SigmaPoints | None = None):
        self.sigma_points = sigma_points  # (checked by __setattr__; None: the defaults)

    def __setattr__(self, name, value):
        # checked whenever set (None or a tuple assigned later had failed on "'NoneType'
        # object has no attribute 'weights'": a trial), None read as the constructor reads it
        if name == "sigma_points":
            _check_sigma_points(value)
            value = value or SigmaPoints()
        super().__setattr__(name, value)

    def _init(self, model, batch_shape, generators):
        own = model_batch_shape(model, matrices_only=True) or method_matrices_batch(model)
        # sigma points [..., 2n+1, n] meet F and H: a raw shape error in torch (one set of a
        # batch of one, [1, n, n], is one model: it had been refused, a trial)
        if own and torch.Size(own).numel() > 1:
            raise ValueError(
                f"the UKF evaluates f and h on sigma points, and this model's F, B or H have "
                f"batch shape {tuple(own)} (one per run): use the Kalman filter or the EKF, "
                "which take them (a batched prior or noise is fine here)"
            )
        return super()._init(model, batch_shape, generators)

    def predict(self, carry, u):
        model, k, sp = carry.model, carry.k, self.sigma_points
        wm, wc, scale = sp.weights(carry.mean.shape[-1], carry.mean.dtype, carry.mean.device)
        try:
            X = sp.points(carry.mean, carry.cov, scale)  # [..., 2n+1, n]
        except ValueError as exc:
            _blame_nonfinite(exc, carry.mean, carry.cov, f"the UKF's estimate at step {k}",
                             "the measurement function h (or the transition f before it) gave "
                             "it on the sigma points")  # fmt: skip
            raise
        FX = model.transition(X, inputs_per_point(u, X), k)
        pred_mean, pred_cov = _moments(FX, wm, wc)
        return Prediction(
            pred_mean, symmetrize(pred_cov + step_covariance(model, "process_cov", k))
        )

    def update(self, carry, prediction, y, mask, *, evidence=True, moments=None):
        # (no shared moments: the sigma points' statistics are recomputed each update)
        model, k, sp = carry.model, carry.k + 1, self.sigma_points
        pred_mean, pred_cov = prediction
        wm, wc, scale = sp.weights(pred_mean.shape[-1], pred_mean.dtype, pred_mean.device)
        try:
            Xp = sp.points(pred_mean, pred_cov, scale)
        except ValueError as exc:  # (it had read as a covariance that overflowed)
            _blame_nonfinite(exc, pred_mean, pred_cov, f"the UKF's prediction at step {k}",
                             "the transition f gave it on the sigma points of the previous "
                             "estimate (e.g. a square root of a negative level), or the "
                             "points' spread √(n + λ)·√P overflowed (a large alpha)")  # fmt: skip
            raise
        Y = model.observe(Xp, k)  # [..., 2n+1, dy]
        if plain_residual(model):
            y_hat = (wm[:, None] * Y).sum(-2)
            dy_pts = Y - y_hat.unsqueeze(-2)
        else:  # angles: averaged as residuals about one point, not as raw numbers
            y_hat, dy_pts = wrapped_spread(model, Y, wm, centre=Y[..., 0, :])
        dx_pts = Xp - pred_mean.unsqueeze(-2)
        residual = model.measurement_residual(y, y_hat)
        if mask is not None:  # (a where: h NaN at an unreceived entry had stopped the update)
            received = mask if mask.dtype == torch.bool else mask != 0
            dy_pts = torch.where(received.unsqueeze(-2), dy_pts, 0.0)
        eye_y = torch.eye(Y.shape[-1], dtype=Y.dtype, device=Y.device)
        residual, _, R, observed = masked_measurement(
            residual, eye_y, step_covariance(model, "measurement_cov", k), mask
        )
        cross = (wc[:, None, None] * outer(dx_pts, dy_pts)).sum(-3)  # Pxy [..., n, dy]
        pyy = (wc[:, None, None] * outer(dy_pts, dy_pts)).sum(-3)
        # Statistical linearisation H̃ = Pxyᵀ P⁻⁻¹ for the Joseph form, whose noise is R plus
        # the linearisation's error Ω = Pyy − H̃ P⁻ H̃ᵀ: then P = P⁻ − K S Kᵀ, the UKF's
        # posterior (with R alone it came out smaller by K Ω Kᵀ: overconfident on a
        # nonlinear model, Var 0.062 where the UKF's is 0.113 in one review's step)
        H_stat = _statistical_gain(pred_cov, cross).transpose(-1, -2)
        # Ω = Pyy − H̃ Pxy (H̃ P⁻ H̃ᵀ = H̃ Pxy), formed as the weighted sum of the points'
        # linearisation residuals e = dy − H̃ dx, Ω = Σ wᶜ e eᵀ (equal, since Σ wᶜ dx dxᵀ =
        # P⁻): positive semidefinite by construction for non-negative weights. The
        # difference lost that to round-off where R is tiny beside Pyy (a numerics trial: a
        # posterior with a negative eigenvalue, then a jittered factor and 4.25 nats off)
        lin_err = dy_pts - dx_pts @ H_stat.transpose(-1, -2)
        omega = symmetrize((wc[:, None, None] * outer(lin_err, lin_err)).sum(-3))
        mean, cov, S, log_lik = update_given(
            pred_mean, pred_cov, residual, cross, symmetrize(pyy + R), H_stat, R + omega,
            observed, evidence, mask,
        )  # fmt: skip
        out = StepOutput(mean, cov, pred_mean, pred_cov, residual, S, log_lik)
        return GaussianState(mean, cov, k, model), out


def _statistical_gain(pred_cov: Tensor, cross: Tensor) -> Tensor:
    """``P⁻⁻¹ Pxy`` ``[..., n, dy]``, by the pseudo-inverse where ``P⁻`` is singular (a
    process noise that leaves a state known, a reset: it raised in the solve, where the
    Kalman filter and the EKF run). On the range of ``P⁻``, where ``Pxy`` lies, it is the
    same map: ``Ω`` and the Joseph form are unchanged."""
    gain, info = torch.linalg.solve_ex(pred_cov, cross)
    if info.device.type != "meta" and bool(info.any()):  # (shapes only: nothing to read)
        gain = torch.linalg.pinv(pred_cov, hermitian=True) @ cross
    return gain


def _blame_nonfinite(exc: Exception, mean: Tensor, cov: Tensor, what: str, cause: str) -> None:
    """A :class:`NumericalBreakdown` naming ``what`` and its ``cause`` where ``mean`` or
    ``cov`` is not finite (the error ``exc`` had named an overflowed covariance, not the
    step or the function); nothing otherwise."""
    if mean.device.type == "meta" or (bool(torch.isfinite(mean).all())
                                      and bool(torch.isfinite(cov).all())):  # fmt: skip
        return
    raise NumericalBreakdown(f"{what} is NaN or inf: {cause}") from exc


def unscented_kalman_step(
    model: StateSpaceModel,
    state: GaussianState,
    y: Tensor,
    u: Tensor | None = None,
    mask: Tensor | None = None,
    sigma_points: SigmaPoints | None = None,
) -> tuple[GaussianState, StepOutput]:
    """One UKF step ``x_{k−1} → x_k``; shapes and input checks as in :func:`difffilter.kalman_step`."""
    return UnscentedKalmanFilter(sigma_points).step(state._replace(model=model), y, u, mask)


def _check_sigma_points(sigma_points) -> None:
    if sigma_points is not None and not isinstance(sigma_points, SigmaPoints):
        raise TypeError(
            f"sigma_points must be a SigmaPoints object (e.g. SigmaPoints(alpha=1.0)); "
            f"got {type(sigma_points).__name__}"
        )


def unscented_kalman_filter(
    model: StateSpaceModel,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    mask: Tensor | None = None,
    sigma_points: SigmaPoints | None = None,
    nonfinite: NonFinite | str = NonFinite.RAISE,
) -> FilterResult:
    """UKF over a whole sequence; shapes, input checks and ``nonfinite`` as in
    :func:`extended_kalman_filter`.

    ``sigma_points`` sets ``(α, β, κ)`` (default ``SigmaPoints(1, 2, 0)``).
    """
    estimator = UnscentedKalmanFilter(sigma_points)
    out = open_loop(estimator, model, ys, us, mask=mask, nonfinite=nonfinite)
    return FilterResult.from_output(out)
