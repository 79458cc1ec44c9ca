"""Optimal stealthy attacks crafted by gradient through a differentiable estimator.

The attacker knows the defender's model, its estimator and its detector (Kerckhoffs: the
worst case), and designs one deterministic sensor attack ``a_1 … a_T`` (zero before
``onset`` and outside ``entries``) on training noise::

    maximise   J(a) = mean over runs b and attacked steps k of  ‖x̂_k(ỹ) − x_k‖²,   ỹ = y + a
    subject to p(a) = mean over runs and attacked steps of 1[s_{b,k}(ỹ) > τ] ≤ α + ε

(``p(0) ≈ α`` when ``τ`` is calibrated, so the budget is an increase of ``ε`` in the
detector's alarm rate over the attacked steps: the rate a defender would see). The attacked
steps of run ``b`` are those the closed loop flags: from ``onset`` on, where an attacked
entry was received (under a mask, a Round-Robin schedule or a lossy network, not every step)

with ``s`` the detector's statistic (the estimator's ``detection.scores``: the NIS of a
χ²-gated filter, the learned head's probability of attack, …), ``τ`` its threshold at the false-alarm rate
``α`` and ``ε`` the slack allowed (the attack may raise the alarm rate that much). The
indicator is smoothed, ``1[s > τ] ≈ σ((s − τ)/t)`` (``t`` a fraction of the statistic's
attack-free standard deviation), which overstates the rate, so the
smoothed constraint bounds the increase over the attack-free run, ``p̃(a) − p̃(0) ≤ ε``;
it enters as a penalty, and the problem is solved by Adam on ``a`` through the estimator's
whole-sequence run (:func:`difffilter.loop.open_loop`)::

    L(a) = − log J(a) + ρ max(0, p̃(a) − p̃(0) − ε)² / ε²

The objective is ``log J``: its gradient ``∇J / J`` keeps one scale however far the error
grows, so the penalty keeps its weight. (It had been ``J/J₀``, ``J₀`` the first iterate's:
once the error grew 10–350× the penalty was swamped and about half the late iterates broke
the budget on their own batch; with ``log J`` 8–21 % on four_tank_bias, seeds 0–3.) With a
fresh training batch at every iteration (``resample``) both ``p̃(0)`` and ``p(0)`` are
that batch's own attack-free rates, so the batch's noise cancels in the difference (the
budget had been the first batch's ``p(0)``: a first batch with a lucky attack-free rate
gave every later iterate more room). An iterate *keeps the budget* where its hard alarm
rate on its batch is ``p(a) ≤ p(0) + ε`` (the smoothed rate guides the gradient; the hard
one decides).

The attack returned is chosen on a held-out batch (``select``) where one is given: the
iterates that kept the budget, in order of decreasing ``J``, are judged on it (at most
``candidates`` of them), and the first that keeps the budget there,
``p_sel(a) ≤ p_sel(0) + ε``, is returned. Choosing the largest ``J`` among the iterates
within budget on their own batches favours batches whose noise alarmed little: on
four_tank_bias that choice raised the alarm rate on 1,000 fresh runs by 2.1× ε (seed 0),
and in a trial on a 2-state plant by 2.4–3.1× ε. Without ``select`` the largest ``J``
within budget on its own batch is returned. The result is a
:class:`~difffilter.attack.TabulatedAttack` (:class:`CraftedAttack`) to be judged on fresh
noise, where the detector's real alarm rate and the error it caused are measured.
"""

from __future__ import annotations

import math
import numbers
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from ._checks import (
    check_finite_number,
    check_positive_int,
    check_rate,
    first_index,
    values_known,
)
from .attack import Channel, TabulatedAttack
from .estimator import Estimator
from .loop import open_loop
from .metrics import nan_as_lowest

__all__ = [
    "CraftedAttack",
    "StealthySettings",
    "TooFewAttackedSteps",
    "attacked_pairs",
    "craft_stealthy_attack",
]


class TooFewAttackedSteps(ValueError):
    """The batch a crafting runs on holds too few attacked (run, step) pairs received
    (none, or fewer than two with a finite attack-free score) to bound the alarm rate on
    or to set the smoothing's temperature: a late onset, packet loss. A ``ValueError``;
    adversarial training catches it alone and skips that crafting (another draw of runs
    and onset may hold enough)."""


def attacked_pairs(runs: int, steps: int, onset: int, entries=None, mask=None) -> Tensor:
    """The (run, step) pairs a sensor attack from ``onset`` (1-based) on ``entries``
    (``None``: all) is attacked on, as the closed loop flags them ``[runs, steps]`` (bool):
    from the onset, where an attacked entry is received (``mask [runs, steps, dy]``, the
    entries received; ``None``: every one). Under a Round-Robin schedule or packet loss
    that is not every step from the onset. Each argument is checked by name (onset 0 had
    marked every step, ``entries=[-1]`` the last entry, a mask of other runs or steps had
    failed inside torch: a stealthy trial)."""
    for name, value, least in (("runs", runs, 0), ("steps", steps, 0), ("onset", onset, 1)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < least:
            raise ValueError(f"{name} must be an integer >= {least}; got {value!r}")
    if mask is not None:
        if not isinstance(mask, Tensor) or mask.dtype != torch.bool or mask.dim() != 3:
            got = (
                f"{mask.dtype} {tuple(mask.shape)}"
                if isinstance(mask, Tensor)
                else type(mask).__name__
            )
            raise ValueError(f"mask must be a bool tensor [runs, steps, dy]; got {got}")
        if tuple(mask.shape[:2]) != (runs, steps):
            raise ValueError(f"mask must hold runs = {runs} and steps = {steps}: [{runs}, "
                             f"{steps}, dy]; got {tuple(mask.shape)}")  # fmt: skip
        if entries is not None:  # (the crafting's own check)
            entries = _check_entries(entries, mask.shape[-1])
    device = None if mask is None else mask.device
    on = torch.arange(1, steps + 1, device=device) >= onset
    if mask is None:
        return on.expand(runs, steps)
    return on & (mask & _entry_mask(mask.shape[-1], entries, device)).any(-1)


def _entry_mask(dim: int, entries, device=None) -> Tensor:
    """``[dim]`` (bool): the attacked entries (``None``: every one)."""
    if entries is None:
        return torch.ones(dim, dtype=torch.bool, device=device)
    picked = torch.zeros(dim, dtype=torch.bool, device=device)
    picked[list(entries)] = True
    return picked


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
    # the true states enter the objective J alone: a NaN there had made the attack NaN,
    # then blamed ys, finite, one iteration later (or, after one, a zero attack "raise
    # penalty or lower lr": a trial)
    if values_known(xs) and not bool(torch.isfinite(xs).all()):
        first = first_index(~torch.isfinite(xs))
        raise ValueError(f"xs contains NaN or Inf values (first at index {first}): the true "
                         "states must be finite")  # fmt: skip


def _batch_of(name: str, batch, model, T: int, us, mask) -> tuple:
    """A batch given as ``(ys, xs)`` or ``(ys, xs, us, mask)`` (``name``: ``select`` or what
    ``resample`` returned) as ``(ys, xs, us, mask)``: of ``model``'s sizes over the training
    batch's ``T`` steps (the attack is one table of ``T`` rows), with inputs and receptions
    where the training batch has them (``us``, ``mask``) and none where it has none: a
    filter stepped without a plant's known inputs alarms on most steps, and the budget then
    bounds nothing (a review: 95.9 % against 1.6 %, a held-out budget of 1.01; a pair from
    ``resample`` had kept the first batch's inputs, other runs', and the budgets from the
    second batch on were 0.94–0.96)."""
    sized = isinstance(batch, (tuple, list))
    if not sized or len(batch) not in (2, 4):
        got = f"{len(batch)} items" if sized else type(batch).__name__
        raise ValueError(f"{name} must be a batch (ys, xs) or (ys, xs, us, mask); got {got}")
    given = [n for n, t in (("us", us), ("mask", mask)) if t is not None]
    if len(batch) == 2 and given:
        raise ValueError(
            f"{name} must be (ys, xs, us, mask): the training batch has {' and '.join(given)}, "
            "and these runs need their own (None where the training batch has none)"
        )
    ys, xs, *known = batch
    if known:
        for n, train, own in zip(("us", "mask"), (us, mask), known):
            if (train is None) != (own is None):
                has = ("has none", f"gives {n}") if train is None else ("has one", f"gives no {n}")
                raise ValueError(
                    f"{name} {has[1]} where the training batch {has[0]}: give both batches the "
                    "same (a filter without the plant's known inputs alarms on most steps)"
                )
        us, mask = known
    try:
        _check_batch(model, ys, xs)
    except ValueError as err:
        raise ValueError(f"{name}: {err}") from None
    if ys.shape[1] != T:
        raise ValueError(f"{name} must span the training batch's {T} steps; got {ys.shape[1]}")
    return ys, xs, us, mask


def _warn_far_off(rate: float, steps: int, far: float, threshold: float) -> None:
    """Warn where the first batch's attack-free alarm rate ``p(0)`` over its ``steps``
    attacked (run, step) pairs is far from the false-alarm rate ``far`` the threshold is
    said to have: above ``3 far`` (at least 10 alarms), or below ``far / 3`` where ``far``
    would give at least 10. The budget ``p(0) + ε`` is relative to ``p(0)``: a trial's
    filter stepped without its plant's known inputs alarmed on 4.7 % at a 1 % threshold (a
    budget that bounds little), and an uncalibrated threshold of 1e9 on none, both
    silently."""
    if (rate > 3 * far and rate * steps >= 10) or (far * steps >= 10 and rate < far / 3):
        warnings.warn(
            f"craft_stealthy_attack: the detector alarms on {100 * rate:.3g} % of the first "
            f"batch's attack-free attacked steps at threshold {threshold:.4g}, against far = "
            f"{100 * far:g} %, and the budget p(0) + ε is relative to that rate: is the "
            "threshold calibrated for this estimator, and does it get the plant's known "
            "inputs (us) and receptions (mask) as where it is judged? (A detector whose "
            "false alarms fall at start-up alarms less after a late onset.)",
            RuntimeWarning, stacklevel=3,
        )  # fmt: skip


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


#: Why a crafted attack is zero where no iterate kept the alarm budget (the warning's words).
_NONE_KEPT = "no iterate kept the budget on its own batch"


def _keeps_budget(rate: float, budget: float) -> bool:
    """``rate ≤ budget`` up to the round-off of the budget's sum (:data:`_BUDGET_ROUND_OFF`)."""
    return rate <= budget + _BUDGET_ROUND_OFF


class CraftedAttack(TabulatedAttack):
    """A crafted sensor attack: ``values [T, dy]`` (the same for every run), injected at
    every step from ``onset`` on (flag where the step is attacked; with ``entries``, the
    attacked measurement entries, per entry: under a mask a step where only other entries
    arrived carries no attack, and had been flagged as attacked, a trial). ``budget``: the hard
    alarm rate the first iterate had to keep, its batch's ``p(0) + ε`` (module docstring;
    each ``history`` row ends with its own); ``selection``: how it was chosen on a held-out
    batch (:func:`craft_stealthy_attack`), or ``None``."""

    channel = Channel.SENSOR

    def __init__(self, values: Tensor, onset: int, history: list | None = None, settings=None,
                 budget: float | None = None, selection: dict | None = None,
                 entries: tuple[int, ...] | None = None):  # fmt: skip
        if not isinstance(values, Tensor) or values.dim() != 2:
            raise ValueError(
                f"values must be a tensor [T, dy]; got {getattr(values, 'shape', values)!r}"
            )
        _check_onset(onset, values.shape[0])
        self.entries = None if entries is None else _check_entries(entries, values.shape[1])
        self.values, self.onset = values.detach().clone(), int(onset)
        self.history, self.settings, self.budget = list(history or []), settings, budget
        self.selection = selection

    def within_budget(self) -> list:
        """The ``history`` rows of the iterates that kept the alarm budget on their own
        batch (rate ≤ the row's budget, else :attr:`budget`; every row without either) with a
        finite J.
        Without a held-out selection :attr:`values` is the best of them by J, zeros where
        there is none."""

        def budget(h):
            return h[4] if len(h) > 4 else self.budget

        return [h for h in self.history if math.isfinite(h[1])
                and (budget(h) is None or _keeps_budget(h[3], budget(h)))]  # fmt: skip

    def kept_error(self) -> float:
        """The crafting's objective ``J`` of the attack returned (:attr:`values`): with a
        held-out selection, the chosen iterate's ``J`` on the held-out batch; without one,
        the best ``J`` of :meth:`within_budget` on its own batch; 0.0 where the attack is
        zero (no iterate kept the budget)."""
        if self.selection is None:
            return max((h[1] for h in self.within_budget()), default=0.0)
        chosen = self.selection["iteration"]
        return next((j for it, j, _ in self.selection["judged"] if it == chosen), 0.0)

    def sample(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        if tuple(self.values.shape) != (num_steps, dim):
            raise ValueError(
                f"the crafted attack is [{self.values.shape[0]}, {self.values.shape[1]}]; the "
                f"loop needs [{num_steps}, {dim}]"
            )
        shape = torch.Size((batch_shape,) if isinstance(batch_shape, int) else batch_shape)
        on = torch.arange(1, num_steps + 1, device=device) >= self.onset
        if self.entries is None:
            flags = on.expand(*shape, num_steps)
        else:  # per entry: [*, T, dy]
            picked = _entry_mask(dim, self.entries, device)
            flags = (on.unsqueeze(-1) & picked).expand(*shape, num_steps, dim)
        values = self.values.to(dtype=dtype, device=device).expand(*shape, num_steps, dim)
        return values, flags


@dataclass(frozen=True)
class StealthySettings:
    """The optimiser's settings (module docstring): ``iterations`` of Adam at ``lr``,
    smoothing temperature ``temperature`` (in units of the statistic's standard deviation
    over the attacked steps of the attack-free training run, so that one setting fits a
    χ² statistic and a learned probability alike), penalty weight
    ``penalty``, slack ``slack`` (ε) over the false-alarm rate, the start: a bias of
    ``init`` times the measurement noise's standard deviation, and ``candidates``: how many
    iterates within budget at most are judged on the held-out batch (``select``)."""

    iterations: int = 300
    lr: float = 0.01
    temperature: float = 0.18
    penalty: float = 50.0
    slack: float = 0.003
    init: float = 0.3
    candidates: int = 32

    def __post_init__(self):
        # frozen: the checked values are set through object.__setattr__ (a number from
        # YAML or numpy becomes the plain int or float the optimiser expects)
        set_ = object.__setattr__
        for name in ("iterations", "candidates"):
            set_(self, name, check_positive_int(getattr(self, name), name))
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
    select=None,
    progress=None,
    warn_far_off: bool = True,
) -> CraftedAttack:
    """Craft a stealthy sensor attack against ``estimator``'s detector (module docstring).

    Args:
        estimator: a differentiable :class:`~difffilter.estimator.Estimator` whose steps
            score (``detection.scores``: higher means attack; NaN a step without a score,
            which never alarms and counts in the rates as the lowest score, as the
            calibration counts it).
        model: its model. ys: clean training measurements ``[B, T, dy]``; xs: the true
            states ``[B, T, dx]``; us: the inputs the estimator knows ``[B, T, du]``, or
            ``None``; mask: the entries received ``[B, T, dy]`` (a lossy network), or
            ``None``. Give the estimator what it gets in the study: a filter stepped
            without a plant's known inputs alarms on most attack-free steps (49–73 % at
            a 1 % threshold in a trial), and the budget ``p(0) + ε`` then bounds nothing.
        threshold: ``τ`` of the detector at the false-alarm rate ``far``. A warning where
            the first batch's attack-free rate over the attacked steps is far from ``far``
            (above 3 ``far``, or below ``far``/3 where ``far`` would give 10 alarms): the
            budget is relative to that rate.
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
            (``us``, ``mask``) are the first. Four items where the first batch has ``us``
            or ``mask``, each batch its own, ``None`` exactly where the first batch has none.
            Every batch spans the same ``T`` steps. The budget of each iterate is its own
            batch's ``p(0) + ε``.
        select: ``(ys, xs)`` or ``(ys, xs, us, mask)`` (four where the training batch has
            ``us`` or ``mask``, ``None`` exactly where it has none), a held-out batch of any
            number of runs over the same ``T`` steps on which the attack is chosen (module
            docstring; the robustness study gives 256 runs), or ``None``: the best iterate
            within budget on its own batch, which another batch's noise may not confirm
            (judge it on fresh runs: the robustness study does).
        progress: ``(iteration, J, alarm rate) → None`` after every iteration, or ``None``.
        warn_far_off: the warning of ``threshold`` above, or not (a caller that says the
            rate elsewhere: the adversary of a training logs it at every crafting, and the
            robustness study's report explains a detector whose alarms fall at start-up).

    Returns a :class:`CraftedAttack` (zero, with a ``RuntimeWarning``, where no iterate kept
    the budget) with ``history``
    ``[(iteration, J, p̃(a) − p̃(0), p(a), p(0) + ε)]`` (each on its own batch), ``budget``
    the first batch's ``p(0) + ε`` and, with ``select``, ``selection`` ``{"runs", "budget"
    (the held-out batch's p(0) + ε), "judged" [(iteration, J, p(a))], "iteration" (the one
    returned, or None)}``.
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
    held_out = None if select is None else _batch_of("select", select, model, T, us, mask)
    s = settings
    like = dict(dtype=ys.dtype, device=ys.device)
    attacked = (torch.arange(1, T + 1, device=ys.device) >= onset).to(ys.dtype)
    window = attacked.unsqueeze(-1) * _entry_mask(dy, entries, ys.device).to(ys.dtype)  # [T, dy]
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

    unseeded = generator is None and start is None

    def run(received: Tensor, us: Tensor | None, mask: Tensor | None):
        carry = None if start is None else start(received.shape[0])
        gens = None if generator is None or carry is not None else generator()
        if not unseeded:
            return open_loop(estimator, model, received, us, mask=mask, generator=gens,
                             carry=carry)  # fmt: skip
        before = torch.random.get_rng_state()
        out = open_loop(estimator, model, received, us, mask=mask)
        if not torch.equal(before, torch.random.get_rng_state()):
            # the attacked and attack-free runs would filter with other draws: the noise the
            # budget's p(a) − p(0) cancels did not (0.31 points, about ε, at the zero attack
            # of a particle filter), and no crafting repeated itself (a trial)
            raise ValueError(
                f"estimator {type(estimator).__name__} draws random numbers, and neither "
                "generator nor start is given: its runs drew from torch's global generator, "
                "so the attacked and attack-free runs filtered with other draws; give "
                "generator=lambda: torch.Generator().manual_seed(s) (or start=, its carry)"
            )
        return out

    def pairs(name: str, mask: Tensor | None, runs: int) -> Tensor:
        # the (run, step) pairs the loop calls attacked [B, T] (attacked_pairs). The rates
        # and J had been taken over every step from the onset: under a Round-Robin schedule
        # that delivers the attacked entries on a share f of the steps the budget ε bounded
        # the rise over all of them, and the rise over the steps judged was ε/f (a
        # threat-model trial: 1.5 ε with f = 1/2, 4.4 ε on tracking's four-sensor cycle)
        steps = attacked_pairs(runs, T, onset, entries, mask)
        if not bool(steps.any()):  # (the rates and J of no pair are NaN: Adam would take them)
            raise TooFewAttackedSteps(
                f"craft_stealthy_attack: the {name} batch receives no attacked entry from onset "
                f"{onset} on (mask{'' if entries is None else f' on entries {entries}'}): "
                "there is no attacked step to bound the alarm rate on"
            )
        return steps

    with torch.no_grad():
        free = run(ys, us, mask)
    on_batch = pairs("training", mask, ys.shape[0])
    # t in units of the attack-free statistic's spread: one setting fits any detector. A NaN
    # score is a step without a score (a window not yet full, a step without data): as in
    # the calibration and the scoring it never alarms, counts in the rates as the lowest
    # score and is left out of the spread (it had made the spread NaN and the crafting refuse
    # a detector whose warm-up the onset reached, onset 1 by default, with "got 800" pairs)
    quiet = free.detection.scores[on_batch]
    scored = quiet[torch.isfinite(quiet)]
    spread = float(scored.std()) if scored.numel() > 1 else math.nan
    if not math.isfinite(spread):
        raise TooFewAttackedSteps(
            "craft_stealthy_attack needs the detector's attack-free scores on at least two "
            f"attacked (run, step) pairs finite, to set the smoothing's temperature; got "
            f"{scored.numel()} finite of {quiet.numel()} (runs {tuple(ys.shape[:-2])}, onset "
            f"{onset} of {T} steps)"
        )
    temperature = s.temperature * spread + 1e-12

    def smoothed_rate(out, steps: Tensor) -> Tensor:
        # σ((s − τ)/t) with a NaN score as −∞: 0, no alarm, and no gradient
        scores = nan_as_lowest(out.detection.scores)
        return torch.sigmoid((scores - threshold) / temperature)[steps].mean()

    def squared_error(out, xs, steps: Tensor) -> Tensor:  # J: over the attacked (run, step) pairs
        return (out.means - xs).square().sum(-1)[steps].mean()

    def hard_rate(out, steps: Tensor) -> float:
        return float((out.detection.scores > threshold)[steps].double().mean())

    def free_rates(out, steps: Tensor) -> tuple[Tensor, float]:
        # the attack-free rates of a batch: p̃(0) (the penalty's reference) and p(0)
        return smoothed_rate(out, steps), hard_rate(out, steps)

    with torch.no_grad():
        reference = free_rates(free, on_batch)
    if warn_far_off:
        _warn_far_off(reference[1], int(on_batch.sum()), far, threshold)
    history, kept = [], []
    for it in range(s.iterations):
        a = raw.cumsum(0) * sigma * window
        if resample is not None and it > 0:
            ys, xs, us, mask = _batch_of(f"resample({it})", resample(it), model, T, us, mask)
            on_batch = pairs(f"resample({it})", mask, ys.shape[0])
            with torch.no_grad():  # this batch's own attack-free rates: its noise cancels
                reference = free_rates(run(ys, us, mask), on_batch)
        out = run(ys + a, us, mask)
        error = squared_error(out, xs, on_batch)
        p = smoothed_rate(out, on_batch)
        excess = torch.relu(p - reference[0] - s.slack) / s.slack
        loss = -error.clamp_min(1e-30).log() + s.penalty * excess.square()
        rate = hard_rate(out, on_batch)
        value, budget = float(error.detach()), reference[1] + s.slack
        if _keeps_budget(rate, budget) and math.isfinite(value):
            kept.append((value, it, a.detach().clone()))
        # the gradient of the attack alone: backward() had also filled the .grad of every
        # other leaf that requires one (ys, a learned estimator's weights, a model's
        # parameters), added to at every iteration under the caller's feet (a trial)
        (raw.grad,) = torch.autograd.grad(loss, raw, allow_unused=True)
        optimiser.step()
        history.append((it, value, float(p.detach() - reference[0]), rate, budget))
        if progress is not None:
            progress(it, value, rate)
    none = torch.zeros(T, dy, **like)
    if select is None:
        if not kept:  # a zero attack read as "the detector withstood it" (say why it is zero)
            warnings.warn(f"craft_stealthy_attack: {_NONE_KEPT}: the attack returned is zero; "
                          "raise penalty or lower lr", RuntimeWarning, stacklevel=2)  # fmt: skip
        best = max(kept, key=lambda k: k[0], default=(0.0, -1, none))
        return CraftedAttack(best[2], onset, history, s, budget=history[0][4], entries=entries)

    ys, xs, us, mask = held_out
    on_batch = pairs("select", mask, ys.shape[0])
    with torch.no_grad():  # the held-out runs' own attack-free rate: their budget
        budget = hard_rate(run(ys, us, mask), on_batch) + s.slack
    chosen, judged = None, []
    for _, it, a in sorted(kept, key=lambda k: -k[0])[: s.candidates]:
        with torch.no_grad():
            out = run(ys + a, us, mask)
        judged.append((it, float(squared_error(out, xs, on_batch)), hard_rate(out, on_batch)))
        if _keeps_budget(judged[-1][2], budget):
            chosen = (it, a)
            break
    if chosen is None:
        why = (f"none of the {len(judged)} iterates of largest error that kept the budget on "
               "their own batch kept it on the held-out batch (select)" if judged
               else _NONE_KEPT)  # fmt: skip
        warnings.warn(f"craft_stealthy_attack: {why}: the attack returned is zero; raise "
                      "penalty or candidates, or lower lr", RuntimeWarning, stacklevel=2)  # fmt: skip
    selection = {"runs": int(ys.shape[0]), "budget": budget, "judged": judged,
                 "iteration": None if chosen is None else chosen[0]}  # fmt: skip
    return CraftedAttack(none if chosen is None else chosen[1], onset, history, s,
                         budget=history[0][4], selection=selection, entries=entries)  # fmt: skip
