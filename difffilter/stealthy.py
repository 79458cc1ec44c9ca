"""Optimal stealthy attacks crafted by gradient through a differentiable estimator.

The attacker knows the defender's model, its estimator and its detector (Kerckhoffs: the
worst case), and designs one deterministic sensor attack ``a_1 … a_T`` (zero before
``onset`` and outside ``entries``) on training noise::

    maximise   J(a) = mean over runs b and attacked steps k of  ‖x̂_k(ỹ) − x_k‖²,   ỹ = y + a
    subject to p(a) = mean over runs and attacked steps of 1[s_{b,k}(ỹ) > τ] ≤ α + ε

(``p(0) ≈ α`` when ``τ`` is calibrated, so the budget is an increase of ``ε`` in the
detector's alarm rate over the attacked steps: the rate a defender would see)

with ``s`` the detector's statistic (the estimator's ``detection.scores``: the NIS of a
χ²-gated filter, the learned head's probability of attack, …), ``τ`` its threshold at the false-alarm rate
``α`` and ``ε`` the slack allowed (the attack may raise the alarm rate that much). The
indicator is smoothed, ``1[s > τ] ≈ σ((s − τ)/t)`` (``t`` a fraction of the statistic's
attack-free standard deviation), which overstates the rate, so the
smoothed constraint bounds the increase over the attack-free run, ``p̃(a) − p̃(0) ≤ ε``;
it enters as a penalty, and the problem is solved by Adam on ``a`` through the estimator's
whole-sequence run (:func:`difffilter.loop.open_loop`)::

    L(a) = − J(a)/J₀ + ρ max(0, p̃(a) − p̃(0) − ε)² / ε²

``J₀`` is ``J`` at the start (a scale). The attack returned is the iterate of largest ``J``
whose *hard* alarm rate on the training runs, ``p(a) − p(0) ≤ ε``, keeps the budget (the
smoothed rate guides the gradient; the hard one decides). The result is a
:class:`~difffilter.attack.TabulatedAttack` (:class:`CraftedAttack`) to be judged on fresh
noise, where the detector's real alarm rate and the error it caused are measured.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch
from torch import Tensor

from ._checks import check_finite_number, check_positive_int, check_rate
from .attack import Channel, TabulatedAttack
from .estimator import Estimator
from .loop import open_loop

__all__ = ["CraftedAttack", "StealthySettings", "craft_stealthy_attack"]


def _check_batch(model, ys, xs) -> None:
    """``ys [B, T, dy]`` and ``xs [B, T, dx]`` of ``model``'s sizes, one batch dimension."""
    for name, t, d, what in (("ys", ys, model.dim_y, "dy"), ("xs", xs, model.dim_x, "dx")):
        if not isinstance(t, Tensor) or t.dim() != 3 or t.shape[-1] != d:
            got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"{name} must be a tensor [B, T, {what} = {d}]; got {got}")
    if xs.shape[:2] != ys.shape[:2]:
        raise ValueError(
            f"xs must hold the states of ys's runs and steps, [{ys.shape[0]}, {ys.shape[1]}, "
            f"{model.dim_x}]; got {tuple(xs.shape)}"
        )


def _check_onset(onset, T: int) -> None:
    """The first attacked measurement, 1-based, within the ``T`` steps."""
    if isinstance(onset, bool) or not isinstance(onset, numbers.Integral) or not 1 <= onset <= T:
        raise ValueError(f"onset must be an integer in [1, {T}] (1-based); got {onset!r}")


def _check_entries(entries, dy: int) -> tuple[int, ...]:
    """Distinct measurement entries in ``[0, dy)`` (no negative index: ``-1`` is not
    taken for the last entry), at least one."""
    try:
        picked = tuple(entries)
    except TypeError:
        raise ValueError(
            f"entries must be a list of measurement entries in [0, {dy}); got {entries!r}"
        ) from None
    bad = [e for e in picked
           if isinstance(e, bool) or not isinstance(e, numbers.Integral) or not 0 <= e < dy]  # fmt: skip
    if not picked or bad or len(set(picked)) != len(picked):
        raise ValueError(
            f"entries must be distinct measurement entries in [0, {dy}), at least one; got "
            f"{entries!r}"
        )
    return tuple(int(e) for e in picked)


#: Round-off allowed when a hard alarm rate is held to ``p(0) + ε``. A rate is a count over
#: ``n`` (run, step) pairs, ``k/n``, so one more alarm moves it by ``1/n`` (above 1e-9 for
#: any batch that fits in memory), while the bound ``k₀/n + ε`` is rounded on its addition:
#: an attack exactly ``ε`` above ``p(0)`` (``(k₀ + εn)/n``) can compare above it (115 of
#: 1,500 such cases at n = 100–10,000, k₀ < 60, ε = 0.001–0.01). The tolerance admits
#: that round-off and no further alarm.
_BUDGET_ROUND_OFF = 1e-12


def _keeps_budget(rate: float, budget: float) -> bool:
    """``rate ≤ budget`` up to the round-off of the budget's sum (:data:`_BUDGET_ROUND_OFF`)."""
    return rate <= budget + _BUDGET_ROUND_OFF


class CraftedAttack(TabulatedAttack):
    """A crafted sensor attack: ``values [T, dy]`` (the same for every run), injected at
    every step from ``onset`` on (flag where the step is attacked). ``budget``: the hard
    alarm rate an iterate had to keep, ``p(0) + ε`` (module docstring), when crafted."""

    channel = Channel.SENSOR

    def __init__(self, values: Tensor, onset: int, history: list | None = None, settings=None,
                 budget: float | None = None):  # fmt: skip
        if not isinstance(values, Tensor) or values.dim() != 2:
            raise ValueError(
                f"values must be a tensor [T, dy]; got {getattr(values, 'shape', values)!r}"
            )
        _check_onset(onset, values.shape[0])
        self.values, self.onset = values.detach().clone(), int(onset)
        self.history, self.settings, self.budget = list(history or []), settings, budget

    def within_budget(self) -> list:
        """The ``history`` rows of the iterates that kept the alarm budget (rate ≤
        :attr:`budget`; every row without one): :attr:`values` is the best of them by J,
        zeros where there is none."""
        return [h for h in self.history if self.budget is None or _keeps_budget(h[3], self.budget)]

    def sample(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        if tuple(self.values.shape) != (num_steps, dim):
            raise ValueError(
                f"the crafted attack is [{self.values.shape[0]}, {self.values.shape[1]}]; the "
                f"loop needs [{num_steps}, {dim}]"
            )
        shape = torch.Size((batch_shape,) if isinstance(batch_shape, int) else batch_shape)
        flags = (torch.arange(1, num_steps + 1, device=device) >= self.onset).expand(
            *shape, num_steps
        )
        values = self.values.to(dtype=dtype, device=device).expand(*shape, num_steps, dim)
        return values, flags


@dataclass(frozen=True)
class StealthySettings:
    """The optimiser's settings (module docstring): ``iterations`` of Adam at ``lr``,
    smoothing temperature ``temperature`` (in units of the statistic's standard deviation
    over the attacked steps of the attack-free training run, so that one setting fits a
    χ² statistic and a learned probability alike), penalty weight
    ``penalty``, slack ``slack`` (ε) over the false-alarm rate, and the start: a bias of
    ``init`` times the measurement noise's standard deviation."""

    iterations: int = 300
    lr: float = 0.01
    temperature: float = 0.18
    penalty: float = 50.0
    slack: float = 0.003
    init: float = 0.3

    def __post_init__(self):
        # frozen: the checked values are set through object.__setattr__ (a number from
        # YAML or numpy becomes the plain int or float the optimiser expects)
        set_ = object.__setattr__
        set_(self, "iterations", check_positive_int(self.iterations, "iterations"))
        for name in ("lr", "temperature"):
            set_(self, name, check_finite_number(getattr(self, name), name, positive=True))
        set_(self, "penalty", check_finite_number(self.penalty, "penalty", nonnegative=True))
        set_(self, "init", check_finite_number(self.init, "init"))
        slack = check_finite_number(self.slack, "slack", positive=True)
        if slack >= 1:  # ε is an increase of a rate: 1 would allow every step to alarm
            raise ValueError(
                f"slack (ε, an increase of the alarm rate) must be in (0, 1); got {slack!r}"
            )
        set_(self, "slack", slack)


def craft_stealthy_attack(
    estimator: Estimator,
    model,
    ys: Tensor,
    xs: Tensor,
    threshold: float,
    *,
    far: float,
    us: Tensor | None = None,
    mask: Tensor | None = None,
    onset: int = 1,
    entries: tuple[int, ...] | None = None,
    settings: StealthySettings = StealthySettings(),
    generator=None,
    start=None,
    resample=None,
    progress=None,
) -> CraftedAttack:
    """Craft a stealthy sensor attack against ``estimator``'s detector (module docstring).

    Args:
        estimator: a differentiable :class:`~difffilter.estimator.Estimator` whose steps
            score (``detection.scores``: higher means attack).
        model: its model. ys: clean training measurements ``[B, T, dy]``; xs: the true
            states ``[B, T, dx]``; us: the inputs the estimator knows ``[B, T, du]``, or
            ``None``; mask: the entries received ``[B, T, dy]`` (a lossy network), or
            ``None``. Give the estimator what it gets in the study: a filter stepped
            without a plant's known inputs alarms on most attack-free steps (49–73 % at
            a 1 % threshold in a trial), and the budget ``p(0) + ε`` then bounds nothing.
        threshold: ``τ`` of the detector at the false-alarm rate ``far``.
        onset: first attacked measurement (1-based); entries: attacked measurement entries
            (``None``: all).
        generator: ``() → generator`` of the estimator's own draws (the same at every
            iteration), or ``None``.
        start: ``runs → carry``, the estimator's starting carry (the same draws at every
            iteration: a particle filter's initial particles and generators), or ``None``
            (``estimator.init``). A particle filter's gradient flows through the particles
            and weights between resamplings, not through the resampler's discrete choice.
        resample: ``iteration → (ys, xs)`` or ``(ys, xs, us, mask)``, a fresh training
            batch for every iteration (stochastic optimisation over the noise: without it
            the attack may fit the training noise and alarm more on fresh noise); ``ys, xs``
            (``us``, ``mask``) are the first. The
            budget ``p(0) + ε`` is set on the first batch, and each iterate's hard rate is
            that of its own batch: the iterate kept is the best one that kept the budget on
            the batch it ran on, which another batch's noise may not confirm (judge it on
            fresh runs: the robustness study does).
        progress: ``(iteration, J, alarm rate) → None`` after every iteration, or ``None``.

    Returns a :class:`CraftedAttack` with ``history`` ``[(iteration, J, p̃(a) − p̃(0),
    p(a))]`` and ``budget`` ``p(0) + ε`` (zero if no iterate kept the budget, ``p(a) ≤
    budget``).
    """
    _check_batch(model, ys, xs)
    check_rate(far, "far")
    threshold = check_finite_number(threshold, "threshold")
    T, dy = ys.shape[-2:]
    _check_onset(onset, T)
    if entries is not None:
        entries = _check_entries(entries, dy)
    if not isinstance(settings, StealthySettings):
        raise TypeError(f"settings must be a StealthySettings; got {type(settings).__name__}")
    s = settings
    like = dict(dtype=ys.dtype, device=ys.device)
    attacked = (torch.arange(1, T + 1, device=ys.device) >= onset).to(ys.dtype)
    picked = torch.ones(dy, **like)
    if entries is not None:
        picked = torch.zeros(dy, **like)
        picked[list(entries)] = 1.0
    window = attacked.unsqueeze(-1) * picked  # [T, dy]
    sigma = model.measurement_cov(1).diagonal(dim1=-2, dim2=-1).sqrt().reshape(-1, dy)[0]
    # increments in units of σ: a_k = σ Σ_{j ≤ k} d_j, so a slow drift (what a filter
    # without a bias state follows without alarm) is a constant d, easy for Adam to find.
    # The rows before the onset inject nothing themselves but sum into the level at onset
    # (every one gets the onset row's gradient): Adam moves that level up to onset × lr an
    # iteration. Kept so, the crafted attacks of the reports were made this way.
    raw = torch.zeros(T, dy, **like)
    raw[onset - 1] = s.init
    raw.requires_grad_(True)
    optimiser = torch.optim.Adam([raw], lr=s.lr)
    on = attacked.bool()

    def run(received: Tensor, us: Tensor | None, mask: Tensor | None):
        carry = None if start is None else start(received.shape[0])
        gens = None if generator is None or carry is not None else generator()
        return open_loop(estimator, model, received, us, mask=mask, generator=gens, carry=carry)

    with torch.no_grad():
        free = run(ys, us, mask)
    # t in units of the attack-free statistic's spread: one setting fits any detector
    quiet = free.detection.scores[:, on]
    spread = float(quiet.std()) if quiet.numel() > 1 else math.nan
    if not math.isfinite(spread):
        raise ValueError(
            "craft_stealthy_attack needs the detector's attack-free scores on at least two "
            f"attacked (run, step) pairs, all finite, to set the smoothing's temperature; got "
            f"{quiet.numel()} (runs {tuple(ys.shape[:-2])}, onset {onset} of {T} steps)"
        )
    temperature = s.temperature * spread + 1e-12

    def smoothed_rate(out) -> Tensor:
        return torch.sigmoid((out.detection.scores - threshold) / temperature)[:, on].mean()

    def hard_rate(out) -> float:
        return float((out.detection.scores > threshold)[:, on].double().mean())

    with torch.no_grad():
        bound, hard_bound = smoothed_rate(free) + s.slack, hard_rate(free) + s.slack
    history, scale, best = [], None, (-1.0, torch.zeros(T, dy, **like))
    for it in range(s.iterations):
        a = raw.cumsum(0) * sigma * window
        if resample is not None and it > 0:
            ys, xs, *known = resample(it)
            if known:
                us, mask = known
        out = run(ys + a, us, mask)
        error = (out.means - xs).square().sum(-1)[:, on].mean()
        p = smoothed_rate(out)
        if scale is None:
            scale = error.detach().clamp_min(1e-12)
        excess = torch.relu(p - bound) / s.slack
        loss = -error / scale + s.penalty * excess.square()
        rate, value = hard_rate(out), float(error.detach())
        if _keeps_budget(rate, hard_bound) and value > best[0]:
            best = (value, a.detach().clone())
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        history.append((it, value, float(p.detach() - bound + s.slack), rate))
        if progress is not None:
            progress(it, value, rate)
    return CraftedAttack(best[1], onset, history, s, budget=hard_bound)
