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
the rule. The fused estimators' ``extras`` carry their locals (``"local_means"``
``[2, B, T, 3]``, ``"local_attacks"`` ``[2, B, T, 2]``) and the CI weight ``"omega"``.

:func:`compensated_loop` closes the loop of Remark 1: ``u_sent,k = u_k − â_f,k`` (the
fused attack estimate of the previous step), the plant receives ``u_sent + a``, and the
plant's noise is replayed from the study's ``plant`` stream (the same draws as the
simulated runs, so ``compensate=False`` reproduces them exactly).
"""

from __future__ import annotations

import torch

from difffilter.estimator import Detection, EstimatorOutput
from difffilter.fdi.adaptive_kf import adaptive_kalman_filter, wald_statistic
from difffilter.fdi.fusion import covariance_intersection, information_fusion
from difffilter.fdi.mdpf import (
    adaptive_particle_filter,
    adaptive_particle_init,
    adaptive_particle_step,
)
from difffilter.models.estimators import SuiteContext, register

from .robot import GROUPS

__all__ = ["group_measurements", "local_pair", "fuse_pair", "compensated_loop"]


def _entries(group) -> list[int]:
    return [2 * i + j for i in group for j in (0, 1)]


def group_measurements(ys: torch.Tensor, groups=GROUPS) -> torch.Tensor:
    """``ys [..., 12]`` → ``[G, ..., 6]``: each group's range–bearing entries."""
    return torch.stack([ys[..., _entries(g)] for g in groups])


def _opts(ctx: SuiteContext) -> dict:
    sc = ctx.scenario
    return {"forgetting": sc.forgetting, "attack_cov0": sc.attack_cov0}


def local_pair(ctx: SuiteContext, tr) -> EstimatorOutput:
    """Both local estimators as one batched run: outputs ``[2, B, T, ·]``."""
    sc = ctx.scenario
    model = ctx.model.group(GROUPS)
    return adaptive_particle_filter(
        model, group_measurements(tr.y_recv), tr.us, num_particles=sc.num_particles,
        reading=sc.reading, generator=ctx.streams("particles/propagate"),
        resample_generator=ctx.streams("particles/resample"),
        initial_state=adaptive_particle_init(
            model, sc.num_particles, (2, len(tr.y_recv)), ctx.streams("particles/init"),
            attack_cov0=sc.attack_cov0),
        **_opts(ctx),
    )  # fmt: skip


def fuse_pair(means, covs, attacks, attack_covs, rule: str):
    """Fuse locals stacked first (``[2, …, d]``) → ``(x̂, P, â, S, ω or None)``."""
    if rule == "ci":
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


def _fused(rule: str):
    def factory(ctx: SuiteContext):
        def run(tr):
            out = local_pair(ctx, tr)
            x, P, a, S, omega = fuse_pair(
                out.means, out.covs, out.attack, out.extras["attack_covs"], rule
            )
            score = wald_statistic(a, S)
            extras = {"attack_covs": S, "local_means": out.means, "local_attacks": out.attack}
            if omega is not None:
                extras["omega"] = omega
            thr = out.detection.threshold
            return EstimatorOutput(
                x, P, attack=a, detection=Detection(score, score > thr, thr), extras=extras
            )

        return run

    return factory


def _zhang(group):
    def factory(ctx: SuiteContext):
        model = ctx.model if group is None else ctx.model.group(group)

        def run(tr):
            ys = tr.y_recv if group is None else tr.y_recv[..., _entries(group)]
            return adaptive_kalman_filter(model, ys, tr.us, **_opts(ctx))

        return run

    return factory


register("zhang_akf", "Zhang's adaptive EKF (Automatica 2018), all six lidars")(_zhang(None))
register("zhang_akf_group1", "Zhang's adaptive EKF, lidars {1, 2, 3}")(_zhang(GROUPS[0]))
register("zhang_akf_group2", "Zhang's adaptive EKF, lidars {4, 5, 6}")(_zhang(GROUPS[1]))
register("mdpf_local_1", "local estimator (A1)–(A8), lidars {1, 2, 3}")(_local(0))
register("mdpf_local_2", "local estimator (A1)–(A8), lidars {4, 5, 6}")(_local(1))
register("mdpf_fused_ci", "the two locals fused by covariance intersection")(_fused("ci"))
register("mdpf_fused_naive", "the two locals fused by naive information fusion")(_fused("naive"))


@torch.no_grad()
def compensated_loop(ctx: SuiteContext, runs: int, *, compensate: bool = True, rule: str = "ci"):
    """The fused estimator in closed loop with ``u ← u − â`` (module docstring).

    Returns a dict of ``"x"`` true states ``[B, T, 3]``, ``"means"`` fused estimates,
    ``"attack"`` fused ``â [B, T, 2]``, ``"sent"`` the sent inputs ``[B, T, 2]`` and
    ``"applied"`` the plant's inputs (``sent + a``).
    """
    sc, model = ctx.scenario, ctx.model
    dtype, T, N = ctx.dtype, sc.steps, sc.num_particles
    plant = ctx.streams("plant")
    us = sc.inputs(runs, dtype)
    values, flags = sc.attack_model().sample((runs,), T, 2, ctx.streams("attack"), dtype=dtype)
    injected = flags.unsqueeze(-1).to(dtype) * values
    gm = model.group(GROUPS)
    state = adaptive_particle_init(
        gm, N, (2, runs), ctx.streams("particles/init"), attack_cov0=sc.attack_cov0
    )
    prop, res = ctx.streams("particles/propagate"), ctx.streams("particles/resample")
    x = model.initial.mean.expand(runs, 3).clone()
    a_hat = x.new_zeros(runs, 2)
    xs, means, attacks, sent_all = [], [], [], []
    for t in range(T):
        sent = us[:, t] - a_hat if compensate else us[:, t]
        x = model.sample_transition(x, sent + injected[:, t], t, plant)
        y = model.sample_measurement(x, t + 1, plant)
        state, est = adaptive_particle_step(
            gm, state, group_measurements(y), sent.expand(2, runs, 2), reading=sc.reading,
            forgetting=sc.forgetting, generator=prop, resample_generator=res,
        )  # fmt: skip
        xf, _, af, _, _ = fuse_pair(est.mean, est.cov, est.attack, est.extras["attack_covs"], rule)
        a_hat = af
        xs.append(x)
        means.append(xf)
        attacks.append(af)
        sent_all.append(sent)
    sent = torch.stack(sent_all, 1)
    return {
        "x": torch.stack(xs, 1),
        "means": torch.stack(means, 1),
        "attack": torch.stack(attacks, 1),
        "sent": sent,
        "applied": sent + injected,
    }
