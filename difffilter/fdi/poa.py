"""Probability-of-attack (PoA) detection on weighted particle sets and its thresholds.

Sadeghzadeh-Nokhodberiz, Meskin & Hasanzadeh, "Modified particle filters for detection
of FDI attacks and state estimation in networked nonlinear systems", IEEE Access 2022.

For a particle set ``{x^i, w^i}`` approximating ``p(x_k | ·)`` and a (possibly attacked)
measurement ``ỹ_k = G x_k + v_k + l_k γ_k``::

    z^i = ỹ_k − G x^i                                   residual samples (eqs 9, 15)
    β_k = Σ_{i : ‖z^i‖ > η_k} w^i                        PoA (eqs 10, 14, 17, 58)
    alarm (l̂_k = 1)  ⇔  β_k > ζ

Thresholds (Theorem 1, Remark 3, Theorem 2)::

    K_k = Q Gᵀ (R + G Q Gᵀ)⁻¹                            gain of the modified proposal (35)
    η_k = ς_k ‖γ‖_min,   ς_k = |σ̄_k − 1|,  σ̄_k the singular value of G K_k nearest to 1   (45)
          (= σ_min(I − G K_k), the bound the proof needs, when G K_k is symmetric PSD)
    ζ   = α (N − 1)/N,   p_l N/(N − 1) ≤ α < 1                                          (46, 53)

so the smallest admissible ``α`` gives ``ζ = p_l``. When ``p_l`` is unknown (Remark 6) it
is replaced by the running fraction of detected attacks (:class:`RunningAttackRate`).

The diagnostic :func:`literal_probability_of_attack` evaluates the Gaussian likelihood
literally in float64 (``(2π)^{−m/2} |R|^{−1/2} exp(−½ rᵀR⁻¹r)``) and normalises in linear
space, as a naive implementation would: for large attacks every density underflows to 0,
the normalised weights are ``0/0 = NaN`` and ``NaN > ζ`` is false, so no alarm is raised.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from .._assignments import note_assignment
from .._checks import (
    broadcast_or_none,
    check_finite_number,
    check_fraction,
    check_integer,
    check_one_model,
    check_positive_definite,
    model_batch_shape,
    real_number,
)
from ..gaussian import kalman_gain
from ..linalg import LOG_2PI, NumericalBreakdown, safe_cholesky

__all__ = [
    "modified_pf_gain",
    "attack_threshold",
    "attack_threshold_factor",
    "InfeasibleThreshold",
    "detection_threshold",
    "probability_of_attack",
    "PoADetector",
    "poa_detector_for",
    "literal_gaussian_density",
    "literal_probability_of_attack",
    "RunningAttackRate",
    "AttackRateState",
]


def _as_matrix(value, name: str, dtype=None) -> Tensor:
    t = torch.as_tensor(value, dtype=dtype if dtype is not None else torch.float64)
    if t.dim() < 2:
        raise ValueError(
            f"{name} must be a matrix of shape [..., m, n]; got shape {tuple(t.shape)}"
        )
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains NaN or Inf values; every entry must be finite")
    return t


def modified_pf_gain(G, Q, R) -> Tensor:
    """Gain of the modified (Kalman-corrected) proposal, eq. (35): ``K = Q Gᵀ (R + G Q Gᵀ)⁻¹``.

    Shapes: ``G [..., dy, dx]``, ``Q [..., dx, dx]``, ``R [..., dy, dy]`` → ``K [..., dx, dy]``.
    ``R + G Q Gᵀ`` is solved by Cholesky (``ValueError`` if not positive definite). Computed
    in ``G``'s dtype, float64 where ``G`` is not a tensor of its own (a float32 ``G`` gives a
    float32 ``K``: cast ``G`` to float64 first for the gain's round-off).
    """
    # in G's own floating dtype: float32 G, Q and R had given a float64 K that eq. (36)'s
    # float32 particles then refused inside torch (an apishapes trial)
    G = _as_matrix(G, "G", G.dtype if isinstance(G, Tensor) and G.is_floating_point() else None)
    Q = _as_matrix(Q, "Q", G.dtype)
    R = _as_matrix(R, "R", G.dtype)
    dy, dx = G.shape[-2:]
    if Q.shape[-2:] != (dx, dx):
        raise ValueError(
            f"Q must have shape [..., {dx}, {dx}] to match G [{dy}, {dx}]; got {tuple(Q.shape)}"
        )
    if R.shape[-2:] != (dy, dy):
        raise ValueError(
            f"R must have shape [..., {dy}, {dy}] to match G [{dy}, {dx}]; got {tuple(R.shape)}"
        )
    # a measurement covariance: a negative or zero R (a sign typo in a design R) had given a
    # gain and an η of its own without a word (R + G Q Gᵀ stayed positive definite)
    check_positive_definite(R, "R")
    cross = Q @ G.transpose(-1, -2)  # [dx, dy]
    return kalman_gain(cross, R + G @ cross)[0]


_THRESHOLD_RULES = ("paper", "guaranteed")


def attack_threshold_factor(G, K, *, rule: str = "paper") -> Tensor:
    """``ς`` of Theorem 1: ``|σ̄ − 1|``, ``σ̄`` the singular value of ``G K`` nearest to 1.

    ``rule="paper"`` is eq. (45) as printed. The proof needs ``‖(I − G K) γ‖ ≥ ς ‖γ‖``
    (eq. 41), which holds for that ``ς`` when ``G K`` is symmetric positive semi-definite
    (``G = I`` with ``Q`` and ``R`` commuting, as in the paper and the four-tank and LFC
    scenarios); for a non-symmetric ``G K`` (a linearised nonlinear measurement, a
    correlated ``R`` with an anisotropic ``Q``) it can overstate the bound, and an attack of
    norm ``‖γ‖_min`` may leave a noise-free corrected residual below ``η``.
    ``rule="guaranteed"`` returns ``σ_min(I − G K)``, the largest ``ς`` for which eq. (41)
    holds for every ``γ``; it equals the paper's value whenever ``G K`` is symmetric
    positive semi-definite.

    Shapes: ``G [..., dy, dx]``, ``K [..., dx, dy]`` → ``[...]``.
    """
    if rule not in _THRESHOLD_RULES:
        raise ValueError(f"rule must be one of {_THRESHOLD_RULES}; got {rule!r}")
    G = _as_matrix(G, "G")
    K = _as_matrix(K, "K", G.dtype)
    if K.shape[-2] != G.shape[-1] or K.shape[-1] != G.shape[-2]:
        raise ValueError(
            f"K must have shape [..., {G.shape[-1]}, {G.shape[-2]}] (the transpose of G's); got {tuple(K.shape)}"
        )
    GK = G @ K
    if rule == "guaranteed":
        eye = torch.eye(GK.shape[-1], dtype=GK.dtype, device=GK.device)
        return torch.linalg.svdvals(eye - GK)[..., -1]  # svdvals are in descending order
    sv = torch.linalg.svdvals(GK)
    nearest = torch.gather(sv, -1, (sv - 1.0).abs().argmin(-1, keepdim=True)).squeeze(-1)
    return (nearest - 1.0).abs()


def attack_threshold(G, K, gamma_min: float, *, rule: str = "paper") -> Tensor:
    """Residual-norm threshold of Theorem 1, eq. (45): ``η = ς ‖γ‖_min``.

    ``gamma_min`` is the smallest attack norm to be guaranteed detectable (a lower bound
    on ``‖γ_k‖``); ``rule`` chooses ``ς`` (:func:`attack_threshold_factor`). Returns ``η``
    ``[...]`` (a 0-dim tensor for single matrices). With ``G = I``, ``Q = 1e-4 I`` and
    ``R = 1e-3 diag(1, 1, .5, .5)``, ``G K`` has singular values 1/11 and 1/6, so
    ``ς = 5/6`` and ``η = 0.28·5/6 = 0.233`` (the paper's value, by either rule).
    """
    try:  # any real number: numpy's and a 0-dim tensor's too (np.float32 had been refused)
        gamma_min = check_finite_number(gamma_min, "gamma_min", positive=True)
    except (TypeError, ValueError):
        raise ValueError(
            f"gamma_min must be a finite number > 0 (a lower bound on ‖γ_k‖); got {gamma_min!r}"
        ) from None
    return attack_threshold_factor(G, K, rule=rule) * gamma_min


class InfeasibleThreshold(ValueError):
    """Eq. (53) has no solution: ``p_l N/(N − 1) ≥ 1`` (an attack on (almost) every step
    for the particle count), so no PoA threshold ``ζ`` exists; a suite skips the PoA
    estimators with this message and runs the others."""


def detection_threshold(
    p_l: float | None, num_particles: int, *, alpha: float | None = None
) -> float:
    """PoA threshold ``ζ = α (N − 1)/N`` (eq. 46).

    With ``alpha=None`` it uses the smallest ``α`` of eq. (53), ``α = p_l N/(N − 1)``, so
    ``ζ = p_l``; an explicit ``alpha ∈ (0, 1)`` (Remark 3, ``p_l`` unknown) gives
    ``ζ = α(N − 1)/N``. ``ValueError`` if eq. (53) has no solution (``p_l N/(N−1) ≥ 1``).
    """
    n = check_integer(num_particles, "num_particles", 2)
    if alpha is None:
        if p_l is None or not 0.0 <= float(p_l) <= 1.0:
            raise ValueError(f"p_l must lie in [0, 1] when alpha is not given; got {p_l!r}")
        alpha = float(p_l) * n / (n - 1)
        if not alpha < 1.0:
            raise InfeasibleThreshold(
                f"eq. (53) needs p_l N/(N-1) < 1; got p_l = {p_l}, N = {n} (alpha = {alpha:.4g}); "
                "use more particles or pass alpha"
            )
        # ζ = α(N − 1)/N = p_l exactly: computed, it could land an ulp below p_l (0.5 at
        # N = 200, 500), and β = p_l, which must not alarm, did
        return float(p_l)
    elif not 0.0 < float(alpha) < 1.0:
        raise ValueError(f"alpha must lie in (0, 1) (eq. 46); got {alpha!r}")
    if p_l is not None:  # both given: α must meet eq. (53) for p_l (it had been ignored)
        if not 0.0 <= float(p_l) <= 1.0:
            raise ValueError(f"p_l must lie in [0, 1]; got {p_l!r}")
        least = float(p_l) * n / (n - 1)
        if float(alpha) < least:
            raise ValueError(
                f"alpha = {alpha} is below eq. (53)'s p_l N/(N-1) = {least:.4g} for p_l = {p_l}, "
                f"N = {n}: Theorem 2's guarantee needs alpha >= it (or pass p_l=None, Remark 3)"
            )
    return float(alpha) * (n - 1) / n


def _check_residuals(residuals) -> None:
    if not isinstance(residuals, Tensor) or residuals.dim() < 2 or residuals.shape[-2] < 1:
        raise ValueError(
            "residuals must be a tensor of shape [..., N, dy] with N >= 1 particles; got "
            f"{getattr(residuals, 'shape', type(residuals))}"
        )
    if not residuals.is_floating_point():
        raise TypeError(f"residuals must be a floating-point tensor; got {residuals.dtype}")


def _exceed(residuals: Tensor, eta) -> Tensor:
    _check_residuals(residuals)
    eta = torch.as_tensor(eta, dtype=residuals.dtype, device=residuals.device)
    if bool((eta < 0).any()) or not bool(torch.isfinite(eta).all()):
        raise ValueError("eta must be finite and >= 0")
    runs = residuals.shape[:-2]
    if broadcast_or_none(eta.shape, runs) != runs:
        # (an η [B, 1] for residuals [B, N, dy] had given β [B, B], every run against every
        # run's threshold, silently: a red-team trial)
        raise ValueError(
            f"eta has shape {tuple(eta.shape)}; it must be a number or one per run, of a shape "
            f"that broadcasts to the residuals' runs {tuple(runs)} without adding dimensions"
        )
    if bool(torch.isnan(residuals).any()):
        # NaN > η² is false: a NaN residual would silently count as "below threshold"
        raise ValueError(
            "residuals contains NaN values; the PoA cannot tell whether they exceed eta "
            "(±Inf residuals are allowed and count as exceeding)"
        )
    # ‖z‖ > η ⇔ ‖z‖² > η² (η ≥ 0): no square root per particle
    return residuals.square().sum(-1) > (eta * eta).unsqueeze(-1)


def probability_of_attack(residuals: Tensor, eta, log_weights: Tensor | None = None) -> Tensor:
    """PoA ``β = Σ_{i: ‖z^i‖ > η} w^i`` (eqs 14 and 58).

    Args:
        residuals: ``z^i`` ``[..., N, dy]`` (``ỹ − G x^i``, or ``ỹ − G x̃^{i+}`` for the
            modified PF).
        eta: threshold, a number or ``[...]``.
        log_weights: ``[..., N]`` (normalised or not; softmax is applied), ``None`` for
            equal weights ``1/N`` (eq. 58).

    Returns ``β`` ``[...]`` in ``[0, 1]``. Rows whose weights are all equal use the exact
    count ``#{‖z^i‖ > η}/N`` (a float sum of ``1/N``'s is not exact, and ``β = ζ`` must
    not raise an alarm by round-off); a row where every particle (none) exceeds ``η`` is
    exactly 1 (0), and weighted sums are clipped to ``[0, 1]`` (the softmax's weights sum
    to ``1 ± 4.4e-16``: a threshold calibrated at ``β = 1`` read the steps where every
    particle exceeded as alarms or not by round-off, and a user trial's calibrated
    detection rate came from those alone).

    Never silently "no attack": NaN residuals raise ``ValueError`` (``±Inf`` residuals
    exceed any ``η``), as do log-weights that are NaN or all ``−inf`` in a row (``β``
    would be NaN and ``NaN > ζ`` false).
    """
    exceed = _exceed(residuals, eta).to(residuals.dtype)
    if log_weights is None:
        return exceed.mean(-1)
    if log_weights.shape[-1] != residuals.shape[-2]:
        raise ValueError(
            f"log_weights must have shape [..., {residuals.shape[-2]}] (one per particle); got {tuple(log_weights.shape)}"
        )
    beta = (torch.softmax(log_weights, dim=-1) * exceed).sum(-1)
    if bool(torch.isnan(beta).any()):
        raise ValueError(
            "log_weights are NaN or all -inf in some row; the PoA of such a row is undefined "
            "(normalisable log-weights needed)"
        )
    equal = (log_weights == log_weights[..., :1]).all(-1)
    counted = equal | (exceed == exceed[..., :1]).all(-1)  # equal weights, or all or none
    return torch.where(counted, exceed.mean(-1), beta.clamp(0.0, 1.0))


class PoADetector:
    """The PoA detector: ``β = Σ_{‖z^i‖>η} w^i``, alarm when ``β > ζ``.

    Args:
        eta: residual-norm threshold ``η`` (:func:`attack_threshold`), a number or one
            per run (a tensor of the runs' batch shape, checked by the filters at ``init``).
        zeta: PoA threshold ``ζ`` (:func:`detection_threshold`), in ``[0, 1)``.
    """

    def __init__(self, eta, zeta: float):
        self.eta, self.zeta = eta, zeta  # (checked by __setattr__)

    def __setattr__(self, name, value):
        # checked whenever set, not at __init__ alone: the filters read detector.zeta and
        # .eta at every step, and a NaN ζ assigned later never alarmed (β > NaN is false: a
        # detector trial)
        if name == "eta":
            eta_t = torch.as_tensor(value, dtype=torch.float64)
            if bool((eta_t < 0).any()) or not bool(torch.isfinite(eta_t).all()):
                raise ValueError(f"eta must be finite and >= 0; got {value!r}")
        elif name == "zeta":
            value = check_fraction(value, "zeta")
        super().__setattr__(name, value)

    def check_runs(self, batch_shape, model=None) -> None:
        """Refuse an ``η`` per run that does not match the runs ``batch_shape`` (of a
        ``model`` of several parameter sets, their broadcast). A tensor ``η`` needs as many
        dimensions as the batch and must broadcast to it: with fewer, torch would align it
        on the last batch dimension, not the first, silently."""
        shape = torch.as_tensor(self.eta).shape
        if len(shape) == 0:
            return
        batch = torch.Size(batch_shape)
        if model is not None:
            batch = broadcast_or_none(batch, model_batch_shape(model)) or batch
        if len(shape) != len(batch) or broadcast_or_none(shape, batch) != batch:
            raise ValueError(
                f"detector.eta has shape {tuple(shape)}; a threshold per run needs the runs' "
                f"batch shape {tuple(batch)} (or one that broadcasts to it with as many "
                "dimensions, e.g. [B, 1]), or a single number"
            )

    def __call__(
        self, residuals: Tensor, log_weights: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """``(β [...], alarm [...])`` for residuals ``[..., N, dy]`` and log-weights ``[..., N]``."""
        beta = probability_of_attack(residuals, self.eta, log_weights)
        return beta, beta > self.zeta

    def __repr__(self) -> str:
        return (
            f"PoADetector(eta={float(torch.as_tensor(self.eta).mean()):.4g}, zeta={self.zeta:.4g})"
        )


def literal_gaussian_density(residuals: Tensor, cov) -> Tensor:
    """``N(r; 0, R)`` evaluated literally in float64: ``(2π)^{−m/2} |R|^{−1/2} exp(−½ rᵀR⁻¹r)``.

    Diagnostic only (Fig. 9 question): a density below ~5e-324 underflows to exactly 0.
    Shapes: ``residuals [..., dy]``, ``cov [dy, dy]`` → ``[...]`` (float64).
    """
    r = residuals.to(torch.float64)
    R = torch.as_tensor(cov, dtype=torch.float64, device=r.device)
    m = r.shape[-1]
    if R.shape != (m, m):
        raise ValueError(f"cov must have shape [{m}, {m}]; got {tuple(R.shape)}")
    chol = safe_cholesky(R, name="cov")
    z = torch.linalg.solve_triangular(chol, r.reshape(-1, m).transpose(0, 1), upper=False)
    quad = z.square().sum(0).reshape(r.shape[:-1])
    log_norm = 0.5 * m * LOG_2PI + torch.log(chol.diagonal()).sum()
    # one exp of the whole exponent, as MATLAB's mvnpdf does: exactly 0 below ~5e-324
    return torch.exp(-0.5 * quad - log_norm)


def literal_probability_of_attack(
    residuals: Tensor, cov, eta, prior_weights: Tensor | None = None
) -> Tensor:
    """PoA with the posterior weights formed in linear float64 space (a naive implementation).

    ``w^i = p(ỹ | x^i) w^i_{k−1} / Σ_j p(ỹ | x^j) w^j_{k−1}`` (eq. 7; eq. 17's weights where
    the prior weights are uniform, as after every resampling) with the literal density of
    :func:`literal_gaussian_density`; ``β = Σ_{‖z^i‖>η} w^i``. When every density
    underflows the weights are ``0/0 = NaN`` and so is ``β`` — compare with ``β > ζ``,
    which is then false (no alarm), the IEEE semantics a MATLAB implementation shares.

    Shapes: ``residuals [..., N, dy]``, ``prior_weights [..., N]`` (linear, ``None``:
    uniform) → ``[...]`` float64.
    """
    _check_residuals(residuals)
    dens = literal_gaussian_density(residuals, cov)
    if prior_weights is not None:
        dens = dens * prior_weights.to(torch.float64)
    w = dens / dens.sum(-1, keepdim=True)
    exceed = _exceed(residuals.to(torch.float64), eta).to(torch.float64)
    return (w * exceed).sum(-1)


class AttackRateState(NamedTuple):
    """State of :class:`RunningAttackRate`: detections ``count [...]`` after ``steps`` steps."""

    count: Tensor
    steps: int


class RunningAttackRate:
    """Remark 6: ``ζ`` from a running estimate of ``p_l`` when ``p_l`` is unknown.

    For the first ``warmup`` steps ``ζ = α₀ (N − 1)/N`` with a chosen ``α₀ ∈ (0, 1)``
    (eq. 46); afterwards ``p̂_l = #{alarms}/#{steps}`` and ``α = p̂_l N/(N − 1)`` (eq. 53),
    clipped to ``[alpha_min, alpha_max] ⊂ (0, 1)`` so that ``ζ`` stays a proper threshold
    while few attacks have been seen ([DEF] bounds; Remark 6 notes ``p̂_l ≥ p_l`` is
    harmless).

    Args:
        num_particles: ``N``.
        alpha0: ``α₀`` [DEF 0.5].
        warmup: steps with ``α₀`` [DEF 10].
        alpha_min, alpha_max: clipping bounds of ``α`` [DEF 0.05, 0.95].
    """

    def __init__(
        self,
        num_particles: int,
        *,
        alpha0: float = 0.5,
        warmup: int = 10,
        alpha_min: float = 0.05,
        alpha_max: float = 0.95,
    ):
        self.n, self.alpha0, self.warmup = num_particles, alpha0, warmup
        # (the pair checked together here; either assigned later, against the other)
        lo, hi = _check_alpha_bounds(alpha_min, alpha_max)
        object.__setattr__(self, "alpha_min", lo)
        object.__setattr__(self, "alpha_max", hi)

    def __setattr__(self, name, value):
        # checked whenever set, as PoADetector's ζ is: zeta() reads them at every step, and
        # alpha0 = NaN or warmup = 0 assigned later gave ζ = NaN (β = 1 never alarmed), 1.5
        # a ζ above 1 (a red-team trial)
        if name == "n":
            value = check_integer(value, "num_particles", 2)
            if "n" in self.__dict__:
                note_assignment()  # (the filters check a rate's N against theirs again)
        elif name == "warmup":
            value = check_integer(value, "warmup", 1)
        elif name == "alpha0":
            alpha0 = real_number(value)
            if alpha0 is None or not 0.0 < alpha0 < 1.0:
                raise ValueError(f"alpha0 must lie in (0, 1); got {value!r}")
            value = alpha0
        elif name in ("alpha_min", "alpha_max"):
            bounds = {"alpha_min": getattr(self, "alpha_min", None),
                      "alpha_max": getattr(self, "alpha_max", None), name: value}  # fmt: skip
            lo, hi = _check_alpha_bounds(bounds["alpha_min"], bounds["alpha_max"])
            value = lo if name == "alpha_min" else hi
        super().__setattr__(name, value)

    def init(self, batch_shape=(), *, dtype=torch.float64, device=None) -> AttackRateState:
        """The state before the first step. The alarms are counted in float64 whatever
        ``dtype`` (exact to 2^53 alarms): a float32 count stopped at 2^24 (16,777,216: after
        about five days of a 10 ms loop alarming on 39 % of the steps, a user trial), and the
        estimate ``p̂_l`` then fell; :meth:`zeta` and :meth:`estimate` come back in float64
        (the caller casts them)."""
        del dtype  # (kept for the callers: the count is float64 whatever the filter's)
        count = torch.zeros(torch.Size(batch_shape), dtype=torch.float64, device=device)
        return AttackRateState(count, 0)

    def zeta(self, state: AttackRateState) -> Tensor:
        """``ζ`` for the next step ``[...]``."""
        scale = (self.n - 1) / self.n
        if state.steps < self.warmup:
            return torch.full_like(state.count, self.alpha0 * scale)
        p_hat = state.count / state.steps
        raw = p_hat * self.n / (self.n - 1)
        alpha = raw.clamp(self.alpha_min, self.alpha_max)
        # unclipped, ζ = α(N − 1)/N is p̂_l exactly (eqs 46, 53): computed, it landed an ulp
        # below p̂_l (0.49999999999999994 for 0.5 at N = 200), and β = p̂_l alarmed (a
        # red-team trial), as detection_threshold has it for a known p_l
        return torch.where(alpha == raw, p_hat, alpha * scale)

    def update(self, state: AttackRateState, alarms: Tensor) -> AttackRateState:
        """Count this step's decisions ``alarms [...]``."""
        return AttackRateState(state.count + alarms.to(state.count.dtype), state.steps + 1)

    def estimate(self, state: AttackRateState) -> Tensor:
        """``p̂_l`` so far ``[...]`` (NaN before the first step)."""
        return state.count / state.steps if state.steps else torch.full_like(state.count, math.nan)


def _check_alpha_bounds(alpha_min, alpha_max) -> tuple[float, float]:
    lo, hi = real_number(alpha_min), real_number(alpha_max)
    if lo is None or hi is None or not 0.0 < lo <= hi < 1.0:
        raise ValueError(f"need 0 < alpha_min <= alpha_max < 1; got {alpha_min!r}, {alpha_max!r}")
    return lo, hi


def poa_detector_for(
    model, *, gamma_min: float, p_l: float, num_particles: int, R=None, rule: str = "paper"
) -> PoADetector:
    """The PoA detector of a model with the paper's thresholds (Theorem 1, eqs 46/53).

    ``η = ς ‖γ‖_min`` with ``ς`` from ``G K`` (eq. 45), ``K = Q Gᵀ (R + G Q Gᵀ)⁻¹``
    (eq. 35), where ``G`` is the model's ``observation_matrix(1)`` or, for a nonlinear
    measurement, its Jacobian at the prior mean; ``Q = process_cov(0)``; ``R`` is the
    model's ``measurement_cov(1)`` unless given (the paper keeps the ``η`` of its
    nominal ``R`` in the high-noise case). ``ζ = p_l`` (the smallest ``α`` of eq. 53).
    ``rule="guaranteed"`` takes ``ς = σ_min(I − G K)`` (:func:`attack_threshold_factor`):
    the paper's ``ς`` is the guaranteed one only when ``G K`` is symmetric positive
    semi-definite, which a nonlinear measurement's Jacobian rarely gives.
    """
    check_one_model(model, "poa_detector_for", "make a detector per parameter set")
    if hasattr(model, "observation_matrix"):
        G = model.observation_matrix(1)
    else:
        G = model.observation_jacobian(model.initial.mean, 1)
        if not bool(torch.isfinite(G).all()):  # (it failed as "G contains NaN or Inf")
            raise NumericalBreakdown(
                "the observation Jacobian ∂h/∂x at the prior mean, the PoA detector's G "
                "(Theorem 1), holds NaN or inf: h is not differentiable there (e.g. a range "
                "or bearing measured at the sensor's own position), so the thresholds of "
                "eqs (45)/(46) cannot be computed (start the prior mean elsewhere)"
            )
    G = G.detach().to(torch.float64)
    # (a list R in float64: under a float32 default it had been rounded first, η 2e-9 off)
    R = (
        model.measurement_cov(1)
        if R is None
        else torch.as_tensor(R, dtype=torch.float64)
        if not isinstance(R, Tensor)
        else R
    )
    K = modified_pf_gain(G, model.process_cov(0).detach().double(), R.detach().double())
    eta = float(attack_threshold(G, K, gamma_min, rule=rule))
    return PoADetector(eta, detection_threshold(p_l, num_particles))
