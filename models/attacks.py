"""False-data-injection attack generators (measurement channel).

Bias injection attack of the modified-PF paper (Sadeghzadeh-Nokhodberiz et al., IEEE
Access 2022, eqs 3–4)::

    ỹ_k     = y_k + l_k γ_k,                 l_k ~ Bernoulli(p_l) i.i.d.     (3)
    γ_{k+1} = τ γ_k + (1 − τ) γ̄,             γ_0 = 0, 0 < τ < 1              (4)

so ``γ_k = (1 − τ^k) γ̄`` converges slowly to the bias ``γ̄`` (a stealthy, low-pass
attack). The attack value evolves at every step whether or not it is injected; the
Bernoulli flag only decides whether the packet of step ``k`` carries it.

Time convention (as everywhere in difffilter, :mod:`difffilter.ssm`): a measurement
sequence ``ys [..., T, dy]`` holds ``y_1 … y_T``, so ``gammas[..., t, :] = γ_{t+1}`` and
``flags[..., t] = l_{t+1}``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

__all__ = ["BiasAttack", "AttackRealisation"]


class AttackRealisation(NamedTuple):
    """One realisation of an attack on a measurement sequence.

    Attributes:
        y_recv: received measurements ``ỹ = y + l γ`` ``[..., T, dy]``.
        flags: attack indicators ``l_k`` ``[..., T]`` (bool).
        gammas: attack values ``γ_k`` ``[..., T, dy]`` (injected only where ``flags``).
    """

    y_recv: Tensor
    flags: Tensor
    gammas: Tensor


@dataclass(frozen=True)
class BiasAttack:
    """The bias FDI attack of eqs (3)–(4).

    Args:
        gamma_bar: steady-state bias ``γ̄`` (``dy`` numbers).
        tau: convergence factor ``τ ∈ (0, 1)`` of eq. (4).
        p_l: probability ``p_l ∈ [0, 1]`` that a packet is attacked (eq. 3).
    """

    gamma_bar: tuple[float, ...]
    tau: float = 0.9
    p_l: float = 0.5

    def __post_init__(self):
        gb = tuple(float(g) for g in self.gamma_bar)
        if not gb or not all(math.isfinite(g) for g in gb):
            raise ValueError(
                f"gamma_bar must be a non-empty sequence of finite numbers; got {self.gamma_bar!r}"
            )
        object.__setattr__(self, "gamma_bar", gb)
        if not 0.0 < float(self.tau) < 1.0:
            raise ValueError(f"tau must lie in (0, 1) (eq. 4); got {self.tau!r}")
        if not 0.0 <= float(self.p_l) <= 1.0:
            raise ValueError(f"p_l must lie in [0, 1] (a Bernoulli probability); got {self.p_l!r}")

    @property
    def dim(self) -> int:
        """Measurement dimension ``dy``."""
        return len(self.gamma_bar)

    def values(self, num_steps: int, *, dtype=torch.float64, device=None) -> Tensor:
        """``γ_1 … γ_T`` of eq. (4) by the recursion itself, ``[T, dy]``.

        The recursion runs in float64 and is cast at the end, so it equals the closed
        form ``(1 − τ^k) γ̄`` to round-off in any dtype.
        """
        if isinstance(num_steps, bool) or not isinstance(num_steps, int) or num_steps < 1:
            raise ValueError(f"num_steps must be an integer >= 1; got {num_steps!r}")
        gamma_bar = torch.tensor(self.gamma_bar, dtype=torch.float64)
        gamma = torch.zeros_like(gamma_bar)  # γ_0 = 0
        out = []
        for _ in range(num_steps):
            gamma = self.tau * gamma + (1.0 - self.tau) * gamma_bar
            out.append(gamma)
        return torch.stack(out).to(dtype=dtype, device=device)

    def sample_flags(
        self, batch_shape, num_steps: int, generator: torch.Generator | None = None, *, device=None
    ) -> Tensor:
        """Bernoulli flags ``l_1 … l_T`` ``[*batch_shape, T]`` (bool) from ``generator``.

        ``l_k = 1`` iff ``u_k < p_l`` with ``u_k ~ U[0, 1)`` drawn in float64, so the same
        generator state gives nested attack sets for increasing ``p_l``.
        """
        if isinstance(num_steps, bool) or not isinstance(num_steps, int) or num_steps < 1:
            raise ValueError(f"num_steps must be an integer >= 1; got {num_steps!r}")
        shape = torch.Size((batch_shape,) if isinstance(batch_shape, int) else batch_shape)
        u = torch.rand(
            shape + (num_steps,), generator=generator, dtype=torch.float64, device=device
        )
        return u < self.p_l

    def apply(
        self,
        y_true: Tensor,
        generator: torch.Generator | None = None,
        *,
        flags: Tensor | None = None,
    ) -> AttackRealisation:
        """Attack ``y_true [..., T, dy]``: draw ``l_k`` (or use ``flags [..., T]``) and add ``l_k γ_k``.

        Returns an :class:`AttackRealisation` with ``gammas`` expanded to ``y_true``'s shape.
        """
        if not isinstance(y_true, Tensor) or y_true.dim() < 2 or y_true.shape[-1] != self.dim:
            shape = tuple(y_true.shape) if isinstance(y_true, Tensor) else type(y_true).__name__
            raise ValueError(f"y_true must be a tensor of shape [..., T, {self.dim}]; got {shape}")
        num_steps = y_true.shape[-2]
        if flags is None:
            flags = self.sample_flags(y_true.shape[:-2], num_steps, generator, device=y_true.device)
        elif flags.shape != y_true.shape[:-1]:
            raise ValueError(
                f"flags must have shape {tuple(y_true.shape[:-1])} (y_true without its last dim); got {tuple(flags.shape)}"
            )
        flags = flags.bool()
        gammas = self.values(num_steps, dtype=y_true.dtype, device=y_true.device).expand(
            y_true.shape
        )
        y_recv = y_true + flags.unsqueeze(-1).to(y_true.dtype) * gammas
        return AttackRealisation(y_recv, flags, gammas)
