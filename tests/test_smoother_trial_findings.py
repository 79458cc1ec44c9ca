"""The smoothers (a red-team trial, 2026-12-07; each test failed before its fix)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import torch

import difffilter as df

F64 = torch.float64


def _t(a):
    return torch.tensor(a, dtype=F64)


W = _t([[1.0, 0.1, 0.0], [-0.2, 0.9, 1.0]])
Q, R = _t([[0.3, 0.05], [0.05, 0.2]]), _t([[0.4]])
M0, P0 = _t([0.5, -1.0]), _t([[1.0, 0.2], [0.2, 2.0]])


def _joining(x, u):  # a transition that joins x and u, as a network's does
    return torch.cat([x, u], -1) @ W.mT


def test_the_unscented_and_particle_smoothers_take_a_transition_that_joins_x_and_u():
    """They handed f the input as ``[..., 1, du]`` beside ``[..., M, dx]`` points, and a
    ``torch.cat`` transition failed on "Sizes of tensors must match", where the UKF and the
    particle filter whose results they smooth run it (one input row per point). The model is
    linear in (x, u): the Kalman smoother of the same linear model is the truth."""
    model = df.NonlinearGaussianModel(_joining, lambda x: x[..., :1] + 0.5 * x[..., 1:], Q, R,
                                      M0, P0, dim_u=1)  # fmt: skip
    linear = df.LinearGaussianModel(W[:, :2], _t([[1.0, 0.5]]), Q, R, M0, P0, B=W[:, 2:])
    rng = np.random.default_rng(0)
    ys, us = _t(rng.normal(size=(2, 6, 1))), _t(rng.normal(size=(2, 6, 1)))
    truth = df.kalman_smoother(linear, ys, us)
    smoothed = df.unscented_rts_smoother(model, df.unscented_kalman_filter(model, ys, us), us)
    torch.testing.assert_close(smoothed.means, truth.means, rtol=0, atol=1e-12)
    torch.testing.assert_close(smoothed.covs, truth.covs, rtol=0, atol=1e-12)
    pf = df.particle_filter(model, ys, us, num_particles=64, return_particles=True,
                            generator=torch.Generator().manual_seed(0))  # fmt: skip
    joined = df.particle_smoother(model, pf, us)
    plain = df.particle_smoother(linear, pf, us)  # (the same particles, f as matrices)
    torch.testing.assert_close(joined.means, plain.means, rtol=0, atol=1e-12)


def test_the_particle_smoother_is_callable_after_its_module_is_imported():
    """The function and its submodule shared the name ``particle_smoother``: importing
    anything from the module first made ``df.particle_smoother`` the module ("'module'
    object is not callable"), and the other order made the module the function. Run in a
    fresh interpreter: the order of imports is the point."""
    code = (
        "from difffilter.particle_smoothing import ParticleSmootherResult, CHUNK_ELEMENTS\n"
        "import difffilter as df\n"
        "import difffilter.particle_smoothing as module\n"
        "assert callable(df.particle_smoother), type(df.particle_smoother)\n"
        "assert df.particle_smoother is module.particle_smoother\n"
        "assert df.ParticleSmootherResult is ParticleSmootherResult\n"
        "assert module.CHUNK_ELEMENTS == CHUNK_ELEMENTS\n"
        "print('ok')\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
    names = set(df._WHERE)  # (the functions and classes; df.__all__ names modules as well)
    modules = {p.stem for p in __import__("pathlib").Path(df.__file__).parent.glob("*.py")}
    assert not names & modules, f"public names that are also submodules: {names & modules}"


def test_the_ekf_and_its_smoother_take_one_input_sequence_for_a_batch_of_runs():
    """``us [T, du]`` shared by ``ys [B, T, dy]``: the EKF (and the extended smoother) handed
    a transition that joins x and u the input unbatched beside ``x [B, dx]`` and failed in
    ``torch.cat``, where the UKF and the particle filter take it (a red-team trial's aside)."""
    model = df.NonlinearGaussianModel(_joining, lambda x: x[..., :1] + 0.5 * x[..., 1:], Q, R,
                                      M0, P0, dim_u=1)  # fmt: skip
    linear = df.LinearGaussianModel(W[:, :2], _t([[1.0, 0.5]]), Q, R, M0, P0, B=W[:, 2:])
    rng = np.random.default_rng(1)
    ys, us = _t(rng.normal(size=(3, 6, 1))), _t(rng.normal(size=(6, 1)))
    truth = df.kalman_smoother(linear, ys, us)
    filtered = df.extended_kalman_filter(model, ys, us)
    torch.testing.assert_close(filtered.means, truth.filtered.means, rtol=0, atol=1e-12)
    smoothed = df.extended_kalman_smoother(model, ys, us)
    torch.testing.assert_close(smoothed.means, truth.means, rtol=0, atol=1e-12)
    ekf = df.ExtendedKalmanFilter()
    carry = ekf.init(model, (3,))
    carry, out = ekf.step(carry, ys[:, 0], us[0])
    torch.testing.assert_close(out.mean, truth.filtered.means[:, 0], rtol=0, atol=1e-12)
