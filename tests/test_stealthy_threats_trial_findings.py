"""Findings of a red-team trial of the crafted, replayed and covert attacks: their arguments
and defaults. Each test failed on the code before its fix."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.stealthy import attacked_pairs
from difffilter.threats import (
    Covert,
    KSigmaBias,
    Ramp,
    Replay,
    check_attack_fits,
    threat_from_dict,
)

F64 = torch.float64


def _linear(dx: int, dy: int, du: int) -> df.LinearGaussianModel:
    g = torch.Generator().manual_seed(dx * 10 + dy)
    return df.LinearGaussianModel(0.5 * torch.eye(dx, dtype=F64), torch.randn(dy, dx, generator=g, dtype=F64),
                                  0.01 * torch.eye(dx, dtype=F64), 0.04 * torch.eye(dy, dtype=F64),
                                  torch.zeros(dx, dtype=F64), torch.eye(dx, dtype=F64),
                                  B=torch.ones(dx, du, dtype=F64))  # fmt: skip


@pytest.mark.parametrize("other,what", [((2, 2, 1), "dim_x"), ((3, 2, 2), "dim_u")])
def test_a_covert_attackers_model_of_other_sizes_is_refused_before_the_run(other, what):
    # (it had failed inside Covert.step: "mat1 and mat2 shapes cannot be multiplied")
    attack = Covert(Ramp(0.2, channel="actuator", onset=3), _linear(*other))
    with pytest.raises(ValueError, match=f"covert attack's plant has {what}"):
        check_attack_fits(attack, _linear(3, 2, 1), 10)
    check_attack_fits(
        Covert(Ramp(0.2, channel="actuator", onset=3), _linear(3, 2, 1)), _linear(3, 2, 1), 10
    )


@pytest.mark.parametrize("kwargs,match", [
    ({"onset": 0}, "onset must be an integer >= 1"),
    ({"onset": 2.5}, "onset must be an integer >= 1"),
    ({"entries": [-1], "mask": torch.ones(2, 5, 2, dtype=torch.bool)}, r"entries must be distinct .* in \[0, 2\)"),
    ({"mask": torch.ones(3, 5, 2, dtype=torch.bool)}, "mask must hold runs = 2 and steps = 5"),
])  # fmt: skip
def test_attacked_pairs_names_its_arguments(kwargs, match):
    # onset 0 had marked every step attacked, entries [-1] the last entry
    args = {"runs": 2, "steps": 5, "onset": 3, **kwargs}
    with pytest.raises(ValueError, match=match):
        attacked_pairs(**args)
    mask = torch.tensor([True, False]).expand(2, 5, 2).clone()
    pairs = attacked_pairs(2, 5, 3, entries=[1], mask=mask)
    assert not pairs.any()  # (entry 1 never received)
    assert attacked_pairs(2, 5, 3).tolist() == [[False, False, True, True, True]] * 2


def test_a_seamless_replay_of_a_short_recording_says_its_default_window_needs_more():
    # its own default (5) had been refused for a delay of 3 as a level_window the caller never
    # set; a default of the whole recording (w = d) would estimate no gap at all (a review)
    phi, C = 0.9 * torch.eye(2, dtype=F64), torch.eye(2, dtype=F64)
    with pytest.raises(ValueError, match="default level_window .* needs delay >= 5"):
        Replay(delay=3, onset=6, loop=(phi, C))
    assert Replay(delay=3, onset=6, loop=(phi, C), level_window=1).level_window == 1
    assert Replay(delay=8, onset=10, loop=(phi, C)).level_window == 5


def test_a_covert_attackers_model_of_other_sizes_is_refused_by_the_loop():
    # (check_attack_fits refused it, but closed_loop never calls that: torch's matmul error)
    from difffilter.loop import DrawnNoise, KnownInputs, closed_loop

    plant = _linear(3, 2, 1)
    attack = Covert(Ramp(0.2, channel="actuator", onset=3), _linear(2, 2, 1))
    with pytest.raises(ValueError, match="covert attack's plant has dim_x = 2"):
        closed_loop(plant, 10, noise=DrawnNoise(torch.Generator().manual_seed(0)),
                    x0=torch.zeros(2, 3, dtype=F64), attack=attack,
                    controller=KnownInputs(torch.zeros(2, 10, 1, dtype=F64)))  # fmt: skip


def test_a_ksigma_bias_on_the_actuators_needs_its_sigma():
    # σ = √diag R, the sensors' noise, had been taken for the inputs'
    model = _linear(2, 2, 2)
    with pytest.raises(ValueError, match="ksigma_bias on the actuators needs sigma"):
        threat_from_dict({"kind": "ksigma_bias", "k": 2.0, "channel": "actuator"}, model)
    with pytest.raises(ValueError, match="ksigma_bias on the actuators needs sigma"):
        threat_from_dict({"kind": "covert", "signal": {"kind": "ksigma_bias", "k": 2.0}}, model)
    with pytest.raises(ValueError, match="ksigma_bias on the actuators needs sigma"):
        KSigmaBias.of(model, 2.0, channel="actuator")
    threat_from_dict({"kind": "ksigma_bias", "k": 2.0}, model)  # (the sensors': √diag R)
