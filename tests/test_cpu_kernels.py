"""Decisions taken from a factorisation's success, alike on every CPU. MKL chooses its
kernels by the CPU: its AVX2 float32 Cholesky factorises matrices singular in exact
arithmetic (``[[1, 1], [1, 1]]``: a last pivot of 3e-4 for 0, its reciprocal square roots
being inexact) where its AVX-512 one fails, so a model, a pair of local estimates and an
error's explanation were taken on one machine and refused on another (a review on an
AVX-512 machine; CI and users run on either). Here MKL is held to its AVX2 kernels in a
process of its own (on a CPU without AVX-512 those are its kernels anyway)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

_DECISIONS = """
def _decisions():
    # float32 matrices at float32's precision: rank-one g gᵀ of rounded entries (one in ten
    # had been decided by the CPU's kernels) and covariances of condition 1e3 to 1e9
    from difffilter._checks import cholesky_fails
    g = torch.Generator().manual_seed(0)
    v = torch.randn(3000, 3, 1, generator=g)
    e, q = torch.linalg.eigh((lambda a: a @ a.mT)(torch.randn(3000, 3, 3, generator=g,
                                                              dtype=torch.float64)))
    e[:, 0] = e[:, -1] * torch.logspace(-9, -3, 3000, dtype=torch.float64)
    near = ((q * e[:, None, :]) @ q.mT).float()
    fails = torch.cat([cholesky_fails((v @ v.mT).float()), cholesky_fails((near + near.mT) / 2)])
    return "".join("1" if f else "0" for f in fails.tolist())
"""

_UNDER_AVX2 = (
    """
import torch, difffilter as df
"""
    + _DECISIONS
    + """
from difffilter.fdi import covariance_intersection, information_fusion
from difffilter.parallel_kalman import _cause

print("float32 factorises [[1, 1], [1, 1]]:", int(torch.linalg.cholesky_ex(
    torch.ones(2, 2)).info) == 0)
def refused(make):
    try:
        make()
    except ValueError as error:
        return str(error)
    return "taken"

for g in ([[1.0], [1.0]], [[0.5], [1.0]], [[1.0], [2.0]], [[0.1], [0.3]]):
    q = torch.tensor(g) @ torch.tensor(g).T
    print("model", refused(lambda: df.LinearGaussianModel(
        torch.eye(2), torch.eye(2)[:1], q, torch.eye(1), torch.zeros(2), torch.eye(2))))
singular = [torch.tensor([[9.0, 3.0], [3.0, 1.0]]),
            torch.tensor([[5.0, -2.0, 6.0], [-2.0, 4.0, -4.0], [6.0, -4.0, 8.0]])]
for p in singular:
    covs, means = torch.stack([p, torch.eye(len(p))]), torch.zeros(2, len(p))
    for fuse in (information_fusion, covariance_intersection):
        print("fusion", refused(lambda: fuse(means, covs)))
print("decisions", _decisions())
print("cause", _cause(torch.ones(1, 2, 1), 1e-8 * torch.eye(2)[None], torch.eye(1)[None]))
"""
)


@pytest.fixture(scope="module")
def under_avx2() -> list[str]:
    env = {**os.environ, "MKL_ENABLE_INSTRUCTIONS": "AVX2"}
    run = subprocess.run([sys.executable, "-c", _UNDER_AVX2], env=env, capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert run.returncode == 0, run.stderr
    return run.stdout.splitlines()


def test_a_float32_rank_one_covariance_is_refused_on_every_cpu(under_avx2):
    models = [line for line in under_avx2 if line.startswith("model ")]
    assert len(models) == 4
    assert all("Q must be positive definite (all eigenvalues > 0" in m for m in models[:3]), models
    # (the rounded (0.1, 0.3)(0.1, 0.3)ᵀ is definite as its float32 values are, by 3e-9)
    assert "is positive definite in exact arithmetic" in models[3], models


def test_float32_definiteness_is_decided_alike_under_either_kernels(under_avx2):
    """A review: float32 matrices whose pivots are float32's round-off were refused or taken
    by the kernels (one rounded rank-one matrix in ten, 1,800 of 20,000); every decision of
    this process (its CPU's kernels) is now that of the AVX2 ones."""
    import torch

    namespace = {"torch": torch}
    exec(_DECISIONS, namespace)
    (line,) = [line for line in under_avx2 if line.startswith("decisions ")]
    here = namespace["_decisions"]()
    assert line.removeprefix("decisions ") == here
    assert here[:3000] == "1" * 3000 and 0 < here[3000:].count("1") < 3000


def test_a_singular_float32_local_covariance_is_not_fused_on_any_cpu(under_avx2):
    """``[[9, 3], [3, 1]]`` (rank one) was fused on AVX2, its covariance 8 % off the limit of
    fusing ``P + t I``; the rank-two 3×3 (det 0) was fused on both kinds of CPU."""
    fused = [line for line in under_avx2 if line.startswith("fusion ")]
    assert len(fused) == 4
    assert all("a local covariance is singular or indefinite" in f for f in fused), fused


def test_the_parallel_filters_explanation_names_the_singular_s_on_every_cpu(under_avx2):
    """H Q Hᵀ + R = [[1, 1], [1, 1]] + 1e-8 I, singular in float32: AVX2 had blamed I + C J."""
    (cause,) = [line for line in under_avx2 if line.startswith("cause ")]
    assert "H Q Hᵀ + R positive definite, and here it is singular" in cause


def test_float32_definiteness_does_not_depend_on_the_order_of_the_states():
    """A review: the pivot floor refused a Q in one order of its states and took it in
    another (x3 = x1 + 0.01·x2 + e, a last pivot of 9.7e-7 of its variance in one
    order, none below 1e-4 in the other); the correlation matrix's eigenvalue decides."""
    import itertools

    import torch

    from difffilter._checks import cholesky_fails

    a = 0.01  # (x3's own noise 3e-4: the correlation matrix's smallest eigenvalue 4.5e-8)
    q = torch.tensor([[1, 0, 1], [0, 1, a], [1, a, 1 + a * a + 1e-7]], dtype=torch.float32)
    g = torch.Generator().manual_seed(3)
    near = torch.randn(200, 3, 3, generator=g, dtype=torch.float64)
    near = near @ near.mT
    e, v = torch.linalg.eigh(near)
    e[:, 0] = e[:, -1] * torch.logspace(-8, -4, 200, dtype=torch.float64)
    near = ((v * e[:, None, :]) @ v.mT).float()
    near = (near + near.mT) / 2
    for order in itertools.permutations(range(3)):
        p = list(order)
        assert bool(cholesky_fails(q[p][:, p])) is True
        assert torch.equal(cholesky_fails(near[:, p][:, :, p]), cholesky_fails(near))


def test_a_definite_float32_covariance_in_mixed_units_is_not_called_rank_deficient():
    """A review: judged on its unscaled eigenvalues, a definite float32 P0 of variances 1
    and 1e-12 read as "rank-deficient (Q = 0, P0 = 0, q g gᵀ)", and the message offered
    units, which the scale-free check does not see; the same matrix in equal units read
    "positive definite … too near singular for float32"."""
    import pytest
    import torch

    import difffilter as df

    rho = 1 - 2.0**-23  # 1 − 1.2e-7, exact in float32: below the floor d·ε₃₂ = 2.4e-7
    corr = torch.tensor([[1.0, rho], [rho, 1.0]], dtype=torch.float64)
    for scales in ((1.0, 1.0), (1.0, 1e-6), (1e3, 1e-3)):
        s = torch.diag(torch.tensor(scales, dtype=torch.float64))
        with pytest.raises(ValueError) as error:
            df.LinearGaussianModel(torch.eye(2), torch.eye(2), torch.eye(2), torch.eye(2),
                                   torch.zeros(2), (s @ corr @ s).float())  # fmt: skip
        message = str(error.value)
        assert "P0 is positive definite in exact arithmetic" in message, message
        assert "too near singular for float32" in message and "units" not in message


def test_the_smoother_takes_a_float32_filters_own_predicted_covariances():
    """A review: after a precise first position reading (R = 1e-6 beside P0 = I) a float32
    constant-velocity filter's predicted covariance has a correlation within 1e-6 of 1; the
    filter ran, float32 factorised it, and the smoother refused it as "too near singular"
    (its check of a filter's output now asks only that it be definite, decided in float64).
    At R = 1e-7 (a correlation eigenvalue of 1e-7, under the floor d·ε₃₂: a mutation trial
    found R = 1e-6 above it, where undoing the fix passed)."""
    import torch

    import difffilter as df

    def cv(dtype):
        q = 1e-8 * torch.tensor([[1 / 3, 1 / 2], [1 / 2, 1.0]], dtype=torch.float64)
        return df.LinearGaussianModel(torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=dtype),
                                      torch.tensor([[1.0, 0.0]], dtype=dtype), q.to(dtype),
                                      torch.tensor([[1e-7]], dtype=dtype),
                                      torch.zeros(2, dtype=dtype), torch.eye(2, dtype=dtype))  # fmt: skip

    m32, m64 = cv(torch.float32), cv(torch.float64)
    _, ys, _ = m64.simulate(60, batch_shape=(2,), generator=torch.Generator().manual_seed(0))
    smoothed = df.rts_smoother(m32, df.kalman_filter(m32, ys.float()))
    exact = df.rts_smoother(m64, df.kalman_filter(m64, ys))
    sd = exact.covs.diagonal(dim1=-2, dim2=-1).sqrt()
    assert float(((smoothed.means.double() - exact.means) / sd).abs().max()) < 0.5


def test_the_variance_a_refusal_suggests_fixes_a_covariance_in_mixed_units():
    """A review: the suggested ``Q + 1e-4 · max(diag) · I`` added 1e-4 to a variance of
    1e-8 (a rank-one g gᵀ of g = (1, 1e-4)); in mixed units each variance is raised by 1e-4
    of itself, which float32 then resolves."""
    import pytest
    import torch

    import difffilter as df

    def model(q):
        return df.LinearGaussianModel(torch.eye(2), torch.eye(2)[:1], q, torch.eye(1),
                                      torch.zeros(2), torch.eye(2))  # fmt: skip

    g = torch.tensor([[1.0], [1e-4]])
    q = g @ g.T
    with pytest.raises(ValueError, match=r"Q \+ 1e-04 · diag\(Q\) \(each variance raised"):
        model(q)
    fixed = model(q + 1e-4 * torch.diag(q.diagonal()))
    assert float(fixed.process_noise.cov[1, 1]) < 1.1e-8  # (the small variance kept its scale)


def test_the_suggested_variance_is_one_the_check_takes_at_any_size_and_for_zero_variances():
    """A review: the suggested 1e-4 lifted the correlation eigenvalue to 1e-4, under the
    floor d·ε₃₂ from d = 839, so the fixed matrix was refused with the same advice; for
    Q = 0 the suggestion was 0 again, and beside a zero variance it raised one of 1e-8 to
    1e4."""
    import re

    import pytest
    import torch

    import difffilter as df

    def model(q):
        n = q.shape[-1]
        return df.LinearGaussianModel(torch.eye(n), torch.eye(n)[:1], q, torch.eye(1),
                                      torch.zeros(n), torch.eye(n))  # fmt: skip

    ones = torch.ones(850, 850)
    with pytest.raises(ValueError, match=r"Q \+ 1e-03 · max\(diag\) · I") as error:
        model(ones)
    size = float(re.search(r"Q \+ (\S+) · max", str(error.value)).group(1))
    model(ones + size * torch.eye(850))  # taken: the suggestion clears the floor
    with pytest.raises(ValueError, match=r"a variance of its own on each state \(Q = 0"):
        model(torch.zeros(2, 2))
    with pytest.raises(ValueError, match=r"Q \+ 1e-04 · diag\(Q\) .* on state 2, whose variance"):
        model(torch.diag(torch.tensor([1e8, 1e-8, 0.0])))


def test_an_indefinite_matrix_is_called_indefinite_and_told_no_variance():
    """A review: a negative variance was told to raise each variance by 1e-4 of itself
    (−1 → −1.0001), and every indefinite matrix ([[1, 2], [2, 1]]: eigenvalue −1) was
    called "a rank-deficient covariance" that "needs a small variance added"."""
    import pytest
    import torch

    import difffilter as df

    for q, negative in ((torch.tensor([[-1.0]]), True), (torch.tensor([[1.0, 2.0], [2.0, 1.0]]), False),
                        (torch.diag(torch.tensor([1.0, -1e-3])).double(), True),
                        (torch.tensor([[0.0, 1.0], [1.0, 1.0]]), False)):  # fmt: skip
        n = q.shape[-1]
        with pytest.raises(ValueError) as error:
            df.LinearGaussianModel(torch.eye(n, dtype=q.dtype), torch.eye(n, dtype=q.dtype)[:1],
                                   q, torch.eye(1, dtype=q.dtype), torch.zeros(n, dtype=q.dtype),
                                   torch.eye(n, dtype=q.dtype))  # fmt: skip
        message = str(error.value)
        assert "Q must be positive definite, and it is indefinite" in message, message
        assert ("a negative variance" in message) is negative
        assert "variance added" not in message and "raised by" not in message


def test_float32_rank_deficiency_and_mixed_unit_indefiniteness_are_told_apart():
    """A review: judged against float64's round-off, the float32 textbook q g gᵀ of a
    constant-velocity model (dt = 0.1), whose zero eigenvalue float32's rounding moves by
    about ε₃₂, was called indefinite; and judged on raw eigenvalues, [[1, 2], [2, 1]] at a
    scale of 1e-8 beside a variance of 1e8 (its correlation's eigenvalue −1) was called
    rank-deficient and told to add a variance."""
    import pytest
    import torch

    import difffilter as df

    def refusal(q):
        n = q.shape[-1]
        with pytest.raises(ValueError) as error:
            df.LinearGaussianModel(torch.eye(n, dtype=q.dtype), torch.eye(n, dtype=q.dtype)[:1],
                                   q, torch.eye(1, dtype=q.dtype), torch.zeros(n, dtype=q.dtype),
                                   torch.eye(n, dtype=q.dtype))  # fmt: skip
        return str(error.value)

    for dt in (0.3, 0.1, 0.05, 0.01):
        g = torch.tensor([[dt**2 / 2], [dt]], dtype=torch.float64)
        message = refusal((g @ g.T).float())
        # (rank-deficient, or definite by its rounded float32 values and too near singular)
        assert "indefinite" not in message, message
        assert "a rank-deficient covariance" in message or "too near singular" in message
    block = torch.zeros(3, 3, dtype=torch.float64)
    block[0, 0] = 1e8
    block[1:, 1:] = 1e-8 * torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=torch.float64)
    message = refusal(block)
    assert "indefinite (its correlation matrix's smallest eigenvalue is -1)" in message, message


def test_the_determinant_shortcut_does_not_pass_a_matrix_under_the_floor():
    """A mutation trial: with the shortcut's bound set to 1 no test failed, and a float32
    correlation of 1 − 3·2⁻²⁴ (smallest eigenvalue 1.8e-7, under the floor 2.4e-7;
    determinant 3.6e-7) passed it. Its bound (d/(d−1))^(d−1) = 2 here sends it to the
    eigenvalues, which refuse it."""
    import torch

    from difffilter._checks import cholesky_fails

    rho = 1 - 3 * 2.0**-24
    q = torch.tensor([[1.0, rho], [rho, 1.0]], dtype=torch.float32)
    assert torch.linalg.eigvalsh(q.double())[0] < 2 * torch.finfo(torch.float32).eps
    assert bool(cholesky_fails(q)) is True
    assert bool(cholesky_fails(q, resolved=False)) is False  # definite as its values are


def test_a_rank_one_float64_matrix_is_called_rank_deficient_not_definite():
    """A mutation trial: with the definite branch's threshold at 0 no test failed, and 30
    of 200 rank-one float64 3×3 (a smallest eigenvalue of round-off, ±1e-17) read as
    "positive definite in exact arithmetic"."""
    import pytest
    import torch

    import difffilter as df

    g = torch.randn(200, 3, 1, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for q in (g @ g.mT)[:40]:
        with pytest.raises(ValueError, match="a rank-deficient covariance"):
            df.LinearGaussianModel(torch.eye(3, dtype=q.dtype), torch.eye(3, dtype=q.dtype)[:1],
                                   q, torch.eye(1, dtype=q.dtype), torch.zeros(3, dtype=q.dtype),
                                   torch.eye(3, dtype=q.dtype))  # fmt: skip


def test_the_indefinite_threshold_scales_with_the_dimension():
    """A mutation trial: dropping the d of the threshold −10·d·ε left every test passing.
    A float32 correlation of 1 + 15·2⁻²³ (smallest eigenvalue −1.8e-6: between −10·ε₃₂ and
    −10·d·ε₃₂ at d = 2) is round-off of the rank-one [[1, 1], [1, 1]] and is told to add a
    variance; 1 + 25·2⁻²³ (−3.0e-6, under −10·d·ε₃₂) is indefinite."""
    import pytest
    import torch

    import difffilter as df

    def refusal(rho):
        q = torch.tensor([[1.0, rho], [rho, 1.0]], dtype=torch.float32)
        with pytest.raises(ValueError) as error:
            df.LinearGaussianModel(torch.eye(2), torch.eye(2)[:1], q, torch.eye(1),
                                   torch.zeros(2), torch.eye(2))  # fmt: skip
        return str(error.value)

    near = refusal(1 + 15 * 2.0**-23)
    assert "indefinite" not in near and "a rank-deficient covariance" in near, near
    far = refusal(1 + 25 * 2.0**-23)
    assert "it is indefinite (its correlation matrix's smallest eigenvalue is -2.98e-06)" in far
