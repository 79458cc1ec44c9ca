"""Mobile robot (unicycle) seen by six lidars, under an actuator FDI attack.

Tan, Weng, Chen & Yu, "Nonlinear fusion estimation for false data injection attack
signals in cyber-physical systems" (Sci. China Inf. Sci., supplementary App. B;
parameters and provenance in docs/scenarios.md §4). State ``x = [s_x (cm), s_y (cm),
θ (rad)]``, input ``u = [u_p (cm/s), u_r (rad/s)]``::

    x_k = f(x_{k−1}, u_k) + B(k) a_k + w,  f = x + T₀ [u_p cos θ, u_p sin θ, u_r]    (B1)–(B3)
    B(k) = T₀ [[cos θ_{k−1}, 0], [sin θ_{k−1}, 0], [0, 1]] = ∂f/∂u                    (B4)
    y_k^i = [‖s_i − p_k‖, wrap(θ_k − atan2(s_yi − s_y, s_xi − s_x))] + v,  i = 1 … 6  (B5)–(B7)

so ``f(x, u) + B a = f(x, u + a)``: the attack is an :class:`~.attacks.ActuatorInjection`
on ``u``. The truth's process noise is input noise, ``w = B(k) n``, ``n ~ N(0, diag(1 cm²/s²,
1 deg²/s²))`` (the paper's 2×2 ``Q``); the filters' ``Q`` (``process_cov``) is the 3×3
``diag(1 cm², 1 cm², 1 deg²)`` [DEF] that (A4) needs, an upper bound on ``B n``'s
covariance. Bearing residuals are wrapped to ``(−π, π]``.

Time: ``us[:, t]`` is ``u_{k}`` with ``k = t + 1`` (it moves ``x_t`` to ``x_{t+1}``), so
the paper's attack ``a(k)``, ``k ≥ 30``, starts at index ``t = 29``.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from difffilter._checks import check_finite_number, check_model_dtype
from difffilter.fdi.mdpf import Reading
from difffilter.linalg import matvec, rowwise
from difffilter.noise import Gaussian
from difffilter.ssm import StateSpaceModel

from .attacks import ActuatorInjection
from .registry import register
from .scenario import Scenario, plant_entries
from .tracking import wrap_angle

__all__ = ["DEG", "SENSORS", "GROUPS", "RobotModel", "RobotScenario"]

DEG = math.pi / 180.0
#: Lidar positions (cm), (B7).
SENSORS = ((-120.0, 0.0), (-60.0, -60.0), (60.0, -60.0), (-60.0, 60.0), (60.0, 60.0), (120.0, 0.0))
#: The two local groups of App. B: sensors {1, 2, 3} and {4, 5, 6} (0-based).
GROUPS = ((0, 1, 2), (3, 4, 5))


class RobotModel(StateSpaceModel):
    """The unicycle (B2) with range–bearing lidars (B6); closed-form Jacobians.

    ``sensors``: positions ``[S, 2]``, or ``[G, S, 2]`` for ``G`` sensor groups run as a
    leading batch dimension (``x [G, ..., dx]``, e.g. the two local estimators at once).
    ``dim_y = 2S`` (``[r_1, b_1, …, r_S, b_S]``). ``meas_var``: the (range cm², bearing
    rad²) variances of every lidar, or one pair per lidar ``[S, 2]``; ``R`` is diagonal
    (assign ``measurement_noise`` for a correlated one).
    """

    dim_x, dim_u = 3, 2

    def __init__(
        self,
        *,
        sensors=SENSORS,
        dt: float = 1.0,
        input_var=(1.0, DEG**2),
        filter_q=(1.0, 1.0, DEG**2),
        meas_var=(1.0, DEG**2),
        x0=(0.0, 0.0, 0.0),
        p0=(1.0, 1.0, DEG**2),
        dtype=torch.float64,
    ):
        check_model_dtype(dtype, "dtype")  # (float16 had failed in torch's Cholesky)
        pos = torch.as_tensor(sensors, dtype=dtype)
        if pos.dim() not in (2, 3) or pos.shape[-1] != 2:
            raise ValueError(f"sensors must have shape [S, 2] or [G, S, 2]; got {tuple(pos.shape)}")
        if not bool(torch.isfinite(pos).all()):  # (NaN ranges had been simulated: a trial)
            raise ValueError("sensors contains NaN or Inf positions; every position must be finite")
        dim_y = 2 * pos.shape[-2]
        var = torch.tensor(meas_var, dtype=dtype)
        if var.shape == (dim_y // 2, 2):  # one (range, bearing) pair per lidar
            R = var.reshape(dim_y)
        elif var.shape == (2,):
            R = var.repeat(dim_y // 2)
        else:
            raise ValueError(
                f"meas_var must be one (range, bearing) variance pair for every lidar, shape "
                f"(2,), or one per lidar, shape ({dim_y // 2}, 2); got {tuple(var.shape)}"
            )
        # each named in its errors (Gaussian had named a wrong length "loc": a trial)
        x0, p0 = plant_entries(x0, "x0", 3, dtype), plant_entries(p0, "p0", 3, dtype, positive=True)
        filter_q = plant_entries(filter_q, "filter_q", 3, dtype, positive=True)
        input_var = plant_entries(input_var, "input_var", 2, dtype, positive=True)
        self._setup(
            pos, dt,
            initial=Gaussian(x0, torch.diag(p0)),
            process_noise=Gaussian(torch.zeros(3, dtype=dtype), torch.diag(filter_q)),
            input_noise=Gaussian(torch.zeros(2, dtype=dtype), torch.diag(input_var)),
            measurement_noise=Gaussian(torch.zeros(dim_y, dtype=dtype), torch.diag(R)),
        )  # fmt: skip

    def _matrices_read(self) -> list[tuple[str, Tensor]]:
        """What :func:`~difffilter._checks.check_model` checks finite at a run's start: the
        sensor positions, written NaN in place had simulated NaN ranges (a robot trial)."""
        return [("sensor_pos", self._buffers["sensor_pos"])]

    def __setattr__(self, name, value):
        # dt assigned later is checked as the constructor checks it (dt = -1 had run the
        # robot backwards, NaN simulated NaN states, "1" failed in torch: a robot trial)
        if name == "dt":
            value = check_finite_number(value, "dt", positive=True)
        super().__setattr__(name, value)

    def _setup(self, pos, dt, *, initial, process_noise, input_noise, measurement_noise):
        """Set every attribute once (first assignments: building a model, e.g. a group,
        changes no other model's validation, :mod:`difffilter._assignments`)."""
        super().__init__()
        # (a NaN or negative dt had built a model that simulated NaN or ran backwards)
        self.dt = dt  # (checked by __setattr__)
        self.num_sensors = pos.shape[-2]
        self.dim_y = 2 * self.num_sensors
        self.register_buffer("sensor_pos", pos)
        self.initial, self.process_noise = initial, process_noise
        self.input_noise, self.measurement_noise = input_noise, measurement_noise

    def group(self, indices) -> RobotModel:
        """The same robot seen by the sensors ``indices`` only (0-based), or by several
        groups stacked (``indices`` a sequence of equal-length sequences → ``[G, S, 2]``).

        The group keeps this model's noise as it is: its ``R`` is the rows and columns of
        the full ``R`` that its sensors' entries index (per-lidar variances and
        correlations included), and the prior, ``Q`` and the truth's input noise are the
        model's own, on the same tensors (gradients and in-place edits reach them). It had
        rebuilt ``R`` from lidar 1's variances and kept only the diagonals of ``Q`` and
        ``P_0``: a model made noisier on lidars 4–6 gave bit-identical group estimates.
        Stacked groups share one ``R``, so their sensors' blocks of ``R`` must be equal
        (:meth:`groups_share_noise`); groups seen with different noise are estimated one
        group at a time (``model.group(g)`` for each).
        """
        pos = self.sensor_pos
        try:
            idx = torch.as_tensor(indices)
        except (TypeError, ValueError, RuntimeError):  # ragged groups: torch's own message
            idx = None
        if (
            idx is None
            or idx.dim() not in (1, 2)
            or idx.numel() == 0
            or idx.dtype.is_floating_point
            or idx.dtype == torch.bool  # (a mask had been read as indices 0 and 1: a trial)
            or any(
                len(set(g)) != len(g) for g in (idx.tolist() if idx.dim() == 2 else [idx.tolist()])
            )
        ):
            raise ValueError(
                "indices must be sensor indices (a sequence of distinct ints) or equal-length "
                f"groups of them; got {indices!r}"
            )
        if pos.dim() != 2:
            raise ValueError(
                f"group selects from a model of one sensor set [S, 2]; this one has sensors of "
                f"shape {tuple(pos.shape)}"
            )
        if bool(((idx < 0) | (idx >= self.num_sensors)).any()):
            raise ValueError(
                f"indices must lie in 0 … {self.num_sensors - 1} (0-based sensors); got {indices!r}"
            )
        noise = self.measurement_noise
        if not isinstance(noise, Gaussian):
            raise ValueError(
                f"group needs a Gaussian measurement noise (its R is sliced per sensor); got "
                f"{type(noise).__name__}"
            )
        locs, covs = _noise_blocks(noise, idx.tolist() if idx.dim() == 2 else [idx.tolist()])
        if not _all_equal(locs) or not _all_equal(covs):
            raise ValueError(
                "the stacked groups see different measurement noise (their sensors' blocks of R "
                "differ), and stacked groups share one R: estimate each group on its own "
                "model, model.group(g) for each g (groups_share_noise tells which applies)"
            )
        out = RobotModel.__new__(RobotModel)
        out._setup(pos[idx], self.dt, initial=_same_noise(self.initial),
                   process_noise=_same_noise(self.process_noise),
                   input_noise=_same_noise(self.input_noise),
                   measurement_noise=Gaussian(locs[0], covs[0]))  # fmt: skip
        return out

    def groups_share_noise(self, groups) -> bool:
        """Whether the sensor groups ``groups`` (equal-length sequences of 0-based indices)
        see the same measurement noise (equal blocks of ``R`` and of its mean), so that
        :meth:`group` can stack them."""
        try:  # (numpy's and tensors' integers too, as group() takes them)
            flat = [None if isinstance(i, bool) else operator.index(i) for g in groups for i in g]
        except TypeError:
            flat = [None]
        if any(i is None or not 0 <= i < self.num_sensors for i in flat):
            # (an index past the sensors had failed in torch's IndexError at the estimator's
            # init, and -1 read as the last sensor: a robot-estimators trial)
            raise ValueError(
                f"groups: indices must lie in 0 … {self.num_sensors - 1} (0-based sensors); "
                f"got {groups!r}"
            )
        noise = self.measurement_noise
        if not isinstance(noise, Gaussian):
            return False
        locs, covs = _noise_blocks(noise, [list(g) for g in groups])
        return _all_equal(locs) and _all_equal(covs)

    # -- dynamics ------------------------------------------------------------------
    def transition(self, x, u, k):
        if u is None:
            return x
        # u may be one row for many particles ([..., 1, 2] against [..., N, 3])
        speed, turn, th = torch.broadcast_tensors(u[..., 0], u[..., 1], x[..., 2])
        step = torch.stack((speed * torch.cos(th), speed * torch.sin(th), turn), -1)
        return x + self.dt * step

    def transition_jacobian(self, x, u, k):
        th = x[..., 2]
        lead = torch.broadcast_shapes(x.shape[:-1], () if u is None else u.shape[:-1])
        jac = torch.eye(3, dtype=x.dtype, device=x.device).expand(lead + (3, 3)).clone()
        if u is not None:
            jac[..., 0, 2] = -self.dt * u[..., 0] * torch.sin(th)
            jac[..., 1, 2] = self.dt * u[..., 0] * torch.cos(th)
        return jac

    def input_jacobian(self, x, u, k):
        """``B(k) = ∂f/∂u`` (B4) at ``x [..., 3]`` → ``[..., 3, 2]``."""
        th = x[..., 2]
        z = torch.zeros_like(th)
        rows = (torch.stack((torch.cos(th), z), -1), torch.stack((torch.sin(th), z), -1),
                torch.stack((z, torch.ones_like(th)), -1))  # fmt: skip
        return self.dt * torch.stack(rows, -2)

    def sample_transition(self, x, u, k, generator=None):
        """``f(x, u) + B(θ) n``, ``n ~ N(0, input_var)``: the truth's input noise."""
        n = self.input_noise.sample(x.shape[:-1], generator)
        return self.transition(x, u, k) + matvec(self.input_jacobian(x, u, k), n)

    def linearize_components(self, x, u, y, k):
        """Everything one adaptive update needs, on component lists (the fast path of
        :class:`~difffilter.fdi.mdpf.AdaptiveKalmanProposal`): ``x`` (3 tensors ``[...]``),
        ``u`` the effective input (2), ``y`` the measurement (``dim_y`` tensors, broadcasting)
        → ``(f(x, u), ∂f/∂x, ∂f/∂u, wrapped y − h(f), ∂h/∂x at f)`` as lists (3; 3×3; 3×2;
        dim_y; dim_y×3). Constant entries are Python numbers. Per lidar, with
        ``(d_x, d_y) = s_i − p`` and ``r = |s_i − p|``::

            ε_r = y_r − r,   ε_b = π − ((π − y_b + θ − atan2(d_y, d_x)) mod 2π)   (wrapped)
            ∂h/∂x = [[−d_x/r, −d_y/r, 0], [−d_y/r², d_x/r², 1]]

        written so that each entry costs one elementwise kernel where it can (the
        ``y``-only terms are per-run tensors ``[..., 1]``, not per-particle).
        """
        T = self.dt
        pos = self.sensor_pos
        if pos.dim() == 2:
            sensors = pos.tolist()
        else:  # [G, S, 2]: per-group coordinates [G, 1, …] against x [G, …]
            shape = pos.shape[:1] + (1,) * (x[0].dim() - 1)
            sensors = [
                (pos[:, i, 0].reshape(shape), pos[:, i, 1].reshape(shape))
                for i in range(pos.shape[1])
            ]
        c, s = torch.cos(x[2]), torch.sin(x[2])
        up = u[0] if T == 1.0 else T * u[0]
        vc, vs = up * c, up * s
        xp = [x[0] + vc, x[1] + vs, x[2] + (u[1] if T == 1.0 else T * u[1])]
        F = [[1.0, 0.0, -vs], [0.0, 1.0, vc], [0.0, 0.0, 1.0]]
        B = [[c if T == 1.0 else T * c, 0.0], [s if T == 1.0 else T * s, 0.0], [0.0, T]]
        e, H = [], []
        for i, (px, py) in enumerate(sensors):
            dx, dy = px - xp[0], py - xp[1]
            r = torch.sqrt(torch.addcmul(dx * dx, dy, dy))
            e.append(y[2 * i] - r)
            t = xp[2] + (math.pi - y[2 * i + 1])  # π − y_b + θ, a new tensor
            t.sub_(torch.atan2(dy, dx))  # π − (y_b − θ + atan2(d_y, d_x))
            e.append(math.pi - torch.remainder(t, 2 * math.pi))
            ir = torch.reciprocal(r)
            nir = -ir
            hr0, hr1 = dx * nir, dy * nir  # −d_x/r, −d_y/r
            H.append([hr0, hr1, 0.0])
            H.append([hr1 * ir, hr0 * nir, 1.0])  # −d_y/r², d_x/r²
        return xp, F, B, e, H

    # -- measurements ----------------------------------------------------------------
    def _offsets(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """``s_i − p`` per sensor ``[..., S]`` (x and the sensor groups broadcast)."""
        pos = self.sensor_pos
        if pos.dim() == 3:  # [G, S, 2] against x [G, ..., 3]
            pos = pos.reshape(pos.shape[:1] + (1,) * (x.dim() - 2) + pos.shape[1:])
        return pos[..., 0] - x[..., 0:1], pos[..., 1] - x[..., 1:2]

    def observe(self, x, k):
        dx, dy = self._offsets(x)
        bearing = wrap_angle(x[..., 2:3] - torch.atan2(dy, dx))
        y = torch.stack((torch.hypot(dx, dy), bearing), -1)
        return y.reshape(y.shape[:-2] + (self.dim_y,))

    def observation_jacobian(self, x, k):
        dx, dy = self._offsets(x)
        r2 = dx.square() + dy.square()
        r = r2.sqrt()
        z, one = torch.zeros_like(r), torch.ones_like(r)
        rows = torch.stack(
            (torch.stack((-dx / r, -dy / r, z), -1), torch.stack((-dy / r2, dx / r2, one), -1)),
            -2,
        )  # [..., S, 2, 3]
        return rows.reshape(rows.shape[:-3] + (self.dim_y, 3))

    def measurement_residual(self, y, y_hat):
        d = rowwise(torch.sub, y, y_hat)
        d = d.reshape(d.shape[:-1] + (-1, 2))
        return torch.stack((d[..., 0], wrap_angle(d[..., 1])), -1).flatten(-2)


def _noise_blocks(noise: Gaussian, groups) -> tuple[list[Tensor], list[Tensor]]:
    """The mean ``[..., 2S]`` and covariance ``[..., 2S, 2S]`` blocks of each sensor group's
    range–bearing entries (``2i``, ``2i + 1`` for sensor ``i``)."""
    loc, cov = noise.mean, noise.cov
    blocks = [torch.tensor([2 * i + j for i in g for j in (0, 1)], device=cov.device)
              for g in groups]  # fmt: skip
    return [loc[..., e] for e in blocks], [cov[..., e[:, None], e] for e in blocks]


def _all_equal(tensors) -> bool:
    return all(t.shape == tensors[0].shape and torch.equal(t, tensors[0]) for t in tensors[1:])


def _same_noise(noise):
    """The same noise in a module of its own (a Gaussian on the same tensors, so that
    gradients and in-place edits reach the model it came from; another noise itself)."""
    return Gaussian(noise.loc, noise.cov) if isinstance(noise, Gaussian) else noise


@dataclass(frozen=True)
class RobotScenario(Scenario):
    """The lidar-robot study (App. B); fields are the paper's values unless marked [DEF].

    Attributes:
        velocity: commanded ``u_p`` (cm/s) [DEF]. turn_rate_deg: commanded ``u_r``
            (deg/s) [DEF]. attack: ``(a_p cm/s, a_r deg/s)`` (B9). attack_from: first
            attacked ``k`` (B9: 30). forgetting: ``λ₁ = λ₂`` (0.7). attack_cov0: ``S_0 = ω I``
            [DEF 10]. reading: eq. (5) reading of the local estimators [DEF ``"draw"``].
        turn_rate_range_deg: ``(lo, hi)``: run ``r`` of ``R`` commands ``u_r`` evenly spaced
            from ``lo`` to ``hi`` deg/s instead of ``turn_rate_deg`` (a training variant:
            paths of many curvatures, so that a network does not learn one path's inputs).
        false_alarm_rate: the per-step rate of the robot's detectors: the Wald tests on
            ``(â, S)`` (χ²₂) and any χ²/CUSUM detector named on a robot study [DEF 1 %].
            It had said 0.5 %, at which a named χ²/CUSUM detector ran, while the Wald tests
            ran at the library's 1 % whatever it said.
    """

    family: str = "robot"
    state_unit: ClassVar[str] = "cm, rad"  # (s_x, s_y, θ) pooled
    attack_unit: ClassVar[str] = "cm/s, rad/s"  # (a_p, a_r) on the actuators, as simulated
    description: str = ""
    paper: str = "Tan, Weng, Chen & Yu, nonlinear fusion estimation of FDI attacks, App. B"
    runs: int = 100
    steps: int = 100
    dt: float = 1.0
    num_particles: int = 100
    velocity: float = 5.0
    turn_rate_deg: float = 5.0
    attack: tuple = (20.0, 20.0)
    attack_from: int = 30
    forgetting: float = 0.7
    attack_cov0: float = 10.0
    reading: Reading = Reading.DRAW
    turn_rate_range_deg: tuple | None = None
    false_alarm_rate: float = 0.01
    checkpoint: str | None = "checkpoints/robot_nn_ekf.ckpt"  # gaussian_nn_ekf without --ckpt

    def __post_init__(self):
        # the study reads the attack estimate at k = attack_from + 14 and errors from k = 40
        if not 1 <= self.attack_from or self.steps < max(self.attack_from + 14, 41):
            raise ValueError(
                f"steps must be at least max(attack_from + 14, 41) and attack_from ≥ 1 (the "
                f"report reads â at k = attack_from + 14 and the errors from k = 40); got "
                f"steps={self.steps!r}, attack_from={self.attack_from!r}"
            )
        if isinstance(self.attack_from, bool):  # (True had been taken for k = 1: a trial)
            raise ValueError(f"attack_from must be an integer step ≥ 1; got {self.attack_from!r}")
        rates = self.turn_rate_range_deg
        if rates is not None and (
            not isinstance(rates, (tuple, list)) or len(rates) != 2
            or any(isinstance(r, bool) or not isinstance(r, (int, float)) or not math.isfinite(r)
                   for r in rates)
        ):  # fmt: skip
            # (three entries or a number failed at the first run in Python's unpacking, NaN
            # commanded NaN turn rates: a robot trial)
            raise ValueError("turn_rate_range_deg must be None or two finite numbers (lo, hi) in "
                             f"deg/s; got {rates!r}")  # fmt: skip
        attack = self.attack
        if (not isinstance(attack, (tuple, list)) or len(attack) != 2
                or any(isinstance(a, bool) or not isinstance(a, (int, float))
                       or not math.isfinite(a) for a in attack)):  # fmt: skip
            # (a third entry had been dropped without a word: a trial)
            raise ValueError("attack must be two finite numbers (a_p cm/s on the speed, a_r "
                             f"deg/s on the turn rate); got {attack!r}")  # fmt: skip

    def system(self, dtype: torch.dtype = torch.float64, device=None) -> RobotModel:
        return self._on_device(RobotModel(dt=self.dt, dtype=dtype), device)

    def attack_model(self) -> ActuatorInjection:
        return ActuatorInjection((self.attack[0], self.attack[1] * DEG), start=self.attack_from - 1)

    def inputs(self, runs: int, dtype: torch.dtype, device=None) -> Tensor:
        """``u = (u_p cm/s, u_r rad/s)`` ``[runs, T, 2]``, constant along each run."""
        u = torch.tensor((self.velocity, self.turn_rate_deg * DEG), dtype=dtype, device=device)
        u = u.expand(runs, self.steps, 2).clone()
        if self.turn_rate_range_deg is not None:
            lo, hi = self.turn_rate_range_deg
            rates = torch.linspace(lo, hi, runs, dtype=dtype, device=device) * DEG
            u[..., 1] = rates.unsqueeze(-1)
        return u

    def paper_numbers(self) -> dict:
        return {"figures_only": True, "attack": {"a_p_cm_s": self.attack[0], "a_r_deg_s": self.attack[1]},
                "attack_from_k": self.attack_from, "forgetting": self.forgetting}  # fmt: skip


_ESTIMATORS = (
    "zhang_akf",
    "zhang_akf_group1",
    "zhang_akf_group2",
    "mdpf_local_1",
    "mdpf_local_2",
    "mdpf_fused_ci",
    "mdpf_fused_naive",
    "mdpf_fused_ci_compensated",
    "gaussian_nn_ekf",
)


def _notes(inputs: str) -> tuple[str, ...]:
    """The robot scenarios' notes, with the commanded ``inputs`` of the scenario (the
    turning variants' had read u = (5 cm/s, 5 deg/s): a trial of the variants)."""
    return (f"[DEF] u = {inputs} (unstated); filters' Q = diag(1 cm², 1 cm², 1 deg²) for "
            "(A4); truth's noise is input noise N(0, diag(1 cm²/s², 1 deg²/s²)) through B(k).",
            *_NOTES)  # fmt: skip


_NOTES = (
    "[DEF] P0 = diag(1 cm², 1 cm², 1 deg²), S0 = 10 I, Υ0 = 0, â0 = 0, M = 100 particles per local.",
    "[DEF] eq. (5) of the letter is missing: 'draw' reading x̂ʲ ~ N(x̄ˡ, Pˡ), âʲ = āˡ; fusion by "
    "covariance intersection (naive information fusion as ablation).",
)

register(
    RobotScenario(
        name="robot_actuator_attack",
        description="unicycle, 6 lidars, actuator attack a = (20 cm/s, 20 deg/s) from k = 30, u = (5, 5)",
        estimators=_ESTIMATORS,
        notes=_notes("(5 cm/s, 5 deg/s)"),
    )
)
register(
    RobotScenario(
        name="robot_actuator_attack_turning",
        description="as robot_actuator_attack with u = (5 cm/s, 10 deg/s): the attacked path leaves the nominal one",
        estimators=_ESTIMATORS,
        notes=_notes("(5 cm/s, 10 deg/s)"),
        turn_rate_deg=10.0,
    )
)
register(
    RobotScenario(
        name="robot_actuator_attack_turn_rates",
        description="as robot_actuator_attack with u_r evenly spread over 0-15 deg/s across the "
        "runs (training data: many path curvatures)",
        estimators=_ESTIMATORS,
        notes=_notes("(5 cm/s, u_r evenly spread over 0-15 deg/s across the runs)"),
        turn_rate_range_deg=(0.0, 15.0),
        headline=False,
    )
)
