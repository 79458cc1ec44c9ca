"""The particle smoother's checks of a filter result it is handed (a particle-smoother
trial): log-weights of another shape, dtype or with NaN, particles of no step axis, no
steps or NaN, and inputs with runs the filter never had are named, not misread or failed
in torch."""

import dataclasses

import pytest
import torch

import difffilter as df

F64 = torch.float64


def _model(dim_u: int = 0):
    F = torch.tensor([[0.9, 0.2], [-0.1, 0.8]], dtype=F64)
    H = torch.tensor([[1.0, 0.0]], dtype=F64)
    Q = torch.tensor([[0.3, 0.05], [0.05, 0.2]], dtype=F64)
    R = torch.tensor([[0.5]], dtype=F64)
    B = torch.tensor([[1.0], [0.5]], dtype=F64) if dim_u else None
    return df.LinearGaussianModel(
        F, H, Q, R, torch.tensor([1.0, -1.0], dtype=F64), 2 * torch.eye(2, dtype=F64), B=B
    )


@pytest.fixture(scope="module")
def filtered():
    model = _model()
    _, ys, _ = model.simulate(6, (3,), generator=torch.Generator().manual_seed(0))
    pf = df.particle_filter(
        model, ys, num_particles=50, return_particles=True,
        generator=torch.Generator().manual_seed(5),
    )  # fmt: skip
    return model, pf


def test_a_filter_result_of_its_own_still_smooths_to_the_rts_smoother(filtered):
    model, pf = filtered
    _, ys, _ = model.simulate(6, (3,), generator=torch.Generator().manual_seed(0))
    exact = df.kalman_smoother(model, ys)
    sd = exact.covs.diagonal(dim1=-2, dim2=-1).sqrt()
    got = df.particle_smoother(model, pf)
    assert float(((got.means - exact.means).abs() / sd).max()) < 1.0


def _bad_log_weights(L):
    nan = L.clone()
    nan[0, 2, 3] = float("nan")
    plus_inf = L.clone()
    plus_inf[1, 0, 0] = float("inf")
    return {
        "one step short": L[:, 1:],  # had been read shifted a step: 0.9 posterior sd off
        "integer": L.round().long(),
        "NaN": nan,
        "+inf": plus_inf,
        "other N": L[..., :40],
        "other runs": L[:1],
        "no run axis": L[0],
        "float32": L.float(),
    }


@pytest.mark.parametrize("case", list(_bad_log_weights(torch.zeros(3, 6, 50, dtype=F64))))
def test_log_weights_not_of_the_particles_are_named(filtered, case):
    model, pf = filtered
    bad = _bad_log_weights(pf.log_weights)[case]
    with pytest.raises(ValueError, match="log_weights"):
        df.particle_smoother(model, dataclasses.replace(pf, log_weights=bad))


def test_zero_weights_stay_allowed(filtered):
    model, pf = filtered
    L = pf.log_weights.clone()
    L[0, 3, 7] = float("-inf")  # a particle of zero weight: allowed, weighs nothing
    L[0, 3] = L[0, 3] - torch.logsumexp(L[0, 3], -1, keepdim=True)
    out = df.particle_smoother(model, dataclasses.replace(pf, log_weights=L))
    assert torch.isfinite(out.means).all()
    assert out.log_weights[0, 3, 7] == float("-inf")


def test_particles_of_no_step_axis_no_step_or_nan_are_named(filtered):
    model, pf = filtered
    P, L = pf.particles, pf.log_weights
    nan = P.clone()
    nan[0, 2, 3, 0] = float("nan")
    cases = [(P[0, 0], L[0, 0], "T, N, dx"), (P[:, :0], L[:, :0], "T >= 1"),
             (nan, L, "NaN")]  # fmt: skip
    for particles, log_w, words in cases:
        with pytest.raises(ValueError, match="filtered.particles") as err:
            df.particle_smoother(
                model, dataclasses.replace(pf, particles=particles, log_weights=log_w)
            )
        assert words in str(err.value)


def test_inputs_with_runs_the_filter_never_had_are_named():
    model = _model(dim_u=1)
    gen = torch.Generator().manual_seed(1)
    us = torch.randn(4, 5, 1, dtype=F64, generator=gen)
    _, ys, _ = model.simulate(5, (4,), us=us, generator=gen)
    one = df.particle_filter(model, ys[0], us[0], num_particles=30, return_particles=True,
                             generator=torch.Generator().manual_seed(2))  # fmt: skip
    four = df.particle_filter(model, ys, us, num_particles=30, return_particles=True,
                              generator=torch.Generator().manual_seed(2))  # fmt: skip
    for result, inputs in ((one, us), (one, us[:1]), (four, us.expand(2, 4, 5, 1))):
        with pytest.raises(ValueError, match="us's batch shape"):
            df.particle_smoother(model, result, inputs)
    # inputs shared by every run still broadcast to the runs
    shared = df.particle_smoother(model, four, us[0])
    each = df.particle_smoother(model, four, us[0].expand(4, 5, 1))
    torch.testing.assert_close(shared.means, each.means, rtol=0, atol=0)
