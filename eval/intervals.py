"""How sure the acceptance's verdicts are: paired bootstrap intervals over the runs.

Every estimator of a study runs on the same ``B`` runs (the same noise, loads and attacks:
named streams of one master seed; a closed-loop estimator on the same exogenous draws in
its own loop), so two estimators compare run by run. Each acceptance metric is a ratio of
sums over the runs of per-run totals,

    state_rmse  = √(Σ_b SE_b / Σ_b n_b),     SE_b = Σ_{t,i} (x̂_{b,t,i} − x_{b,t,i})²,  n_b = T·dx
    attack_rmse = √(Σ_b ASE_b / Σ_b m_b),    over run b's attacked steps (m_b entries)
    tpr_at_far  = Σ_b hits_b / Σ_b attacked_b,   fpr_at_far = Σ_b false_b / Σ_b clear_b
    rmse_p      = mean_t √(Σ_b E_{b,t} / B)  (a per-step metric, :func:`register_stepwise`:
                  tracking's position error, E_{b,t} = (x̂ − x)²_px + (x̂ − x)²_py)

so a resample of the runs (``B`` drawn with replacement) is a multiplicity vector
``w ∈ ℕ^B`` and each metric is its totals summed with weights ``w``: ``R`` resamples are one
``[R, B]`` matrix ``W``, every metric ``[R]`` one product ``W @ totals``. The check's own
statistic is recomputed in every resample, the best analytic estimator chosen again in
each (the best of the resampled analytic values, as :func:`~.acceptance.best_analytic`
chooses on the study):

    TPR      d = tpr_learned − max_analytic tpr          holds where d ≥ −0.01
    state    r = state_learned / min_analytic state      holds where r ≤ 1.05  (1.1 on a threat)
    attack   r = attack_learned / min_analytic attack    holds where r ≤ 1
    FPR      fpr_learned                                 holds where α/2 ≤ fpr ≤ 2α

Reported: the statistic on the study, the percentile interval at ``level`` (default 95 %)
and the share of resamples in which the check holds. The thresholds are held fixed (they
come from the calibration's own runs), and only the runs vary: a training seed's spread is
the sweep's to report, not this. With few runs (the LFC studies' 20) the percentile
interval is rough; it still says whether a check that holds or fails by a hair would go the
other way on other runs.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from difffilter._checks import check_rate
from difffilter.models.streams import Streams

from .acceptance import ROBUST_STATE_FACTOR, TOLERANCES, at_least, at_most
from .calibration import alarms_at
from .scoring import comparable_attack

__all__ = [
    "RESAMPLES", "LEVEL", "STREAM", "register_stepwise", "run_totals", "study_totals",
    "threat_totals", "resample_weights", "resampled_metric", "acceptance_intervals",
    "checks_intervals", "robustness_intervals",
]  # fmt: skip

#: Resamples of the runs per study, and the interval's coverage.
RESAMPLES = 2000
LEVEL = 0.95
#: The named stream the resamples are drawn from (of the study's master seed).
STREAM = "acceptance/bootstrap"

#: Per-step metrics: ``{metric: squared error [B, T] from (means [B, T, dx], x [B, T, dx])}``.
_STEPWISE: dict[str, Callable[[Tensor, Tensor], Tensor]] = {}


def register_stepwise(metric: str, squared_error: Callable[[Tensor, Tensor], Tensor]) -> None:
    """Declare ``metric`` a per-step state metric ``mean_t √(mean_b E_{b,t})`` with
    ``E = squared_error(means, x)`` ``[B, T]`` (the family that reports it registers it)."""
    _STEPWISE[metric] = squared_error


def run_totals(output, traj, threshold: float | None, *, state_metric: str = "state_rmse",
               attacked_input: bool = True) -> dict[str, Tensor]:  # fmt: skip
    """Per-run totals ``{name: [B] (or [B, T]) float64}`` of one estimator's ``output`` on the
    trajectories ``traj`` it ran on, at its calibrated ``threshold`` (module docstring):
    ``se``, ``n`` (or ``step_se [B, T]`` for a :func:`register_stepwise` metric); where the
    estimate measures the attack, ``attack_se``, ``attack_n``; where it detects at a
    threshold, ``hits``, ``attacked``, ``false``, ``clear`` (an estimator fed the clean
    measurements has no attacked step)."""
    if state_metric != "state_rmse" and state_metric not in _STEPWISE:
        raise ValueError(f"state_metric must be 'state_rmse' or a registered per-step metric "
                         f"({', '.join(sorted(_STEPWISE)) or 'none'}); got {state_metric!r}")  # fmt: skip
    with torch.no_grad():
        return _run_totals(output, traj, threshold, state_metric, attacked_input)


def _run_totals(output, traj, threshold, state_metric, attacked_input) -> dict[str, Tensor]:
    means, x = output.means.double(), traj.x.double()
    if state_metric in _STEPWISE:
        totals = {"step_se": _STEPWISE[state_metric](means, x)}
    else:
        se = (means - x).square().sum((1, 2))
        totals = {"se": se, "n": torch.full_like(se, x.shape[1] * x.shape[2])}
    flags = traj.flags
    if comparable_attack(output, traj) and bool(flags.any()):
        diff = torch.where(flags[..., None], output.attack.double() - traj.attack.double(), 0.0)
        totals["attack_se"] = diff.square().sum((1, 2))
        totals["attack_n"] = flags.sum(1).double() * diff.shape[-1]
    det = output.detection
    if threshold is not None and det is not None and det.scores is not None:
        alarms = alarms_at(det.scores, threshold)
        flags = flags if attacked_input else torch.zeros_like(flags)
        totals.update(hits=(alarms & flags).sum(1).double(), attacked=flags.sum(1).double(),
                      false=(alarms & ~flags).sum(1).double(), clear=(~flags).sum(1).double())  # fmt: skip
    return totals


def resample_weights(runs: int, resamples: int = RESAMPLES, seed: int = 0) -> Tensor:
    """``W [resamples, runs]`` float64: row r counts how often each run was drawn in
    resample r (``runs`` draws with replacement, uniformly; from the named stream
    :data:`STREAM` of master seed ``seed``), so every row sums to ``runs``."""
    if runs < 1 or resamples < 1:
        raise ValueError(f"runs and resamples must be >= 1; got {runs}, {resamples}")
    draws = torch.randint(runs, (resamples, runs), generator=Streams(seed)(STREAM))
    weights = torch.zeros(resamples, runs, dtype=torch.float64)
    return weights.scatter_add_(1, draws, torch.ones_like(draws, dtype=torch.float64))


def resampled_metric(totals: dict[str, Tensor], metric: str, weights: Tensor) -> Tensor | None:
    """``metric`` of every resample ``[R]`` from one estimator's ``totals`` and the resample
    ``weights [R, B]`` (a row of ones: the study's own value); ``None`` where the totals do
    not give it. A resample with a zero denominator gives NaN."""

    def ratio(num, den):
        if num not in totals:
            return None
        return (weights @ totals[num]) / (weights @ totals[den])

    if metric == "tpr_at_far":
        return ratio("hits", "attacked")
    if metric == "fpr_at_far":
        return ratio("false", "clear")
    if metric == "attack_rmse":
        value = ratio("attack_se", "attack_n")
        return None if value is None else value.sqrt()
    if metric in _STEPWISE:  # a per-step state metric (mean over steps of the per-step RMSE)
        if "step_se" not in totals:
            return None
        return ((weights @ totals["step_se"]) / weights.sum(1, keepdim=True)).sqrt().mean(1)
    if metric == "state_rmse":
        value = ratio("se", "n")
        return None if value is None else value.sqrt()
    raise ValueError(f"no interval for metric {metric!r}: tpr_at_far, fpr_at_far, attack_rmse, "
                     f"state_rmse or a registered per-step metric")  # fmt: skip


def _summary(values: Tensor, holds: Callable[[Tensor], Tensor], level: float) -> dict:
    """``{estimate, low, high, holds_share}`` from a statistic's ``values [1 + R]`` (row 0 the
    study itself, then the resamples: :func:`_study_and_resamples`): the percentile interval
    of the resamples at ``level`` (NaN resamples left out) and the share where ``holds``."""
    estimate, samples = values[0], values[1:]
    ok = ~torch.isnan(samples)
    study = None if bool(torch.isnan(estimate)) else float(estimate)
    if not bool(ok.any()):
        return {"estimate": study, "low": None, "high": None, "holds_share": None}
    tail = (1.0 - level) / 2.0
    low, high = torch.quantile(samples[ok], torch.tensor([tail, 1.0 - tail], dtype=samples.dtype))
    return {"estimate": study, "low": float(low), "high": float(high),
            "holds_share": float(holds(samples[ok]).double().mean())}  # fmt: skip


def _study_and_resamples(runs: int, resamples: int, seed: int) -> Tensor:
    """``[1 + R, B]``: a row of ones (the study, every run once), then :func:`resample_weights`;
    the row alone for one run, which has no spread to resample (its "intervals" were points
    and every share 0 or 100 %: every interval and share is then ``None``)."""
    ones = torch.ones(1, runs, dtype=torch.float64)
    if runs < 2:
        return ones
    return torch.cat([ones, resample_weights(runs, resamples, seed)])


def _best(values: dict[str, Tensor], higher: bool) -> Tensor | None:
    """Per resample the best of ``values`` ``{estimator: [R]}`` (NaN and ``±∞`` ignored, as
    :func:`eval.acceptance.best_analytic` drops a value that is not finite), or ``None``."""
    if not values:
        return None
    stacked = torch.stack(list(values.values()))
    fill = -math.inf if higher else math.inf
    stacked = torch.where(torch.isfinite(stacked), stacked, fill)
    best = stacked.amax(0) if higher else stacked.amin(0)
    return torch.where(torch.isinf(best), torch.nan, best)


def study_totals(result, names, state_metric: str) -> dict[str, dict[str, Tensor]]:
    """:func:`run_totals` of ``names`` in ``result`` (a suite) at its calibrated thresholds."""
    from difffilter.models import estimators as registry

    thresholds = result.calibration.thresholds if result.calibration is not None else {}
    return {name: run_totals(result.outputs[name], result.traj_of(name), thresholds.get(name),
                             state_metric=state_metric,
                             attacked_input=not registry.get(name).clean_input)
            for name in names}  # fmt: skip


def _roles(result, role_of):
    names = [n for n in result.outputs if n in result.metrics]
    analytic = [n for n in names if role_of.get(n) == "analytic"]
    learned = [n for n in names if role_of.get(n) == "learned"]
    return analytic, learned


def _paired(totals: dict, name: str, analytic: list[str], metric: str, statistic: str,
            higher: bool, weights: Tensor) -> Tensor | None:  # fmt: skip
    """``[1 + R]``: ``name``'s ``metric`` against the best analytic's, chosen again in every
    row of ``weights`` (``statistic``: ``"difference"`` or ``"ratio"``), or ``None`` where
    either side lacks the metric."""
    own = resampled_metric(totals[name], metric, weights)
    best = _best({n: v for n in analytic
                  if (v := resampled_metric(totals[n], metric, weights)) is not None}, higher)  # fmt: skip
    if own is None or best is None:
        return None
    return own - best if statistic == "difference" else own / best


def acceptance_intervals(result, role_of: dict[str, str], *, far: float, state_metric: str,
                         resamples: int = RESAMPLES, level: float = LEVEL) -> dict[str, Any] | None:  # fmt: skip
    """The headline checks' intervals of every learned estimator of ``result`` (a calibrated
    suite) against its analytic ones: :func:`checks_intervals` of their :func:`run_totals`,
    or ``None`` with nothing to judge (no calibration, no learned or analytic estimator)."""
    analytic, learned = _roles(result, role_of)
    if result.calibration is None or not learned or not analytic:
        return None
    totals = study_totals(result, analytic + learned, state_metric)
    return checks_intervals(totals, role_of, runs=result.runs, seed=result.seed, far=far,
                            state_metric=state_metric, resamples=resamples, level=level)  # fmt: skip


def checks_intervals(totals: dict[str, dict[str, Tensor]], role_of: dict[str, str], *,
                     runs: int, seed: int, far: float, state_metric: str,
                     resamples: int = RESAMPLES, level: float = LEVEL) -> dict[str, Any]:  # fmt: skip
    """The headline checks' intervals (module docstring) of every learned estimator of
    ``totals`` (``{estimator: run_totals(...)}`` on the same ``runs`` of master seed
    ``seed``) against the analytic ones, at the calibrated rate ``far``: ``{"level",
    "resamples", "runs", "seed_stream", "estimators": {learned: {metric: {"statistic",
    "estimate", "low", "high", "holds_share"}}}}``."""
    # (a level of 95 had failed in torch.quantile, one of −0.5 given low > high; a far of 1,
    # meant as 1 %, had judged every rate against a band of [0.5, 2] without a word)
    far, level = check_rate(far, "far"), check_rate(level, "level", kind="a confidence level")
    analytic = [n for n in totals if role_of.get(n) == "analytic"]
    learned = [n for n in totals if role_of.get(n) == "learned"]
    weights = _study_and_resamples(runs, resamples, seed)
    tol = TOLERANCES
    lo, hi = (far * f for f in tol["fpr_band"])
    checks = (  # metric, statistic, higher is better, where a resample's statistic holds
        ("tpr_at_far", "difference", True, lambda d: at_least(d, -tol["tpr_margin"])),
        (state_metric, "ratio", False, lambda r: at_most(r, tol["state_factor"])),
        ("attack_rmse", "ratio", False, lambda r: at_most(r, 1.0)),
    )  # fmt: skip
    in_band = lambda v: at_least(v, lo) & at_most(v, hi)  # noqa: E731
    out = {}
    for name in learned:
        rows = {}
        for metric, statistic, higher, holds in checks:
            values = _paired(totals, name, analytic, metric, statistic, higher, weights)
            if values is not None:
                rows[metric] = {"statistic": statistic, **_summary(values, holds, level)}
        fpr = resampled_metric(totals[name], "fpr_at_far", weights)
        if fpr is not None:
            rows["fpr_at_far"] = {"statistic": "value", **_summary(fpr, in_band, level)}
        out[name] = rows
    return {"level": level, "resamples": resamples, "runs": runs,
            "seed_stream": STREAM, "estimators": out}  # fmt: skip


def threat_totals(result, role_of: dict[str, str]) -> dict[str, dict[str, Tensor]]:
    """:func:`run_totals` (``state_rmse``) of the analytic and learned estimators of one
    threat's suite ``result``, for :func:`robustness_intervals`."""
    analytic, learned = _roles(result, role_of)
    return study_totals(result, analytic + learned, "state_rmse")


def robustness_intervals(totals: dict[str, dict[str, dict[str, Tensor]]], role_of: dict[str, str],
                         *, runs: int, seed: int, resamples: int = RESAMPLES,
                         level: float = LEVEL) -> dict[str, dict]:  # fmt: skip
    """The robustness checks' intervals (:func:`~.acceptance.judge_robustness`) from each
    threat's :func:`threat_totals` ``{threat: {estimator: totals}}``: ``{learned: {"state":
    {threat: interval}, "worst_tpr": interval}}``, each ``{"estimate", "low", "high",
    "holds_share"}``. The state check is the ratio to the best analytic on that threat
    (holds within :data:`~.acceptance.ROBUST_STATE_FACTOR`); the worst-case check is the
    difference between the learned estimator's lowest TPR over the threats and the best of
    the analytic estimators' lowest, every minimum and maximum taken again in each resample
    (holds where ≥ 0). The threats' studies share their seed, so their runs are the same
    runs (the same noise and initial draws) and resample together."""
    level = check_rate(level, "level", kind="a confidence level")
    names = {n for per in totals.values() for n in per}
    analytic = sorted(n for n in names if role_of.get(n) == "analytic")
    learned = sorted(n for n in names if role_of.get(n) == "learned")
    weights = _study_and_resamples(runs, resamples, seed)
    within = lambda r: at_most(r, ROBUST_STATE_FACTOR)  # noqa: E731

    def worst_tpr(name):  # [1 + R]: the lowest TPR over the threats where it detects
        rates = [v for per in totals.values() if name in per
                 if (v := resampled_metric(per[name], "tpr_at_far", weights)) is not None]  # fmt: skip
        return _best(dict(enumerate(rates)), higher=False)

    def run_everywhere(name) -> bool:  # not run under a threat (absent there): no worst case
        return all(name in per for per in totals.values())

    rivals = {n: w for n in analytic if run_everywhere(n) and (w := worst_tpr(n)) is not None}
    best_worst = _best(rivals, higher=True)
    out = {}
    for name in learned:
        state = {}
        for threat, per in totals.items():
            present = [n for n in analytic if n in per]
            if name in per and per[name].get("broke_down"):  # no estimate: holds nowhere
                state[threat] = {"estimate": None, "low": None, "high": None, "holds_share": 0.0}
            elif name in per and present:
                ratio = _paired(per, name, present, "state_rmse", "ratio", False, weights)
                if ratio is not None:
                    state[threat] = _summary(ratio, within, level)
        mine = worst_tpr(name) if run_everywhere(name) else None  # (as judge_robustness)
        gap = None if mine is None or best_worst is None else mine - best_worst
        out[name] = {"state": state,
                     "worst_tpr": None if gap is None else _summary(gap, lambda d: at_least(d, 0.0), level)}  # fmt: skip
    return out
