"""Johansson's quadruple-tank process (the plant of the modified-PF paper, SCENARIOS.md §1).

Continuous dynamics (levels ``h`` in cm, pump voltages ``v`` in V)::

    ḣ1 = −a1/A1 √(2g h1) + a3/A1 √(2g h3) + γ1 k1/A1 v1
    ḣ2 = −a2/A2 √(2g h2) + a4/A2 √(2g h4) + γ2 k2/A2 v2
    ḣ3 = −a3/A3 √(2g h3) + (1 − γ2) k2/A3 v2
    ḣ4 = −a4/A4 √(2g h4) + (1 − γ1) k1/A4 v1

Discrete model used by the paper's filters (Euler, levels clipped at 0 inside the
square roots)::

    x_{k+1} = x_k + dt · f_c(max(x_k, 0), v) + ϖ_k,    ϖ_k ~ N(0, Q)
    y_k     = G x_k + v_k,                             v_k ~ N(0, R)

Parameters: Johansson, IEEE TCST 8(3) 2000, minimum-phase point P−; ``G = I``,
``Q = 1e-4 I`` (derived from the paper's threshold, see SCENARIOS.md); ``dt = 1 s``,
``p(x_0) = N(x*, 1e-2 I)`` are [DEF] defaults.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from difffilter.noise import Gaussian
from difffilter.ssm import StateSpaceModel

__all__ = ["FourTankParameters", "FourTankModel", "R_NOMINAL", "R_HIGH"]

#: Measurement-noise covariance of Figs 6–8 (tr R = 0.003) [P].
R_NOMINAL = (1e-3, 1e-3, 0.5e-3, 0.5e-3)
#: High-noise case of Figs 11–12 (tr R = 0.015) [P].
R_HIGH = (5e-3, 5e-3, 2.5e-3, 2.5e-3)


@dataclass(frozen=True)
class FourTankParameters:
    """Physical constants of the quadruple tank (Johansson 2000, operating point P−) [R]."""

    A: tuple[float, float, float, float] = (28.0, 32.0, 28.0, 32.0)  # cm²
    a: tuple[float, float, float, float] = (0.071, 0.057, 0.071, 0.057)  # cm²
    g: float = 981.0  # cm/s²
    k: tuple[float, float] = (3.33, 3.35)  # cm³/(V s)
    gamma: tuple[float, float] = (0.70, 0.60)
    v: tuple[float, float] = (3.0, 3.0)  # V

    def fixed_point(self) -> tuple[float, float, float, float]:
        """Exact equilibrium of the continuous model (closed form from ḣ = 0).

        ``h3 = ((1−γ2) k2 v2 / a3)² / 2g``, ``h4 = ((1−γ1) k1 v1 / a4)² / 2g``,
        ``h1 = ((γ1 k1 v1 + (1−γ2) k2 v2) / a1)² / 2g``,
        ``h2 = ((γ2 k2 v2 + (1−γ1) k1 v1) / a2)² / 2g`` — (12.263, 12.783, 1.634, 1.409).
        """
        (a1, a2, a3, a4), g = self.a, self.g
        (k1, k2), (g1, g2), (v1, v2) = self.k, self.gamma, self.v
        q1, q2 = g1 * k1 * v1, g2 * k2 * v2
        q3, q4 = (1 - g2) * k2 * v2, (1 - g1) * k1 * v1
        return (
            ((q1 + q3) / a1) ** 2 / (2 * g),
            ((q2 + q4) / a2) ** 2 / (2 * g),
            (q3 / a3) ** 2 / (2 * g),
            (q4 / a4) ** 2 / (2 * g),
        )


class FourTankModel(StateSpaceModel):
    """Euler-discretised quadruple tank with all four levels measured (``G = I``).

    Args:
        R: measurement-noise variances (diagonal) or a ``[4, 4]`` covariance;
            default :data:`R_NOMINAL`.
        Q: process-noise variance (isotropic) or ``[4, 4]`` covariance; default 1e-4.
        dt: sampling period in s [DEF 1 s].
        P0: prior variance around the fixed point [DEF 1e-2].
        x0: prior mean; default the exact fixed point.
        params: :class:`FourTankParameters`.
        dtype, device: of every buffer (float32 for speed, float64 for tests).

    No input (``dim_u = 0``): the pump voltages are the constant ``params.v``.
    """

    dim_x = 4
    dim_y = 4
    dim_u = 0

    def __init__(
        self,
        R=R_NOMINAL,
        Q=1e-4,
        *,
        dt: float = 1.0,
        P0=1e-2,
        x0=None,
        params: FourTankParameters | None = None,
        dtype: torch.dtype = torch.float32,
        device=None,
    ):
        super().__init__()
        p = params or FourTankParameters()
        self.params = p
        self.dt = float(dt)
        if not self.dt > 0:
            raise ValueError(f"dt must be > 0; got {dt}")
        kw = {"dtype": dtype, "device": device}
        A = torch.tensor(p.A, **kw)
        a = torch.tensor(p.a, **kw)
        k1, k2 = p.k
        g1, g2 = p.gamma
        v1, v2 = p.v
        # ḣ = −(a/A)√(2g h) + (a_in/A)√(2g h_in) + inflow, written as
        #   ḣ = outflow_coef ⊙ √h + couple_coef ⊙ √h[[2, 3, ·, ·]] + inflow
        root = (2.0 * p.g) ** 0.5
        self.register_buffer("outflow", -(a / A) * root)
        self.register_buffer(
            "couple",
            torch.stack([a[2] / A[0], a[3] / A[1], A.new_zeros(()), A.new_zeros(())]) * root,
        )
        inflow = torch.tensor(
            [
                g1 * k1 * v1 / p.A[0],
                g2 * k2 * v2 / p.A[1],
                (1 - g2) * k2 * v2 / p.A[2],
                (1 - g1) * k1 * v1 / p.A[3],
            ],
            **kw,
        )
        self.register_buffer("inflow", inflow)
        self.register_buffer("G", torch.eye(4, **kw))
        x0 = torch.tensor(p.fixed_point(), **kw) if x0 is None else torch.as_tensor(x0, **kw)
        self.initial = Gaussian(x0, _cov(P0, kw, "P0"))
        self.process_noise = Gaussian(torch.zeros(4, **kw), _cov(Q, kw, "Q"))
        self.measurement_noise = Gaussian(torch.zeros(4, **kw), _cov(R, kw, "R"))

    def continuous_rhs(self, x: Tensor) -> Tensor:
        """``f_c(max(x, 0), v)`` for ``x [..., 4]`` → ``[..., 4]`` (cm/s)."""
        s = torch.sqrt(x.clamp_min(0.0))
        coupled = torch.cat([s[..., 2:4], torch.zeros_like(s[..., :2])], dim=-1)
        return self.outflow * s + self.couple * coupled + self.inflow

    def transition(self, x: Tensor, u: Tensor | None, k: int) -> Tensor:
        """``x + dt · f_c(max(x, 0), v)``; ``x [..., 4]`` → ``[..., 4]``."""
        return x + self.dt * self.continuous_rhs(x)

    def transition_jacobian(self, x: Tensor, u: Tensor | None, k: int) -> Tensor:
        """Closed form: ``I + dt · ∂f_c/∂x`` with ``∂√h/∂h = 1/(2√h)`` (0 where ``h ≤ 0``)."""
        pos = x > 0
        d_sqrt = torch.where(
            pos, 0.5 / torch.sqrt(torch.where(pos, x, torch.ones_like(x))), torch.zeros_like(x)
        )
        jac = torch.diag_embed(1.0 + self.dt * self.outflow * d_sqrt)
        jac[..., 0, 2] = self.dt * self.couple[0] * d_sqrt[..., 2]
        jac[..., 1, 3] = self.dt * self.couple[1] * d_sqrt[..., 3]
        return jac

    def observe(self, x: Tensor, k: int) -> Tensor:
        """``G x`` with ``G = I``: ``[..., 4]`` → ``[..., 4]``."""
        # G = I [D]: skip the product (a [N,4]×[4,4] GEMM is slow on CPU); a copy keeps
        # the contract that the result is a new tensor.
        return x.clone()

    def observation_jacobian(self, x: Tensor, k: int) -> Tensor:
        return self.G.expand(x.shape[:-1] + (4, 4))

    def observation_matrix(self, k: int) -> Tensor:
        """``G`` ``[4, 4]`` (the measurement is linear)."""
        return self.G


def _cov(value, kw, name) -> Tensor:
    t = torch.as_tensor(value, **kw)
    if t.dim() == 0:
        return t * torch.eye(4, **kw)
    if t.dim() == 1:
        if t.shape[0] != 4:
            raise ValueError(f"{name} must have 4 diagonal entries; got {t.shape[0]}")
        return torch.diag(t)
    return t
