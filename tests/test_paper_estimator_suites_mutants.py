"""The papers' registered estimator suites (robot, tracking, four-tank) against what their
rows promise: which filter, with which of the scenario's parameters, on which sensors, from
which random streams, and what their outputs, extras and detections hold.

Truths: each registered estimator against the library routine called by hand with the
parameters read off ``docs/scenarios.md`` (lidar positions, groups, streams); numpy
covariance intersection (a golden-section search of ``tr P_f(ω)``) and information
fusion; ``âᵀ S⁻¹ â`` in numpy; identities (the fused estimators' locals are the locals
estimators' outputs, a mask makes unreceived values irrelevant, a clean-data filter is the
attacked-data filter given the clean data, u_sent,k = u_k − â_f,k−1 in the closed loop).
"""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace as NS

import numpy as np
import pytest
import torch

from difffilter.fdi.adaptive_kf import adaptive_kalman_filter
from difffilter.fdi.mdpf import adaptive_particle_filter, adaptive_particle_init
from difffilter.models import estimators, registry
from difffilter.models.estimators import SuiteContext
from difffilter.models.robot import DEG, RobotModel
from difffilter.models.robot_estimators import CompensatingInputs
from difffilter.models.streams import Streams
from difffilter.runtime import one_thread

F64 = torch.float64
#: docs/scenarios.md, Tan et al. (B7): the six lidars in cm; groups {1, 2, 3} and {4, 5, 6}
LIDARS = ((-120.0, 0.0), (-60.0, -60.0), (60.0, -60.0), (-60.0, 60.0), (60.0, 60.0), (120.0, 0.0))
GROUP_1, GROUP_2 = (0, 1, 2), (3, 4, 5)


def _cols(lidars):
    """Range and bearing columns of ``lidars`` (0-based) in the 12-entry measurement."""
    return [c for i in lidars for c in (2 * i, 2 * i + 1)]


def _robot(runs=2, seed=0, **changes):
    sc = replace(registry.get("robot_actuator_attack"), steps=44, num_particles=12, **changes)
    model, streams = sc.system(), Streams(seed)
    tr = sc.simulate(runs, {k: streams(k) for k in ("plant", "attack", "schedule")}, model=model)
    return SuiteContext(sc, model, runs, streams), tr


def _run(name, ctx, tr):
    return estimators.get(name).factory(ctx)(tr)


#: a scenario whose λ, S₀ and eq.-(5) reading differ from the library's defaults
CHANGED = {"forgetting": 0.9, "attack_cov0": 3.0, "reading": "copy"}


@one_thread()
def test_zhang_estimators_run_the_scenarios_lambda_and_s0_on_their_own_lidars():
    """``zhang_akf*`` is Zhang's filter with the scenario's λ and S₀ on all six lidars /
    lidars {1, 2, 3} / {4, 5, 6}: the routine called by hand with λ = 0.9, S₀ = 3 and the
    docs' lidar positions and measurement columns."""
    ctx, tr = _robot(**CHANGED)
    for name, lidars in (("zhang_akf", range(6)), ("zhang_akf_group1", GROUP_1),
                         ("zhang_akf_group2", GROUP_2)):  # fmt: skip
        model = RobotModel(sensors=torch.tensor([LIDARS[i] for i in lidars], dtype=F64))
        want = adaptive_kalman_filter(
            model, tr.y_recv[..., _cols(lidars)], tr.us, forgetting=0.9, attack_cov0=3.0
        )
        got = _run(name, ctx, tr)
        for a, b in ((got.means, want.means), (got.covs, want.covs), (got.attack, want.attack)):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-10, msg=name)


def _locals_by_hand(tr, seed, M, lam, s0, reading):
    """Both locals (A1)–(A8) as one batch on the docs' groups and streams."""
    grouped = RobotModel(
        sensors=torch.tensor([[LIDARS[i] for i in g] for g in (GROUP_1, GROUP_2)], dtype=F64)
    )
    ys = torch.stack([tr.y_recv[..., _cols(g)] for g in (GROUP_1, GROUP_2)])
    s = Streams(seed)
    init = adaptive_particle_init(grouped, M, (2, len(tr.y_recv)), s("particles/init"),
                                  attack_cov0=s0)  # fmt: skip
    return adaptive_particle_filter(
        grouped, ys, tr.us, num_particles=M, reading=reading, forgetting=lam, attack_cov0=s0,
        generator=s("particles/propagate"), resample_generator=s("particles/resample"),
        initial_state=init,
    )  # fmt: skip


@one_thread()
def test_mdpf_locals_are_group_1_and_group_2_with_the_scenarios_settings_and_streams():
    """``mdpf_local_1/2`` report local 1 / 2 of the batched run: every field (means, covs,
    â, Ŝ, ESS, scores, alarms, threshold) equals that group's entry of the adaptive PF run
    by hand with λ, S₀, the reading and M of the scenario and the docs' stream names."""
    ctx, tr = _robot(seed=3, **CHANGED)
    want = _locals_by_hand(tr, 3, 12, 0.9, 3.0, "copy")
    for g, name in enumerate(("mdpf_local_1", "mdpf_local_2")):
        got = _run(name, ctx, tr)
        pairs = ((got.means, want.means[g]), (got.covs, want.covs[g]),
                 (got.attack, want.attack[g]),
                 (got.extras["attack_covs"], want.extras["attack_covs"][g]),
                 (got.extras["ess"], want.extras["ess"][g]),
                 (got.detection.scores, want.detection.scores[g]))  # fmt: skip
        for a, b in pairs:
            torch.testing.assert_close(a, b, rtol=0, atol=1e-10, msg=name)
        assert torch.equal(got.detection.alarms, want.detection.alarms[g]), name
        assert got.detection.threshold == want.detection.threshold


def _ci_numpy(m1, P1, m2, P2):
    """Covariance intersection per cell: ω ∈ [0, 1] minimising tr P_f by golden section,
    P_f⁻¹ = ωP₁⁻¹ + (1−ω)P₂⁻¹, x_f = P_f(ωP₁⁻¹x₁ + (1−ω)P₂⁻¹x₂)."""
    I1, I2 = np.linalg.inv(P1), np.linalg.inv(P2)

    def cost(w):
        return np.trace(np.linalg.inv(w[..., None, None] * I1 + (1 - w)[..., None, None] * I2),
                        axis1=-2, axis2=-1)  # fmt: skip

    lo, hi = np.zeros(m1.shape[:-1]), np.ones(m1.shape[:-1])
    r = (np.sqrt(5) - 1) / 2
    for _ in range(80):
        a, b = hi - r * (hi - lo), lo + r * (hi - lo)
        left = cost(a) < cost(b)
        hi, lo = np.where(left, b, hi), np.where(left, lo, a)
    w = (lo + hi) / 2
    ends = np.stack([cost(np.zeros_like(w)), cost(w), cost(np.ones_like(w))])
    w = np.choose(ends.argmin(0), [np.zeros_like(w), w, np.ones_like(w)])
    Pf = np.linalg.inv(w[..., None, None] * I1 + (1 - w)[..., None, None] * I2)
    inner = (
        w[..., None] * (I1 @ m1[..., None])[..., 0]
        + (1 - w)[..., None] * (I2 @ m2[..., None])[..., 0]
    )
    return (Pf @ inner[..., None])[..., 0], Pf, w


def _info_numpy(m1, P1, m2, P2):
    """Naive information fusion: P_f⁻¹ = P₁⁻¹ + P₂⁻¹, x_f = P_f(P₁⁻¹x₁ + P₂⁻¹x₂)."""
    I1, I2 = np.linalg.inv(P1), np.linalg.inv(P2)
    Pf = np.linalg.inv(I1 + I2)
    return (Pf @ (I1 @ m1[..., None] + I2 @ m2[..., None]))[..., 0], Pf


def _wald_numpy(a, S):
    return np.einsum("...i,...i->...", a, np.linalg.solve(S, a[..., None])[..., 0])


@one_thread()
@pytest.mark.parametrize("name", ["mdpf_fused_ci", "mdpf_fused_naive"])
def test_fused_estimators_fuse_the_locals_estimators_by_their_rule(name):
    """The fused estimators' ``local_means``/``local_attacks`` are the locals estimators'
    outputs, and their x̂, P, â, S (and CI's ω, the state pair's weight) the numpy fusion
    of those locals by the estimator's own rule; score âᵀS⁻¹â (numpy), alarm score >
    the locals' threshold."""
    ctx, tr = _robot(seed=1, **CHANGED)
    fused = _run(name, ctx, tr)
    l1, l2 = _run("mdpf_local_1", ctx, tr), _run("mdpf_local_2", ctx, tr)
    for g, loc in enumerate((l1, l2)):
        torch.testing.assert_close(fused.extras["local_means"][..., g, :], loc.means,
                                   rtol=0, atol=1e-10)  # fmt: skip
        torch.testing.assert_close(fused.extras["local_attacks"][..., g, :], loc.attack,
                                   rtol=0, atol=1e-10)  # fmt: skip
    n = [t.numpy() for t in (l1.means, l1.covs, l2.means, l2.covs)]
    na = [t.numpy() for t in (l1.attack, l1.extras["attack_covs"], l2.attack,
                              l2.extras["attack_covs"])]  # fmt: skip
    if name == "mdpf_fused_ci":
        (x, P, w), (a, S, _) = _ci_numpy(*n), _ci_numpy(*na)
        np.testing.assert_allclose(fused.extras["omega"].numpy(), w, atol=1e-4)
    else:
        (x, P), (a, S) = _info_numpy(*n), _info_numpy(*na)
        assert "omega" not in fused.extras
    # ω is found to a tolerance: the fused values agree to about 1e-6 of their scale
    np.testing.assert_allclose(fused.means.numpy(), x, rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(fused.covs.numpy(), P, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(fused.attack.numpy(), a, rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(fused.extras["attack_covs"].numpy(), S, rtol=1e-5, atol=1e-7)
    score = _wald_numpy(fused.attack.numpy(), fused.extras["attack_covs"].numpy())
    np.testing.assert_allclose(fused.detection.scores.numpy(), score, rtol=1e-8)
    assert fused.detection.threshold == l1.detection.threshold
    assert torch.equal(fused.detection.alarms, fused.detection.scores > l1.detection.threshold)
    assert bool(fused.detection.alarms.any()) and not bool(fused.detection.alarms.all())


def _masked(tr, seed=5):
    """``tr`` with a mask (entries of lidars 1 and 5 lost at some steps) and garbage there."""
    B, T = tr.y_recv.shape[:2]
    mask = torch.ones(B, T, 12, dtype=torch.bool)
    mask[:, 3:40:4, :2] = False
    mask[:, 5:40:3, 8:10] = False
    mask[0, 20] = False
    g = torch.Generator().manual_seed(seed)
    garbage = tr.y_recv.masked_fill(~mask, 0.0) + (~mask) * 1e3 * torch.rand(
        tr.y_recv.shape, generator=g, dtype=F64
    )
    return NS(y_recv=tr.y_recv, us=tr.us, mask=mask), NS(y_recv=garbage, us=tr.us, mask=mask)


@one_thread()
@pytest.mark.parametrize("name", ["mdpf_local_2", "mdpf_fused_ci"])
def test_the_mdpf_estimators_read_the_trajectorys_mask(name):
    """Under a mask the values at unreceived entries change nothing (a dropped mask reads
    them: garbage up to 1e3 moves the estimate), and the mask does change the estimate;
    the fused one still scores âᵀS⁻¹â of its own (â, S) (numpy)."""
    ctx, tr = _robot(seed=2, **CHANGED)
    clean, garbage = _masked(tr)
    a, b = _run(name, ctx, clean), _run(name, ctx, garbage)
    torch.testing.assert_close(a.means, b.means, rtol=0, atol=0)
    torch.testing.assert_close(a.attack, b.attack, rtol=0, atol=0)
    unmasked = _run(name, ctx, tr)
    assert float((unmasked.means - a.means).abs().max()) > 1e-6
    score = _wald_numpy(a.attack.numpy(), a.extras["attack_covs"].numpy())
    np.testing.assert_allclose(a.detection.scores.numpy(), score, rtol=1e-8)
    if name == "mdpf_fused_ci":  # its locals are the masked locals estimators' outputs
        local = _run("mdpf_local_2", ctx, clean)
        torch.testing.assert_close(a.extras["local_means"][..., 1, :], local.means,
                                   rtol=0, atol=1e-10)  # fmt: skip


@one_thread()
@pytest.mark.parametrize("name", ["zhang_akf", "zhang_akf_group2"])
def test_the_zhang_estimators_read_the_trajectorys_mask(name):
    """A review: Zhang's filters ignored the mask and read entries never received (garbage
    up to 1e3 moved the estimate by hundreds of metres). Under the mask they equal the
    adaptive EKF given that mask (its group's columns for a group's filter) whatever the
    unreceived entries hold, and the mask changes the estimate."""
    ctx, tr = _robot(seed=2, **CHANGED)
    clean, garbage = _masked(tr)
    a, b = _run(name, ctx, clean), _run(name, ctx, garbage)
    torch.testing.assert_close(a.means, b.means, rtol=0, atol=0)
    assert float((_run(name, ctx, tr).means - a.means).abs().max()) > 1e-6
    cols = list(range(12)) if name == "zhang_akf" else [6, 7, 8, 9, 10, 11]
    model = ctx.model if name == "zhang_akf" else ctx.model.group((3, 4, 5))
    sc = ctx.scenario
    want = adaptive_kalman_filter(model, clean.y_recv[..., cols], clean.us,
                                  mask=clean.mask[..., cols], forgetting=sc.forgetting,
                                  attack_cov0=sc.attack_cov0)  # fmt: skip
    torch.testing.assert_close(a.means, want.means, rtol=0, atol=0)


def test_compensating_inputs_send_u_minus_the_attack_estimate_of_the_step():
    """Remark 1 on a varying command: ``init`` is u₀, step k sends u_k − â (NaN after the
    last row, refused past it, as KnownInputs reads a table), ``compensate=False`` or â = 0
    sends u_k (numbers by hand)."""
    us = torch.arange(2 * 4 * 2, dtype=F64).reshape(2, 4, 2)
    a = torch.tensor([[0.5, -1.0], [2.0, 0.25]], dtype=F64)
    ctl = CompensatingInputs(us)
    torch.testing.assert_close(ctl.init((2,), F64, None), us[:, 0])
    for k in (1, 2, 3):
        want = torch.tensor([[2.0 * k, 2.0 * k + 1], [8.0 + 2 * k, 9.0 + 2 * k]], dtype=F64) - a
        torch.testing.assert_close(ctl(k, None, NS(attack=a)), want, rtol=0, atol=0)
    assert bool(ctl(4, None, NS(attack=a)).isnan().all())
    with pytest.raises(ValueError, match=r"cover u_0 … u_3 \(T = 4\); step 7"):
        ctl(7, None, NS(attack=a))
    for c, att in ((CompensatingInputs(us, compensate=False), a), (ctl, torch.zeros_like(a))):
        torch.testing.assert_close(c(2, None, NS(attack=att)), us[:, 2], rtol=0, atol=0)


@one_thread()
def test_the_compensated_loop_sends_u_minus_the_previous_fused_ci_estimate():
    """``mdpf_fused_ci_compensated``: the plant receives u_k − â_f,k−1 + a_k with â_f the
    CI-fused estimate of the loop's own previous step (u₀ uncompensated), and the loop's
    estimator is the CI fusion (its ω reported)."""
    ctx, tr = _robot(seed=4)
    res = _run("mdpf_fused_ci_compensated", ctx, tr)
    traj, out = res.trajectories, res.output
    torch.testing.assert_close(traj.us[:, 0], tr.us[:, 0], rtol=0, atol=0)
    torch.testing.assert_close(traj.us[:, 1:], tr.us[:, 1:] - out.attack[:, :-1], rtol=0, atol=0)
    torch.testing.assert_close(traj.attack, tr.attack, rtol=0, atol=0)
    assert "omega" in out.extras
    assert float(out.attack[:, -1, 0].mean()) == pytest.approx(20.0, rel=0.2)
    assert float(out.attack[:, -1, 1].mean()) == pytest.approx(20 * DEG, rel=0.2)


# ---------------------------------------------------------------- tracking (Song et al.)


def _tracking(runs=2, seed=0, steps=16, **changes):
    sc = replace(registry.get("tracking_rrp_deception"), steps=steps, num_particles=48, **changes)
    model, streams = sc.system(), Streams(seed)
    tr = sc.simulate(runs, {k: streams(k) for k in ("plant", "attack", "schedule")}, model=model)
    return SuiteContext(sc, model, runs, streams), tr


def _as_received(tr, y_recv):
    return NS(y_recv=y_recv, y_true=tr.y_true, mask=tr.mask, flags=tr.flags, info=tr.info)


@one_thread()
def test_rrp_spf_nm_is_rrp_spf_da_given_the_attack_free_data():
    """RRP-SPF-NM reads the normal data: it equals RRP-SPF-DA handed ``y_true`` as its
    received data, and differs from RRP-SPF-DA on the attacked data; and RRP-SPF-DA reads
    the attacked data (a ``y_true`` it does not read changes nothing)."""
    ctx, tr = _tracking(seed=1)
    assert bool((tr.flags & tr.mask.any(-1)).any())  # a scheduled packet was replaced
    nm = _run("rrp_spf_nm", ctx, tr)
    da_clean = _run("rrp_spf_da", ctx, _as_received(tr, tr.y_true))
    torch.testing.assert_close(nm.means, da_clean.means, rtol=0, atol=0)
    da = _run("rrp_spf_da", ctx, tr)
    assert float((da.means - nm.means).abs().max()) > 1e-3
    other = NS(y_recv=tr.y_recv, y_true=tr.y_true + 5.0, mask=tr.mask, flags=tr.flags,
               info=tr.info)  # fmt: skip
    torch.testing.assert_close(_run("rrp_spf_da", ctx, other).means, da.means, rtol=0, atol=0)


@one_thread()
@pytest.mark.parametrize("name", ["rrp_pf_da", "rrp_spf_da", "rrp_pf_da_ekf_proposal"])
def test_round_robin_filters_read_only_the_scheduled_sensor(name):
    """The Round-Robin filters read the scheduled sensor only: values at the unscheduled
    entries (garbage in the box's range) change nothing, one packet is counted a step."""
    ctx, tr = _tracking(seed=2)
    g = torch.Generator().manual_seed(7)
    junk = torch.where(tr.mask, tr.y_recv, 50 * torch.rand(tr.y_recv.shape, generator=g, dtype=F64))
    a, b = _run(name, ctx, tr), _run(name, ctx, _as_received(tr, junk))
    torch.testing.assert_close(a.means, b.means, rtol=0, atol=0)
    assert a.extras["transmissions"].tolist() == [16, 16]


@one_thread()
def test_ekf_proposal_filter_scores_a_probability_and_alarms_above_one_half():
    """RRP-PF-DA with the EKF proposal: its score is a probability, alarm = score > 0.5,
    and it is not the bootstrap filter (the proposal changes the estimate)."""
    ctx, tr = _tracking(seed=3)
    out = _run("rrp_pf_da_ekf_proposal", ctx, tr)
    p = out.detection.scores
    assert bool(((p >= 0) & (p <= 1)).all()) and out.detection.threshold == 0.5
    assert torch.equal(out.detection.alarms, p > 0.5)
    boot = _run("rrp_pf_da", ctx, tr)
    assert float((out.means - boot.means).abs().max()) > 1e-6


@one_thread()
def test_ekf_proposal_filter_does_not_alarm_at_a_responsibility_just_below_one_half():
    """The alarm is ``score > 0.5``: the range of step 5's packet is moved (bisection on
    the shift) until the score lies in (0.4, 0.5); there the filter does not alarm."""
    ctx, tr = _tracking(seed=3)
    k, col = 5, int(tr.mask[0, 5].nonzero()[0])

    def score(shift):
        y = tr.y_recv[:, : k + 1].clone()
        y[0, k, col] += shift
        sub = NS(y_recv=y, y_true=tr.y_true[:, : k + 1], mask=tr.mask[:, : k + 1],
                 flags=tr.flags[:, : k + 1], info=tr.info)  # fmt: skip
        out = _run("rrp_pf_da_ekf_proposal", ctx, sub)
        return float(out.detection.scores[0, k]), bool(out.detection.alarms[0, k])

    lo, hi = 0.0, 40.0
    assert score(lo)[0] < 0.4 and score(hi)[0] > 0.5
    for _ in range(40):
        mid = (lo + hi) / 2
        p, alarm = score(mid)
        if 0.4 < p < 0.5:
            break
        lo, hi = (mid, hi) if p <= 0.4 else (lo, mid)
    assert 0.4 < p < 0.5 and not alarm


@one_thread()
def test_ekf_proposal_filter_is_eq_15_with_the_scenarios_defensive_weight():
    """On η̄ = 0.4: the driver by hand with eq. (15) (η̄ = 0.4, ξ ~ U([−10, 80] × [−π/2,
    π/2]) per sensor, docs) and the EKF proposal with defensive weight ρ = η̄ = 0.4."""
    import math

    from difffilter import fdi
    from difffilter.models.tracking import DeceptionEKFProposal
    from difffilter.noise import UniformBox
    from difffilter.particle import particle_filter

    ctx, tr = _tracking(seed=6, eta_bar=0.4)
    box = UniformBox(torch.tensor([-10.0, -math.pi / 2] * 4, dtype=F64),
                     torch.tensor([80.0, math.pi / 2] * 4, dtype=F64))  # fmt: skip
    lik = fdi.DeceptionMixtureLikelihood(0.4, fdi.ReplacementDeception(box))
    want = particle_filter(ctx.model, tr.y_recv, mask=tr.mask, likelihood=lik,
                           proposal=DeceptionEKFProposal(0.4), innovations=False,
                           **ctx.particle_kwargs(2))  # fmt: skip
    got = _run("rrp_pf_da_ekf_proposal", ctx, tr)
    torch.testing.assert_close(got.means, want.means, rtol=0, atol=1e-12)


@one_thread()
def test_pf_da_scores_the_scheduled_sensors_posterior_attack_probability():
    """PF-DA reads all four sensors; its score at step k is the per-sensor attack
    probability of the sensor the Round-Robin schedule sent (picked by hand from the
    mask), alarm above 0.5, and it counts four packets a step."""
    ctx, tr = _tracking(seed=4)
    out = _run("pf_da", ctx, tr)
    per = out.extras["sensor_attack_probability"]
    B, T, S = per.shape
    assert S == 4
    sched = tr.mask.reshape(B, T, S, 2)[..., 0].long().argmax(-1)
    want = per.gather(-1, sched[..., None])[..., 0]
    torch.testing.assert_close(out.detection.scores, want, rtol=0, atol=0)
    assert torch.equal(out.detection.alarms, want > 0.5)
    assert out.extras["transmissions"].tolist() == [4 * T, 4 * T]
    # a packet with one entry lost is still the scheduled sensor's (as the counts read it)
    mask = tr.mask.clone()
    mask[:, 3].view(B, S, 2)[torch.arange(B), sched[:, 3], 1] = False
    part = _run("pf_da", ctx, NS(y_recv=tr.y_recv, mask=mask, flags=tr.flags, info=tr.info))
    torch.testing.assert_close(part.detection.scores, want, rtol=0, atol=0)


# ---------------------------------------------------------------- four-tank


def _four_tank(name="four_tank_bias", runs=2, seed=0, steps=20, **changes):
    sc = replace(registry.get(name), steps=steps, num_particles=40, **changes)
    model, streams = sc.system(), Streams(seed)
    tr = sc.simulate(runs, {k: streams(k) for k in ("plant", "attack", "schedule")}, model=model)
    return SuiteContext(sc, model, runs, streams, sc.estimator_options()), tr


@one_thread()
def test_modified_pf_unknown_pl_runs_remark_6s_rate_for_the_scenarios_n():
    """``modified_pf_unknown_pl``: the modified PF with the oracle γ̂ = γ, the docs' PoA
    detector (η = 0.233, ζ = 0.5) and Remark 6's running p̂_l for the scenario's N = 40."""
    from difffilter import fdi

    ctx, tr = _four_tank(seed=1, steps=24)
    got = _run("modified_pf_unknown_pl", ctx, tr)
    want = fdi.modified_particle_filter(
        ctx.model, tr.y_recv, tr.us, mask=tr.mask, detector=fdi.PoADetector(0.233, 0.5),
        gamma_hat=tr.info["attack_values"], attack_rate=fdi.RunningAttackRate(40),
        **ctx.particle_kwargs(2),
    )  # fmt: skip
    torch.testing.assert_close(got.means, want.means, rtol=0, atol=1e-12)
    assert torch.equal(got.detection.alarms, want.detection.alarms)
    # eq. (46) in the warm-up (10 steps, α₀ = 0.5): ζ = α₀ (N − 1)/N = 0.4875 for N = 40
    zeta = torch.as_tensor(got.detection.threshold).expand(2, 24)
    torch.testing.assert_close(zeta[:, :10], torch.full((2, 10), 0.4875, dtype=F64))


@one_thread()
def test_modified_pf_eta_theorem1_uses_theorem_1s_eta_for_r_times_5():
    """``modified_pf_eta_theorem1`` on R × 5: η = 0.2692 (Theorem 1 for that R, docs), ζ =
    0.5: the modified PF with that detector by hand, not the nominal η = 0.233."""
    from difffilter import fdi

    ctx, tr = _four_tank("four_tank_bias_high_noise", seed=2, steps=24)
    eta = ctx.options["eta_theorem1"]
    assert eta == pytest.approx(0.2692, abs=1e-4)
    got = _run("modified_pf_eta_theorem1", ctx, tr)
    kw = ctx.particle_kwargs(2)
    want = fdi.modified_particle_filter(
        ctx.model, tr.y_recv, tr.us, mask=tr.mask, detector=fdi.PoADetector(eta, 0.5),
        gamma_hat=tr.info["attack_values"], **kw,
    )  # fmt: skip
    torch.testing.assert_close(got.detection.scores, want.detection.scores, rtol=0, atol=1e-12)
    assert torch.equal(got.detection.alarms, want.detection.alarms)
    nominal = _run("modified_pf", ctx, tr)
    assert not torch.equal(got.detection.scores, nominal.detection.scores)


@one_thread()
def test_normal_pf_literal_is_the_poa_pf_with_the_literal_density():
    """``normal_pf_literal``: the normal PF + PoA (η = 0.233, ζ = 0.5) with the Gaussian
    density in float64 literally; on γ̄ = 1 (31 σ: the density underflows) it differs
    from the same filter with the log-density."""
    from difffilter import fdi

    ctx, tr = _four_tank("four_tank_bias_large", seed=3, steps=24)
    got = _run("normal_pf_literal", ctx, tr)
    det = fdi.PoADetector(0.233, 0.5)

    def poa(literal):
        return fdi.particle_filter_poa(ctx.model, tr.y_recv, detector=det, literal=literal,
                                       **ctx.particle_kwargs(2))  # fmt: skip

    torch.testing.assert_close(got.means, poa(True).means, rtol=0, atol=1e-12)
    assert float((got.means - poa(False).means).abs().max()) > 1e-6


@one_thread()
def test_open_loop_pf_reads_no_measurement():
    """``open_loop_pf`` (all weights 1/N): any received data give the same estimate."""
    ctx, tr = _four_tank(seed=4)
    a = _run("open_loop_pf", ctx, tr)
    b = _run("open_loop_pf", ctx, NS(y_recv=tr.y_recv + 3.0, mask=tr.mask, us=tr.us))
    torch.testing.assert_close(a.means, b.means, rtol=0, atol=0)


@one_thread()
def test_kf_linearised_is_a_numpy_kalman_filter_on_the_fixed_point_linearisation():
    """``kf_linearised``: a numpy KF on δx_{k+1} = F δx_k + w, F the central-difference
    Jacobian at x* = the fixed point, Q = 1e-4 I, R = 1e-3 diag(1, 1, .5, .5), P₀ = 1e-2 I
    (docs), on y − x* (G = I), shifted back by x*; an unreceived entry is skipped."""
    ctx, tr = _four_tank(seed=5, steps=12)
    x_star = ctx.model.initial.mean
    assert (
        float((x_star - torch.tensor([12.263, 12.783, 1.634, 1.409], dtype=F64)).abs().max()) < 1e-3
    )
    h, I4 = 1e-5, np.eye(4)
    F = np.stack([((ctx.model.transition(x_star + h * torch.tensor(e), None, 0)
                    - ctx.model.transition(x_star - h * torch.tensor(e), None, 0)) / (2 * h)).numpy()
                  for e in I4], -1)  # fmt: skip
    Q, R = 1e-4 * I4, 1e-3 * np.diag([1.0, 1.0, 0.5, 0.5])
    mask = torch.ones(tr.y_recv.shape, dtype=torch.bool)
    mask[:, 4, 1] = False
    mask[1, 7] = False
    got = _run("kf_linearised", ctx, NS(y_recv=tr.y_recv, mask=mask, us=tr.us))
    xs = x_star.numpy()
    for b in range(2):
        x, P = np.zeros(4), 1e-2 * I4
        for k in range(12):
            x, P = F @ x, F @ P @ F.T + Q
            rec = mask[b, k].numpy()
            H = I4[rec]
            S = H @ P @ H.T + R[np.ix_(rec, rec)]
            K = P @ H.T @ np.linalg.inv(S)
            x = x + K @ ((tr.y_recv[b, k].numpy() - xs)[rec] - H @ x)
            P = (I4 - K @ H) @ P
            np.testing.assert_allclose(got.means[b, k].numpy(), x + xs, rtol=0, atol=1e-7)
            np.testing.assert_allclose(got.covs[b, k].numpy(), P, rtol=1e-6, atol=1e-12)


@one_thread()
def test_responsibility_score_uses_the_predictive_weights():
    """The responsibility of the proposal filters, P(l_k = 1 | ỹ_{1:k}) under the
    *predictive* weights: with the bootstrap proposal it equals RRP-PF-DA's score, which
    comes by another route (η̄ p_ξ(ỹ_k) over the evidence increment of the step)."""
    from difffilter.models.tracking_estimators import _responsibility_pf

    ctx, tr = _tracking(seed=5)
    hook = _responsibility_pf(ctx, tr).detection.scores
    evidence = _run("rrp_pf_da", ctx, tr).detection.scores
    torch.testing.assert_close(hook, evidence, rtol=1e-9, atol=1e-12)
    assert float(evidence.max()) > 0.5 > float(evidence.min())


@one_thread()
def test_pf_da_is_the_product_of_per_sensor_mixtures_with_the_scenarios_rate():
    """PF-DA on η̄ = 0.4: the driver by hand on all four sensors' data with the product of
    per-sensor mixtures, rate 0.4 and the docs' box [−10, 80] × [−π/2, π/2]."""
    import math

    from difffilter.models.tracking import PerSensorDeception
    from difffilter.particle import particle_filter

    ctx, tr = _tracking(seed=7, eta_bar=0.4)
    lik = PerSensorDeception(0.4, (-10.0, -math.pi / 2), (80.0, math.pi / 2), 4)
    want = particle_filter(ctx.model, tr.info["y_all"], likelihood=lik, innovations=False,
                           **ctx.particle_kwargs(2))  # fmt: skip
    got = _run("pf_da", ctx, tr)
    torch.testing.assert_close(got.means, want.means, rtol=0, atol=1e-12)


@one_thread()
def test_ukf_chi_square_is_the_generic_chi_square_ukf_with_counts():
    """``ukf_chi_square`` is the UKF gated by χ² (the generic ``chi_square_ukf``, not the
    EKF one) on the received data, with one packet a step counted."""
    ctx, tr = _tracking(seed=8)
    got = _run("ukf_chi_square", ctx, tr)
    ukf = estimators.get("chi_square_ukf").factory(ctx)(tr)
    torch.testing.assert_close(got.means, ukf.means, rtol=0, atol=0)
    torch.testing.assert_close(got.detection.scores, ukf.detection.scores, rtol=0, atol=0)
    ekf = estimators.get("chi_square_ekf").factory(ctx)(tr)
    assert float((ekf.means - ukf.means).abs().max()) > 1e-9
    assert got.extras["transmissions"].tolist() == [16, 16]
