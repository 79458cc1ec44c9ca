"""The robot family's estimators and its compensated closed loop (Tan et al., App. B).

==================  =========================================================================
name                what it runs
==================  =========================================================================
zhang_akf           Zhang's adaptive EKF (λ, S₀ of the scenario) on all six lidars
zhang_akf_group1/2  the same on sensors {1, 2, 3} / {4, 5, 6}
mdpf_local_1/2      the local estimator (A1)–(A8) of group 1 / 2: both locals run as one
                    batched program (``[2, runs, N]`` particles), this one reported
mdpf_fused_ci       the two locals fused by covariance intersection (states and attacks)
mdpf_fused_naive    the same locals fused by naive information fusion (ablation)
==================  =========================================================================

The four MDPF estimators draw from the same streams (``particles/init``,
``particles/propagate``, ``particles/resample``), so their locals are identical: the
fused estimators differ from the locals only by the fusion, and from each other only by
the rule. The fused estimator is :class:`FusedLocals` (the two locals as one batched
:class:`~difffilter.fdi.AdaptiveParticleFilter`, fused at every step); its ``extras``
carry the locals (``"local_means"`` ``[B, T, 2, 3]``, ``"local_attacks"``
``[B, T, 2, 2]``) and the CI weight ``"omega"``.

``mdpf_fused_ci_compensated`` closes the loop of Remark 1 in difffilter's closed loop:
``u_sent,k = u_k − â_f,k`` (the fused attack estimate of the previous step, the
controller :class:`CompensatingInputs`), the plant receives ``u_sent + a``, and the
plant's noise is drawn from the study's ``plant`` stream (the same draws as the
simulated runs, so ``compensate=False`` reproduces them exactly).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch

from difffilter.estimator import Detection, Estimator, EstimatorOutput, Generators
from difffilter.fdi.adaptive_kf import adaptive_kalman_filter, wald_statistic
from difffilter.fdi.fusion import FusionRule, covariance_intersection, information_fusion
from difffilter.fdi.mdpf import (
    AdaptiveParticleFilter,
    adaptive_particle_filter,
    adaptive_particle_init,
)
from difffilter.gain_schedule import _STALE, _stamp, _unchanged
from difffilter.loop import (
    DrawnNoise,
    KnownInputs,
    LoopResult,
    _step_through,
    closed_loop,
    open_loop,
)
from difffilter.models.estimators import SuiteContext, family_register
from difffilter.particle import ParticleState
from difffilter.results import StepOutput

from .robot import GROUPS, RobotScenario

__all__ = [
    "group_measurements",
    "local_pair",
    "fuse_pair",
    "FusedCarry",
    "FusedLocals",
    "CompensatingInputs",
]

#: Every estimator here reads the robot scenario (its lidar groups) and estimates the
#: attack on the actuators.
register = family_register(RobotScenario, "robot", estimates="actuator")


def _entries(group) -> list[int]:
    return [2 * i + j for i in group for j in (0, 1)]


def group_measurements(ys: torch.Tensor, groups=GROUPS) -> torch.Tensor:
    """``ys [..., 12]`` → ``[G, ..., 6]``: each group's range–bearing entries."""
    return torch.stack([ys[..., _entries(g)] for g in groups])


def _opts(ctx: SuiteContext) -> dict:
    """The adaptive estimators' settings of the scenario: ``λ``, ``S_0`` and the Wald test's
    false-alarm rate (the scenario's ``false_alarm_rate``: it had been left at the library's
    1 % whatever the scenario said, a trial of the variants)."""
    sc = ctx.scenario
    return {"forgetting": sc.forgetting, "attack_cov0": sc.attack_cov0,
            "false_alarm_rate": sc.false_alarm_rate}  # fmt: skip


def local_pair(ctx: SuiteContext, tr) -> EstimatorOutput:
    """Both local estimators as one batched run: outputs ``[2, B, T, ·]``."""
    sc = ctx.scenario
    model = ctx.model.group(GROUPS)
    return adaptive_particle_filter(
        model, group_measurements(tr.y_recv), tr.us, num_particles=sc.num_particles,
        mask=None if tr.mask is None else group_measurements(tr.mask),
        reading=sc.reading, generator=ctx.streams("particles/propagate"),
        resample_generator=ctx.streams("particles/resample"),
        initial_state=adaptive_particle_init(
            model, sc.num_particles, (2, len(tr.y_recv)), ctx.streams("particles/init"),
            attack_cov0=sc.attack_cov0),
        **_opts(ctx),
    )  # fmt: skip


def fuse_pair(means, covs, attacks, attack_covs, rule: FusionRule | str):
    """Fuse locals stacked first (``[2, …, d]``) → ``(x̂, P, â, S, ω or None)``."""
    if FusionRule(rule) is FusionRule.CI:
        x, P, omega = covariance_intersection(means.movedim(0, -2), covs.movedim(0, -3))
        a, S, _ = covariance_intersection(attacks.movedim(0, -2), attack_covs.movedim(0, -3))
        return x, P, a, S, omega
    x, P = information_fusion(means.movedim(0, -2), covs.movedim(0, -3))
    a, S = information_fusion(attacks.movedim(0, -2), attack_covs.movedim(0, -3))
    return x, P, a, S, None


def _local(index: int):
    def factory(ctx: SuiteContext):
        def run(tr):
            out = local_pair(ctx, tr)
            det = out.detection
            return EstimatorOutput(
                out.means[index], out.covs[index], attack=out.attack[index],
                detection=Detection(det.scores[index], det.alarms[index], det.threshold),
                extras={"attack_covs": out.extras["attack_covs"][index], "ess": out.extras["ess"][index]},
            )  # fmt: skip

        return run

    return factory


def _fused(rule: FusionRule):
    def factory(ctx: SuiteContext):
        est = _fused_locals(ctx, rule)

        def run(tr):
            return open_loop(est, ctx.model, tr.y_recv, tr.us, mask=tr.mask,
                             generator=_generators(ctx))  # fmt: skip

        return run

    return factory


def _generators(ctx: SuiteContext) -> Generators:
    return Generators(ctx.streams("particles/init"), ctx.streams("particles/propagate"),
                      ctx.streams("particles/resample"))  # fmt: skip


def _zhang(group):
    def factory(ctx: SuiteContext):
        model = ctx.model if group is None else ctx.model.group(group)

        def run(tr):
            # (the schedule's mask too: without it the filter read entries never received)
            ys, mask = tr.y_recv, tr.mask
            if group is not None:
                ys = ys[..., _entries(group)]
                mask = None if mask is None else mask[..., _entries(group)]
            return adaptive_kalman_filter(model, ys, tr.us, mask=mask, **_opts(ctx))

        return run

    return factory


register("zhang_akf", "Zhang's adaptive EKF (Automatica 2018), all six lidars")(_zhang(None))
register("zhang_akf_group1", "Zhang's adaptive EKF, lidars {1, 2, 3}")(_zhang(GROUPS[0]))
register("zhang_akf_group2", "Zhang's adaptive EKF, lidars {4, 5, 6}")(_zhang(GROUPS[1]))
register("mdpf_local_1", "local estimator (A1)–(A8), lidars {1, 2, 3}")(_local(0))
register("mdpf_local_2", "local estimator (A1)–(A8), lidars {4, 5, 6}")(_local(1))
register("mdpf_fused_ci", "the two locals fused by covariance intersection")(_fused(FusionRule.CI))
register("mdpf_fused_naive", "the two locals fused by naive information fusion")(
    _fused(FusionRule.NAIVE)
)


class FusedCarry(NamedTuple):
    """Carry of :class:`FusedLocals`: the locals' carry ``local_states`` (one
    :class:`~difffilter.ParticleState` of the stacked groups ``[G, ...]``, or a tuple of one
    per group where the groups see different noise) and the full model."""

    local_states: Any
    model: Any
    #: The :class:`_ModelStamp` of ``model`` when the locals' grouped models were made from
    #: it (``None``: not checked).
    model_stamp: Any = None


def _check_fused_local(local) -> None:
    """A local whose ``S₀`` the fusion can invert (assigned later, ``attack_cov0 = 0`` had
    failed at the first step on "covs must be positive definite": an MDPF trial)."""
    if getattr(local, "attack_cov0", None) == 0:
        raise ValueError("local.attack_cov0 must be > 0: the fusion inverts each local's "
                         "attack covariance S, which S₀ = 0 keeps at 0")  # fmt: skip


class FusedLocals(Estimator):
    """The two local estimators of the sensor groups, fused at every step (App. B).

    One :class:`~difffilter.fdi.AdaptiveParticleFilter` runs both locals as a batch
    ``[G, ...]`` on the grouped model (each group's range–bearing entries); the fusion
    ``rule`` (:class:`~difffilter.fdi.fusion.FusionRule`: CI or information fusion) combines
    their states and attack estimates. Groups that see different measurement noise (blocks
    of ``R`` that differ: :meth:`~difffilter.models.robot.RobotModel.groups_share_noise`)
    cannot share one batched model; their locals then run one group at a time, each on its
    own group's model, from the same generators. The carry is a :class:`FusedCarry`; a step
    takes the full model's measurement ``y [..., 2S]`` (all lidars). Step output: the fused
    ``x̂, P, â``, the Wald score on ``(â, Ŝ)`` with the locals' threshold, ``extras``
    ``"attack_covs"`` ``Ŝ``, ``"local_means" [..., G, dx]``, ``"local_attacks" [..., G, du]``
    and, for CI, ``"omega"``.

    Whole sequences of stacked groups take a private fast path: the locals over the whole
    sequence, then the fusion of all runs and steps at once (one batched covariance
    intersection instead of ``T``), equal to the composed steps up to round-off (tested).
    """

    carry_type = FusedCarry

    def __init__(self, local: AdaptiveParticleFilter, rule: FusionRule | str = FusionRule.CI,
                 groups=GROUPS):  # fmt: skip
        if not isinstance(local, AdaptiveParticleFilter):  # (its carry read as the pair's:
            # an adaptive KF failed in "'Tensor' object has no attribute 'log_weights'")
            raise TypeError(f"local must be an AdaptiveParticleFilter (the paper's local "
                            f"estimator); got {type(local).__name__}")  # fmt: skip
        self.local, self.rule, self.groups = local, FusionRule(rule), tuple(groups)
        if len(self.groups) != 2:  # (three had run every local, then failed in the fusion)
            raise ValueError(f"groups must be two sensor groups (the fusion of a pair); got "
                             f"{len(self.groups)}: {self.groups!r}")  # fmt: skip
        _check_fused_local(local)

    def _init(self, model, batch_shape, generators):
        _check_fused_local(self.local)  # (its attack_cov0 may have been assigned since)
        if model.groups_share_noise(self.groups):
            grouped = model.group(self.groups)
            states = self.local._init(grouped, torch.Size((len(self.groups),)) + batch_shape,
                                      generators)  # fmt: skip
        else:
            states = tuple(self.local._init(model.group(g), batch_shape, generators)
                           for g in self.groups)  # fmt: skip
        return FusedCarry(states, model, _ModelStamp(model, self.groups))

    def _model_of(self, carry):
        return carry.model

    def batch_of(self, carry):
        states = carry.local_states
        if isinstance(states, ParticleState):
            return states.log_weights.shape[1:-1]
        return states[0].log_weights.shape[:-1]

    def _check_carry(self, carry):
        states = carry.local_states
        for state in (states,) if isinstance(states, ParticleState) else states:
            self.local._check_carry(state)

    def _locals_step(self, states, y, u, mask):
        """One step of the locals → (their new carry, mean, cov, attack, attack cov
        stacked first ``[G, ...]``, threshold)."""
        if isinstance(states, ParticleState):
            G = len(self.groups)
            u = None if u is None else u.expand((G,) + u.shape)
            # the mask too, grouped as the measurements (it was dropped: a lost entry read as 0)
            grouped_mask = None if mask is None else group_measurements(mask, self.groups)
            states, out = self.local._step(states, group_measurements(y, self.groups), u,
                                           grouped_mask)  # fmt: skip
            return (states, out.mean, out.cov, out.attack, out.extras["attack_covs"],
                    out.threshold)  # fmt: skip
        new, outs = [], []
        for state, g in zip(states, self.groups):
            entries = _entries(g)
            state, out = self.local._step(state, y[..., entries], u,
                                          None if mask is None else mask[..., entries])  # fmt: skip
            new.append(state)
            outs.append(out)
        stack = [torch.stack([getattr(o, f) for o in outs]) for f in ("mean", "cov", "attack")]
        attack_covs = torch.stack([o.extras["attack_covs"] for o in outs])
        return (tuple(new), *stack, attack_covs, outs[0].threshold)

    def _fuse(self, mean, cov, attack, attack_covs):
        """The locals' estimates stacked first ``[G, ...]`` (one step or whole sequences)
        fused → ``(x̂, P, â, Wald score, extras)``."""
        x, P, a, S, omega = fuse_pair(mean, cov, attack, attack_covs, self.rule)
        extras = {"attack_covs": S, "local_means": mean.movedim(0, -2),
                  "local_attacks": attack.movedim(0, -2)}  # fmt: skip
        if omega is not None:
            extras["omega"] = omega
        return x, P, a, wald_statistic(a, S), extras

    def _step(self, carry, y, u, mask):
        stamp = carry.model_stamp
        if stamp is not None and not stamp.holds(carry.model, self.groups):
            raise ValueError(
                "FusedLocals: the model changed since init (a noise or tensor of it assigned "
                "or written in place) or its groups were assigned, and the locals step grouped "
                "copies made at init (they would filter the model and groups as they were): "
                "init a new carry from them as they are now"
            )
        states, *local, thr = self._locals_step(carry.local_states, y, u, mask)
        x, P, a, score, extras = self._fuse(*local)
        return FusedCarry(states, carry.model, stamp), StepOutput(
            x, P, attack=a, score=score, alarm=score > thr, threshold=thr, extras=extras
        )

    def _run(self, carry, ys, us, mask):
        states = carry.local_states
        if mask is not None or not isinstance(states, ParticleState):
            return None
        G, batch = len(self.groups), self.batch_of(carry)
        us = None if us is None else us.expand((G,) + us.shape)
        out = _step_through(self.local, states, group_measurements(ys, self.groups), us, None,
                            torch.Size((G,)) + batch, None)  # fmt: skip
        x, P, a, score, extras = self._fuse(out.means, out.covs, out.attack,
                                            out.extras["attack_covs"])  # fmt: skip
        thr = out.detection.threshold
        return EstimatorOutput(x, P, attack=a, detection=Detection(score, score > thr, thr),
                               extras=extras)  # fmt: skip


class _ModelStamp:
    """The tensors a model holds (its noises' included), each with the gain schedule's stamp
    (:func:`~difffilter.gain_schedule._stamp`: version, memory, ``requires_grad``): an
    assignment (``model.measurement_noise = …``: other tensors) or a write in place is seen
    by :meth:`holds`. It holds the tensors themselves (an id could be a freed tensor's,
    taken by its replacement); a copy or a pickle of a carry copies them with the model,
    and :meth:`__setstate__` stamps the copies anew where they were unchanged, as the gain
    schedule does."""

    __slots__ = ("entries", "groups")

    def __init__(self, model, groups=None):
        self.entries = tuple((t, _stamp(t)) for t in _tensors_of(model))
        # the sensor groups the locals' models were made for (FusedLocals.groups assigned
        # since init had regrouped y over the old groups' models, lidar positions and all:
        # 120.8 m off; an options trial)
        self.groups = _groups_key(groups)

    def holds(self, model, groups=None) -> bool:
        now = _tensors_of(model)
        return (
            self.groups in (None, _groups_key(groups))
            and len(now) == len(self.entries)
            and all(t is held and _unchanged(t, s) for t, (held, s) in zip(now, self.entries))
        )

    def __getstate__(self):
        return tuple((t, _unchanged(t, stamp)) for t, stamp in self.entries), self.groups

    def __setstate__(self, state):
        if not state or _is_entry(state[0]):  # (pickled before the groups were kept)
            entries, self.groups = state, None
        else:
            entries, self.groups = state
        self.entries = tuple((t, _stamp(t) if same else _STALE) for t, same in entries)


def _tensors_of(model) -> list:
    return list(model.state_dict(keep_vars=True).values())


def _groups_key(groups):
    """Sensor groups as nested tuples (a list assigned compares equal), or ``None``."""
    return None if groups is None else tuple(tuple(int(i) for i in g) for g in groups)


def _is_entry(value) -> bool:
    """Whether ``value`` is one ``(tensor, unchanged)`` entry of a stamp's pickled state."""
    return (isinstance(value, tuple) and len(value) == 2 and isinstance(value[0], torch.Tensor)
            and isinstance(value[1], bool))  # fmt: skip


class CompensatingInputs(KnownInputs):
    """Remark 1's controller: the commanded inputs ``us [B, T, du]`` minus the fused attack
    estimate, ``u_sent,k = u_k − â_f,k`` (``compensate=False``: the commanded inputs).

    The table read as :class:`~difffilter.loop.KnownInputs` reads it: a loop of more steps
    than rows is refused, and the input after the last row is NaN, so that a loop resumed
    from that state is refused (the last row had been repeated: a resumed loop drove its
    first step with ``u_{T−1}``, a robot-loop trial)."""

    def __init__(self, us: torch.Tensor, *, compensate: bool = True):
        super().__init__(us)
        self.compensate = bool(compensate)

    def __call__(self, k, y, out):
        u = super().__call__(k, y, out)
        if not self.compensate:
            return u
        if out is None or out.attack is None:  # (an AttributeError/TypeError on None)
            raise ValueError(
                "CompensatingInputs subtracts the estimator's attack estimate (Remark 1), and "
                + ("this loop has no estimator" if out is None else
                   "the estimator's output carries none (out.attack is None)")
                + ": give closed_loop an estimator of the attack (the fused locals), or "
                "compensate=False"
            )  # fmt: skip
        return u - out.attack


def _fused_locals(ctx: SuiteContext, rule: FusionRule) -> FusedLocals:
    sc = ctx.scenario
    local = AdaptiveParticleFilter(sc.num_particles, reading=sc.reading, **_opts(ctx))
    return FusedLocals(local, rule)


def _compensated(compensate: bool = True):
    """A registry factory: the CI-fused estimator in its own closed loop with Remark 1's
    controller (module docstring); scored against that loop's states."""

    def factory(ctx: SuiteContext):
        sc, model, est = ctx.scenario, ctx.model, _fused_locals(ctx, FusionRule.CI)

        def run(tr) -> LoopResult:
            runs = tr.x.shape[0]
            x0 = model.initial.mean.expand(runs, model.dim_x).clone()
            # the study's schedule and input loss, drawn as Scenario.simulate draws them (a
            # lossy robot scenario's loop had filtered every lidar at every step, 11.9 cm
            # from the study's runs with compensate=False; a trial of the registry)
            losses = sc.input_loss_schedule()
            if losses is not None:
                us = sc.inputs(runs, ctx.dtype)
                losses = losses.draw(runs, sc.steps, us.shape[-1], ctx.streams("input_schedule"),
                                     device=us.device)  # fmt: skip
            return closed_loop(
                model, sc.steps, noise=DrawnNoise(ctx.streams("plant")), x0=x0, estimator=est,
                controller=CompensatingInputs(sc.inputs(runs, ctx.dtype), compensate=compensate),
                attack=sc.simulated_attack(), attack_generator=ctx.streams("attack"),
                generator=_generators(ctx), mask=tr.mask, input_loss=losses,
            )  # fmt: skip

        return run

    return factory


register("mdpf_fused_ci_compensated", "mdpf_fused_ci in Remark 1's closed loop: the sent input "
         "compensated by the fused attack estimate, u − â")(_compensated())  # fmt: skip
