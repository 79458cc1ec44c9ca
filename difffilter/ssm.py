"""State-space models: the interface every filter runs on.

Time convention (shared by every filter, simulator and result in difffilter)::

    x_0     ~ initial                         (prior, no measurement at k = 0)
    x_{k+1} = f(x_k, u_k, k) + w_k,   w_k ~ process_noise,      k = 0 … T−1
    y_k     = h(x_k, k) + v_k,        v_k ~ measurement_noise,  k = 1 … T

A measurement sequence ``ys [..., T, dy]`` holds ``y_1 … y_T``; ``us [..., T, du]`` holds
``u_0 … u_{T−1}`` (``us[..., t, :]`` drives the step to the state measured by
``ys[..., t, :]``). Filter outputs ``means[..., t, :]`` are ``E[x_{t+1} | y_{1:t+1}]``.
"""

from __future__ import annotations

import functools
import inspect
import math
import numbers
import threading
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from ._assignments import CountsAssignments
from ._checks import (
    _all_finite,
    _check_us,
    add_note,
    as_tensor,
    broadcast_or_none,
    broadcast_shapes,
    check_batch_shape,
    check_batch_shapes,
    check_finite,
    check_model,
    check_model_batch,
    check_model_dtype,
    check_positive_definite,
    check_positive_int,
    check_square,
    check_vector_last,
    model_dtype_device,
    values_known,
    version_stamp,
)
from .linalg import JACOBIAN_THREAD, matvec, rowwise, under_transform
from .noise import Gaussian, NoiseModel, _shape, register_tensor

__all__ = [
    "StateSpaceModel",
    "LinearGaussianModel",
    "NonlinearGaussianModel",
    "batched_jacobian",
    "wrapped_spread",
]


#: One thread at a time differentiates by ``torch.func``: its forward-mode levels are the
#: process's, and two threads' EKFs (one estimator, two carries, two models) interleaved
#: them: "invalid forward AD level" errors blamed on the model, results up to 0.85
#: posterior standard deviations off without an error, a segmentation fault (a deployment
#: trial). Re-entrant: a model function may itself take a Jacobian.
_JACOBIAN_LOCK = threading.RLock()


def batched_jacobian(
    fn: Callable[..., Tensor], x: Tensor, *args: Tensor | None, what: str | None = None
) -> Tensor:
    """Jacobian ``∂fn(x, *args)/∂x`` for every row of ``x [..., n]`` → ``[..., m, n]``.

    Uses ``torch.func.vmap(torch.func.jacfwd(fn))`` over the flattened leading dimensions,
    so ``fn`` must act on a single vector ``[n]`` (every model function in difffilter
    broadcasts over leading dimensions, so it does). ``args`` broadcast with ``x``'s
    leading dimensions; ``None`` arguments are passed through unbatched. ``what`` names
    ``fn`` in the error where ``torch.func`` cannot trace it.
    """
    lead = x.shape[:-1]
    for a in args:
        if a is not None:
            lead = broadcast_shapes(lead, a.shape[:-1])
    flat_x = x.expand(lead + x.shape[-1:]).reshape(-1, x.shape[-1])
    flat_args = []
    in_dims = [0]
    for a in args:
        if a is None:
            flat_args.append(None)
            in_dims.append(None)
        else:
            flat_args.append(a.expand(lead + a.shape[-1:]).reshape(-1, a.shape[-1]))
            in_dims.append(0)
    if torch.is_grad_enabled() and not torch.is_inference_mode_enabled():
        # a carry made under torch.inference_mode() holds inference tensors, which autograd
        # cannot save for a model with parameters: its values, as normal tensors (the
        # error had blamed the user's function: a serialisation trial)
        flat_x = flat_x.clone() if flat_x.is_inference() else flat_x
        flat_args = [a.clone() if a is not None and a.is_inference() else a for a in flat_args]
    empty = flat_x.shape[0] == 0
    if empty:
        # vmap over no rows hands fn a per-row view of no entries, on which a model's
        # x[..., 0] raises inside the user's code: differentiate one row of zeros for the
        # Jacobian's shape and keep none of it (a batch-dims trial: 0 runs had crashed the
        # EKF where the UKF and the PF return empty outputs)
        flat_x = flat_x.new_zeros((1,) + flat_x.shape[1:])
        flat_args = [a if a is None else a.new_zeros((1,) + a.shape[1:]) for a in flat_args]
    try:
        with _JACOBIAN_LOCK:
            # (under_transform: whose dual level; re-entrant, so the outer one is restored)
            outer, JACOBIAN_THREAD[0] = JACOBIAN_THREAD[0], threading.get_ident()
            try:
                jac = torch.func.vmap(torch.func.jacfwd(fn, argnums=0), in_dims=tuple(in_dims))(
                    flat_x, *flat_args
                )
            finally:
                JACOBIAN_THREAD[0] = outer
        if empty:
            jac = jac[:0]
    except RuntimeError as error:  # what torch.func says of numpy, .item(), ... is cryptic
        name = what or getattr(fn, "__qualname__", None) or type(fn).__name__
        raise RuntimeError(
            f"differentiating {name} with torch.func (an extended or unscented Kalman filter "
            "needs its Jacobian) failed: it must be written in torch operations on its input "
            "tensor (no numpy, .item(), .tolist(), .numpy() or Python branches on values); "
            "or give the model closed-form transition_jacobian/observation_jacobian. "
            f"torch said: {error}"
        ) from error
    # In x's dtype: a function that promotes (e.g. builds a float64 constant from a Python
    # float) would otherwise hand float64 Jacobians to a float32 filter.
    return jac.reshape(lead + jac.shape[-2:]).to(x.dtype)


class StateSpaceModel(CountsAssignments):
    """Base class of all state-space models (see the module docstring for the equations).

    Subclasses set ``dim_x``, ``dim_y``, ``dim_u`` (0 when there is no input) and the
    noise modules ``initial``, ``process_noise`` and ``measurement_noise``, and implement
    ``transition(x, u, k)`` and ``observe(x, k)``. Every method broadcasts over leading
    batch dimensions (runs ``B``, particles ``N``): ``x [..., dx]``, ``u [..., du]`` or
    ``None``, ``y [..., dy]``.

    Jacobians default to ``torch.func`` automatic differentiation; override
    ``transition_jacobian``/``observation_jacobian`` with closed forms when known.
    Time-varying noise: override ``process_cov(k)``/``measurement_cov(k)`` and set
    ``time_varying = True`` so filters do not cache them across steps. With Gaussian noise
    that is all: the default sampling and density hooks then draw from and evaluate
    ``N(loc, process_cov(k))``/``N(loc, measurement_cov(k))`` (:meth:`process_noise_at`,
    :meth:`measurement_noise_at`), so simulation, the particle filters and the Gaussian
    filters see one model. A non-Gaussian noise's hooks (``sample_transition``,
    ``sample_measurement``, ``measurement_log_prob``) are the subclass's to override too:
    its ``*_cov`` methods are read by the Gaussian filters only.
    """

    dim_x: int
    dim_y: int
    dim_u: int = 0
    time_varying: bool = False
    initial: NoiseModel
    process_noise: NoiseModel
    measurement_noise: NoiseModel

    # -- dynamics --------------------------------------------------------------------
    def transition(self, x: Tensor, u: Tensor | None, k: int) -> Tensor:
        """Mean of ``x_{k+1}`` given ``x_k`` ``[..., dx]`` and ``u_k`` ``[..., du]`` → ``[..., dx]``."""
        raise NotImplementedError

    def observe(self, x: Tensor, k: int) -> Tensor:
        """Mean of ``y_k`` given ``x_k`` ``[..., dx]`` → ``[..., dy]``."""
        raise NotImplementedError

    def transition_jacobian(self, x: Tensor, u: Tensor | None, k: int) -> Tensor:
        """``∂f/∂x`` at ``x [..., dx]`` → ``[..., dx, dx]`` (autodiff by default)."""
        return batched_jacobian(lambda xi, ui: self.transition(xi, ui, k), x, u,
                                what=f"the transition of {type(self).__name__}")  # fmt: skip

    def observation_jacobian(self, x: Tensor, k: int) -> Tensor:
        """``∂h/∂x`` at ``x [..., dx]`` → ``[..., dy, dx]`` (autodiff by default)."""
        return batched_jacobian(lambda xi: self.observe(xi, k), x,
                                what=f"the observation of {type(self).__name__}")  # fmt: skip

    # -- noise -----------------------------------------------------------------------
    def process_cov(self, k: int) -> Tensor:
        """Covariance ``Q_k`` of ``w_k`` ``[..., dx, dx]``."""
        return self.process_noise.cov

    def measurement_cov(self, k: int) -> Tensor:
        """Covariance ``R_k`` of ``v_k`` ``[..., dy, dy]``."""
        return self.measurement_noise.cov

    def process_noise_at(self, k: int) -> NoiseModel:
        """The noise model of ``w_k``: ``process_noise``, or a Gaussian of covariance
        ``process_cov(k)`` about its mean where a subclass overrides :meth:`process_cov` and
        the noise is Gaussian (time-varying noise, one override)."""
        return self._noise_at("process_noise", "process_cov", k)

    def measurement_noise_at(self, k: int) -> NoiseModel:
        """The noise model of ``v_k``: ``measurement_noise``, or a Gaussian of covariance
        ``measurement_cov(k)`` about its mean where a subclass overrides
        :meth:`measurement_cov` and the noise is Gaussian."""
        return self._noise_at("measurement_noise", "measurement_cov", k)

    def _varying_noise(self, cov_method: str) -> bool:
        """Whether this model's class overrides ``cov_method`` (``"process_cov"`` or
        ``"measurement_cov"``), or the model holds one of its own (assigned on the object:
        read by the Gaussian filters, it had been left out of ``simulate`` and the particle
        filters, which drew with the noise module's, 100 times smaller: a trial), i.e. its
        noise may differ from the noise module's at some step: fast paths that read the
        noise module directly step aside."""
        return (getattr(type(self), cov_method) is not getattr(StateSpaceModel, cov_method)
                or cov_method in self.__dict__)  # fmt: skip

    def _noise_at(self, noise_name: str, cov_method: str, k: int) -> NoiseModel:
        noise = getattr(self, noise_name)
        if not (isinstance(noise, Gaussian) and self._varying_noise(cov_method)):
            return noise
        try:
            return Gaussian(noise.loc, getattr(self, cov_method)(k))
        except ValueError as exc:  # (it said "cov must be …", naming neither method nor step)
            singular = ("; a singular covariance runs in the Kalman filters but cannot be "
                        "drawn from: override sample_transition, sample_measurement and "
                        "measurement_log_prob for it"
                        if "positive definite" in str(exc) else "")  # fmt: skip
            raise ValueError(
                f"{type(self).__name__}.{cov_method}({k}) (what simulate and the particle "
                f"filters draw and weigh with): {exc}{singular}"
            ) from exc

    def sample_initial(self, sample_shape=(), generator: torch.Generator | None = None) -> Tensor:
        """Draw ``x_0`` ``[*sample_shape, dx]``; a prior with one mean or covariance per run
        (batch ``[B]``) draws ``[*broadcast(sample_shape, B), dx]``, one per run (``sample``
        would prepend ``sample_shape`` to its batch: 16 runs for a sweep of 4)."""
        initial = self.initial
        if _has_batch(initial):
            runs = broadcast_shapes(_shape(sample_shape), initial.batch_shape)
            return _draw_per_run(initial, runs + (initial.dim,), generator)
        return initial.sample(sample_shape, generator)

    def sample_transition(self, x: Tensor, u: Tensor | None, k: int, generator=None) -> Tensor:
        """Draw ``x_{k+1} ~ p(· | x_k)`` for ``x [..., dx]`` → ``[..., dx]``."""
        mean = self.transition(x, u, k)
        process_noise = self.process_noise_at(k)
        perturb = getattr(process_noise, "perturb", None)
        if perturb is not None:  # fused mean + noise where the noise model offers it
            return perturb(mean, generator)
        if _has_batch(process_noise):  # one noise per run
            return mean + _draw_per_run(process_noise, mean.shape, generator)
        noise = process_noise.sample(mean.shape[:-1], generator)
        return mean + noise.reshape(mean.shape)

    def sample_measurement(self, x: Tensor, k: int, generator=None) -> Tensor:
        """Draw ``y_k ~ p(· | x_k)`` for ``x [..., dx]`` → ``[..., dy]``."""
        mean = self.observe(x, k)
        measurement_noise = self.measurement_noise_at(k)
        if _has_batch(measurement_noise):  # one noise (an R, a box) per run
            return mean + _draw_per_run(measurement_noise, mean.shape, generator)
        noise = measurement_noise.sample(mean.shape[:-1], generator)
        return mean + noise.reshape(mean.shape)

    def measurement_residual(self, y: Tensor, y_hat: Tensor) -> Tensor:
        """``y − ŷ`` ``[..., dy]`` (broadcasting); a model with angles overrides it to wrap them.

        The Gaussian filters' innovations, the Kalman proposal and
        ``measurement_log_prob`` all go through it.
        """
        return rowwise(torch.sub, y, y_hat)

    def measurement_log_prob(
        self, y: Tensor, x: Tensor, k: int, mask: Tensor | None = None
    ) -> Tensor:
        """``log p(y_k | x_k)`` of the received entries: ``y [..., dy]``, ``x [..., dx]`` → ``[...]``.

        ``mask [..., dy]`` marks received entries; unreceived ones are marginalised out.
        """
        return self.measurement_noise_at(k).log_prob(
            self.measurement_residual(y, self.observe(x, k)), mask=mask
        )

    # -- simulation ------------------------------------------------------------------
    @torch.no_grad()
    def simulate(
        self,
        num_steps: int,
        batch_shape=(),
        us: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Simulate ``x_0 … x_T`` and ``y_1 … y_T``.

        Returns ``(xs [*batch, T, dx], ys [*batch, T, dy], x0 [*batch, dx])`` where
        ``xs[..., t, :] = x_{t+1}`` is the state measured by ``ys[..., t, :]``; ``batch`` is
        ``batch_shape`` broadcast with the model's parameter sets (a model of ``B`` sets:
        ``B`` runs, or ``(N, B)`` for ``batch_shape=(N, 1)``).
        """
        num_steps = check_positive_int(num_steps, "num_steps")
        # the noise models in the model's dtype, as every filter checks: a float64
        # measurement noise on a float32 model had simulated float32 xs beside float64 ys,
        # and a float64 process noise failed in torch's words at the second step
        check_model(self)
        batch_shape = check_batch_shape(batch_shape, least=0)
        # the runs: a model of B parameter sets simulates B runs (as the filters read it)
        batch_shape = check_model_batch(self, batch_shape, "batch_shape")
        if us is not None:  # ignored before on a model without input; a short one raised late
            dtype, device = model_dtype_device(self)
            us = _check_us(self, us, batch_shape, num_steps, dtype, device, "the runs'")
        x = self.sample_initial(batch_shape, generator)
        x0 = x
        xs, ys = [], []
        for t in range(num_steps):
            u = None if us is None else us[..., t, :]
            x = self.sample_transition(x, u, t, generator)
            xs.append(x)
            ys.append(self.sample_measurement(x, t + 1, generator))
        return torch.stack(xs, -2), torch.stack(ys, -2), x0


def _has_batch(noise) -> bool:
    """Whether ``noise`` has one set of parameters per run (its ``has_batch()``; a noise
    object without that method is taken to have none)."""
    has_batch = getattr(noise, "has_batch", None)
    return has_batch is not None and bool(has_batch())


def _draw_per_run(noise, shape, generator: torch.Generator | None = None) -> Tensor:
    """Draws ``[*shape]`` (``shape = [..., d]``) from a batched noise model, independent at
    every entry of ``shape[:-1]``, whose trailing dimensions take the noise's batch (one box
    per run: ``[B, d]`` bounds for draws ``[B, d]``). ``sample`` prepends its shape to the
    batch instead: a batched prior drawn as ``sample((B,))`` had made ``B × B`` runs, and a
    batched process or measurement noise failed in a reshape (a noise trial).

    A Gaussian draws through :meth:`~difffilter.noise.Gaussian.draw_like`; any other noise
    through ``sample(lead)``, ``lead`` the runs' leading dimensions in front of its batch,
    with one more leading dimension for each batch dimension of 1 that spreads over several
    runs (its draws are moved onto that dimension)."""
    if isinstance(noise, Gaussian):
        return noise.draw_like(shape, generator)
    shape, batch = torch.Size(shape), noise.batch_shape
    runs = shape[:-1]
    if broadcast_or_none(runs, batch) != runs or shape[-1:] != (noise.dim,):
        raise ValueError(
            f"this {type(noise).__name__} has one set of parameters per run (batch "
            f"{tuple(batch)}), which does not fit draws of shape {tuple(shape)}: its batch must "
            "match their trailing batch dimensions (a particle filter takes one model for all runs)"
        )
    at = len(runs) - len(batch)
    lead, tail = runs[:at], runs[at:]
    spread = [i for i in range(len(batch)) if batch[i] != tail[i]]  # a batch of 1 over runs
    draws = noise.sample(lead + torch.Size(tail[i] for i in spread), generator)
    if spread:  # [*lead, *spread runs, *batch, d] → [*lead, *tail, d]
        first = len(lead) + len(spread)
        draws = draws.squeeze(tuple(first + i for i in spread))
        draws = draws.movedim(tuple(range(len(lead), first)), tuple(len(lead) + i for i in spread))
    return draws.reshape(shape)


def inputs_per_point(u: Tensor | None, points: Tensor) -> Tensor | None:
    """``u [..., du]`` beside ``points [..., M, dx]`` (sigma points, particles): one row per
    point, ``[..., M, du]`` (a view). A transition that joins ``x`` and ``u`` (``torch.cat``)
    had failed on ``[..., 1, du]`` in the UKF and the particle filters, where the EKF and
    the model's own width check take it."""
    if u is None:
        return None
    lead = torch.broadcast_shapes(u.shape[:-1] + (1,), points.shape[:-1])
    return u.unsqueeze(-2).expand(*lead, u.shape[-1])


def inputs_per_row(u: Tensor | None, x: Tensor) -> Tensor | None:
    """``u [..., du]`` beside states ``x [..., dx]``: one row per run, ``u`` broadcast to
    ``x``'s runs (a view). One input sequence shared by a batch of runs (``us [T, du]``
    beside ``ys [B, T, dy]``) had reached a transition that joins ``x`` and ``u``
    (``torch.cat``) unbatched in the EKF and its smoother, and failed there, where the UKF
    and the particle filters (:func:`inputs_per_point`) take it."""
    if u is None or u.shape[:-1] == x.shape[:-1]:
        return u
    lead = torch.broadcast_shapes(u.shape[:-1], x.shape[:-1])
    return u.expand(*lead, u.shape[-1])


def plain_residual(model) -> bool:
    """Whether ``model`` keeps the base class's ``y − ŷ`` (no angle to wrap)."""
    return type(model).measurement_residual is StateSpaceModel.measurement_residual


#: Re-centring passes of :func:`wrapped_spread` after its first mean.
RECENTRING_PASSES = 2


def wrapped_spread(model, points: Tensor, weights: Tensor,
                   centre: Tensor | None = None) -> tuple[Tensor, Tensor]:  # fmt: skip
    """The weighted mean ``ŷ [..., dy]`` of predicted measurements ``points [..., n, dy]``
    (sigma points' or particles') and their deviations ``[..., n, dy]`` for a model whose
    ``measurement_residual`` wraps angles, under ``weights [..., n]`` (summing to 1).

    Where no deviation from the plain weighted mean wraps (the residual equals the plain
    difference) and the cloud spans less than half a turn in each component (the residual
    of its highest point about its lowest does not wrap), that mean is it (three residual
    calls). Otherwise residuals about a start
    ``c`` are averaged, ``ŷ = c + Σᵢ wᵢ r(pᵢ, c)``, and the mean is taken again about ``ŷ``
    (:data:`RECENTRING_PASSES` times: a start in the tail wraps the far points the wrong
    way, and each pass moves it to the middle); the deviations are ``r(pᵢ, ŷ)``. The starts
    are ``centre [..., dy]`` where given (the UKF's centre sigma point: the points lie
    symmetric about it), else both the plain weighted mean (right wherever nothing wraps)
    and the point of largest weight (right for a cloud that straddles ±π, where the plain
    mean lies across the circle), keeping per run and component the mean of the smaller
    weighted spread ``Σᵢ wᵢ r(pᵢ, ŷ)²``. The plain ``Σᵢ wᵢ pᵢ`` of bearings on both sides of
    ±π lies near 0: the UKF's innovation covariance made from it was 5.4 rad² where 0.005
    was right (a trial). Models with the plain residual (:func:`plain_residual`) keep the
    filters' plain sums."""
    weights = weights.expand(points.shape[:-1])
    w_row = weights.unsqueeze(-2)  # [..., 1, n]
    plain = (w_row @ points).squeeze(-2)
    dev = model.measurement_residual(points, plain.unsqueeze(-2))
    diff = points - plain.unsqueeze(-2)
    # nothing wrapped, and the cloud narrower than half a turn in each component (the span
    # from its lowest to its highest point does not wrap either): a cloud even on both
    # sides of ±π has its plain mean near 0 with no deviation wrapping, and a spread of 9.3
    # rad² where 0.01 was right (a review)
    high, low = points.amax(-2), points.amin(-2)
    if _unwrapped(dev, diff) and _unwrapped(model.measurement_residual(high, low), high - low):
        return plain, dev
    if centre is not None:
        starts = [centre]
    else:
        top = weights.argmax(-1, keepdim=True).unsqueeze(-1)  # [..., 1, 1]
        starts = [plain, torch.take_along_dim(points, top, dim=-2).squeeze(-2)]
    best = None
    for mean in starts:
        for _ in range(1 + RECENTRING_PASSES):
            about = model.measurement_residual(points, mean.unsqueeze(-2))
            mean = mean + (w_row @ about).squeeze(-2)
        dev = model.measurement_residual(points, mean.unsqueeze(-2))
        spread = (w_row @ dev.square()).squeeze(-2)  # [..., dy]: per component
        if best is None:
            best = (mean, dev, spread)
            continue
        closer = spread < best[2]
        best = (torch.where(closer, mean, best[0]),
                torch.where(closer.unsqueeze(-2), dev, best[1]),
                torch.where(closer, spread, best[2]))  # fmt: skip
    return best[0], best[1]


def _unwrapped(residual: Tensor, difference: Tensor) -> bool:
    """Whether a residual is the plain difference everywhere (nothing wrapped)."""
    return bool(((residual - difference).abs() <= 1e-9 * (1.0 + difference.abs())).all())


class LinearGaussianModel(StateSpaceModel):
    """``x_{k+1} = F x_k + B u_k + w_k``, ``y_k = H x_k + v_k``, Gaussian noise and prior.

    Args:
        F: transition matrix ``[*, dx, dx]``.
        H: observation matrix ``[*, dy, dx]``.
        Q: process-noise covariance ``[*, dx, dx]``.
        R: measurement-noise covariance ``[*, dy, dy]``.
        m0, P0: prior mean ``[*, dx]`` and covariance ``[*, dx, dx]`` of ``x_0``.
        B: optional input matrix ``[*, dx, du]``.

    ``F`` sets the model's dtype and device: the other arguments are converted to them (a
    float32 ``F``, e.g. ``torch.tensor`` of Python floats, makes a float32 model of float64
    ``Q`` and ``R``; build ``F`` in the dtype you mean). ``nn.Parameter`` arguments become
    learnable parameters; other tensors are buffers (and keep their autograd history).
    Time-varying linear models override
    ``transition_matrix(k)``, ``observation_matrix(k)``, ``control_matrix(k)`` and the
    covariance methods (``process_cov(k)``, ``measurement_cov(k)``: simulation and the
    particle filters follow them too), and set ``time_varying = True``.
    """

    def __init__(self, F, H, Q, R, m0, P0, B=None):
        super().__init__()
        F = as_tensor(F, "F")
        dtype, device = F.dtype, F.device
        check_model_dtype(dtype, "F (which sets the model's dtype)")
        H = as_tensor(H, "H", dtype=dtype, device=device)
        Q = as_tensor(Q, "Q", dtype=dtype, device=device)
        R = as_tensor(R, "R", dtype=dtype, device=device)
        m0 = as_tensor(m0, "m0", dtype=dtype, device=device)
        P0 = as_tensor(P0, "P0", dtype=dtype, device=device)
        check_square(F, "F")
        dx = F.shape[-1]
        if H.dim() < 2 or H.shape[-1] != dx:
            raise ValueError(f"H must have shape [..., dy, {dx}]; got {tuple(H.shape)}")
        dy = H.shape[-2]
        check_finite(F, "F")
        check_finite(H, "H")
        check_positive_definite(Q, "Q", dx)
        check_positive_definite(R, "R", dy)
        check_vector_last(m0, "m0", dx)
        check_finite(m0, "m0")
        check_positive_definite(P0, "P0", dx)
        self.dim_x, self.dim_y = dx, dy
        register_tensor(self, "F", F)
        register_tensor(self, "H", H)
        if B is not None:
            B = as_tensor(B, "B", dtype=dtype, device=device)
            if B.dim() < 2 or B.shape[-2] != dx:
                raise ValueError(f"B must have shape [..., {dx}, du]; got {tuple(B.shape)}")
            check_finite(B, "B")
            self.dim_u = B.shape[-1]
            register_tensor(self, "B", B)
        else:
            self.B = None
        check_batch_shapes(F=F.shape[:-2], H=H.shape[:-2], Q=Q.shape[:-2], R=R.shape[:-2],
                           m0=m0.shape[:-1], P0=P0.shape[:-2],
                           **({} if B is None else {"B": B.shape[:-2]}))  # fmt: skip
        self.initial = Gaussian(m0, P0)
        self.process_noise = Gaussian(torch.zeros(dx, dtype=dtype, device=device), Q)
        self.measurement_noise = Gaussian(torch.zeros(dy, dtype=dtype, device=device), R)

    def __init_subclass__(cls, **kwargs):
        # a time-varying model's own F_k, H_k, B_k are checked finite when read, as its
        # process_cov(k) and measurement_cov(k) are (step_covariance): a NaN B_k had run to
        # NaN means from that step on without an error, and a NaN F_k or H_k was blamed on
        # "Q, R and P0" (a dense-Gaussian trial); the built-in ones are checked when set
        super().__init_subclass__(**kwargs)
        for name in _STEP_MATRICES:
            own = cls.__dict__.get(name)
            if callable(own) and not getattr(own, "_checks_finite", False):
                setattr(cls, name, _finite_step_matrix(own, name))

    def _matrices_read(self) -> list[tuple[str, Tensor]]:
        """``F``, ``H`` and ``B`` where this model's filters read them as stored (not where a
        subclass overrides the method that reads them): :func:`check_model` checks them
        finite, written in place since construction."""
        return [(name, getattr(self, name)) for name in ("F", "H", "B")
                if isinstance(getattr(self, name, None), Tensor) and not self._reads_own(name)]  # fmt: skip

    def __setattr__(self, name, value):
        # F, H and B assigned after construction are checked as the constructor checks
        # them, and B sets dim_u (None: no input): another shape or dtype had been taken
        # and the filters failed in torch's words (or the UKF ran on a broadcast), B = None
        # crashed the Kalman filter, and a B of another width left dim_u stale (a trial of
        # models changed under the filters)
        if (name in ("Q", "R", "m0", "P0") and "measurement_noise" in self._modules
                and not self._reads_own(name)):  # fmt: skip
            # (the constructor's arguments, kept in the noise models and the prior: an
            # attribute of that name had been set beside them and never read, a trial)
            where = {"Q": "model.process_noise", "R": "model.measurement_noise",
                     "m0": "model.initial", "P0": "model.initial"}[name]  # fmt: skip
            raise AttributeError(
                f"{name} is kept in {where} (a Gaussian), not as model.{name}: assign {where} "
                "= difffilter.noise.Gaussian(…), or write its tensor in place"
            )
        if (name in ("F", "H", "B") and "measurement_noise" in self._modules
                and not self._reads_own(name)):  # fmt: skip
            value = self._checked_matrix(name, value)
            if name == "B":
                super().__setattr__("dim_u", 0 if value is None else value.shape[-1])
        super().__setattr__(name, value)

    def _reads_own(self, name: str) -> bool:
        """Whether a subclass reads an attribute ``name`` its own way: one that overrides
        the method the attribute feeds (``transition_matrix`` for ``F``,
        ``observation_matrix`` for ``H``, ``control_matrix`` for ``B``, ``process_cov`` for
        ``Q``, ``measurement_cov`` for ``R``: a time-varying model's tables, unchecked
        here), or any subclass for the prior's ``m0``, ``P0``."""
        cls = type(self)
        if cls is LinearGaussianModel:
            return False
        method = {"Q": "process_cov", "R": "measurement_cov", "F": "transition_matrix",
                  "H": "observation_matrix", "B": "control_matrix"}.get(name)  # fmt: skip
        return method is None or getattr(cls, method) is not getattr(LinearGaussianModel, method)

    def _checked_matrix(self, name: str, value):
        """``value`` for ``F``, ``H`` or ``B`` against the model's dims, dtype and device."""
        if value is None and name == "B":
            return None
        dx, dy = self.dim_x, self.dim_y
        want = {"F": f"[..., {dx}, {dx}]", "H": f"[..., {dy}, {dx}]", "B": f"[..., {dx}, du]"}
        if not isinstance(value, Tensor):
            raise ValueError(f"{name} must be a tensor {want[name]}; got {type(value).__name__}")
        rows, cols = {"F": (dx, dx), "H": (dy, dx), "B": (dx, None)}[name]
        if value.dim() < 2 or value.shape[-2] != rows or cols not in (None, value.shape[-1]):
            raise ValueError(f"{name} must have shape {want[name]}; got {tuple(value.shape)}")
        noise = self.process_noise.cov
        if value.dtype != noise.dtype or value.device != noise.device:
            raise ValueError(
                f"{name} is {value.dtype} on {value.device} and the model {noise.dtype} on "
                f"{noise.device}: give it the model's (or convert the model: model.to(...))"
            )
        if value.device.type != "meta":
            check_finite(value, name)
        return value

    def transition_matrix(self, k: int) -> Tensor:
        """``F_k`` ``[*, dx, dx]``."""
        return self.F

    def observation_matrix(self, k: int) -> Tensor:
        """``H_k`` ``[*, dy, dx]``."""
        return self.H

    def control_matrix(self, k: int) -> Tensor | None:
        """``B_k`` ``[*, dx, du]`` or ``None``."""
        return self.B

    def transition(self, x, u, k):
        out = matvec(self.transition_matrix(k), x)
        B = self.control_matrix(k)
        if B is not None and u is not None:
            out = out + matvec(B, u)
        return out

    def observe(self, x, k):
        return matvec(self.observation_matrix(k), x)

    def transition_jacobian(self, x, u, k):
        F = self.transition_matrix(k)
        return F.expand(broadcast_shapes(x.shape[:-1], F.shape[:-2]) + F.shape[-2:])

    def observation_jacobian(self, x, k):
        H = self.observation_matrix(k)
        return H.expand(broadcast_shapes(x.shape[:-1], H.shape[:-2]) + H.shape[-2:])


_STEP_MATRICES = ("transition_matrix", "observation_matrix", "control_matrix")


def _finite_step_matrix(method: Callable, name: str) -> Callable:
    """``method`` (a subclass's ``transition_matrix``, ``observation_matrix`` or
    ``control_matrix``) whose returned matrix is refused by name where an entry is NaN or
    Inf (under a transform, or on the meta device, values are not read)."""

    @functools.wraps(method)
    def checked(self, *args, **kwargs):
        value = method(self, *args, **kwargs)
        if isinstance(value, Tensor) and value.is_floating_point() and not under_transform(value):
            _check_step_matrix(self, value, name, args)
        return value

    checked._checks_finite = True
    return checked


def _check_step_matrix(model, value: Tensor, name: str, args) -> None:
    """``value`` (``model.name(*args)``) finite: a view of a stored table (``self.Fs[k]``)
    checks the whole table once and remembers it while it is unwritten (its version and
    memory), a tensor the model holds likewise, so that each later read costs a lookup
    (checking every read with torch's reduction had made a time-varying Kalman filter 25 %
    slower: a review); a matrix computed afresh is checked at each read by its host sum
    (:func:`_finite_now`)."""
    source = value._base
    if source is None:
        held = any(value is t for t in model._buffers.values()) or any(
            value is t for t in model._parameters.values()
        )
        if not held:  # computed afresh: checked at each read (about 5 µs: a model of computed
            # matrices filters 20 % slower for it; views of a stored table are checked once)
            if not _finite_now(value):
                step = ", ".join(map(repr, args))
                raise ValueError(
                    f"{type(model).__name__}.{name}({step}) contains NaN or Inf values; every "
                    "entry must be finite"
                )
            return
        source = value
    memo = model.__dict__.get("_finite_tables_cache")
    if memo is None:
        memo = {}
        object.__setattr__(model, "_finite_tables_cache", memo)  # (no assignment counted)
    seen = memo.get(name)
    # its version and memory (a new object for an inference tensor: checked again); the
    # memory too, as a copied model's tables start their versions again (a deepcopy's memo
    # had matched a table written NaN since: a review)
    stamp = (version_stamp(source), source.data_ptr())
    if seen is not None and seen[0] is source and seen[1] == stamp:
        return
    if not values_known(value):
        return
    if _all_finite(source):
        memo[name] = (source, stamp)  # (held: its id is not reused while remembered)
        return
    if not _all_finite(value):  # (the table holds a NaN elsewhere: named at its own step)
        step = ", ".join(map(repr, args))
        raise ValueError(
            f"{type(model).__name__}.{name}({step}) contains NaN or Inf values; every entry "
            "must be finite"
        )


def _finite_now(value: Tensor) -> bool:
    """Whether ``value`` (not under a transform: the caller asked) is finite, ``True`` where
    its values cannot be read: a CPU tensor by its host sum (about 2 µs, against 7 for
    torch's reduction and read-back, which a computed matrix pays at every read; every
    entry where the sum is not finite), others by :func:`_all_finite`."""
    if value.device.type == "cpu" and value.dtype in _NUMPY_SAFE:
        array = value.detach().numpy()
        return math.isfinite(array.sum()) or bool(np.isfinite(array).all())
    return not values_known(value) or _all_finite(value)


_NUMPY_SAFE = (torch.float32, torch.float64)


def _arity(fn: Callable, names: tuple[str, ...] = ("x", "u", "k")) -> int:
    """How many of ``names`` (``f``'s ``x, u, k``; ``h``'s ``x, k``) ``fn`` is called with:
    its positional arguments without a default, and after them those with a default that
    carry the next of ``names`` (``f(x, u=None)`` takes ``u``: counted by defaults alone,
    it was called as ``f(x)`` and its input silently dropped; ``f(x, dt=0.1)`` still gets
    ``x`` alone). A module (a network) is called through ``forward``: its own signature is
    ``Module.__call__``'s ``*args``, which had counted all of ``names`` and called
    ``forward(x)`` with three arguments (a noise trial)."""
    if isinstance(fn, torch.nn.Module):
        fn = fn.forward
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return len(names)
    if any(p.kind == p.VAR_POSITIONAL for p in params):
        return len(names)
    positional = [p for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    n = sum(p.default is p.empty for p in positional)
    while n < min(len(positional), len(names)) and positional[n].name == names[n]:
        n += 1
    return n


class NonlinearGaussianModel(StateSpaceModel):
    """``x_{k+1} = f(x_k, u_k, k) + w_k``, ``y_k = h(x_k, k) + v_k`` from plain functions.

    Args:
        transition: ``f(x)``, ``f(x, u)`` or ``f(x, u, k)``; ``x [..., dx]`` → ``[..., dx]``.
        observe: ``h(x)`` or ``h(x, k)``; ``x [..., dx]`` → ``[..., dy]``.
        Q, R, m0, P0: as in :class:`LinearGaussianModel`.
        dim_u: input dimension (0 when there is no input).
        transition_jacobian, observation_jacobian: optional closed forms with the same
            arguments as ``transition``/``observe`` returning ``[..., dx, dx]`` and
            ``[..., dy, dx]``; by default ``torch.func`` computes them.
    """

    def __init__(
        self,
        transition: Callable,
        observe: Callable,
        Q,
        R,
        m0,
        P0,
        *,
        dim_u: int = 0,
        transition_jacobian: Callable | None = None,
        observation_jacobian: Callable | None = None,
    ):
        super().__init__()
        if not callable(transition) or not callable(observe):
            raise ValueError("transition and observe must be callables (functions of x)")
        Q = as_tensor(Q, "Q")
        dtype, device = Q.dtype, Q.device
        R = as_tensor(R, "R", dtype=dtype, device=device)
        m0 = as_tensor(m0, "m0", dtype=dtype, device=device)
        P0 = as_tensor(P0, "P0", dtype=dtype, device=device)
        check_square(Q, "Q")
        check_square(R, "R")
        dx, dy = Q.shape[-1], R.shape[-1]
        check_positive_definite(Q, "Q", dx)
        check_positive_definite(R, "R", dy)
        if m0.dim() < 1 or m0.shape[-1] != dx:  # (Q fixes dx: name both)
            raise ValueError(
                f"m0 must have shape [..., {dx}]: Q is {dx}×{dx}, so the state has {dx} entries; "
                f"got m0 {tuple(m0.shape)}"
            )
        check_finite(m0, "m0")
        check_positive_definite(P0, "P0", dx)
        check_batch_shapes(Q=Q.shape[:-2], R=R.shape[:-2], m0=m0.shape[:-1], P0=P0.shape[:-2])
        if isinstance(dim_u, bool) or not isinstance(dim_u, numbers.Integral) or dim_u < 0:
            raise ValueError(f"dim_u must be an integer >= 0 (0: no input); got {dim_u!r}")
        self.dim_x, self.dim_y, self.dim_u = dx, dy, int(dim_u)
        self._f, self._h = transition, observe
        self._f_arity, self._h_arity = _arity(transition), _arity(observe, ("x", "k"))
        if self.dim_u and self._f_arity <= 1:
            raise ValueError(
                f"dim_u = {self.dim_u}, but transition takes x alone, so the input would never "
                "reach it: write f(x, u) or f(x, u, k), or leave dim_u at 0"
            )
        self._jf, self._jh = transition_jacobian, observation_jacobian
        self._rows_of_its_own: dict[str, torch.Size] = {}  # (found by _check_widths)
        self.initial = Gaussian(m0, P0)
        self.process_noise = Gaussian(torch.zeros(dx, dtype=dtype, device=device), Q)
        self.measurement_noise = Gaussian(torch.zeros(dy, dtype=dtype, device=device), R)
        if not self.dim_u and self._f_arity >= 2:
            self._check_takes_no_input(m0.reshape(-1, dx)[:1])
        self._check_widths(m0.reshape(-1, dx)[:1])
        self._check_jacobians(m0.reshape(-1, dx)[0], P0.reshape(-1, dx, dx)[0])

    def _apply(self, fn, *args, **kwargs):
        """``.to(dtype)``, ``.float()``, ``.double()``: the functions probed again in the new
        dtype, as when built (a float64 constant in ``f`` had been refused for a model built
        in float32, and taken for one converted to it: ``simulate`` returned float64 states
        beside a float32 ``x0``, the UKF float64 means: an ssm trial)."""
        before = self.initial.mean.dtype
        out = super()._apply(fn, *args, **kwargs)
        mean = self.initial.mean
        if mean.dtype != before and mean.dtype in (torch.float32, torch.float64):
            try:
                self._check_widths(mean.detach().reshape(-1, self.dim_x)[:1])
            except ValueError as error:  # refused: the model stays in its dtype, usable
                super()._apply(lambda t: t.to(before) if t.is_floating_point() else t)
                add_note(error, f"(the model was not converted: it stays {before})")
                raise
        return out

    def _check_takes_no_input(self, mean: Tensor) -> None:
        """A transition ``f(x, u[, k])`` of a model without input (``dim_u = 0``) is given
        ``u = None``: where that fails on ``None`` (``u @ B.T``), ``dim_u`` was forgotten,
        and is named here (the filters had failed inside ``f`` with torch's "unsupported
        operand type(s) for @: 'NoneType'", and giving ``us`` was refused as "the model has
        no input": a core-filter trial). Any other failure is left to the width probes."""
        try:
            self.transition(mean.detach().clone(), None, 0)
        except Exception as error:  # noqa: BLE001 (a probe: the width probes name the rest)
            if "NoneType" not in str(error):  # (u @ B, u[..., 0], torch.sin(u), u.shape)
                return
            raise ValueError(
                "transition takes an input u but fails on u=None, and the model has no input "
                f"(dim_u = 0): give dim_u=<width of u>, or have f ignore u when it is None "
                f"({type(error).__name__}: {error})"
            ) from None

    def _check_jacobians(self, mean: Tensor, cov: Tensor) -> None:
        """The closed-form Jacobians given, at ``n`` distinct states about the prior
        (``m0 ± ½`` of its standard deviations), against ``torch.func``'s derivatives of
        ``f`` and ``h``: their shape ``[n, rows, dx]`` (or one matrix ``[rows, dx]`` that is
        the derivative at every state), and their values within ``1e-4`` of the largest
        entry. A wrong shape had failed mid-filter as torch's raw matmul error, and a
        transposed Jacobian, or one of run 0's state (``x[0]``), had filtered silently and
        wrongly (a trial: means 0.028 off, 1.5 posterior standard deviations). Where either
        side cannot be evaluated at those states, the check is left out."""
        given = [(name, closed, default, rows, what) for name, closed, default, rows, what in (
            ("transition_jacobian", self._jf, StateSpaceModel.transition_jacobian, self.dim_x,
             "transition"),
            ("observation_jacobian", self._jh, StateSpaceModel.observation_jacobian,
             self.dim_y, "observe")) if closed is not None]  # fmt: skip
        if not given:
            return
        n, dx = _probe_runs(self.dim_x, self.dim_y), self.dim_x
        spread = cov.detach().diagonal().clamp_min(0).sqrt()
        offsets = torch.linspace(-0.5, 0.5, n, dtype=mean.dtype, device=mean.device)
        x = mean.detach() + offsets.unsqueeze(-1) * spread  # [n, dx]
        u = None if self.dim_u == 0 else x.new_zeros(n, self.dim_u)
        for name, _, default, rows, what in given:
            call = (lambda: self.transition_jacobian(x, u, 0)) if what == "transition" else (
                lambda: self.observation_jacobian(x, 1))  # fmt: skip
            try:
                got = call()
                want = (default(self, x, u, 0) if what == "transition"
                        else default(self, x, 1)).detach()  # fmt: skip
            except Exception:  # noqa: BLE001 (a probe: left to fail where it is used)
                continue
            if (
                not isinstance(got, Tensor)
                or got.shape[-2:] != (rows, dx)
                or not _broadcasts(got.shape[:-2], x.shape[:-1])
            ):
                shape = tuple(got.shape) if isinstance(got, Tensor) else type(got).__name__
                raise ValueError(
                    f"{name} returns {shape} for x [{n}, {dx}]; it must return [..., {rows}, "
                    f"{dx}]: the derivative of {what} (one row per output, one column per state)"
                )
            finite = want.isfinite() & got.detach().expand_as(want).isfinite()
            if not bool(finite.any()):
                continue
            diff = (got.detach().expand_as(want) - want).abs()[finite].max()
            scale = want.abs()[finite].max()
            if float(diff) > 1e-4 * max(float(scale), torch.finfo(want.dtype).tiny):
                raise ValueError(
                    f"{name} is not the derivative of {what}: at {n} states about the prior mean "
                    f"it differs from torch.func's by up to {float(diff):.3g} (largest entry "
                    f"{float(scale):.3g}). A transposed one, or one of a single state (x[0]: "
                    "rows, not entries, of a batch), filters wrongly and silently; leave it out "
                    "to have torch.func compute it (an approximation on purpose: override "
                    f"{name} in a subclass)"
                )

    def _check_widths(self, mean: Tensor) -> None:
        """``f`` and ``h`` on ``n`` runs at the prior mean ``mean [1, dx]`` (``n`` from
        :func:`_probe_runs`, neither ``dx`` nor ``dy``) return ``[n, dx]`` and ``[n, dy]``
        (Q's and R's sizes), or a constant that broadcasts to them, and compute each run from
        its own state and input. A wrong width otherwise broadcast silently in the UKF (a
        1-entry measurement against a 2-entry prediction) and failed deep in torch elsewhere,
        and a function written for one state (``x[0]``, ``x[1]``, ``u[0]``: rows, not entries,
        of a batch) ran on a batch of two runs of two states with wrong numbers and no error
        (a teaching trial: EKF RMSE 3.85 against 0.18). A result is a constant where it
        does not depend on ``x`` or ``u`` (no gradient reaches them; ``relu(x[0])`` flat at
        the mean still depends on them), and a run's result that has a non-zero derivative
        in another run's state or input mixes runs (``u[0]``, ``x - x.mean(0)``). A function
        that cannot run on ``n`` runs under autograd (per-run parameters of another batch,
        numpy inside) is probed on the mean alone, widths and dtypes; one that cannot run on
        that either is left to fail where it is used."""
        n = _probe_runs(self.dim_x, self.dim_y)
        if under_transform():  # (requires_grad_ is refused inside torch.func's transforms: a
            # model built inside one had failed there; its widths and dtypes are still probed)
            self._check_widths_at(mean.detach().expand(n, self.dim_x).clone(), runs=False)
            return
        if not self._check_widths_at(mean.detach().expand(n, self.dim_x).clone(), runs=True):
            self._check_widths_at(mean.detach().clone(), runs=False)  # widths and dtypes alone
        self._find_rows_of_its_own(mean.detach().clone())

    def _find_rows_of_its_own(self, x: Tensor) -> None:
        """Records in ``_rows_of_its_own`` a function that returns more rows than the one
        state ``x [1, dx]`` it is given: it holds values per run (``gain [B, 1] * x``), right
        on the runs' states alone (:meth:`_check_rows_of_its_own`). The probe on ``n`` runs
        cannot see it where ``n = B``."""
        u = None if self.dim_u == 0 else x.new_zeros(1, self.dim_u)
        for name, fn in (("transition", lambda: self.transition(x, u, 0)),
                         ("observe", lambda: self.observe(x, 1))):  # fmt: skip
            try:
                with torch.no_grad():
                    out = fn()
            except Exception:  # noqa: BLE001 (a probe: left to fail where it is used)
                continue
            if isinstance(out, Tensor) and out.dim() >= 1:
                if broadcast_or_none(out.shape[:-1], x.shape[:-1]) != x.shape[:-1]:
                    self._rows_of_its_own[name] = out.shape[:-1]

    def _check_widths_at(self, x: Tensor, runs: bool) -> bool:
        """:meth:`_check_widths` on ``x [n, dx]``: whether both functions ran (``False``: one
        raised, a probe to retry on the mean alone); raises on a wrong width or dtype and,
        with ``runs``, on a result that keeps neither the runs nor a constant, or mixes
        runs."""
        n = x.shape[0]
        u = None if self.dim_u == 0 else x.new_zeros(n, self.dim_u)
        leaves = [t.requires_grad_(True) if runs else t for t in (x, u) if t is not None]
        ran = True
        for name, fn, want, size in (("transition", lambda: self.transition(x, u, 0), self.dim_x, "Q"),
                                     ("observe", lambda: self.observe(x, 1), self.dim_y, "R")):  # fmt: skip
            try:
                with torch.set_grad_enabled(runs):
                    out = fn()
            except Exception:  # noqa: BLE001 (a probe, not the model's use)
                ran = False
                continue
            if not isinstance(out, Tensor):
                continue
            depends = out.requires_grad
            runs_kept = out.shape[:-1] == x.shape[:-1]
            constant = not runs_kept and not depends and _broadcasts(out.shape[:-1], x.shape[:-1])
            # the runs as its last axis, or runs lost (x[0]: one run's dx entries)
            hint = (
                _ONE_STATE_HINT.format(n=n)
                if runs and (out.shape[-1:] == (n,) or not (runs_kept or constant))
                else ""
            )
            if out.dim() < 1 or out.shape[-1] != want:
                raise ValueError(
                    f"{name} returns {tuple(out.shape)} for x [{n}, {self.dim_x}] ({n} run(s) at "
                    f"the prior mean); {size} is {want}×{want}, so it must return [..., {want}]"
                    + hint
                )
            if runs and not (runs_kept or constant):
                raise ValueError(
                    f"{name} returns {tuple(out.shape)} for x [{n}, {self.dim_x}] ({n} runs at the "
                    f"prior mean); it must keep x's runs: [{n}, {want}]" + hint
                )
            if out.dtype != x.dtype:  # the EKF failed in torch
                raise ValueError(
                    f"{name} returns {out.dtype} for x of the model's {x.dtype}: return the "
                    "dtype of x (e.g. build constants with x.new_tensor or dtype=x.dtype)"
                )
            if runs and runs_kept and depends and _mixes_runs(out, leaves):
                raise ValueError(
                    f"{name}'s result for one run depends on the states or inputs of other runs "
                    f"(probed on {n} runs at the prior mean): a plant computes each run from its "
                    "own x[..., :] and u[..., :]" + _ONE_STATE_HINT.format(n=n)
                )
        return ran

    def transition(self, x, u, k):
        if self._rows_of_its_own:
            self._check_rows_of_its_own("transition", x)
        return _dispatch(self._f, self._f_arity, x, self._input(x, u), k)

    def observe(self, x, k):
        if self._rows_of_its_own:
            self._check_rows_of_its_own("observe", x)
        return self._h(x) if self._h_arity <= 1 else self._h(x, k)

    def _check_rows_of_its_own(self, name: str, x: Tensor) -> None:
        """A function holding values per run (``gain [B, 1] * x``) is right on the runs'
        states ``x [B, dx]`` alone: on a stack of them (the UKF's sigma points
        ``[B, 2n+1, dx]``, particles ``[B, N, dx]``, the EKF's Jacobian of one state) its
        values meet the wrong axis. At ``B = 2n+1`` the UKF had moved sigma point ``i`` of
        every run with run ``i``'s gain, silently (an EKF/UKF trial); elsewhere torch's raw
        shape errors."""
        rows = self._rows_of_its_own.get(name)
        if rows is not None and x.shape[:-1] != rows:
            raise ValueError(
                f"{name} holds values of its own per run ({tuple(rows)} rows for one state "
                f"[1, {self.dim_x}]), so it applies to the runs' states [{', '.join(map(str, rows))}, "
                f"{self.dim_x}] alone; it was given x {list(x.shape)} (sigma points, particles "
                "or one state for its Jacobian), where those values would meet the wrong axis. "
                "Write it for x [..., dx] of any leading shape with one parameter set, and run "
                "one model per set; an EKF can take it with closed-form transition_jacobian "
                "and observation_jacobian"
            )

    def transition_jacobian(self, x, u, k):
        if self._jf is None:
            return super().transition_jacobian(x, u, k)
        return _dispatch(self._jf, self._f_arity, x, self._input(x, u), k)

    def _input(self, x: Tensor, u: Tensor | None) -> Tensor | None:
        """``u``, or zeros ``[..., du]`` for ``x [..., dx]`` where a model with inputs is
        given none: the filters take a missing input as zero (the linear model's ``B u`` is
        left out), and ``f(x, u)`` had been handed ``None`` (a ``TypeError`` inside the
        user's own function, naming neither ``us`` nor what to pass)."""
        if u is None and self.dim_u:
            return x.new_zeros(x.shape[:-1] + (self.dim_u,))
        return u

    def observation_jacobian(self, x, k):
        if self._jh is None:
            return super().observation_jacobian(x, k)
        return self._jh(x) if self._h_arity <= 1 else self._jh(x, k)


def _probe_runs(dx: int, dy: int) -> int:
    """The runs of :meth:`NonlinearGaussianModel._check_widths`'s probe, neither ``dx`` nor
    ``dy``: more than ``dx`` where it is small (so a function written for one state,
    indexing up to ``x[dx − 1]``, runs on them), else the first of 2, 3, 4 (a plant of 400
    states built ``[n, 400, 400]`` per run: a probe of 801 runs took a second and a
    gigabyte; nobody indexes 16 entries one by one)."""
    first = dx + 1 if dx < 16 else 2
    return next(n for n in range(first, first + 3) if n not in (dx, dy))


def _mixes_runs(out: Tensor, leaves: list[Tensor]) -> bool:
    """Whether the last run's result ``out[-1]`` has a finite non-zero derivative in the other
    runs' rows of the probe's ``leaves`` (``x [n, dx]``, ``u [n, du]``). ``False`` where no
    derivative can be taken."""
    try:
        grads = torch.autograd.grad(out[-1].sum(), leaves, allow_unused=True)
    except RuntimeError:
        return False
    # (finite entries alone: the backward of an elementwise function that is NaN at the
    # mean, sqrt(x − 1) at 0, multiplies the other rows' zeros by NaN)
    return any(g is not None and bool(((g[:-1] != 0) & g[:-1].isfinite()).any()) for g in grads)


def _broadcasts(shape: torch.Size, runs: torch.Size) -> bool:
    """Whether a result's batch ``shape`` broadcasts to the probe's ``runs``, and to them alone."""
    try:
        return broadcast_shapes(shape, runs) == runs
    except RuntimeError:
        return False


#: The end of :meth:`NonlinearGaussianModel._check_widths`'s errors.
_ONE_STATE_HINT = (
    ". Write the function for a batch: x[..., i] for entry i (x[i] is run i of {n}), and "
    "torch.stack([...], dim=-1) to build the result"
)


def _dispatch(fn: Callable, arity: int, x, u, k):
    if arity <= 1:
        return fn(x)
    if arity == 2:
        return fn(x, u)
    return fn(x, u, k)
