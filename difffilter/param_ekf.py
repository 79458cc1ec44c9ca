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
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn
from torch.func import functional_call, jacrev, vmap

from .gaussian import kalman_gain

__all__ = [
    "WeightTemplate",
    "LearnerState",
    "EKFRule",
    "GradientRule",
    "ParamEKF",
    "OnlineGradientDescent",
    "EKFOptimizer",
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
    covariances ``rho [N, P, P]`` and running noise ``upsilon [N]`` (``None`` for plain
    gradient steps) and the step count ``k``."""

    theta: Tensor
    rho: Tensor | None
    upsilon: Tensor | None
    k: int


class WeightTemplate:
    """A module's parameters as flat per-run vectors ``θ [N, P]`` (row-major, registration
    order), and its output and Jacobian at them.

    ``forward(θ, x [N, ...]) → [N, m]`` and ``jacobian(θ, x) → ([N, m], [N, m, P])`` use the
    module's closed forms (``batched_forward``/``batched_jacobian``) when it has them, else
    ``torch.func`` (``vmap`` of ``jacrev`` of ``functional_call``).
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
            want = batch_shape + self.shapes[n]
            try:
                value = value.expand(want)
            except RuntimeError as exc:
                raise ValueError(
                    f"params[{n!r}] must broadcast to {tuple(want)}; got {tuple(value.shape)}"
                ) from exc
            flat.append(value.reshape(batch_shape.numel(), -1))
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

    def jacobian(self, theta: Tensor, x: Tensor, *, autodiff: bool = False):
        """``(f [N, m], H = ∂f/∂θ [N, m, P])`` (``autodiff=True`` ignores closed forms)."""
        with torch.no_grad():
            if hasattr(self.module, "batched_jacobian") and not autodiff:
                return self.module.batched_jacobian(self.unflatten(theta), x)

            def with_aux(t, xi):
                out = self._single(t, xi)
                return out, out

            H, out = vmap(jacrev(with_aux, has_aux=True))(theta, x)
        return out, H


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
        init_noise: ``Υ(0)`` (scalar; [DEF] tr Θ).
        process_noise: ``Q_ρ``, added to ``ρ`` after every update (0 = the paper).

    Cost per step: ``O(N·P²·m)`` time and ``O(N·P²)`` memory. ``donate``: :meth:`step`
    updates the state's ``ρ`` in place (:func:`ekf_weight_update`): the state given is
    consumed (copy ``rho`` first to keep it), which halves the passes over memory.
    """

    def __init__(
        self,
        *,
        lr: float = 1.0,
        init_cov: float = 10.0,
        init_noise: float = 1e-3,
        process_noise: float = 0.0,
        donate: bool = False,
    ):
        for name, val in (("lr", lr), ("init_cov", init_cov), ("init_noise", init_noise)):
            if not val > 0:
                raise ValueError(f"{name} must be positive; got {val!r}")
        if not process_noise >= 0:
            raise ValueError(f"process_noise must be >= 0; got {process_noise!r}")
        self.lr, self.init_cov = float(lr), float(init_cov)
        self.init_noise, self.process_noise = float(init_noise), float(process_noise)
        self.donate = bool(donate)

    def init(self, theta: Tensor) -> LearnerState:
        """``θ [N, P]`` with ``ρ(0) = init_cov·I``, ``Υ(0) = init_noise``."""
        N, P = theta.shape
        eye = torch.eye(P, dtype=theta.dtype, device=theta.device)
        rho = (self.init_cov * eye).expand(N, P, P).clone()
        ups = torch.full((N,), self.init_noise, dtype=theta.dtype, device=theta.device)
        return LearnerState(theta, rho, ups, 0)

    def step(self, state: LearnerState, H: Tensor, e: Tensor) -> LearnerState:
        """One update (eqs 11–14) with ``H = ∂f(ζ_{k−1}, x_k)/∂ζ [N, m, P]`` and the
        residual ``e_k [N, m]``."""
        with torch.no_grad():
            k = state.k + 1
            ups = state.upsilon + ((e * e).sum(-1) - state.upsilon) / k
            step, rho = ekf_weight_update(
                state.rho, H, e, ups, self.process_noise, k, donate=self.donate
            )
            return LearnerState(state.theta + self.lr * step, rho, ups, k)


class GradientRule:
    """The plain gradient rule of the paper's "traditional" baseline: ``ζ_k = ζ_{k−1} +
    lr · H_kᵀ e_k`` (a gradient step on ``½‖e_k‖²``), ``lr`` [DEF] 0.01."""

    def __init__(self, *, lr: float = 0.01):
        if not lr > 0:
            raise ValueError(f"lr must be positive; got {lr!r}")
        self.lr = float(lr)

    def init(self, theta: Tensor) -> LearnerState:
        return LearnerState(theta, None, None, 0)

    def step(self, state: LearnerState, H: Tensor, e: Tensor) -> LearnerState:
        with torch.no_grad():
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
    rho = property(lambda self: self.state.rho)
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
        return inputs.reshape((self.batch_shape.numel(),) + inputs.shape[nb:]).to(self.dtype)

    def predict(self, inputs: Tensor) -> Tensor:
        """``f(ζ, x)`` for every run: ``inputs [*batch, ...]`` → ``[*batch, m]``."""
        out = self.template.forward(self.theta, self._flat_inputs(inputs))
        return out.reshape(self.batch_shape + out.shape[1:])

    def jacobian(self, inputs: Tensor, *, autodiff: bool = False) -> tuple[Tensor, Tensor]:
        """``(f [N, m], H = ∂f/∂ζ [N, m, P])`` at the current weights, runs flattened."""
        return self.template.jacobian(self.theta, self._flat_inputs(inputs), autodiff=autodiff)

    def step(self, inputs: Tensor, targets: Tensor) -> ParamStepOutput:
        """One update from ``inputs [*batch, ...]`` and ``targets [*batch, m]``."""
        pred, H = self.jacobian(inputs)
        m = pred.shape[-1]
        want = self.batch_shape + (m,)
        if tuple(targets.shape) != tuple(want):
            raise ValueError(f"targets must have shape {tuple(want)}; got {tuple(targets.shape)}")
        e = targets.reshape(-1, m).to(self.dtype) - pred
        self.state = self.rule.step(self.state, H, e)
        return ParamStepOutput(pred.reshape(want), e.reshape(want))


class ParamEKF(_Learner):
    """EKF over the weights of ``module``, one filter per run (eqs 10–14; see module doc).

    Args:
        module: template network; its parameters' shapes define ``ζ`` (all of them are
            trained; pass a module holding only the trainable ones).
        batch_shape: independent filters, e.g. ``(B,)`` runs or ``(B, J)`` runs × areas.
        params: initial weights ``{name: [*batch, *shape]}`` (broadcast; default: the
            template's own weights for every run).
        lr, init_cov, init_noise, process_noise: as in :class:`EKFRule`.

    State (:attr:`state`, a :class:`LearnerState`): ``theta [N, P]``, ``rho [N, P, P]``,
    ``upsilon [N]``, step counter ``k``.
    """

    def __init__(self, module, batch_shape, *, params=None, lr=1.0, init_cov=10.0,
                 init_noise=1e-3, process_noise=0.0):  # fmt: skip
        rule = EKFRule(lr=lr, init_cov=init_cov, init_noise=init_noise,
                       process_noise=process_noise, donate=True)  # fmt: skip
        super().__init__(module, batch_shape, params, rule)

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


class EKFOptimizer(torch.optim.Optimizer):
    """The EKF over weights (eqs 10–14) as an optimizer of one shared parameter vector.

    ``step(jacobian, residual)`` takes ``S`` samples of an ``m``-vector output at the current
    weights: ``jacobian [S, m, P]`` (``∂f(ζ, x_s)/∂ζ``, the parameters flattened row-major
    in the order given) and ``residual [S, m]`` (``target_s − f(ζ, x_s)``; zero rows carry
    no information, e.g. unreceived entries). It stacks them into one measurement and
    applies eqs (11)–(14) with ``Υ_k = Υ_{k−1} + (mean_s ‖e_s‖² − Υ_{k−1}) / k``.

    Args:
        params: the tensors ``ζ`` (e.g. ``[W, V]``; one parameter group).
        lr, init_cov, init_noise, process_noise: as in :class:`EKFRule`.

    State (``state_dict``): ``rho [P, P]``, ``upsilon``, ``k``. Cost per step
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
        update, rho = ekf_weight_update(
            state["rho"].unsqueeze(0), H, e.reshape(1, -1), state["upsilon"].reshape(1),
            group["process_noise"], state["k"], donate=True,
        )  # fmt: skip
        state["rho"] = rho[0]
        update = update[0] * group["lr"]
        i = 0
        for p in params:
            p.add_(update[i : i + p.numel()].reshape(p.shape))
            i += p.numel()
        return per_sample
