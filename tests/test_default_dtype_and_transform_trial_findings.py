"""Findings of red-team trials of the global default dtype and of gradients through this
session's code: numbers given as lists rounded to a float32 default, the four-tank caches
under torch.func, and the adaptive KF's attack_cov0 gradient. Each test failed on the code
before its fix."""

from __future__ import annotations

import torch

import difffilter as df

D = torch.float64


def _with_default(dtype, fn):
    previous = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        return fn()
    finally:
        torch.set_default_dtype(previous)


def test_a_deception_vector_given_as_a_list_keeps_float64():
    # under the float32 default a list ρ had been rounded first: means 6e-9 off
    from difffilter.fdi.mixture import BiasDeception

    rho = [0.1, 0.3]
    low = _with_default(torch.float32, lambda: BiasDeception(rho).rho)
    high = _with_default(torch.float64, lambda: BiasDeception(rho).rho)
    assert torch.equal(low.to(D), high.to(D))
    assert low.dtype == torch.float64


def test_a_poa_threshold_of_a_list_r_does_not_hang_on_the_default_dtype():
    # η had been 0.2250000022 under the float32 default for 0.2250000000
    from difffilter.fdi.poa import poa_detector_for

    eye = torch.eye(2, dtype=D)
    model = df.LinearGaussianModel(
        0.9 * eye, eye, 0.1 * eye, 0.1 * eye, torch.zeros(2, dtype=D), eye
    )
    R = [[0.1, 0.0], [0.0, 0.1]]
    low = _with_default(
        torch.float32,
        lambda: poa_detector_for(model, gamma_min=0.3, p_l=0.2, num_particles=100, R=R),
    )
    high = _with_default(
        torch.float64,
        lambda: poa_detector_for(model, gamma_min=0.3, p_l=0.2, num_particles=100, R=R),
    )
    assert float(low.eta) == float(high.eta)


def test_a_four_tank_model_built_under_torch_func_filters():
    # its caches had read data_ptr() of wrapped tensors: "Cannot access data pointer"
    from difffilter.models.four_tank import FourTankModel

    ys = FourTankModel(dtype=D).simulate(5, (2,), generator=torch.Generator().manual_seed(0))[1]

    def loss(scale):
        model = FourTankModel(dtype=D)
        model.step_offset = model.step_offset * scale  # (a plant parameter under the transform)
        return df.extended_kalman_filter(model, ys).log_likelihood.sum()

    one = torch.tensor(1.0, dtype=D)
    got = torch.func.grad(loss)(one)
    h = 1e-6
    want = (loss(one + h) - loss(one - h)) / (2 * h)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


def test_the_adaptive_kfs_attack_cov0_carries_its_gradient():
    # made a number, its gradient had been dropped: 0 for −0.756
    from difffilter.fdi.adaptive_kf import adaptive_kalman_filter

    eye = torch.eye(2, dtype=D)
    model = df.LinearGaussianModel(
        0.9 * eye, eye, 0.1 * eye, 0.2 * eye, torch.zeros(2, dtype=D), eye, B=eye
    )
    g = torch.Generator().manual_seed(0)
    ys, us = torch.randn(2, 8, 2, generator=g, dtype=D), torch.randn(2, 8, 2, generator=g, dtype=D)

    def loss(omega):
        return (
            adaptive_kalman_filter(model, ys, us, attack_cov0=omega).extras["log_likelihood"].sum()
        )

    omega = torch.tensor(0.7, dtype=D, requires_grad=True)
    (got,) = torch.autograd.grad(loss(omega), omega)
    h = 1e-6
    want = (loss(torch.tensor(0.7 + h, dtype=D)) - loss(torch.tensor(0.7 - h, dtype=D))) / (2 * h)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-7)
    assert float(got) != 0.0
