"""Mutation-review tests of :mod:`difffilter.bounds` on a nonlinear model (float64).

The existing suite checks the PCRB on linear-Gaussian models, where every path has the
same Jacobians; these checks use a nonlinear, time-varying scalar model with many
paths, so that the Monte Carlo means of the Tichavský recursion matter.
"""

from __future__ import annotations

import numpy as np
import torch

import difffilter as df


def _hand_pcrb(x0, xs, a, c, q, r, p0):
    """Tichavský et al. (1998) for ``x_{k+1} = (a + k/10) x_k + sin x_k + w``, ``y_k = c k x² + v``, by hand in
    numpy: ``D11 = E[F²]/q``, ``D12 = −E[F]/q``, ``D22 = 1/q + E[H_k²]/r``,
    ``J ← D22 − D12²/(J + D11)``, ``F`` at ``x_k`` (``x_0`` first) and ``H`` at ``x_{k+1}``."""
    J, prev, out = 1.0 / p0, x0, []
    for t in range(xs.shape[1]):
        F = a + 0.1 * t + np.cos(prev)
        H = 2.0 * c * (t + 1) * xs[:, t]
        d11, d12 = np.mean(F**2) / q, -np.mean(F) / q
        d22 = 1.0 / q + np.mean(H**2) / r
        J = d22 - d12**2 / (J + d11)
        out.append(J)
        prev = xs[:, t]
    return np.array(out)


def test_pcrb_nonlinear_time_varying_matches_hand_recursion():
    """``posterior_crb`` of a nonlinear model with a step-dependent observation, over 64
    sample paths, equals the recursion computed by hand in numpy (the Monte Carlo means of
    ``F²``, ``F`` and ``H_k²`` at the right states and steps, ``f`` read at ``k`` for ``x_k → x_{k+1}``)."""
    a, c, q, r, p0 = 0.6, 0.3, 0.4, 0.5, 1.2
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    model = df.NonlinearGaussianModel(
        lambda x, u, k: (a + 0.1 * k) * x + torch.sin(x),
        lambda x, k: c * k * x**2,
        t([[q]]),
        t([[r]]),
        t([0.0]),
        t([[p0]]),
    )
    rng = np.random.default_rng(7)
    M, T = 64, 5
    x0 = rng.normal(0.0, 1.0, M)
    xs = rng.normal(0.0, 1.5, (M, T))
    res = df.posterior_crb(
        model,
        torch.tensor(xs, dtype=torch.float64).unsqueeze(-1),
        torch.tensor(x0, dtype=torch.float64).unsqueeze(-1),
    )
    want = _hand_pcrb(x0, xs, a, c, q, r, p0)
    np.testing.assert_allclose(res.information[:, 0, 0].numpy(), want, rtol=1e-10)
    np.testing.assert_allclose(res.bound[:, 0, 0].numpy(), 1.0 / want, rtol=1e-10)


def test_particle_smoother_reads_a_time_varying_transition_at_its_own_k():
    """FFBSm on ``x_{k+1} = (0.5 + 0.3 k) x_k + w``: the smoothing weights equal the
    recursion written out in numpy (Doucet, Godsill & Andrieu 2000) with the Gaussian
    transition density of ``f(·, k)``, the stored index ``t`` holding ``x_{t+1}``, so the
    step to index ``t + 1`` is read at ``k = t + 1``."""
    q = 0.2
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    model = df.NonlinearGaussianModel(
        lambda x, u, k: (0.5 + 0.3 * k) * x, lambda x: x, t([[q]]), t([[0.5]]), t([0.0]), t([[1.0]])
    )
    _, ys, _ = model.simulate(5, (1,), generator=torch.Generator().manual_seed(2))
    pf = df.particle_filter(
        model,
        ys,
        num_particles=6,
        return_particles=True,
        generator=torch.Generator().manual_seed(3),
    )
    out = df.particle_smoother(model, pf)
    x = pf.particles[0, :, :, 0].numpy()  # [T, N]
    w = np.exp(pf.log_weights[0].numpy())  # [T, N]
    T = x.shape[0]
    ws = [w[-1]]
    for s in range(T - 2, -1, -1):
        k = s + 1
        ahead = (0.5 + 0.3 * k) * x[s]  # f(x_k^i, k) [N_i]
        dens = np.exp(-0.5 * (x[s + 1][None, :] - ahead[:, None]) ** 2 / q)  # [N_i, N_j]
        denom = (w[s][:, None] * dens).sum(0)  # [N_j]
        new = w[s] * (dens * (ws[-1] / denom)[None, :]).sum(1)
        ws.append(new / new.sum())
    ws = np.stack(ws[::-1])
    np.testing.assert_allclose(np.exp(out.log_weights[0].numpy()), ws, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(out.means[0, :, 0].numpy(), (ws * x).sum(-1), rtol=1e-9)
