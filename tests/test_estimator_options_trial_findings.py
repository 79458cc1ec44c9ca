"""Findings of a trial of estimator options assigned after construction: a gated filter's
χ² detector (or its ``dim``) of another size, ``FusedLocals.groups``, and a learned
estimator's particle-filter settings on ``inner`` — each had been taken, half followed or
ignored without a word."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

import difffilter as df
from difffilter import Generators

F64 = torch.float64


def _model():
    t = lambda a: torch.tensor(a, dtype=F64)  # noqa: E731
    return df.LinearGaussianModel(t([[1.0, 0.1], [0.0, 0.95]]), t(np.eye(2)), t(1e-3 * np.eye(2)),
                                  t(1e-2 * np.eye(2)), torch.zeros(2, dtype=F64), t(np.eye(2)))  # fmt: skip


def test_a_gated_filters_chi_square_detector_of_another_size_assigned_since_init_is_named():
    from difffilter.fdi import ChiSquareDetector, GatedFilter

    model = _model()
    _, ys, _ = model.simulate(4, (2,), generator=torch.Generator().manual_seed(0))
    for change in ("dim", "detector"):
        gated = GatedFilter(ChiSquareDetector(2, 0.01), df.KalmanFilter())
        carry, _ = gated.step(gated.init(model, (2,)), ys[:, 0])
        if change == "dim":
            gated.detector.dim = 5
        else:
            gated.detector = ChiSquareDetector(5, 0.01)
        # (it had tested the 2-entry statistic against χ²₅: 15.09 for 9.21 at 1 %)
        with pytest.raises(ValueError, match=r"ChiSquareDetector\(dim=5\) tests a 5-entry"):
            gated.step(carry, ys[:, 1])


def test_fused_locals_groups_assigned_since_init_are_refused_at_the_next_step():
    from difffilter.fdi import AdaptiveParticleFilter
    from difffilter.models.robot import DEG, RobotModel
    from difffilter.models.robot_estimators import FusedLocals

    model, T = RobotModel(), 4
    us = torch.tensor([5.0, 5.0 * DEG], dtype=F64).expand(T, 2).clone()
    _, ys, _ = model.simulate(T, us=us, generator=torch.Generator().manual_seed(1))

    def gens():
        return Generators(*(torch.Generator().manual_seed(i) for i in range(3)))

    est = FusedLocals(AdaptiveParticleFilter(32))
    carry, _ = est.step(est.init(model, (), gens()), ys[0], us[0])
    est.groups = [[0, 1, 2], [3, 4, 5]]  # the same groups as lists: followed
    carry, _ = est.step(carry, ys[1], us[1])
    est.groups = ((3, 4, 5), (0, 1, 2))  # swapped: had been 120.8 m off
    with pytest.raises(ValueError, match="or its groups were assigned"):
        est.step(carry, ys[2], us[2])
    carry, _ = est.step(est.init(model, (), gens()), ys[2], us[2])  # a new carry: runs
    import pickle

    again = pickle.loads(pickle.dumps(carry))  # the groups travel with a copied carry
    est.groups = ((0, 1, 2), (3, 4, 5))
    with pytest.raises(ValueError, match="or its groups were assigned"):
        est.step(again, ys[3], us[3])


class _QuietNetwork(nn.Module):
    """One 2-channel area, no attack estimated, a low detection logit."""

    num_areas, area_dim, resid_dim, extra_inputs, detection_head = 1, 2, 2, 0, True

    def __init__(self):
        super().__init__()
        self.a, self.b = 2, 3
        self.V = nn.Parameter(torch.zeros(1, 1, 10, dtype=F64))

    def forward(self, delta, W=None, V=None):
        lead = delta.shape[:-2]
        return torch.zeros(lead + (1, 2), dtype=F64), torch.full(lead + (1,), -3.0, dtype=F64)

    def area_template(self):
        return nn.Linear(1, 1)

    def area_params(self):
        return {"W": self.V, "V": self.V}


@pytest.mark.parametrize("name, value", [("num_particles", 20), ("ess_threshold", 1.0)])
def test_a_learned_estimators_particle_filter_follows_its_inner_settings(name, value):
    from difffilter.models.learned_estimator import NeuralCompensation

    model = _model()
    _, ys, _ = model.simulate(6, generator=torch.Generator().manual_seed(1))

    def run(est):
        carry, means = est.init(model, (), generator=torch.Generator().manual_seed(3)), []
        for k in range(6):
            carry, out = est.step(carry, ys[k])
            means.append(out.mean)
        return torch.stack(means), carry

    assigned = NeuralCompensation(_QuietNetwork(), df.ParticleFilter(50))
    setattr(assigned.inner, name, value)  # after construction: had been ignored
    options = {"num_particles": 50, name: value}
    built = NeuralCompensation(_QuietNetwork(), df.ParticleFilter(**options))
    (a, carry_a), (b, carry_b) = run(assigned), run(built)
    assert carry_a.particles.shape == carry_b.particles.shape
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    if name == "num_particles":  # mid-run: a count other than the carry's is refused
        assigned.inner.num_particles = 30
        with pytest.raises(ValueError, match="particles"):
            assigned.step(carry_a, ys[0])


def _identity_model():
    eye = torch.eye(2, dtype=F64)
    return df.LinearGaussianModel(eye, eye, 0.01 * eye, 0.01 * eye, torch.zeros(2, dtype=F64), eye)


def test_a_poa_particle_filters_detector_and_literal_assigned_since_built():
    from difffilter.fdi.modified_pf import PoAParticleFilter
    from difffilter.fdi.poa import PoADetector

    pf = PoAParticleFilter(50, PoADetector(0.3, 0.2))
    carry = pf.init(_identity_model(), generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="detector must be a PoADetector; got dict"):
        pf.detector = {"eta": 0.3, "zeta": 0.2}  # (taken; the next step: a bare AttributeError)
    pf.detector = PoADetector(0.5, 0.1)  # a detector: followed
    _, out = pf.step(carry, torch.zeros(2, dtype=F64))
    assert out.threshold == 0.1
    with pytest.raises(AttributeError, match="literal is built into the filter's likelihood"):
        pf.literal = True  # (the score had followed it, the weights not: 0.42 off)
    with pytest.raises(ValueError, match="literal must be True or False"):
        PoAParticleFilter(50, PoADetector(0.3, 0.2), literal="no")


def test_a_modified_particle_filters_attack_rate_assigned_since_built_is_the_weightings():
    from difffilter.fdi.modified_pf import ModifiedParticleFilter
    from difffilter.fdi.poa import PoADetector, RunningAttackRate

    model, gamma = _identity_model(), torch.zeros(5, 2, dtype=F64)

    def first_threshold(pf):
        carry = pf.init(model, generator=torch.Generator().manual_seed(0))
        return float(pf.step(carry, torch.zeros(2, dtype=F64))[1].threshold)

    assigned = ModifiedParticleFilter(50, PoADetector(0.3, 0.2), gamma)
    assigned.attack_rate = RunningAttackRate(50, alpha0=0.9)  # (a new attribute, unread)
    assert assigned.likelihood.attack_rate is assigned.attack_rate
    built = ModifiedParticleFilter(50, PoADetector(0.3, 0.2), gamma,
                                   attack_rate=RunningAttackRate(50, alpha0=0.9))  # fmt: skip
    assert first_threshold(assigned) == first_threshold(built) == pytest.approx(0.9 * 49 / 50)
    with pytest.raises(ValueError, match="attack_rate must be a RunningAttackRate or None"):
        assigned.attack_rate = 0.3
    assigned.base_likelihood = None
    assert assigned.likelihood.base is None


def test_a_fixed_gain_of_another_shape_assigned_between_steps_is_named():
    from difffilter.observers import FixedGainFilter

    F = torch.tensor([[1.0, 0.1], [0.0, 0.9]], dtype=F64)
    H = torch.tensor([[1.0, 0.0]], dtype=F64)
    eye = torch.eye(2, dtype=F64)
    model = df.LinearGaussianModel(F, H, 0.01 * eye, 0.01 * torch.eye(1, dtype=F64),
                                   torch.zeros(2, dtype=F64), eye)  # fmt: skip
    observer = FixedGainFilter(torch.tensor([[0.5], [0.2]], dtype=F64))
    carry, _ = observer.step(observer.init(model), torch.tensor([0.4], dtype=F64))
    observer.gain = torch.tensor([[0.3]], dtype=F64)  # [1, 1] had broadcast to both states
    with pytest.raises(ValueError, match=r"gain must have shape \[2, 1\]; got \(1, 1\)"):
        observer.step(carry, torch.tensor([1.0], dtype=F64))


def test_a_mixture_particle_filters_cov_dims_is_its_whole_sequence_runs_too():
    from difffilter.fdi.mixture import (
        DeceptionMixtureLikelihood,
        MixtureParticleFilter,
        ReplacementDeception,
    )
    from difffilter.loop import open_loop
    from difffilter.noise import Gaussian

    model = _identity_model()
    _, ys, _ = model.simulate(6, generator=torch.Generator().manual_seed(0))
    deception = ReplacementDeception(
        Gaussian(torch.zeros(2, dtype=F64), 4 * torch.eye(2, dtype=F64))
    )
    pf = MixtureParticleFilter(32, DeceptionMixtureLikelihood(0.1, deception))
    pf.cov_dims = 1  # (the tabulated fast path had dropped it: covs [T, 2, 2])
    gens = Generators(*(torch.Generator().manual_seed(s) for s in (1, 2, 3)))
    assert open_loop(pf, model, ys, generator=gens).covs.shape == (6, 1, 1)


def test_the_tracking_per_sensor_likelihood_follows_its_rate_assigned_since_built():
    import math

    from difffilter.models.tracking import PerSensorDeception, TrackingModel

    model = TrackingModel()
    x = torch.tensor([20.0, 0.3, 20.0, 0.3], dtype=torch.float32)
    gen = torch.Generator().manual_seed(0)
    particles = x + torch.randn(30, 4, generator=gen) * torch.tensor([1.0, 0.01, 1.0, 0.01])
    y = model.observe(x, 1) + torch.tensor([1.0, 0.01] * 4)
    y[2] = 50.0  # sensor 2's range replaced
    low, high = (-10.0, -math.pi / 2), (80.0, math.pi / 2)
    assigned = PerSensorDeception(0.2, low, high, 4)
    assigned.rate = 0.6  # (its log terms had been computed when built: 2.67 off)
    built = PerSensorDeception(0.6, low, high, 4)
    mask = torch.ones(8, dtype=torch.bool)
    mask[3] = False
    for m in (None, mask):
        torch.testing.assert_close(assigned(model, y, particles, 1, m), built(model, y, particles, 1, m),
                                   rtol=0, atol=0)  # fmt: skip
    with pytest.raises(ValueError, match=r"rate .* must lie in \[0, 1\]; got 1.5"):
        assigned.rate = 1.5
    assigned.high = torch.tensor([-20.0, 2.0])  # below low: named at the next use
    with pytest.raises(ValueError, match="low below high"):
        assigned(model, y, particles, 1, None)


def test_a_learned_estimators_attach_and_init_read_inner_as_it_is_now():
    """A review: ``attach`` had kept the count built in (refusing the 20 particles init made
    after ``inner.num_particles = 20``); an ``on_loss="hold"`` assigned to an inner filter
    the constructor would refuse ran."""
    from difffilter.expected_input import ExpectedInputKalmanFilter
    from difffilter.models.learned_estimator import NeuralCompensation
    from difffilter.particle import particle_init

    model = _model()
    est = NeuralCompensation(_QuietNetwork(), df.ParticleFilter(50))
    est.inner.num_particles = 20
    gens = Generators(*(torch.Generator().manual_seed(s) for s in (1, 2, 3)))
    state = particle_init(model, 20, (), torch.Generator().manual_seed(0))
    assert est.attach(state, model, gens).particles.shape == (20, 2)
    with pytest.raises(ValueError, match="20 particles"):
        est.attach(particle_init(model, 50, (), torch.Generator().manual_seed(0)), model, gens)
    eye = torch.eye(2, dtype=F64)
    actuated = df.LinearGaussianModel(eye, eye, 0.01 * eye, 0.01 * eye, torch.zeros(2, dtype=F64),
                                      eye, B=eye)  # fmt: skip
    inner = ExpectedInputKalmanFilter(0.9)
    est = NeuralCompensation(_QuietNetwork(), inner)
    inner.on_loss = "hold"
    with pytest.raises(ValueError, match=r"carry holds more than the state \(on held inputs"):
        est.init(actuated, ())


def test_a_fused_modified_particle_filter_refuses_a_rate_or_likelihood_assigned_later():
    from difffilter.fdi.modified_pf import ModifiedParticleFilter
    from difffilter.fdi.poa import PoADetector, RunningAttackRate
    from difffilter.particle import ModelLikelihood

    pf = ModifiedParticleFilter(50, PoADetector(0.3, 0.2), torch.zeros(5, 2, dtype=F64), fused=True)
    with pytest.raises(ValueError, match="fused=True does not support attack_rate"):
        pf.attack_rate = RunningAttackRate(50, alpha0=0.9)
    with pytest.raises(ValueError, match="fused=True does not support base_likelihood"):
        pf.base_likelihood = ModelLikelihood()
    assert pf.attack_rate is None and pf.base_likelihood is None


def test_attach_on_a_learned_estimator_over_a_gaussian_filter_is_named():
    """``attach`` takes particles (particle filter only, its docstring): over a Kalman filter it
    had failed with a bare ``AttributeError: 'NeuralCompensation' object has no attribute
    'pf'``."""
    from difffilter.models.learned_estimator import NeuralCompensation
    from difffilter.particle import particle_init

    model = _model()
    est = NeuralCompensation(_QuietNetwork(), df.KalmanFilter())
    state = particle_init(model, 20, (), torch.Generator().manual_seed(0))
    with pytest.raises(TypeError, match="this one's inner is a KalmanFilter: start its carry"):
        est.attach(state, model, Generators())


def test_a_nan_threshold_is_refused_by_detection():
    """``Detection(threshold=nan)`` had been taken: no score exceeds it, and the report read
    the threshold as null (noted last session). ``None`` says there is none."""
    from difffilter.estimator import Detection, stack_steps

    scores = torch.zeros(2, 3)
    for nan in (float("nan"), np.float64("nan")):
        with pytest.raises(ValueError, match="threshold must be a number, not NaN"):
            Detection(scores, scores > 0, nan)
    assert Detection(scores, scores > 0, None).threshold is None
    # nor as a tensor, nor stacked from steps that each gave NaN (a review)
    for nan in (torch.tensor(float("nan")), torch.full((2, 3), float("nan")),
                torch.tensor([0.5, float("nan"), 0.5])):  # fmt: skip
        with pytest.raises(ValueError, match="threshold must not hold NaN"):
            Detection(scores, scores > 0, nan)
    steps = [df.StepOutput(torch.zeros(2, 1), score=torch.zeros(2), alarm=torch.zeros(2) > 0,
                           threshold=float("nan")) for _ in range(3)]  # fmt: skip
    with pytest.raises(ValueError, match="threshold must not hold NaN"):
        stack_steps(steps, torch.Size([2]))


def test_an_arrival_rate_of_a_0d_numpy_array_is_taken_as_a_0d_tensor_is():
    """A 0-d tensor was taken as the rate and a 0-d numpy array (``np.array(0.9)``) refused
    (a trial); a boolean or a string is refused either way."""
    from difffilter.expected_input import ExpectedInputKalmanFilter

    for rate in (np.array(0.9), torch.tensor(0.9, dtype=F64), 0.9):
        assert float(ExpectedInputKalmanFilter(rate).arrival_rate) == 0.9
    for bad in (np.array(True), np.array("0.9"), np.array(1.5)):
        with pytest.raises(ValueError, match="arrival_rate must"):
            ExpectedInputKalmanFilter(bad)
