"""The threat library (a red-team trial, 2026-12-07; each test failed before its fix, the
coverage test wherever the two spellings differ)."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.models import registry
from difffilter.threat_distribution import ThreatDistribution
from difffilter.threats import KSigmaBias, threat_from_dict

F64 = torch.float64


def test_a_k_sigma_bias_of_a_model_of_one_r_per_run_is_refused():
    """``σ = √diag R`` of the first run was taken for every run: 2 σ in run 0, 1 σ in run
    1, 0.67 σ in run 2 for ``k = 2``, without a word."""
    R = torch.stack(
        [torch.diag(torch.tensor([1.0, 4.0], dtype=F64)) * (i + 1) ** 2 for i in range(3)]
    )
    eye = torch.eye(2, dtype=F64)
    model = df.LinearGaussianModel(0.9 * eye, eye, 0.01 * eye, R, torch.zeros(2, dtype=F64), eye)
    with pytest.raises(ValueError, match="differs between its runs"):
        KSigmaBias.of(model, 2.0)
    with pytest.raises(ValueError, match="differs between its runs"):
        threat_from_dict({"kind": "ksigma_bias", "k": 2.0, "onset": 1}, model=model)
    # one R for every run, given per run: one σ, as before
    same = df.LinearGaussianModel(0.9 * eye, eye, 0.01 * eye, R[:1].expand(3, 2, 2),
                                  torch.zeros(2, dtype=F64), eye)  # fmt: skip
    assert KSigmaBias.of(same, 2.0).sigma == (1.0, 2.0)


@pytest.mark.parametrize("trained", ["SENSOR", "Sensor", "sensor"])
@pytest.mark.parametrize("threat", [None, "sensor", "SENSOR"])
def test_a_channel_spelt_another_way_is_the_same_channel_in_training_coverage(trained, threat):
    """A training distribution with ``channel: SENSOR`` and a threat that leaves the channel
    out (the same attack, built the same) read "kind only" in the robustness report's "in
    training" column: the fields were compared as written."""
    model = registry.get("four_tank_bias").system()
    drawn = {"kind": "ramp", "slope": {"uniform": [0.002, 0.03]}, "onset": 21, "channel": trained}
    dist = ThreatDistribution({"ramp": {"weight": 1.0, **drawn}}, model=model)
    spec = {"kind": "ramp", "slope": 0.005, "onset": 21}
    if threat is not None:
        spec["channel"] = threat
    assert threat_from_dict(spec, model) == threat_from_dict({**drawn, "slope": 0.005}, model)
    assert dist.covers(spec) == "within"
    assert dist.covers({**spec, "channel": "actuator", "entries": [0]}) != "within"
