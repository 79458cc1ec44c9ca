"""Every evaluation metric, defined once, with its unit.

:data:`METRICS` is the single source of the metric names, units and definitions: the
JSON Schema of ``metrics.json`` (:mod:`difffilter.eval.report`), the reports, the
TensorBoard tables and ``docs/metrics.md`` read it. :func:`score` computes all of them
for one estimator's :class:`~difffilter.EstimatorOutput` on a batch of
:class:`~difffilter.models.scenario.Trajectories`.

Pooling: RMSEs pool every run, step and component (one mean of squares, then the root);
detection counts and rates pool every run and step. ROC curves are the library's
:func:`difffilter.metrics.roc_curve` (float64, ties grouped; NaN scores rank lowest).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from difffilter import metrics as dm
from difffilter.attack import Channel, same_side
from difffilter.estimator import EstimatorOutput

__all__ = [
    "Metric",
    "AFTER_ATTACK_STEPS",
    "METRICS",
    "FALSE_ALARM_BUDGET",
    "HEADLINE",
    "score",
    "roc",
    "auc",
    "rmse_over_time",
    "rates_by_size",
    "comparable_attack",
    "episode_steps",
    "episode_delay",
]

#: The headline metrics (the leaderboard's columns and the TensorBoard HPARAMS table's).
HEADLINE = ("attack_rmse", "auc", "tpr_at_1pct_fpr", "detection_delay_s", "state_rmse",
            "state_rmse_vs_attack_free", "time_per_step_s")  # fmt: skip

#: The false-alarm rate at which ``tpr_at_1pct_fpr`` reads the ROC curve.
FALSE_ALARM_BUDGET = 0.01


@dataclass(frozen=True)
class Metric:
    """A metric's unit and one-line definition (the formula of docs/metrics.md)."""

    unit: str
    definition: str
    kind: str = "number"  # "number" or "integer"


#: The attack-free steps ``1 … AFTER_ATTACK_STEPS`` after an attacked step of the same run
#: are those of ``fpr_at_far_after_attack`` (:func:`difffilter.metrics.after_attack`).
AFTER_ATTACK_STEPS = 10

METRICS: dict[str, Metric] = {
    "state_rmse": Metric(
        "state units",
        "sqrt(mean over runs, steps and state components of (x_hat - x)^2): pooled RMSE against the truth",
    ),
    "state_rmse_vs_attack_free": Metric(
        "state units",
        "pooled RMSE against the scenario's attack-free reference estimator under common random numbers",
    ),
    "attack_rmse": Metric(
        "attack units",
        "sqrt(mean over runs, attacked steps and attack channels of (a_hat - a)^2); a_hat = 0 where "
        "the estimator sees no attack",
    ),
    "tpr": Metric("fraction", "attacked steps with an alarm / attacked steps (pooled)"),
    "fpr": Metric("fraction", "attack-free steps with an alarm / attack-free steps (pooled)"),
    "false_alarms": Metric("count", "alarms on attack-free steps, all runs", "integer"),
    "missed_attacks": Metric("count", "attacked steps without an alarm, all runs", "integer"),
    "false_alarms_per_1000_steps": Metric(
        "per 1,000 steps", "1000 * false_alarms / (runs * steps)"
    ),
    "auc": Metric(
        "fraction",
        "area under the ROC curve of the detection scores (every run and step one sample)",
    ),
    "tpr_at_1pct_fpr": Metric(
        "fraction",
        "TPR of the score threshold whose false-alarm rate on the attack-free steps is at most 1 %",
    ),
    "detection_delay_steps": Metric(
        "steps",
        "mean over detected attack episodes (maximal runs of attacked steps) of first alarm - onset",
    ),
    "detection_delay_s": Metric("s", "detection_delay_steps * dt"),
    "attack_episodes": Metric("count", "attack episodes over all runs", "integer"),
    "episodes_detected": Metric("count", "episodes with an alarm inside them", "integer"),
    "time_per_step_s": Metric(
        "s",
        "wall time of the batched run / (runs * steps): time per run and step, what it "
        "cost in this study (work reused from an earlier scenario is not counted again)",
    ),
    "threshold": Metric(
        "score units",
        "the detector's own threshold, the one its alarms (tpr, fpr) came from (alarm when "
        "score > threshold; a CUSUM's tau), where it is one number for every run and step; "
        "null where it changes with the step or the decision is not a threshold of the score",
    ),
    "threshold_at_far": Metric(
        "score units",
        "the smallest score threshold whose false-alarm rate on attack-free calibration runs "
        "(their own seed) is at most the target rate (far.target); alarm when score > threshold",
    ),
    "tpr_at_far": Metric(
        "fraction", "attacked steps with score > threshold_at_far / attacked steps (pooled)"
    ),
    "fpr_at_far": Metric(
        "fraction",
        "attack-free steps of this study with score > threshold_at_far / attack-free steps: "
        "the false-alarm rate met on fresh runs",
    ),
    "fpr_at_far_after_attack": Metric(
        "fraction",
        f"attack-free steps 1 to {AFTER_ATTACK_STEPS} steps after an attacked step of the same "
        "run with score > threshold_at_far / such steps: the false alarms an attack leaves behind (fpr_at_far "
        "counts them with the rest)",
    ),
    "detection_delay_at_far_steps": Metric(
        "steps",
        "detection_delay_steps with the alarms at threshold_at_far (score > threshold_at_far): "
        "every detector's delay at the one false-alarm rate",
    ),
    "detection_delay_at_far_s": Metric("s", "detection_delay_at_far_steps * dt"),
    "impact": Metric(
        "state units",
        "mean over attacked runs of the largest |x_hat_k - x_k| at attacked steps before the "
        "run's first alarm on an attacked step at threshold_at_far: the estimation error an "
        "attacker causes unseen",
    ),
}


def _rmse(a: Tensor, b: Tensor) -> float:
    return float(dm.rmse(a.double(), b.double()))


def _nan_lowest(scores: Tensor) -> Tensor:
    """``scores`` in float64 with NaN (no score) below every score."""
    return dm.nan_as_lowest(scores.double())


def auc(scores: Tensor, flags: Tensor) -> float | None:
    """ROC AUC of ``scores [B, T]`` against ``flags [B, T]``; ``None`` if one class is absent."""
    area = dm.roc_auc(_nan_lowest(scores), flags.bool())
    return None if math.isnan(area) else area


def roc(scores: Tensor, flags: Tensor) -> tuple[Tensor, Tensor]:
    """``(fpr [M], tpr [M])`` of the ROC curve of ``scores [B, T]`` against ``flags [B, T]``."""
    fpr, tpr, _ = dm.roc_curve(_nan_lowest(scores), flags.bool())
    return fpr, tpr


def _tpr_at(scores: Tensor, flags: Tensor, budget: float) -> float | None:
    y = flags.flatten().long()
    if int(y.sum()) in (0, y.numel()):
        return None
    fpr, tpr = roc(scores, flags)
    ok = fpr <= budget + 1e-12
    return float(tpr[ok].max()) if bool(ok.any()) else 0.0


def rmse_over_time(means: Tensor, reference: Tensor) -> Tensor:
    """Per-step RMSE pooled over runs and components ``[T]``."""
    return (means.double() - reference.double()).square().mean(dim=(0, 2)).sqrt()


def score(
    output: EstimatorOutput,
    traj,
    *,
    dt: float,
    wall_s: float,
    reference_means: Tensor | None = None,
    attacked_input: bool = True,
) -> dict[str, Any]:
    """Every metric of :data:`METRICS` for one estimator (``None`` where it does not apply).

    Args:
        output: the estimator's output on ``traj`` (``means [B, T, dx]``).
        traj: the :class:`~difffilter.loop.Trajectories` the estimator ran on (``x``,
            ``attack``, ``flags``): the truth, from the loop, never from the output.
        dt: sampling period in s. wall_s: wall time of the batched run.
        reference_means: the attack-free reference estimate ``[B, T, dx]`` or ``None``.
        attacked_input: ``False`` for an estimator fed the clean measurements (its
            every alarm is false; no TPR, AUC or delay).
    """
    _check_runs_fit(output, traj, reference_means)
    B, T = traj.flags.shape
    out: dict[str, Any] = dict.fromkeys(METRICS)
    out["state_rmse"] = _rmse(output.means, traj.x)
    if reference_means is not None:
        out["state_rmse_vs_attack_free"] = _rmse(output.means, reference_means)
    flags = traj.flags
    if comparable_attack(output, traj) and bool(flags.any()):
        out["attack_rmse"] = _rmse(output.attack[flags], traj.attack[flags])
    out["time_per_step_s"] = wall_s / (B * T)
    det = output.detection
    if det is None:
        return out
    alarms = det.alarms
    if not attacked_input:
        flags = torch.zeros_like(flags)
    rates = dm.detection_rates(alarms, flags)
    out.update(
        threshold=own_threshold(det),
        fpr=_finite(rates["fpr"]),
        false_alarms=rates["false_alarms"],
        false_alarms_per_1000_steps=1000.0 * rates["false_alarms"] / (B * T),
    )
    if attacked_input and bool(flags.any()):
        delay = episode_delay(alarms, traj)
        steps = _finite(delay["mean_delay"])
        out.update(
            tpr=_finite(rates["tpr"]),
            missed_attacks=rates["missed_attacks"],
            auc=auc(det.scores, flags),
            tpr_at_1pct_fpr=_tpr_at(det.scores, flags, FALSE_ALARM_BUDGET),
            detection_delay_steps=steps,
            detection_delay_s=None if steps is None else steps * dt,
            attack_episodes=delay["episodes"],
            episodes_detected=delay["detected"],
        )
    return out


def _check_runs_fit(output: EstimatorOutput, traj, reference_means: Tensor | None) -> None:
    """The estimate is of ``traj``'s runs and steps: ``output.means`` (and
    ``reference_means``) of ``traj.x``'s shape ``[B, T, dx]``. An output of 4 of 8 runs
    failed inside torch ("The size of tensor a (4) must match …"), one of a single run
    ``[T, dx]`` on an IndexError about a boolean mask, naming neither argument."""
    want = tuple(traj.x.shape)
    for name, means in (("output.means", output.means), ("reference_means", reference_means)):
        if means is not None and tuple(means.shape) != want:
            raise ValueError(
                f"{name} {tuple(means.shape)} and traj.x {want} must have the same shape "
                "[B, T, dx]: score the output of the runs traj holds (every run, as a batch, "
                "e.g. estimator.run(system, traj.y_recv, traj.us))"
            )


def episode_steps(traj) -> Tensor:
    """The steps ``[B, T]`` (bool) whose runs of consecutive steps are the attack's episodes,
    for the detection delay: ``traj.flags``, and under a sensor schedule the attack's own
    steps (``info["attack_flags"]``) in the episodes of which at least one attacked reading
    arrived, the lost ones included. A lost reading does not end an attack: labelled step
    by step, a threat-model trial's 33 attacked runs under 20 % sensor loss split into 242
    episodes, each timed from its own start (a delay of 2.1 steps against 10.8 from the
    attacks' onsets); an attack none of whose readings arrived is none for the estimator
    (a review: 122 of 400 runs of a two-step attack under 50 % loss had counted as missed).
    The labels of TPR and FPR stay ``traj.flags``; :func:`episode_delay` times them."""
    info = getattr(traj, "info", None) or {}  # (what holds flags alone: no schedule)
    own = info.get("attack_flags")
    flags = traj.flags
    if (
        getattr(traj, "mask", None) is None
        or own is None
        or (info.get("attack_channel") is Channel.ACTUATOR)
    ):
        return flags
    own = own.any(-1) if own.dim() == 3 else own
    steps = flags | own.expand_as(flags)
    onset = steps & ~torch.cat([torch.zeros_like(steps[..., :1]), steps[..., :-1]], -1)
    episode = torch.cumsum(onset.long(), -1)  # [B, T]: the episode of each step, per run
    count = int(episode.max()) + 1
    key = torch.arange(steps.shape[0], device=steps.device).unsqueeze(-1) * count + episode
    seen = torch.zeros(steps.shape[0] * count, dtype=torch.bool, device=steps.device)
    seen[key[flags]] = True  # an episode with an attacked reading received
    return steps & seen[key]


def episode_delay(alarms: Tensor, traj) -> dict[str, float | int]:
    """:func:`difffilter.metrics.detection_delay` of ``alarms [B, T]`` over the episodes of
    :func:`episode_steps`, an episode detected at its first alarm on a step labelled
    attacked (``traj.flags``: a reading that arrived), as ``impact`` reads it."""
    return dm.detection_delay(alarms & traj.flags, episode_steps(traj))


def comparable_attack(output: EstimatorOutput, traj) -> bool:
    """Whether ``output``'s attack estimate measures the attack ``traj`` recorded: an
    estimate on the side of the plant the attack acted on (the sensors or the actuators,
    :func:`difffilter.attack.same_side`) with as many entries. Shapes alone are not enough:
    a one-sensor plant with one actuator would compare volts with metres."""
    if output.attack is None or output.attack.shape[-1] != traj.attack.shape[-1]:
        return False
    return same_side(output.attack_channel, traj.info.get("attack_channel", Channel.SENSOR))


def own_threshold(detection) -> float | None:
    """``detection.threshold`` as one number where it is one for every run and step (a
    number, or a tensor of one value throughout), else ``None`` (a windowed χ²'s during its
    first steps, a running ``ζ_k``, no threshold at all)."""
    tau = detection.threshold
    if isinstance(tau, torch.Tensor):
        if tau.numel() == 0 or not bool((tau == tau.flatten()[0]).all()):
            return None
        tau = tau.flatten()[0].item()
    return None if tau is None else _finite(float(tau))


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


def rates_by_size(alarms: Tensor, flags: Tensor, sizes: Tensor, bins) -> list[dict[str, Any]]:
    """Detection rate of attacked steps binned by attack size ``(lo, hi]``.

    ``alarms``, ``flags``, ``sizes`` (e.g. ``‖γ_k‖``): ``[B, T]``; ``bins``: increasing
    edges. Returns one ``{"lo", "hi", "steps", "rate"}`` per bin (``rate`` ``None`` if empty).
    """
    # 0/1 integer flags as a mask: ``alarms[m]`` with an integer ``m`` picked whole runs
    # (a metrics trial: rate 0.125 where 1 of 4 attacked steps alarmed is 0.25)
    dm._check_binary(flags, None, "flags", "(True on an attacked step)", "the attack's flags")
    dm._check_binary(alarms, None, "alarms", "(True on an alarmed step)", "a detector's decisions")
    flags = flags.bool()
    rows = []
    for lo, hi in zip(bins[:-1], bins[1:]):
        m = flags & (sizes > lo) & (sizes <= hi)
        rate = float(alarms[m].double().mean()) if bool(m.any()) else None
        rows.append({"lo": lo, "hi": hi, "steps": int(m.sum()), "rate": rate})
    return rows
