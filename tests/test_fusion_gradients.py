"""Covariance intersection from a fusion trial: its ω was found by a search that records
no gradient, so every derivative through the fused estimate held ω constant (a chain
KF → CI → loss: autograd +4.28, finite differences −33.31); with equal local covariances
ω drifted to 1 (local 1 alone, so swapping the locals changed the answer); a singular or
NaN local covariance gave NaN, or torch's own error."""

from __future__ import annotations

import pytest
import torch

from difffilter.fdi.fusion import covariance_intersection

F64 = torch.float64


def _pair(d, seed):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(2, d, d, generator=g, dtype=F64)
    covs = A @ A.mT + 0.3 * torch.eye(d, dtype=F64)
    means = torch.randn(2, d, generator=g, dtype=F64)
    return means, covs


def _reference(means, covs):
    """CI written out: ω the root of J′(ω) = −tr(P A P) (J = tr P_f convex, so J′ rises
    through 0), found by bisection to round-off; P_f and x̂_f by torch.linalg."""
    info = torch.linalg.inv(covs)
    A = info[0] - info[1]

    def fused_cov(w):
        return torch.linalg.inv(w * info[0] + (1 - w) * info[1])

    lo, hi = torch.tensor(0.0, dtype=F64), torch.tensor(1.0, dtype=F64)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        P = fused_cov(mid)
        rising = -(P @ A @ P).trace() > 0
        lo, hi = torch.where(rising, lo, mid), torch.where(rising, mid, hi)
    w = 0.5 * (lo + hi)
    P = fused_cov(w)
    return P @ (w * info[0] @ means[0] + (1 - w) * info[1] @ means[1]), P, w


@pytest.mark.parametrize("d", [2, 4])  # the by-hand path (d ≤ 3) and torch.linalg's
def test_the_fused_estimate_is_differentiated_with_its_omega(d):
    means, covs = _pair(d, 1)
    mean, cov, omega = covariance_intersection(means, covs, iterations=80)
    ref_mean, ref_cov, ref_omega = _reference(means, covs)
    assert 0.01 < float(ref_omega) < 0.99  # an interior minimiser: ω moves with the covs
    assert float(omega) == pytest.approx(float(ref_omega), abs=1e-7)
    torch.testing.assert_close(mean, ref_mean, rtol=1e-7, atol=1e-9)
    weights = torch.linspace(0.5, 1.5, d * d, dtype=F64).reshape(d, d)

    def loss(c, fuse=covariance_intersection):
        mean, cov = (fuse(means, c, iterations=80) if fuse is covariance_intersection
                     else _reference(means, c))[:2]  # fmt: skip
        return (mean**2).sum() + (weights * cov).sum()

    covs = covs.requires_grad_(True)
    (grad,) = torch.autograd.grad(loss(covs), covs)
    h = 1e-6
    numeric = torch.zeros_like(covs)
    with torch.no_grad():
        for idx in torch.cartesian_prod(*(torch.arange(n) for n in covs.shape)):
            i, j, k = (int(v) for v in idx)
            if k < j:
                continue
            bump = torch.zeros_like(covs)
            bump[i, j, k] = bump[i, k, j] = h  # symmetric: one entry and its mirror
            diff = (loss(covs + bump, _reference) - loss(covs - bump, _reference)) / (2 * h)
            numeric[i, j, k] = diff if j == k else diff / 2
            numeric[i, k, j] = numeric[i, j, k]
    torch.testing.assert_close(0.5 * (grad + grad.mT), numeric, rtol=1e-6, atol=1e-8)


def test_equal_local_covariances_give_the_symmetric_rule():
    means, covs = _pair(3, 2)
    same = torch.stack([covs[0], covs[0]])
    mean, _, omega = covariance_intersection(means, same)
    swapped, _, _ = covariance_intersection(means.flip(0), same)
    assert float(omega) == 0.5
    torch.testing.assert_close(mean, 0.5 * (means[0] + means[1]))
    torch.testing.assert_close(swapped, mean, rtol=0, atol=1e-15)


def test_a_local_covariance_that_cannot_be_fused_is_named():
    means, covs = _pair(2, 3)
    singular = covs.clone()
    singular[1] = torch.tensor([[1.0, 1.0], [1.0, 1.0]], dtype=F64)
    with pytest.raises(ValueError, match="covs must be positive definite"):
        covariance_intersection(means, singular)
    bad = covs.clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="means and covs must be finite"):
        covariance_intersection(means, bad)
    lopsided = covs.clone()
    lopsided[0, 0, 1] += 1.0
    with pytest.raises(ValueError, match="covs must be symmetric"):
        covariance_intersection(means, lopsided)


def test_no_derivative_of_omega_where_the_minimiser_is_a_bound_the_search_stopped_short_of():
    """From the second review: after 20 iterations a search for ω = 1 stops at 0.99997,
    and the derivative was taken as if it were inside (dω/dcovs 0.356 for 0)."""
    g = torch.Generator().manual_seed(5)
    A = torch.randn(2, 3, 3, generator=g, dtype=F64)
    good = A[0] @ A[0].mT + 0.05 * torch.eye(3, dtype=F64)
    covs = torch.stack([good, good + 5.0 * torch.eye(3, dtype=F64)])  # local 1 better in all
    means = torch.randn(2, 3, generator=g, dtype=F64)
    _, _, omega = covariance_intersection(means, covs, iterations=20)
    assert 0.999 < float(omega) < 1.0  # short of the bound
    c = covs.clone().requires_grad_(True)
    _, _, omega = covariance_intersection(means, c, iterations=20)
    (grad,) = torch.autograd.grad(omega, c)
    assert float(grad.abs().max()) == 0.0


@pytest.mark.filterwarnings("ignore:There is a performance drop")  # (vmap of addcmul_)
def test_forward_mode_and_vmap_give_the_same_derivative():
    """Forward mode had kept ω constant (0.634 for 0.616), and ``vmap`` stopped at the
    input checks (Python booleans of batched tensors)."""
    means, covs = _pair(2, 1)
    direction = torch.randn(2, 2, 2, dtype=F64, generator=torch.Generator().manual_seed(7))
    direction = direction + direction.mT

    def fused_mean(c):
        return covariance_intersection(means, c, iterations=60)[0]

    _, forward = torch.func.jvp(fused_mean, (covs,), (direction,))
    c = covs.clone().requires_grad_(True)
    out = fused_mean(c)
    reverse = torch.stack([torch.autograd.grad(out[i], c, retain_graph=True)[0].mul(direction).sum()
                           for i in range(2)])  # fmt: skip
    torch.testing.assert_close(forward, reverse, rtol=1e-10, atol=1e-12)
    batched = torch.func.vmap(fused_mean)(torch.stack([covs, covs * 2.0]))
    torch.testing.assert_close(batched[0], fused_mean(covs), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(batched[1], fused_mean(covs * 2.0), rtol=1e-12, atol=1e-12)


def test_a_float32_pair_that_factorises_but_does_not_invert_is_refused_by_name():
    """Covariances of condition 1e8 in float32 (beyond 1/ε): a quarter of such pairs passed
    the pair check's Cholesky and stopped in ``torch.linalg.inv`` ("The diagonal element 2
    is zero"), naming neither ``covs`` nor the dtype; every failure is now the ValueError."""
    from difffilter.fdi import covariance_intersection, information_fusion

    g = torch.Generator().manual_seed(1)
    outcomes = set()
    for _ in range(40):
        basis, _ = torch.linalg.qr(torch.randn(2, 2, 2, generator=g, dtype=torch.float64))
        covs = (basis * torch.logspace(0, 8, 2, dtype=torch.float64)) @ basis.transpose(-1, -2)
        means = torch.randn(2, 2, generator=g, dtype=torch.float64)
        for fuse in (covariance_intersection, information_fusion):
            try:
                fuse(means.float(), covs.float())
                outcomes.add("fused")
            except ValueError as error:
                assert "covs must be positive definite" in str(error)
                outcomes.add("inverse" if "precision" in str(error) else "factor")
            fuse(means, covs)  # float64 holds every one of them
    # Which refusal a pair met was the CPU's round-off (MKL's kernels: fusions and both
    # refusals on one machine, fusions and the Cholesky's on an AVX-512 one); the pair check
    # is decided in float64 now (difffilter._checks.cholesky_fails), the inverse of a pair
    # it takes is still float32's: fusions and a refusal by name on every CPU
    assert {"fused", "factor"} <= outcomes <= {"fused", "factor", "inverse"}


def test_a_covariance_that_does_not_invert_is_refused_naming_covs_and_the_dtype():
    """The inverse's own refusal, met on every CPU: ``[[1, 1], [1, 1]]`` has an exact zero
    pivot, so ``torch.linalg.inv_ex`` reports it whatever its kernels' round-off."""
    from difffilter.fdi.fusion import _information

    covs = torch.eye(2).expand(2, 2, 2).clone()
    covs[1] = 1.0
    with pytest.raises(ValueError, match=r"cannot be inverted in float32 .*float64 may hold"):
        _information(covs)
    torch.testing.assert_close(_information(covs[:1].double()), covs[:1].double())
