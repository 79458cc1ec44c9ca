"""Posterior Cramér–Rao bound (PCRB): the accuracy floor of any state estimator.

Tichavský, Muravchik & Nehorai (IEEE TSP 46(5), 1998): for
``x_{k+1} = f(x_k, u_k) + w_k``, ``w_k ~ N(0, Q)``, ``y_k = h(x_k) + v_k`` with a
measurement noise of density ``p_v`` (independent of ``x``), the Bayesian information
matrix ``J_k`` of ``x_k`` given ``y_{1:k}`` obeys ``E[(x̂_k − x_k)(x̂_k − x_k)ᵀ] ⪰ J_k⁻¹``
for every estimator ``x̂_k`` and::

    J_0     = P_0⁻¹                                           (Gaussian prior)
    D11_k   = E[F̃_kᵀ Q⁻¹ F̃_k],   D12_k = −E[F̃_k]ᵀ Q⁻¹,   D21_k = D12_kᵀ
    D22_k   = Q⁻¹ + E[H̃_{k+1}ᵀ J_v(m_{k+1}) H̃_{k+1}]
    J_{k+1} = D22_k − D21_k (J_k + D11_k)⁻¹ D12_k

with ``F̃_k = ∂f/∂x(x_k)``, ``H̃_k = ∂h/∂x(x_k)``, the expectations over the true
trajectories (Monte Carlo over the given sample paths), and ``J_v(m)`` the Fisher
information of the measurement noise restricted to the received entries ``m``:

* Gaussian ``p_v = N(0, R)``: ``J_v(m) = Mᵀ (R_mm)⁻¹ M`` (``M`` selects the received
  entries; unreceived entries contribute no information) — closed form;
* any other noise model (the glint Gaussian mixture): ``J_v(m) = E[s sᵀ]`` with
  ``s = ∇_v log p_v^m(v)`` the score of the marginal density of the received entries,
  by **Monte Carlo** over ``num_samples`` draws ``v ~ p_v`` from an explicit
  ``torch.Generator`` (standard error ∝ 1/√num_samples; the draws are shared by every
  mask pattern).

On a linear-Gaussian model ``J_k⁻¹`` equals the Kalman filter's posterior covariance
``P_{k|k}`` (also with a mask): ``J_{k+1} = (Q + F J_k⁻¹ Fᵀ)⁻¹ + Hᵀ R_m⁻¹ H``.

Shapes: trajectories ``xs [..., M, T, dx]`` (``M`` Monte Carlo paths, ``xs[..., t, :] =
x_{t+1}``), initial states ``x0 [..., M, dx]``, mask ``[..., T, dy]`` (bool, shared by
the ``M`` paths: the bound conditional on that schedule; leading dimensions give a batch
of bounds, e.g. one per attack-flag pattern).
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import torch
from torch import Tensor

from ._checks import (
    _check_float_tensor,
    _check_us,
    check_finite,
    check_inputs_given,
    check_model,
    check_positive_definite,
    check_positive_int,
    model_dtype_device,
    step_covariance,
)
from .linalg import symmetrize
from .noise import Gaussian, NoiseModel
from .particle import transition_law_unsaid
from .ssm import StateSpaceModel

__all__ = [
    "PCRBResult",
    "gaussian_information",
    "noise_information",
    "measurement_information_moments",
    "posterior_crb",
]


class PCRBResult(NamedTuple):
    """The bound over ``T`` steps.

    Attributes:
        information: Bayesian information ``J_k`` ``[..., T, dx, dx]`` (k = 1 … T).
        bound: ``J_k⁻¹`` ``[..., T, dx, dx]``, the lower bound on the MSE matrix.
    """

    information: Tensor
    bound: Tensor

    def rmse(self, index) -> Tensor:
        """``sqrt(tr J_k⁻¹[index, index])`` ``[..., T]``: the RMSE floor of components ``index``."""
        idx = torch.as_tensor(index, device=self.bound.device).reshape(-1)  # an int: [1]
        return self.bound[..., idx, idx].sum(-1).sqrt()


def _check_mask(mask: Tensor | None, dim: int, name: str = "mask") -> Tensor | None:
    if mask is None:
        return None
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool or mask.shape[-1:] != (dim,):
        # (a docs trial: a float mask of the right shape was told only its shape)
        got = (f"{mask.dtype} {tuple(mask.shape)}" if isinstance(mask, Tensor)
               else type(mask).__name__)  # fmt: skip
        raise ValueError(f"{name} must be a bool tensor [..., {dim}] (True = received); got {got}")
    return mask


def gaussian_information(R: Tensor, mask: Tensor | None = None) -> Tensor:
    """``J_v(m) = Mᵀ (R_mm)⁻¹ M`` of ``N(0, R)`` for ``R [dy, dy]``, ``mask [..., dy]`` → ``[..., dy, dy]``.

    Unreceived entries get zero rows and columns (the information of the marginal of the
    received entries; an entry correlated with an unreceived one loses that correlation).
    Symmetric to the bit (``torch.linalg.inv`` of a symmetric matrix is not: a float32
    result had failed ``posterior_crb``'s check of ``information=``).
    """
    if mask is None:
        return symmetrize(_inverse_noise_cov(R))
    _check_mask(mask, R.shape[-1])
    m = mask.to(R.dtype)
    mm = m.unsqueeze(-1) * m.unsqueeze(-2)
    eye = torch.eye(R.shape[-1], dtype=R.dtype, device=R.device)
    padded = R * mm + torch.diag_embed(1.0 - m) * eye  # R_mm on the received block, I elsewhere
    return symmetrize(_inverse_noise_cov(padded) * mm)


def _inverse_noise_cov(R: Tensor) -> Tensor:
    return _definite_inverse(
        R, "the measurement noise covariance R (of the received entries)",
        "its information R⁻¹ is infinite along a noiseless direction; add a small jitter to "
        "R (e.g. 1e-9 I)",
    )  # fmt: skip


def _definite_inverse(M: Tensor, name: str, singular: str) -> Tensor:
    """``M⁻¹`` of a covariance ``M [..., d, d]`` the bound inverts (``R``, ``Q_k``, ``P₀``):
    finite and symmetric, not singular (``singular`` says what that means and what to do),
    and positive definite. A covariance written in place after the model was built
    (training, ``load_state_dict``) had been inverted as it came: a negated ``Q`` gave a
    "bound" of negative variances, a negated ``R`` a negative-definite information, NaN an
    all-NaN bound, where the filters refuse the model (a bounds trial)."""
    check_finite(M, name)
    inverse, info = torch.linalg.inv_ex(M)
    if bool(info.any()):  # (torch's "linalg.inv: The diagonal element 1 is zero")
        raise ValueError(f"{name} is singular: {singular}")
    check_positive_definite(M, name)
    return inverse


def noise_information(
    noise: NoiseModel,
    mask: Tensor | None = None,
    *,
    num_samples: int = 200_000,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Fisher information ``J_v(m) = E[s sᵀ]`` of an additive noise ``p_v`` on the received entries.

    ``noise``: a :mod:`difffilter.noise` model of dimension ``dy``; ``mask [..., dy]`` or
    ``None`` → ``[..., dy, dy]``. A :class:`~difffilter.noise.Gaussian` uses the closed
    form (:func:`gaussian_information`); any other model (``GaussianMixture``, a product
    of per-sensor mixtures) the Monte Carlo estimate of the module docstring: ``v ~ p_v``
    (``num_samples`` draws from ``generator``), ``s = ∇_v log p_v(v; mask)`` by autograd,
    computed once per distinct mask pattern (also under ``torch.inference_mode()``). A
    noise whose log-density has no gradient in ``v`` (a uniform box: the bound's
    regularity conditions fail) is refused (``ValueError``), and so is one whose score in
    a received entry is zero on every draw (uniform in that entry: it would get no
    information, the "bound" of a Gaussian × uniform noise 5–7× above a particle filter's
    MSE); declare such an entry's information with ``posterior_crb(information=…)``.
    """
    if not isinstance(noise, NoiseModel):
        raise ValueError(f"noise must be a difffilter.noise model; got {type(noise).__name__}")
    dim = noise.dim
    _check_mask(mask, dim)
    if isinstance(noise, Gaussian):
        return gaussian_information(noise.cov, mask)
    check_positive_int(num_samples, "num_samples")
    with torch.no_grad():
        v = noise.sample((num_samples,), generator)
    patterns = (
        torch.ones(1, dim, dtype=torch.bool, device=v.device)
        if mask is None
        else mask.reshape(-1, dim)
    )
    unique, inverse = torch.unique(patterns, dim=0, return_inverse=True)
    infos = []
    for pattern in unique:
        # (enable_grad does not lift inference mode: the score had failed there in torch's
        # "element 0 of tensors does not require grad")
        with torch.inference_mode(False), torch.enable_grad():
            vv = v.detach().clone().requires_grad_(True)
            m = None if bool(pattern.all()) else pattern.clone().expand_as(vv)
            log_p = noise.log_prob(vv, mask=m).sum()
            if not log_p.requires_grad:
                raise ValueError(
                    f"noise_information needs a log-density differentiable in v, and "
                    f"{type(noise).__name__}'s has no gradient (a uniform noise: the bound's "
                    "regularity conditions fail); pass information= yourself"
                )
            (score,) = torch.autograd.grad(log_p, vv)
        score = score * pattern.to(score.dtype)  # unreceived entries: no information
        _check_every_entry_scored(noise, score, pattern)
        infos.append(symmetrize(score.transpose(-1, -2) @ score / num_samples))
    out = torch.stack(infos)[inverse]
    if mask is None:
        return out[0]
    return out.reshape(mask.shape + (dim,))


def _check_every_entry_scored(noise: NoiseModel, score: Tensor, pattern: Tensor) -> None:
    """Refuse a received entry whose score ``score [num_samples, dy]`` is zero on every
    draw: the sum's gradient alone had let a noise uniform in one entry through (the
    Gaussian entries gave the sum a graph), and that entry got zero information."""
    flat = pattern & (score == 0).all(0)
    if bool(flat.any()):
        entries = ", ".join(str(int(j)) for j in flat.nonzero().flatten())
        raise ValueError(
            f"noise_information needs a log-density differentiable in every received entry "
            f"of v, and {type(noise).__name__}'s score in entry {entries} is zero on all "
            f"{score.shape[0]} draws (uniform there: the bound's regularity conditions fail); "
            "pass information= yourself"
        )


def _measurement_law_unsaid(model: StateSpaceModel) -> bool:
    """Whether ``model`` draws or weighs its measurements its own way (its class overrides
    ``sample_measurement`` or ``measurement_log_prob``) without declaring
    ``samples_measurement_noise = True`` (its draw is ``h(x) + v``, ``v ~`` its
    ``measurement_noise``): the measurement side of
    :func:`~difffilter.particle.transition_law_unsaid`."""
    cls = type(model)
    own = (cls.sample_measurement is not StateSpaceModel.sample_measurement
           or cls.measurement_log_prob is not StateSpaceModel.measurement_log_prob)  # fmt: skip
    return own and not getattr(model, "samples_measurement_noise", False)


def measurement_information_moments(model: StateSpaceModel, xs: Tensor, k0: int = 1) -> Tensor:
    """``G_k[i, j] = E_x[H̃_{k,i}ᵀ H̃_{k,j}]`` for ``xs [..., M, T, dx]`` → ``[..., T, dy, dy, dx, dx]``.

    ``H̃_{k,i}`` is row ``i`` of ``∂h/∂x`` at ``x_k`` (``k = k0 + t``); the mean is over
    the ``M`` paths. Then ``E[H̃ᵀ J_v H̃] = Σ_ij J_v[i, j] G[i, j]`` for any ``J_v``.
    """
    T = xs.shape[-2]
    out = []
    for t in range(T):
        x = xs[..., t, :]
        H = model.observation_jacobian(x, k0 + t)  # [..., M, dy, dx]
        # (a constant Jacobian, [dy, dx], broadcasts in the filters: had failed in einsum)
        H = H.expand(x.shape[:-1] + H.shape[-2:])
        out.append(torch.einsum("...mia,...mjb->...ijab", H, H) / H.shape[-3])
    return torch.stack(out, dim=-5)


def _pcrb_information(model, xs, x0, us, mask, information, num_samples, generator) -> Tensor:
    """The arguments of :func:`posterior_crb` checked; ``J_v`` for every step
    ``[..., T, dy, dy]`` (given, or from the measurement noise and the mask)."""
    if not isinstance(model, StateSpaceModel):
        raise ValueError(f"model must be a difffilter.StateSpaceModel; got {type(model).__name__}")
    # its noises of its dimensions, written covariances symmetric (a 1-dim R assigned to a
    # model of two sensors had given a bound 2.6× the one of R = 0.5 I: a covariance-write
    # trial), as the filters check them
    check_model(model, prior=False)
    # Q⁻¹ and P0⁻¹ are the Fisher information of Gaussians alone: another law's is larger,
    # and a mixture's process noise had given a "bound" a particle filter beat by 0.55×
    for what, law in (("process noise", getattr(model, "process_noise", None)),
                      ("prior (model.initial)", getattr(model, "initial", None))):  # fmt: skip
        if not isinstance(law, Gaussian):
            raise ValueError(
                f"posterior_crb needs a Gaussian {what} (its information is the inverse "
                f"covariance); got {type(law).__name__}"
            )
    if transition_law_unsaid(model):
        warnings.warn(
            f"{type(model).__name__} draws its transitions its own way (sample_transition): the "
            "bound assumes x_{k+1} = f(x_k, u_k) + w, w ~ N(0, process_cov), and where the "
            "truth draws another noise it is no bound (the robot's input noise: its EKF came "
            "within 0.86 of it); a class whose draw has that law says so with "
            "samples_process_noise = True",
            stacklevel=3,
        )
    if information is None and _measurement_law_unsaid(model):
        warnings.warn(
            f"{type(model).__name__} draws or weighs its measurements its own way "
            "(sample_measurement / measurement_log_prob): the bound takes J_v from "
            f"measurement_noise ({type(model.measurement_noise).__name__}), and where the truth "
            "has another law it is no bound (a Laplace noise of the same variance has twice "
            "the information: a particle filter reached 0.84 of it); pass that law's "
            "information=, or a class whose draw and density are measurement_noise's says so "
            "with samples_measurement_noise = True",
            stacklevel=3,
        )
    dx, dy = model.dim_x, model.dim_y
    if not isinstance(xs, Tensor) or xs.dim() < 3 or xs.shape[-1] != dx:
        got = tuple(xs.shape) if isinstance(xs, Tensor) else type(xs).__name__
        raise ValueError(f"xs must be a tensor [..., M, T, {dx}] of true trajectories; got {got}")
    if not isinstance(x0, Tensor) or x0.shape != xs.shape[:-2] + (dx,):
        got = tuple(x0.shape) if isinstance(x0, Tensor) else type(x0).__name__
        raise ValueError(
            f"x0 must have shape {tuple(xs.shape[:-2]) + (dx,)} (xs without T); got {got}"
        )
    # the model's dtype and device, as the filters ask (a docs trial: float32 paths on a
    # float64 model met torch's "expected scalar type Double but found Float")
    dtype, device = model_dtype_device(model)
    _check_float_tensor(xs, "xs", f"[..., M, T, {dx}]", dtype, device)
    _check_float_tensor(x0, "x0", f"[..., M, {dx}]", dtype, device)
    if not bool(torch.isfinite(xs).all()) or not bool(torch.isfinite(x0).all()):
        raise ValueError("xs and x0 must be finite")
    T = xs.shape[-2]
    if T == 0 or xs.shape[-3] == 0:  # (a NaN bound, or torch's "non-empty TensorList")
        raise ValueError(f"xs must hold at least one path and one step; got {tuple(xs.shape)}")
    if not callable(getattr(model, "transition_matrix", None)):  # (F does not read u)
        check_inputs_given(model, us, "posterior_crb", "its Jacobians ∂f/∂x at u_k")
    if us is not None:  # (a us without its T axis read path t's input at step t, unsaid)
        _check_us(model, us, xs.shape[:-2], T, dtype, device, against="xs's [..., M]")
    if mask is not None and information is not None:  # (the mask had been ignored)
        raise ValueError(
            "give mask or information, not both: information is J_v of what was received; "
            "zero its rows and columns of the entries not received instead"
        )
    mask = _check_mask(mask, dy)
    if mask is not None and (mask.dim() < 2 or mask.shape[-2] != T):
        raise ValueError(
            f"mask must have shape [..., {T}, {dy}] (one row per step); got {tuple(mask.shape)}"
        )
    _check_unbatched_model(model)
    # R_k read step by step where the model varies it, or where its class overrides
    # measurement_cov (the filters and simulate read the override, time-varying or not:
    # a constant override of 4 I had bounded with the constructor's I, 0.50 against the
    # Kalman filter's 1.20, below the optimal filter; a core-filter trial)
    overridden = isinstance(model.measurement_noise, Gaussian) and model._varying_noise(
        "measurement_cov"
    )
    if information is None and (model.time_varying or overridden):
        if not isinstance(model.measurement_noise, Gaussian):
            raise ValueError(
                "a time-varying model's measurement noise is known to this bound only through "
                "measurement_cov(k) (Gaussian): pass information= [..., T, dy, dy] for "
                f"{type(model.measurement_noise).__name__} noise"
            )
        rows = [None if mask is None else mask[..., t, :] for t in range(T)]
        # checked as the filters read it (an indefinite R_3 had given a "bound", no error)
        parts = [gaussian_information(step_covariance(model, "measurement_cov", t + 1), m)
                 for t, m in enumerate(rows)]  # fmt: skip
        batch = torch.broadcast_shapes(*(p.shape[:-2] for p in parts))
        information = torch.stack([p.expand(batch + (dy, dy)) for p in parts], dim=-3)
    elif information is None:
        noise = model.measurement_noise
        if mask is None:
            jv = noise_information(noise, None, num_samples=num_samples, generator=generator)
            information = jv.expand(T, dy, dy)
        else:
            information = noise_information(
                noise, mask, num_samples=num_samples, generator=generator
            )
    elif not isinstance(information, Tensor) or information.shape[-3:] != (T, dy, dy):
        got = (
            tuple(information.shape)
            if isinstance(information, Tensor)
            else type(information).__name__
        )
        raise ValueError(f"information must be a tensor [..., {T}, {dy}, {dy}]; got {got}")
    else:  # a Fisher information: finite, symmetric, positive semi-definite
        info = information.detach().double()
        ok = bool(torch.isfinite(info).all())
        if ok and info.numel():
            # round-off of the given dtype passes (a fixed 1e-8 had refused float32's, the
            # library's own gaussian_information among them); float64 keeps 1e-8
            eps = torch.finfo(information.dtype).eps if information.is_floating_point() else 0.0
            tol = max(1e-8, 100 * eps) * info.abs().amax().clamp_min(1.0)
            ok = bool((info - info.mT).abs().amax() <= tol) and bool(
                torch.linalg.eigvalsh(symmetrize(info)).amin() >= -tol
            )
        if not ok:
            raise ValueError("information must be finite, symmetric and positive semi-definite "
                             "(a Fisher information)")  # fmt: skip
    # its batch (the mask's) fits the paths' (torch's broadcast error had named neither)
    lead, paths = information.shape[:-3], xs.shape[:-3]
    try:
        torch.broadcast_shapes(lead, paths)
    except RuntimeError:
        raise ValueError(
            f"the mask's or information's batch {tuple(lead)} does not broadcast with the "
            f"paths' batch {tuple(paths)} (xs [..., M, T, dx])"
        ) from None
    return information


def _check_unbatched_model(model: StateSpaceModel) -> None:
    """The bound's leading dimensions are its own batch (``xs [..., M, T, dx]``); a model
    whose matrices carry a batch of their own would line it up with the ``M`` paths."""
    mats = {"process_cov(0)": model.process_cov(0), "measurement_cov(1)": model.measurement_cov(1),
            "initial.cov": model.initial.cov}  # fmt: skip
    # H at step 1 (no measurement at 0: a model defining H_k for k ≥ 1 alone had failed)
    for name, k in (("transition_matrix", 0), ("observation_matrix", 1), ("control_matrix", 0)):
        if callable(getattr(model, name, None)):
            value = getattr(model, name)(k)
            if value is not None:
                mats[f"{name}({k})"] = value
    batched = [f"{n} {tuple(m.shape)}" for n, m in mats.items() if m.dim() > 2]
    if batched:
        raise ValueError(
            "posterior_crb needs a model without batch dimensions of its own (one bound per "
            "model: give the batch through xs [..., M, T, dx]); got " + ", ".join(batched)
        )


def posterior_crb(
    model: StateSpaceModel,
    xs: Tensor,
    x0: Tensor,
    *,
    us: Tensor | None = None,
    mask: Tensor | None = None,
    information: Tensor | None = None,
    num_samples: int = 200_000,
    generator: torch.Generator | None = None,
) -> PCRBResult:
    """The PCRB recursion of the module docstring along ``T`` steps.

    Args:
        model: a :class:`~difffilter.StateSpaceModel` with Gaussian process noise
            (``model.process_cov``) and a Gaussian prior (``model.initial.cov``);
            Jacobians from ``transition_jacobian``/``observation_jacobian``. A
            ``time_varying`` model is read at every step (``Q_k = process_cov(k)``, ``J_v``
            from ``measurement_cov(k + 1)``: its measurement noise must be Gaussian unless
            ``information`` is given; ``J_v`` is read from ``measurement_cov`` too where a
            subclass overrides it, as the filters do; an overriding ``Q_k`` or ``R_k`` is
            checked as the filters check it, and a singular ``Q_k``, which the recursion
            inverts, is refused by name); the model's matrices carry no batch dimensions of
            their own (``ValueError``). A model whose class draws or weighs its measurements
            its own way (``sample_measurement``, ``measurement_log_prob``) is warned unless
            it declares ``samples_measurement_noise = True`` or ``information`` is given,
            as one drawing its transitions is unless ``samples_process_noise = True``.
        xs: true trajectories ``x_1 … x_T`` ``[..., M, T, dx]`` (the expectations over
            ``x`` are means over the ``M`` paths; ``M = 1`` for a linear model). The
            ``[B, T, dx]`` of ``model.simulate`` is read as ``M = B`` paths of ONE bound
            ``[T, dx, dx]``, with no run dimension: ``bound[t]`` is step ``t + 1``, not run
            ``t`` (an analyst's trial read ``bound[0]`` as run 0's).
        x0: their initial states ``[..., M, dx]``.
        us: inputs ``[..., M, T, du]`` or ``None`` (zero inputs); required on a model with
            inputs and without ``transition_matrix``, whose Jacobians read them
            (``ValueError``).
        mask: received entries ``[..., T, dy]`` (bool) or ``None`` (all received); an
            all-false step adds no information. Not with ``information`` (``ValueError``).
        information: ``J_v`` for every step, ``[..., T, dy, dy]``, instead of computing
            it from ``model.measurement_noise`` and ``mask`` with :func:`noise_information`.
        num_samples, generator: of the Monte Carlo Fisher information (non-Gaussian noise).

    Returns a :class:`PCRBResult` (``information``, ``bound``: ``[..., T, dx, dx]``), in
    ``xs``' dtype; the recursion runs in float64 (:func:`_recursion_dtype`).
    """
    information = _pcrb_information(model, xs, x0, us, mask, information, num_samples, generator)
    dx, T = model.dim_x, xs.shape[-2]
    work = _recursion_dtype(xs)
    information = information.to(work)
    G = measurement_information_moments(model, xs).to(work)  # [..., T, dy, dy, dx, dx]

    def q_inv(t: int) -> Tensor:  # Q_t of the transition x_t → x_{t+1}, as the filters read it
        Q = step_covariance(model, "process_cov", t)  # (an indefinite Q_k had been read)
        return _definite_inverse(
            Q.to(work), f"{type(model).__name__}.process_cov({t})",
            "the PCRB recursion needs Q_k⁻¹ (the information of the transition noise, "
            "infinite along a noiseless direction); add a small jitter to Q_k (e.g. 1e-9 I) "
            "or bound a reduced state without the noiseless components",
        )  # fmt: skip

    Q_inv = q_inv(0)
    # Q_t read step by step where the model varies it or its class overrides process_cov, as
    # simulate and the filters read it (an override with time_varying False had been read at
    # k = 0 alone: a bound 4.5 times below the EKF's covariance; a time-index trial)
    varying_q = model.time_varying or (
        isinstance(model.process_noise, Gaussian) and model._varying_noise("process_cov")
    )
    J = _definite_inverse(
        model.initial.cov.to(work), f"{type(model).__name__}.initial.cov",
        "the PCRB starts from its inverse J_0 = P_0⁻¹ (infinite along a component known "
        "exactly); add a small jitter to P_0 (e.g. 1e-9 I) or bound a reduced state without "
        "the known components",
    )  # fmt: skip
    batch = torch.broadcast_shapes(information.shape[:-3], G.shape[:-5])
    J = J.expand(batch + (dx, dx))
    x_prev, out = x0, []
    for t in range(T):
        u = None if us is None else us[..., t, :]
        if varying_q and t > 0:
            Q_inv = q_inv(t)
        Fj = model.transition_jacobian(x_prev, u, t).to(work)  # [..., M, dx, dx]
        Fj = Fj.expand(x_prev.shape[:-1] + Fj.shape[-2:])  # (a constant one, [dx, dx])
        M = Fj.shape[-3]
        D11 = (Fj.transpose(-1, -2) @ Q_inv @ Fj).sum(-3) / M
        D12 = -(Fj.sum(-3) / M).transpose(-1, -2) @ Q_inv
        D22 = Q_inv + torch.einsum(
            "...ij,...ijab->...ab", information[..., t, :, :], G[..., t, :, :, :, :]
        )
        A = J + D11
        # D12 given the batch of A: torch.linalg.solve reads B [dx, dx] beside A [dx, dx, dx]
        # (a batch of masks as long as dx) as dx vectors, not one matrix, and the bounds
        # came out wrong, not even semi-definite (a trial: the tracking report at 4 runs)
        D12_A = D12.expand(A.shape[:-2] + D12.shape[-2:])
        J = symmetrize(D22 - D12.transpose(-1, -2) @ torch.linalg.solve(A, D12_A))
        out.append(J)
        x_prev = xs[..., t, :]
    info = torch.stack(out, dim=-3)
    bound = symmetrize(torch.linalg.inv(info))
    return PCRBResult(info.to(xs.dtype), bound.to(xs.dtype))


def _recursion_dtype(xs: Tensor) -> torch.dtype:
    """float64, where the device has it (mps has not: ``xs``' dtype). ``J = D22 − D21 (J +
    D11)⁻¹ D12`` subtracts two matrices of size ``‖Q⁻¹‖`` to get one of size ``‖J‖``: in
    float32 (``cond Q`` 1.2e5) the "bound" had been 0.79×–1.78× the Kalman filter's
    covariance, above the optimal filter's MSE at step 1; ``dx × dx`` matrices, cheap in
    float64. A float64 ``xs`` runs as before, to the bit."""
    return xs.dtype if xs.device.type == "mps" else torch.float64
