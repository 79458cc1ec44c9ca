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

_UNDER_AVX2 = """
import torch, difffilter as df
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

for g in ([[1.0], [1.0]], [[0.5], [1.0]], [[1.0], [2.0]]):
    q = torch.tensor(g) @ torch.tensor(g).T
    print("model", refused(lambda: df.LinearGaussianModel(
        torch.eye(2), torch.eye(2)[:1], q, torch.eye(1), torch.zeros(2), torch.eye(2))))
singular = [torch.tensor([[9.0, 3.0], [3.0, 1.0]]),
            torch.tensor([[5.0, -2.0, 6.0], [-2.0, 4.0, -4.0], [6.0, -4.0, 8.0]])]
for p in singular:
    covs, means = torch.stack([p, torch.eye(len(p))]), torch.zeros(2, len(p))
    for fuse in (information_fusion, covariance_intersection):
        print("fusion", refused(lambda: fuse(means, covs)))
print("cause", _cause(torch.ones(1, 2, 1), 1e-8 * torch.eye(2)[None], torch.eye(1)[None]))
"""


@pytest.fixture(scope="module")
def under_avx2() -> list[str]:
    env = {**os.environ, "MKL_ENABLE_INSTRUCTIONS": "AVX2"}
    run = subprocess.run([sys.executable, "-c", _UNDER_AVX2], env=env, capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert run.returncode == 0, run.stderr
    return run.stdout.splitlines()


def test_a_float32_rank_one_covariance_is_refused_on_every_cpu(under_avx2):
    models = [line for line in under_avx2 if line.startswith("model ")]
    assert len(models) == 3
    assert all("Q must be positive definite (all eigenvalues > 0" in m for m in models), models


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
