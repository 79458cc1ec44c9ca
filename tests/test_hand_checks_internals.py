"""Independent truths for the library's fast paths and internals that no test reached.

Each check pins a branch the wider tests never take (a fused path on a model unlike the
four-tank one, a tie in the resampling rule, a float32 rounding edge, the calibration
seed of a study), against the general path, a numpy reference of the docstring's equations
or a hand computation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter import _pf_host_step, _pf_single_run, fdi, particle
from difffilter.estimator import Generators
from difffilter.fdi import _components
from difffilter.noise import Gaussian
from difffilter.resampling import OptimalTransport

F64 = torch.float64


# ---------------------------------------------------------------- fused modified PF


def _linear_model(G, R, *, loc=None):
    dx = G.shape[1]
    F = 0.9 * torch.eye(dx, dtype=F64) + 0.05 * torch.ones(dx, dx, dtype=F64)
    Q = torch.diag(torch.linspace(0.05, 0.12, dx, dtype=F64))
    model = df.LinearGaussianModel(F, G, Q, R, torch.zeros(dx, dtype=F64), torch.eye(dx, dtype=F64))
    if loc is not None:
        model.process_noise = Gaussian(loc, Q)
    return model


_SQUARE_G = [[1.0, 0.4, 0.0], [0.0, 1.0, -0.3], [0.2, 0.0, 0.8]]
_FUSED_CASES = {
    # a square G ≠ I (the residual through Gᵀ; a non-diagonal I − GK)
    "square G": (torch.tensor(_SQUARE_G, dtype=F64), torch.diag(torch.tensor([0.1, 0.2, 0.15], dtype=F64)), None),
    # a rectangular G of the first states, [I 0]: equal to an eye of its shape, not the identity
    "G = [I 0]": (torch.eye(2, 3, dtype=F64), 0.2 * torch.eye(2, dtype=F64), None),
    "rectangular G": (torch.tensor([[1.0, 0.5, 0.0, 0.0], [0.0, 0.0, 1.0, 0.3]], dtype=F64),
                      torch.diag(torch.tensor([0.1, 0.2], dtype=F64)), None),
    # a full R (whitened through its Cholesky factor)
    "full R": (torch.eye(2, dtype=F64), torch.tensor([[0.2, 0.08], [0.08, 0.1]], dtype=F64), None),
    # a process noise of nonzero mean
    "noise mean": (torch.eye(2, dtype=F64), torch.diag(torch.tensor([0.1, 0.2], dtype=F64)),
                   torch.tensor([0.05, -0.1], dtype=F64)),
}  # fmt: skip


@pytest.mark.parametrize("case", list(_FUSED_CASES))
def test_fused_modified_pf_equals_the_composed_filter_beyond_the_four_tank_model(case):
    """The fused module's promise (the composed filter's numbers, same generators) on the
    branches the four-tank model (G = I, diagonal R, zero-mean noise) never takes."""
    G, R, loc = _FUSED_CASES[case]
    model = _linear_model(G, R, loc=loc)
    g = torch.Generator().manual_seed(1)
    ys = 0.5 * torch.randn(4, 12, model.dim_y, dtype=F64, generator=g)
    gamma = 0.4 * torch.randn(4, 12, model.dim_y, dtype=F64, generator=g)
    composed, fused = (
        fdi.modified_particle_filter(
            model, ys, num_particles=40, detector=fdi.PoADetector(0.6, 0.4), gamma_hat=gamma,
            generator=torch.Generator().manual_seed(5),
            resample_generator=torch.Generator().manual_seed(6), fused=use_fused,
        )
        for use_fused in (False, True)
    )  # fmt: skip
    assert fused.covs is None  # the fused path ran
    assert 0.0 < float(composed.alarms.double().mean()) < 1.0  # both branches of the gate
    torch.testing.assert_close(fused.scores, composed.scores, rtol=0, atol=1e-12)
    assert torch.equal(fused.alarms, composed.alarms)
    torch.testing.assert_close(fused.means, composed.means, rtol=0, atol=1e-10)


# ---------------------------------------------------------------- one-run PF step


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_one_run_pf_step_resamples_only_below_the_threshold_at_a_tie(dtype):
    """``ESS < ess_threshold · N``, strict: equal weights of N = 4 particles have ESS exactly
    4, so with ``ess_threshold = 1`` the first step must not resample (as the general step)."""
    from difffilter.models.four_tank import FourTankModel

    model = FourTankModel(dtype=dtype)
    with torch.no_grad():
        _, ys, _ = model.simulate(3, (1,), generator=torch.Generator().manual_seed(0))
    pf = df.ParticleFilter(4, ess_threshold=1.0)
    flags = {}
    for general in (False, True):
        carry = pf.init(model, (), Generators.of(torch.Generator().manual_seed(7)))
        assert float(particle._ess(carry.log_weights)) == 4.0
        flags[general] = []
        for y in ys[0]:
            step = particle._particle_step if general else pf.step
            carry, out = step(pf, carry, y, None, None) if general else step(carry, y, None)
            flags[general].append(bool(out.extras["resampled"]))
    assert flags[False][0] is False
    assert flags[False] == flags[True]


# ---------------------------------------------------------------- host-array PF step


@pytest.mark.parametrize("seed", [10642, 17610])
def test_host_systematic_ancestors_stay_on_positive_weights_when_float32_rounds_up(seed):
    """In float32 the last target ``(N − 1 + U) W / N`` rounds up to the total ``W`` for U
    within an ulp of 1: the ancestor is then the last particle of positive weight (the
    docstring's clamp), not N (out of range) or a zero-weight particle."""
    n = 1000
    w = np.full(n, 1.0, dtype=np.float32)
    w[-3:] = 0.0
    w /= w.sum()
    u = torch.rand((1,), generator=torch.Generator().manual_seed(seed), dtype=torch.float32)
    total = np.cumsum(w)[-1]
    last_target = (np.float32(n - 1) + np.float32(u.item())) * (total / np.float32(n))
    assert last_target >= total  # the seed reaches the rounding edge this test is about
    host = _pf_host_step._systematic_ancestors(w, torch.Generator().manual_seed(seed))
    torch_step = _pf_single_run._systematic_ancestors(
        torch.from_numpy(w.copy()), torch.Generator().manual_seed(seed)
    )
    assert int(host.max()) == n - 4
    assert (w[host] > 0).all()
    assert int(torch_step.max()) == n - 4


# ---------------------------------------------------------------- optimal transport


def _sinkhorn_reference(x, log_w, eps):
    """The docstring's transport in numpy: x̃ = (x − Σ w x)/σ (σ the unweighted population
    standard deviation), C_ij = ‖x̃_i − x̃_j‖², log-domain Sinkhorn to convergence with
    a = w, b = 1/N, and y_j = N Σ_i P_ij x_i."""

    def lse(a, axis):
        m = a.max(axis=axis, keepdims=True)
        return (m + np.log(np.exp(a - m).sum(axis=axis, keepdims=True))).squeeze(axis)

    out = np.empty_like(x)
    n = x.shape[1]
    for r in range(x.shape[0]):
        w = np.exp(log_w[r] - lse(log_w[r], 0))
        sd = x[r].std(0)
        xs = (x[r] - (w[:, None] * x[r]).sum(0)) / np.where(sd > 0, sd, 1.0)
        C = ((xs[:, None, :] - xs[None, :, :]) ** 2).sum(-1)
        la, lb = np.log(w), -math.log(n)
        f, g = np.zeros(n), np.zeros(n)
        for _ in range(5000):
            f = -eps * lse(lb + (g[None, :] - C) / eps, 1)
            g = -eps * lse(la[:, None] + (f[:, None] - C) / eps, 0)
        P = np.exp((f[:, None] + g[None, :] - C) / eps + la[:, None] + lb)
        assert np.abs(P.sum(1) - w).max() < 1e-12
        out[r] = n * P.T @ x[r]
    return out


@pytest.mark.parametrize("method", ["kernel", "log"])
def test_optimal_transport_equals_a_numpy_sinkhorn_of_its_docstring(method):
    """Scales differ per coordinate (1 and 3), so the standardisation's σ matters: the
    population standard deviation, unweighted, as the docstring says."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2, 6, 2)) * np.array([1.0, 3.0])
    log_w = rng.normal(size=(2, 6))
    expected = _sinkhorn_reference(x, log_w, 0.5)
    ot = OptimalTransport(epsilon=0.5, tolerance=1e-12, max_iterations=5000, method=method)
    got = ot(torch.tensor(x, dtype=F64), torch.tensor(log_w, dtype=F64)).particles
    np.testing.assert_allclose(got.numpy(), expected, rtol=0, atol=1e-9)


# ---------------------------------------------------------------- Gaussian components


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_component_cholesky_clamps_a_semidefinite_pivot_at_the_smallest_normal(dtype):
    """A = v vᵀ + diag(0, 0, 9), v = (2, 1, 0): the exact factor has L₁₁ = 0; the docstring
    clamps the pivot at ``finfo.tiny`` before the square root, so L₁₁ = √tiny and draws
    ``L ε`` keep variance 0 along the null direction x₁ − x₀/2."""
    A = torch.tensor([[4.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 9.0]], dtype=dtype)
    low = _components.cholesky(_components.to_components(A.expand(5, 3, 3)))
    L = torch.stack(
        [torch.stack([torch.as_tensor(v, dtype=dtype).expand(5) for v in row], -1) for row in low],
        -2,
    )
    root_tiny = torch.finfo(dtype).tiny ** 0.5
    assert float(L[0, 1, 1]) == pytest.approx(root_tiny, rel=1e-6)
    torch.testing.assert_close(L[0, :, 0], torch.tensor([2.0, 1.0, 0.0], dtype=dtype))
    assert float(L[0, 2, 2]) == pytest.approx(3.0)
    eps = torch.randn(5, 3, dtype=dtype, generator=torch.Generator().manual_seed(0))
    x = (L @ eps.unsqueeze(-1)).squeeze(-1)
    assert float((x[:, 1] - 0.5 * x[:, 0]).abs().max()) <= 1e3 * root_tiny


# ---------------------------------------------------------------- watermark study


def test_watermark_thresholds_come_from_the_calibration_seeds_runs(monkeypatch):
    """Every row's threshold is ``threshold_for`` of the attack-free runs drawn from the
    report's calibration seed (full windows), not of the study's own attack-free runs, whose
    false-alarm rate at it the row reports."""
    from difffilter.eval import watermark
    from difffilter.eval.calibration import threshold_for
    from difffilter.models import registry
    from difffilter.models.streams import Streams

    window, runs, far = 50, 3, 0.01
    scenario = registry.get("lfc_step")
    seen = []
    real_loop = watermark.lfc_loop

    def spy(plant, estimator, xi, theta, load, attack=None, **kw):
        out = real_loop(plant, estimator, xi, theta, load, attack=attack, **kw)
        scores = out.output.detection.scores.clone()
        seen.append((xi.clone(), attack is None, kw.get("watermark") is not None, scores))
        return out

    monkeypatch.setattr(watermark, "lfc_loop", spy)
    doc = watermark.watermark_study(scenario, runs=runs, window=window, far=far, seed=0)
    streams = Streams(0)
    assert doc["far"]["calibration_seed"] == streams.seed_of("far-calibration/plant")

    def xi_of(prefix):
        gens = {k: streams(f"{prefix}{k}") for k in ("plant", "attack")}
        return scenario.exogenous(runs, gens)["xi"]

    cal_xi, study_xi = xi_of("far-calibration/"), xi_of("")
    for marked, label in ((False, "without watermark"), (True, "with watermark")):
        free = [(xi, s) for xi, clean, m, s in seen if m == marked and clean]
        (cal,) = [s for xi, s in free if torch.equal(xi, cal_xi)]
        (study,) = [s for xi, s in free if torch.equal(xi, study_xi)]
        row = doc["rows"][f"plain replay, {label}"]
        expected = float(threshold_for(cal[:, window - 1 :], far))
        assert row["threshold"] == pytest.approx(expected, rel=1e-12)
        assert row["threshold"] != pytest.approx(float(threshold_for(study[:, window - 1 :], far)))
        fpr = float((study[:, window - 1 :] > expected).double().mean())
        assert row["fpr_at_far"] == pytest.approx(fpr, abs=1e-15)
