"""Adversarial training: attacks crafted against the current network join its batches.

A min–max alternation. Every ``every`` training steps the adversary crafts one stealthy
sensor attack against the network as it is (:func:`difffilter.stealthy.craft_stealthy_
attack`: maximise the state error through the training filter, with the network's own
detection score held under its current threshold: chosen for the weights as they are,
as the validation chooses it, ``task.current_threshold()``),
``iterations`` Adam steps on ``crafting_runs`` attack-free runs, from a random onset (with
``resample``, fresh runs at every iteration; with ``selection_runs``, the attack chosen on
that many held-out runs, as the evaluation's attacker chooses it). Until
the next crafting, every training batch gets ``runs`` more runs under that attack, on
fresh noise::

    ỹ_k = y_k + a_k,   attack = a_k,   flags = (k ≥ onset) ∧ (an attacked entry received)

(the closed loop's flags, :func:`difffilter.stealthy.attacked_pairs`: under packet loss
a step that received none of the attacked entries carries no attack)

so the network learns both to flag it and to subtract it. The attacker of the evaluation
(``eval/stealthy.py``) is the same crafting with more iterations against the final
network, on noise of its own seed.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import torch

from difffilter.estimator import Generators
from difffilter.models.streams import Streams
from difffilter.stealthy import StealthySettings, TooFewAttackedSteps, craft_stealthy_attack

from .common import mix_seed

__all__ = ["Adversary"]


@dataclass
class Adversary:
    """The attacker of adversarial training (module docstring).

    Args:
        runs: crafted-attack runs added to each training batch.
        iterations: Adam steps of each crafting.
        every: training steps between craftings.
        crafting_runs: attack-free runs the attack is crafted on.
        onsets: ``(first, last)``: the onset is drawn from them (both included).
        resample: fresh crafting runs at every iteration (``craft_stealthy_attack``'s
            ``resample``: the attack is fitted to the noise's law, not to one batch of it),
            or the same ``crafting_runs`` runs at every iteration.
        selection_runs: held-out attack-free runs the attack is chosen on, the iterates of
            largest error tried in turn until one keeps the alarm budget there
            (``craft_stealthy_attack``'s ``select``), or 0: the best iterate within the
            budget on its own batch.
    """

    runs: int
    iterations: int = 20
    every: int = 16
    crafting_runs: int = 8
    onsets: tuple[int, int] = (5, 60)
    resample: bool = False
    selection_runs: int = 0
    attack: torch.Tensor | None = field(default=None, repr=False)
    onset: int | None = None
    history: list = field(default_factory=list, repr=False)

    def __post_init__(self):
        for name in ("runs", "iterations", "every", "crafting_runs"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"adversarial_{name} must be an integer >= 1; got {value!r}")
        if not isinstance(self.resample, bool):
            raise ValueError(f"adversarial_resample must be true or false; got {self.resample!r}")
        sel = self.selection_runs
        if isinstance(sel, bool) or not isinstance(sel, int) or sel < 0:
            raise ValueError(f"adversarial_selection_runs must be an integer >= 0; got {sel!r}")
        if not isinstance(self.onsets, (tuple, list)) or len(self.onsets) != 2:
            # (Python's own "too many values to unpack" had named nothing)
            raise ValueError(f"adversarial_onsets must be [first, last], 1 <= first <= last; "
                             f"got {self.onsets!r}")  # fmt: skip
        self.onsets = lo, hi = tuple(self.onsets)
        if not (isinstance(lo, int) and isinstance(hi, int) and 1 <= lo <= hi):
            raise ValueError(f"adversarial_onsets must be [first, last], 1 <= first <= last; "
                             f"got {self.onsets!r}")  # fmt: skip

    def check_horizon(self, steps: int) -> None:
        """Refuse onsets that start after the scenario's last step: the draw had been clamped
        to the last step, an attack of one row, and a crafting an epoch later failed on too
        few attacked steps, naming no adversarial option (a red-team trial). ``last`` past the
        horizon is clamped (the draw covers the steps there are)."""
        if self.onsets[0] > steps:
            raise ValueError(
                f"adversarial_onsets {list(self.onsets)}: the first onset is after the "
                f"scenario's last step ({steps}): give onsets within 1 … {steps}"
            )
        if self.crafting_runs == 1 and self.onsets[0] >= steps:
            # every onset at the last step: one attacked (run, step), too few for the
            # crafting's smoothing, at every crafting (one drawn there now and then is
            # skipped, craft: a fit had died at such a crafting, an adversarial trial)
            raise ValueError(
                f"adversarial_onsets {list(self.onsets)} start at the last step ({steps}), "
                "and with adversarial_crafting_runs 1 an attack there has one attacked step, "
                "too few to craft on: give adversarial_crafting_runs >= 2, or an earlier "
                "first onset"
            )

    def due(self, step: int) -> bool:
        return self.attack is None or step % self.every == 0

    def craft(self, task, step: int) -> dict:
        """A new attack against ``task``'s network as it is now; returns what to log."""
        scenario, seed = task.scenario_of_data(), mix_seed(task.hparams.model_seed, step, 17)
        streams = Streams(seed)
        T = scenario.steps
        self.check_horizon(T)
        hi = min(self.onsets[1], T)
        onset = int(torch.randint(self.onsets[0], hi + 1, (), generator=streams("adversary/onset")))
        free = scenario.with_threat(None)
        device = task.device  # drawn on the CPU, crafted where the weights are

        def runs_of(prefix: str, runs: int):
            # the inputs and the receptions the training batches give the filter (task.py):
            # a crafting without the sensor schedule's mask ran on measurements it never gets
            tr = free.simulate(runs, streams.simulation(prefix), dtype=task._dtype)
            us = None if tr.us is None else tr.us.to(device)
            mask = None if tr.mask is None else tr.mask.to(device)
            return tr.y_true.to(device), tr.x.to(device), us, mask

        ys, xs, us, mask = runs_of("adversary/", self.crafting_runs)
        # (passed only where set: the crafting of before is called exactly as before)
        fresh = {}
        if self.resample:  # iteration 0 keeps the first batch above
            fresh["resample"] = lambda it: runs_of(f"adversary/{it}/", self.crafting_runs)
        if self.selection_runs:
            fresh["select"] = runs_of("adversary/selection/", self.selection_runs)
        estimator = task.estimator_object(training=True)
        params = list(task.estimator.parameters())
        flags = [p.requires_grad for p in params]
        for p in params:  # the attacker differentiates through the network, not into it
            p.requires_grad_(False)

        def generators():
            # one generator for the prior particles and the proposals, drawn one after the
            # other (as the task's own runs do): two generators of one stream drew the same
            # numbers twice, proposal noise equal to the initial particles' deviations
            particles = streams("adversary/particles", device)
            return Generators(particles, particles, streams("adversary/resample", device))

        settings = StealthySettings(iterations=self.iterations)
        try:
            # a zero attack (no iterate within the budget, on its own batch or the held-out
            # one) is logged as an error of 0 and leaves the batches as they are (augment):
            # no warning at every crafting
            with torch.enable_grad(), warnings.catch_warnings():
                warnings.filterwarnings(
                    "ignore", message="craft_stealthy_attack: (no iterate|none of the)"
                )
                crafted = craft_stealthy_attack(
                    estimator, task.system, ys, xs,
                    task.current_threshold(), far=task.false_alarm_rate, us=us, mask=mask,
                    onset=onset, settings=settings, generator=generators, **fresh,
                    # the attack-free rate is logged below instead: on a few crafting runs
                    # it strays from the target at times, and a warning at every crafting
                    # of a long run would bury the rest
                    warn_far_off=False,
                )  # fmt: skip
        except TooFewAttackedSteps as error:
            # a batch of too few received attacked steps (a late onset under packet loss):
            # this crafting is skipped, the attack of before kept; the next due step draws
            # other runs and another onset (a fit had died at such a crafting: a review)
            warnings.warn(f"adversarial training skipped the crafting at step {step}: {error}",
                          stacklevel=2)  # fmt: skip
            return {"adversarial_skipped": 1.0, "adversarial_onset": float(onset)}
        finally:
            for p, f in zip(params, flags, strict=True):
                p.requires_grad_(f)
        self.attack, self.onset = crafted.values.to(task._dtype), onset
        # the error of the attack kept: the best iterate within the alarm budget (zero, and
        # no attack, where none was; an iterate over the budget is not what the batches get);
        # with a selection, the chosen iterate's error on the held-out runs
        kept = crafted.kept_error()
        self.history.append((step, onset, kept))
        # the crafting runs' attack-free alarm rate at the threshold it crafted under: far
        # from the target rate, the alarm budget bounds little (or nothing)
        return {"adversarial_error": kept, "adversarial_onset": float(onset),
                "adversarial_attack_free_alarm_rate": crafted.budget - settings.slack}  # fmt: skip

    def state_dict(self) -> dict:
        """What a resumed run needs to go on with the same attack (a checkpoint's entry)."""
        return {"attack": self.attack, "onset": self.onset, "history": list(self.history)}

    def load_state_dict(self, state: dict) -> None:
        self.attack, self.onset = state["attack"], state["onset"]
        self.history = [tuple(h) for h in state["history"]]

    def kept_craftings(self) -> int:
        """The craftings that kept an attack (an error above zero: one that kept none, a zero
        attack of error 0, left the batches as they were)."""
        return sum(1 for entry in self.history if kept_an_attack(entry))

    def augment(self, batch: dict, scenario, seed: int, dtype) -> dict:
        """``batch`` with :attr:`runs` runs under the current attack appended (fresh
        attack-free runs of stream ``seed``, the attack added to what is received); ``batch``
        itself where the crafting kept no attack (every iterate broke the alarm budget: a
        zero attack, whose runs would be attack-free runs flagged as attacked)."""
        from .task import training_batch

        if not bool(self.attack.any()):
            return batch

        extra = training_batch(scenario.with_threat(None), self.runs, seed, dtype)
        T, dy = self.attack.shape
        attack = self.attack.to(extra["y_recv"]).expand(self.runs, T, dy)
        extra["y_recv"] = extra["y_recv"] + attack
        mask = extra.get("mask")
        # the attack on the entries received, zero on the others (Trajectories.attack): the
        # network's estimate is zero there by construction, so a label there was a loss no
        # weights could lower (a red-team trial: attack_mse 0.05 for a perfect estimator)
        extra["attack"] = attack.clone() if mask is None else attack * mask.to(attack.dtype)
        on = torch.arange(1, T + 1) >= self.onset
        flags = batch["flags"]
        # where an attacked entry arrived, as the closed loop flags (a lossy scenario's
        # steps that received nothing had been flagged: 48 of 142, a trial)
        hit = attack != 0 if mask is None else (attack != 0) & mask.bool()
        extra["flags"] = (on & hit.any(-1) if flags.dim() == 2
                          else on[:, None] & hit)  # fmt: skip
        if batch["attack"].shape[-1] != dy:
            raise ValueError("adversarial training needs a sensor attack on every channel")
        return {k: torch.cat([batch[k], extra[k].to(batch[k].dtype)]) for k in batch}


def kept_an_attack(entry) -> bool:
    """Whether a crafting of :attr:`Adversary.history`, ``(step, onset, kept error)``, kept an
    attack: the error of the attack kept is 0 exactly where none was (a zero attack)."""
    return float(entry[2]) > 0
