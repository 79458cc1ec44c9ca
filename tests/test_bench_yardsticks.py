"""The benchmarks' yardsticks compute what the library calls beside them compute (a ratio
to a yardstick that does more, or less, is no ratio)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import difffilter as df

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
bench = pytest.importorskip("bench")


def test_the_numpy_kalman_loop_is_the_kalman_filter():
    """Sections 1 and 1c time ``numpy_kf_run`` against ``kalman_filter``: the same last mean
    and log-likelihood, on one factorisation a step (it had also solved ``S`` by LU and
    ``L z = r`` by a general solve: 1.12–1.15× slower for the same numbers)."""
    model = bench.tracking_cv_model()
    _, ys, _ = model.simulate(200, (1,), generator=torch.Generator().manual_seed(0))
    mean, log_lik = bench.numpy_kf_run(*bench.numpy_matrices(model), ys[0].numpy())
    ref = df.kalman_filter(model, ys[0])
    np.testing.assert_allclose(mean, ref.means[-1].numpy(), rtol=0, atol=1e-10)
    assert log_lik == pytest.approx(float(ref.log_likelihood), abs=1e-9)


def test_the_memory_child_runs_on_the_parents_threads(monkeypatch):
    """Section 3's child process had run on every core while the parent ran on ``--threads``."""
    calls = []

    def run(argv, **kwargs):
        calls.append(argv)
        raise SystemExit  # (the command is all this test reads)

    monkeypatch.setattr(bench.subprocess, "run", run)
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with pytest.raises(SystemExit):
            bench.bench_memory()
    finally:
        torch.set_num_threads(previous)
    assert calls[0][-1] == "1" and "torch.set_num_threads(int(sys.argv[2]))" in calls[0][2]


def test_the_numpy_particle_loop_draws_in_the_particles_float32():
    """A benchmark trial: the loop drew its noise in float64 and cast it to float32, 1.5–5 %
    of work that difffilter's float32 filter does not do, flattering every PF ratio."""

    class Recording:
        def __init__(self):
            self.rng, self.dtypes = np.random.default_rng(0), []

        def standard_normal(self, size, dtype=np.float64):
            self.dtypes.append(np.dtype(dtype))
            return self.rng.standard_normal(size, dtype=dtype)

        def random(self):
            return self.rng.random()

    model = bench.FourTankModel(dtype=torch.float32)  # (section 2's)
    ys = np.full((5, 4), 10.0, dtype=np.float32)
    rng = Recording()
    bench.numpy_bootstrap_pf_run(model, ys, 100, rng)
    assert rng.dtypes and set(rng.dtypes) == {np.dtype(np.float32)}


def test_the_benchmarks_threads_must_be_positive():
    """An interrupts trial: ``bench.py --threads 0`` reached ``torch.set_num_threads``, a
    traceback where a usage error is due."""
    for bad in ("0", "-1", "two"):
        with pytest.raises(SystemExit) as stopped:
            bench.main(["--threads", bad])
        assert stopped.value.code == 2
