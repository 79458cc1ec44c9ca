"""Four-tank plant extensions, the bias FDI attack generator (eqs 3–4) and the scenarios."""

from __future__ import annotations

import math

import pytest
import torch
from attacked import simulate_attacked

from difffilter import fdi
from difffilter.models import registry
from difffilter.models.attacks import BiasAttack
from difffilter.models.four_tank import (
    R_HIGH,
    R_NOMINAL,
    FourTankModel,
    FourTankScenario,
)


def test_attack_values_follow_eq4_and_its_closed_form():
    attack = BiasAttack((0.5, 0.5, 0.5, 0.5), tau=0.9, p_l=0.5)
    g = attack.values(6)
    # γ_1 = (1 − τ) γ̄, then γ_{k+1} = τ γ_k + (1 − τ) γ̄ (γ_0 = 0)
    assert torch.allclose(g[0], torch.full((4,), 0.05, dtype=torch.float64))
    for k in range(1, 6):
        assert torch.allclose(g[k], 0.9 * g[k - 1] + 0.1 * 0.5)
    k = torch.arange(1, 7, dtype=torch.float64)
    assert torch.allclose(g, (1 - 0.9**k).unsqueeze(-1) * 0.5)
    # ‖γ_k‖ = 1 − 0.9^k: 0.1, 0.19, 0.271 (≤ ‖γ‖_min = 0.28: undetectable by design), 0.3439
    assert torch.allclose(
        g.norm(dim=-1)[:4], torch.tensor([0.1, 0.19, 0.271, 0.3439], dtype=torch.float64)
    )


def test_attack_flags_are_bernoulli_reproducible_and_nested():
    a_lo, a_hi = BiasAttack((1.0,), p_l=0.3), BiasAttack((1.0,), p_l=0.6)
    f1 = a_lo.sample_flags((200,), 100, torch.Generator().manual_seed(3))
    f2 = a_lo.sample_flags((200,), 100, torch.Generator().manual_seed(3))
    assert f1.shape == (200, 100) and f1.dtype == torch.bool
    assert torch.equal(f1, f2)
    n = f1.numel()
    assert abs(f1.double().mean().item() - 0.3) < 5 * math.sqrt(0.3 * 0.7 / n)
    f_hi = a_hi.sample_flags((200,), 100, torch.Generator().manual_seed(3))
    assert bool((f1 <= f_hi).all())  # same uniforms: a larger p_l only adds attacks


def test_the_sensor_channel_adds_l_gamma_exactly_where_flagged():
    from difffilter.attack import Channel, inject

    attack = BiasAttack((0.5, -0.25), tau=0.8, p_l=0.5)
    y = torch.randn(3, 10, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    values, flags = attack.init((3,), 10, 2, torch.Generator().manual_seed(1), dtype=y.dtype)
    received, change = inject(Channel.SENSOR, y, values, flags)
    diff = received - y
    assert torch.allclose(diff, flags.unsqueeze(-1) * values) and torch.allclose(diff, change)
    assert torch.equal(diff[~flags], torch.zeros_like(diff[~flags]))
    assert bool(flags.any()) and not bool(flags.all()) and attack.channel is Channel.SENSOR
    assert torch.equal(values[0], attack.values(10, dtype=y.dtype))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"gamma_bar": (1.0,), "tau": 1.0}, "tau"),
        ({"gamma_bar": (1.0,), "tau": 0.0}, "tau"),
        ({"gamma_bar": (1.0,), "p_l": 1.5}, "p_l"),
        ({"gamma_bar": ()}, "gamma_bar"),
        ({"gamma_bar": (math.nan,)}, "gamma_bar"),
    ],
)
def test_attack_rejects_bad_parameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        BiasAttack(**kwargs)


def test_attack_rejects_bad_shapes():
    attack = BiasAttack((1.0, 1.0))
    with pytest.raises(ValueError, match="gamma_bar has 2 entries"):
        attack.init((5,), 4, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="num_steps"):
        attack.values(0)


def test_simulation_shapes_initial_state_and_independent_streams():
    model = FourTankModel(dtype=torch.float64)
    kw = {
        "plant_generator": torch.Generator().manual_seed(0),
        "attack_generator": torch.Generator().manual_seed(1),
    }
    tr = simulate_attacked(model, BiasAttack((0.5,) * 4), 5, 20, **kw)
    assert tr.x.shape == tr.y_true.shape == tr.y_recv.shape == tr.gammas.shape == (5, 20, 4)
    assert tr.flags.shape == (5, 20)
    assert torch.allclose(tr.x0, model.initial.mean.expand(5, 4))  # x_0 = fixed point [DEF]
    # a different attack on the same plant stream leaves the plant untouched
    tr2 = simulate_attacked(
        model,
        BiasAttack((2.0,) * 4, p_l=0.9),
        5,
        20,
        plant_generator=torch.Generator().manual_seed(0),
        attack_generator=torch.Generator().manual_seed(9),
    )
    assert torch.equal(tr.x, tr2.x) and torch.equal(tr.y_true, tr2.y_true)
    # R × 5 with the same stream: same states, measurement noise scaled by √5
    model5 = FourTankModel(R=R_HIGH, dtype=torch.float64)
    tr5 = simulate_attacked(
        model5,
        BiasAttack((0.5,) * 4),
        5,
        20,
        plant_generator=torch.Generator().manual_seed(0),
        attack_generator=torch.Generator().manual_seed(1),
    )
    assert torch.equal(tr5.x, tr.x)
    assert torch.allclose(tr5.y_true - tr5.x, math.sqrt(5) * (tr.y_true - tr.x))
    with pytest.raises(ValueError, match="gamma_bar"):
        simulate_attacked(model, BiasAttack((1.0,)), 2, 3, **kw)


@pytest.mark.parametrize(
    "shape", [(3, 4), (100, 50, 4)]
)  # the second uses the cached full-size coefficients
def test_transition_matches_euler_step_of_the_continuous_model(shape):
    model = FourTankModel(dtype=torch.float64)
    x = 5.0 + 4.0 * torch.randn(
        *shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64
    )
    x[..., 0] = (
        x[..., 0].clamp_max(-0.1) if shape[0] == 3 else x[..., 0]
    )  # negative levels: √max(x, 0)
    expected = x + model.dt * model.continuous_rhs(x)
    assert torch.allclose(model.transition(x, None, 0), expected, atol=1e-12)
    M, c = model.sqrt_affine_form()
    assert torch.allclose(x + c + torch.sqrt(x.clamp_min(0)) @ M, expected, atol=1e-12)
    with pytest.raises(AttributeError):
        model.dt = 2.0  # read-only: the step coefficients are built from it


def test_scenarios_are_registered_with_the_paper_parameters():
    names = registry.names("four_tank")
    assert {
        "four_tank_bias",
        "four_tank_bias_high_noise",
        "four_tank_bias_large",
        "four_tank_bias_noisy_estimate",
    } <= set(names)
    base = registry.get("four_tank_bias")
    assert isinstance(base, FourTankScenario)
    assert (
        base.R == R_NOMINAL
        and base.gamma_bar == (0.5,) * 4
        and base.p_l == 0.5
        and base.num_particles == 100
    )
    assert registry.get("four_tank_bias_high_noise").R == R_HIGH
    assert registry.get("four_tank_bias_large").gamma_bar == (1.0,) * 4
    assert registry.get("four_tank_bias_noisy_estimate").gamma_hat_noise_var == 1e-2
    model = base.model()
    eta = fdi.attack_threshold(
        model.G,
        fdi.modified_pf_gain(model.G, model.process_cov(0), model.measurement_cov(1)),
        base.gamma_min,
    )
    assert abs(float(eta) - 0.28 * 5 / 6) < 1e-12  # the paper's η = 0.233
    assert base.attack().gamma_bar == base.gamma_bar
