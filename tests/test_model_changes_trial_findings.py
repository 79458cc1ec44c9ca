"""Findings of a trial of models changed under the filters (each failed before its fix):
a change after construction is followed, as a model built with it, or refused by name."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter import fdi
from difffilter.loop import open_loop
from difffilter.models.lfc import LFCPlant
from difffilter.models.tracking import TrackingModel

D = torch.float64


def _model(Q=None, R=None, B=True):
    return df.LinearGaussianModel(
        torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=D), torch.tensor([[1.0, 0.0]], dtype=D),
        (torch.diag(torch.tensor([0.01, 0.02], dtype=D)) if Q is None else Q).clone(),
        (torch.tensor([[0.1]], dtype=D) if R is None else R).clone(),
        torch.tensor([0.5, -0.2], dtype=D), torch.eye(2, dtype=D),
        B=torch.tensor([[0.0], [0.1]], dtype=D) if B else None,
    )  # fmt: skip


def _data():
    g = torch.Generator().manual_seed(0)
    _, ys, _ = _model().simulate(20, (3,), generator=g)
    return ys, torch.randn(3, 20, 1, generator=g, dtype=D)


def _apf_means(est, model):
    ys, us = _data()
    return open_loop(est, model, ys, us, generator=torch.Generator().manual_seed(1)).means


@pytest.mark.parametrize("which", ["R", "Q"])
def test_the_adaptive_pf_follows_noise_given_new_storage(which):
    """``R.data = new`` keeps the tensor and its version: the information form's constants
    had been kept, the old noise filtered on (1.56 off a model built with the new one)."""
    new = {
        "R": torch.tensor([[0.4]], dtype=D),
        "Q": torch.diag(torch.tensor([0.05, 0.01], dtype=D)),
    }
    est, model = fdi.AdaptiveParticleFilter(32), _model()
    _apf_means(est, model)
    noise = model.measurement_noise if which == "R" else model.process_noise
    noise._cov.data = new[which].clone()
    fresh = _apf_means(fdi.AdaptiveParticleFilter(32), _model(**{which: new[which]}))
    torch.testing.assert_close(_apf_means(est, model), fresh, rtol=0, atol=1e-12)


def test_the_adaptive_pf_leaves_the_information_form_when_r_wants_a_gradient():
    """The key held the gradient flags but compared only the versions: ``requires_grad_()``
    after a first run kept the information form, and the loss had no gradient to R."""
    est, model = fdi.AdaptiveParticleFilter(32), _model()
    _apf_means(est, model)
    model.measurement_noise._cov.requires_grad_()
    (grad,) = torch.autograd.grad(
        _apf_means(est, model).square().sum(), model.measurement_noise._cov
    )
    assert bool(torch.isfinite(grad).all()) and float(grad.abs().sum()) > 0


def test_the_tracking_sampler_follows_its_process_noise_written_in_place():
    """The fast sampler drew with the factor made at construction: Q written in place (4×)
    drew the old variances, and ``simulate`` was 0.515 off a model built with the new Q."""
    edited, fresh = TrackingModel(), TrackingModel(sigma_omega=0.11)
    with torch.no_grad():
        edited.process_noise._cov.mul_(4.0)
    torch.testing.assert_close(edited.process_cov(0), fresh.process_cov(0), rtol=1e-12, atol=0)
    draws = [
        m.simulate(5, (3,), generator=torch.Generator().manual_seed(0))[0] for m in (edited, fresh)
    ]
    torch.testing.assert_close(draws[0], draws[1], rtol=1e-10, atol=1e-12)


def test_a_linear_models_matrices_assigned_later_are_checked_and_b_sets_the_inputs():
    """F, H or B of another shape or dtype had been taken (the filters failing in torch's
    words, the UKF running on a broadcast), ``B = None`` crashed the Kalman filter in
    ``torch.pad``, and a B of another width left ``dim_u`` stale."""
    model = _model()
    for name, value, match in (
        ("H", torch.eye(2, dtype=D), r"H must have shape \[\.\.\., 1, 2\]"),
        ("F", torch.eye(3, dtype=D), r"F must have shape \[\.\.\., 2, 2\]"),
        ("F", torch.eye(2), "F is torch.float32 on cpu and the model torch.float64"),
        ("B", torch.ones(3, 1, dtype=D), r"B must have shape \[\.\.\., 2, du\]"),
        ("H", torch.tensor([[float("nan"), 0.0]], dtype=D), "H contains NaN"),
    ):
        with pytest.raises(ValueError, match=match):
            setattr(model, name, value)
    ys, us = _data()
    model.B = None
    assert model.dim_u == 0
    with pytest.raises(ValueError, match="us was given but the model has no input"):
        df.kalman_filter(model, ys, us)
    torch.testing.assert_close(
        df.kalman_filter(model, ys).means, df.kalman_filter(_model(B=False), ys).means
    )
    model.B = torch.ones(2, 2, dtype=D)
    assert model.dim_u == 2
    df.kalman_filter(model, ys, torch.ones(3, 20, 2, dtype=D))


def test_a_prior_mean_written_nan_is_refused_by_the_whole_sequence_filters():
    """``init`` refused it; ``open_loop`` and ``kalman_filter`` ran to NaN means."""
    model = _model()
    with torch.no_grad():
        model.initial.loc.fill_(float("nan"))
    ys, us = _data()
    for run in (
        lambda: df.kalman_filter(model, ys, us),
        lambda: open_loop(df.ExtendedKalmanFilter(), model, ys, us),
    ):
        with pytest.raises(
            ValueError, match="model.initial.mean \\(the prior mean m0\\) contains NaN"
        ):
            run()


def test_the_lfc_plants_sampling_time_is_read_only():
    """``LFCPlant.dt`` assigned later had been stored beside matrices discretised with the
    old one (F 1.7 off a plant built with it)."""
    plant = LFCPlant(dt=0.01)
    with pytest.raises(AttributeError):
        plant.dt = 0.001
    assert plant.dt == 0.01


def test_a_subclass_that_reads_its_own_tables_keeps_them():
    """The checks of F/H/B and the refusal of Q/R/m0/P0 apply where the model's own methods
    read them: a time-varying subclass whose ``process_cov`` reads a table ``self.Q`` and
    whose ``transition_matrix`` reads ``self.F`` per step keeps assigning them."""

    class TimeVarying(df.LinearGaussianModel):
        time_varying = True

        def transition_matrix(self, k):
            return self.F[min(k, len(self.F) - 1)]

        def process_cov(self, k):
            return self.Q[min(k, len(self.Q) - 1)]

    model = TimeVarying(torch.eye(2, dtype=D), torch.eye(2, dtype=D), torch.eye(2, dtype=D),
                        torch.eye(2, dtype=D), torch.zeros(2, dtype=D), torch.eye(2, dtype=D))  # fmt: skip
    model.F = torch.stack([torch.eye(2, dtype=D), 0.5 * torch.eye(2, dtype=D)])
    model.Q = [0.1 * torch.eye(2, dtype=D)] * 3
    assert torch.equal(model.transition_matrix(1), 0.5 * torch.eye(2, dtype=D))
    ys = torch.ones(1, 2, 2, dtype=D)
    # step 1 by hand: m⁻ = F₀ m₀ = 0, P⁻ = F₀ P₀ F₀ᵀ + Q₀ = 1.1 I, K = 1.1/2.1, m₁ = K·1
    torch.testing.assert_close(df.kalman_filter(model, ys).means[0, 0],
                               torch.full((2,), 1.1 / 2.1, dtype=D), rtol=1e-12, atol=0)  # fmt: skip
