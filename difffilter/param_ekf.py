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
``k``) lives in the optimizer's ``state_dict``, so a Lightning checkpoint resumes it.

Both hold one independent parameter vector per run: parameters ``[*batch, *shape]``,
inputs ``[*batch, ...]``, outputs ``[*batch, m]``. Jacobians come from ``torch.func``
(``vmap`` of ``jacrev`` of ``functional_call``), so any module whose forward maps one
input to a vector works. A module may instead provide closed forms,
``batched_forward(params, x)`` → ``[N, m]`` and ``batched_jacobian(params, x)`` →
``([N, m], [N, m, P])`` with ``params = {name: [N, *shape]}``, ``x [N, ...]`` and the
parameters flattened row-major in registration order; they are used when present.
Nothing here is differentiable through the updates: the rules run under
``torch.no_grad``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn
from torch.func import functional_call, jacrev, vmap

__all__ = ["ParamEKF", "OnlineGradientDescent", "EKFOptimizer", "ParamStepOutput"]


class ParamStepOutput(NamedTuple):
    """What a learning step saw: the prediction with the old weights and its residual.

    ``prediction [*batch, m]`` is ``f(ζ_{k−1}, x_k)``; ``residual [*batch, m]`` is
    ``target_k − prediction``.
    """

    prediction: Tensor
    residual: Tensor


class _BatchedParams:
    """Flattened per-run parameter vectors ``θ [N, P]`` of a template module."""

    def __init__(self, module: nn.Module, batch_shape, params: dict[str, Tensor] | None):
        if not isinstance(module, nn.Module):
            raise ValueError(f"module must be an nn.Module; got {type(module).__name__}")
        self.module = module
        self.batch_shape = torch.Size(
            (batch_shape,) if isinstance(batch_shape, int) else tuple(batch_shape)
        )
        if len(self.batch_shape) == 0 or any(s < 1 for s in self.batch_shape):
            raise ValueError(f"batch_shape must be non-empty positive sizes; got {batch_shape!r}")
        base = dict(module.named_parameters())
        if not base:
            raise ValueError("module has no parameters to train")
        params = {} if params is None else dict(params)
        unknown = set(params) - set(base)
        if unknown:
            raise ValueError(f"params has names the module does not: {sorted(unknown)}")
        self.names = list(base)
        self.shapes = {n: base[n].shape for n in self.names}
        flat = []
        for n in self.names:
            value = params.get(n, base[n]).detach()
            want = self.batch_shape + self.shapes[n]
            try:
                value = value.expand(want)
            except RuntimeError as exc:
                raise ValueError(
                    f"params[{n!r}] must broadcast to {tuple(want)}; got {tuple(value.shape)}"
                ) from exc
            flat.append(value.reshape(self.batch_shape.numel(), -1))
        self.theta = torch.cat(flat, dim=1).clone()  # [N, P]
        self.dtype = self.theta.dtype
        # Buffers (non-trainable state) travel with the template, unbatched.
        self.buffers = dict(module.named_buffers())

    @property
    def num_params(self) -> int:
        return self.theta.shape[1]

    def unflatten(self, theta: Tensor) -> dict[str, Tensor]:
        """``θ [..., P]`` → ``{name: [..., *shape]}``."""
        out, i = {}, 0
        for n in self.names:
            size = self.shapes[n].numel()
            out[n] = theta[..., i : i + size].reshape(theta.shape[:-1] + self.shapes[n])
            i += size
        return out

    def params(self) -> dict[str, Tensor]:
        """Current parameters ``{name: [*batch, *shape]}`` (views of the flat vector)."""
        return self.unflatten(self.theta.reshape(self.batch_shape + (-1,)))

    def _single(self, theta: Tensor, x: Tensor) -> Tensor:
        out = functional_call(self.module, {**self.unflatten(theta), **self.buffers}, (x,))
        if out.dim() != 1:
            raise ValueError(
                f"the module must map one input to a vector [m]; got {tuple(out.shape)}"
            )
        return out

    def _flat_inputs(self, inputs: Tensor) -> Tensor:
        nb = len(self.batch_shape)
        if tuple(inputs.shape[:nb]) != tuple(self.batch_shape):
            raise ValueError(
                f"inputs must have shape [{', '.join(map(str, self.batch_shape))}, ...]; "
                f"got {tuple(inputs.shape)}"
            )
        return inputs.reshape((self.batch_shape.numel(),) + inputs.shape[nb:]).to(self.dtype)

    def predict(self, inputs: Tensor) -> Tensor:
        """``f(ζ, x)`` for every run: ``inputs [*batch, ...]`` → ``[*batch, m]``."""
        x = self._flat_inputs(inputs)
        with torch.no_grad():
            if hasattr(self.module, "batched_forward"):
                out = self.module.batched_forward(self.unflatten(self.theta), x)
            else:
                out = vmap(self._single)(self.theta, x)
        return out.reshape(self.batch_shape + out.shape[1:])

    def jacobian(self, inputs: Tensor, *, autodiff: bool = False) -> tuple[Tensor, Tensor]:
        """``(f [N, m], H = ∂f/∂ζ [N, m, P])`` at the current weights, runs flattened.

        ``autodiff=True`` ignores a module's closed form (used to test it).
        """
        x = self._flat_inputs(inputs)
        with torch.no_grad():
            if hasattr(self.module, "batched_jacobian") and not autodiff:
                return self.module.batched_jacobian(self.unflatten(self.theta), x)

            def with_aux(theta, xi):
                out = self._single(theta, xi)
                return out, out

            H, out = vmap(jacrev(with_aux, has_aux=True))(self.theta, x)
        return out, H

    def _targets(self, targets: Tensor, m: int) -> Tensor:
        want = self.batch_shape + (m,)
        if tuple(targets.shape) != tuple(want):
            raise ValueError(f"targets must have shape {tuple(want)}; got {tuple(targets.shape)}")
        return targets.reshape(-1, m).to(self.dtype)


def _ekf_gain_step(rho: Tensor, H: Tensor, e: Tensor, upsilon: Tensor, q: float, k: int) -> Tensor:
    """Eqs (12) and (14) for ``N`` filters: returns ``λ_k e_k [N, P]`` and updates ``ρ [N, P, P]``
    in place (``H [N, m, P]``, ``e [N, m]``, ``Υ [N]``, ``Q_ρ = q``, ``k`` the step count)."""
    rho_Ht = rho @ H.transpose(-1, -2)  # ρHᵀ [N, P, m]
    eye_m = torch.eye(H.shape[-2], dtype=H.dtype, device=H.device)
    S = H @ rho_Ht + upsilon[:, None, None] * eye_m
    gain = torch.linalg.solve(S, rho_Ht.transpose(-1, -2)).transpose(-1, -2)  # λ [N, P, m]
    # ρ ← ρ − λ(Hρ) with Hρ = (ρHᵀ)ᵀ (ρ is symmetric), in place: ρ is the big [N, P, P]
    # array, and this step is bound by passes over its memory.
    rho.baddbmm_(gain, rho_Ht.transpose(-1, -2), alpha=-1.0)
    if q > 0:
        rho.diagonal(dim1=-2, dim2=-1).add_(q)
    if k % 16 == 0:  # round-off slowly breaks the symmetry; restore it now and then
        rho.copy_(0.5 * (rho + rho.transpose(-1, -2)))
    return (gain @ e.unsqueeze(-1)).squeeze(-1)


class ParamEKF(_BatchedParams):
    """EKF over the weights of ``module``, one filter per run (eqs 10–14; see module doc).

    Args:
        module: template network; its parameters' shapes define ``ζ`` (all of them are
            trained; pass a module holding only the trainable ones).
        batch_shape: independent filters, e.g. ``(B,)`` runs or ``(B, J)`` runs × areas.
        params: initial weights ``{name: [*batch, *shape]}`` (broadcast; default: the
            template's own weights for every run).
        lr: ``η`` of eq. (11) (the paper: a constant learning rate; [DEF] 1).
        init_cov: ``ρ(0) = init_cov·I`` ([DEF] 10).
        init_noise: ``Υ(0)`` (scalar; [DEF] tr Θ).
        process_noise: ``Q_ρ``, added to ``ρ`` after every update (0 = the paper).

    State: ``theta [N, P]``, ``rho [N, P, P]``, ``upsilon [N]``, step counter ``k``.
    Cost per step: ``O(N·P²·m)`` time and ``O(N·P²)`` memory.
    """

    def __init__(
        self,
        module: nn.Module,
        batch_shape,
        *,
        params: dict[str, Tensor] | None = None,
        lr: float = 1.0,
        init_cov: float = 10.0,
        init_noise: float = 1e-3,
        process_noise: float = 0.0,
    ):
        super().__init__(module, batch_shape, params)
        for name, val in (("lr", lr), ("init_cov", init_cov), ("init_noise", init_noise)):
            if not val > 0:
                raise ValueError(f"{name} must be positive; got {val!r}")
        if not process_noise >= 0:
            raise ValueError(f"process_noise must be >= 0; got {process_noise!r}")
        self.lr, self.process_noise = float(lr), float(process_noise)
        N, P = self.theta.shape
        eye = torch.eye(P, dtype=self.dtype)
        self.rho = (init_cov * eye).expand(N, P, P).clone()
        self.upsilon = torch.full((N,), float(init_noise), dtype=self.dtype)
        self.k = 0

    def step(self, inputs: Tensor, targets: Tensor) -> ParamStepOutput:
        """One update (eqs 11–14) from ``inputs [*batch, ...]`` and ``targets [*batch, m]``."""
        with torch.no_grad():
            pred, H = self.jacobian(inputs)  # [N, m], [N, m, P]
            m = pred.shape[-1]
            e = self._targets(targets, m) - pred
            self.k += 1
            self.upsilon = self.upsilon + ((e * e).sum(-1) - self.upsilon) / self.k
            self.theta = self.theta + self.lr * _ekf_gain_step(
                self.rho, H, e, self.upsilon, self.process_noise, self.k
            )
        shape = self.batch_shape + (m,)
        return ParamStepOutput(pred.reshape(shape), e.reshape(shape))

    def gain_norm(self) -> Tensor:
        """``tr ρ / P`` per filter ``[*batch]``: how much the filter is still willing to adapt."""
        tr = self.rho.diagonal(dim1=-2, dim2=-1).mean(-1)
        return tr.reshape(self.batch_shape)


class OnlineGradientDescent(_BatchedParams):
    """Plain online gradient steps ``ζ_k = ζ_{k−1} + lr·H_kᵀ e_k`` (the paper's baseline).

    Same arguments and interface as :class:`ParamEKF` (without the covariances); ``lr``
    [DEF] 0.01.
    """

    def __init__(self, module, batch_shape, *, params=None, lr: float = 0.01):
        super().__init__(module, batch_shape, params)
        if not lr > 0:
            raise ValueError(f"lr must be positive; got {lr!r}")
        self.lr = float(lr)
        self.k = 0

    def step(self, inputs: Tensor, targets: Tensor) -> ParamStepOutput:
        with torch.no_grad():
            pred, H = self.jacobian(inputs)
            m = pred.shape[-1]
            e = self._targets(targets, m) - pred
            self.k += 1
            self.theta = self.theta + self.lr * (H.transpose(-1, -2) @ e.unsqueeze(-1)).squeeze(-1)
        shape = self.batch_shape + (m,)
        return ParamStepOutput(pred.reshape(shape), e.reshape(shape))


class EKFOptimizer(torch.optim.Optimizer):
    """The EKF over weights (eqs 10–14) as an optimizer of one shared parameter vector.

    ``step(jacobian, residual)`` takes ``S`` samples of an ``m``-vector output at the current
    weights: ``jacobian [S, m, P]`` (``∂f(ζ, x_s)/∂ζ``, the parameters flattened row-major
    in the order given) and ``residual [S, m]`` (``target_s − f(ζ, x_s)``; zero rows carry
    no information, e.g. unreceived entries). It stacks them into one measurement and
    applies eqs (11)–(14) with ``Υ_k = Υ_{k−1} + (mean_s ‖e_s‖² − Υ_{k−1}) / k``.

    Args:
        params: the tensors ``ζ`` (e.g. ``[W, V]``; one parameter group).
        lr, init_cov, init_noise, process_noise: as in :class:`ParamEKF`.

    State (``state_dict``): ``rho [P, P]``, ``upsilon``, ``k``. Cost per step
    ``O(P²·S·m + (S·m)³)``.
    """

    def __init__(self, params, *, lr=1.0, init_cov=10.0, init_noise=1e-3, process_noise=0.0):
        for name, val in (("lr", lr), ("init_cov", init_cov), ("init_noise", init_noise)):
            if not val > 0:
                raise ValueError(f"{name} must be positive; got {val!r}")
        if not process_noise >= 0:
            raise ValueError(f"process_noise must be >= 0; got {process_noise!r}")
        defaults = dict(
            lr=lr, init_cov=init_cov, init_noise=init_noise, process_noise=process_noise
        )
        super().__init__(params, defaults)
        if len(self.param_groups) != 1:
            raise ValueError("EKFOptimizer takes one parameter group (one vector ζ)")

    @torch.no_grad()
    def step(self, jacobian: Tensor, residual: Tensor, closure=None) -> Tensor:  # type: ignore[override]
        """One update; returns ``‖e_s‖²`` per sample ``[S]`` before it. ``closure`` (what
        Lightning's optimizer wrapper passes; it runs its hooks) is called first."""
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
        state = self.state[params[0]]
        if not state:
            dtype, device = params[0].dtype, params[0].device
            state["rho"] = group["init_cov"] * torch.eye(P, dtype=dtype, device=device)
            state["upsilon"] = torch.tensor(float(group["init_noise"]), dtype=dtype, device=device)
            state["k"] = 0
        e = residual.to(params[0].dtype)
        per_sample = e.square().sum(-1)
        state["k"] += 1
        state["upsilon"] += (per_sample.mean() - state["upsilon"]) / state["k"]
        H = jacobian.to(e.dtype).reshape(1, -1, P)
        update = _ekf_gain_step(
            state["rho"].unsqueeze(0), H, e.reshape(1, -1), state["upsilon"].reshape(1),
            group["process_noise"], state["k"],
        )[0] * group["lr"]  # fmt: skip
        i = 0
        for p in params:
            p.add_(update[i : i + p.numel()].reshape(p.shape))
            i += p.numel()
        return per_sample
