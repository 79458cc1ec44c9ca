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
