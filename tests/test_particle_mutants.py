"""Particle-filter step against independent numpy/float64 evaluations of its equations
(a mutation review of ``particle.py``, ``_pf_single_run.py`` and ``_pf_host_step.py``):
the resampling stream on every path, the defensive Kalman proposal's component pick, the
hooks' view of the step, the masked innovation covariance, the prior draw's stream, a
stateful likelihood's carried state and the host step's per-dtype constants."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter import particle
from difffilter.estimator import Generators

D = torch.float64
F_NP = np.array([[0.9, 0.2], [-0.1, 0.8]])
H_NP = np.array([[1.0, 0.5], [0.0, 1.0]])
Q_DIAG = np.array([0.04, 0.09])
R_DIAG = np.array([0.25, 0.16])


def _model(dtype=D):
    t = lambda a: torch.tensor(a, dtype=dtype)  # noqa: E731
    return df.LinearGaussianModel(
        t(F_NP), t(H_NP), t(np.diag(Q_DIAG)), t(np.diag(R_DIAG)),
        torch.zeros(2, dtype=dtype), torch.eye(2, dtype=dtype),
    )  # fmt: skip


def _state(n, dtype=D, batch=()):
    g = torch.Generator().manual_seed(11)
    x = torch.randn(*batch, n, 2, generator=g, dtype=D)
    lw = torch.log_softmax(1.5 * torch.randn(*batch, n, generator=g, dtype=D), -1)
    return particle.ParticleState(x.to(dtype), lw.to(dtype), 0)


def _log_normal_diag(r, var):
    """``log N(r; 0, diag(var))`` summed over the last axis, numpy float64."""
    return -0.5 * ((r * r / var).sum(-1) + np.log(2 * np.pi * var).sum())


def _hand_step(x, lw, y, u_offset, eps):
    """Systematic resampling with offset ``U`` (``a_j = F⁻¹((j + U)/N)``), bootstrap
    propagation ``F x + √q ε`` and the weights/evidence of the module docstring, all in
    numpy float64."""
    n = lw.shape[0]
    w = np.exp(lw)
    cdf = np.cumsum(w)
    a = np.searchsorted(cdf, (np.arange(n) + u_offset) / n * cdf[-1], side="right")
    new = x[a] @ F_NP.T + eps * np.sqrt(Q_DIAG)
    joint = -math.log(n) + _log_normal_diag(y - new @ H_NP.T, R_DIAG)
    top = joint.max()
    evidence = top + math.log(np.exp(joint - top).sum())
    return new, joint - evidence, evidence


@pytest.mark.parametrize("path", ["general", "single", "host"])
def test_resampling_draws_its_offset_from_the_resample_generator(path):
    """With separate propagate and resample generators, every path resamples with the
    offset ``U`` of the resample stream and propagates with the propagate stream: the new
    particles, log-weights and evidence equal a numpy evaluation of the step with those
    draws (a resampler fed from the propagate stream, or ``particle_step`` ignoring its
    ``resample_generator``, draws other numbers)."""
    n, model = 8, _model()
    state = _state(n)
    y = torch.tensor([0.4, -0.3], dtype=D)
    gp, gr = torch.Generator().manual_seed(5), torch.Generator().manual_seed(6)
    u_offset = torch.rand((1,), generator=torch.Generator().manual_seed(6), dtype=D).item()
    eps = torch.randn(n, 2, generator=torch.Generator().manual_seed(5), dtype=D).numpy()
    new_np, lw_np, ev_np = _hand_step(
        state.particles.numpy(), state.log_weights.numpy(), y.numpy(), u_offset, eps
    )
    if path == "general":
        new, out = particle.particle_step(
            model, state, y, ess_threshold=1.0, generator=gp, resample_generator=gr
        )
    else:
        pf = df.ParticleFilter(n, ess_threshold=1.0)
        carry = pf.attach(state, model, Generators(None, gp, gr))
        with torch.set_grad_enabled(path == "single"):
            new, out = pf.step(carry, y)
    assert bool(out.extras["resampled"])
    np.testing.assert_allclose(new.particles.numpy(), new_np, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(new.log_weights.detach().numpy(), lw_np, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(float(out.log_likelihood), ev_np, rtol=1e-10)


def test_defensive_kalman_proposal_draws_the_prior_component_with_probability_rho():
    """``q = (1 − ρ) N(μ, Σ) + ρ N(f, Q)``: a particle whose pick uniform is below ``ρ``
    is ``f + chol(Q) ε`` with ``f = F x`` (numpy), every other one is not; the ε and the
    uniforms are re-drawn from a copy of the generator in the proposal's order (normals,
    then uniforms)."""
    n, rho, model = 400, 0.25, _model()
    x = torch.randn(n, 2, generator=torch.Generator().manual_seed(1), dtype=D)
    y = torch.tensor([3.0, -2.0], dtype=D)
    new, _ = particle.KalmanProposal(defensive=rho)(
        model, x, None, y, 0, None, torch.Generator().manual_seed(2)
    )
    g = torch.Generator().manual_seed(2)
    eps = torch.randn(n, 2, generator=g, dtype=D).numpy()
    pick = torch.rand(n, generator=g, dtype=D).numpy() < rho
    prior_draw = x.numpy() @ F_NP.T + eps * np.sqrt(Q_DIAG)
    at_prior = np.isclose(new.numpy(), prior_draw, rtol=0, atol=1e-12).all(-1)
    assert 60 < pick.sum() < 140  # ~Binomial(400, 0.25): mean 100, sd 8.7
    np.testing.assert_array_equal(at_prior, pick)


def test_hooks_see_the_new_carry_and_leave_no_unasked_prior_weights():
    """A hook is called with the step's new carry (its ``k`` and particles are those the
    step returns) and may read ``prior_log_weights`` (the normalised predictive weights:
    ``logsumexp = 0``); without ``record_prior`` the step's extras do not keep them."""
    seen = {}

    def hook(model, y, mask, carry, out):
        seen["k"], seen["particles"] = carry.k, carry.particles
        seen["prior"] = out.extras["prior_log_weights"]
        return {"mean_x0": carry.particles[..., 0].mean(-1)}

    n, model = 16, _model()
    pf = df.ParticleFilter(n, hooks=(hook,))
    carry = pf.attach(_state(n, batch=(2,)), model, Generators.of(torch.Generator().manual_seed(0)))
    new, out = pf.step(carry, torch.tensor([[0.1, 0.2], [-0.5, 0.3]], dtype=D))
    assert seen["k"] == 1 and seen["particles"] is new.particles
    np.testing.assert_allclose(
        out.extras["mean_x0"].numpy(), new.particles[..., 0].mean(-1).numpy(), rtol=1e-14
    )
    np.testing.assert_allclose(torch.logsumexp(seen["prior"], -1).numpy(), 0.0, atol=1e-12)
    assert "prior_log_weights" not in out.extras


def test_masked_innovation_covariance_is_the_received_block_with_unit_stand_ins():
    """``S' = M (Σᵢ wᵢ (hᵢ − ŷ)(hᵢ − ŷ)ᵀ + R) M + (I − M)`` (``masked_measurement``'s
    convention) and ``y − ŷ`` zero where unreceived, against numpy on the step's own
    proposed particles and predictive weights; one run receives entry 0 only, the other
    both."""
    n, model = 12, _model()
    state = _state(n, batch=(2,))
    mask = torch.tensor([[True, False], [True, True]])
    y = torch.tensor([[0.3, 9.0], [-0.2, 0.5]], dtype=D)
    new, out = particle.particle_step(
        model, state, y, mask=mask, ess_threshold=0.0, generator=torch.Generator().manual_seed(4)
    )
    w = np.exp(state.log_weights.numpy())  # no resampling, bootstrap: predictive = w_{k-1}
    h = new.particles.numpy() @ H_NP.T
    for b in range(2):
        m = mask[b].numpy().astype(float)
        y_hat = w[b] @ h[b]
        dev = h[b] - y_hat
        s = (dev.T * w[b]) @ dev + np.diag(R_DIAG)
        expected = np.outer(m, m) * s + np.diag(1.0 - m)
        np.testing.assert_allclose(out.innovation_cov[b].numpy(), expected, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(
            out.innovation[b].numpy(), m * (y[b].numpy() - y_hat), atol=1e-13
        )


def test_init_draws_the_prior_particles_from_the_init_generator():
    """``init`` with separate generators draws ``x₀ ~ N(m₀, P₀)`` (here ``m₀ = 0``,
    ``P₀ = I``: the normals themselves) from ``Generators.init``, not the propagate one."""
    n = 6
    pf = df.ParticleFilter(n)
    gens = Generators(torch.Generator().manual_seed(21), torch.Generator().manual_seed(22),
                      torch.Generator().manual_seed(23))  # fmt: skip
    carry = pf.init(_model(), (), gens)
    expected = torch.randn(n, 2, generator=torch.Generator().manual_seed(21), dtype=D)
    np.testing.assert_allclose(carry.particles.numpy(), expected.numpy(), rtol=0, atol=0)


class _CountingLikelihood:
    """A stateful likelihood: its state counts the steps; the density is the model's."""

    def init(self, model, batch_shape, dtype, device):
        return torch.zeros(batch_shape, dtype=dtype, device=device)

    def weigh(self, state, model, y, particles, k, mask, predictive):
        log_p = model.measurement_log_prob(y.unsqueeze(-2), particles, k)
        return state + 1, log_p, {"count": state + 1}


def test_attach_keeps_a_stateful_likelihoods_carried_state():
    """``attach`` initialises a stateful likelihood's state only where the carry holds
    none: a carry with ``aux = 5`` steps to a count of 6, a fresh one to 1."""
    n, model = 8, _model()
    pf = df.ParticleFilter(n, likelihood=_CountingLikelihood())
    gens = Generators.of(torch.Generator().manual_seed(3))
    y = torch.tensor([0.0, 0.1], dtype=D)
    held = pf.attach(_state(n)._replace(aux=torch.tensor(5.0, dtype=D)), model, gens)
    fresh = pf.attach(_state(n), model, gens)
    assert float(pf.step(held, y)[1].extras["count"]) == 6.0
    assert float(pf.step(fresh, y)[1].extras["count"]) == 1.0


def test_host_steps_of_two_dtypes_at_one_n_keep_their_own_dtype():
    """The host step's cached constants (uniform weights, ``arange``) are per dtype: a
    resampling float64 step and then a float32 one at the same ``N`` each return their
    own dtype, and the float32 evidence equals the numpy float64 evaluation (same draws)
    to float32 precision."""
    n = 8
    y = torch.tensor([0.4, -0.3])
    for dtype in (D, torch.float32, D):
        state = _state(n, dtype)
        pf = df.ParticleFilter(n, ess_threshold=1.0)
        carry = pf.attach(state, _model(dtype), Generators.of(torch.Generator().manual_seed(9)))
        with torch.no_grad():
            new, out = pf.step(carry, y.to(dtype))
            new2, out2 = pf.step(new, y.to(dtype))  # the second step reads the uniform weights
        assert bool(out.extras["resampled"])
        for t in (new.log_weights, new.particles, out.log_likelihood, new2.log_weights):
            assert t.dtype == dtype
        g = torch.Generator().manual_seed(9)
        u_offset = torch.rand((1,), generator=g, dtype=dtype).item()
        eps = torch.randn(n, 2, generator=g, dtype=dtype).numpy().astype(np.float64)
        _, lw_np, ev_np = _hand_step(
            state.particles.numpy().astype(np.float64),
            state.log_weights.numpy().astype(np.float64), y.numpy().astype(np.float64),
            u_offset, eps,
        )  # fmt: skip
        tol = 1e-10 if dtype == D else 2e-4
        np.testing.assert_allclose(float(out.log_likelihood), ev_np, rtol=tol, atol=tol)
        np.testing.assert_allclose(new.log_weights.numpy(), lw_np, rtol=tol, atol=tol)


class _TimeVarying(df.LinearGaussianModel):
    """``H_k = (1 + k/2) H`` and ``R_k = (1 + k/5) R``: the step's measurement is at
    ``k + 1`` of the state it propagates from."""

    time_varying = True

    def observation_matrix(self, k):
        return self.H * (1.0 + 0.5 * k)

    def measurement_cov(self, k):
        return self.measurement_noise.cov * (1.0 + 0.2 * k)


def _time_varying():
    t = lambda a: torch.tensor(a, dtype=D)  # noqa: E731
    return _TimeVarying(
        t(F_NP), t(H_NP), t(np.diag(Q_DIAG)), t(np.diag(R_DIAG)),
        torch.zeros(2, dtype=D), torch.eye(2, dtype=D),
    )  # fmt: skip


def _log_normal(r, cov):
    """``log N(r; 0, cov)`` over the last axis, numpy float64."""
    sol = np.linalg.solve(cov, r[..., None])[..., 0]
    return -0.5 * ((r * sol).sum(-1) + np.linalg.slogdet(2 * np.pi * cov)[1])


def _normalised_np(joint):
    top = joint.max(-1, keepdims=True)
    evidence = top[..., 0] + np.log(np.exp(joint - top).sum(-1))
    return joint - evidence[..., None], evidence


@pytest.mark.parametrize("innovations", [False, True])
def test_the_step_weighs_and_predicts_with_the_measurement_models_at_k_plus_one(innovations):
    """From ``k = 0`` the bootstrap step weighs with ``N(y; H₁ x', R₁)`` (``H₁ = 1.5 H``,
    ``R₁ = 1.2 R``) on its own proposed particles ``x'`` (numpy log-sum-exp: independent of
    the draws), and its innovation covariance is ``Σ wᵢ (H₁x'ᵢ − ŷ)(·)ᵀ + R₁``."""
    n, model = 10, _time_varying()
    state = _state(n, batch=(2,))
    y = torch.tensor([[0.5, -0.4], [1.0, 0.2]], dtype=D)
    new, out = particle.particle_step(
        model, state, y, ess_threshold=0.0, innovations=innovations,
        generator=torch.Generator().manual_seed(8),
    )  # fmt: skip
    h1, r1 = 1.5 * H_NP, 1.2 * np.diag(R_DIAG)
    x, lw = new.particles.numpy(), state.log_weights.numpy()
    h = x @ h1.T
    log_w, evidence = _normalised_np(lw + _log_normal(y.numpy()[:, None, :] - h, r1))
    np.testing.assert_allclose(out.log_likelihood.numpy(), evidence, rtol=1e-12)
    np.testing.assert_allclose(new.log_weights.numpy(), log_w, atol=1e-11)
    if innovations:
        w = np.exp(lw)
        y_hat = np.einsum("bn,bnd->bd", w, h)
        dev = h - y_hat[:, None, :]
        s = np.einsum("bn,bni,bnj->bij", w, dev, dev) + r1
        np.testing.assert_allclose(out.innovation_cov.numpy(), s, rtol=1e-12, atol=1e-14)


def test_the_kalman_proposal_is_optimal_with_the_measurement_models_at_k_plus_one():
    """On a linear-Gaussian model the Kalman proposal's incremental weight is exactly
    ``N(y; H₁ F x, H₁ Q H₁ᵀ + R₁)`` whatever it draws: the new log-weights and the evidence
    equal that numpy evaluation on the pre-step particles (a proposal built at ``k`` with
    ``H₀``, ``R₀`` leaves draw-dependent weights)."""
    n, model = 10, _time_varying()
    state = _state(n)
    y = torch.tensor([0.8, -0.6], dtype=D)
    new, out = particle.particle_step(
        model, state, y, ess_threshold=0.0, proposal=particle.KalmanProposal(),
        generator=torch.Generator().manual_seed(12),
    )  # fmt: skip
    h1, r1 = 1.5 * H_NP, 1.2 * np.diag(R_DIAG)
    f = state.particles.numpy() @ F_NP.T
    s = h1 @ np.diag(Q_DIAG) @ h1.T + r1
    joint = state.log_weights.numpy() + _log_normal(y.numpy() - f @ h1.T, s)
    log_w, evidence = _normalised_np(joint)
    np.testing.assert_allclose(float(out.log_likelihood), evidence, rtol=1e-11)
    np.testing.assert_allclose(new.log_weights.numpy(), log_w, atol=1e-10)


@pytest.mark.parametrize("path", ["general", "single", "host"])
def test_an_ess_equal_to_the_threshold_does_not_resample(path):
    """The step resamples when ``ESS < ess_threshold · N`` (strictly): uniform weights of
    ``N = 4`` (``1/4`` exact, ESS exactly 4) at ``ess_threshold = 1`` keep every particle in
    place (the new particles are ``F x + √q ε`` of the given ones, numpy)."""
    n, model = 4, _model()
    x = torch.randn(n, 2, generator=torch.Generator().manual_seed(2), dtype=D)
    state = particle.ParticleState(
        x, torch.full((n,), -math.log(n), dtype=D), 0, ess=torch.tensor(4.0, dtype=D)
    )
    y = torch.tensor([0.1, 0.2], dtype=D)
    gen = torch.Generator().manual_seed(5)
    if path == "general":
        new, out = particle.particle_step(model, state, y, ess_threshold=1.0, generator=gen)
    else:
        pf = df.ParticleFilter(n, ess_threshold=1.0)
        with torch.set_grad_enabled(path == "single"):
            new, out = pf.step(pf.attach(state, model, Generators.of(gen)), y)
    eps = torch.randn(n, 2, generator=torch.Generator().manual_seed(5), dtype=D).numpy()
    assert not bool(out.extras["resampled"])
    np.testing.assert_allclose(
        new.particles.numpy(), x.numpy() @ F_NP.T + eps * np.sqrt(Q_DIAG), rtol=1e-13, atol=1e-13
    )


def test_after_a_full_resampling_the_kalman_proposals_predictive_mean_weighs_by_p_over_q():
    """After resampling every particle (equal weights), the Kalman proposal's predictive
    mean is still ``Σᵢ wᵢ x'ᵢ`` with ``wᵢ ∝ N(x'ᵢ; f, Q) / N(x'ᵢ; μ, Σ)`` (numpy: ``K = Q Hᵀ
    S⁻¹``, ``μ = f + K (y − H f)``, ``Σ = (I − K H) Q``), not the plain average. All particles
    start at one point, so ``f`` is the same whichever ancestors are drawn."""
    n, model = 12, _model()
    x0 = np.array([0.3, -0.2])
    lw = torch.log_softmax(torch.randn(n, generator=torch.Generator().manual_seed(1), dtype=D), -1)
    state = particle.ParticleState(torch.tensor(np.tile(x0, (n, 1))), lw, 0)
    y = torch.tensor([1.2, -0.9], dtype=D)
    new, out = particle.particle_step(
        model, state, y, ess_threshold=1.0, proposal=particle.KalmanProposal(),
        generator=torch.Generator().manual_seed(3),
    )  # fmt: skip
    assert bool(out.extras["resampled"])
    q, r = np.diag(Q_DIAG), np.diag(R_DIAG)
    f = F_NP @ x0
    s = H_NP @ q @ H_NP.T + r
    gain = q @ H_NP.T @ np.linalg.inv(s)
    mu = f + gain @ (y.numpy() - H_NP @ f)
    sigma = (np.eye(2) - gain @ H_NP) @ q
    xp = new.particles.numpy()
    log_ratio = _log_normal(xp - f, q) - _log_normal(xp - mu, sigma)
    w = np.exp(log_ratio - log_ratio.max())
    w /= w.sum()
    np.testing.assert_allclose(out.pred_mean.numpy(), w @ xp, rtol=1e-10, atol=1e-12)
    assert np.abs(w @ xp - xp.mean(0)).max() > 1e-3  # the plain average is another number


def test_the_kalman_proposal_with_per_run_masks_weighs_by_the_received_entries():
    """Runs receiving different entries (``[True, False]`` and ``[True, True]``, so not a
    shared schedule): the Kalman proposal's incremental weight is exactly the marginal
    ``N(y_r; H_r F x, H_r Q H_rᵀ + R_r)`` of each run's received entries ``r`` (numpy), so
    the new log-weights and the evidence are those whatever the draws."""
    n, model = 10, _model()
    state = _state(n, batch=(2,))
    mask = torch.tensor([[True, False], [True, True]])
    y = torch.tensor([[0.6, 50.0], [-0.3, 0.4]], dtype=D)
    new, out = particle.particle_step(
        model, state, y, mask=mask, ess_threshold=0.0, proposal=particle.KalmanProposal(),
        generator=torch.Generator().manual_seed(14),
    )  # fmt: skip
    q, r = np.diag(Q_DIAG), np.diag(R_DIAG)
    for b in range(2):
        keep = mask[b].numpy()
        h = H_NP[keep]
        f = state.particles[b].numpy() @ F_NP.T
        s = h @ q @ h.T + r[np.ix_(keep, keep)]
        joint = state.log_weights[b].numpy() + _log_normal(y[b].numpy()[keep] - f @ h.T, s)
        log_w, evidence = _normalised_np(joint)
        np.testing.assert_allclose(float(out.log_likelihood[b]), evidence, rtol=1e-11)
        np.testing.assert_allclose(new.log_weights[b].numpy(), log_w, atol=1e-10)


@pytest.mark.parametrize("path", ["single", "host"])
def test_one_run_steps_follow_a_time_varying_measurement_model(path):
    """One run through ``ParticleFilter.step`` (the one-run paths where they apply) on the
    model of ``R_k = (1 + k/5) R``, ``H_k = (1 + k/2) H``: the evidence and new log-weights are
    the numpy ``N(y; H₁ x', R₁)`` weighting of the returned particles."""
    n, model = 10, _time_varying()
    state = _state(n)
    y = torch.tensor([0.5, -0.4], dtype=D)
    pf = df.ParticleFilter(n, ess_threshold=0.0)
    with torch.set_grad_enabled(path == "single"):
        new, out = pf.step(
            pf.attach(state, model, Generators.of(torch.Generator().manual_seed(4))), y
        )
    h1, r1 = 1.5 * H_NP, 1.2 * np.diag(R_DIAG)
    joint = state.log_weights.numpy() + _log_normal(y.numpy() - new.particles.numpy() @ h1.T, r1)
    log_w, evidence = _normalised_np(joint)
    np.testing.assert_allclose(float(out.log_likelihood), evidence, rtol=1e-12)
    np.testing.assert_allclose(new.log_weights.detach().numpy(), log_w, atol=1e-11)


@pytest.mark.parametrize("grad", [True, False])
@pytest.mark.parametrize("option", ["cov_dims", "record_prior"])
def test_one_run_cov_dims_and_record_prior_are_honoured(grad, option):
    """On one run, ``cov_dims = 1`` gives the ``[1, 1]`` weighted variance
    ``Σᵢ wᵢ (x'ᵢ₀ − x̂₀)²`` of the new particles under the new weights (numpy), and
    ``record_prior`` reports the predictive log-weights (here the given ones: bootstrap, no
    resampling)."""
    n, model = 10, _model()
    state = _state(n)
    kwargs = {"cov_dims": 1} if option == "cov_dims" else {"record_prior": True}
    pf = df.ParticleFilter(n, ess_threshold=0.0, **kwargs)
    with torch.set_grad_enabled(grad):
        new, out = pf.step(
            pf.attach(state, model, Generators.of(torch.Generator().manual_seed(4))),
            torch.tensor([0.5, -0.4], dtype=D),
        )
    if option == "cov_dims":
        w = np.exp(new.log_weights.detach().numpy())
        x0 = new.particles.detach().numpy()[:, 0]
        var = np.sum(w * (x0 - w @ x0) ** 2)
        assert tuple(out.cov.shape) == (1, 1)
        np.testing.assert_allclose(out.cov.detach().numpy(), [[var]], rtol=1e-12)
    else:
        prior = out.extras["prior_log_weights"].detach().numpy()
        np.testing.assert_allclose(prior, state.log_weights.numpy(), rtol=1e-15)


def test_a_model_density_of_its_own_reads_the_mask():
    """On the time-varying model (its ``measurement_log_prob`` reads ``R_k``: the
    likelihood is the model's own), a run receiving entry 0 alone weighs by
    ``N(y₀; (H₁ x')₀, (R₁)₀₀)`` (numpy); the unreceived entry (50 units off) plays no part."""
    n, model = 10, _time_varying()
    state = _state(n, batch=(2,))
    mask = torch.tensor([[True, False], [True, True]])
    y = torch.tensor([[0.6, 50.0], [-0.3, 0.4]], dtype=D)
    new, out = particle.particle_step(
        model, state, y, mask=mask, ess_threshold=0.0, generator=torch.Generator().manual_seed(6)
    )
    h1, r1 = 1.5 * H_NP, 1.2 * np.diag(R_DIAG)
    for b in range(2):
        keep = mask[b].numpy()
        h = new.particles[b].numpy() @ h1[keep].T
        joint = state.log_weights[b].numpy() + _log_normal(
            y[b].numpy()[keep] - h, r1[np.ix_(keep, keep)]
        )
        log_w, evidence = _normalised_np(joint)
        np.testing.assert_allclose(float(out.log_likelihood[b]), evidence, rtol=1e-12)
        np.testing.assert_allclose(new.log_weights[b].numpy(), log_w, atol=1e-11)


class _HalfImpossible:
    """The bootstrap draw with a correction ``−inf`` at particle 0 and ``0.3 i`` at the
    others: a proposal whose density ratio vanishes for some particles only."""

    def __call__(self, model, particles, u, y, k, mask, generator):
        new = model.sample_transition(particles, None, k, generator)
        c = 0.3 * torch.arange(particles.shape[-2], dtype=particles.dtype)
        c[0] = -math.inf
        return new, c.expand(particles.shape[:-1]).clone()


def test_a_correction_minus_inf_at_some_particles_only_is_normalised_with_the_rest():
    """``prior_log_weights = log_softmax(log w + c)`` (numpy) where only some ``cᵢ`` are
    ``−inf``: particle 0 gets ``−inf``, the others the renormalised rest (the reset to
    ``log w`` is for runs whose every ``cᵢ`` is ``−inf``); the step is not degenerate."""
    n, model = 6, _model()
    state = _state(n, batch=(2,))
    _, out = particle.particle_step(
        model, state, torch.zeros(2, 2, dtype=D), ess_threshold=0.0, proposal=_HalfImpossible(),
        generator=torch.Generator().manual_seed(2),
    )  # fmt: skip
    c = 0.3 * np.arange(n)
    c[0] = -np.inf
    joint = state.log_weights.numpy() + c
    expected = joint - np.log(np.exp(joint[:, 1:]).sum(-1, keepdims=True))
    np.testing.assert_allclose(out.extras["prior_log_weights"].numpy(), expected, rtol=1e-12)
    assert not bool(out.extras["degenerate"].any())


def test_the_gradient_of_the_posterior_mean_in_y_is_the_weighted_score_covariance():
    """Bootstrap, no resampling, two runs: ``x̂ = Σᵢ wᵢ x'ᵢ`` with ``wᵢ ∝ w̄ᵢ N(y; H x'ᵢ, R)``
    has ``∂x̂/∂y = Σᵢ wᵢ (x'ᵢ − x̂) sᵢᵀ`` with ``sᵢ = ∂ log N(y; H x'ᵢ, R)/∂y = R⁻¹ (H x'ᵢ − y)`` (closed form, numpy on
    the step's own particles), through the normalisation's autograd graph."""
    n, model = 10, _model()
    state = _state(n, batch=(2,))
    y = torch.tensor([[0.5, -0.4], [1.0, 0.2]], dtype=D, requires_grad=True)
    new, out = particle.particle_step(
        model, state, y, ess_threshold=0.0, generator=torch.Generator().manual_seed(8)
    )
    grads = [torch.autograd.grad(out.mean[b, j], y, retain_graph=True)[0][b] for b in range(2)
             for j in range(2)]  # fmt: skip
    x, w = new.particles.detach().numpy(), np.exp(new.log_weights.detach().numpy())
    for b in range(2):
        s = (x[b] @ H_NP.T - y[b].detach().numpy()) / R_DIAG  # ∂ log N(y; Hx, R)/∂y
        mean = w[b] @ x[b]
        jac = np.einsum("n,ni,nj->ij", w[b], x[b] - mean, s)
        got = torch.stack(grads[2 * b : 2 * b + 2]).numpy()
        np.testing.assert_allclose(got, jac, rtol=1e-10, atol=1e-12)


def test_a_float64_host_resampling_after_a_float32_one_searches_float64_targets():
    """The systematic targets ``(j + U)/N`` of a float64 host step are float64 even after a
    float32 host step at the same ``N`` (the cached ``arange`` is per dtype): a cumulative
    weight placed between ``U/N`` and ``float32(U)/N`` separates the two, and the
    ancestors must be the float64 search's (numpy), seen in the new particles."""
    n = 4
    pf = df.ParticleFilter(n, ess_threshold=1.0)
    y = torch.tensor([0.1, 0.2])
    with torch.no_grad():  # a float32 resampling host step at this N first
        s32 = _state(n, torch.float32)
        pf.step(pf.attach(s32, _model(torch.float32), Generators.of(torch.Generator())), y)
    u = torch.rand((1,), generator=torch.Generator().manual_seed(31), dtype=D).item()
    u32 = float(np.float32(u))
    assert u32 != u
    w0 = (u + u32) / 2 / n  # the first cumulative weight, between the two targets
    w = np.array([w0] + [(1 - w0) / (n - 1)] * (n - 1))
    x = torch.randn(n, 2, generator=torch.Generator().manual_seed(1), dtype=D)
    state = particle.ParticleState(x, torch.log(torch.tensor(w)), 0)
    with torch.no_grad():
        new, _ = pf.step(
            pf.attach(state, _model(), Generators.of(torch.Generator().manual_seed(31))),
            y.to(D),
        )
    a = np.searchsorted(np.cumsum(w), (np.arange(n) + u) / n, side="right")
    g = torch.Generator().manual_seed(31)
    torch.rand((1,), generator=g, dtype=D)
    eps = torch.randn(n, 2, generator=g, dtype=D).numpy()
    expected = x.numpy()[a] @ F_NP.T + eps * np.sqrt(Q_DIAG)
    np.testing.assert_allclose(new.particles.numpy(), expected, rtol=1e-13, atol=1e-13)


def test_weighted_moments_normalise_unnormalised_log_weights():
    """``weighted_moments`` takes ``w = softmax(log_weights)``: log-weights shifted by 3
    (unnormalised) give the numpy mean ``Σ wᵢ xᵢ`` and covariance ``Σ wᵢ (xᵢ − x̂)(xᵢ − x̂)ᵀ``."""
    g = torch.Generator().manual_seed(17)
    x = torch.randn(2, 7, 3, generator=g, dtype=D)
    lw = torch.randn(2, 7, generator=g, dtype=D) + 3.0
    mean, cov = particle.weighted_moments(x, lw)
    w = np.exp(lw.numpy())
    w /= w.sum(-1, keepdims=True)
    m = np.einsum("bn,bnd->bd", w, x.numpy())
    dev = x.numpy() - m[:, None, :]
    np.testing.assert_allclose(mean.numpy(), m, rtol=1e-12)
    np.testing.assert_allclose(cov.numpy(), np.einsum("bn,bni,bnj->bij", w, dev, dev), rtol=1e-12)


class _TimeVaryingH(df.LinearGaussianModel):
    """``H_k = (1 + k/2) H`` with a constant ``R``: the model's default density applies."""

    time_varying = True

    def observation_matrix(self, k):
        return self.H * (1.0 + 0.5 * k)


@pytest.mark.parametrize("innovations", [False, True])
def test_the_default_density_observes_at_k_plus_one_without_innovations(innovations):
    """A batched bootstrap step from ``k = 0`` on ``H_k = (1 + k/2) H``, constant ``R``
    (the default-density branch, which observes itself when no innovations were asked):
    evidence and log-weights are the numpy ``N(y; H₁ x', R)`` weighting of the returned
    particles."""
    t = lambda a: torch.tensor(a, dtype=D)  # noqa: E731
    model = _TimeVaryingH(t(F_NP), t(H_NP), t(np.diag(Q_DIAG)), t(np.diag(R_DIAG)),
                          torch.zeros(2, dtype=D), torch.eye(2, dtype=D))  # fmt: skip
    state = _state(10, batch=(2,))
    y = torch.tensor([[0.5, -0.4], [1.0, 0.2]], dtype=D)
    new, out = particle.particle_step(
        model, state, y, ess_threshold=0.0, innovations=innovations,
        generator=torch.Generator().manual_seed(8),
    )  # fmt: skip
    h = new.particles.numpy() @ (1.5 * H_NP).T
    joint = state.log_weights.numpy() + _log_normal(y.numpy()[:, None, :] - h, np.diag(R_DIAG))
    log_w, evidence = _normalised_np(joint)
    np.testing.assert_allclose(out.log_likelihood.numpy(), evidence, rtol=1e-12)
    np.testing.assert_allclose(new.log_weights.numpy(), log_w, atol=1e-11)


def test_the_host_step_compares_the_ess_with_the_threshold_in_the_weights_dtype():
    """float32, ``N = 10``, ``ess_threshold = 0.33``: a carried ESS of exactly
    ``float32(3.3) < 3.3`` is not below the threshold as the torch step compares it (in
    float32: ``float32(3.3) < float32(3.3)`` is false), so neither step resamples."""
    n, model = 10, _model(torch.float32)
    z = torch.randn(n, generator=torch.Generator().manual_seed(3), dtype=D)
    lo, hi = 0.0, 20.0  # bisect the temperature for an ESS of 3.3 (numpy/float64)
    for _ in range(80):
        c = (lo + hi) / 2
        w = np.exp(c * z.numpy() - np.logaddexp.reduce(c * z.numpy()))
        lo, hi = (c, hi) if 1.0 / np.sum(w * w) > 3.3 else (lo, c)
    lw = torch.log_softmax(c * z, -1).float()
    state = particle.ParticleState(
        torch.randn(n, 2, generator=torch.Generator().manual_seed(4)), lw, 0,
        ess=torch.tensor(3.3, dtype=torch.float32),
    )  # fmt: skip
    pf = df.ParticleFilter(n, ess_threshold=0.33)
    for grad in (True, False):
        carry = pf.attach(state, model, Generators.of(torch.Generator().manual_seed(5)))
        with torch.set_grad_enabled(grad):
            _, out = pf.step(carry, torch.tensor([0.1, 0.2]))
        assert not bool(out.extras["resampled"])
