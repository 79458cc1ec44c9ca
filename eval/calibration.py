"""Every detector at one false-alarm rate: thresholds from attack-free runs.

A detector's scores ``s_k`` (higher means attack) are turned into alarms ``s_k > τ``. The
threshold of the comparison is chosen for a target false-alarm rate ``α`` (default 1 %)
on attack-free runs of the scenario, never on the runs it is judged on::

    τ_α = the smallest score τ with  #{attack-free steps with s > τ} ≤ ⌊α n⌋,

``n`` the attack-free calibration steps pooled over runs. The calibration runs come from
their own master seed (``Streams(seed).seed_of("far-calibration")``), so the study's noise,
attacks and particles are fresh for it; the learned detectors are calibrated the same way
as the analytic ones. :func:`calibrated_metrics` then reads the study's scores at ``τ_α``.
"""

from __future__ import annotations

import math
import numbers
import warnings
from dataclasses import dataclass, field
from statistics import NormalDist

import torch

from difffilter._checks import check_positive_int, check_rate
from difffilter.metrics import after_attack, nan_as_lowest, threshold_for
from difffilter.metrics import finite_scores as _finite_scores
from difffilter.models.streams import far_calibration_seed

from .scoring import AFTER_ATTACK_STEPS, episode_delay

__all__ = [
    "Calibration",
    "threshold_for",
    "calibrate",
    "calibrated_metrics",
    "alarms_at",
    "alarm_clustering",
    "calibration_seed",
    "below_target_note",
    "calibration_mismatch",
]


@dataclass(frozen=True)
class Calibration:
    """Thresholds of one scenario's detectors at the target false-alarm rate.

    Attributes:
        far: the target ``α``; runs, seed: of the attack-free calibration runs.
        thresholds: ``{estimator: τ_α}`` (estimators with detection scores only).
        measured: ``{estimator: false-alarm rate at τ_α on the calibration runs}``.
        tied: ``{estimator: share of the calibration scores equal to τ_α}`` for the
            detectors whose rate fell to half the target or below: a discrete score (the PoA β of
            the particle filters, 1 where every particle exceeds η) ties there, and no
            threshold meets ``α`` (alarms are ``s > τ``).
        steps: ``{estimator: calibration steps}``, the ``n`` of ``τ_α``'s ``⌊α n⌋`` alarms
            (a step without a score, NaN, counts as its lowest, as
            :func:`~difffilter.metrics.threshold_for` counts it): with ``α n < 1`` no step
            may alarm at all, and fewer than :data:`RESOLVED` expected alarms leave ``τ_α``
            to a handful of scores (the scored steps alone had been counted here, so a
            detector scoring 5 % of 5,000 steps was said to rest on 2.35 alarms where its
            threshold rested on 50).
        scored: ``{estimator: calibration steps with a score}``: where fewer than ``⌊α n⌋``,
            every scored step alarms (``τ_α = −∞``) and the rate falls short of ``α``.
        broke_down: ``{estimator: why}`` for those that broke down on the calibration runs
            (:class:`~difffilter.linalg.NumericalBreakdown`): no threshold, so no
            ``*_at_far`` metrics in a study where they ran.
        startup: ``{estimator: {"alarms_at_first_step": share, "rate_after_first_step":
            rate}}`` for the detectors that spend most of their false alarms
            (:data:`STARTUP_SHARE` or more) at the first step of the calibration runs: a
            start-up transient (the particle filters' probability of attack is above 0 at
            step 1 of every four-tank run and 0 on nearly every later step, so at 1 % their
            threshold is 0 and every alarm of the calibration is at step 1). Their rate over
            all steps meets the target; their rate from step 2 on is the second number.
        at_floor: ``{estimator: share of its calibration scores at τ_α}`` where ``τ_α`` is
            its lowest score and its rate is not below the target (nor explained by
            start-up): it alarms wherever its score leaves its floor at all, its most
            sensitive setting (a trial's 4-run LFC calibration gave the learned head τ = 0,
            and its alarms were then exactly its χ² confirmation's).
        concentrated: ``{estimator: {"alarms": N, "effective_alarms": N / D}}`` where the
            calibration's alarms cluster in a few runs (:func:`alarm_clustering`): ``c_r`` the
            alarms of run ``r`` at ``τ_α``, ``D`` their variance over the runs divided by
            their mean (about 1 for alarms that fall independently, as a Poisson count's),
            ``N / D`` the independent alarms they are worth, listed where it is below
            :data:`RESOLVED` and ``D`` is above what independent alarms give (the dispersion
            test at :data:`CLUSTERING_LEVEL`). Steps of one run are not independent draws:
            where a few runs hold the alarms (the LFC online learners, whose per-run EKF
            over the weights settles differently in each run: on two draws of
            ``lfc_step``'s 20 runs, 200 alarms worth 1.2–9.7) the threshold rests on those runs, and its rate on
            fresh runs varies from one draw of runs to the next far more than the step
            count says. A detector already listed under ``unresolved`` (``α n`` below
            :data:`RESOLVED`) is not listed again.
        scenario: ``Scenario.attack_free_key()`` of the scenario calibrated (its name and
            horizon; ``None``: not recorded): a study of another warns
            (:func:`calibration_mismatch`).
    """

    far: float
    runs: int
    seed: int
    thresholds: dict[str, float] = field(default_factory=dict)
    measured: dict[str, float] = field(default_factory=dict)
    tied: dict[str, float] = field(default_factory=dict)
    steps: dict[str, int] = field(default_factory=dict)
    broke_down: dict[str, str] = field(default_factory=dict)
    startup: dict[str, dict] = field(default_factory=dict)
    at_floor: dict[str, float] = field(default_factory=dict)
    concentrated: dict[str, dict] = field(default_factory=dict)
    scenario: tuple | None = None
    scored: dict[str, int] = field(default_factory=dict)

    def summary(self) -> dict:
        """The calibration as metrics.json's ``"far"`` entry (``below_target`` only where a
        detector could not meet the rate, with its ``cause``: ``"ties"``, ``"too few
        steps"`` (``α n < 1``) or ``"no score"``; ``unresolved`` where fewer than
        :data:`RESOLVED` alarms are expected on the calibration steps; ``broke_down``,
        ``{estimator: why}``, only where one broke down on the calibration runs;
        ``startup`` only where a detector's calibration alarms fall mostly at the first
        step; ``at_floor`` only where a threshold is its detector's lowest score;
        ``concentrated`` only where a detector's alarms cluster in a few runs)."""
        below = {name: {"measured_on_calibration": self.measured[name],
                        "threshold": self.thresholds[name], "tied_at_threshold": share,
                        "cause": self._cause(name)}
                 for name, share in self.tied.items()}  # fmt: skip
        few = {name: n for name, n in self.steps.items() if 0 < self.far * n < RESOLVED}
        return {"target": self.far, "calibration_runs": self.runs, "calibration_seed": self.seed,
                "measured_on_calibration": dict(self.measured),
                **({"below_target": below} if below else {}),
                **({"unresolved": few} if few else {}),
                **({"broke_down": dict(self.broke_down)} if self.broke_down else {}),
                **({"startup": dict(self.startup)} if self.startup else {}),
                **({"at_floor": dict(self.at_floor)} if self.at_floor else {}),
                **({"concentrated": dict(self.concentrated)} if self.concentrated else {})}  # fmt: skip

    def _cause(self, name: str) -> str:
        n, scored = self.steps.get(name), self.scored.get(name, self.steps.get(name))
        if scored == 0:
            return "no score"
        if n is not None and self.far * n < 1:
            return "too few steps"
        if n is not None and scored is not None and scored <= math.floor(self.far * n):
            return "few scores"
        return "ties"


#: Fewer expected alarms than this on the calibration steps (``α n``) leave the threshold to
#: a handful of scores: its rate on fresh runs is ``(⌊α n⌋ + 1)/(n + 1)`` in expectation
#: for continuous scores, and varies widely from one calibration draw to another (an
#: auditor's trial: at α = 0.001 on 2,000 steps, 17–29 % of calibrations above 2α).
RESOLVED = 10

#: The share of a detector's calibration alarms at the runs' first step from which the
#: calibration reports them as a start-up transient (:attr:`Calibration.startup`).
STARTUP_SHARE = 0.5

_CAUSES = {
    "ties": "its scores are discrete and tie there (alarms are s > τ), so no threshold "
    "meets the rate",
    "too few steps": "too few calibration steps for the target (α n < 1: not one step may "
    "alarm); give more --calibration-runs",
    "no score": "it scored no calibration step (every score NaN)",
    "few scores": "it scored fewer calibration steps than the target's share of them (the "
    "others NaN, no data): every scored step alarms and the rate still falls short",
}


def below_target_note(far: dict | None) -> str | None:
    """Sentences for a report naming the detectors whose calibrated rate fell short of the
    target, each with why (``far``: metrics.json's entry; a ``below_target`` entry without
    ``cause``, of an older file, is read as ties), the calibration's resolution where
    fewer than :data:`RESOLVED` alarms are expected on its steps, and the estimators that
    broke down on the calibration runs."""
    far = far or {}
    below, few = far.get("below_target"), far.get("unresolved")
    notes = []
    if below:
        each = "; ".join(
            f"`{name}` alarms on {100 * b['measured_on_calibration']:.2f} % of them, "
            f"{100 * b['tied_at_threshold']:.1f} % of its scores being equal to its threshold "
            f"{_threshold_text(b['threshold'])}: {_CAUSES[b.get('cause', 'ties')]}"
            for name, b in below.items()
        )
        notes.append(
            f"Below the {100 * far['target']:g} % target on the calibration runs: {each}. "
            "Their `*_at_far` metrics are at that lower rate, not at the target."
        )
    if few:
        notes.append(resolution_note(far["target"], min(few.values()), "--calibration-runs"))
    startup = far.get("startup")
    if startup:
        alike: dict[str, list[str]] = {}  # detectors of the same figures: one clause
        for name, e in startup.items():
            figures = (f"{100 * e['alarms_at_first_step']:.0f} % of the alarms at step 1, "
                       f"{100 * e['rate_after_first_step']:.2f} % of the steps from step 2 on")  # fmt: skip
            alike.setdefault(figures, []).append(f"`{name}`")
        each = "; ".join(f"{', '.join(names)}: {figures}" for figures, names in alike.items())
        notes.append(
            "False alarms at start-up: these detectors spend their calibrated rate mostly at "
            f"the first step of each run ({each}), a transient of the filter's prior, so after "
            "it they alarm far less than the target and their threshold is as low as their "
            "scores allow; in a study their false alarms are mostly that first step, a larger "
            "share of the unattacked steps the earlier an attack starts."
        )
    floor = far.get("at_floor")
    if floor:
        each = "; ".join(f"`{name}` ({100 * share:.0f} % of its scores there)"
                         for name, share in floor.items())  # fmt: skip
        notes.append(
            f"At their lowest score: {each}. Their threshold is the floor of their scores, so "
            "they alarm wherever the score leaves it at all, their most sensitive setting; "
            "the rate they meet is what that gives, not a threshold chosen among their "
            "scores (more calibration runs may lift it off the floor)."
        )
    concentrated = far.get("concentrated")
    if concentrated:
        runs = far.get("calibration_runs")
        of = f" of the {runs}" if runs else ""
        each = "; ".join(f"`{name}` {e['alarms']:,} alarms worth {e['effective_alarms']:.1f}"
                         for name, e in concentrated.items())  # fmt: skip
        notes.append(
            f"Alarms in few runs: these detectors' calibration alarms cluster in a few{of} "
            f"runs ({each} independent ones), so each threshold rests on those runs and its "
            "rate on fresh runs varies from one draw of runs to another far more than the "
            "steps' count suggests; give more --calibration-runs."
        )
    for name, why in (far.get("broke_down") or {}).items():
        notes.append(f"`{name}` has no threshold: it broke down on the attack-free calibration "
                     f"runs ({why}), so it has no `*_at_far` metrics.")  # fmt: skip
    return " ".join(notes) or None


def _threshold_text(threshold) -> str:
    """A threshold for a sentence: ``±∞`` (metrics.json's ``null``: JSON has no infinity) is
    what a detector gets whose scores are infinite on more than the target share of the
    calibration steps (or all NaN)."""
    if threshold is None or not math.isfinite(threshold):
        return "±∞ (infinite scores on more than the target share of the steps, or none finite)"
    return f"{threshold:.6g}"


def resolution_note(target: float, steps: int, more: str) -> str:
    """The sentence for a calibration of ``steps`` steps at ``target`` that expects
    fewer than :data:`RESOLVED` alarms (``more``: the option that gives more runs): its
    threshold's expected rate on fresh runs, ``(⌊α n⌋ + 1)/(n + 1)`` for continuous scores."""
    expected = (math.floor(target * steps + 1e-9) + 1) / (steps + 1)
    return (
        f"Few calibration steps for the {100 * target:g} % target ({steps:,} steps: "
        f"{target * steps:.3g} alarms expected, fewer than {RESOLVED}): each threshold rests "
        f"on a handful of scores, and its rate on fresh runs is about {100 * expected:.2g} % "
        f"in expectation and varies widely between calibration draws; give more {more}."
    )


#: Expected calibration alarms below which ``difffilter-train calibrate`` states the
#: threshold's sampling spread (at 100 the binomial standard deviation of the rate is a
#: tenth of the target).
WELL_RESOLVED = 100


def sampling_note(target: float, steps: int, run_steps: int) -> str:
    """The sentence for a calibration of ``steps`` steps (``run_steps`` a run) that
    expects fewer than :data:`WELL_RESOLVED` alarms: the binomial standard deviation of the
    rate, ``√(α(1 − α)/n)``, and the ``--runs`` that expects about 100 alarms. A new user's
    trial calibrated a 5 % threshold on its plant's 8 runs of 60 steps (24 alarms), met
    7 % on fresh runs, and no note had said that the spread is that wide."""
    spread = math.sqrt(target * (1 - target) / steps)
    runs = math.ceil(WELL_RESOLVED / (target * run_steps))
    return (
        f"{steps:,} calibration steps at the {100 * target:g} % target expect "
        f"{target * steps:.3g} alarms: the threshold's rate on fresh runs varies by about "
        f"±{100 * spread:.2g} % between calibration draws (one binomial standard deviation; "
        f"wider where alarms come in bursts); --runs {runs:,} expects about {WELL_RESOLVED}"
    )


def calibration_seed(seed: int) -> int:
    """The master seed of the calibration runs of a study of master seed ``seed``."""
    return far_calibration_seed(seed)


def calibrate(
    scenario,
    *,
    far: float = 0.01,
    runs: int | None = None,
    seed: int = 0,
    estimators=None,
    add=(),
    checkpoint=None,
    progress: bool = True,
    cache: dict | None = None,
    study_runs: int | None = None,
) -> Calibration:
    """Run ``scenario``'s estimators on attack-free runs and pick every detector's ``τ_α``.

    ``runs`` (default the scenario's), ``estimators``, ``add`` and ``checkpoint`` as for
    :func:`~difffilter.eval.suite.run_suite` (an empty list of ``estimators`` and no
    ``add``: no detector, nothing to run); the runs come from :func:`calibration_seed`.
    ``cache`` (a dict shared by one evaluation) keeps the result for the same scenario,
    runs, estimators, checkpoint and target. ``study_runs``: the runs of the study the
    thresholds are for (default ``runs``): its detectors' own calibrations (a CUSUM's τ)
    follow its seed and its runs, so the threshold is picked for the detector judged.
    """
    from .suite import broken_down, run_suite

    far = check_rate(far, "far")
    runs = scenario.runs if runs is None else runs
    # (a study's size of 0, -5 or 2.5 had been taken as the default silently)
    study_runs = runs if study_runs is None else check_positive_int(study_runs, "study_runs")
    # (None, the scenario's own estimators, and [], only `add`'s, are two keys: one had
    # answered for the other, 1 threshold of 11: a red-team trial)
    key = ("far-calibration", scenario.attack_free_key(), runs, seed, far,
           None if estimators is None else tuple(estimators), tuple(add), str(checkpoint),
           study_runs)  # fmt: skip
    if cache is not None and key in cache:
        return cache[key]
    cal_seed = calibration_seed(seed)
    if estimators is not None and not list(estimators) and not add:
        return Calibration(far, runs, cal_seed, scenario=scenario.attack_free_key())
    result = run_suite(
        scenario.with_threat(None), runs=runs, seed=cal_seed, estimators=estimators, add=add,
        progress=progress, checkpoint=checkpoint, cache=cache, calibration=None,
        label=f"{scenario.name}: calibrating at {far:g} (attack-free runs)",
        detector_seed=seed, detector_runs=study_runs,  # the study's detectors (a CUSUM's τ)
    )  # fmt: skip
    thresholds, measured, tied, steps, startup, floor, few, scored = {}, {}, {}, {}, {}, {}, {}, {}
    for name, out in result.outputs.items():
        if out.detection is None or out.detection.scores is None:
            continue
        scores = _finite_scores(out.detection.scores)
        thresholds[name] = threshold_for(scores, far)
        measured[name] = float((scores > thresholds[name]).double().mean())
        steps[name] = scores.numel()  # the n of threshold_for, a NaN its lowest score
        scored[name] = int((~torch.isnan(out.detection.scores)).sum())
        # (one coarse for its steps is named as such, under unresolved, not twice)
        clustered = alarm_clustering(out.detection.scores, thresholds[name])
        if clustered is not None and far * steps[name] >= RESOLVED:
            few[name] = clustered
        # ties at τ: the rate cannot be met (class docstring); at exactly half too (a trial's
        # particle filters at --far 0.02: 1.00 %, their start-up alone, unsaid)
        if measured[name] <= far / 2:
            tied[name] = float((scores == thresholds[name]).double().mean())
        transient = _startup(out.detection.scores, thresholds[name])
        if transient is not None:
            startup[name] = transient
        elif name not in tied and (share := _at_floor(scores, thresholds[name])) is not None:
            floor[name] = share
    calibration = Calibration(far, runs, cal_seed, thresholds, measured, tied, steps,
                              broken_down(result.skipped), startup, floor, few,
                              scenario.attack_free_key(), scored)  # fmt: skip
    _warn_unthresholded(estimators, calibration, result)
    if tied:  # (from Python the note was in summary() alone: a teaching trial read "0.0" as
        # "detects nothing")
        below = calibration.summary()
        warnings.warn(below_target_note({k: below[k] for k in ("target", "below_target")}),
                      stacklevel=2)  # fmt: skip
    if cache is not None:
        cache[key] = calibration
    return calibration


#: The dispersion test's level (:func:`alarm_clustering`). Measured on independent χ² scores
#: (1,000 calibrations each of 100 × 100 and 200 × 50 steps at 0.1 %, 20 × 100 and 100 × 100
#: at 1 %): 5, 0, 0 and 0 called clustered (the test's χ² approximation is coarse for a
#: tenth of an alarm a run); the LFC online learners' statistics are 8–62 times the bound.
CLUSTERING_LEVEL = 1e-4


def alarm_clustering(scores: torch.Tensor, threshold: float) -> dict | None:
    """``{"alarms": N, "effective_alarms": N / D}`` where the alarms of ``scores [runs, T,
    ...]`` at ``threshold`` cluster in runs (:attr:`Calibration.concentrated`), else ``None``.

    ``c_r`` the alarms of run ``r`` (over its steps and areas), ``c̄`` their mean over the
    ``R`` runs and ``D = Σ (c_r − c̄)² / ((R − 1) c̄)`` their dispersion: a rate measured
    on such runs varies ``D`` times as much as one of ``N`` independent alarms, so they are
    worth ``N / D``. Listed where ``N / D`` < :data:`RESOLVED` and ``(R − 1) D`` exceeds the
    ``1 −`` :data:`CLUSTERING_LEVEL` quantile of χ² with ``R − 1`` degrees of freedom (the
    dispersion test of a Poisson count; Wilson–Hilferty's approximation): the test keeps
    independent alarms of an ``N`` near :data:`RESOLVED` off the list, whose ``D`` strays
    from 1 by chance (a review: the participation ratio ``N² / Σ c_r²`` of before flagged a
    third of independent χ² calibrations)."""
    runs = scores.shape[0]
    counts = alarms_at(scores, threshold).reshape(runs, -1).sum(1).double()
    total = float(counts.sum())
    if runs < 2 or not total:
        return None
    mean = total / runs
    statistic = float(((counts - mean) ** 2).sum()) / mean  # (R − 1) D
    k = runs - 1
    z = NormalDist().inv_cdf(1 - CLUSTERING_LEVEL)
    critical = k * (1 - 2 / (9 * k) + z * math.sqrt(2 / (9 * k))) ** 3
    effective = total * k / statistic if statistic else math.inf
    if statistic <= critical or effective >= RESOLVED:
        return None
    return {"alarms": int(total), "effective_alarms": effective}


def _warn_unthresholded(estimators, calibration: Calibration, result) -> None:
    """A warning naming the estimators asked for by name (``estimators``) that the
    scenario could not run, with why, and, where the calibration got no threshold at all, those
    that report no detection score: another family's estimator, or one that detects
    nothing, had left the calibration empty without a word (a calibration trial). A list
    that mixes detectors with estimators that detect nothing (a study's own list) is
    calibrated as it is: those get no threshold, as the class says."""
    # (``add``'s names the CLI notes once itself, as a study of every scenario meets them)
    asked = [n for n in dict.fromkeys(estimators or ())
             if n not in calibration.thresholds and n not in calibration.broke_down]  # fmt: skip
    why = {n: result.skipped[n] for n in asked if n in result.skipped}
    if not calibration.thresholds and not calibration.broke_down:
        why.update({n: "it reports no detection score" for n in asked if n not in why})
    if why:
        each = "; ".join(f"{n!r}: {reason}" for n, reason in why.items())
        warnings.warn(f"calibrate: no threshold for {each}", stacklevel=3)


def calibration_mismatch(calibration: Calibration, scenario) -> str | None:
    """Why ``calibration`` does not fit a study of ``scenario`` (calibrated on a scenario of
    another ``attack_free_key``: another scenario's name or another horizon; a scenario
    changed under its own name is not seen), or ``None``."""
    made, study = calibration.scenario, scenario.attack_free_key()
    if made is None or tuple(made) == tuple(study):
        return None
    return (f"the calibration was made on {_key_text(made)}, the study runs {_key_text(study)}: "
            "its thresholds meet the target rate on the attack-free runs of the scenario "
            "calibrated, not necessarily on this one's; calibrate(scenario, far=…) on the "
            "study's scenario, unless judging another plant at those thresholds is the point")  # fmt: skip


def _key_text(key) -> str:
    key = tuple(key)
    if len(key) == 2 and isinstance(key[0], str) and isinstance(key[1], int):
        return f"{key[0]!r} over {key[1]} steps"
    return repr(key)


def _startup(scores: torch.Tensor, threshold: float) -> dict | None:
    """``{"alarms_at_first_step", "rate_after_first_step"}`` of ``scores [B, T, ...]`` at
    ``threshold`` where at least :data:`STARTUP_SHARE` of the alarms are at the first step,
    else ``None`` (no alarm, one step, or alarms spread over the run). Time is dim 1: a
    study's detection scores are ``[runs, T]`` (every registered detector's, the LFC's
    too), or ``[runs, T, areas]``, as the calibration's own counting reads them."""
    if scores.dim() < 2 or scores.shape[1] < 2:
        return None
    alarms = alarms_at(scores, threshold)
    total = int(alarms.sum())
    share = int(alarms[:, 0].sum()) / total if total else 0.0
    if share < STARTUP_SHARE:
        return None
    return {"alarms_at_first_step": share,
            "rate_after_first_step": float(alarms[:, 1:].double().mean())}  # fmt: skip


def _at_floor(scores: torch.Tensor, threshold: float) -> float | None:
    """The share of the calibration ``scores`` (flat, NaN as ``−∞``) equal to ``threshold``
    where it is their lowest finite score, else ``None``."""
    finite = scores[torch.isfinite(scores)]
    if not finite.numel() or threshold != float(finite.min()):
        return None
    return float((scores == threshold).double().mean())


def alarms_at(scores: torch.Tensor, threshold: float) -> torch.Tensor:
    """The alarms ``scores > threshold`` (bool, ``scores``' shape), compared in float64; a
    NaN score (no data at that step) never alarms. ``threshold``: a number, ``±∞`` allowed;
    NaN refused (nothing had alarmed, and the metrics read 0 without a word)."""
    if (
        isinstance(threshold, bool)
        or not isinstance(threshold, numbers.Real)
        or math.isnan(threshold)
    ):
        raise ValueError(f"threshold must be a number (±inf allowed); got {threshold!r}")
    return nan_as_lowest(scores.double()) > threshold


def calibrated_metrics(output, traj, threshold: float | None, *, attacked_input: bool = True,
                       dt: float | None = None):  # fmt: skip
    """``threshold_at_far``, ``tpr_at_far``, ``fpr_at_far``, ``fpr_at_far_after_attack``,
    ``impact`` and ``detection_delay_at_far_steps`` (``_s`` with ``dt``, the sampling period)
    of one estimator's ``output`` on ``traj`` at ``threshold`` (``None``: all ``None``).
    The delay is that of :func:`difffilter.metrics.detection_delay` with the alarms at the
    calibrated threshold, not the estimator's own (an estimator alarming at every step had
    the best delay, 0, beside every detector judged at the common rate).

    ``fpr_at_far_after_attack``: the alarm rate on the attack-free steps 1 to
    :data:`AFTER_ATTACK_STEPS` after an attacked step of the same run (the false alarms an
    attack leaves behind, which ``fpr_at_far`` counts with the rest; ``None`` without such
    steps). ``impact``: over the attacked runs, the mean of the largest estimation error
    ``‖x̂_k − x_k‖`` at attacked steps before the run's first alarm on an attacked step at
    the threshold (the error an attacker causes while the detector has not seen it)."""
    out = dict.fromkeys(("threshold_at_far", "tpr_at_far", "fpr_at_far",
                         "fpr_at_far_after_attack", "impact", "detection_delay_at_far_steps",
                         "detection_delay_at_far_s"))  # fmt: skip
    det = output.detection
    if threshold is None or det is None or det.scores is None:
        return out
    alarms = alarms_at(det.scores, threshold)
    flags = traj.flags if attacked_input else torch.zeros_like(traj.flags)
    out["threshold_at_far"] = threshold
    if bool((~flags).any()):
        out["fpr_at_far"] = float(alarms[~flags].double().mean())
    if bool(flags.any()):
        out["tpr_at_far"] = float(alarms[flags].double().mean())
        after = after_attack(flags, AFTER_ATTACK_STEPS)
        if bool(after.any()):
            out["fpr_at_far_after_attack"] = float(alarms[after].double().mean())
        # attacked and before the first alarm on an attacked step (a false alarm before the
        # onset does not count as seeing the attack)
        unseen = flags & ((alarms & flags).long().cumsum(-1) == 0)
        error = (output.means.double() - traj.x.double()).norm(dim=-1)
        worst = torch.where(unseen, error, torch.zeros_like(error)).amax(-1)
        attacked_runs = flags.any(-1)
        out["impact"] = float(worst[attacked_runs].mean())
        steps = episode_delay(alarms, traj)["mean_delay"]
        if math.isfinite(steps):  # (no episode detected: no delay)
            out["detection_delay_at_far_steps"] = steps
            out["detection_delay_at_far_s"] = None if dt is None else steps * dt
    return out
