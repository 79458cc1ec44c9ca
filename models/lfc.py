"""Two-area load-frequency control (LFC) under false-data injection (Sargolzaei et al., TII 2020).

Plant, eqs (34)–(42) of the paper. Area ``i`` has the state
``xⁱ = [Δf, ΔP_g, ΔP_tu, ΔP_tie, ∫(βΔf + ΔP_tie)]`` and::

    ẋⁱ = Aᵢ xⁱ + Σ_{j≠i} Aᵢⱼ xʲ + Bᵢ uⁱ + Fᵢ ΔP_lⁱ                          (34)–(41)

    Aᵢ = [[−μ/J, 1/J, 0, −1/J, 0],          Bᵢ = e₃ / T_g,   Fᵢ = −e₁ / J,
          [0, −1/T_tu, 1/T_tu, 0, 0],        Aᵢⱼ = −2π Tᵢⱼ at (4, 1), else 0.
          [−1/(ω T_g), 0, −1/T_g, 0, 0],
          [2π Σ_{j≠i} Tᵢⱼ, 0, 0, 0, 0],
          [β, 0, 0, 1, 0]]

The stacked 10-state model is discretised exactly by a zero-order hold (the paper's
eq. 42): ``A_d = e^{AΔt}``, ``B_d = ∫₀^Δt e^{Aα} dα B``, both read off one matrix exponential
of the augmented block matrix ``[[A, B], [0, 0]]Δt`` (Van Loan). The discrete model is::

    X_{k+1} = A_d X_k + B_d U_k + F_d ΔP_l + D ξ_k,    ξ_k ~ N(0, Ξ)           (42)
    Z_k     = X_k + M_k + θ_k,                          θ_k ~ N(0, Θ)

Time grid (difffilter's convention): ``X_0 = 0`` is the prior, measurements ``Z_k`` arrive
at ``t_k = kΔt`` for ``k = 1 … T``; ``U_k`` is applied on ``[t_k, t_{k+1})``.

Attack scenarios I–IV (eqs 44–47 and Sec. VII-D) and a random-attack generator for
training and validation live here, together with the scenario registrations
``lfc_step``, ``lfc_sine``, ``lfc_simultaneous``, ``lfc_sawtooth`` and ``lfc_sine_1ms``.

Values the paper leaves open are ``[DEF]`` defaults (``docs/scenarios.md``, LFC); each
is named in :data:`DEFAULT_NOTES` and in the scenario's ``notes``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import ClassVar

import torch
from torch import Tensor, nn

import difffilter
from difffilter._checks import Choice, check_finite_number, check_integer, check_model_dtype
from difffilter.attack import Channel, TabulatedAttack, attack_dim
from difffilter.control import zoh_discretize
from difffilter.fdi import ChiSquareDetector, GatedFilter
from difffilter.kalman import KalmanFilter
from difffilter.linalg import safe_cholesky
from difffilter.loop import LoopResult, ReplayedNoise, closed_loop
from difffilter.models.registry import Scenario, register
from difffilter.models.scenario import OWN_ATTACK, simulation_dtype
from difffilter.models.schedules import AllSensors
from difffilter.threats import Covert, Shaped

from .attacks import Signal

__all__ = [
    "NUM_AREAS",
    "AREA_DIM",
    "STATE_DIM",
    "STATE_NAMES",
    "STATE_UNITS",
    "LFCParameters",
    "continuous_model",
    "LFCPlant",
    "SecureController",
    "Watermarked",
    "LFCScenario",
    "LFCAttack",
    "scenario_attack",
    "sawtooth_pulse_train",
    "random_attacks",
    "DEFAULT_NOTES",
]

NUM_AREAS = 2
AREA_DIM = 5
STATE_DIM = NUM_AREAS * AREA_DIM
STATE_NAMES = tuple(
    f"{n}_{i + 1}" for i in range(NUM_AREAS) for n in ("df", "dPg", "dPtu", "dPtie", "ace_int")
)
#: Each state's unit, in STATE_NAMES' order: the frequency deviation in Hz, the powers in
#: p.u., and the integral of the area control error ACE = β Δf + ΔP_tie (p.u.) in p.u.·s
#: (a figure had labelled it p.u.).
STATE_UNITS = ("Hz", "p.u.", "p.u.", "p.u.", "p.u.·s") * NUM_AREAS

# Tolerance for comparing sample times with interval ends: k·Δt is not exact in binary
# floating point (300·0.01 may round below 3), and the paper's intervals are closed.
_T_EPS = 1e-9


@dataclass(frozen=True)
class LFCParameters:
    """Physical parameters of the two areas (one value per area).

    [DEF] Table I of Sargolzaei et al., TSG 2016 (the paper's ref. [31]) was not available.
    These are the two-area values of Zhang et al., IEEE TPS 28(3) 2013 (the paper's
    ref. [36]) as recorded in docs/scenarios.md (LFC) ("recalled from memory, not verified").
    """

    inertia: tuple[float, float] = (10.0, 12.0)  # J = 2H, p.u.·s
    damping: tuple[float, float] = (1.0, 1.5)  # μ = D, p.u./Hz
    turbine_time: tuple[float, float] = (0.3, 0.4)  # T_tu, s
    governor_time: tuple[float, float] = (0.1, 0.17)  # T_g, s
    droop: tuple[float, float] = (0.05, 0.05)  # ω = R, Hz/p.u.
    freq_bias: tuple[float, float] = (21.0, 21.5)  # β, p.u./Hz
    tie_stiffness: float = 0.198  # T_12 = T_21, p.u./rad

    def __post_init__(self):
        # finite too: a NaN passed "v <= 0" and built a plant of NaN matrices (a fuzzing trial)
        for name in ("inertia", "turbine_time", "governor_time", "droop"):
            vals = getattr(self, name)
            if len(vals) != NUM_AREAS or not all(0 < v < math.inf for v in vals):
                raise ValueError(
                    f"{name} must hold {NUM_AREAS} finite positive values; got {vals!r}"
                )
        for name in ("damping", "freq_bias"):
            vals = getattr(self, name)
            if len(vals) != NUM_AREAS or not all(math.isfinite(v) for v in vals):
                raise ValueError(f"{name} must hold {NUM_AREAS} finite values; got {vals!r}")
        if not 0 <= self.tie_stiffness < math.inf:  # (0: two areas without a tie line)
            raise ValueError(
                f"tie_stiffness must be a finite number >= 0; got {self.tie_stiffness!r}"
            )


def continuous_model(params: LFCParameters | None = None, *, dtype=torch.float64):
    """Stacked continuous-time matrices of eqs (34)–(41).

    Returns ``(A [10, 10], B [10, 2], F [10, 2])`` where column ``i`` of ``B`` (``F``) is the
    control input (load deviation) of area ``i``.
    """
    p = params or LFCParameters()
    A = torch.zeros(STATE_DIM, STATE_DIM, dtype=dtype)
    B = torch.zeros(STATE_DIM, NUM_AREAS, dtype=dtype)
    F = torch.zeros(STATE_DIM, NUM_AREAS, dtype=dtype)
    two_pi_t = 2.0 * math.pi * p.tie_stiffness
    for i in range(NUM_AREAS):
        o = AREA_DIM * i
        J, mu, Ttu, Tg, w, beta = (
            p.inertia[i],
            p.damping[i],
            p.turbine_time[i],
            p.governor_time[i],
            p.droop[i],
            p.freq_bias[i],
        )
        A[o, o], A[o, o + 1], A[o, o + 3] = -mu / J, 1.0 / J, -1.0 / J
        A[o + 1, o + 1], A[o + 1, o + 2] = -1.0 / Ttu, 1.0 / Ttu
        A[o + 2, o], A[o + 2, o + 2] = -1.0 / (w * Tg), -1.0 / Tg
        # Two areas: Σ_{j≠i} 2πT_ij has a single term.
        A[o + 3, o] = two_pi_t
        A[o + 4, o], A[o + 4, o + 3] = beta, 1.0
        B[o + 2, i] = 1.0 / Tg
        F[o, i] = -1.0 / J
        for j in range(NUM_AREAS):
            if j != i:  # A_ij of eq. (41): the other area's frequency drives the tie line
                A[o + 3, AREA_DIM * j] = -two_pi_t
    return A, B, F


class LFCPlant(nn.Module):
    """Discrete two-area LFC plant with process/measurement noise and a load disturbance.

    Args:
        dt: sampling time in seconds (the paper: 0.01; Fig. 7: 0.001).
        params: physical parameters (:class:`LFCParameters`).
        process_var: ``Ξ = process_var·I`` with ``D = I``, the covariance of the discrete-time
            noise ``ξ_k`` of eq. (42). [DEF] (not given in the paper): ``1e-6·dt/0.01``, i.e.
            1e-6 per 10 ms step, a white-noise intensity of 1e-4 s⁻¹ that the 1 ms variant
            keeps (1e-7 per step) so that both sampling times simulate the same plant.
        measurement_var: ``Θ = measurement_var·I``. [DEF] 1e-4.
        dtype: floating dtype of every buffer.

    Buffers: ``A, B, F`` (continuous), ``Ad, Bd, Fd`` (ZOH), ``C = I₁₀``, ``Q = Ξ``, ``R = Θ``.
    The continuous ``A, B, F`` are discretised once, here: written later they change no
    discrete matrix (build a plant of other parameters: ``LFCPlant(params=…)``).
    """

    def __init__(
        self,
        dt: float = 0.01,
        params: LFCParameters | None = None,
        *,
        process_var: float | None = None,
        measurement_var: float = 1e-4,
        dtype=torch.float64,
    ):
        super().__init__()
        # (float16 had failed at the first draw, int64 truncated Ad to 0 and ±1: a review)
        check_model_dtype(dtype, "dtype")
        # finite as well as positive: inf passes "> 0" and turns every later state NaN
        dt = check_finite_number(dt, "dt", positive=True)
        if process_var is None:
            process_var = 1e-6 * dt / 0.01
        process_var = check_finite_number(process_var, "process_var", positive=True)
        measurement_var = check_finite_number(measurement_var, "measurement_var", positive=True)
        self._dt = dt
        self._params = params or LFCParameters()
        A, B, F = continuous_model(self.params, dtype=torch.float64)
        Ad, BFd = zoh_discretize(A, torch.cat([B, F], dim=1), self.dt)
        eye = torch.eye(STATE_DIM, dtype=torch.float64)
        for name, value in {
            "A": A,
            "B": B,
            "F": F,
            "Ad": Ad,
            "Bd": BFd[:, :NUM_AREAS],
            "Fd": BFd[:, NUM_AREAS:],
            "C": eye,
            "Q": process_var * eye,
            "R": measurement_var * eye,
        }.items():
            self.register_buffer(name, value.to(dtype))

    @property
    def dt(self) -> float:
        """Sampling time in s (read-only: ``Ad``, ``Bd`` and ``Fd`` are discretised with it;
        assigned later, it had been stored and the old matrices kept, 1.7 off a plant built
        with it: a trial of models changed under the filters)."""
        return self._dt

    @property
    def params(self) -> LFCParameters:
        """The plant's parameters (read-only: the matrices are built from them once, here;
        assigned later, they had been stored beside the old matrices, A 0.125 and the LQR
        gain 8.05 off a plant built with them: a trial)."""
        return self._params

    @params.setter
    def params(self, value) -> None:
        raise AttributeError(
            "LFCPlant.params are built into its matrices by the constructor: build a new "
            "LFCPlant(params=…)"
        )

    @property
    def dtype(self):
        return self.Ad.dtype

    @property
    def process_var(self) -> float:
        """``Ξ``'s variance as the buffer ``Q`` holds it now (loaded or edited):
        ``ValueError`` where ``Q`` is not a multiple of ``I``."""
        return _isotropic_variance(self.Q, "Q")

    @property
    def measurement_var(self) -> float:
        """``Θ``'s variance as the buffer ``R`` holds it now: ``ValueError`` where ``R`` is
        not a multiple of ``I``."""
        return _isotropic_variance(self.R, "R")

    def model(self, *, init_cov: float = 1e-2, knows_load: bool = True):
        """Eq. (42) as a :class:`~difffilter.LinearGaussianModel` with the input
        ``[U (2), ΔP_l (2)]``: ``B = [B_d, F_d]``, ``H = I``, ``Q = Ξ``, ``R = Θ``, prior
        ``N(0, init_cov·I)``. ``knows_load=False`` gives the observers' model, to which the
        load is an unknown input (``B = [B_d, 0]``; [DEF], as in eq. 2): the same input
        vector reaches both, the observers simply do not use its load part.

        The model holds the buffers ``Ad, C, Q, R`` themselves (a write in place reaches a
        filter on it), and a ``B`` made here from ``Bd`` and ``Fd``: after a write into
        either, build the model again (a filter on the old one had gone on with the old
        ``B``, 9.8e-3 off a step later: a trial of models changed under the filters)."""
        eye = torch.eye(STATE_DIM, dtype=self.dtype, device=self.Ad.device)
        load = self.Fd if knows_load else torch.zeros_like(self.Fd)
        return difffilter.LinearGaussianModel(
            self.Ad, self.C, self.Q, self.R, torch.zeros_like(eye[0]), init_cov * eye,
            B=torch.cat([self.Bd, load], dim=1),
        )  # fmt: skip

    def sample_noise(
        self, num_runs: int, steps: int, generator: torch.Generator
    ) -> tuple[Tensor, Tensor]:
        """Process and measurement noise ``(ξ [B, T, 10], θ [B, T, 10])`` from ``generator``:
        ``ξ = L_Q ε``, ``θ = L_R ε'`` with ``L`` the Cholesky factors of the buffers ``Q``
        and ``R`` as they are now (the filter's model reads the same buffers; they had been
        drawn from the constructor's variances, so a loaded state dict changed the model
        and not the noise).

        Drawn once per Monte Carlo study and shared by every estimator (common random
        numbers): ``ξ[:, k]`` drives ``X_k → X_{k+1}``, ``θ[:, k]`` corrupts ``Z_{k+1}``.
        """
        if not isinstance(generator, torch.Generator):
            raise ValueError("generator must be a torch.Generator (every draw is seeded)")
        shape = (num_runs, steps, STATE_DIM)
        factors = [safe_cholesky(cov, name=name) for cov, name in ((self.Q, "Q"), (self.R, "R"))]
        # ε on the generator's device (CPU), then to the buffers'; drawn ξ first, as before
        eps = [torch.randn(shape, generator=generator, dtype=self.dtype) for _ in factors]
        return tuple(e.to(L.device) @ L.mT for e, L in zip(eps, factors))


def _isotropic_variance(cov: Tensor, name: str) -> float:
    """``v`` of ``cov = v·I`` (``ValueError`` naming ``name`` otherwise)."""
    v = cov[0, 0]
    if not torch.equal(cov, v * torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)):
        raise ValueError(f"{name} is not a multiple of I: read the buffer {name} itself")
    return float(v)


class SecureController:
    """The LFC controllers as the closed loop's :class:`~difffilter.loop.Controller`:
    ``U_k = −K₁(Z_k − M̂_k)`` (the paper's secure controller, eq. 17 with ``K₂ = 0``;
    ``M̂`` the estimator's attack estimate) or, with ``compensate=False``, the traditional
    ``U_k = −K₁ Z_k``; the plant's input is ``[U_k, ΔP_l]`` (the load rides along:
    :meth:`LFCPlant.model`).

    Args:
        K1: the LQR gain ``[2, 10]``.
        load: the load deviation per run ``[B or 1, 2]``.
        compensate: secure (default) or traditional controller.
    """

    def __init__(self, K1: Tensor, load: Tensor, *, compensate: bool = True):
        self._check_fields(K1, load)
        self.K1, self.load, self.compensate = K1, load, bool(compensate)

    @staticmethod
    def _check_fields(K1, load, runs: torch.Size | None = None) -> None:
        """``K1 [2, 10]`` floating and ``load [2]``, ``[1, 2]`` or ``[B, 2]`` (``B`` the
        loop's ``runs`` where known): a load ``[1]`` had been applied to both areas (a
        review; lfc_loop refuses it by name)."""
        if (
            not isinstance(K1, Tensor)
            or not K1.is_floating_point()
            or K1.shape != (NUM_AREAS, STATE_DIM)
        ):  # (torch's expand/matmul at the first input had named neither: an LFC trial)
            got = f"{tuple(K1.shape)} {K1.dtype}" if isinstance(K1, Tensor) else type(K1).__name__
            raise ValueError(
                f"K1 must be a floating tensor [{NUM_AREAS}, {STATE_DIM}] (the LQR gain, "
                f"lqr_gain(plant)); got {got}"
            )
        real = isinstance(load, Tensor) and not (load.dtype == torch.bool or load.is_complex())
        if runs is None:  # when built: [2] or [any runs, 2]
            fits = real and load.shape[-1:] == (NUM_AREAS,) and load.dim() in (1, 2)
        else:
            fits = real and tuple(load.shape) in ((NUM_AREAS,), (1, NUM_AREAS),
                                                  (*runs, NUM_AREAS))  # fmt: skip
        if not fits:
            got = tuple(load.shape) if isinstance(load, Tensor) else type(load).__name__
            per_run = "[B, 2]" if runs is None else f"[{', '.join(map(str, runs))}, 2]"
            raise ValueError(f"load must be a real tensor [2] or [1, 2] (one for every run) "
                             f"or {per_run} (one per run); got {got}")  # fmt: skip

    def check(self, batch_shape, dtype, device) -> None:
        """``K1`` and ``load`` as the constructor checks them, the load for the loop's runs
        (a loop resumed after either was assigned checks them again:
        :class:`~difffilter.loop.Controller`)."""
        self._check_fields(self.K1, self.load, torch.Size(batch_shape))

    def init(self, batch_shape, dtype, device) -> Tensor:
        self.check(batch_shape, dtype, device)
        u = torch.zeros(tuple(batch_shape) + (self.K1.shape[0],), dtype=dtype, device=device)
        return torch.cat([u, self.load.to(dtype).expand(u.shape)], -1)

    def __call__(self, k: int, y: Tensor, out) -> Tensor:
        attack = None if out is None else out.attack
        feedback = y - attack if self.compensate and attack is not None else y
        # U = −(Z·K₁ᵀ), K₁ read at every step: a K1 assigned (or written) mid-run is
        # followed (the gain made once when built had kept the old one, while Watermarked
        # read the new: a closed-loop trial); bit for bit Z·(−K₁ᵀ), negation being exact
        u = (feedback @ self.K1.T.to(feedback.dtype)).neg_()
        return torch.cat([u, self.load.to(u.dtype).expand(u.shape)], -1)


class Watermarked:
    """A controller whose control input carries a physical watermark (Mo & Sinopoli 2009):
    ``U_k + ΔU_k``, ``ΔU_k ~ N(0, diag(std²))`` i.i.d. from ``generator``, on the first
    ``len(std)`` entries of the input (the control; the load that rides along gets none).

    The loop hands what was sent to the plant and to the estimator alike, so the estimator
    knows the watermark; a replayed measurement does not carry its effect, and the
    innovations show it. The price is the control cost the noise adds."""

    def __init__(self, inner, std: Tensor, generator: torch.Generator):
        self._check_fields(std, generator)
        self.inner, self.std, self.generator = inner, std, generator

    @staticmethod
    def _check_fields(std, generator) -> None:
        if not isinstance(std, Tensor) or std.dim() != 1 or not bool((std >= 0).all()):
            raise ValueError(f"std must be a tensor [du] of non-negative numbers; got {std!r}")
        if not isinstance(generator, torch.Generator):
            # (None drew from torch's global stream, two identical loops marked apart; 5
            # failed at the first step on torch's "invalid combination of arguments")
            raise ValueError(
                f"generator must be a torch.Generator (the watermark's draws); got {generator!r}"
            )

    def check(self, batch_shape, dtype, device, controls: int | None = None) -> None:
        """``std`` and ``generator`` as the constructor checks them, ``std`` no longer than
        the control inputs (``controls``; the inner controller's ``K1`` rows where it has
        one), and the inner controller's own checks: at ``init``, and when a loop resumes
        (a ``std`` of four entries assigned between chunks had marked the LFC loads)."""
        self._check_fields(self.std, self.generator)
        inner_check = getattr(self.inner, "check", None)
        if callable(inner_check):
            inner_check(batch_shape, dtype, device)
        # the control entries alone: an LFC controller's input ends with the loads, which
        # the observer's model leaves out (3 or 4 entries had marked them, a watermark the
        # observer does not know: a red-team trial)
        gain = getattr(self.inner, "K1", None)
        controls = gain.shape[0] if isinstance(gain, Tensor) else controls
        if controls is not None and self.std.shape[0] > controls:
            # (more than the input: a raw torch size error)
            raise ValueError(
                f"Watermarked: std has {self.std.shape[0]} entries and the controller "
                f"{controls} control inputs: one per control input marked (the first "
                "len(std) entries; the loads that ride along get none)"
            )

    def init(self, batch_shape, dtype, device) -> Tensor:
        u = self.inner.init(batch_shape, dtype, device)
        self.check(batch_shape, dtype, device, controls=u.shape[-1])
        return u

    def __call__(self, k: int, y: Tensor, out) -> Tensor:
        u = self.inner(k, y, out)
        n = self.std.shape[0]
        if n > u.shape[-1]:  # (a std assigned later, of an inner controller without K1 that
            # check() cannot count: a raw torch size error, a review)
            raise ValueError(
                f"Watermarked: std has {n} entries and the controller's input {u.shape[-1]}: "
                "one per control input marked (the first len(std) entries)"
            )
        noise = torch.randn(*u.shape[:-1], n, generator=self.generator, dtype=u.dtype,
                            device=u.device)  # fmt: skip
        return torch.cat([u[..., :n] + noise * self.std.to(u.dtype), u[..., n:]], -1)


# -- attacks ---------------------------------------------------------------------------------


def _between(t: Tensor, lo: float, hi: float) -> Tensor:
    """Indicator of the closed interval ``lo ≤ t ≤ hi`` (with the sample-time tolerance)."""
    return ((t >= lo - _T_EPS) & (t <= hi + _T_EPS)).to(t.dtype)


def sawtooth_pulse_train(
    t: Tensor,
    *,
    width: float = 0.2,
    period: float = 0.5,
    skew: float = 1.0,
    amplitude: float = 1.0,
    start: float = 0.0,
    stop: float = 10.0,
) -> Tensor:
    """MATLAB ``pulstran(t, start:period:stop, 'tripuls', width, skew)`` times ``amplitude``.

    ``tripuls(τ, w, s)`` is ``(τ + w/2)/(w/2·(1+s))`` on ``−w/2 ≤ τ < s·w/2`` and
    ``(w/2 − τ)/(w/2·(1−s))`` on ``s·w/2 ≤ τ < w/2``, else 0. With ``s = 1`` each pulse is a
    ramp from 0 to (just under) ``amplitude`` over ``width`` seconds, centred on its delay,
    followed by an instant drop. Shape: ``t [T]`` → ``[T]``.
    """
    if not (0 < width < math.inf and 0 < period < math.inf and -1.0 <= skew <= 1.0):
        raise ValueError(
            "width and period must be positive and finite and skew must lie in [-1, 1]"
        )
    if not (math.isfinite(start) and math.isfinite(stop) and stop >= start):
        raise ValueError(
            f"start and stop must be finite with stop >= start; got {start!r}, {stop!r}"
        )
    if not isinstance(t, Tensor) or t.dim() != 1:  # (torch's broadcasting error had named no t)
        got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
        raise ValueError(f"t must be a 1-D tensor of sample times [T]; got {got}")
    n_pulses = int(math.floor((stop - start) / period + 1e-9)) + 1
    delays = start + period * torch.arange(n_pulses, dtype=t.dtype)
    tau = t[:, None] - delays[None, :]
    half = width / 2.0
    peak = skew * half
    rise = (tau >= -half - _T_EPS) & (tau < peak - _T_EPS)
    fall = (tau >= peak - _T_EPS) & (tau < half - _T_EPS)
    out = torch.zeros_like(tau)
    # from the pulse's start on the time grid: exactly 0 there (k·dt − d + w/2 was ±1e-16,
    # a ramp value of 1e-15 that counted the step as attacked, 16 steps a run on lfc_sawtooth)
    lead = tau + half
    lead = torch.where(lead.abs() <= _T_EPS, torch.zeros_like(lead), lead)
    out = torch.where(rise, lead / (half * (1.0 + skew)), out)
    if skew < 1.0:
        out = torch.where(fall, (half - tau) / (half * (1.0 - skew)), out)
    return amplitude * out.clamp(0.0, 1.0).sum(dim=1)


class LFCAttack(Choice):
    """The attack of an LFC scenario: the paper's signals (eqs 44–47), none, or random
    attacks drawn per run (:func:`random_attacks`: the training distribution)."""

    STEP = "step"
    SINE = "sine"
    SIMULTANEOUS = "simultaneous"
    SAWTOOTH = "sawtooth"
    NONE = "none"
    RANDOM = "random"


def scenario_attack(kind: LFCAttack | str, t: Tensor) -> Tensor:
    """Attack ``α [T, 10]`` of scenario ``kind`` at the sample times ``t [T]`` (seconds).

    Channel indices are zero-based (the paper's state 3 of area 1 is channel 2, state 3 of
    area 2, the global state 8, is channel 7).

    * ``step`` (I, eq. 44): 0.4 on 3 ≤ t ≤ 5, 0.9 on 7 ≤ t ≤ 8 (the gap 5 < t < 7 is
      unspecified; [DEF] 0).
    * ``sine`` (II, eq. 45): 1.5·sin(10t) for t ≥ 3.
    * ``simultaneous`` (III, eqs 46–47): channel 2: 0.6 on [0.1, 5], 1.2 on [7, 8];
      channel 7: 0.9·sin(10t) on [0.1, 5], 0.1 on [7, 8]; 0 elsewhere.
    * ``sawtooth`` (IV): ``pulstran(t, 0:0.5:10, 'tripuls', 0.2, 1)`` on channel 2
      ([DEF] amplitude 1, channel α^{1,3}, the whole 0–10 s).
    * ``none``: no attack.
    """
    kind = LFCAttack(kind)
    if kind is LFCAttack.RANDOM:
        raise ValueError("kind RANDOM is drawn per run by random_attacks, not a fixed signal")
    if t.dim() != 1 or not t.is_floating_point():  # (integer times truncated every value)
        raise ValueError(f"t must be a 1-D floating tensor of sample times [T]; got "
                         f"{tuple(t.shape)} {t.dtype}")  # fmt: skip
    alpha = torch.zeros(t.shape[0], STATE_DIM, dtype=t.dtype)
    if kind is LFCAttack.STEP:
        alpha[:, 2] = 0.4 * _between(t, 3.0, 5.0) + 0.9 * _between(t, 7.0, 8.0)
    elif kind is LFCAttack.SINE:
        alpha[:, 2] = 1.5 * torch.sin(10.0 * t) * (t >= 3.0 - _T_EPS).to(t.dtype)
    elif kind is LFCAttack.SIMULTANEOUS:
        first, second = _between(t, 0.1, 5.0), _between(t, 7.0, 8.0)
        alpha[:, 2] = 0.6 * first + 1.2 * second
        alpha[:, 7] = 0.9 * torch.sin(10.0 * t) * first + 0.1 * second
    elif kind is LFCAttack.SAWTOOTH:
        alpha[:, 2] = sawtooth_pulse_train(t)
    return alpha


# Angular frequencies the random sinusoids avoid, so that the training and validation
# distribution never contains scenario II/III's 10 rad/s carrier (rad/s).
EXCLUDED_OMEGA = (9.0, 11.0)


def random_attacks(
    num_runs: int,
    steps: int,
    dt: float,
    *,
    generator: torch.Generator,
    channels: tuple[int, ...] | None = None,
    max_events: int = 3,
    min_events: int = 0,
    amplitude: tuple[float, float] = (0.1, 2.0),
    dtype=torch.float64,
) -> Tensor:
    """Random FDI attacks ``α [B, T, 10]`` for training and validation.

    Each run holds ``U{min_events … max_events}`` events; each event picks a channel (from
    ``channels``, default all ten), an onset ``U[0, 0.9·T·Δt]``, a duration ``U[0.3, 6]`` s, a
    signed amplitude ``±U[amplitude]`` and one of four shapes:

    * step (a box from onset to onset + duration),
    * ramp (linear rise over ``U[0.1, 3]`` s, then held until the event ends),
    * sinusoid ``A·sin(ω(t − onset) + φ)``, ``ω ~ U[2, 40]`` rad/s outside ``EXCLUDED_OMEGA``,
    * rectangular pulse train (period ``U[0.2, 2]`` s, duty ``U[0.1, 0.9]``).

    The test signals of scenarios I–IV are never drawn: the sinusoids avoid 10 rad/s and
    there is no periodic sawtooth; the remaining shapes have continuous random parameters.
    Events on the same channel add. All draws come from ``generator``.
    """
    chans = _check_random_attacks(num_runs, steps, generator, channels, min_events, max_events,
                                  amplitude)  # fmt: skip
    check_finite_number(dt, "dt", positive=True)  # (NaN made every entry NaN; 0 every onset 0)
    lo_amp, hi_amp = amplitude
    g = generator
    B, E = num_runs, max(max_events, 1)

    def u(*shape):
        return torch.rand(*shape, generator=g, dtype=dtype)

    t = dt * torch.arange(1, steps + 1, dtype=dtype)  # [T]
    horizon = steps * dt
    n_events = torch.randint(min_events, max_events + 1, (B, 1), generator=g)
    active = (torch.arange(E)[None, :] < n_events).to(dtype)  # [B, E]
    channel = chans[torch.randint(0, chans.numel(), (B, E), generator=g)]
    kind = torch.randint(0, 4, (B, E), generator=g)
    onset = 0.9 * horizon * u(B, E)
    duration = 0.3 + 5.7 * u(B, E)
    sign = torch.where(u(B, E) < 0.5, -1.0, 1.0).to(dtype)
    amp = sign * (lo_amp + (hi_amp - lo_amp) * u(B, E))
    rise = 0.1 + 2.9 * u(B, E)
    # ω uniform on [2, 40] minus the excluded band: draw on the shortened interval, then
    # shift the part above the band's lower edge past it.
    width = EXCLUDED_OMEGA[1] - EXCLUDED_OMEGA[0]
    omega = 2.0 + (38.0 - width) * u(B, E)
    omega = torch.where(omega >= EXCLUDED_OMEGA[0], omega + width, omega)
    phase = 2.0 * math.pi * u(B, E)
    period = 0.2 + 1.8 * u(B, E)
    duty = 0.1 + 0.8 * u(B, E)

    tau = t[None, None, :] - onset[..., None]  # [B, E, T] time since onset
    window = ((tau >= 0) & (tau <= duration[..., None])).to(dtype)
    shapes = torch.stack(
        [
            torch.ones_like(tau),
            (tau / rise[..., None]).clamp(0.0, 1.0),
            torch.sin(omega[..., None] * tau + phase[..., None]),
            (torch.remainder(tau, period[..., None]) < duty[..., None] * period[..., None]).to(
                dtype
            ),
        ],
        dim=0,
    )  # [4, B, E, T]
    shape = shapes.gather(0, kind[None, ..., None].expand(1, B, E, steps))[0]
    signal = amp[..., None] * shape * window * active[..., None]  # [B, E, T]
    one_hot = torch.nn.functional.one_hot(channel, STATE_DIM).to(dtype)  # [B, E, 10]
    return torch.einsum("bet,bec->btc", signal, one_hot)


def _check_random_attacks(num_runs, steps, generator, channels, min_events, max_events,
                          amplitude) -> Tensor:  # fmt: skip
    """The arguments of :func:`random_attacks` checked; the channel indices as a tensor."""
    if not isinstance(generator, torch.Generator):
        raise ValueError("generator must be a torch.Generator (every draw is seeded)")
    # (a float count had failed in torch's randint, naming neither: an LFC trial)
    check_integer(num_runs, "num_runs", 1)
    check_integer(steps, "steps", 1)
    check_integer(min_events, "min_events")
    check_integer(max_events, "max_events")
    if not 0 <= min_events <= max_events:
        raise ValueError(f"need 0 <= min_events <= max_events; got {min_events}, {max_events}")
    chans = torch.arange(STATE_DIM) if channels is None else torch.as_tensor(channels)
    if chans.numel() == 0 or bool(((chans < 0) | (chans >= STATE_DIM)).any()):
        raise ValueError(f"channels must be indices in 0..{STATE_DIM - 1}; got {channels!r}")
    if not 0 <= amplitude[0] <= amplitude[1] < math.inf:  # (inf had made every entry NaN)
        raise ValueError(f"amplitude must be (low, high) with 0 <= low <= high < inf; got "
                         f"{amplitude!r}")  # fmt: skip
    if chans.is_floating_point() or chans.dtype == torch.bool:
        raise ValueError(
            f"channels must be integer indices in 0..{STATE_DIM - 1}; got {channels!r}"
        )
    return chans


# -- the closed loop ---------------------------------------------------------------------------


def lqr_gain(plant: LFCPlant) -> Tensor:
    """The LQR gain ``K₁ [2, 10]`` of the plant (the reduced CARE, [DEF] ``Q = I, R = I``)."""
    from difffilter.control import lqr

    K1, _ = lqr(plant.A.double(), plant.B.double())
    return K1.to(plant.dtype)


def check_no_attack_on_loads(attack) -> None:
    """Raise where ``attack`` (a covert attack's signal too) acts on the loads: entries
    2 and 3 of the LFC input ``[U₁, U₂, ΔP_l1, ΔP_l2]`` (``entries`` left out: all four).
    The loads are the plant's, carried by no network; and the observers' model, which a
    covert attacker runs as the defender's, has no load columns (``B = [B_d, 0]``), so a
    covert attack there concealed nothing: the received measurement 0.017 off the
    attack-free one, against a sensor noise of 0.01 (a trial). An attack of one's own,
    whose entries are not declared, is not checked."""
    signal = attack.signal if isinstance(attack, Covert) else attack
    if not isinstance(signal, Shaped) or Channel(signal.channel) is not Channel.ACTUATOR:
        return
    entries = signal.entries
    if entries is None or any(i >= NUM_AREAS for i in entries):
        raise ValueError(
            "an actuator attack on the LFC acts on the control inputs U1, U2 (entries: [0], "
            "[1] or [0, 1]): the input's entries 2 and 3 are the loads, which no network "
            f"carries and the observers' model does not hold; got entries {entries!r}"
            + (" (all four)" if entries is None else "")
        )


def lfc_loop(
    plant: LFCPlant,
    estimator,
    xi: Tensor,
    theta: Tensor,
    load: Tensor,
    *,
    attack=None,
    compensate: bool = True,
    generator=None,
    K1: Tensor | None = None,
    steps: int | None = None,
    state=None,
    progress=None,
    watermark=None,
    attack_generator: torch.Generator | None = None,
    forks: dict | None = None,
    fork=None,
) -> LoopResult:
    """One LFC closed loop (eq. 42 with the secure or traditional controller) around
    ``estimator`` on the observers' model, replaying the draws ``xi, theta [B, T, 10]``
    and the load ``[B or 1, 2]`` (:func:`difffilter.loop.closed_loop`): ``X_0 = 0`` [DEF],
    ``Z_k = X_k + α_k + θ_k``. ``steps``/``state``: run a chunk of the loop and resume it;
    ``progress``: called after every step; ``watermark``: a :class:`Watermarked` wrapper
    factory ``controller → controller`` (``None``: none); ``attack_generator``: the
    attack's own draws (a random walk's steps, the runs a ``share`` attacks); ``forks``,
    ``fork``: keep :class:`~difffilter.loop.LoopFork` s, continue one (a resumed loop runs
    to the end of the draws unless ``steps``)."""
    check_no_attack_on_loads(attack)
    B, T, _ = xi.shape
    if not isinstance(load, Tensor) or tuple(load.shape) not in ((2,), (1, 2), (B, 2)):
        got = tuple(load.shape) if isinstance(load, Tensor) else type(load).__name__
        raise ValueError(f"load must be a tensor [2] or [1, 2] (one for every run) or [{B}, 2] "
                         f"(one per run of xi); got {got}")  # fmt: skip
    K1 = lqr_gain(plant) if K1 is None else K1
    x0 = torch.zeros(B, STATE_DIM, dtype=xi.dtype, device=xi.device)
    controller = SecureController(K1, load, compensate=compensate)
    if watermark is not None:
        controller = watermark(controller)
    if steps is None:  # to the end of the draws from where the loop resumes
        steps = T - (fork.state.k if fork is not None else state.k if state is not None else 0)
    return closed_loop(
        plant.model(), steps, noise=ReplayedNoise(xi, theta), x0=x0,
        estimator=estimator, model=plant.model(knows_load=False),
        controller=controller, attack=attack, attack_generator=attack_generator,
        generator=generator, state=state, horizon=T, progress=progress, forks=forks, fork=fork,
    )  # fmt: skip


# -- scenarios -------------------------------------------------------------------------------

PAPER = "Sargolzaei, Yazdani, Abbaspour, Crane, Dixon, IEEE TII 16(1), 2020"

DEFAULT_NOTES = (
    "[DEF] plant parameters: Zhang et al. TPS 2013 two-area set (TSG 2016 Table I unavailable)",
    "[DEF] noise: D = I, Xi = 1e-6 I per 10 ms step (1e-7 per 1 ms step: same intensity), "
    "Theta = 1e-4 I per sample",
    "[DEF] load: 0.01 p.u. step in area 1 at t = 0 (paper: stochastic load of its ref. [39]); "
    "unknown to the observers",
    "[DEF] LQR weights Q = I10, R = I2 on the reduced 9-state controllable model",
    "[DEF] Kalman observer Sigma(0) = 1e-2 I, X_hat(0) = X(0) = 0",
    "[DEF] NN sizes a = b = 3, 10 tanh units; initial weights s*U[0,1] (s chosen on validation)",
)

# Table I (attack-estimate RMSE) and Table II (state-5 RMSE) of the paper.
PAPER_TABLES = {
    "step": {
        "traditional_ad": 0.225363,
        "proposed_ad": 0.068807,
        "state5_traditional_ctrl": 0.066127,
        "state5_secure_ctrl": 0.064231,
    },
    "sine": {
        "traditional_ad": 0.405883,
        "proposed_ad": 0.186432,
        "state5_traditional_ctrl": 0.064558,
        "state5_secure_ctrl": 0.064236,
    },
    "simultaneous": {
        "traditional_ad": 0.549188,
        "proposed_ad": 0.133867,
        "state5_traditional_ctrl": 0.076106,
        "state5_secure_ctrl": 0.064159,
    },
    "sawtooth": {
        "traditional_ad": 0.232860,
        "proposed_ad": 0.221108,
        "state5_traditional_ctrl": 0.064502,
        "state5_secure_ctrl": 0.064219,
    },
}


# The estimators every LFC scenario runs (registered in difffilter.models.lfc_estimators).
LFC_ESTIMATORS = (
    "kf_attack_free",
    "uncompensated",
    "kf_nn_ekf",
    "traditional_ad",
    "kf_nn_grad",
    "kf_nn_grad_ekf",
    "kf_nn_ekf_qrho0",
    "traditional_ad_robust",
    "traditional_ad_diagonal",
    "chi_square_kf",
    "cusum_kf",
)


@dataclass(frozen=True)
class LFCScenario(Scenario):
    """An LFC attack scenario: plant sampling, horizon, load and attack, in closed loop.

    Every estimator runs in its own closed loop (:meth:`loop`: the plant, the estimator,
    the secure controller) on the scenario's draws (:meth:`exogenous`: noise, load and, for
    random attacks, the attack), so that every estimator sees the same random numbers.

    Attributes:
        attack: :class:`LFCAttack`: one of the paper's signals (eqs 44–47), none, or
            random (:func:`random_attacks`, one draw per run: the training and validation
            distribution).
        dt: sampling time (s); ``duration``: horizon (s), so ``steps = duration / dt``.
        load: constant load deviation per area (p.u.), applied from t = 0. [DEF]
        load_range: for training: a load per run ``~ U[−range/2, range/2]`` per area
            instead of ``load`` (``None``: the fixed load).
        random_channels, max_events, amplitude: the random attacks' channels (``None``: all
            ten), events per run and amplitude range (:func:`random_attacks`).
        attacked_channels: zero-based channels the attack targets (metric channels, eq. 43).
        paper_table: the paper's Table I/II entries for this scenario (``{}`` if none).
    """

    attack: LFCAttack = LFCAttack.NONE
    dt: float = 0.01
    duration: float = 10.0
    load: tuple[float, float] = (0.01, 0.0)
    load_range: float | None = None
    random_channels: tuple[int, ...] | None = None
    max_events: int = 3
    amplitude: tuple[float, float] = (0.1, 2.0)
    attacked_channels: tuple[int, ...] = (2,)
    paper_table: dict = field(default_factory=dict, hash=False, compare=False)
    runs: int = 20
    steps: int = 0  # derived: duration / dt
    false_alarm_rate: float = 0.01  # [DEF] of the chi-square and CUSUM detectors
    checkpoint: str | None = "checkpoints/lfc_nn_grad.ckpt"  # kf_nn_grad without --ckpt
    single_thread: bool = False  # the EKF over the weights: [B, P, P] covariances
    estimators: tuple[str, ...] = LFC_ESTIMATORS

    closed_loop = True
    state_unit: ClassVar[str] = "p.u. (Δf in Hz)"  # the paper's per-unit system
    attack_unit: ClassVar[str] = "p.u. (Δf in Hz)"  # on the measured states
    attack_entry_names: ClassVar[tuple[str, ...]] = STATE_NAMES  # C = I: every state measured

    def __post_init__(self):
        object.__setattr__(self, "attack", LFCAttack(self.attack))
        if not (0 < self.dt < math.inf and self.dt <= self.duration < math.inf):
            raise ValueError(f"dt must be positive and duration >= dt, both finite; got dt = "
                             f"{self.dt!r}, duration = {self.duration!r}")  # fmt: skip
        object.__setattr__(self, "steps", int(round(self.duration / self.dt)))
        check_integer(self.max_events, "max_events")  # (else refused only at simulate)
        if self.load_range is not None:  # (a negative range had drawn mirrored loads)
            object.__setattr__(self, "load_range", check_finite_number(
                self.load_range, "load_range (the width of U[-range/2, range/2])",
                nonnegative=True))  # fmt: skip
        _check_attacked_channels(self.attacked_channels, self.attack)

    def with_steps(self, steps: int) -> LFCScenario:
        return dataclasses.replace(self, duration=steps * self.dt)

    def with_threat(self, attack) -> LFCScenario:
        """As :meth:`Scenario.with_threat`; an actuator attack on the loads is refused here,
        before a study (:func:`check_no_attack_on_loads`)."""
        if attack is not OWN_ATTACK:
            check_no_attack_on_loads(attack)
        return super().with_threat(attack)

    def times(self, dtype=torch.float64) -> Tensor:
        """Sample times ``t_k = kΔt``, ``k = 1 … T`` → ``[T]``."""
        return self.dt * torch.arange(1, self.steps + 1, dtype=dtype)

    def attack_signal(self, dtype=torch.float64) -> Tensor:
        """The scenario's attack ``α [T, 10]`` (one of the paper's signals)."""
        return scenario_attack(self.attack, self.times(dtype))

    def system(self, dtype: torch.dtype = torch.float64, device=None):
        """The observers' model (:meth:`LFCPlant.model` without the load)."""
        return self._on_device(LFCPlant(dt=self.dt, dtype=dtype).model(knows_load=False), device)

    def attack_model(self):
        """The scenario's attack: the known signal ``α [T, 10]`` on the sensors (``None``
        without one, and for random attacks, whose per-run draws are in :meth:`exogenous`)."""
        fixed = self.attack not in (LFCAttack.NONE, LFCAttack.RANDOM)
        return Signal(self.attack_signal()) if fixed else None

    def feedback_gain(self, dtype=torch.float64) -> Tensor:
        """The LQR gain ``K₁ [2, 10]`` of ``U = −K₁(Z − M̂)``."""
        return lqr_gain(LFCPlant(dt=self.dt, dtype=dtype))

    def exogenous(self, runs, generators, *, dtype=torch.float64) -> dict:
        """The draws every loop replays: ``xi, theta [B, T, 10]`` (``generators["plant"]``),
        the load ``[B or 1, 2]`` and, for random attacks, ``attack [B, T, 10]``
        (``generators["attack"]``, if given); with an ``"attack"`` generator,
        ``attack_seed [B]``: the seed of the attack's own draws (one number, repeated per
        run so that the draws slice by runs), so that every estimator's loop meets the
        same random attack."""
        plant = LFCPlant(dt=self.dt, dtype=dtype)
        xi, theta = plant.sample_noise(runs, self.steps, generators["plant"])
        load = torch.tensor(self.load, dtype=dtype)[None]
        if self.load_range is not None:
            u = torch.rand(runs, NUM_AREAS, generator=generators["plant"], dtype=dtype)
            load = (u - 0.5) * self.load_range
        draws = {"xi": xi, "theta": theta, "load": load}
        if self.attack is LFCAttack.RANDOM and generators.get("attack") is not None:
            # (attack-free runs, e.g. a detector's calibration, draw no attack)
            draws["attack"] = random_attacks(
                runs, self.steps, self.dt, generator=generators["attack"],
                channels=self.random_channels, max_events=self.max_events,
                amplitude=self.amplitude, dtype=dtype,
            )  # fmt: skip
        if generators.get("attack") is not None:
            seed = torch.randint(2**62, (1,), generator=generators["attack"])
            draws["attack_seed"] = seed.expand(runs)
        return draws

    def loop(self, estimator, draws, *, generator=None, steps=None, state=None, compensate=True,
             attack=OWN_ATTACK, progress=None, forks=None, fork=None):  # fmt: skip
        """``estimator`` in its own closed loop on ``draws`` (:func:`lfc_loop`): the secure
        controller (``compensate=False``: the traditional one), the scenario's attack (or
        ``attack``: another one, ``None`` for none); ``forks``/``fork`` as in
        :func:`~difffilter.loop.closed_loop`."""
        attack, attack_generator = self._attack_of(draws, attack)
        plant = LFCPlant(dt=self.dt, dtype=draws["xi"].dtype).to(draws["xi"].device)
        return lfc_loop(plant, estimator, draws["xi"], draws["theta"], draws["load"],
                        attack=attack, compensate=compensate, generator=generator, steps=steps,
                        state=state, progress=progress, attack_generator=attack_generator,
                        forks=forks, fork=fork)  # fmt: skip

    def simulate(self, runs, generators, *, dtype=None, attack=OWN_ATTACK, model=None):
        """The traditional closed loop ``U = −K₁Z`` with its Kalman observer (``attack=None``:
        attack-free). ``info`` carries the exogenous draws (``xi, theta [B, T, 10]``,
        ``load``) that every estimator's own closed loop replays (common random numbers).
        ``us[:, t]`` is the input applied before ``x_{t+1}`` (control and load)."""
        self._check_no_losses()
        dtype = simulation_dtype(dtype, model)
        draws = self.exogenous(runs, generators, dtype=dtype)
        loop = self.loop(self._shared_observer(draws, attack), draws, compensate=False,
                         attack=attack)  # fmt: skip
        info = {**loop.trajectories.info, **draws}
        return loop.trajectories._replace(info=info)

    def _check_no_losses(self) -> None:
        """The LFC loops deliver every measurement and every input (the paper's network):
        a subclass's ``schedule()`` or ``input_loss_schedule()`` is refused, where it had been
        ignored without a word (a lossy LFC scenario ran 100 % received; a registry trial)."""
        if not isinstance(self.schedule(), AllSensors) or self.input_loss_schedule() is not None:
            raise ValueError(
                f"scenario {self.name!r}: the LFC loops take every measurement and input; a "
                "schedule() or input_loss_schedule() of losses is not supported on them"
            )

    def _shared_observer(self, draws, attack):
        """The estimator of :meth:`simulate`'s loop: a Kalman filter, χ²-gated at the
        scenario's false-alarm rate where the attack reads the estimator's output (so that
        an adaptive attack finds a score and an alarm there too; the traditional controller
        reads the measurement, not the estimate, so the loop's truth does not depend on it).
        Every estimator that an adaptive attack is judged against runs in a loop of its own
        (:func:`~difffilter.models.generic_estimators.meets_adaptive_attack`)."""
        if not getattr(self._attack_of(draws, attack)[0], "reads_view", False):
            return KalmanFilter()
        detector = ChiSquareDetector(self.system().dim_y, self.false_alarm_rate)
        return GatedFilter(detector, KalmanFilter())

    def paper_numbers(self) -> dict:
        return dict(self.paper_table)

    def _attack_of(self, draws, attack=OWN_ATTACK):
        """``(attack, its generator)`` of a loop on ``draws`` (:meth:`loop`'s ``attack``)."""
        if attack is OWN_ATTACK and self.threat is not OWN_ATTACK:
            attack = self.threat
        elif attack is OWN_ATTACK:
            attack = Signal(draws["attack"]) if "attack" in draws else self.attack_model()
        generator = None
        if "attack_seed" in draws:  # the same draws in every estimator's loop
            seed = int(draws["attack_seed"].reshape(-1)[0])
            generator = torch.Generator(device=draws["xi"].device).manual_seed(seed)
        return attack, generator

    def attack_onset(self, draws) -> int | None:
        """The steps before the attack of a loop on ``draws`` (:meth:`loop`'s, this scenario's
        own or threat) first acts in any run: its table, drawn as the loop draws it. ``None``
        for no attack, one that never acts, or one that reads the loop (its onset is not
        known beforehand: a replay, a covert attack)."""
        attack, generator = self._attack_of(draws)
        if not isinstance(attack, TabulatedAttack) or getattr(attack, "conceals", False):
            return None
        xi = draws["xi"]
        model = LFCPlant(dt=self.dt, dtype=xi.dtype).model()
        dim = attack_dim(model, attack.channel)
        _, flags = attack.init(xi.shape[:1], xi.shape[1], dim, generator, dtype=xi.dtype,
                               device=xi.device)  # fmt: skip
        acting = flags.reshape(*flags.shape[:2], -1).any(-1).any(0).nonzero()
        return int(acting[0]) if len(acting) else None

    def attack_free_key(self) -> tuple:
        """The built-in LFC scenarios differ in their attack only: without it, the same
        loops. The detectors' rate and the default checkpoint are part of the key (a
        variant of its own rate or network had been handed another scenario's calibration,
        a CUSUM's τ of 16.7 where its own is 12.6: a trial)."""
        return ("lfc", self.dt, self.steps, self.load, self.load_range, self.false_alarm_rate,
                self.checkpoint)  # fmt: skip


#: The channels the paper's signals attack (eqs 44–47: state 3 of area 1; scenario III also
#: state 8, of area 2), where eq. 43 is scored.
PAPER_ATTACK_CHANNELS = {LFCAttack.STEP: (2,), LFCAttack.SINE: (2,),
                         LFCAttack.SIMULTANEOUS: (2, 7), LFCAttack.SAWTOOTH: (2,)}  # fmt: skip


def _check_attacked_channels(channels, attack: LFCAttack) -> None:
    """``attacked_channels``: distinct channels ``0 … 9``, those of the paper's signal where
    the attack is one (eq. 43 had been scored on channel 2 alone of scenario III's two, 0.57
    where 1.02 is its zero estimate's, on a doubled channel twice, and on ``-1`` as ace_int_2:
    a trial)."""
    given = tuple(channels) if isinstance(channels, (tuple, list)) else None
    if (given is None or not given or len(set(given)) != len(given)
            or any(isinstance(c, bool) or not isinstance(c, int) or not 0 <= c < STATE_DIM
                   for c in given)):  # fmt: skip
        raise ValueError(f"attacked_channels must be distinct channels 0 … {STATE_DIM - 1} (a "
                         f"tuple of integers); got {channels!r}")  # fmt: skip
    signal = PAPER_ATTACK_CHANNELS.get(attack)
    if signal is not None and tuple(sorted(given)) != signal:
        raise ValueError(f"attacked_channels of the paper's {attack.value} attack are {signal} "
                         f"(the channels its signal attacks, where eq. 43 is scored); got {given}")  # fmt: skip


def _lfc(name, attack, description, channels=(2,), dt=0.01, table_key=None, headline=True):
    return register(
        LFCScenario(
            name=name,
            family="lfc",
            description=description,
            paper=PAPER,
            notes=DEFAULT_NOTES,
            attack=attack,
            dt=dt,
            attacked_channels=channels,
            paper_table=dict(PAPER_TABLES.get(table_key or attack, {})),
            headline=headline,
        )
    )


_lfc("lfc_step", "step", "LFC scenario I: steps 0.4 (3-5 s) and 0.9 (7-8 s) on dP_tu of area 1")
_lfc("lfc_sine", "sine", "LFC scenario II: 1.5 sin(10t) from t = 3 s on dP_tu of area 1")
_lfc(
    "lfc_simultaneous",
    "simultaneous",
    "LFC scenario III: steps on state 3 and a sinusoid then step on state 8 (both areas)",
    channels=(2, 7),
)
_lfc("lfc_sawtooth", "sawtooth", "LFC scenario IV: 2 Hz sawtooth pulse train on dP_tu of area 1")
_lfc(
    "lfc_sine_1ms",
    "sine",
    "LFC scenario II sampled at 1 ms (the paper's Fig. 7)",
    dt=0.001,
    table_key="none",
    headline=False,
)

# The training and validation distribution of the learned estimator (never the test signals:
# the random sinusoids avoid 10 rad/s and there is no periodic sawtooth).
register(
    LFCScenario(
        name="lfc_random_attacks",
        family="lfc",
        description="LFC with random attacks (steps, ramps, sinusoids, pulse trains) on all "
        "ten channels and a random load per run: the learned estimator's training data",
        paper=PAPER,
        # (its load is drawn, not DEFAULT_NOTES' fixed step: a trial of the variants)
        notes=tuple(
            "[DEF] load: a load per run and area ~ U[-0.01, 0.01] p.u. (load_range 0.02) from "
            "t = 0, unknown to the observers"
            if note.startswith("[DEF] load:")
            else note
            for note in DEFAULT_NOTES
        ),
        attack="random",
        load_range=0.02,
        attacked_channels=tuple(range(STATE_DIM)),
        headline=False,
    )
)
