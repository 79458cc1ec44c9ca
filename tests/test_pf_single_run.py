"""The particle filter's one-run steps (difffilter._pf_single_run, difffilter._pf_host_step)
against the general step.

For one run on the default strategies, ``ParticleFilter.step`` takes the written-out step,
and where no gradient can be recorded its host-array form; both must give the general
step's numbers (the same draws in the same order), values and gradients, in float64 where
round-off cannot move a resampling decision.
"""

from __future__ import annotations

import math
from functools import partial

import pytest
import torch

import difffilter as df
from difffilter import _pf_host_step, particle
from difffilter._pf_single_run import applies
from difffilter.estimator import Generators
from difffilter.models.four_tank import FourTankModel
from difffilter.resampling import Multinomial

STEPS = 40


def _linear_model(dtype=torch.float64, control=False, full_noise=False, cls=df.LinearGaussianModel):
    """A 3-state, 2-output linear model (of class ``cls``); a 1-input control matrix and a
    full (not diagonal) measurement covariance on request."""
    F = torch.tensor([[0.9, 0.1, 0.0], [0.0, 0.8, 0.2], [0.1, 0.0, 0.7]], dtype=dtype)
    H = torch.tensor([[1.0, 0.0, 0.5], [0.0, 1.0, 0.0]], dtype=dtype)
    R = (
        torch.tensor([[0.3, 0.1], [0.1, 0.2]], dtype=dtype)
        if full_noise
        else 0.2 * torch.eye(2, dtype=dtype)
    )
    B = torch.tensor([[1.0], [0.0], [0.5]], dtype=dtype) if control else None
    return cls(F, H, 0.05 * torch.eye(3, dtype=dtype), R,
                                  torch.zeros(3, dtype=dtype), torch.eye(3, dtype=dtype), B=B)  # fmt: skip


def _data(model, steps=STEPS, seed=0, du=0):
    gen = torch.Generator().manual_seed(seed)
    us = torch.randn(steps, du, generator=gen, dtype=torch.float64) if du else None
    with torch.no_grad():
        _, ys, _ = model.simulate(steps, (1,), generator=gen, us=None if us is None else us[None])
    return ys[0], us


def _run(pf, model, ys, us, general: bool, host: bool = False, masks=None):
    """Step ``pf`` through ``ys`` from one seeded carry: through ``pf.step`` (the one-run
    step where it applies; with ``host``, under ``torch.no_grad()``, where the host-array
    step applies, asserted) or the general step (given ``y`` zeroed where ``masks [T, dy]``
    says unreceived, as the public step hands it on). Returns the carries and outputs."""
    gens = Generators.of(torch.Generator().manual_seed(7))
    carry = pf.init(model, (), gens)
    carries, outs = [], []
    with torch.set_grad_enabled(not host):
        for k, y in enumerate(ys):
            u = None if us is None else us[k]
            mask = None if masks is None else masks[k]
            if general:
                y = y if mask is None else y.where(mask, 0.0)
                carry, out = particle._particle_step(pf, carry, y, u, mask)
            else:
                assert (_pf_host_step.density(carry, y, u) is not None) == host
                carry, out = pf.step(carry, y, u, mask)
            carries.append(carry)
            outs.append(out)
    return carries, outs


def _assert_same(a, b, tol=1e-10):
    (ca, oa), (cb, ob) = a, b
    for x, y in zip(ca, cb):
        torch.testing.assert_close(x.particles, y.particles, atol=tol, rtol=tol)
        torch.testing.assert_close(x.log_weights, y.log_weights, atol=tol, rtol=tol)
        torch.testing.assert_close(x.ess, y.ess, atol=tol, rtol=tol)
    for x, y in zip(oa, ob):
        for name in ("mean", "cov", "pred_mean", "log_likelihood", "innovation", "innovation_cov"):
            u, v = getattr(x, name), getattr(y, name)
            assert (u is None) == (v is None), name
            if u is not None:
                torch.testing.assert_close(u, v, atol=tol, rtol=tol, msg=name)
        for name in ("ess", "resampled", "degenerate"):
            torch.testing.assert_close(x.extras[name], y.extras[name], atol=tol, rtol=tol)
        assert set(x.extras) == set(y.extras)
        assert x.log_likelihood.shape == () and x.extras["resampled"].dtype == torch.bool


@pytest.mark.parametrize("innovations", [True, False])
@pytest.mark.parametrize("case", ["four_tank", "linear_control", "full_noise"])
def test_the_one_run_step_equals_the_general_step(case, innovations):
    du = 1 if case == "linear_control" else 0
    if case == "four_tank":
        model = FourTankModel(dtype=torch.float64)
    else:
        model = _linear_model(control=du > 0, full_noise=case == "full_noise")
    ys, us = _data(model, du=du)
    pf = df.ParticleFilter(200, innovations=innovations)
    assert applies(pf, pf.init(model, ()), None)
    fused, general = _run(pf, model, ys, us, False), _run(pf, model, ys, us, True)
    assert any(bool(o.extras["resampled"]) for o in fused[1])  # both branches ran
    assert not all(bool(o.extras["resampled"]) for o in fused[1])
    _assert_same(fused, general)


def test_gradients_equal_the_general_steps():
    """d/dy of the summed evidence and means through both steps (the same detached
    maximum, the same non-differentiable ancestors)."""
    model = _linear_model()
    ys, _ = _data(model, steps=12)
    pf = df.ParticleFilter(64)

    def grad(general):
        y = ys.clone().requires_grad_(True)
        _, outs = _run(pf, model, y, None, general)
        loss = sum(o.log_likelihood + o.mean.square().sum() + o.cov.sum() for o in outs)
        (g,) = torch.autograd.grad(loss, y)
        return g

    g_fused, g_general = grad(False), grad(True)
    assert g_fused.abs().sum() > 0
    torch.testing.assert_close(g_fused, g_general, atol=1e-10, rtol=1e-10)


def test_a_degenerate_step_resets_as_the_general_step():
    """A measurement every particle finds impossible: evidence −inf, weights reset to the
    predictive ones, the step flagged; then filtering goes on, in both steps alike."""
    model = _linear_model()
    ys, _ = _data(model, steps=6)
    ys = ys.clone()
    ys[3] = 1e200
    pf = df.ParticleFilter(50)
    fused, general = _run(pf, model, ys, None, False), _run(pf, model, ys, None, True)
    out = fused[1][3]
    assert bool(out.extras["degenerate"]) and out.log_likelihood.item() == -math.inf
    assert torch.isfinite(fused[1][5].log_likelihood)
    _assert_same(fused, general)


def test_where_the_one_run_step_does_not_apply():
    model = _linear_model()
    carry = df.ParticleFilter(10).init(model, ())
    batched = df.ParticleFilter(10).init(model, (3,))
    assert applies(df.ParticleFilter(10), carry, None)
    assert not applies(df.ParticleFilter(10), batched, None)  # a batch of runs
    assert not applies(df.ParticleFilter(10), carry, torch.tensor([True, False]))  # a mask
    assert not applies(df.ParticleFilter(10, resampler=Multinomial()), carry, None)
    assert not applies(df.ParticleFilter(10, proposal=df.KalmanProposal()), carry, None)
    assert not applies(df.ParticleFilter(10, record_prior=True), carry, None)
    assert not applies(df.ParticleFilter(10, hooks=[lambda *a: {}]), carry, None)
    assert not applies(df.ParticleFilter(10, cov_dims=1), carry, None)


# ----------------------------------------------------------------- the host-array step ----
class _WrappedAngleModel(df.LinearGaussianModel):
    """The linear model with its first output an angle: residuals wrapped into (−π, π]."""

    def measurement_residual(self, y, y_hat):
        r = super().measurement_residual(y, y_hat)
        return torch.cat([torch.remainder(r[..., :1] + math.pi, 2 * math.pi) - math.pi,
                          r[..., 1:]], dim=-1)  # fmt: skip


def _host_case(case: str):
    """``(model, ys [T, dy], us [T, du] or None)`` of a host-step case: the four-tank plant,
    the linear model with an input, or with an angle whose measurements are off by 2π
    (only wrapping undoes it)."""
    du = 1 if case == "linear_control" else 0
    if case == "four_tank":
        model = FourTankModel(dtype=torch.float64)
    elif case == "angles":
        model = _linear_model(cls=_WrappedAngleModel)
    else:
        model = _linear_model(control=True)
    ys, us = _data(model, du=du)
    if case == "angles":
        ys = ys + torch.tensor([2 * math.pi, 0.0], dtype=ys.dtype)
    return model, ys, us


@pytest.mark.parametrize("innovations", [True, False])
@pytest.mark.parametrize("case", ["four_tank", "linear_control", "angles"])
def test_the_host_step_equals_the_general_step(case, innovations):
    """Under ``torch.no_grad()`` one run takes the host-array step: the general step's
    numbers (both resampling branches run), in float64."""
    model, ys, us = _host_case(case)
    pf = df.ParticleFilter(200, innovations=innovations)
    host = _run(pf, model, ys, us, False, host=True)
    general = _run(pf, model, ys, us, True, host=True)
    assert any(bool(o.extras["resampled"]) for o in host[1])
    assert not all(bool(o.extras["resampled"]) for o in host[1])
    _assert_same(host, general)


def _lossy(ys, seed=3, lost=0.3):
    """``(ys with NaN where unreceived, masks [T, dy])``: each entry lost with probability
    ``lost``, and one step with every entry lost and one with none (a lossy network)."""
    masks = torch.rand(ys.shape, generator=torch.Generator().manual_seed(seed)) >= lost
    masks[5], masks[6] = False, True
    return ys.masked_fill(~masks, math.nan), masks


@pytest.mark.parametrize("innovations", [True, False])
@pytest.mark.parametrize("case", ["four_tank", "linear_control", "angles"])
def test_a_masked_host_step_equals_the_general_step(case, innovations, monkeypatch):
    """A mask of received entries (NaN in the lost ones) keeps one run on the host-array
    step: the general step's marginal density of the received entries and its masked
    predictive moments, in float64 (before, any mask took the general step)."""
    taken = []
    host_step = _pf_host_step.host_step
    monkeypatch.setattr(_pf_host_step, "host_step", lambda *a: taken.append(a[-1]) or host_step(*a))
    model, ys, us = _host_case(case)
    ys, masks = _lossy(ys)
    pf = df.ParticleFilter(200, innovations=innovations)
    host = _run(pf, model, ys, us, False, host=True, masks=masks)
    general = _run(pf, model, ys, us, True, host=True, masks=masks)
    assert len(taken) == len(ys) and all(torch.equal(m, masks[k]) for k, m in enumerate(taken))
    assert any(bool(o.extras["resampled"]) for o in host[1])
    _assert_same(host, general)
    if innovations:  # a lost entry: no innovation, a unit variance apart from the rest
        out, lost = host[1][5], ~masks[5]
        assert bool((out.innovation[lost] == 0).all())
        torch.testing.assert_close(out.innovation_cov, torch.eye(model.dim_y, dtype=ys.dtype))


def test_a_masked_host_steps_evidence_is_the_received_entries_density_by_hand():
    """The evidence of a masked step against its definition, from the step's own draws:
    ``log Σᵢ w⁻ᵢ N(y_M; h_M(xᵢ), R_MM)`` over the received entries ``M``, with ``w⁻`` the
    carry's weights (no resampling at ess_threshold 0) and ``xᵢ`` the proposed particles;
    the new weights ``w⁻ᵢ N(…) / Σ``; every entry lost: evidence 0, weights unchanged."""
    model = FourTankModel(dtype=torch.float64)
    ys, _ = _data(model, steps=3)
    pf = df.ParticleFilter(64, ess_threshold=0.0)
    mask = torch.tensor([True, False, True, False])
    sd = model.measurement_noise.cov.diagonal().sqrt()
    with torch.no_grad():
        carry = pf.init(model, (), Generators.of(torch.Generator().manual_seed(1)))
        carry, _ = pf.step(carry, ys[0])
        new, out = pf.step(carry, ys[1].masked_fill(~mask, math.nan), None, mask)
        r = (ys[1] - model.observe(new.particles, 2))[:, mask] / sd[mask]
        log_n = -0.5 * r.square().sum(-1) - sd[mask].log().sum() - math.log(2 * math.pi)
        joint = carry.log_weights + log_n
        torch.testing.assert_close(out.log_likelihood, torch.logsumexp(joint, 0), rtol=1e-12,
                                   atol=1e-12)  # fmt: skip
        torch.testing.assert_close(new.log_weights, joint - torch.logsumexp(joint, 0),
                                   rtol=1e-12, atol=1e-12)  # fmt: skip
        lost = torch.zeros(4, dtype=torch.bool)
        after, out = pf.step(new, torch.full((4,), math.nan, dtype=torch.float64), None, lost)
    assert abs(out.log_likelihood.item()) < 1e-12
    torch.testing.assert_close(after.log_weights, new.log_weights, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.mean, out.pred_mean, rtol=1e-12, atol=1e-12)


def _batch_of_one_runs(pf, model, ys, us, masks, host: bool):
    """``(through pf.step, through the general step)``: each ``(carries, outputs)`` of a
    carry from ``init(model, (1,))`` stepped with ``ys[k][None]`` (``us``, ``masks`` alike),
    from one seed."""
    runs = []
    for general in (False, True):
        carry = pf.init(model, (1,), Generators.of(torch.Generator().manual_seed(7)))
        carries, outs = [], []
        with torch.set_grad_enabled(not host):
            for k, y in enumerate(ys):
                u = None if us is None else us[k][None]
                mask = None if masks is None else masks[k][None]
                if general:
                    y = y if mask is None else y.where(masks[k], 0.0)
                    carry, out = particle._particle_step(pf, carry, y[None], u, mask)
                else:
                    carry, out = pf.step(carry, y[None], u, mask)
                carries.append(carry)
                outs.append(out)
        runs.append((carries, outs))
    return runs


@pytest.mark.parametrize("lossy", [False, True], ids=["received", "lost"])
@pytest.mark.parametrize("host", [True, False], ids=["no_grad", "grad"])
@pytest.mark.parametrize("case", ["four_tank", "linear_control", "angles"])
def test_a_batch_of_one_takes_its_runs_step_with_the_batched_numbers(case, host, lossy,
                                                                     monkeypatch):  # fmt: skip
    """A carry of ``init(model, (1,))`` steps its one run on the one-run steps (the host
    step without gradients, the written-out one with them; a mask takes the host step or,
    with gradients, the general step of the run) and gives the batched general step's
    numbers and shapes ``[1, …]`` (before, it took the batched general step, about 1.7 times
    as slow)."""
    model, ys, us = _host_case(case)
    masks = None
    if lossy:
        ys, masks = _lossy(ys)
    runs = []
    monkeypatch.setattr(particle._single_run, "run_of",
                        lambda c, f=particle._single_run.run_of: runs.append(c) or f(c))  # fmt: skip
    pf = df.ParticleFilter(200)
    (ca, oa), (cb, ob) = _batch_of_one_runs(pf, model, ys, us, masks, host)
    assert len(runs) == len(ys)  # every step went through its run
    for x, y in zip(ca, cb):
        for name in ("particles", "log_weights", "ess", "weights"):
            u, v = getattr(x, name), getattr(y, name)
            if v is None:  # (the general step keeps no weights: the one-run steps do)
                v = y.log_weights.exp()
            assert u.shape == v.shape, name
            torch.testing.assert_close(u, v, atol=1e-10, rtol=1e-10, msg=name)
    for x, y in zip(oa, ob):
        for name, u in zip(x._fields, x):
            v = getattr(y, name)
            if name == "extras":
                assert set(u) == set(v)
                u, v = list(u.values()), list(v.values())
            else:
                u, v = [u], [v]
            for a, b in zip(u, v):
                assert (a is None) == (b is None), name
                if isinstance(a, torch.Tensor):
                    assert a.shape == b.shape and a.dtype == b.dtype, name
                    torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10, msg=name)
    assert any(bool(o.extras["resampled"]) for o in oa)
    if not host:  # gradients flow through the run's step as through the batched one
        grads = []
        for general in (False, True):
            y = ys[:4].where(~torch.isnan(ys[:4]), 0.0).clone().requires_grad_(True)
            carry = pf.init(model, (1,), Generators.of(torch.Generator().manual_seed(7)))
            loss = 0.0
            for k in range(4):
                u = None if us is None else us[k][None]
                step = partial(particle._particle_step, pf) if general else pf.step
                carry, out = step(carry, y[k][None], u, None)
                loss = loss + out.log_likelihood.sum() + out.mean.sum()
            grads.append(torch.autograd.grad(loss, y)[0])
        assert grads[0].abs().sum() > 0
        torch.testing.assert_close(grads[0], grads[1], atol=1e-10, rtol=1e-10)


def test_particle_filter_on_one_run_is_the_online_step_to_the_last_bit_in_float32():
    """``particle_filter`` on ``ys [1, T, dy]`` steps its run as the online step of an
    unbatched carry does, on the host arrays: in float32 the two agree exactly (before, the
    batched step's sums, in another order, moved resampling targets: 6e-3 apart here)."""
    model = FourTankModel(dtype=torch.float32)
    with torch.no_grad():
        _, ys, _ = model.simulate(40, (1,), generator=torch.Generator().manual_seed(0))
        pf = df.ParticleFilter(500)
        carry = pf.init(model, (), torch.Generator().manual_seed(5))
        means, lls = [], []
        for y in ys[0]:
            carry, out = pf.step(carry, y)
            means.append(out.mean)
            lls.append(out.log_likelihood)
        whole = df.particle_filter(model, ys, num_particles=500,
                                   generator=torch.Generator().manual_seed(5))  # fmt: skip
    assert torch.equal(whole.means[0], torch.stack(means))
    assert torch.equal(whole.log_likelihood[0], torch.stack(lls).sum())


def test_a_batch_of_one_whose_model_was_given_one_parameter_set_keeps_the_batched_step():
    """``init`` refuses a model with parameter sets, but one may be assigned afterwards
    (``model.F = F[None]``): then the run's step could not read the model as it is, and the
    step stays the batched general one (the numbers of before), until the set is gone."""
    model = _linear_model()
    ys, _ = _data(model, steps=6)
    pf = df.ParticleFilter(30)
    one_of = particle._single_run.one_of_a_batch
    outs = {}
    for general in (False, True):
        carry = pf.init(model, (1,), Generators.of(torch.Generator().manual_seed(3)))
        assert one_of(pf, carry, ys[0][None], None, None)
        F = model.F
        model.F = F[None]
        assert not one_of(pf, carry, ys[0][None], None, None)
        with torch.no_grad():
            for y in ys:
                step = particle._particle_step if general else pf.step
                carry, out = (
                    step(pf, carry, y[None], None, None) if general else step(carry, y[None])
                )
        model.F = F
        assert one_of(pf, carry, ys[0][None], None, None)
        outs[general] = out
    assert outs[False].mean.shape == (1, 3)
    torch.testing.assert_close(outs[False].mean, outs[True].mean, rtol=0, atol=0)


def test_a_masked_degenerate_host_step_resets_as_the_general_step():
    """A received entry every particle finds impossible (the lost one holds NaN): evidence
    −∞, the predictive weights kept, the step flagged, as the general step; a far-off value
    in a lost entry alone is never read."""
    model = _linear_model()
    ys, _ = _data(model, steps=6)
    masks = torch.ones(ys.shape, dtype=torch.bool)
    masks[3, 1] = masks[4, 0] = False
    ys = ys.clone()
    ys[3, 0], ys[3, 1] = 1e200, math.nan  # impossible where received
    ys[4, 0] = 1e200  # far off, but lost
    pf = df.ParticleFilter(50)
    host, general = (
        _run(pf, model, ys, None, flag, host=True, masks=masks) for flag in (False, True)
    )
    assert bool(host[1][3].extras["degenerate"]) and host[1][3].log_likelihood.item() == -math.inf
    assert not bool(host[1][4].extras["degenerate"]) and torch.isfinite(host[1][4].log_likelihood)
    _assert_same(host, general)


def test_a_masked_host_step_in_float32_follows_the_general_step():
    model = FourTankModel(dtype=torch.float32)
    ys, _ = _data(model, steps=10)
    ys, masks = _lossy(ys.float())
    pf = df.ParticleFilter(100)
    oh = _run(pf, model, ys, None, False, host=True, masks=masks)[1]
    og = _run(pf, model, ys, None, True, host=True, masks=masks)[1]
    assert [bool(o.extras["resampled"]) for o in oh] == [bool(o.extras["resampled"]) for o in og]
    for a, b in zip(oh, og):
        torch.testing.assert_close(a.mean, b.mean, atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(a.log_likelihood, b.log_likelihood, atol=1e-3, rtol=1e-4)


def test_the_host_step_in_float32_follows_the_general_step():
    """float32 (what the online benchmark runs): the same resampling decisions and the
    estimates within float32 round-off over a short run."""
    model = FourTankModel(dtype=torch.float32)
    ys, _ = _data(model, steps=10)
    ys = ys.float()
    pf = df.ParticleFilter(100)
    oh = _run(pf, model, ys, None, False, host=True)[1]
    og = _run(pf, model, ys, None, True, host=True)[1]
    assert [bool(o.extras["resampled"]) for o in oh] == [bool(o.extras["resampled"]) for o in og]
    for a, b in zip(oh, og):
        assert a.mean.dtype == torch.float32 and a.log_likelihood.dtype == torch.float32
        torch.testing.assert_close(a.mean, b.mean, atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(a.log_likelihood, b.log_likelihood, atol=1e-3, rtol=1e-4)
        torch.testing.assert_close(a.innovation_cov, b.innovation_cov, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("n", [19, 53])
def test_the_first_decision_to_resample_is_the_general_steps_at_every_threshold(n):
    """A carry from init has no ESS: the host step once took its own log-sum-exp of the
    equal weights, which rounds otherwise than torch's in float32 (N = 19 at ess_threshold
    1: the host resampled at the first step, the general step did not)."""
    model = FourTankModel(dtype=torch.float32)
    ys, _ = _data(model, steps=5)
    pf = df.ParticleFilter(n, ess_threshold=1.0)
    oh = _run(pf, model, ys.float(), None, False, host=True)[1]
    og = _run(pf, model, ys.float(), None, True, host=True)[1]
    assert [bool(o.extras["resampled"]) for o in oh] == [bool(o.extras["resampled"]) for o in og]
    for a, b in zip(oh, og):
        torch.testing.assert_close(a.mean, b.mean, atol=1e-4, rtol=1e-4)


def test_a_degenerate_host_step_resets_as_the_general_step():
    model = _linear_model()
    ys, _ = _data(model, steps=6)
    ys = ys.clone()
    ys[3] = 1e200
    pf = df.ParticleFilter(50)
    host, general = (
        _run(pf, model, ys, None, False, host=True),
        _run(pf, model, ys, None, True, host=True),
    )
    out = host[1][3]
    assert bool(out.extras["degenerate"]) and out.log_likelihood.item() == -math.inf
    assert torch.isfinite(host[1][5].log_likelihood)
    _assert_same(host, general)


class _BlowsUp(df.LinearGaussianModel):
    """The linear model whose transition gives NaN from step ``k = 2`` on (``nan_state``) or
    whose observation gives NaN from measurement 3 on (a plug-in's NaN, not an underflow)."""

    nan_state = True

    def transition(self, x, u, k):
        out = super().transition(x, u, k)
        return out if not self.nan_state or k < 2 else torch.full_like(out, math.nan)

    def observe(self, x, k):
        out = super().observe(x, k)
        return out if self.nan_state or k < 3 else torch.full_like(out, math.nan)


@pytest.mark.parametrize("nan_state", [True, False], ids=["particles", "likelihood"])
@pytest.mark.parametrize("path", ["general", "one-run", "host"])
def test_a_nan_particle_or_density_is_named_on_every_path(nan_state, path):
    """A step whose every weight is NaN because the model's transition (or observation) gave
    NaN raises the general step's error naming the proposal (or the likelihood) at
    measurement 3, on the one-run torch step and the host-array step alike; before, the
    two one-run paths took it for an underflow (evidence NaN, mean NaN, flagged degenerate)
    and filtered on. A real underflow still resets on every path (the tests above)."""
    model = _linear_model(cls=_BlowsUp)
    model.nan_state = nan_state
    ys, _ = _data(_linear_model(), steps=4)
    pf = df.ParticleFilter(20)
    culprit = "particles proposed by BootstrapProposal" if nan_state else "likelihood of Model"
    with pytest.raises(ValueError, match=f"the {culprit}.* at step 3"):
        _run(pf, model, ys, None, general=path == "general", host=path == "host")


@pytest.mark.parametrize(
    "dtype, n", [(torch.float32, 1000), (torch.float32, 3), (torch.float64, 300)]
)
def test_after_a_degenerate_host_step_the_next_decision_is_the_general_steps(dtype, n):
    """ess_threshold = 1 after a reset to equal weights: ESS = N up to round-off decides
    the next resampling. The host took numpy's exp and dot (1000.00006 against torch's
    999.9998 in float32): other decisions, other draws, means 0.08–0.6 apart."""
    model = _linear_model(dtype)
    ys, _ = _data(model, steps=12)
    ys = ys.clone().to(dtype)
    ys[4] = ys[8] = 1e30 if dtype == torch.float32 else 1e200
    pf = df.ParticleFilter(n, ess_threshold=1.0)
    host, general = (_run(pf, model, ys, None, flag, host=True) for flag in (False, True))
    assert bool(host[1][4].extras["degenerate"])
    flags = [[bool(o.extras["resampled"]) for o in run[1]] for run in (host, general)]
    assert flags[0] == flags[1]
    if dtype == torch.float64:  # (float32: the resampling's round-off picks other ancestors)
        for a, b in zip(host[1], general[1]):
            torch.testing.assert_close(a.mean, b.mean, atol=1e-12, rtol=1e-12)


def test_a_carry_of_unnormalised_or_stale_weights_is_refused():
    """A carry made by hand: log-weights that do not sum to one scaled every mean (the
    steps add to them), and a replaced log_weights with the old ess/weights caches kept
    fed the stale weights to the prediction and the resampling decision."""
    model = _linear_model()
    pf = df.ParticleFilter(20, ess_threshold=0.0)
    carry = pf.init(model, (), torch.Generator().manual_seed(0))
    y = torch.tensor([2.0, 0.0], dtype=torch.float64)
    with torch.no_grad():
        carry, _ = pf.step(carry, y)
    uniform = torch.full((20,), -math.log(20), dtype=torch.float64)
    with pytest.raises(ValueError, match="log_weights must be normalised"):
        pf.step(
            carry._replace(
                log_weights=torch.zeros(20, dtype=torch.float64), ess=None, weights=None
            ),
            y,
        )
    with pytest.raises(ValueError, match="carry.weights is not exp"):
        pf.step(carry._replace(log_weights=uniform), y)
    with pytest.raises(ValueError, match="carry.ess is not"):
        pf.step(carry._replace(log_weights=uniform, weights=None), y)
    pf.step(carry._replace(log_weights=uniform, ess=None, weights=None), y)  # accepted


def test_the_host_step_reads_a_measurement_noise_changed_in_place():
    """The host copies of ``1/σ²`` follow the noise model's covariance (cached against
    its version): scaling ``R`` in place between steps changes the next step's weights
    as in the general step."""
    model = _linear_model()
    ys, _ = _data(model, steps=8)
    pf = df.ParticleFilter(64)

    def run(general):
        gens = Generators.of(torch.Generator().manual_seed(3))
        carry, outs = pf.init(model, (), gens), []
        with torch.no_grad():
            for k, y in enumerate(ys):
                if k == 4:
                    model.measurement_noise._cov.mul_(4.0)
                step = particle._particle_step if general else (lambda p, c, *a: p.step(c, a[0]))
                carry, out = step(pf, carry, y, None, None)
                outs.append(out)
                if k == 7:
                    model.measurement_noise._cov.div_(4.0)
        return outs

    host, general = run(False), run(True)
    for a, b in zip(host, general):
        torch.testing.assert_close(a.log_likelihood, b.log_likelihood, atol=1e-10, rtol=1e-10)
        torch.testing.assert_close(a.mean, b.mean, atol=1e-10, rtol=1e-10)


def test_where_the_host_step_does_not_apply():
    model = _linear_model()
    pf = df.ParticleFilter(10)
    carry = pf.init(model, ())
    y = torch.zeros(2, dtype=torch.float64)
    with torch.no_grad():
        assert _pf_host_step.density(carry, y, None) is not None
        grad_carry = carry._replace(particles=carry.particles.clone().requires_grad_(True))
        assert _pf_host_step.density(grad_carry, y, None) is None  # a gradient is wanted
        assert _pf_host_step.density(carry, y.clone().requires_grad_(True), None) is None
        full = _linear_model(full_noise=True)
        assert _pf_host_step.density(pf.init(full, ()), y, None) is None  # not diagonal
        half = carry._replace(particles=carry.particles.half())
        assert _pf_host_step.density(half, y, None) is None
    assert _pf_host_step.density(carry, y, None) is None  # grad mode on


def test_a_host_step_carry_goes_on_with_gradients():
    """Carries made without gradients feed a step with gradients: d/dy flows there."""
    model = _linear_model()
    ys, _ = _data(model, steps=6)
    pf = df.ParticleFilter(32)
    carry = pf.init(model, (), torch.Generator().manual_seed(0))
    with torch.no_grad():
        for y in ys[:3]:
            carry, _ = pf.step(carry, y)
    y = ys[3].clone().requires_grad_(True)
    _, out = pf.step(carry, y)
    (g,) = torch.autograd.grad(out.log_likelihood, y)
    assert torch.isfinite(g).all() and g.abs().sum() > 0


def test_inference_mode_gives_the_no_grad_numbers_and_keeps_carries_vouched():
    """Under ``torch.inference_mode()`` (tensors without version counters) the host step
    gives the numbers of ``torch.no_grad()``, and each returned carry is vouched for, so
    the next step skips the full validation."""
    from difffilter import _vouched

    model = _linear_model()
    ys, _ = _data(model, steps=10)
    pf = df.ParticleFilter(64)

    def run(mode):
        carry, outs = pf.init(model, (), Generators.of(torch.Generator().manual_seed(5))), []
        with mode():
            for y in ys:
                carry, out = pf.step(carry, y)
                assert _vouched.vouched(pf, carry) is not None
                outs.append(out)
        return outs

    for a, b in zip(run(torch.inference_mode), run(torch.no_grad)):
        torch.testing.assert_close(a.mean, b.mean, atol=0, rtol=0)
        torch.testing.assert_close(a.log_likelihood, b.log_likelihood, atol=0, rtol=0)


def test_checked_steps_accept_the_filters_own_carries_with_subnormal_weights():
    """float32, four-tank: a weight of 5.48e-42 (subnormal, fewer digits) differed from
    exp(log w) by 0.03 % relative, and every checked step (full_checks, or a carry copied)
    refused the carry the filter had just made (`make bench` stopped at section 2b)."""
    import copy

    model = FourTankModel(dtype=torch.float32)
    with torch.no_grad():
        _, ys, _ = model.simulate(50, (1,), generator=torch.Generator().manual_seed(0))
    pf = df.ParticleFilter(100)
    pf.full_checks = True
    gen = torch.Generator().manual_seed(1)
    subnormal = False
    with torch.no_grad():
        for _ in range(2):
            carry = pf.init(model, (), gen)
            for y in ys[0]:
                carry, _ = pf.step(carry, y)
                w = carry.weights
                subnormal |= bool(((w > 0) & (w < torch.finfo(w.dtype).tiny)).any())
                pf.step(copy.deepcopy(carry), y)  # a copy is checked in full too
    assert subnormal  # the case met


def test_equal_weights_at_ess_threshold_one_resample_as_the_torch_steps_decide():
    """A fuzzing trial: after a step whose weights come out exactly equal (every entry
    lost; a measurement noise of 1e30 that no particle tells apart), the host step's ESS
    by numpy, 1/(w·w) = 100.00000000000001, and the torch steps', 99.999999999999957, put
    ESS = N on either side of ess_threshold · N = N: one path resampled and the other did
    not, and the same seeds gave means 0.005–0.1 apart. The host step now takes torch's
    dot, so its decisions and numbers are the torch steps'."""
    d = torch.float64
    eye = torch.eye(1, dtype=d)
    ys = torch.tensor([[0.3], [0.5], [0.1], [-0.2], [0.4]], dtype=d)
    lost = torch.tensor([[True], [False], [True], [True], [True]])
    for R, masks in ((0.1 * eye, lost), (1e30 * eye, None)):
        model = df.LinearGaussianModel(0.9 * eye, eye, 0.1 * eye, R, torch.zeros(1, dtype=d), eye)
        pf = df.ParticleFilter(100, ess_threshold=1.0)
        host = _run(pf, model, ys, None, general=False, host=True, masks=masks)
        general = _run(pf, model, ys, None, general=True, masks=masks)
        one_run = _run(pf, model, ys, None, general=False, host=False, masks=masks)
        _assert_same(host, general)
        _assert_same(host, one_run)
        decided = [[bool(o.extras["resampled"]) for o in run[1]] for run in (host, one_run)]
        assert decided[0] == decided[1] and any(decided[0][1:])
