"""A scenario of one's own draws its runs' initial states from the estimators' prior where
it says so (``random_initial``), and starts them at the prior's mean otherwise."""

from __future__ import annotations

import pytest
import torch


def test_a_scenario_of_ones_own_may_draw_its_initial_states_from_the_prior(isolated_registry):
    """``random_initial`` (Python and YAML): each run's ``x_0 ~ N(m₀, P₀)``, drawn from the
    plant's stream (the sample mean and covariance of 4,000 runs within a few standard
    errors of m₀ = (1, −2), P₀ = diag(0.04, 0.09)); by default every run starts at m₀ (a
    trial's own re-simulation drew x_0 and its attack-free error came out 5 % off). The
    attack-free key tells the two apart (their calibrations are not shared)."""
    from difffilter.models.streams import Streams
    from difffilter.models.yaml_scenario import scenario_from_dict

    doc = {"name": "drawn", "steps": 3, "plant": {"F": [[0.9, 0.0], [0.0, 0.8]],
           "H": [[1.0, 0.0]], "Q": 1.0e-4, "R": 1.0e-2, "m0": [1.0, -2.0], "P0": [0.04, 0.09]}}  # fmt: skip
    fixed = scenario_from_dict(doc)
    drawn = scenario_from_dict({**doc, "random_initial": True})
    gens = lambda: Streams(0).simulation()  # noqa: E731
    x0 = drawn.simulate(4000, gens()).info["x0"]
    torch.testing.assert_close(x0.mean(0), torch.tensor([1.0, -2.0], dtype=torch.float64),
                               atol=4 * 0.3 / 4000**0.5, rtol=0)  # fmt: skip
    cov = torch.cov(x0.T)
    torch.testing.assert_close(cov.diagonal(), torch.tensor([0.04, 0.09], dtype=torch.float64),
                               rtol=0.1, atol=0)  # fmt: skip
    assert abs(float(cov[0, 1])) < 4 * (0.04 * 0.09 / 4000) ** 0.5
    assert (fixed.simulate(5, gens()).info["x0"] == torch.tensor([1.0, -2.0])).all()
    assert drawn.attack_free_key() != fixed.attack_free_key() == ("drawn", 3)
    with pytest.raises(ValueError, match="random_initial must be true or false; got 'yes'"):
        scenario_from_dict({**doc, "random_initial": "yes"}, "f.yaml")
