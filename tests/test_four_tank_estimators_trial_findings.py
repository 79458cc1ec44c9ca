"""Findings of a red-team trial of the four-tank estimators (2026-12-06)."""

from __future__ import annotations

import pytest
import torch

from difffilter import fdi
from difffilter.models.four_tank import R_HIGH, FourTankModel, FourTankScenario
from difffilter.models.four_tank_estimators import linearised_four_tank

D = torch.float64


def test_the_fused_modified_pf_takes_a_full_process_noise():
    # a non-diagonal Q had failed on a missing attribute in the small-set propagation
    Q = torch.tensor([[1e-4, 3e-5, 0, 0], [3e-5, 1e-4, 0, 0], [0, 0, 1e-4, 0], [0, 0, 0, 1e-4]],
                     dtype=D)  # fmt: skip
    model = FourTankModel(Q=Q, dtype=D)
    ys = model.initial.mean.expand(2, 5, 4).clone()

    def run(fused):
        return fdi.modified_particle_filter(
            model, ys, num_particles=8, detector=fdi.PoADetector(0.233, 0.5),
            gamma_hat=torch.zeros(2, 5, 4, dtype=D), fused=fused,
            generator=torch.Generator().manual_seed(1),
            resample_generator=torch.Generator().manual_seed(2),
        )  # fmt: skip

    assert torch.allclose(run(True).means, run(False).means, rtol=0, atol=1e-12)


def test_the_theorem_1_estimator_is_skipped_where_eq_53_has_no_zeta():
    # its option was read before the detector that skips: a bare KeyError ended the suite
    from eval.suite import run_suite

    scenario = FourTankScenario(name="ft_hi_pl", R=R_HIGH, p_l=0.995, steps=10, runs=2,
                                num_particles=20)  # fmt: skip
    result = run_suite(scenario, runs=2, estimators=("modified_pf_eta_theorem1",), progress=False)
    assert "no PoA threshold" in result.skipped["modified_pf_eta_theorem1"]


def test_the_linearisation_is_at_the_fixed_point_with_the_prior_as_a_deviation():
    x0 = (10.0, 11.0, 2.0, 1.0)
    model = FourTankModel(x0=x0, dtype=D)
    lin, x_star = linearised_four_tank(model)
    # the prior mean had been taken for x*: no equilibrium, and a prior deviation of 0
    assert torch.allclose(model.continuous_rhs(x_star), torch.zeros(4, dtype=D), atol=1e-12)
    assert torch.equal(x_star, torch.tensor(model.params.fixed_point(), dtype=D))
    assert torch.equal(lin.initial.mean, torch.tensor(x0, dtype=D) - x_star)
    # the default prior is the fixed point: a deviation of zero, as before
    default, at = linearised_four_tank(FourTankModel(dtype=D))
    assert torch.equal(default.initial.mean, torch.zeros(4, dtype=D))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"R": torch.eye(3) * 1e-3}, r"R must have shape \[\.\.\., 4, 4\]"),
        ({"Q": torch.eye(5) * 1e-4}, r"Q must have shape \[\.\.\., 4, 4\]"),
        ({"R": -1e-3 * torch.eye(4)}, "R must be positive definite"),
        ({"P0": torch.ones(4, 4)}, "P0 must be positive definite"),
        ({"P0": torch.eye(4).expand(2, 4, 4)}, r"P0 must be a number, 4 variances or a \[4, 4\]"),
    ],
)
def test_the_plant_names_a_bad_covariance(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FourTankModel(dtype=D, **kwargs)


@pytest.mark.parametrize("bad", [(-5e-5,) * 4, (0.0,) * 4])
def test_the_design_r_of_the_poa_threshold_is_checked_as_a_covariance(bad):
    """A negative or zero ``eta_design_R`` (a sign typo) set η = 0.28 or 0 (every step an
    alarm) without a word, where the same values as the scenario's ``R`` are refused."""
    import dataclasses

    from difffilter.models import registry

    scenario = registry.get("four_tank_bias")
    assert scenario.estimator_options()["poa_eta"] == pytest.approx(0.23333, abs=1e-4)
    with pytest.raises(ValueError, match="eta_design_R must be positive definite"):
        dataclasses.replace(scenario, eta_design_R=bad)
    G = torch.eye(4, dtype=torch.float64)
    with pytest.raises(ValueError, match="R must be positive definite"):
        fdi.modified_pf_gain(G, 1e-4 * G, torch.diag(torch.tensor(bad, dtype=torch.float64)))
