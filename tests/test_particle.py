"""Particle filter: Monte Carlo limits against the exact Kalman filter."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import constant_velocity

import difffilter as df
from difffilter import resampling
from difffilter.particle import KalmanProposal, particle_filter, particle_init, particle_step

RUNS = 200  # independent PF replicates on the same data


@pytest.fixture(scope="module")
def data():
    model = constant_velocity()
    _, ys, _ = model.simulate(25, (), generator=torch.Generator().manual_seed(7))
    return model, ys, df.kalman_filter(model, ys)


def test_pf_log_likelihood_within_three_standard_errors_of_kf(data):
    model, ys, kf = data
    res = particle_filter(
        model,
        ys.expand(RUNS, -1, -1),
        num_particles=2000,
        generator=torch.Generator().manual_seed(0),
    )
    # the PF estimates p(y) without bias; log p̂ has a small negative bias (Jensen), so
    # compare the log of the mean likelihood estimate
    log_mean = torch.logsumexp(res.log_likelihood, 0) - math.log(RUNS)
    # delta-method standard error of log(mean p̂)
    w = torch.exp(res.log_likelihood - res.log_likelihood.max())
    se = (w.std() / w.mean() / math.sqrt(RUNS)).item()
    assert abs(log_mean.item() - kf.log_likelihood.item()) < 3 * se + 1e-3
    # and the per-replicate log estimates scatter around the truth too
    assert (
        abs(res.log_likelihood.mean().item() - kf.log_likelihood.item())
        < 3 * res.log_likelihood.std().item()
    )


def test_pf_log_likelihood_error_shrinks_with_particles(data):
    model, ys, kf = data
    errors = []
    for n in (100, 1000, 10000):
        res = particle_filter(
            model,
            ys.expand(64, -1, -1),
            num_particles=n,
            generator=torch.Generator().manual_seed(n),
        )
        errors.append((res.log_likelihood - kf.log_likelihood).square().mean().sqrt().item())
    assert errors[0] > errors[1] > errors[2]
    # root-mean-square error decays roughly like N^{-1/2}: at least a factor 2 per decade
    assert errors[0] / errors[2] > 4


def test_pf_means_agree_with_kf_within_monte_carlo_error(data):
    model, ys, kf = data
    res = particle_filter(
        model,
        ys.expand(RUNS, -1, -1),
        num_particles=1000,
        generator=torch.Generator().manual_seed(3),
    )
    mean_of_means = res.means.mean(0)
    se = res.means.std(0) / math.sqrt(RUNS)
    # PF means are consistent with O(1/N) bias; allow 4 standard errors plus a small bias term
    bias_allowance = 0.02 * kf.covs.diagonal(dim1=-2, dim2=-1).sqrt()
    assert torch.all((mean_of_means - kf.means).abs() < 4 * se + bias_allowance)
    # the posterior covariances match too, up to the O(1/ESS) downward bias of a weighted
    # sample covariance (≈7 % at the step with the lowest ESS ≈ 70, N = 1000)
    sd = kf.covs.diagonal(dim1=-2, dim2=-1).sqrt()
    scaled_error = (res.covs.mean(0) - kf.covs) / (sd.unsqueeze(-1) * sd.unsqueeze(-2))
    assert scaled_error.abs().max() < 0.1


def test_kalman_proposal_is_exact_optimal_proposal_on_linear_model(data):
    model, ys, kf = data
    boot = particle_filter(
        model, ys.expand(64, -1, -1), num_particles=300, generator=torch.Generator().manual_seed(1)
    )
    opt = particle_filter(
        model,
        ys.expand(64, -1, -1),
        num_particles=300,
        proposal=KalmanProposal(),
        generator=torch.Generator().manual_seed(1),
    )
    # same target: both estimates centre on the KF; the optimal proposal has no larger spread
    for res in (boot, opt):
        assert (
            abs(res.log_likelihood.mean().item() - kf.log_likelihood.item())
            < 3 * res.log_likelihood.std().item() + 0.5
        )
    assert opt.log_likelihood.std() < 1.2 * boot.log_likelihood.std()


def test_defensive_kalman_proposal_correction_is_the_mixture_density(data):
    model, ys, _ = data
    x_prev = torch.tensor([[0.5, -1.0, 2.0, 0.3], [3.0, 0.2, -1.0, 0.0]], dtype=ys.dtype)
    x_prev = x_prev[:, : model.dim_x]
    rho, y = 0.3, ys[3]
    new, corr = KalmanProposal(defensive=rho)(
        model, x_prev, None, y, 2, None, torch.Generator().manual_seed(0)
    )
    # the same moments from the Kalman filter: prior N(F x, Q), then the update with y
    for i in range(len(x_prev)):
        prior = df.GaussianState(x_prev[i], torch.zeros(model.dim_x, model.dim_x, dtype=y.dtype), 2)
        post, out = df.kalman_step(model, prior, y)
        p = torch.distributions.MultivariateNormal(out.pred_mean, out.pred_cov).log_prob(new[i])
        k = torch.distributions.MultivariateNormal(post.mean, post.cov).log_prob(new[i])
        q = torch.logaddexp(k + math.log(1 - rho), p + math.log(rho))
        assert torch.allclose(corr[i], p - q, rtol=1e-9, atol=1e-9)
    with pytest.raises(ValueError, match="defensive"):
        KalmanProposal(defensive=1.0)


#: One of each resampler of the library (also run on CUDA by tests/test_cuda.py).
EVERY_RESAMPLER = [
    resampling.Multinomial(),
    resampling.Systematic(),
    resampling.Stratified(),
    resampling.Residual(),
    resampling.Soft(0.5),
    resampling.StopGradient(),
    resampling.OptimalTransport(),
]


@pytest.mark.parametrize(
    "resampler",
    EVERY_RESAMPLER,
    ids=lambda r: type(r).__name__,
)
def test_every_resampler_gives_a_consistent_filter(data, resampler):
    model, ys, kf = data
    # optimal transport costs O(N²) per Sinkhorn iteration: a smaller cloud keeps CI fast
    runs, n = (8, 200) if isinstance(resampler, resampling.OptimalTransport) else (32, 500)
    res = particle_filter(
        model,
        ys.expand(runs, -1, -1),
        num_particles=n,
        resampler=resampler,
        generator=torch.Generator().manual_seed(5),
    )
    assert torch.isfinite(res.log_likelihood).all()
    rmse_to_kf = (res.means - kf.means).square().mean().sqrt()
    assert rmse_to_kf < 0.35 * kf.covs.diagonal(dim1=-2, dim2=-1).sqrt().mean()


def test_pf_is_reproducible_from_its_generator(data):
    model, ys, _ = data
    a = particle_filter(model, ys, num_particles=64, generator=torch.Generator().manual_seed(11))
    b = particle_filter(model, ys, num_particles=64, generator=torch.Generator().manual_seed(11))
    c = particle_filter(model, ys, num_particles=64, generator=torch.Generator().manual_seed(12))
    assert torch.equal(a.means, b.means) and not torch.equal(a.means, c.means)


def test_pf_step_api_and_particle_storage(data):
    model, ys, _ = data
    whole = particle_filter(
        model,
        ys[:5],
        num_particles=50,
        generator=torch.Generator().manual_seed(2),
        return_particles=True,
    )
    assert whole.particles.shape == (5, 50, 4) and whole.log_weights.shape == (5, 50)
    torch.testing.assert_close(
        torch.logsumexp(whole.log_weights, -1), torch.zeros(5, dtype=torch.float64)
    )
    g = torch.Generator().manual_seed(2)
    state = particle_init(model, 50, (), g)
    for t in range(5):
        state, out = particle_step(model, state, ys[t], generator=g)
        torch.testing.assert_close(out.mean, whole.means[t])
    torch.testing.assert_close(state.particles, whole.particles[-1])


def test_fully_masked_step_is_pure_prediction(data):
    model, ys, _ = data
    mask = torch.ones(25, 2, dtype=torch.bool)
    mask[4] = False
    res = particle_filter(
        model,
        ys,
        num_particles=200,
        mask=mask,
        ess_threshold=0.0,
        generator=torch.Generator().manual_seed(4),
        return_particles=True,
    )
    # no weight change, zero evidence increment, and the particles just moved by the dynamics
    torch.testing.assert_close(res.log_weights[4], res.log_weights[3])
    assert res.log_likelihood_increments[4] == 0
    torch.testing.assert_close(res.pred_means[4], res.means[4])


def test_sis_without_resampling_degenerates_but_stays_finite(data):
    model, ys, _ = data
    res = particle_filter(
        model, ys, num_particles=100, ess_threshold=0.0, generator=torch.Generator().manual_seed(0)
    )
    assert not res.resampled.any()
    assert res.ess[-1] < res.ess[0]
    assert torch.isfinite(res.means).all()


class _CallOnly:
    """A user resampler with only ``__call__`` (no ``resample_normalized`` fast path)."""

    def __init__(self):
        self.inner = resampling.Systematic()

    def __call__(self, particles, log_weights, generator=None):
        return self.inner(particles, log_weights, generator)


def test_call_only_resampler_equals_the_fast_path_under_partial_resampling(data):
    model, ys, _ = data
    ys = ys.expand(8, *ys.shape)  # 8 runs whose ESS crosses the threshold at different steps
    kwargs = dict(num_particles=64, ess_threshold=0.3)
    fast = particle_filter(
        model,
        ys,
        resampler=resampling.Systematic(),
        generator=torch.Generator().manual_seed(3),
        **kwargs,
    )
    slow = particle_filter(
        model, ys, resampler=_CallOnly(), generator=torch.Generator().manual_seed(3), **kwargs
    )
    # the case under test really happens: at some step some rows resample, not all
    per_step = fast.resampled.float().mean(0)
    assert bool(((per_step > 0) & (per_step < 1)).any())
    torch.testing.assert_close(slow.means, fast.means)
    torch.testing.assert_close(slow.log_likelihood, fast.log_likelihood)


def _same_draws(model, ys, option: str, values):
    """One 4-run filter per value of ``option``, all on the same random numbers."""
    return [
        particle_filter(model, ys.expand(4, -1, -1), num_particles=100,
                        generator=torch.Generator().manual_seed(5), **{option: v})
        for v in values
    ]  # fmt: skip


def test_skipping_innovations_changes_no_estimate(data):
    model, ys, _ = data
    runs = _same_draws(model, ys, "innovations", (True, False))
    assert runs[1].innovations is None and runs[1].innovation_covs is None
    assert runs[0].innovations.shape == (4, ys.shape[-2], ys.shape[-1])
    for name in ("means", "covs", "pred_means", "log_likelihood", "ess"):
        assert torch.equal(getattr(runs[0], name), getattr(runs[1], name))


def test_cov_dims_is_the_leading_block_of_the_full_covariance(data):
    model, ys, _ = data
    runs = _same_draws(model, ys, "cov_dims", (None, 2))
    assert runs[1].covs.shape == (4, ys.shape[-2], 2, 2)
    torch.testing.assert_close(runs[1].covs, runs[0].covs[..., :2, :2], atol=1e-12, rtol=0)
    assert torch.equal(runs[0].means, runs[1].means)
    with pytest.raises(ValueError, match="cov_dims"):
        particle_filter(model, ys, num_particles=10, cov_dims=model.dim_x + 1)
    state = particle_init(model, 10, (), torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="cov_dims"):
        particle_step(model, state, ys[0], cov_dims=0)


def test_one_row_resampling_is_that_of_the_batched_rows():
    """The one-run paths of systematic resampling (offspring counts by ``bincount``, a
    plain row gather) give the batched rows' ancestors and particles exactly, zero
    weights included."""
    from difffilter.resampling import _gather_particles, systematic_ancestors

    gen = torch.Generator().manual_seed(3)
    w = torch.rand(6, 50, generator=gen, dtype=torch.float64)
    w[:, ::7] = 0.0
    w[:, -3:] = 0.0  # past the last particle of positive weight: clamped to it
    cdf, offset = w.cumsum(-1), torch.rand(6, 1, generator=gen, dtype=torch.float64)
    x = torch.randn(6, 50, 3, generator=gen, dtype=torch.float64)
    rows = systematic_ancestors(cdf, offset)
    batched = _gather_particles(x, rows)
    for i in range(6):
        one = systematic_ancestors(cdf[i], offset[i])
        assert torch.equal(one, rows[i])
        assert torch.equal(_gather_particles(x[i], one), batched[i])
        assert bool((w[i][one] > 0).all())
    counts = systematic_ancestors(cdf, offset, torch.full((6, 1), 20.0, dtype=torch.float64))
    for i in range(6):
        one = systematic_ancestors(cdf[i], offset[i], torch.full((1,), 20.0, dtype=torch.float64))
        assert torch.equal(one, counts[i])


@pytest.mark.parametrize("nonlinear", [False, True], ids=["linear", "jacobian"])
def test_kalman_proposal_on_entries_every_run_receives_equals_the_masked_update(nonlinear):
    """When every run receives the same entries (a Round-Robin schedule) the proposal's
    update runs on those entries alone; it equals the masked update that a batch with
    different masks takes (the run whose mask differs only forces that path), and with
    nothing received the proposal is the prior ``N(f, Q)``."""
    from difffilter.models import registry
    from difffilter.particle import kalman_proposal_moments

    if nonlinear:
        sc = registry.get("tracking_rrp_deception")
        model, k = sc.system(), 3
        tr = sc.simulate(3, {n: torch.Generator().manual_seed(i)
                             for i, n in enumerate(("plant", "attack", "schedule"))})  # fmt: skip
        y = tr.y_recv[:, k]
        x = tr.x[:, k - 1].unsqueeze(-2) + 0.1 * torch.randn(
            3, 7, 4, generator=torch.Generator().manual_seed(5), dtype=torch.float64
        )
    else:
        model, k = constant_velocity(), 0
        _, ys, _ = model.simulate(1, (3,), generator=torch.Generator().manual_seed(4))
        y = ys[:, 0]
        x = model.sample_initial((3, 7), torch.Generator().manual_seed(5))
    dy = y.shape[-1]
    shared = torch.zeros(dy, dtype=torch.bool)
    shared[:2] = True
    mixed = shared.expand(3, dy).clone()
    mixed[2] = ~shared  # a third run receives the other entries
    general = kalman_proposal_moments(model, x, None, y, k, mixed)
    fast = kalman_proposal_moments(model, x[:2], None, y[:2], k, mixed[:2])
    for a, b in zip(fast, general):  # Σ may come shared ([dx, dx]) or per run: broadcast
        b = b[:2] if b.dim() > 2 else b
        a, b = torch.broadcast_tensors(a, b)
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    nothing = kalman_proposal_moments(model, x, None, y, k, torch.zeros(3, dy, dtype=torch.bool))
    f, Q, mu, sigma = nothing
    assert torch.equal(mu, f) and torch.equal(sigma, Q.expand_as(sigma))
