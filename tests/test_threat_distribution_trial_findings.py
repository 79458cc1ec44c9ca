"""Findings of a red-team trial of the training distribution of attacks and its coverage
labels (each failed before its fix)."""

from __future__ import annotations

import json
from collections import Counter

import pytest
import torch

from difffilter.eval.coverage import training_coverage
from difffilter.models import registry
from difffilter.threat_distribution import KIND_ONLY, WITHIN, ThreatDistribution
from difffilter.threats import threat_from_dict


def _card(tmp_path, threats):
    checkpoint = tmp_path / "net.ckpt"
    checkpoint.write_text("")
    checkpoint.with_suffix(".json").write_text(
        json.dumps({"data_config": {"threats": threats}, "model_config": {}})
    )
    return checkpoint


def test_a_channel_drawn_by_choice_is_covered_option_by_option(tmp_path):
    """covers() read the channel's choice as one Channel and failed: the robustness study
    of a network trained on such a distribution died at its end."""
    sc = registry.get("four_tank_bias")
    threats = {"own": {"weight": 0.5},
               "bias": {"weight": 0.5, "kind": "bias", "value": 0.5, "onset": 3,
                        "channel": {"choice": ["sensor", "replacement"]}}}  # fmt: skip
    d = ThreatDistribution(threats, model=sc.system(), own=sc.attack_model())
    assert d.covers({"kind": "bias", "value": 0.5, "onset": 3}) == WITHIN
    assert d.covers({"kind": "bias", "value": 0.5, "onset": 3, "channel": "replacement"}) == WITHIN
    assert d.covers({"kind": "bias", "value": 0.5, "onset": 4}) == KIND_ONLY
    labels = training_coverage(_card(tmp_path, threats), {"b": {"kind": "bias", "value": 0.5, "onset": 3}},
                               sc.system(), own=sc.attack_model())["threats"]  # fmt: skip
    assert labels == {"b": WITHIN}


def test_coverage_fills_the_scenarios_sampling_period_and_the_models_sigma(tmp_path):
    """A field left out was compared as the class's default where training and the study
    fill it in: the very sinusoid trained on read "kind only", one at 20× another frequency
    "within"; ksigma_bias at the model's own σ "kind only", at σ = 1 "within"."""
    sc = registry.get("lfc_sine")
    model, own = sc.system(), sc.attack_model()
    spec = {"kind": "sinusoid", "amplitude": 0.3, "omega": 2.0, "onset": 20}
    trained = {"s": {"weight": 1.0, **{**spec, "omega": {"uniform": [1.0, 3.0]}}}}
    checkpoint = _card(tmp_path, trained)
    for dt, label in ((sc.dt, WITHIN), (20 * sc.dt, KIND_ONLY)):
        got = training_coverage(checkpoint, {"t": {**spec, "dt": dt}}, model, own=own, dt=sc.dt)
        assert got["threats"]["t"] == label, dt
    assert (
        training_coverage(checkpoint, {"t": spec}, model, own=own, dt=sc.dt)["threats"]["t"]
        == WITHIN
    )

    tank = registry.get("four_tank_bias").system()
    sigma = [float(s) for s in threat_from_dict({"kind": "ksigma_bias"}, model=tank).sigma]
    d = ThreatDistribution({"k": {"weight": 1, "kind": "ksigma_bias", "k": {"uniform": [1, 3]},
                                  "onset": 21}}, model=tank)  # fmt: skip
    assert d.covers({"kind": "ksigma_bias", "k": 1.5, "onset": 21, "sigma": sigma}) == WITHIN
    assert d.covers({"kind": "ksigma_bias", "k": 1.5, "onset": 21, "sigma": 1.0}) == KIND_ONLY


def test_a_number_covers_the_vector_of_it_on_every_entry():
    """Bias(value=0.5) and Bias(value=[0.5]*4) are one attack; the constant and choice
    cases compared their lengths."""
    tank = registry.get("four_tank_bias").system()
    for trained in (0.5, {"choice": [0.5, 1.0]}, [0.5] * 4):
        d = ThreatDistribution({"b": {"weight": 1, "kind": "bias", "value": trained, "onset": 5}},
                               model=tank)  # fmt: skip
        for study in (0.5, [0.5] * 4):
            assert d.covers({"kind": "bias", "value": study, "onset": 5}) == WITHIN, (
                trained,
                study,
            )
        assert d.covers({"kind": "bias", "value": [0.5, 0.5, 0.5, 0.6], "onset": 5}) == KIND_ONLY


def test_weights_whose_sum_overflows_draw_their_shares():
    """Three weights of 1e308 (each finite) drew shares of 0.47, 0.31 and 0.22."""
    d = ThreatDistribution({"b": {"weight": 1e308, "kind": "bias"}, "none": {"weight": 1e308},
                            "own": {"weight": 1e308}})  # fmt: skip
    g = torch.Generator().manual_seed(0)
    shares = Counter(d.sample(g)[0] for _ in range(3000))
    assert all(abs(n / 3000 - 1 / 3) < 0.04 for n in shares.values()) and len(shares) == 3


@pytest.mark.parametrize("signed", [True, "no"])
def test_signed_on_a_choice_is_refused_as_on_randint(signed):
    """A second trial: ``{choice: [0.5, 1.0], signed: true}`` had been taken and drawn with
    one sign only (no negative value in 2,000 draws); choice returned before the check."""
    entry = {"weight": 1, "kind": "bias", "value": {"choice": [0.5, 1.0], "signed": signed}}
    with pytest.raises(ValueError, match="signed applies to uniform and loguniform only"):
        ThreatDistribution({"b": entry})
    entry["value"] = {"uniform": [0.5, 1.0], "signed": True}  # where it belongs: both signs
    g = torch.Generator().manual_seed(0)
    draws = [ThreatDistribution({"b": entry}).sample(g)[1].value[0] for _ in range(200)]
    assert 60 < sum(v < 0 for v in draws) < 140
