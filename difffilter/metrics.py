"""Evaluation metrics of the FDI literature (docs/metrics.md), batched over runs.

Conventions: alarms, attack flags and scores are ``[..., T]`` (runs first, time last);
counts and rates pool every run and step unless ``valid`` excludes some steps. The three
"since the attack" functions (:func:`steps_since_attack`, :func:`after_attack`,
:func:`alarm_rate_since_attack`) take ``[B, T, ...]`` instead (time on dim 1, trailing
axes the LFC plant's areas): pass ``time_dim=-1`` for runs ``[..., T]`` of several axes.
"""

from __future__ import annotations

import math
import numbers

import torch
from torch import Tensor

from ._checks import broadcast_or_none, check_rate

__all__ = [
    "rmse",
    "detection_counts",
    "detection_rates",
    "roc_curve",
    "roc_auc",
    "detection_delay",
    "threshold_for",
    "finite_scores",
    "nan_as_lowest",
    "after_attack",
    "steps_since_attack",
    "alarm_rate_since_attack",
]


def rmse(estimate: Tensor, truth: Tensor, *, dim=None) -> Tensor:
    """Root-mean-square error ``√mean((estimate − truth)²)`` over ``dim`` (all entries by default).

    ``estimate`` and ``truth`` broadcast (for example ``[B, T, d]`` each; ``truth`` may be
    a number, e.g. ``rmse(errors, 0.0)``); the result is a 0-d tensor, or the broadcast
    shape without ``dim``."""
    if isinstance(truth, numbers.Real) and not isinstance(truth, bool):
        truth = torch.as_tensor(truth, dtype=getattr(estimate, "dtype", None))
    _check_tensors(estimate=estimate, truth=truth)
    if broadcast_or_none(estimate.shape, truth.shape) is None:  # torch's "size of tensor a"
        raise ValueError(
            f"estimate {tuple(estimate.shape)} and truth {tuple(truth.shape)} must have one "
            "shape or broadcast (e.g. both [B, T, d]: the same runs and steps)"
        )
    if not estimate.is_floating_point() and not estimate.is_complex():  # integer counts:
        estimate = estimate.double()  # in float64 before the difference (torch's mean had
    if not truth.is_floating_point() and not truth.is_complex():  # refused a Long input;
        truth = truth.double()  # uint8 had wrapped at −, int16 overflowed at the square)
    sq = (estimate - truth).square()
    return torch.sqrt(sq.mean() if dim is None else sq.mean(dim=dim))


def _check_tensors(valid: object = None, **required: object) -> None:
    """Each of ``required`` is a ``torch.Tensor``, and ``valid`` one or ``None``: a numpy
    array (a notebook user's scores or alarms) failed on its missing ``.bool()``, in
    ``torch.ones_like`` or at ``-``, in errors that named no argument."""
    for name, value in (*required.items(), ("valid", valid)):
        if not isinstance(value, Tensor) and not (name == "valid" and value is None):
            either = " or None" if name == "valid" else ""
            raise TypeError(
                f"{name} must be a torch.Tensor{either} (torch.as_tensor(array) for a numpy "
                f"array); got {type(value).__name__}"
            )


def _check_labels(labels: Tensor, valid: Tensor | None = None) -> None:
    """ROC ``labels`` are bool or 0/1: ``.bool()`` took any other value (a score: the
    arguments swapped) for an attacked step, and the AUC came out ``nan``, "one class
    absent", without a word."""
    _check_binary(labels, valid, "labels", "(True on an attacked step)",
                  "are the arguments swapped? The scores come first, (scores, labels)")  # fmt: skip


def _check_binary(t: Tensor, valid: Tensor | None, name: str, meaning: str, hint: str) -> None:
    """``t`` is bool or holds only 0 and 1 where ``valid`` (the entries scored; another
    value marks an unscored step, e.g. −1 or NaN, as it may) (one reduction, and none for
    bool): ``.bool()`` reads any other value, a score passed for a decision, as ``True``,
    silently."""
    if t.dtype == torch.bool:
        return
    binary = (t == 0) | (t == 1)
    if valid is not None:
        binary = binary | ~valid.bool()  # broadcast both ways (labels [T] beside valid [B, T])
    if not bool(binary.all()):
        raise ValueError(
            f"{name} must be bool {meaning} or hold only 0 and 1; got {t.dtype} with other "
            f"values: {hint}"
        )


def _check_fits(primary: str, shape: torch.Size, **others: Tensor | None) -> None:
    """Each of ``others`` has the shape of ``primary`` or broadcasts to it (a labels tensor
    of 5 steps against scores of 17 failed inside torch's expand)."""
    for name, t in others.items():
        if t is None:
            continue
        if broadcast_or_none(t.shape, shape) != shape:
            raise ValueError(f"{name} {tuple(t.shape)} must have the shape of {primary} "
                             f"{tuple(shape)} (or broadcast to it)")  # fmt: skip


def _check_decisions(alarms: Tensor, attacked: Tensor, valid: Tensor | None = None) -> None:
    """Per-step ``alarms`` and ``attacked`` flags are bool or 0/1 (:func:`_check_binary`):
    scores given for the alarms (``detection_rates(scores, flags)``) were all "alarms"."""
    _check_binary(alarms, valid, "alarms", "(the detector's decisions, e.g. scores > threshold)",
                  "scores are decisions only against a threshold (scores > threshold)")  # fmt: skip
    _check_binary(attacked, valid, "attacked", "(True on an attacked step)",
                  "are the arguments swapped? The alarms come first, (alarms, attacked)")  # fmt: skip


def _valid(alarms: Tensor, valid: Tensor | None) -> Tensor:
    return (
        torch.ones_like(alarms, dtype=torch.bool)
        if valid is None
        else valid.bool().expand(alarms.shape)
    )


def detection_counts(
    alarms: Tensor, attacked: Tensor, valid: Tensor | None = None
) -> dict[str, int]:
    """Confusion counts of per-step decisions ``alarms [..., T]`` against ``attacked [..., T]``.

    Returns ``{"tp", "fp", "tn", "fn"}`` pooled over every run and step in ``valid``.
    """
    _check_tensors(alarms=alarms, attacked=attacked, valid=valid)
    _check_fits("alarms", alarms.shape, attacked=attacked, valid=valid)
    _check_decisions(alarms, attacked, valid)
    a, y = alarms.bool(), attacked.bool()
    v = _valid(a, valid)
    return {
        "tp": int((a & y & v).sum()),
        "fp": int((a & ~y & v).sum()),
        "tn": int((~a & ~y & v).sum()),
        "fn": int((~a & y & v).sum()),
    }


def detection_rates(
    alarms: Tensor, attacked: Tensor, valid: Tensor | None = None
) -> dict[str, float | int]:
    """Per-step TPR = TP/(TP+FN) and FPR = FP/(FP+TN), plus the counts.

    ``alarms``, ``attacked`` and ``valid`` (steps to score) are bool ``[B, T]`` (any equal
    shapes).

    ``false_alarms`` = FP and ``missed_attacks`` = FN (the paper's counts). Rates are
    ``nan`` when their denominator is zero.
    """
    c = detection_counts(alarms, attacked, valid)
    pos, neg = c["tp"] + c["fn"], c["fp"] + c["tn"]
    return {
        "tpr": c["tp"] / pos if pos else math.nan,
        "fpr": c["fp"] / neg if neg else math.nan,
        "false_alarms": c["fp"],
        "missed_attacks": c["fn"],
        **c,
    }


def roc_curve(
    scores: Tensor, labels: Tensor, valid: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """ROC by sweeping the threshold over every distinct score (alarm when score ≥ threshold).

    Returns ``(fpr [M], tpr [M], thresholds [M])`` starting at (0, 0) and ending at (1, 1)
    (at (1, 0) without a positive label, at (0, 1) without a negative one: a rate with
    no denominator stays 0),
    computed in float64. Ties are grouped, so the curve is exact for discrete scores.
    ``thresholds[i]`` (``i ≥ 1``) is the score at which point ``i`` is reached; the first
    point's ``+∞`` stands for "never alarm", also where some scores are ``+∞`` (a windowed
    χ² score under packet loss), which point 1 then alarms on at the same ``+∞``.
    """
    _check_scores(scores, labels, valid)
    tp, fp, thr, pos, neg = _roc_counts(scores, labels, valid)
    return fp / neg.clamp_min(1), tp / pos.clamp_min(1), thr


def _roc_counts(scores: Tensor, labels: Tensor, valid: Tensor | None = None):
    """``(tp [M], fp [M], thresholds [M], positives, negatives)``: the true- and false-alarm
    counts of :func:`roc_curve`'s points (float64, exact integers), from (0, 0); the
    callers check the inputs (:func:`_check_scores`)."""
    v = _valid(scores, valid)
    s = scores[v].double().flatten()
    y = labels.bool().expand(scores.shape)[v].flatten()
    order = torch.argsort(s, descending=True)
    s, y = s[order], y[order]
    tp = torch.cumsum(y.double(), 0)
    fp = torch.cumsum((~y).double(), 0)
    # keep the last index of each group of tied scores
    last = torch.ones_like(s, dtype=torch.bool)
    if s.numel() > 1:
        last[:-1] = s[1:] != s[:-1]
    tp, fp, thr = tp[last], fp[last], s[last]
    pos, neg = y.sum().double(), (~y).sum().double()
    zero = torch.zeros(1, dtype=torch.float64, device=s.device)
    thr = torch.cat([torch.tensor([math.inf], dtype=torch.float64, device=s.device), thr])
    return torch.cat([zero, tp]), torch.cat([zero, fp]), thr, pos, neg


def _check_scores(scores: Tensor, labels: Tensor, valid: Tensor | None) -> None:
    """Labels and ``valid`` fit ``scores``, and no valid score is NaN: a NaN sorted among
    the scores as it happened to fall (an AUC of 0.4877 where mapping NaN to the lowest
    score gives 0.4508); the labels are bool or 0/1 (:func:`_check_labels`)."""
    _check_tensors(scores=scores, labels=labels, valid=valid)
    _check_fits("scores", scores.shape, labels=labels, valid=valid)
    _check_labels(labels, valid)
    if bool(torch.isnan(scores[_valid(scores, valid)]).any()):
        raise ValueError("scores contain NaN (a step without a score): map them first, e.g. "
                         "difffilter.metrics.nan_as_lowest(scores), or mark them invalid")  # fmt: skip


def roc_auc(scores: Tensor, labels: Tensor, valid: Tensor | None = None) -> float:
    """Area under the ROC curve (trapezoid rule, summed in counts: exact for a perfect
    detector); ``nan`` if one class is absent.

    ``scores`` (higher means attack; finite: map NaN first), ``labels`` (bool, or 0/1:
    any other value is refused, e.g. the arguments swapped) and ``valid``: equal shapes,
    for example ``[B, T]``; every valid entry is one sample."""
    _check_scores(scores, labels, valid)
    y = labels.bool().expand(scores.shape)[_valid(scores, valid)]
    if bool(y.all()) or not bool(y.any()):
        return math.nan
    tp, fp, _, pos, neg = _roc_counts(scores, labels, valid)
    # the trapezoids in counts (exact integers) and one division: a perfect detector's area
    # is 1 exactly (the rates' trapezoids gave 1 ± 2.2e-16, and metrics.json read
    # AUC = 1.0000000000000002)
    twice = (torch.diff(fp) * (tp[1:] + tp[:-1])).sum()
    return float(twice / (2.0 * pos * neg))


def detection_delay(alarms: Tensor, attacked: Tensor) -> dict[str, float | int]:
    """Mean delay from the onset of each attack episode to the first alarm at or after it.

    ``alarms`` and ``attacked``: bool ``[B, T]`` (runs, steps).

    An episode is a maximal run of consecutive attacked steps in one run; its delay is
    ``first alarm index ≥ onset − onset`` if that alarm falls inside the episode, else
    the episode is missed. Returns ``{"mean_delay" (steps, nan if none detected),
    "episodes", "detected", "missed"}``. Vectorised over runs and steps.
    """
    _check_tensors(alarms=alarms, attacked=attacked)
    if alarms.shape[-1] == 0 or alarms.numel() == 0:  # no step (or no run): no episode
        return {"mean_delay": math.nan, "episodes": 0, "detected": 0, "missed": 0}
    _check_fits("alarms", alarms.shape, attacked=attacked)
    _check_decisions(alarms, attacked)
    a = alarms.bool().reshape(-1, alarms.shape[-1])
    y = attacked.bool().expand(alarms.shape).reshape(-1, alarms.shape[-1])
    T = y.shape[-1]
    prev = torch.cat([torch.zeros_like(y[:, :1]), y[:, :-1]], dim=1)
    onset = y & ~prev
    # episode id of each attacked step: cumulative count of onsets
    episode = torch.cumsum(onset.long(), dim=1)
    idx = torch.arange(T, device=y.device).expand_as(y)
    # first alarmed step inside each episode: min over (attacked & alarmed) steps grouped by (run, episode)
    hit = y & a
    n_ep = int(episode.max()) + 1 if y.numel() else 1
    key = torch.arange(y.shape[0], device=y.device).unsqueeze(1) * n_ep + episode
    big = torch.full((y.shape[0] * n_ep,), T, dtype=torch.long, device=y.device)
    first_hit = big.scatter_reduce(0, key[hit], idx[hit], reduce="amin")
    onset_at = big.scatter_reduce(0, key[onset], idx[onset], reduce="amin")
    has_ep = onset_at < T
    detected = has_ep & (first_hit < T)
    delays = (first_hit - onset_at)[detected].double()
    return {
        "mean_delay": float(delays.mean()) if delays.numel() else math.nan,
        "episodes": int(has_ep.sum()),
        "detected": int(detected.sum()),
        "missed": int((has_ep & ~detected).sum()),
    }


def finite_scores(scores: Tensor) -> Tensor:
    """``scores`` flattened in float64, NaN (no score: a step without data) as ``−∞``;
    ``±∞`` stay themselves (``nan_to_num`` alone would clamp them to the largest finite
    float: a threshold of 1.8e308 where ``#{s > τ} ≤ ⌊α n⌋`` needs ``+∞``)."""
    _check_tensors(scores=scores)
    return nan_as_lowest(scores.double().flatten())


def nan_as_lowest(scores: Tensor) -> Tensor:
    """``scores`` with NaN as ``−∞`` and every other value, ``±∞`` included, kept."""
    _check_tensors(scores=scores)
    return torch.nan_to_num(scores, nan=-math.inf, posinf=math.inf, neginf=-math.inf)


def threshold_for(scores: Tensor, far: float) -> float:
    """``τ_α`` of attack-free ``scores`` (any shape, every entry one step): the smallest score
    ``τ`` with ``#{s > τ} ≤ ⌊α n⌋`` (alarms are ``s > τ``).

    At most ``⌊α n⌋`` of the scores exceed it; ties at the threshold never alarm, so with
    discrete scores the rate may fall below ``α``. A NaN score (a step without data: no
    alarm possible) counts in ``n`` as the lowest score: the rate is over every step, so
    among the scored steps alone it is higher (``α / (1 − NaN share)``)."""
    far = check_rate(far, "far")  # a string or NaN compared with 0 raised a TypeError
    _check_tensors(scores=scores)  # a numpy array failed on its missing .double()
    s = finite_scores(scores)
    if s.numel() == 0:
        raise ValueError("scores must hold at least one attack-free step")
    # ⌊α n⌋ of α and n, not of their product's round-off (0.29 · 100 = 28.999999999999996)
    # and below n, as ⌊α n⌋ is for α < 1 (that guard had made it n, and τ −inf, for α
    # within 1e-12 of 1: a trial of the JSON writers found a card's threshold −Infinity)
    allowed = min(int(math.floor(far * s.numel() * (1 + 1e-12))), s.numel() - 1)
    ranked = torch.sort(s, descending=True).values
    return float(ranked[allowed])


def steps_since_attack(flags: Tensor, *, time_dim: int = 1) -> Tensor:
    """Steps since the last attacked step of the same run (and area): ``[B, T, ...]``
    int64 for ``flags [B, T, ...]`` (bool, time on dim 1), ``0`` on an attacked step and
    ``−1`` where the run has not been attacked yet. One running maximum over the steps::

        last_k = max{j ≤ k : flags_j}    steps_k = k − last_k   (−1 without such j)

    ``time_dim`` names the time axis where it is not dim 1 (``-1`` for ``[..., T]``, runs
    of several axes, the module's usual layout); every other axis is a run (or an area).
    """
    _check_tensors(flags=flags)
    if flags.dtype != torch.bool or flags.dim() < 2:
        raise ValueError(
            f"flags must be a bool tensor [B, T, ...]; got {flags.dtype} of shape "
            f"{tuple(flags.shape)}"
        )
    dim = _time_axis(time_dim, flags.dim())
    T = flags.shape[dim]
    view = [1] * flags.dim()
    view[dim] = T
    t = torch.arange(T, device=flags.device).view(view)
    last = torch.where(flags, t, -1).cummax(dim=dim).values  # the last attacked step ≤ k
    return torch.where(last >= 0, t - last, -1)


def _time_axis(time_dim, ndim: int) -> int:
    """``time_dim`` as a non-negative axis of a tensor of ``ndim ≥ 2`` axes (bool and
    out-of-range values refused by name)."""
    if isinstance(time_dim, bool) or not isinstance(time_dim, numbers.Integral):
        raise TypeError(f"time_dim must be an int; got {type(time_dim).__name__}")
    if not -ndim <= time_dim < ndim:
        raise ValueError(f"time_dim must name one of flags' {ndim} axes; got {time_dim}")
    return int(time_dim) % ndim


def after_attack(flags: Tensor, steps: int, *, time_dim: int = 1) -> Tensor:
    """Where ``flags [B, T, ...]`` (bool, time on dim 1, or on ``time_dim``) is false
    within ``steps`` steps after a true entry of the same run (and area): ``[B, T, ...]``
    bool (:func:`steps_since_attack` in ``1 … steps``; the training task's after-attack
    weight and the evaluation's ``fpr_at_far_after_attack`` read it)."""
    since = steps_since_attack(flags, time_dim=time_dim)
    return (since >= 1) & (since <= steps)


def alarm_rate_since_attack(
    alarms: Tensor,
    flags: Tensor,
    edges=(1, 5, 10, 20, 50, 100, 200),
    *,
    before: bool = False,
    time_dim: int = 1,
) -> tuple[Tensor, Tensor]:
    """The alarm rate on attack-free steps by the steps since the run's last attacked step:
    ``(rates [M], counts [M])`` float64 and int64 for ``M = len(edges)`` bins
    ``[e_0, e_1), …, [e_{M−1}, ∞)`` of :func:`steps_since_attack`, each rate the share of
    the bin's steps where ``alarms`` is true (NaN for an empty bin). ``alarms`` and
    ``flags`` ``[B, T, ...]`` bool; ``edges`` increasing integers ≥ 1. Steps before a
    run's first attack are in no bin (their rate is the plain false-alarm rate), unless
    ``before``: then they are one more bin, the last (``M = len(edges) + 1``). Where
    ``fpr_at_far_after_attack`` gives one number for steps 1–10, this shows how long an
    estimator's alarms outlast the attack (the report's ``false_alarms_after_attack.png``).
    ``time_dim`` as in :func:`steps_since_attack` (``-1`` for ``[..., T]``).
    """
    _check_tensors(alarms=alarms, flags=flags)
    if alarms.shape != flags.shape or alarms.dtype != torch.bool:
        raise ValueError(
            f"alarms must be a bool tensor of flags' shape {tuple(flags.shape)}; got "
            f"{alarms.dtype} of shape {tuple(alarms.shape)}"
        )
    given = list(edges)
    edges = [int(e) for e in given]
    if edges != given:  # (1.5 had been taken for 1 without a word)
        raise ValueError(f"edges must be increasing integers ≥ 1; got {given}")
    if not edges or edges[0] < 1 or any(b <= a for a, b in zip(edges, edges[1:])):
        raise ValueError(f"edges must be increasing integers ≥ 1; got {edges}")
    since = steps_since_attack(flags, time_dim=time_dim)
    bins = torch.bucketize(since, torch.tensor(edges, device=flags.device), right=True) - 1
    if before:
        bins = torch.where(since < 0, len(edges), bins)
    # attacked steps (0: every edge is ≥ 1), steps below the first edge and, without
    # ``before``, the steps before a run's first attack (−1) land below bin 0: in no bin
    keep = bins >= 0
    bins, hits = bins[keep], alarms[keep]
    size = len(edges) + int(before)
    counts = torch.bincount(bins, minlength=size).cpu()
    alarmed = torch.bincount(bins[hits], minlength=size).cpu()
    rates = alarmed.double() / counts.double()  # 0/0: NaN, an empty bin
    return rates, counts
