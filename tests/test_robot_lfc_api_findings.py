"""What a trial of the robot and LFC Python APIs found, each checked against an independent
truth: a group's noise is the full model's (per lidar, correlated), a noise edited under the
adaptive particle filter is followed, the fused locals step online, and the LFC plant draws
the noise its buffers hold."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter import Generators
from difffilter.fdi.adaptive_kf import adaptive_kalman_filter
from difffilter.fdi.fusion import covariance_intersection
from difffilter.fdi.mdpf import AdaptiveParticleFilter
from difffilter.loop import open_loop
from difffilter.models.lfc import LFCPlant
from difffilter.models.robot import DEG, GROUPS, SENSORS, RobotModel
from difffilter.models.robot_estimators import FusedCarry, FusedLocals
from difffilter.noise import Gaussian

F64 = torch.float64


def _runs(runs=2, steps=12, seed=1):
    """Robot runs of the default model: ``(ys [B, T, 12], us [B, T, 2])``."""
    us = torch.tensor([5.0, 5.0 * DEG], dtype=F64).expand(runs, steps, 2).clone()
    _, ys, _ = RobotModel().simulate(
        steps, (runs,), us=us, generator=torch.Generator().manual_seed(seed)
    )
    return ys, us


def _gens(seed=0):
    return Generators(*(torch.Generator().manual_seed(seed + i) for i in range(3)))


def _noisy_second_group(scale=100.0, correlation=0.0):
    """The default robot with lidars 4–6 ``scale`` times noisier (and, optionally, range and
    bearing of lidar 5 correlated)."""
    m = RobotModel()
    var = torch.tensor([1.0, DEG**2] * 3 + [scale, scale * DEG**2] * 3, dtype=F64)
    R = torch.diag(var)
    c = correlation * math.sqrt(var[8] * var[9])
    R[8, 9] = R[9, 8] = c
    m.measurement_noise = Gaussian(torch.zeros(12, dtype=F64), R)
    return m


# -- RobotModel.group ---------------------------------------------------------------------
def test_a_group_keeps_the_full_models_per_lidar_and_correlated_noise():
    """The group's R is the full R's rows and columns of its sensors' entries; Q and P0 stay
    the full matrices (the group had rebuilt R from lidar 1's variances and kept only the
    diagonals of Q and P0)."""
    m = _noisy_second_group(correlation=0.3)
    Q = torch.tensor([[1.0, 0.2, 0.0], [0.2, 2.0, 0.01], [0.0, 0.01, DEG**2]], dtype=F64)
    m.process_noise = Gaussian(torch.zeros(3, dtype=F64), Q)
    m.initial = Gaussian(torch.tensor([1.0, 2.0, 0.1], dtype=F64), 2 * Q)
    R = m.measurement_cov(0)
    g = m.group(GROUPS[1])
    torch.testing.assert_close(g.measurement_cov(0), R[6:, 6:], rtol=0, atol=0)
    torch.testing.assert_close(g.process_cov(0), Q, rtol=0, atol=0)
    torch.testing.assert_close(g.initial.cov, 2 * Q, rtol=0, atol=0)
    torch.testing.assert_close(g.initial.mean, m.initial.mean, rtol=0, atol=0)
    one = m.group([4])
    torch.testing.assert_close(one.measurement_cov(0), R[8:10, 8:10], rtol=0, atol=0)
    assert one.measurement_cov(0)[0, 1] != 0
    torch.testing.assert_close(one.sensor_pos, torch.tensor([SENSORS[4]], dtype=F64))


def test_zhangs_filter_on_a_group_equals_it_on_a_model_built_for_those_lidars():
    """zhang_akf_group2's model: the full model made noisier on lidars 4–6, grouped, filters
    as a model built from those lidars and that noise directly."""
    ys, us = _runs()
    grouped = _noisy_second_group().group(GROUPS[1])
    direct = RobotModel(sensors=SENSORS[3:], meas_var=(100.0, 100.0 * DEG**2))
    a = adaptive_kalman_filter(grouped, ys[..., 6:], us)
    b = adaptive_kalman_filter(direct, ys[..., 6:], us)
    torch.testing.assert_close(a.means, b.means, rtol=0, atol=1e-12)
    default = adaptive_kalman_filter(RobotModel().group(GROUPS[1]), ys[..., 6:], us)
    assert (default.means - a.means).abs().max() > 1e-3  # the edit matters


def test_per_lidar_variances_at_construction_are_the_assigned_models():
    per_lidar = [(1.0, DEG**2)] * 3 + [(100.0, 100 * DEG**2)] * 3
    built = RobotModel(meas_var=per_lidar)
    torch.testing.assert_close(built.measurement_cov(0), _noisy_second_group().measurement_cov(0),
                               rtol=0, atol=0)  # fmt: skip
    with pytest.raises(ValueError, match=r"meas_var must be .* shape \(6, 2\)"):
        RobotModel(meas_var=[1.0, 2.0, 3.0])


def test_a_group_is_differentiable_in_the_full_models_noise():
    m = RobotModel()
    cov = m.measurement_noise.cov.clone().requires_grad_(True)
    m.measurement_noise = Gaussian(torch.zeros(12, dtype=F64), cov)
    m.group(GROUPS[1]).measurement_cov(0).trace().backward()
    expected = torch.zeros(12, 12, dtype=F64)
    expected[range(6, 12), range(6, 12)] = 1.0
    torch.testing.assert_close(cov.grad, expected)


def test_stacked_groups_of_different_noise_are_refused_by_name():
    assert RobotModel().groups_share_noise(GROUPS)
    m = _noisy_second_group()
    assert not m.groups_share_noise(GROUPS)
    with pytest.raises(ValueError, match="groups_share_noise"):
        m.group(GROUPS)
    for bad in ([7], [[0, 1], [2]], [0.5], []):
        with pytest.raises(ValueError, match="indices"):
            m.group(bad)


# -- FusedLocals ----------------------------------------------------------------------------
def test_the_fused_locals_step_online_with_the_full_models_measurement():
    """est.init + est.step with y [B, 12] gives the whole-sequence numbers (the step had
    refused 12 entries and raised IndexError with 6)."""
    ys, us = _runs(steps=10)
    model, est = RobotModel(), FusedLocals(AdaptiveParticleFilter(15))
    whole = open_loop(est, model, ys, us, generator=_gens())
    carry = est.init(model, (2,), _gens())
    assert isinstance(carry, FusedCarry) and carry.model is model
    means = []
    for t in range(ys.shape[1]):
        carry, out = est.step(carry, ys[:, t], us[:, t])
        means.append(out.mean)
    torch.testing.assert_close(torch.stack(means, 1), whole.means, rtol=0, atol=1e-10)
    with pytest.raises(ValueError, match=r"\[\.\.\., 12\]"):
        est.step(carry, ys[:, 0, :6], us[:, 0])


def test_fused_locals_of_groups_with_different_noise_run_each_group_on_its_own_noise():
    """Groups of different R run one at a time: the fused output equals each local's own
    public steps on its group's model, from the same generators in the same order, fused by
    covariance intersection (the R edit had changed nothing at all)."""
    ys, us = _runs(steps=8)
    m = _noisy_second_group()
    est = FusedLocals(AdaptiveParticleFilter(12), "ci")
    fused = open_loop(est, m, ys, us, generator=_gens())
    local = AdaptiveParticleFilter(12)
    gens = _gens()
    groups = [m.group(g) for g in GROUPS]
    carries = [local.init(g, (2,), gens) for g in groups]
    entries = [list(range(0, 6)), list(range(6, 12))]
    means, locals_ = [], []
    for t in range(ys.shape[1]):
        outs = []
        for i in range(2):
            carries[i], out = local.step(carries[i], ys[:, t, entries[i]], us[:, t])
            outs.append(out)
        x, _, _ = covariance_intersection(torch.stack([o.mean for o in outs], -2),
                                          torch.stack([o.cov for o in outs], -3))  # fmt: skip
        means.append(x)
        locals_.append(torch.stack([o.mean for o in outs], -2))
    torch.testing.assert_close(fused.means, torch.stack(means, 1), rtol=0, atol=1e-10)
    torch.testing.assert_close(
        fused.extras["local_means"], torch.stack(locals_, 1), rtol=0, atol=1e-10
    )
    default = open_loop(est, RobotModel(), ys, us, generator=_gens())
    assert (default.means - fused.means).abs().max() > 1e-3


# -- AdaptiveParticleFilter: a noise edited under it ---------------------------------------------
@pytest.mark.parametrize("form", ["information", "covariance", "auto"])
@pytest.mark.parametrize("how", ["assign", "in_place", "correlated"])
def test_the_adaptive_pf_follows_a_noise_edited_under_it(form, how):
    """The same estimator object after an edit of R filters as a fresh one (the information
    form had kept R and Q from its first step: 125 cm off)."""
    ys, us = _runs(steps=8)
    ys = ys[..., :6]
    model = RobotModel().group(GROUPS[0])
    est = AdaptiveParticleFilter(10, form=form)
    before = open_loop(est, model, ys, us, generator=_gens())
    if how == "assign":
        model.measurement_noise = Gaussian(
            torch.zeros(6, dtype=F64), 100 * model.measurement_noise.cov
        )
    elif how == "in_place":
        with torch.no_grad():
            model.measurement_noise.cov.mul_(100)
    else:  # a correlated R: the information form no longer applies
        R = model.measurement_noise.cov.clone()
        R[0, 1] = R[1, 0] = 0.5 * math.sqrt(R[0, 0] * R[1, 1])
        model.measurement_noise = Gaussian(torch.zeros(6, dtype=F64), R)
    if how == "correlated" and form == "information":
        with pytest.raises(ValueError, match="diagonal R"):
            open_loop(est, model, ys, us, generator=_gens())
        return
    reused = open_loop(est, model, ys, us, generator=_gens())
    fresh = open_loop(AdaptiveParticleFilter(10, form=form), model, ys, us, generator=_gens())
    torch.testing.assert_close(reused.means, fresh.means, rtol=0, atol=0)
    assert (reused.means - before.means).abs().max() > 1e-3


# -- LFCPlant ----------------------------------------------------------------------------------
def test_the_lfc_plant_draws_the_noise_its_loaded_buffers_hold():
    """After load_state_dict the truth's noise is the loaded Q and R, as the filter's model
    is (it had drawn from the constructor's variances: 100× too small on both)."""
    src = LFCPlant(process_var=1e-4, measurement_var=1e-2)
    p = LFCPlant()
    p.load_state_dict(src.state_dict())
    assert (p.process_var, p.measurement_var) == (1e-4, 1e-2)
    xi, theta = p.sample_noise(200, 500, torch.Generator().manual_seed(0))
    # 10⁶ draws: the sample variance is within 1 % of the truth at 7 standard errors
    assert abs(xi.var().item() / 1e-4 - 1) < 0.01 and abs(theta.var().item() / 1e-2 - 1) < 0.01


def test_the_lfc_plants_default_draws_are_unchanged_and_a_correlated_q_is_drawn_as_it_is():
    g = torch.Generator().manual_seed(3)
    xi, theta = LFCPlant().sample_noise(4, 6, g)
    g = torch.Generator().manual_seed(3)
    old_xi = torch.randn(4, 6, 10, generator=g, dtype=F64) * math.sqrt(1e-6)
    old_theta = torch.randn(4, 6, 10, generator=g, dtype=F64) * math.sqrt(1e-4)
    assert torch.equal(xi, old_xi) and torch.equal(theta, old_theta)
    p = LFCPlant()
    with torch.no_grad():
        p.Q[0, 1] = p.Q[1, 0] = 0.5e-6
    with pytest.raises(ValueError, match="Q is not a multiple of I"):
        _ = p.process_var
    xi, _ = p.sample_noise(400, 500, torch.Generator().manual_seed(1))
    corr = torch.corrcoef(xi.reshape(-1, 10).T)[0, 1]
    assert abs(corr.item() - 0.5) < 0.01  # 2·10⁵ pairs: standard error 0.002


@pytest.mark.parametrize("rule", ["ci", "naive"])
def test_fusion_refuses_means_and_covariances_of_two_dtypes(rule):
    """A float64 mean with a float32 covariance had been fused in silently promoted
    precision."""
    from difffilter.fdi.fusion import information_fusion

    fuse = covariance_intersection if rule == "ci" else information_fusion
    means, covs = torch.zeros(2, 3, dtype=F64), torch.eye(3).expand(2, 3, 3).clone()
    with pytest.raises(ValueError, match="means and covs must share one dtype"):
        fuse(means, covs)
    assert fuse(means, covs.double())[0].dtype == F64
