"""The BCE's weight on the steps just after an attack (``after_attack_weight``)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from difffilter.metrics import after_attack
from difffilter.train.task import FilterEstimatorTask


def test_after_attack_marks_the_quiet_steps_within_the_window_after_an_attacked_step():
    flags = torch.tensor(
        [[0, 1, 1, 0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 0, 0, 0, 0, 1]], dtype=torch.bool
    )
    expected = torch.tensor(
        [[0, 0, 0, 1, 1, 0, 0, 1, 1], [0, 0, 0, 0, 0, 0, 0, 0, 0]], dtype=torch.bool
    )
    assert torch.equal(after_attack(flags, 2), expected)
    areas = torch.stack([flags, ~flags], -1)  # [B, T, J]: each area its own
    assert torch.equal(after_attack(areas, 2)[..., 0], expected)
    assert torch.equal(
        after_attack(areas, 1)[0, :, 1], torch.tensor([0, 1, 0, 0, 0, 0, 1, 0, 0]).bool()
    )


def test_the_bce_weighs_the_steps_after_an_attack():
    """The loss is the mean of ω_k·BCE_k with ω = after_attack_weight after an attack."""
    gen = torch.Generator().manual_seed(0)
    flags = torch.rand(3, 12, generator=gen) < 0.3
    logits = torch.randn(3, 12, generator=gen)
    out = SimpleNamespace(attack=torch.zeros(3, 12, 4), means=torch.zeros(3, 12, 4),
                          extras={"attack_logit": logits})  # fmt: skip
    truth = {"attack": torch.zeros(3, 12, 4), "x": torch.zeros(3, 12, 4), "flags": flags}
    each = torch.nn.functional.binary_cross_entropy_with_logits(
        logits, flags.float(), reduction="none"
    )
    for weight, steps in ((1.0, 20), (5.0, 3)):
        task = FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=4,
                                   after_attack_weight=weight, after_attack_steps=steps)  # fmt: skip
        omega = 1.0 + (weight - 1.0) * after_attack(flags, steps).float()
        assert float(task._losses(out, truth)["bce"]) == pytest.approx(
            float((omega * each).mean()), rel=1e-6
        )


@pytest.mark.parametrize(("option", "value"), [("after_attack_weight", 0.0), ("after_attack_steps", 0),
                                               ("after_attack_steps", 2.5)])  # fmt: skip
def test_bad_after_attack_options_are_refused_by_name(option, value):
    with pytest.raises(ValueError, match=option):
        FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=4, **{option: value})


def test_truncated_backpropagation_is_refused_on_an_open_loop():
    """An open loop trains on whole sequences: ``tbptt_steps`` there once only stretched the
    one-cycle schedule (20 steps of a 80-step schedule, the rate never annealed)."""
    with pytest.raises(
        ValueError, match="tbptt_steps needs a closed-loop scenario; four_tank_bias"
    ):
        FilterEstimatorTask("four_tank_bias", num_particles=20, hidden=4, tbptt_steps=5)
    FilterEstimatorTask("lfc_random_attacks", filter="kf", tbptt_steps=5)  # a closed loop takes it


def test_no_particles_is_refused_not_replaced_by_the_default():
    for n in (0, -3):  # 0 once fell back to the scenario's number silently
        with pytest.raises(ValueError, match=f"num_particles must be a positive integer.*got {n}"):
            FilterEstimatorTask("four_tank_bias", num_particles=n, hidden=4)
