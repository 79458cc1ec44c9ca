"""Residual-based attack detectors: chi-square and CUSUM (docs/metrics.md).

Both consume a filter's innovations ``r_k [..., T, m]`` and innovation covariances
``S_k [..., T, m, m]`` (any difffilter filter result provides them) through the
normalised innovation squared ``g_k = r_kᵀ S_k⁻¹ r_k``, which is χ²_m-distributed when
the model is right and there is no attack.

**Masked results** (entries not received): a filter gives such an entry innovation 0 and
variance 1, so ``g_k`` has ``m_k`` degrees of freedom, the entries received. Pass the mask
to :meth:`ChiSquareDetector.detect` and :meth:`ChiSquareDetector.step`: each step is judged
against ``χ²`` of the degrees of freedom its window holds, and its score is the
:func:`chi_square_equivalent` of the statistic (the value of a full window's ``χ²`` with
the same tail probability), so one threshold on the scores is one false-alarm rate
whatever arrived (a threshold calibrated on the raw statistic pooled 1, 2 and 3 received
entries and alarmed 0.07 %, 0.79 % and 1.79 % of them for 1 %: a packet-loss trial). A
window without data scores 0 and never alarms. :class:`CusumDetector` counts a missing
entry's mean (``g_k + m − m_k``: pass the mask to :meth:`CusumDetector.detect`, or add it
to the ``g`` given to :meth:`CusumDetector.run`); its drift ``b`` keeps the mean, not the
variance, so its rate still varies with ``m_k`` (a trial: 0.41 %, 0.87 %, 1.43 % for 1, 2,
3 of 3 entries at a calibrated 1 %).

**Non-finite input raises.** A detector must never answer "no alarm" for a statistic it
could not compute (``NaN > τ`` is false): NaN or ±Inf innovations or covariances, and NaN,
``−inf`` or negative statistics ``g``, raise ``ValueError`` naming the argument, as do
non-symmetric innovation covariances. A statistic of ``+inf`` (``νᵀS⁻¹ν`` overflowed from a
huge but finite measurement) is beyond every threshold: an alarm. Validate or clean the
filter output (e.g. ``nonfinite="skip"`` in the filters) before detection.
"""

from __future__ import annotations

import functools
import math
import numbers
import warnings

import numpy as np
import torch
from torch import Tensor

from .._checks import (
    broadcast_or_none,
    broadcast_shapes,
    check_finite_number,
    check_mask,
    check_one_dtype_device,
    check_positive_int,
    check_rate,
    check_square,
    check_symmetric,
    host_array,
    values_known,
)
from ..linalg import mahalanobis_sq_chol, safe_cholesky

__all__ = [
    "normalized_innovation_squared",
    "chi_square_equivalent",
    "chi_square_quantile",
    "chi_square_upper_quantile",
    "ChiSquareDetector",
    "CusumDetector",
    "missing_entries_counted",
]


def _check_statistic(
    t, name: str, *, alarm_on_inf: bool = False, nonnegative: bool = False
) -> Tensor:
    """``t`` must be a floating tensor with finite entries (a NaN would read as "no alarm");
    with ``alarm_on_inf`` a detector's statistic may be ``+inf``, beyond every threshold:
    a huge but finite measurement overflows ``νᵀS⁻¹ν`` (from 1e20 in float32, 1e155 in
    float64), and the gated filters raised on it where they should alarm (a user trial).
    With ``nonnegative`` (a NIS ``g = νᵀS⁻¹ν``) a negative entry is refused: in a window
    or a CUSUM sum it cancels later evidence (a ``g`` of −100 silenced an alarming 30 two
    steps later: a detector trial)."""
    if not isinstance(t, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor; got {type(t).__name__}")
    if not t.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor; got {t.dtype}")
    ok = ~torch.isnan(t) & (t != -math.inf) if alarm_on_inf else torch.isfinite(t)
    if not bool(ok.all()):
        what = "NaN or −inf" if alarm_on_inf else "NaN or Inf"
        raise ValueError(
            f"{name} contains {what} values; a detector cannot decide on a statistic it "
            "could not compute (it raises instead of returning 'no alarm')"
        )
    if nonnegative and bool((t < 0).any()):
        raise ValueError(
            f"{name} must be >= 0, a normalised innovation squared νᵀS⁻¹ν per step; got a "
            f"minimum of {float(t.min()):.6g}"
        )
    return t


def _check_sequence(
    t, name: str, event_dims: int, *, alarm_on_inf: bool = False, nonnegative: bool = False
) -> Tensor:
    """A statistic over time: ``[..., T]`` plus ``event_dims`` trailing dimensions, ``T ≥ 1``
    (``alarm_on_inf``, ``nonnegative``: as :func:`_check_statistic`)."""
    _check_statistic(t, name, alarm_on_inf=alarm_on_inf, nonnegative=nonnegative)
    shape = "[..., T" + ", m" * event_dims + "]"
    if t.dim() < 1 + event_dims or t.shape[t.dim() - 1 - event_dims] < 1:
        raise ValueError(f"{name} must be a sequence {shape} of T >= 1 steps; got {tuple(t.shape)}")
    return t


def _check_calibration_sequence(t, name: str) -> Tensor:
    """An attack-free statistic ``[..., T]`` to calibrate on: a sequence of at least one
    run (no runs had failed in torch's max: a batch-dims trial)."""
    _check_sequence(t, name, 0)
    if t.numel() == 0:
        raise ValueError(f"{name} has no runs to calibrate on: {tuple(t.shape)}")
    return t


def normalized_innovation_squared(
    innovations: Tensor, innovation_covs: Tensor, *, mask: Tensor | None = None
) -> Tensor:
    """``g_k = r_kᵀ S_k⁻¹ r_k``: ``[..., T, m]``, ``[..., T, m, m]`` → ``[..., T]``.

    ``mask [..., T, m]`` (bool, broadcasting to the innovations) or ``None``: the entries
    received, for a masked result (a filter run with a mask: lost entries have innovation 0
    and a unit placeholder variance). Where ``S`` must be jittered to factorise, the jitter
    is then the received entries' own (:func:`~difffilter.linalg.safe_cholesky`), so ``g``
    is the received sub-model's in any unit (scaled by the placeholders' 1s too, a float32
    ``g`` of redundant sensors with variances near 1e-6 was 0.8 for 1). Where ``S``
    factorises the mask changes no number.

    ``ValueError`` for non-finite entries, non-symmetric or non-positive-definite ``S``.
    """
    _check_statistic(innovations, "innovations")
    if innovations.dim() < 1:
        raise ValueError(f"innovations must have shape [..., m]; got {tuple(innovations.shape)}")
    _check_statistic(innovation_covs, "innovation_covs")
    check_square(innovation_covs, "innovation_covs", innovations.shape[-1])
    check_symmetric(innovation_covs, "innovation_covs")
    if broadcast_or_none(innovations.shape[:-1], innovation_covs.shape[:-2]) is None:
        raise ValueError(
            f"innovations {tuple(innovations.shape)} [..., T, m] and innovation_covs "
            f"{tuple(innovation_covs.shape)} [..., T, m, m] must share their leading dimensions "
            "(or broadcast)"
        )
    # (as whiteness and nees: a float32 S had whitened float64 innovations into a float32
    # statistic, 1.5e-5 off, and the alarms were decided on it)
    check_one_dtype_device(innovations, "innovations", innovation_covs, "innovation_covs")
    if mask is not None:
        mask = check_mask(mask, "mask", innovations.shape)
    return _nis(innovations, innovation_covs, mask)


def _nis(innovations: Tensor, innovation_covs: Tensor, mask: Tensor | None = None) -> Tensor:
    """:func:`normalized_innovation_squared` without the checks (a filter's own output).
    (An ``S`` shared by runs with masks of their own is factorised once where it needs no
    jitter, per run where it does: :func:`~difffilter.linalg.safe_cholesky`. Expanded to
    the mask's runs first, it had taken the batched product instead of the shared factor's,
    and the mask had moved the NIS by round-off, 1.9e-6 in float32.)"""
    chol = safe_cholesky(innovation_covs, name="innovation_covs", mask=mask)
    return mahalanobis_sq_chol(innovations, chol)


def _agreeing(score: Tensor, alarm: Tensor, limit: Tensor) -> Tensor:
    """``score`` (:func:`chi_square_equivalent` of a window's statistic) above the full
    window's threshold ``limit`` exactly where the window alarmed against its own degrees
    of freedom: scipy's map lands within a few ulp of ``limit`` for a statistic a few ulp
    from its own threshold, and had crossed it the other way (alarms with a score below
    the threshold and the reverse, 18 of 401 values within 200 ulp: a detectors trial).
    The few such scores are set to ``limit`` or the number above it."""
    above = score > limit
    if bool((above == alarm).all()):
        return score
    up = torch.nextafter(limit, torch.full_like(limit, math.inf))
    return torch.where(alarm & ~above, up, torch.where(~alarm & above, limit, score))


def chi_square_equivalent(g: Tensor, dof, full_dof) -> Tensor:
    """``x = F⁻¹_{χ²_D}(F_{χ²_d}(g))``: a statistic ``g`` of ``d = dof`` degrees of freedom as
    the value of ``χ²_D`` (``D = full_dof``) with the same upper tail probability.

    ``dof`` and ``full_dof`` broadcast with ``g [...]`` (numbers or tensors). ``x = g``
    where ``d = D`` (unchanged, bit for bit), ``0`` where ``d = 0`` (no data: below every
    threshold); ``x > F⁻¹_{χ²_D}(1 − α)`` exactly where ``g > F⁻¹_{χ²_d}(1 − α)``, so one
    threshold is one false-alarm rate over steps of any ``d``. Where the tail underflows
    (``g`` beyond about 1,400: deep in an attack) ``x`` equates the tails' asymptotic
    series (:func:`_log_tail_asymptotic`).
    Differentiable in ``g`` (first order): ``dx/dg = f_{χ²_d}(g) / f_{χ²_D}(x)``, from
    scipy's distributions on the CPU (the map runs only where ``0 < d < D``).
    """
    if not isinstance(g, Tensor) or not g.is_floating_point():
        # (an integer g had come back truncated, [1, 3, 4, 8] for [1.84, 3.16, 4.38, 8.93];
        # numpy and list g failed inside torch: an apishapes trial)
        got = g.dtype if isinstance(g, Tensor) else type(g).__name__
        raise ValueError(f"g must be a floating tensor (a statistic); got {got}")
    d = torch.as_tensor(dof, device=g.device).to(torch.float64)
    full = torch.as_tensor(full_dof, device=g.device).to(torch.float64)
    if d.shape != full.shape:
        d, full = torch.broadcast_tensors(d, full)
    if bool((d > full).any()) or bool((d < 0).any()):
        raise ValueError("dof must lie in [0, full_dof]")
    partial = (d > 0) & (d < full)
    none = d == 0
    if not bool(partial.any()):
        return torch.where(none, torch.zeros((), dtype=g.dtype, device=g.device), g)
    from scipy import special

    shape = broadcast_shapes(g.shape, d.shape)
    sel = np.broadcast_to(host_array(partial).astype(bool), shape).copy()  # (writable)
    # g's values, also inside a torch.func transform (whose wrappers have no storage: .numpy()
    # had raised under grad/jvp/jacrev/jacfwd with a mask; a gradients trial); its derivative
    # rides on g itself below
    gn = np.broadcast_to(host_array(g).astype(np.float64), shape)[sel]
    dn = np.broadcast_to(host_array(d), shape)[sel]
    Dn = np.broadcast_to(host_array(full), shape)[sel]
    # scipy.stats.chi2's own functions without its argument handling (about 180 µs of a
    # masked online χ² step: a recorded-log trial), the same numbers bit for bit:
    # sf = chdtrc, cdf = chdtr, ppf = 2 gammaincinv(D/2, ·), isf = chdtri
    # (below 0, outside the support: scipy.stats's tail 1, where chdtrc gives NaN; a review)
    at = np.maximum(gn, 0.0)
    tail = special.chdtrc(dn, at)
    # the lower tail where it is the smaller (more digits), the upper one elsewhere
    x = np.where(tail > 0.5, 2 * special.gammaincinv(Dn / 2, special.chdtr(dn, at)),
                 special.chdtri(Dn, tail))  # fmt: skip
    infinite = np.isinf(gn)  # an overflowed νᵀS⁻¹ν stays beyond every threshold
    x[infinite] = np.inf
    under = (tail < 1e-290) & ~infinite
    if under.any():
        gu, du, Du = gn[under], dn[under], Dn[under]
        target = _log_tail_asymptotic(gu, du)
        xu = gu.copy()
        for _ in range(12):  # x/2 = (D/2 − 1) log(x/2) − log Γ(D/2) + log(series) − target
            xu = xu + 2 * (_log_tail_asymptotic(xu, Du) - target)
        x[under] = xu
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = np.exp(_chi2_logpdf(gn, dn) - _chi2_logpdf(x, Dn))
    slope = np.where(np.isfinite(slope) & (gn > 0) & ~infinite, slope, 0.0)
    mapped = torch.zeros(shape, dtype=torch.float64)
    rate = torch.zeros(shape, dtype=torch.float64)
    mapped[torch.from_numpy(sel)] = torch.from_numpy(x)
    rate[torch.from_numpy(sel)] = torch.from_numpy(slope)
    mapped, rate = (t.to(dtype=g.dtype, device=g.device) for t in (mapped, rate))
    g = g.expand(shape)
    # the value x, the derivative dx/dg (nothing through an infinite g: inf − inf is NaN)
    moved = torch.where(torch.isinf(g), torch.zeros((), dtype=g.dtype, device=g.device),
                        g - g.detach())  # fmt: skip
    mapped = mapped + rate * moved
    zero = torch.zeros((), dtype=g.dtype, device=g.device)
    return torch.where(partial, mapped, torch.where(none, zero, g))


def _chi2_logpdf(x: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """``log f_{χ²_dof}(x)`` as ``scipy.stats.chi2.logpdf`` computes it for ``x ≥ 0``:
    ``(k/2 − 1) log x − x/2 − log Γ(k/2) − (k/2) log 2``."""
    from scipy import special

    return (
        special.xlogy(dof / 2.0 - 1, x)
        - x / 2.0
        - special.gammaln(dof / 2.0)
        - (np.log(2) * dof) / 2.0
    )


def _log_tail_asymptotic(x: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """``log P(χ²_dof > x)`` for large ``x`` (hundreds and more): the incomplete gamma
    function's asymptotic series ``Γ(a, z) ≈ z^{a−1} e^{−z} Σ_j (a−1)…(a−j)/z^j``, four
    terms, ``a = dof/2``, ``z = x/2``."""
    from scipy.special import gammaln

    a, z = dof / 2, x / 2
    term, series = np.ones_like(z), np.ones_like(z)
    for j in range(1, 4):
        term = term * (a - j) / z
        series = series + term
    return (a - 1) * np.log(z) - z - gammaln(a) + np.log(series)


def chi_square_quantile(dof: float, prob: float) -> float:
    """``F⁻¹_{χ²_dof}(prob)``: the χ² quantile, from ``scipy.stats.chi2.ppf``.

    (It replaced our bisection on ``torch.special.gammainc``: the same values to 5e-13 in
    relative terms, measured 4.6× faster per call, and a well-kept implementation.)
    """
    if not 0.0 < prob < 1.0:
        raise ValueError(f"prob must lie in (0, 1); got {prob}")
    if not 0 < dof < math.inf:  # (an infinite dof had returned NaN)
        raise ValueError(f"dof must be a finite number > 0; got {dof}")
    return _chi2_ppf(float(dof), float(prob))


def chi_square_upper_quantile(dof: float, rate: float) -> float:
    """``F⁻¹_{χ²_dof}(1 − rate)`` from the upper tail: the threshold of a false-alarm
    ``rate`` (``chi_square_quantile(dof, 1 − rate)`` loses the rate's digits below 1e-6 and
    all of them below 1e-16)."""
    if not 0.0 < rate < 1.0:
        raise ValueError(f"rate must lie in (0, 1); got {rate}")
    if not 0 < dof < math.inf:  # (an infinite dof had returned NaN)
        raise ValueError(f"dof must be a finite number > 0; got {dof}")
    return _chi2_isf(float(dof), float(rate))


@functools.lru_cache(maxsize=4096)
def _chi2_isf(dof: float, rate: float) -> float:
    """``F⁻¹_{χ²_dof}(1 − rate)`` from the upper tail (``scipy.stats.chi2.isf``): ``1 − rate``
    keeps no digits of a rate below 1e-16 (a threshold of 80 on χ²_3, a rate of 3e-17,
    read back as "prob 1.0"), and loses some from 1e-6 on (60 read back as 59.99986)."""
    from scipy.stats import chi2

    return float(chi2.isf(rate, dof))


@functools.lru_cache(maxsize=4096)
def _chi2_ppf(dof: float, prob: float) -> float:
    """``scipy.stats.chi2.ppf``, kept: a gated filter's online step asks for the same
    quantile at every step, and one call cost about 150 µs, more than the EKF's step."""
    from scipy.stats import chi2

    return float(chi2.ppf(prob, dof))


def _window_sums(g: Tensor, window: int) -> Tensor:
    """``Σ`` of the last ``window`` values of ``g [..., T]`` at every step (fewer at the
    start), as a difference of running totals summed in float64: in float32 over a long run
    the totals' round-off swamped the window's sum (a numerics trial: score errors of 0.25
    and 2 % of the alarms flipped at T = 4e6)."""
    c = torch.cumsum(g.to(torch.float64), dim=-1)
    shifted = torch.cat([torch.zeros_like(c[..., :window]), c[..., :-window]], dim=-1)
    sums = c - shifted[..., : c.shape[-1]]
    # a difference of two totals is off by the totals' accumulated round-off (about
    # √T·ε·max|total|): after one large statistic (1e16) every later window had been off by
    # up to 4.2, alarms flipping on clean steps for the rest of the run (a long-run trial).
    # A run whose round-off could reach 1e-9 has its windows summed directly (the online
    # step's sums), decided per run so that a run's scores do not hang on its batch (a
    # review); ordinary runs keep the cheap path, bit for bit
    if c.numel():
        bound = math.sqrt(c.shape[-1]) * _FLOAT64_EPS * c.abs().amax(-1, keepdim=True)
        direct = ~(bound <= _WINDOW_SUM_TOL)  # (NaN totals too: their windows summed alone)
        if bool(direct.any()):
            padded = torch.nn.functional.pad(g.to(torch.float64), (window - 1, 0))
            sums = torch.where(direct, padded.unfold(-1, window, 1).sum(-1), sums)
    return sums.to(g.dtype)


_FLOAT64_EPS = torch.finfo(torch.float64).eps
#: The round-off of a window sum taken as a difference of running totals above which the
#: windows are summed directly (:func:`_window_sums`).
_WINDOW_SUM_TOL = 1e-9


class ChiSquareDetector:
    """χ² detector (Mo & Sinopoli 2009): alarm when ``Σ_{j=k−W+1}^{k} g_j > F⁻¹_{χ²_{mW}}(1 − α)``.

    Args:
        dim: measurement dimension ``m`` (degrees of freedom of one ``g_k``).
        false_alarm_rate: per-step false-alarm probability ``α`` under the model, of a
            filter that keeps every measurement (a filter gated by this detector drops
            those it alarms on and runs above ``α``: 1.04–1.12 % for 1 % in a trial,
            docs/metrics.md). Watching an ungated filter, the test alarms on clean steps
            after an attack as well, where the filter's estimate followed the attacked
            readings (92 % of the unattacked steps on ``four_tank_bias``, 2.3 % gated:
            docs/metrics.md, "Gate the filter the test watches").
        window: ``W`` ≥ 1 steps summed (the first ``W−1`` steps use the steps available
            and the matching ``χ²`` quantile).
    """

    def __init__(self, dim: int, false_alarm_rate: float = 0.01, window: int = 1):
        self.dim, self.false_alarm_rate, self.window = dim, false_alarm_rate, window  # checked

    def __setattr__(self, name, value):
        # checked whenever set, not at __init__ alone (a NaN rate assigned later had run)
        if name == "false_alarm_rate":
            value = check_rate(value, "false_alarm_rate")  # rejects NaN, "0.01"
        elif name in ("dim", "window"):
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1; got {value!r}")
            value = int(value)  # (a numpy integer had failed in torch's mask broadcast)
        super().__setattr__(name, value)

    @classmethod
    def at_threshold(cls, dim: int, threshold: float, window: int = 1) -> ChiSquareDetector:
        """The detector whose full-window threshold is ``threshold`` (``τ``, e.g. calibrated
        on attack-free data of one's own with :func:`difffilter.metrics.threshold_for`):
        ``α = 1 − F_{χ²_{mW}}(τ)``, the rate ``τ`` has under a Gaussian model (under
        heavy-tailed noise the calibration's rate, not this ``α``, is the one measured)."""
        tau = check_finite_number(threshold, "threshold", positive=True)
        cls(dim, 0.5, window)  # names a wrong dim or window
        from scipy.stats import chi2

        rate = float(chi2.sf(tau, dim * window))
        if not 0.0 < rate < 1.0:
            raise ValueError(
                f"threshold {tau!r} is beyond what χ²_{dim * window} reaches in float64 (a rate "
                f"of {rate!r}): give a threshold of a false-alarm rate in (0, 1)"
            )
        # the rate read back lands up to 2 ulp below τ one time in three, and τ from
        # threshold_for is one of the scores: that score alarmed, one more than the ⌊αn⌋ the
        # calibration allows (a recorded-log trial): the largest rate whose quantile is ≥ τ
        for _ in range(64):
            if chi_square_upper_quantile(dim * window, rate) >= tau:
                break
            rate = math.nextafter(rate, 0.0)
        return cls(dim, rate, window)

    def __repr__(self) -> str:
        return (f"ChiSquareDetector(dim={self.dim}, false_alarm_rate={self.false_alarm_rate:.4g}, "
                f"window={self.window})")  # fmt: skip

    @property
    def threshold(self) -> float:
        """Threshold of a full window: ``F⁻¹_{χ²_{mW}}(1 − α)``."""
        return self.quantile(self.dim * self.window)

    def quantile(self, dof: float) -> float:
        """``F⁻¹_{χ²_dof}(1 − α)``, the threshold of a window of ``dof`` degrees of freedom."""
        return chi_square_upper_quantile(dof, self.false_alarm_rate)

    def _quantile_table(self, like: Tensor) -> Tensor:
        """``F⁻¹_{χ²_d}(1 − α)`` for ``d = 0 … mW`` (``d = 0``: ``+inf``, never an alarm),
        in ``like``'s dtype and on its device, made once for each setting (a rate or window
        set after a first use had the table of before thresholding: 235 alarms for 4, a
        red-team trial)."""
        tables = self.__dict__.setdefault("_tables", {})
        key = (like.dtype, like.device, self.dim, self.false_alarm_rate, self.window)
        if key not in tables:
            q = [math.inf] + [self.quantile(d) for d in range(1, self.dim * self.window + 1)]
            tables[key] = torch.tensor(q, dtype=like.dtype, device=like.device)
        return tables[key]

    def _full_dof(self, num_steps: int) -> Tensor:
        """The degrees of freedom of a full window at each step ``[T]``: ``m·min(t, W)``."""
        t = torch.arange(1, num_steps + 1, dtype=torch.float64).clamp(max=self.window)
        return self.dim * t

    def scores(
        self, innovations: Tensor, innovation_covs: Tensor, *, mask: Tensor | None = None
    ) -> Tensor:
        """Windowed statistic ``[..., T]`` (the sum of the last ``W`` values of ``g``);
        ``mask``: the received entries of a masked result, for a jittered ``S``
        (:func:`normalized_innovation_squared`)."""
        _check_sequence(innovations, "innovations", 1)
        if innovations.shape[-1] != self.dim:  # χ²_dim of another m: a wrong false-alarm rate
            raise ValueError(
                f"innovations have {innovations.shape[-1]} entries a step; this detector was made "
                f"for dim = {self.dim}: build ChiSquareDetector({innovations.shape[-1]}, …)"
            )
        return self._windowed(normalized_innovation_squared(innovations, innovation_covs,
                                                            mask=mask))  # fmt: skip

    def _windowed(self, g: Tensor) -> Tensor:
        """``Σ`` of the last ``W`` values of ``g [..., T]`` at every step."""
        if self.window == 1:
            return g
        overflowed = torch.isinf(g)  # (g ≥ 0: +∞, beyond every threshold)
        if not bool(overflowed.any()):
            return _window_sums(g, self.window)
        # the running total stays +∞ after one overflowed g, and ∞ − ∞ had made every later
        # window NaN, which never alarms (an FDI trial: an attack W steps on missed): the
        # finite values' sums, +∞ where the window holds an overflowed one
        sums = _window_sums(torch.where(overflowed, torch.zeros_like(g), g), self.window)
        held = _window_sums(overflowed.to(g.dtype), self.window) > 0
        return torch.where(held, torch.full_like(sums, math.inf), sums)

    def thresholds(self, num_steps: int, dtype=torch.float64) -> Tensor:
        """Per-step thresholds ``[T]`` (smaller windows at the start): the quantile of each
        step's full window, ``m·min(t, W)`` degrees of freedom."""
        table = self._quantile_table(torch.empty(0, dtype=dtype))
        return table[self._full_dof(num_steps).long()]

    def detect(
        self, innovations: Tensor, innovation_covs: Tensor, mask: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """``(scores [..., T], alarms [..., T])``.

        ``mask [..., T, m]`` (the filter's, ``True`` where received): a filter gives an
        entry it did not receive innovation 0 and variance 1, so ``g_k`` has ``m_k``
        degrees of freedom, the entries received; each step's window is then judged
        against ``χ²`` of the degrees of freedom it holds (no alarm without one). Without
        the mask a masked result was judged against ``χ²_{mW}`` and alarmed far below
        ``α`` (0.016 for 0.05 with half the entries lost)."""
        if mask is None:
            s = self.scores(innovations, innovation_covs)
            return s, s > self.thresholds(s.shape[-1], s.dtype).to(s.device)
        _check_sequence(innovations, "innovations", 1)
        mask = _check_whole_mask(mask, innovations)
        s = self.scores(innovations, innovation_covs, mask=mask)
        dof = self._windowed(mask.sum(-1).to(torch.float64))
        limit = self._quantile_table(s)[dof.long()]
        full = self._full_dof(s.shape[-1]).to(s.device)
        alarm = s > limit
        table = self._quantile_table(s)
        return _agreeing(chi_square_equivalent(s, dof, full), alarm, table[full.long()]), alarm

    # -- online use (one step at a time, e.g. to gate a filter's update) ----------------
    def init(
        self, batch_shape=(), *, dtype=torch.float64, device=None
    ) -> tuple[Tensor, int, Tensor]:
        """Online state: the last ``W − 1`` values of ``g`` ``[*batch, W − 1]``, the step
        count and the entries each of them received ``[*batch, W − 1]``."""
        past = torch.zeros(torch.Size(batch_shape) + (self.window - 1,), dtype=dtype,
                           device=device)  # fmt: skip
        # the thresholds now, not at the first step (importing SciPy for the quantiles took a
        # deployment trial's first step 0.6–1.6 s, past any real-time deadline)
        self._quantile_table(past)
        return past, 0, torch.zeros_like(past, dtype=torch.float64)

    def check_state(self, state, dtype: torch.dtype, name: str = "state") -> None:
        """``ValueError`` naming ``name`` where ``state`` is not an online state of this
        detector (:meth:`init`'s layout, ``dtype``): non-negative window values (``+inf``
        where an overflowed statistic is held, never NaN)
        ``[..., W − 1]``, an integer step count ``≥ 0`` and the entries received."""
        if not isinstance(state, tuple) or len(state) not in (2, 3):
            raise ValueError(f"{name} must be the (window, count, received) of {type(self).__name__}"
                             f".init; got {type(state).__name__}")  # fmt: skip
        past, count = state[0], state[1]
        _check_state_tensor(past, f"{name}[0] (the window's values)", dtype, self.window - 1)
        if isinstance(count, bool) or not isinstance(count, numbers.Integral) or count < 0:
            raise ValueError(f"{name}[1] (the step count) must be an integer >= 0; got {count!r}")
        if len(state) == 3:
            received = state[2]
            _check_state_tensor(received, f"{name}[2] (the entries received)", torch.float64,
                                self.window - 1)  # fmt: skip
            if received.shape != past.shape:
                raise ValueError(f"{name}[2] must have the window's shape {tuple(past.shape)}; "
                                 f"got {tuple(received.shape)}")  # fmt: skip

    def _all_received(self, past: Tensor, count: int) -> Tensor:
        """The entries received of a window whose steps all arrived (a state of
        ``(past, count)``, as :meth:`init` made before masks were counted): ``m`` for each
        step held, ``0`` for the slots before the first step."""
        held = torch.full(past.shape, float(self.dim), dtype=torch.float64, device=past.device)
        empty = max(self.window - 1 - count, 0)
        held[..., :empty] = 0.0
        return held

    def _check_state(self, past: Tensor, held: list) -> None:
        """A state :meth:`init` made for this ``window`` and ``dim``: both may be assigned
        later, and a state of another window kept its old ``g`` values in every score (a
        window set from 3 to 1 read ``g + 10`` at every step and alarmed at each: a detector
        trial), one of a larger ``dim`` indexed past the quantile table; its values
        statistics and counts (a NaN window had scored NaN, never alarming, as a CUSUM's S; a
        negative count received judged the window at fewer degrees: a review)."""
        if not isinstance(past, Tensor) or past.dim() < 1 or past.shape[-1] != self.window - 1:
            held_steps = past.shape[-1] if isinstance(past, Tensor) and past.dim() else None
            raise ValueError(
                f"state must be this detector's init() state, holding window - 1 = "
                f"{self.window - 1} past values; it holds {held_steps} (made for another "
                "window: call init() again after changing window)"
            )
        if self.window > 1:  # (an empty window holds no values)
            _check_state_tensor(past, "state[0] (the window's values)", past.dtype, None)
            if held:
                _check_state_tensor(held[0], "state[2] (the entries received)", held[0].dtype,
                                    None)  # fmt: skip
        if held and bool((held[0] > self.dim).any()):
            raise ValueError(
                f"state counts up to {float(held[0].max()):g} entries received at one step, "
                f"more than dim = {self.dim} (made for another dim: call init() again)"
            )

    def step(
        self, state: tuple[Tensor, int, Tensor], g: Tensor, mask: Tensor | None = None
    ) -> tuple[tuple[Tensor, int, Tensor], Tensor, Tensor]:
        """Feed ``g_k [...]`` (and ``mask_k [..., m]``, the entries received, where some
        were lost); returns ``(state, score [...], alarm [...])`` as :meth:`detect` would
        with the same masks (without one, every entry counts as received: a masked ``g``
        was judged against ``χ²_m`` and alarmed 0.07 % for 1 % where one of 3 arrived).

        ``ValueError`` for a NaN, ``−inf`` or negative ``g`` (``+inf``, an overflowed
        statistic, alarms), or a state :meth:`init` made for another ``window`` or ``dim``."""
        _check_statistic(g, "g", alarm_on_inf=True, nonnegative=True)
        past, count, *held = state
        self._check_state(past, held)
        _check_step_runs(g, past.shape[:-1], "ChiSquareDetector")
        g = g.expand(past.shape[:-1])  # (one g for every run: the window holds it per run)
        past_dof = held[0] if held else self._all_received(past, count)
        score = g + past.sum(-1)
        full = self.dim * min(count + 1, self.window)
        received = None
        if mask is None and (self.window == 1 or bool((past_dof.sum(-1) == full - self.dim).all())):
            alarm = score > self.quantile(full)  # every entry of the window received
        else:
            if mask is None:  # this step's entries all received, earlier ones of the window not
                mask = torch.ones(g.shape + (self.dim,), dtype=torch.bool, device=g.device)
            mask = _step_mask(mask, g, self.dim, score.shape)
            received = mask.sum(-1).to(torch.float64)
            dof = received + past_dof.sum(-1)
            table = self._quantile_table(score)
            alarm = score > table[dof.long()]
            score = _agreeing(chi_square_equivalent(score, dof, full), alarm, table[full])
        if self.window > 1:
            past = torch.cat([past[..., 1:], g.unsqueeze(-1)], dim=-1)
            got = (
                torch.full_like(g, self.dim, dtype=torch.float64) if received is None else received
            )
            got = got.expand(past.shape[:-1])
            past_dof = torch.cat([past_dof.expand(past.shape)[..., 1:], got.unsqueeze(-1)], -1)
        return (past, count + 1, past_dof), score, alarm


class CusumDetector:
    """CUSUM on the normalised innovation squared (Page 1954; Murguia & Ruths 2016).

    ``S_k = max(0, S_{k−1} + g_k − b)``; alarm when ``S_k > τ``, then ``S_k ← 0``.
    ``b > m`` (the mean of ``g`` without attack) makes ``S`` drift down when there is no
    attack. Use :meth:`calibrate` to pick ``τ`` for a target false-alarm rate by Monte
    Carlo on attack-free statistics.

    Args:
        bias: ``b``, a finite number ``> 0``.
        threshold: ``τ``, a finite number ``≥ 0`` (``None`` until calibrated). A NaN
            threshold would never alarm (``S > NaN`` is false) and is rejected, like
            negative and infinite ones.

    NaN, ``−inf`` or negative statistics ``g`` raise ``ValueError``; ``+inf`` alarms (module
    docstring).
    """

    def __init__(self, bias: float, threshold: float | None = None):
        self.bias, self.threshold = bias, threshold

    def __setattr__(self, name, value):
        # checked whenever set (a NaN threshold assigned after __init__ never alarmed)
        if name == "bias":
            value = check_finite_number(value, "bias", positive=True)
        elif name == "threshold":
            value = None if value is None else _check_threshold(value)
        super().__setattr__(name, value)

    def __repr__(self) -> str:
        tau = "None" if self.threshold is None else f"{self.threshold:.6g}"
        return f"CusumDetector(bias={self.bias:.6g}, threshold={tau})"

    def run(self, g: Tensor, threshold: float | None = None) -> tuple[Tensor, Tensor]:
        """``(statistic [..., T], alarms [..., T])`` with reset after each alarm."""
        tau = self.threshold if threshold is None else _check_threshold(threshold)
        if tau is None:
            raise ValueError("threshold is not set: pass threshold= or call calibrate() first")
        # (+inf, an overflowed statistic, alarms and resets, as in step())
        _check_sequence(g, "g", 0, alarm_on_inf=True, nonnegative=True)
        s = torch.zeros_like(g[..., 0])
        stats, alarms = [], []
        for t in range(g.shape[-1]):
            s = torch.clamp(s + g[..., t] - self.bias, min=0.0)
            alarm = s > tau
            stats.append(s)
            alarms.append(alarm)
            s = torch.where(alarm, torch.zeros_like(s), s)
        return torch.stack(stats, -1), torch.stack(alarms, -1)

    def scores(self, g: Tensor) -> Tensor:
        """Statistic without resets ``[..., T]``: a threshold-free score for ROC curves
        (``+inf`` from an overflowed ``g`` on)."""
        _check_sequence(g, "g", 0, alarm_on_inf=True, nonnegative=True)
        s = torch.zeros_like(g[..., 0])
        out = []
        for t in range(g.shape[-1]):
            s = torch.clamp(s + g[..., t] - self.bias, min=0.0)
            out.append(s)
        return torch.stack(out, -1)

    def detect(
        self, innovations: Tensor, innovation_covs: Tensor, mask: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """``(scores [..., T], alarms [..., T])`` from innovations and their covariances.

        ``mask [..., T, m]`` (the filter's, ``True`` where received): ``g_k`` counts each
        missing entry's mean, ``g_k + m − m_k`` (:func:`missing_entries_counted`), as the
        gated filter and :func:`~difffilter.fdi.gated.cusum_detector_for` do (a threshold
        they calibrated alarmed 0.69 % for 1 % here before)."""
        _check_sequence(innovations, "innovations", 1)
        if mask is not None:
            mask = _check_whole_mask(mask, innovations)
        g = normalized_innovation_squared(innovations, innovation_covs, mask=mask)
        if mask is not None:
            g = missing_entries_counted(g, mask)
        _, alarms = self.run(g)
        return self.scores(g), alarms

    # -- online use ----------------------------------------------------------------------
    def init(self, batch_shape=(), *, dtype=torch.float64, device=None) -> Tensor:
        """Online state ``S_0 = 0`` ``[*batch]``."""
        return torch.zeros(torch.Size(batch_shape), dtype=dtype, device=device)

    def check_state(self, state, dtype: torch.dtype, name: str = "state") -> None:
        """``ValueError`` naming ``name`` where ``state`` is no online state ``S ≥ 0`` of
        ``dtype`` (``+inf`` after an overflowed statistic; never NaN: a NaN S had never
        alarmed again)."""
        _check_state_tensor(state, f"{name} (the statistic S)", dtype, None)

    def step(
        self, state: Tensor, g: Tensor, mask: Tensor | None = None, *, dim: int | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """``S_k = max(0, S_{k−1} + g_k − b)``; returns ``(state, S_k, alarm)``, resetting after an alarm.

        ``mask [..., m]`` (this step's, ``True`` where received; as
        :meth:`ChiSquareDetector.step` takes it): ``g_k`` counts each missing entry's
        mean, ``g_k + m − m_k``, as :meth:`detect` does (a recorded-log trial fed the raw NIS
        online under packet loss and differed from ``detect`` on 3 alarms). The CUSUM does
        not know ``m``: the mask's width is taken for it, or checked against ``dim`` where
        given (a 2-wide mask on 3 sensors counted one missing entry for two: a recorded-log
        trial)."""
        if self.threshold is None:
            raise ValueError("threshold is not set: pass threshold= or call calibrate() first")
        _check_statistic(g, "g", alarm_on_inf=True, nonnegative=True)
        if not isinstance(state, Tensor):
            raise TypeError(
                f"state must be CusumDetector.init's tensor; got {type(state).__name__}"
            )
        # its values too (a NaN S had scored NaN and never alarmed again, a negative one
        # cancelled the evidence: GatedFilter checked its carry's, a direct step did not)
        self.check_state(state, state.dtype)
        _check_step_runs(g, state.shape, "CusumDetector")
        if mask is not None:
            mask = torch.as_tensor(mask, device=g.device)
            if mask.dim() == 0:
                raise ValueError("mask must be [..., m]: the step's received entries")
            width = mask.shape[-1] if dim is None else dim
            g = missing_entries_counted(g, _step_mask(mask, g, width, g.shape))
        s = torch.clamp(state + g - self.bias, min=0.0)
        alarm = s > self.threshold
        return torch.where(alarm, torch.zeros_like(s), s), s, alarm

    def calibrate(
        self, g_attack_free: Tensor, false_alarm_rate: float, *, iterations: int = 40
    ) -> float:
        """Set ``τ`` so that the alarm rate on attack-free ``g [..., T]`` is ``false_alarm_rate``.

        Bisection on ``τ`` (the alarm rate is non-increasing in ``τ``); returns and
        stores ``τ``.
        """
        false_alarm_rate = check_rate(false_alarm_rate, "false_alarm_rate")  # (a "0.01" too)
        # (0 bisections returned the bracket's top, max Σg: no alarm at all, unsaid)
        iterations = check_positive_int(iterations, "iterations")
        _check_calibration_sequence(g_attack_free, "g_attack_free")
        mean = float(_finite_mean(g_attack_free))
        if self.bias <= mean:  # (taken without a word before: a closed-loop trial)
            warnings.warn(
                f"CusumDetector: the drift b = {float(self.bias):.4g} is not above the mean of "
                f"g_attack_free ({mean:.4g}): without an attack the statistic grows without "
                "bound, so τ only sets how often it is reset; take b above E[g] (m for the NIS "
                "of m entries)",
                stacklevel=2,
            )
        most = float(self.run(g_attack_free, 0.0)[1].double().mean())
        if most < false_alarm_rate:  # (it returned τ ≈ 0 at that lower rate, unsaid)
            steps = g_attack_free.numel()
            # too few steps to see that rate at all (a one-step YAML scenario's 8 runs read
            # as a rate out of reach, which blamed the rate for the sample's size)
            need = 1.0 / false_alarm_rate  # (inf for a subnormal rate: no count to give)
            few = (
                f"; a rate of {false_alarm_rate} needs at least {math.ceil(need)} attack-free "
                "steps to calibrate on (more runs or steps)"
                if steps < need < math.inf
                else ""
            )
            raise ValueError(
                f"false_alarm_rate {false_alarm_rate} is out of reach: this CUSUM (drift b = "
                f"{float(self.bias):.4g}) alarms on at most {most:.4g} of these {steps} steps "
                f"(g_attack_free {tuple(g_attack_free.shape)}), at τ = 0{few}"
            )
        lo, hi = 0.0, max(1.0, float(g_attack_free.sum(-1).max()))
        for _ in range(iterations):
            mid = 0.5 * (lo + hi)
            rate = float(self.run(g_attack_free, mid)[1].double().mean())
            if rate > false_alarm_rate:
                lo = mid
            else:
                hi = mid
        self.threshold = hi
        return hi


def _check_state_tensor(t, name: str, dtype: torch.dtype, last: int | None) -> None:
    """A detector state's tensor: of ``dtype``, ``≥ 0`` and not NaN (``+inf`` allowed: an
    overflowed statistic), of last size ``last``."""
    if not isinstance(t, Tensor) or t.dtype != dtype:
        got = t.dtype if isinstance(t, Tensor) else type(t).__name__
        raise ValueError(f"{name} must be a {dtype} tensor; got {got}")
    if last is not None and (t.dim() < 1 or t.shape[-1] != last):
        raise ValueError(f"{name} must have shape [..., {last}] (as this detector's init "
                         f"makes it); got {tuple(t.shape)}")  # fmt: skip
    # (+inf is a state the steps keep: an overflowed statistic, which alarms; a review)
    if values_known(t) and not bool(((t >= 0) & ~torch.isnan(t)).all()):
        raise ValueError(f"{name} must be >= 0 and not NaN (a detector's state)")


def _finite_mean(g: Tensor) -> Tensor:
    """The mean of the finite entries of ``g`` (float64; NaN where there are none)."""
    g = g.detach().double()
    return g[torch.isfinite(g)].mean()


def _check_step_runs(g: Tensor, runs: torch.Size, detector: str) -> None:
    """One statistic per run of an online state of ``runs`` (``g`` broadcasting to them): a
    ``g`` of more runs grew the state without a word, or failed in torch's own words (a
    deployment trial passed one run's innovation vector where its NIS belonged)."""
    if broadcast_or_none(g.shape, runs) != runs:
        raise ValueError(
            f"g must be one statistic per run of the state, {tuple(runs)} (the batch_shape "
            f"of {detector}.init), e.g. each run's NIS νᵀS⁻¹ν, not its innovation; got "
            f"{tuple(g.shape)}"
        )


def _check_whole_mask(mask: Tensor, innovations: Tensor) -> Tensor:
    """``mask`` of exactly the innovations' shape ``[..., T, m]``, as the filters take it (a
    ``[T, m]`` mask of one run had been broadcast to every run: 1.60 % alarms for 1.18 %)."""
    mask = check_mask(mask, "mask", innovations.shape)
    if mask.shape != innovations.shape:
        raise ValueError(
            f"mask must have the innovations' shape {tuple(innovations.shape)} (one per run "
            f"and step; mask.expand(...) for one schedule shared by every run); got "
            f"{tuple(mask.shape)}"
        )
    return mask


def _step_mask(mask, g: Tensor, dim: int, runs: torch.Size) -> Tensor:
    """One step's ``mask [..., dim]`` for the statistic ``g``, checked (boolean or 0/1,
    broadcasting to ``g``'s runs and ``dim``) and one row per run: a mask of more runs than
    the state (``runs``; a whole ``[T, m]`` mask given to one run's step) grew the state
    without a word."""
    mask = mask if isinstance(mask, Tensor) else torch.as_tensor(mask)
    mask = check_mask(mask, "mask", mask.shape)  # boolean or 0/1; its shape is judged below
    if broadcast_or_none(mask.shape, g.shape + (dim,)) is None:
        raise ValueError(
            f"mask must broadcast to {tuple(g.shape + (dim,))}; got {tuple(mask.shape)}"
        )
    if mask.shape[-1] != dim:  # (a [..., 1] mask broadcast, and its sum counted 1 of m)
        raise ValueError(
            f"mask must be [..., {dim}] (dim = {dim} measured entries); got {tuple(mask.shape)}"
        )
    if broadcast_shapes(mask.shape[:-1], runs) != runs:
        raise ValueError(
            f"mask [..., {dim}] must be one row per run of g {tuple(g.shape)} (or broadcast "
            f"to it); got {tuple(mask.shape)}"
        )
    return mask


def missing_entries_counted(g: Tensor, mask: Tensor) -> Tensor:
    """``g_k + m − m_k``: the NIS ``g [...]`` of a masked result with each of the ``m − m_k``
    entries not received (``mask [..., m]`` false) counted at its mean, 1, so a CUSUM's drift
    ``b`` (set for ``m`` entries) keeps its meaning (module docstring)."""
    # (a float mask of 0.5s had counted half entries, a numpy one or one of other runs
    # failed inside torch: an apishapes trial)
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool or mask.dim() < 1:
        got = (
            f"{mask.dtype} {tuple(mask.shape)}" if isinstance(mask, Tensor) else type(mask).__name__
        )
        raise ValueError(f"mask must be a bool tensor [..., m] (True where received); got {got}")
    if not isinstance(g, Tensor) or not g.is_floating_point():
        got = g.dtype if isinstance(g, Tensor) else type(g).__name__
        raise ValueError(f"g must be a floating tensor (the NIS); got {got}")
    try:
        torch.broadcast_shapes(g.shape, mask.shape[:-1])
    except RuntimeError:
        raise ValueError(
            f"mask {tuple(mask.shape)} must be g's shape {tuple(g.shape)} plus the entries' axis"
        ) from None
    return g + (mask.shape[-1] - mask.sum(-1)).to(g.dtype)


def _check_threshold(value) -> float:
    return check_finite_number(value, "threshold", nonnegative=True)
