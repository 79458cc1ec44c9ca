"""Online training of any ``nn.Module``'s weights, batched across independent runs.

:class:`ParamEKF` is the extended Kalman filter over network weights of Sargolzaei et al.
(TII 2020, eqs 10–14), after Singhal & Wu and Ljung & Söderström. The weights
``ζ`` are the state of a random-walk model observed through the network::

    target_k = f(ζ, x_k) + noise,     H_k = ∂f(ζ_{k−1}, x_k)/∂ζ   [m, P]      (13)
    e_k      = target_k − f(ζ_{k−1}, x_k)
    Υ_k      = Υ_{k−1} + (e_kᵀe_k − Υ_{k−1}) / k                              (14b)
    λ_k      = ρ_k H_kᵀ (H_k ρ_k H_kᵀ + Υ_k I)⁻¹                              (12)
    ζ_k      = ζ_{k−1} + η λ_k e_k                                            (11)
    ρ_{k+1}  = ρ_k − λ_k H_k ρ_k  (+ Q_ρ I)                                   (14)

(the paper writes ``H`` for our ``Hᵀ`` and indexes (14) one step back; it is the same
recursion.) ``Q_ρ`` is a declared deviation: without it (14) only ever shrinks ``ρ``, and
with it the gain ``λ``, so the network stops adapting; ``process_noise=0`` gives the
paper's equations exactly.

:class:`OnlineGradientDescent` is the plain gradient rule of the paper's "traditional"
baseline: ``ζ_k = ζ_{k−1} + lr · H_kᵀ e_k``, a gradient step on ``½‖e_k‖²``.

:class:`EKFOptimizer` is the same EKF as a ``torch.optim.Optimizer`` over one shared
parameter vector (the weights of a network being trained offline), observed at each step
through a pool of ``S`` samples stacked into one measurement: ``H_k [S·m, P]``, ``e_k
[S·m]``, and ``Υ_k`` the running mean of ``‖e‖²`` per sample. Its state (``ρ``, ``Υ``,
``k`` and, once given ``received``, ``seen``) lives in the optimizer's ``state_dict``, so a
Lightning checkpoint resumes it (one written before ``seen`` resumes as it was). An entry
not received (``received``) carries no information, in the update or in ``Υ``.

The learning rules are pure functions of a :class:`LearnerState` (``θ``, ``ρ``, ``Υ``,
``k``): :class:`EKFRule` and :class:`GradientRule` step it, :class:`WeightTemplate` maps
flat weights through the network, so that the learned estimator keeps every run's
learner in its carry (:mod:`difffilter.fdi.neural`). :class:`ParamEKF` and
:class:`OnlineGradientDescent` are the same rules holding their state, for direct use.

Both hold one independent parameter vector per run: parameters ``[*batch, *shape]``,
inputs ``[*batch, ...]``, outputs ``[*batch, m]``. Jacobians come from ``torch.func``
(``vmap`` of ``jacrev`` of ``functional_call``), so any module whose forward maps one
input to a vector works. A module may instead provide closed forms,
``batched_forward(params, x)`` → ``[N, m]`` and ``batched_jacobian(params, x)`` →
``([N, m], [N, m, P])`` with ``params = {name: [N, *shape]}``, ``x [N, ...]`` and the
parameters flattened row-major in registration order; they are used when present.
Nothing here is differentiable through the updates: the rules run under
``torch.no_grad``.

Speed (the LFC learners: ``N`` = runs × areas = 40 filters of ``P = 350`` weights, ``m = 5``
outputs, 2000 steps per scenario): a step is bound by passes over the ``N·P²`` covariances
(39 MB), not by flops. Two things keep them few, with the same equations:

* a network ``f = W tanh(V x)``, ``x = δ / s`` (:class:`WeightTemplate` recognises it) has the
  Kronecker-factored Jacobian of :class:`KroneckerJacobian`, so ``Hρ`` is two
  vector-times-matrix products over ``ρ``'s rows (one pass) instead of an ``m``-column
  product;
* :class:`EKFRule` defers eq. (14): ``ρ_k = B + β I − Gᵀ G`` with the rows ``G_j = L_j⁻¹ H_j
  ρ_j`` (``S_j = L_j L_jᵀ``) of the last few steps, ``λ_j H_j ρ_j = ρ_j H_jᵀ S_j⁻¹ H_j ρ_j =
  G_jᵀ G_j`` (the symmetric form of (14)), and folds them into ``B`` every ``fold_every``
  steps as one product of ``fold_every·m`` columns (:class:`DeferredCovariance`).

:func:`dense_reference` runs the previous implementation (``ρ`` dense, eq. 14 in place at
every step) for comparisons: the benchmark and the equivalence tests. The two are the same
recursion with round-off in another order; in the LFC closed loop they agree to 1e-9 on
short runs, and on the full scenarios to about 1e-10 in the metrics except where a
learner is chaotic, where any change of order grows (``kf_nn_ekf_qrho0`` on
``lfc_sawtooth``: 7e-4; the dense update's own metrics there move by 1e-5 between one
and two threads).
"""

from __future__ import annotations

import contextlib
import inspect
import weakref
from functools import lru_cache
from typing import NamedTuple

import torch
from torch import Tensor, nn
from torch.func import functional_call, jacrev, vmap

from ._checks import check_finite_number
from .gaussian import kalman_gain
from .linalg import safe_cholesky, symmetrize

__all__ = [
    "WeightTemplate",
    "KroneckerJacobian",
    "DeferredCovariance",
    "LearnerState",
    "dense_reference",
    "EKFRule",
    "GradientRule",
    "ParamEKF",
    "OnlineGradientDescent",
    "EKFOptimizer",
    "ekf_along_sequence",
    "ParamStepOutput",
]


class ParamStepOutput(NamedTuple):
    """What a learning step saw: the prediction with the old weights and its residual.

    ``prediction [*batch, m]`` is ``f(ζ_{k−1}, x_k)``; ``residual [*batch, m]`` is
    ``target_k − prediction``.
    """

    prediction: Tensor
    residual: Tensor


class LearnerState(NamedTuple):
    """The state of ``N`` online learners: flat weights ``theta [N, P]``, the EKF's
    covariances ``rho`` (a :class:`DeferredCovariance`, or ``[N, P, P]`` under
    :func:`dense_reference`; :meth:`EKFRule.covariance` gives the matrices) and running
    noise ``upsilon [N]`` (``None`` for plain gradient steps) and the step count ``k``.
    ``seen [N]``: how many steps informed each learner's ``Υ``, counted from the first
    step given ``received`` (:meth:`EKFRule.step`; ``None`` before: ``k``, every step
    informed)."""

    theta: Tensor
    rho: Tensor | DeferredCovariance | None
    upsilon: Tensor | None
    k: int
    seen: Tensor | None = None


def _bmv(M: Tensor, v: Tensor) -> Tensor:
    """``M_n v_n``: ``M [N, a, b]``, ``v [N, b]`` → ``[N, a]`` (one batched GEMM)."""
    return torch.bmm(M, v.unsqueeze(-1)).squeeze(-1)


@lru_cache(maxsize=16)
def _kronecker_order(m: int, h: int, n: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """``(order, inverse)`` [P]: the covariance order of :class:`KroneckerJacobian` lists
    ``W [m, h]`` and then ``V [h, n]`` column-major, ``θ̃ = θ[order]``, ``θ = θ̃[inverse]``."""
    w = torch.arange(m * h, device=device).reshape(m, h).T.reshape(-1)
    v = m * h + torch.arange(h * n, device=device).reshape(h, n).T.reshape(-1)
    order = torch.cat([w, v])
    return order, torch.argsort(order)


class KroneckerJacobian(NamedTuple):
    """The Jacobian of ``N`` networks ``f = W tanh(V x)`` (``W [m, h]``, ``V [h, n]``) at
    inputs ``x [N, n]``, in factors (eq. 13)::

        ∂f_i/∂W_kj = 1[i = k] h_j,   ∂f_i/∂V_jl = M_ij x_l,   h = tanh(V x),  M = W diag(1 − h²)

    ``hidden h [N, h]``, ``outer M [N, m, h]``, ``inputs x [N, n]``. :meth:`dense` is ``H [N, m,
    P]`` with the weights row-major (``θ``'s order); the EKF keeps its covariance in the
    order ``W``, ``V`` column-major (:meth:`order`), where ``H ρ`` reads ``ρ``'s rows in
    two vector-times-matrix products (:meth:`rows`).
    """

    hidden: Tensor
    outer: Tensor
    inputs: Tensor

    @property
    def sizes(self) -> tuple[int, int, int]:
        """``(m, h, n)``."""
        return self.outer.shape[-2], self.outer.shape[-1], self.inputs.shape[-1]

    def order(self) -> tuple[Tensor, Tensor]:
        """``(order, inverse)`` of the covariance's order (``θ̃ = θ[order]``)."""
        return _kronecker_order(*self.sizes, self.outer.device)

    def dense(self) -> Tensor:
        """``H [N, m, m·h + h·n]`` in ``θ``'s order (the same numbers, bit for bit, as the
        closed form of :class:`~difffilter.models.neural_estimator.AreaNetwork`)."""
        h, M, x = self.hidden, self.outer, self.inputs
        (N, m, hid), eye = M.shape, torch.eye(M.shape[-2], dtype=M.dtype, device=M.device)
        d_w = (eye[None, :, :, None] * h[:, None, None, :]).reshape(N, m, m * hid)
        d_v = (M[..., None] * x[:, None, None, :]).reshape(N, m, hid * x.shape[-1])
        return torch.cat([d_w, d_v], dim=-1)

    def permuted(self) -> Tensor:
        """``H̃ [N, m, P]``: :meth:`dense` in the covariance's order (``H[..., order]``)."""
        h, M, x = self.hidden, self.outer, self.inputs
        (N, m, hid), eye = M.shape, torch.eye(M.shape[-2], dtype=M.dtype, device=M.device)
        d_w = (eye[None, :, None, :] * h[:, None, :, None]).reshape(N, m, hid * m)  # [i, (j, k)]
        d_v = (x[:, None, :, None] * M[:, :, None, :]).reshape(
            N, m, x.shape[-1] * hid
        )  # [i, (l, j)]
        return torch.cat([d_w, d_v], dim=-1)

    def rows(self, rho: Tensor) -> Tensor:
        """``H̃ ρ [N, m, P]`` for ``ρ [N, P, P]`` in the covariance's order::

            (H̃ρ)_i = Σ_j h_j ρ_(j,i) + Σ_j M_ij Σ_l x_l ρ_(l,j)      (ρ_r: row r)

        a pass over ``ρ``'s rows: ``hᵀ [h, m·P]`` and ``xᵀ [n, h·P]`` (views, no copy).
        """
        h, M, x = self.hidden, self.outer, self.inputs
        (N, m, hid), n, P = M.shape, x.shape[-1], rho.shape[-1]
        w_rows = rho[:, : m * hid].reshape(N, hid, m * P)
        v_rows = rho[:, m * hid :].reshape(N, n, hid * P)
        by_w = torch.bmm(h.unsqueeze(1), w_rows).view(N, m, P)
        by_v = torch.bmm(x.unsqueeze(1), v_rows).view(N, hid, P)
        return torch.baddbmm(by_w, M, by_v)


class DeferredCovariance(NamedTuple):
    """``N`` EKF covariances with eq. (14) deferred: ``ρ = base + shift·I − Gᵀ G``, ``G =
    pending[:, :count]``, in the order ``order`` (``None``: ``θ``'s; else ``θ̃ = θ[order]``).

    ``base [N, P, P]``; ``pending [N, C, P]`` holds the rows ``L_j⁻¹ H_j ρ_j`` of the steps
    since the last fold (``m`` per step); ``shift`` the ``Q_ρ`` added since.
    """

    base: Tensor
    pending: Tensor
    count: int
    shift: float
    order: Tensor | None = None
    #: ``(id, version)`` of ``base`` and ``pending`` when a donating rule handed this state
    #: out (``None``: not donated): a later in-place write to them, by a step that ran from
    #: this state, marks it consumed (:meth:`EKFRule.step` refuses it).
    stamp: tuple | None = None

    def dense(self) -> Tensor:
        """``ρ [N, P, P]`` in ``θ``'s order (a new tensor)."""
        rho = self.base.clone()
        if self.count:
            G = self.pending[:, : self.count]
            rho.baddbmm_(G.transpose(-1, -2), G, alpha=-1.0)
        rho.diagonal(dim1=-2, dim2=-1).add_(self.shift)
        if self.order is None:
            return rho
        inverse = torch.argsort(self.order)
        return rho[:, inverse][:, :, inverse]


_REFERENCE = [False]


@contextlib.contextmanager
def dense_reference():
    """Inside, :meth:`EKFRule.init` starts the previous implementation: ``ρ [N, P, P]``
    updated in full at every step (:func:`ekf_weight_update`, symmetrised every 16 steps).
    The same equations; for timing and checking the deferred form against it."""
    before = _REFERENCE[0]
    _REFERENCE[0] = True
    try:
        yield
    finally:
        _REFERENCE[0] = before


class WeightTemplate:
    """A module's parameters as flat per-run vectors ``θ [N, P]`` (row-major, registration
    order), and its output and Jacobian at them.

    ``forward(θ, x [N, ...]) → [N, m]`` and ``jacobian(θ, x) → ([N, m], [N, m, P])`` use the
    module's closed forms (``batched_forward``/``batched_jacobian``) when it has them, else
    ``torch.func`` (``vmap`` of ``jacrev`` of ``functional_call``).

    A module computing ``W tanh(V (δ / in_scale))`` (parameters ``W [m, h]`` then ``V [h, n]``,
    buffer ``in_scale [n]``, one input ``δ [n]``: the LFC area network; checked once, here, on
    random weights and inputs) is ``factored``: :meth:`jacobian` then returns its
    :class:`KroneckerJacobian` (``factored=False``: ``H [N, m, P]``).
    """

    def __init__(self, module: nn.Module):
        if not isinstance(module, nn.Module):
            raise ValueError(f"module must be an nn.Module; got {type(module).__name__}")
        base = dict(module.named_parameters())
        if not base:
            raise ValueError("module has no parameters to train")
        self.module = module
        self.names = list(base)
        self.shapes = {n: base[n].shape for n in self.names}
        self.defaults = {n: base[n].detach() for n in self.names}
        # Buffers (non-trainable state) travel with the template, unbatched.
        self.buffers = dict(module.named_buffers())
        self.factored = self._is_tanh_layer()

    def _is_tanh_layer(self) -> bool:
        """Whether the module is ``W tanh(V (δ / in_scale))``: names and shapes, then its
        forward against that formula at random weights and inputs (a private generator)."""
        W, V, scale = self.shapes.get("W"), self.shapes.get("V"), self.buffers.get("in_scale")
        if (self.names != ["W", "V"] or len(W) != 2 or len(V) != 2 or W[1] != V[0]
                or scale is None or tuple(scale.shape) != (V[1],)):  # fmt: skip
            return False
        dtype = self.defaults["W"].dtype
        if not dtype.is_floating_point:
            return False
        g = torch.Generator().manual_seed(0)
        W_, V_ = (torch.randn(s, generator=g, dtype=dtype) for s in (W, V))
        delta = torch.randn(3, V[1], generator=g, dtype=dtype)
        try:
            with torch.no_grad():
                out = functional_call(self.module, {"W": W_, "V": V_, **self.buffers}, (delta,))
        except Exception:  # noqa: BLE001 - any module that cannot take this input is not one
            return False
        want = torch.tanh((delta / scale) @ V_.T) @ W_.T
        return out.shape == want.shape and torch.allclose(out, want, rtol=1e-10, atol=1e-12)

    @property
    def num_params(self) -> int:
        return sum(s.numel() for s in self.shapes.values())

    def flatten(self, params: dict[str, Tensor], batch_shape: torch.Size) -> Tensor:
        """``{name: [*batch, *shape]}`` (broadcast; missing names: the module's own
        weights) → ``θ [N, P]`` (a new tensor)."""
        unknown = set(params) - set(self.names)
        if unknown:
            raise ValueError(f"params has names the module does not: {sorted(unknown)}")
        flat = []
        for n in self.names:
            value = params.get(n, self.defaults[n]).detach()
            if value.dtype != self.defaults[n].dtype:  # (float32 over a float64 network had
                # failed deep in the factored Jacobian, or learned in float32 unsaid)
                raise ValueError(
                    f"params[{n!r}] must be of the module's dtype {self.defaults[n].dtype}; got "
                    f"{value.dtype} (convert it, or the module: module.to(dtype))"
                )
            want = batch_shape + self.shapes[n]
            try:
                value = value.expand(want)
            except RuntimeError as exc:
                raise ValueError(
                    f"params[{n!r}] must broadcast to {tuple(want)}; got {tuple(value.shape)}"
                ) from exc
            flat.append(
                value.reshape(batch_shape.numel(), self.shapes[n].numel())
            )  # (no -1: no runs)
        return torch.cat(flat, dim=1).clone()

    def unflatten(self, theta: Tensor) -> dict[str, Tensor]:
        """``θ [..., P]`` → ``{name: [..., *shape]}`` (views)."""
        out, i = {}, 0
        for n in self.names:
            size = self.shapes[n].numel()
            out[n] = theta[..., i : i + size].reshape(theta.shape[:-1] + self.shapes[n])
            i += size
        return out

    def _single(self, theta: Tensor, x: Tensor) -> Tensor:
        out = functional_call(self.module, {**self.unflatten(theta), **self.buffers}, (x,))
        if out.dim() != 1:
            raise ValueError(
                f"the module must map one input to a vector [m]; got {tuple(out.shape)}"
            )
        return out

    def forward(self, theta: Tensor, x: Tensor) -> Tensor:
        """``f(θ_n, x_n)`` for every learner: ``[N, P]``, ``[N, ...]`` → ``[N, m]``."""
        with torch.no_grad():
            if hasattr(self.module, "batched_forward"):
                return self.module.batched_forward(self.unflatten(theta), x)
            return vmap(self._single)(theta, x)

    def jacobian(self, theta: Tensor, x: Tensor, *, autodiff: bool = False,
                 factored: bool | None = None):  # fmt: skip
        """``(f [N, m], H = ∂f/∂θ)``: ``[N, m, P]``, or a :class:`KroneckerJacobian` where the
        module is ``factored`` (``factored=False`` asks for ``[N, m, P]``; ``autodiff=True``
        ignores closed forms)."""
        with torch.no_grad():
            if self.factored and factored is not False and not autodiff:
                return self._factors(theta, x)
            if hasattr(self.module, "batched_jacobian") and not autodiff:
                return self.module.batched_jacobian(self.unflatten(theta), x)
            if self.factored and not autodiff:
                out, H = self._factors(theta, x)
                return out, H.dense()

            def with_aux(t, xi):
                out = self._single(t, xi)
                return out, out

            H, out = vmap(jacrev(with_aux, has_aux=True))(theta, x)
        return out, H

    def _factors(self, theta: Tensor, x: Tensor) -> tuple[Tensor, KroneckerJacobian]:
        """``(f [N, m], KroneckerJacobian)`` of ``W tanh(V x̃)``, ``x̃ = x / in_scale`` (the
        operations of the module's closed form, so the same numbers)."""
        p = self.unflatten(theta)
        W, V = p["W"], p["V"]
        xs = x / self.buffers["in_scale"]
        h = torch.tanh(_bmv(V, xs))
        return _bmv(W, h), KroneckerJacobian(h, W * (1.0 - h * h)[:, None, :], xs)


def ekf_weight_update(
    rho: Tensor, H: Tensor, e: Tensor, upsilon: Tensor, q: float, k: int, *, donate: bool = False
) -> tuple[Tensor, Tensor]:
    """Eqs (12) and (14) for ``N`` filters: ``(λ_k e_k [N, P], ρ_{k+1} [N, P, P])`` from
    ``ρ [N, P, P]``, ``H [N, m, P]``, ``e [N, m]``, ``Υ [N]``, ``Q_ρ = q`` and the step count.

    ``λ = ρHᵀ S⁻¹`` with ``S = HρHᵀ + Υ I`` is a Kalman gain (the Gaussian core's
    :func:`~difffilter.gaussian.kalman_gain`) and ``ρ ← ρ − λ(Hρ) (+ Q_ρ I)`` its covariance
    update in the plain form of eq. (14) (``Hρ = (ρHᵀ)ᵀ``: ``ρ`` is symmetric).
    ``donate=True`` writes ``ρ_{k+1}`` into the given ``ρ`` (the caller gives up its
    buffer, as a JAX computation's donated argument): the step is bound by passes over
    ``ρ``'s memory (``N·P²``: 39 MB for 40 runs × areas of the LFC network), and a new
    buffer per step costs as much again.
    """
    rho_Ht = rho @ H.transpose(-1, -2)  # ρHᵀ [N, P, m]
    eye_m = torch.eye(H.shape[-2], dtype=H.dtype, device=H.device)
    S = H @ rho_Ht + upsilon[:, None, None] * eye_m
    gain, _ = kalman_gain(rho_Ht, S)  # λ [N, P, m]
    if donate:
        rho = rho.baddbmm_(gain, rho_Ht.transpose(-1, -2), alpha=-1.0)
    else:  # a new ρ (the one given is not modified); Q_ρ goes onto its diagonal in place
        rho = torch.baddbmm(rho, gain, rho_Ht.transpose(-1, -2), alpha=-1.0)
    if q > 0:
        rho.diagonal(dim1=-2, dim2=-1).add_(q)
    if k % 16 == 0:  # round-off slowly breaks the symmetry; restore it now and then
        rho = 0.5 * (rho + rho.transpose(-1, -2))
    return (gain @ e.unsqueeze(-1)).squeeze(-1), rho


class EKFRule:
    """The EKF over weights (eqs 10–14) as a pure rule over a :class:`LearnerState`.

    Args:
        lr: ``η`` of eq. (11) (the paper: a constant learning rate; [DEF] 1).
        init_cov: ``ρ(0) = init_cov·I`` ([DEF] 10).
        init_noise: ``Υ(0)`` (scalar; [DEF] tr Θ). It is read before the first step
            only: eq. (14b) at ``k = 1`` sets ``Υ_1 = e_1ᵀe_1`` whatever it is (the paper's
            running mean), so a first prediction without error leaves ``Υ_1 = 0``.
        process_noise: ``Q_ρ``, added to ``ρ`` after every update (0 = the paper).
        fold_every: steps between folds of the deferred downdates (:class:`DeferredCovariance`;
            [DEF] 8: fewer make each fold a thin product, more make every step's
            correction ``(H̃ Gᵀ) G`` longer).

    One step, with ``R = H ρ_k = H̃ B + β H̃ − (H̃ Gᵀ) G`` (``H̃``: ``H`` in the covariance's
    order)::

        S = R H̃ᵀ + Υ_k I = L Lᵀ                                          (12)
        λ_k e_k = Rᵀ S⁻¹ e_k = (L⁻¹ R)ᵀ (L⁻¹ e_k)                          (11)
        ρ_{k+1} = ρ_k − (L⁻¹ R)ᵀ (L⁻¹ R) + Q_ρ I = ρ_k − λ_k H ρ_k + Q_ρ I  (14)

    the new rows ``L⁻¹ R [N, m, P]`` appended to ``G``. Cost per step ``O(N·P²·m)`` time
    (one pass over ``B``, and a fold's ``N·P²·m`` multiply-adds amortised) and ``O(N·P²)``
    memory. ``donate``: :meth:`step` writes into the state's buffers (``G`` at every step,
    ``B`` at a fold; under :func:`dense_reference` ``ρ``): the state given is consumed.
    """

    def __init__(
        self,
        *,
        lr: float = 1.0,
        init_cov: float = 10.0,
        init_noise: float = 1e-3,
        process_noise: float = 0.0,
        donate: bool = False,
        fold_every: int = 8,
    ):
        self.lr, self.init_cov, self.init_noise = lr, init_cov, init_noise
        self.process_noise, self.donate, self.fold_every = process_noise, donate, fold_every

    def __setattr__(self, name, value):
        # checked whenever set, not at __init__ alone (finite too: an infinite lr or
        # covariance had been taken, every weight NaN after the first update: a fuzzing
        # trial of the constructors; a NaN lr assigned later ran: a trial of options set later)
        if name in ("lr", "init_cov", "init_noise"):
            value = check_finite_number(value, name, positive=True)
        elif name == "process_noise":
            value = check_finite_number(value, name, nonnegative=True)
        elif name == "fold_every":
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"fold_every must be an integer >= 1; got {value!r}")
        elif name == "donate":
            value = bool(value)
        super().__setattr__(name, value)

    def init(self, theta: Tensor) -> LearnerState:
        """``θ [N, P]`` with ``ρ(0) = init_cov·I`` (any order), ``Υ(0) = init_noise``."""
        N, P = theta.shape
        eye = torch.eye(P, dtype=theta.dtype, device=theta.device)
        rho = (self.init_cov * eye).expand(N, P, P).clone()
        ups = torch.full((N,), self.init_noise, dtype=theta.dtype, device=theta.device)
        if not _REFERENCE[0]:
            rho = DeferredCovariance(rho, theta.new_empty(N, 0, P), 0, 0.0)
            _note_scalar(rho.base)
        return LearnerState(theta, rho, ups, 0)

    @staticmethod
    def covariance(state: LearnerState) -> Tensor:
        """``ρ [N, P, P]`` of ``state`` in ``θ``'s order (a new tensor where deferred)."""
        rho = state.rho
        return rho.dense() if isinstance(rho, DeferredCovariance) else rho

    def step(self, state: LearnerState, H: Tensor | KroneckerJacobian, e: Tensor,
             received: Tensor | None = None) -> LearnerState:  # fmt: skip
        """One update (eqs 11–14) with ``H = ∂f(ζ_{k−1}, x_k)/∂ζ`` (``[N, m, P]`` or a
        :class:`KroneckerJacobian`) and the residual ``e_k [N, m]``.

        ``received [N, m]`` (bool; ``None``: all): the entries whose target arrived. An
        entry that did not carries no information: its rows of ``H`` and ``e`` are zeroed
        (``S`` keeps ``Υ`` on its diagonal there), so a learner that received nothing keeps
        its weights and covariance (``Q_ρ`` aside), and ``Υ`` is the running mean over
        the steps that informed it of ``(m / m_r) ‖e_r‖²`` (``m_r`` entries received: the
        whole residual's energy at the received entries' rate)."""
        _check_step_shapes(state, H, e)
        with torch.no_grad():
            k = state.k + 1
            if received is None:
                seen = None if state.seen is None else state.seen + 1
                ups = state.upsilon + ((e * e).sum(-1) - state.upsilon) / (
                    k if seen is None else seen
                )
            else:
                r = _received(received, e)
                e = _unreceived_zeroed(e, r)
                energy, informed = _informed_energy(e, r)
                before = (
                    state.upsilon.new_full(informed.shape, float(state.k))
                    if state.seen is None
                    else state.seen
                )
                seen = before + informed.to(before.dtype)
                ups = torch.where(informed, state.upsilon + (energy - state.upsilon) / seen.clamp_min(1.0),
                                  state.upsilon)  # fmt: skip
            if not isinstance(state.rho, DeferredCovariance):  # dense_reference()
                dense = H.dense() if isinstance(H, KroneckerJacobian) else H
                if received is not None:
                    dense = _unreceived_zeroed(dense, r)
                step, rho = ekf_weight_update(
                    state.rho, dense, e, ups, self.process_noise, k, donate=self.donate
                )
                return LearnerState(state.theta + self.lr * step, rho, ups, k, seen)
            step, rho = self._deferred(
                state.rho, H, e, ups, state.k, None if received is None else r
            )
            return LearnerState(state.theta + self.lr * step, rho, ups, k, seen)

    def _deferred(self, cov: DeferredCovariance, H, e: Tensor, ups: Tensor, k0: int,
                  keep: Tensor | None = None):  # fmt: skip
        """``(λ_k e_k [N, P] in θ's order, ρ_{k+1})`` on the deferred form (class doc);
        ``keep [N, m]`` (bool) zeroes the rows of ``H`` of the entries not received."""
        if self.donate:
            _check_unconsumed(cov)
        kron = isinstance(H, KroneckerJacobian)
        order, inverse = H.order() if kron else (None, None)
        if not _same_order(cov.order, order):
            if k0:  # ρ(0) = c·I reads the same in any order; a later ρ does not
                raise ValueError("the Jacobian's order changed between steps of one learner")
            cov = _in_order(cov, order)
        Ht = H.permuted() if kron else H  # H̃ [N, m, P]
        R = H.rows(cov.base) if kron else torch.bmm(H, cov.base)  # H̃ B
        if cov.shift:
            R = R.add_(Ht, alpha=cov.shift)
        if cov.count:
            G = cov.pending[:, : cov.count]
            R = R.baddbmm_(torch.bmm(Ht, G.transpose(-1, -2)), G, alpha=-1.0)
        if keep is not None:  # R = H̃ ρ is linear in H̃'s rows: zeroing them at the end is exact
            R, Ht = _unreceived_zeroed(R, keep), _unreceived_zeroed(Ht, keep)
        S = torch.bmm(R, Ht.transpose(-1, -2))
        S.diagonal(dim1=-2, dim2=-1).add_(ups[:, None])
        L = safe_cholesky(symmetrize(S), name="innovation covariance S")
        rows = torch.linalg.solve_triangular(L, R, upper=False)  # L⁻¹ H ρ_k [N, m, P]
        w = torch.linalg.solve_triangular(L, e.unsqueeze(-1), upper=False)  # L⁻¹ e_k
        step = torch.bmm(w.transpose(-1, -2), rows).squeeze(-2)  # λ_k e_k, covariance order
        if inverse is not None:
            step = step[:, inverse]
        return step, self._push(cov, rows)

    def _push(self, cov: DeferredCovariance, rows: Tensor) -> DeferredCovariance:
        """Append ``rows`` to ``G`` and ``Q_ρ`` to the shift; fold when ``G`` is full."""
        (N, m, P), count = rows.shape, cov.count
        size = self.fold_every * m
        if self.donate:  # one buffer of `size` rows, written in place
            pending = cov.pending
            if pending.shape[1] != size:
                # (a state another rule stepped: one that does not donate keeps `count`
                # rows, another fold_every another width; its rows are still to fold, and a
                # fresh buffer without them had dropped eq. (14)'s downdates: a trial)
                pending = rows.new_empty(N, max(size, count + m), P)
                pending[:, :count] = cov.pending[:, :count]
            pending[:, count : count + m] = rows
        else:
            pending = torch.cat([cov.pending[:, :count], rows], dim=1)
        count, shift = count + m, cov.shift + self.process_noise
        if count < size:
            return cov._replace(pending=pending, count=count, shift=shift,
                                stamp=_stamp(cov.base, pending) if self.donate else None)  # fmt: skip
        G = pending[:, :count]
        # one product of `size` columns: the deferral's point (m columns at a time is a
        # thin product that runs several times slower per multiply-add)
        if self.donate:
            base = cov.base.baddbmm_(G.transpose(-1, -2), G, alpha=-1.0)
        else:
            base = torch.baddbmm(cov.base, G.transpose(-1, -2), G, alpha=-1.0)
        base.diagonal(dim1=-2, dim2=-1).add_(shift)
        return DeferredCovariance(base, pending, 0, 0.0, cov.order,
                                  _stamp(base, pending) if self.donate else None)  # fmt: skip


def _check_step_shapes(state: LearnerState, H, e: Tensor) -> None:
    """``ValueError`` unless ``e`` is ``[N, m]`` and ``H`` ``[N, m, P]`` (or factors of
    ``N`` runs and ``m`` outputs) for ``θ [N, P]``: a residual ``[m]`` or ``[1, m]`` of
    ``N`` runs had broadcast, every run updated with run 0's residual (a trial)."""
    N, P = state.theta.shape
    if isinstance(H, KroneckerJacobian):
        m, hid, n = H.sizes
        rows, width = H.outer.shape[0], m * hid + hid * n
    else:
        rows, m, width = H.shape if H.dim() == 3 else (None, None, None)
    if (rows, width) != (N, P):
        shape = H.sizes if isinstance(H, KroneckerJacobian) else tuple(H.shape)
        raise ValueError(f"H must be [N, m, P] = [{N}, m, {P}] for θ [{N}, {P}]; got {shape}")
    if tuple(e.shape) != (N, m):
        raise ValueError(f"e must be the residual [N, m] = [{N}, {m}] (one row per run); got "
                         f"{tuple(e.shape)}")  # fmt: skip


def _stamp(*tensors: Tensor) -> tuple | None:
    """``((id, version), …)`` of ``tensors`` (``None`` for inference tensors: no version).
    The tensor objects, not their memory: a fork's copy may take the memory of a buffer
    freed since, and keying on the memory refused the LFC's forked loops. A detached
    state (new objects over the same buffers) is not seen: copy before resuming twice."""
    if any(t.is_inference() for t in tensors):
        return None
    return tuple((id(t), t._version) for t in tensors)


def _check_unconsumed(cov: DeferredCovariance) -> None:
    """``ValueError`` where a step has already written, in place, the buffers of the
    donated ``cov`` (a copy of it has other tensors and passes)."""
    if cov.stamp is None:
        return
    for t, (ident, version) in zip((cov.base, cov.pending), cov.stamp):
        if id(t) == ident and t._version != version:
            raise ValueError(
                "this learner state was consumed: EKFRule(donate=True) writes its covariance "
                "buffers in place, and a step has already run from this state (a second loop "
                "resumed from one LoopState had run from elsewhere, silently: a trial); resume "
                "each from a copy made before the first (LoopState.copy())"
            )


def _takes_received(step) -> bool:
    """Whether the callable ``step`` takes a ``received`` keyword (or any keyword)."""
    try:
        params = inspect.signature(step).parameters.values()
    except (TypeError, ValueError):  # (a builtin without a signature: assume it does not)
        return False
    return any(p.name == "received" or p.kind is p.VAR_KEYWORD for p in params)


def _received(received: Tensor, e: Tensor) -> Tensor:
    """``received`` ``[N, m]`` (bool), checked against ``e``'s shape."""
    if received.shape != e.shape:
        raise ValueError(f"received must have the residual's shape {tuple(e.shape)}; got "
                         f"{tuple(received.shape)}")  # fmt: skip
    if received.dtype != torch.bool:
        raise ValueError(
            f"received must be a bool tensor (True: the entry arrived); got {received.dtype}"
        )
    return received


def _unreceived_zeroed(t: Tensor, received: Tensor) -> Tensor:
    """``t`` ``[N, m]`` or ``[N, m, P]`` with the entries (rows) not ``received [N, m]`` 0:
    selected, not multiplied, so that a NaN there is never read (NaN · 0 is NaN)."""
    keep = received if t.dim() == received.dim() else received[..., None]
    return torch.where(keep, t, torch.zeros((), dtype=t.dtype, device=t.device))


def _informed_energy(e: Tensor, received: Tensor) -> tuple[Tensor, Tensor]:
    """``((m / m_r) ‖e_r‖² [N], informed [N])`` of residuals ``e [N, m]`` zeroed where not
    ``received``: each one's energy at its received entries' rate (Υ's sample), and whether
    it received any (``m_r > 0``)."""
    count = received.sum(-1).to(e.dtype)
    return (e * e).sum(-1) * (e.shape[-1] / count.clamp_min(1.0)), count > 0


# The bases EKFRule.init made, ρ(0) = c·I, which reads the same in any order: by id, with a
# weak reference and the version they had then (a base written since is no longer known).
_SCALAR_BASES: dict[int, tuple[weakref.ref, int]] = {}


def _note_scalar(base: Tensor) -> None:
    if base.is_inference():  # (no version counter: such a base is permuted, not relabelled)
        return
    key = id(base)
    forget = lambda _ref, key=key: _SCALAR_BASES.pop(key, None)  # noqa: E731
    _SCALAR_BASES[key] = (weakref.ref(base, forget), base._version)


def _known_scalar(base: Tensor) -> bool:
    entry = _SCALAR_BASES.get(id(base))
    return (
        entry is not None
        and entry[0]() is base
        and not base.is_inference()
        and base._version == entry[1]
    )


def _in_order(cov: DeferredCovariance, order: Tensor | None) -> DeferredCovariance:
    """``cov`` of a learner's first step in the Jacobian's ``order`` (``None``: θ's). The
    ``c·I`` of :meth:`EKFRule.init` is relabelled; any other base and pending rows (a
    ``DeferredCovariance`` built by hand, documented in θ's order) are permuted: relabelled,
    a diagonal prior of other variances for ``W`` and ``V`` was read in the Kronecker order
    (the first weights 0.14 off one step of eqs 11–12 by hand: a trial)."""
    if cov.count == 0 and _known_scalar(cov.base):
        return cov._replace(order=order)
    P = cov.base.shape[-1]
    idx = torch.arange(P, device=cov.base.device) if order is None else order.to(cov.base.device)
    if cov.order is not None:  # (θ index i sits at argsort(cov.order)[i] in cov's order)
        idx = torch.argsort(cov.order.to(cov.base.device))[idx]
    base = cov.base[:, idx][:, :, idx]
    pending = cov.pending[:, : cov.count][:, :, idx]
    return DeferredCovariance(base, pending, cov.count, cov.shift, order, None)


def _same_order(a: Tensor | None, b: Tensor | None) -> bool:
    if a is None or b is None:
        return a is b
    return a is b or (a.shape == b.shape and bool(torch.equal(a.to(b.device), b)))


class GradientRule:
    """The plain gradient rule of the paper's "traditional" baseline: ``ζ_k = ζ_{k−1} +
    lr · H_kᵀ e_k`` (a gradient step on ``½‖e_k‖²``), ``lr`` [DEF] 0.01."""

    def __init__(self, *, lr: float = 0.01):
        self.lr = lr

    def __setattr__(self, name, value):  # (checked whenever set, as EKFRule's)
        if name == "lr":
            value = check_finite_number(value, name, positive=True)
        super().__setattr__(name, value)

    def init(self, theta: Tensor) -> LearnerState:
        return LearnerState(theta, None, None, 0)

    def step(self, state: LearnerState, H: Tensor | KroneckerJacobian, e: Tensor,
             received: Tensor | None = None) -> LearnerState:  # fmt: skip
        """``received [N, m]`` (bool; ``None``: all): an entry not received adds nothing."""
        _check_step_shapes(state, H, e)
        with torch.no_grad():
            if isinstance(H, KroneckerJacobian):
                H = H.dense()
            if received is not None:
                e = _unreceived_zeroed(e, _received(received, e))
            step = (e.unsqueeze(-2) @ H).squeeze(-2)  # Hᵀe as eᵀH: no transposed operand
            return LearnerState(state.theta + self.lr * step, None, None, state.k + 1)


class _Learner:
    """A rule with its state, for ``batch_shape`` independent learners (the direct-use API)."""

    def __init__(self, module: nn.Module, batch_shape, params, rule):
        self.template = WeightTemplate(module)
        self.module = module
        self.batch_shape = torch.Size(
            (batch_shape,) if isinstance(batch_shape, int) else tuple(batch_shape)
        )
        if len(self.batch_shape) == 0 or any(s < 1 for s in self.batch_shape):
            raise ValueError(f"batch_shape must be non-empty positive sizes; got {batch_shape!r}")
        self.rule = rule
        theta = self.template.flatten({} if params is None else dict(params), self.batch_shape)
        self.state = rule.init(theta)
        self.dtype = theta.dtype

    theta = property(lambda self: self.state.theta)
    rho = property(lambda self: EKFRule.covariance(self.state))
    upsilon = property(lambda self: self.state.upsilon)
    k = property(lambda self: self.state.k)

    @property
    def num_params(self) -> int:
        return self.template.num_params

    def unflatten(self, theta: Tensor) -> dict[str, Tensor]:
        return self.template.unflatten(theta)

    def params(self) -> dict[str, Tensor]:
        """Current parameters ``{name: [*batch, *shape]}`` (views of the flat vector)."""
        return self.unflatten(self.theta.reshape(self.batch_shape + (-1,)))

    def _flat_inputs(self, inputs: Tensor) -> Tensor:
        nb = len(self.batch_shape)
        if tuple(inputs.shape[:nb]) != tuple(self.batch_shape):
            raise ValueError(
                f"inputs must have shape [{', '.join(map(str, self.batch_shape))}, ...]; "
                f"got {tuple(inputs.shape)}"
            )
        if self.template.factored and tuple(inputs.shape[nb:]) != self.template.shapes["V"][1:]:
            # (the tanh layer's closed forms broadcast x / in_scale: a width-1 input had been
            # learned from as n equal features; another width failed inside torch)
            raise ValueError(
                f"inputs must have shape [{', '.join(map(str, self.batch_shape))}, "
                f"{self.template.shapes['V'][1]}] (the network's input width); got "
                f"{tuple(inputs.shape)}"
            )
        return inputs.reshape((self.batch_shape.numel(),) + inputs.shape[nb:]).to(self.dtype)

    def predict(self, inputs: Tensor) -> Tensor:
        """``f(ζ, x)`` for every run: ``inputs [*batch, ...]`` → ``[*batch, m]``."""
        out = self.template.forward(self.theta, self._flat_inputs(inputs))
        return out.reshape(self.batch_shape + out.shape[1:])

    def jacobian(self, inputs: Tensor, *, autodiff: bool = False) -> tuple[Tensor, Tensor]:
        """``(f [N, m], H = ∂f/∂ζ [N, m, P])`` at the current weights, runs flattened."""
        x = self._flat_inputs(inputs)
        return self.template.jacobian(self.theta, x, autodiff=autodiff, factored=False)

    def step(
        self, inputs: Tensor, targets: Tensor, received: Tensor | None = None
    ) -> ParamStepOutput:
        """One update from ``inputs [*batch, ...]`` and ``targets [*batch, m]`` (``received
        [*batch, m]``, bool: the targets that arrived, as in :meth:`EKFRule.step`)."""
        pred, H = self.template.jacobian(self.theta, self._flat_inputs(inputs))
        m = pred.shape[-1]
        want = self.batch_shape + (m,)
        if tuple(targets.shape) != tuple(want):
            raise ValueError(f"targets must have shape {tuple(want)}; got {tuple(targets.shape)}")
        e = targets.reshape(-1, m).to(self.dtype) - pred
        if received is not None:
            if tuple(received.shape) != tuple(want):
                raise ValueError(
                    f"received must have shape {tuple(want)}; got {tuple(received.shape)}"
                )
            received = received.reshape(-1, m)
        self.state = self.rule.step(self.state, H, e, received)
        return ParamStepOutput(pred.reshape(want), e.reshape(want))


def _rule_setting(name: str) -> property:
    """A learner's ``name``: its rule's (checked when set, read at the next step). A plain
    attribute had been set beside the rule and never read (``ekf.lr = 0.1`` learned at
    the constructor's lr, ``nan`` accepted: a trial of settings assigned later)."""
    return property(
        lambda self: getattr(self.rule, name),
        lambda self, value: setattr(self.rule, name, value),
        doc=f"The rule's ``{name}`` (checked when set; the next step reads it).",
    )


def _initial_setting(name: str) -> property:
    """A setting read once, by the constructor, to make the state (``ρ(0)``, ``Υ(0)``):
    assigning it later is refused, as it would change nothing."""

    def refuse(self, value):
        raise AttributeError(
            f"{name} makes the initial state, built by the constructor: it cannot be assigned "
            f"later (build a new {type(self).__name__}, or set .state)"
        )

    return property(lambda self: getattr(self.rule, name), refuse)


class ParamEKF(_Learner):
    """EKF over the weights of ``module``, one filter per run (eqs 10–14; see module doc).

    Args:
        module: template network; its parameters' shapes define ``ζ`` (all of them are
            trained; pass a module holding only the trainable ones).
        batch_shape: independent filters, e.g. ``(B,)`` runs or ``(B, J)`` runs × areas.
        params: initial weights ``{name: [*batch, *shape]}`` (broadcast; default: the
            template's own weights for every run).
        lr, init_cov, init_noise, process_noise: as in :class:`EKFRule`. ``lr``,
            ``process_noise`` and ``fold_every`` may be assigned later (the rule's, checked;
            the next step reads them); ``init_cov`` and ``init_noise``, which make the
            initial state, may not.

    State (:attr:`state`, a :class:`LearnerState`): ``theta [N, P]``, the covariances
    (:attr:`rho` ``[N, P, P]``), ``upsilon [N]``, step counter ``k``.
    """

    def __init__(self, module, batch_shape, *, params=None, lr=1.0, init_cov=10.0,
                 init_noise=1e-3, process_noise=0.0):  # fmt: skip
        rule = EKFRule(lr=lr, init_cov=init_cov, init_noise=init_noise,
                       process_noise=process_noise, donate=True)  # fmt: skip
        super().__init__(module, batch_shape, params, rule)

    lr = _rule_setting("lr")
    process_noise = _rule_setting("process_noise")
    fold_every = _rule_setting("fold_every")
    init_cov = _initial_setting("init_cov")
    init_noise = _initial_setting("init_noise")

    def gain_norm(self) -> Tensor:
        """``tr ρ / P`` per filter ``[*batch]``: how much the filter is still willing to adapt."""
        tr = self.rho.diagonal(dim1=-2, dim2=-1).mean(-1)
        return tr.reshape(self.batch_shape)


class OnlineGradientDescent(_Learner):
    """Plain online gradient steps ``ζ_k = ζ_{k−1} + lr·H_kᵀ e_k`` (the paper's baseline).

    Same arguments and interface as :class:`ParamEKF` (without the covariances); ``lr``
    [DEF] 0.01.
    """

    def __init__(self, module, batch_shape, *, params=None, lr: float = 0.01):
        super().__init__(module, batch_shape, params, GradientRule(lr=lr))

    lr = _rule_setting("lr")


class EKFOptimizer(torch.optim.Optimizer):
    """The EKF over weights (eqs 10–14) as an optimizer of one shared parameter vector.

    ``step(jacobian, residual)`` takes ``S`` samples of an ``m``-vector output at the current
    weights: ``jacobian [S, m, P]`` (``∂f(ζ, x_s)/∂ζ``, the parameters flattened row-major
    in the order given) and ``residual [S, m]`` (``target_s − f(ζ, x_s)``). It stacks them
    into one measurement and applies eqs (11)–(14) with ``Υ_k = Υ_{k−1} + (mean_s ‖e_s‖² −
    Υ_{k−1}) / k``. ``received [S, m]`` (bool; ``None``: all): the entries whose target
    arrived; the others carry no information (their rows of the Jacobian and the residual
    are zeroed), and ``Υ`` is then the running mean, over the steps that received
    anything, of ``mean_s (m / m_s) ‖e_s‖²`` over the samples that did (``m_s`` entries
    received): an unreceived sample's zero residual had counted as a perfect prediction and
    shrunk ``Υ`` (a trial: 0.389 → 0.039 with 9 such samples beside 1).

    Args:
        params: the tensors ``ζ`` (e.g. ``[W, V]``; one parameter group).
        lr, init_cov, init_noise, process_noise: as in :class:`EKFRule`.

    State (``state_dict``): ``rho [P, P]``, ``upsilon``, ``k``, ``started_from`` (the
    ``init_cov`` and ``init_noise`` of the first step: written into the group later, they are
    refused) and, once a step was given ``received``, ``seen`` (the steps that informed
    ``Υ``). Cost per step
    ``O(P²·S·m + (S·m)³)``.
    """

    def __init__(self, params, *, lr=1.0, init_cov=10.0, init_noise=1e-3, process_noise=0.0):
        EKFRule(lr=lr, init_cov=init_cov, init_noise=init_noise, process_noise=process_noise)
        defaults = dict(
            lr=lr, init_cov=init_cov, init_noise=init_noise, process_noise=process_noise
        )
        super().__init__(params, defaults)
        if len(self.param_groups) != 1:
            raise ValueError("EKFOptimizer takes one parameter group (one vector ζ)")

    def add_param_group(self, param_group: dict) -> None:
        """The one group (the constructor's); another is refused: :meth:`step` updates one
        vector ζ (a group added later had been kept and never trained, its weights fixed)."""
        if self.param_groups:
            raise ValueError(
                "EKFOptimizer takes one parameter group (one vector ζ); another cannot be "
                "added: pass every tensor to train in the constructor's params"
            )
        super().add_param_group(param_group)

    @torch.no_grad()
    def step(self, jacobian: Tensor, residual: Tensor, closure=None,  # type: ignore[override]
             received: Tensor | None = None) -> Tensor:  # fmt: skip
        """One update; returns ``‖e_s‖²`` per sample ``[S]`` before it (of the received
        entries). ``closure`` (what Lightning's optimizer wrapper passes; it runs its hooks)
        is called first."""
        if closure is not None:
            closure()
        group = self.param_groups[0]
        params = group["params"]
        P = sum(p.numel() for p in params)
        if jacobian.dim() != 3 or jacobian.shape[-1] != P or residual.shape != jacobian.shape[:2]:
            raise ValueError(
                f"jacobian must be [S, m, {P}] and residual [S, m]; got "
                f"{tuple(jacobian.shape)} and {tuple(residual.shape)}"
            )
        # the group's settings, checked at every step: LR schedulers and Lightning write
        # them (a NaN lr had made every weight NaN; a negative Q_ρ ran as 0)
        settings = {
            key: check_finite_number(
                group[key], f"param_groups[0][{key!r}]",
                positive=key != "process_noise", nonnegative=key == "process_noise",
            )
            for key in ("lr", "init_cov", "init_noise", "process_noise")
        }  # fmt: skip
        state = self.state[params[0]]
        if not state:
            dtype, device = params[0].dtype, params[0].device
            state["rho"] = settings["init_cov"] * torch.eye(P, dtype=dtype, device=device)
            state["upsilon"] = torch.tensor(settings["init_noise"], dtype=dtype, device=device)
            state["k"] = 0
            state["started_from"] = {key: settings[key] for key in ("init_cov", "init_noise")}
        _check_started_from(state, settings)
        e = residual.to(params[0].dtype)
        H = jacobian.to(e.dtype)
        if received is not None:
            r = _received(received, e)
            e, H = _unreceived_zeroed(e, r), _unreceived_zeroed(H, r)
        for value, name in ((e, "residual"), (H, "jacobian")):
            if not bool(torch.isfinite(value).all()):  # (of the received entries)
                raise ValueError(f"{name} must be finite where received; it holds NaN or inf")
        per_sample = e.square().sum(-1)
        # the step's k, Υ and seen are kept only once the update succeeds: a step refused
        # (a NaN residual or Jacobian) had advanced them, and every later step was refused
        # or ran from a NaN Υ (an EKF-over-weights trial)
        k, upsilon, seen = state["k"] + 1, state["upsilon"], state.get("seen")
        if received is None and seen is None:  # every entry of every step so far
            upsilon = upsilon + (per_sample.mean() - upsilon) / k
        else:
            everything = torch.ones_like(e, dtype=torch.bool)
            energy, informed = _informed_energy(e, everything if received is None else r)
            seen = k - 1 if seen is None else seen
            if bool(informed.any()):
                seen += 1
                upsilon = upsilon + (energy[informed].mean() - upsilon) / seen
        H = H.reshape(1, -1, P)
        update, rho = ekf_weight_update(  # (ρ is written only after S factorised)
            state["rho"].unsqueeze(0), H, e.reshape(1, -1), upsilon.reshape(1),
            settings["process_noise"], k, donate=True,
        )  # fmt: skip
        update = update[0] * settings["lr"]
        state["rho"], state["upsilon"], state["k"] = rho[0], upsilon, k
        if seen is not None:
            state["seen"] = seen
        i = 0
        for p in params:
            p.add_(update[i : i + p.numel()].reshape(p.shape))
            i += p.numel()
        return per_sample


def _check_started_from(state: dict, settings: dict) -> None:
    """``init_cov`` and ``init_noise`` are ``ρ(0)`` and ``Υ(0)``: read at the first step, a
    value written into the group since had been kept there and never used (as
    :class:`ParamEKF` refuses the same assignment). A state of an older version, which did
    not record them, is not checked."""
    for key, used in state.get("started_from", {}).items():
        if settings[key] != used:
            raise ValueError(
                f"param_groups[0][{key!r}] = {settings[key]:g} but this optimizer started from "
                f"{used:g}: it is the state's initial value, read at the first step only; to "
                "start again from it, clear the state (optimizer.state.clear())"
            )


def ekf_along_sequence(step, predict, inputs: Tensor, targets: Tensor,
                       received: Tensor) -> Tensor:  # fmt: skip
    """The EKF over the weights along a sequence of ``S`` samples (the LFC paper's
    Algorithm 1, one measurement per time step): at each step ``t`` one update
    ``step(jacobian=J ⊙ r, residual=(target − out) ⊙ r, received=r)`` (an
    :meth:`EKFOptimizer.step`, or Lightning's wrapper of it, which passes ``received`` on;
    a ``step`` that takes no ``received`` is called without it) from ``predict(inputs[:,
    t]) → (out [S, m], J [S, m, P])``, evaluated at the weights the previous update left,
    and ``r = received[:, t]`` (unreceived entries carry no information, in the update and,
    given ``received``, in ``Υ``; their values are never read, a NaN included).

    Shapes: ``inputs [S, T, in]``, ``targets`` and ``received`` (bool) ``[S, T, m]`` →
    ``‖e_s‖²`` before each update, ``[T, S]``. The recursion is the time loop: each update
    reads the weights of the one before.
    """
    takes = _takes_received(step)
    sq_err = []
    for t in range(inputs.shape[-2]):
        out, jacobian = predict(inputs[:, t])
        keep = received[:, t].bool()
        residual = _unreceived_zeroed(targets[:, t].to(out.dtype) - out, keep)
        jacobian = _unreceived_zeroed(jacobian, keep)
        extra = {"received": keep} if takes else {}  # (Υ of the received entries alone)
        sq_err.append(step(jacobian=jacobian, residual=residual, **extra))
    return torch.stack(sq_err)
