"""Findings of a tracking Python-API trial, each checked against an independent truth.

- one unbatched run's PF keeps a learnable σ_ω's gradient (the per-particle sampler took
  Python floats at construction);
- the sampler follows a loaded state dict and an assigned process noise;
- a Gaussian measurement noise on the Round-Robin mask takes the generic likelihood;
- the attack probabilities stay in [0, 1] despite round-off;
- the scenario's fields are checked by name;
- a packet outside the assumed attack box has attack probability 0 (documented).
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

import difffilter
from difffilter import fdi
from difffilter.models import registry
from difffilter.models.streams import Streams
from difffilter.models.tracking import TrackingModel
from difffilter.noise import Gaussian, UniformBox

F64 = torch.float64


@pytest.fixture(scope="module")
def runs():
    return (
        registry.get("tracking_rrp_deception").with_steps(10).simulate(2, Streams(0).simulation())
    )


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _loglik_and_grad(ys, mask):
    s = torch.tensor(0.055, dtype=F64, requires_grad=True)
    out = difffilter.particle_filter(
        TrackingModel(sigma_omega=s), ys, mask=mask, num_particles=50, ess_threshold=0.0,
        generator=_gen(0), innovations=False,
    )  # fmt: skip
    ll = out.log_likelihood.sum()
    return ll, torch.autograd.grad(ll, s)[0]


def test_one_unbatched_run_keeps_the_gradient_of_a_learnable_sigma_omega(runs):
    ll1, g1 = _loglik_and_grad(runs.y_recv[:1], runs.mask[:1])  # a batch of one
    ll0, g0 = _loglik_and_grad(runs.y_recv[0], runs.mask[0])  # unbatched: [N, 4] particles
    torch.testing.assert_close(ll0, ll1, rtol=1e-12, atol=0)
    torch.testing.assert_close(g0, g1, rtol=1e-9, atol=0)
    assert float(g0) != 0.0


def test_the_per_particle_sampler_is_the_closed_form_of_the_model_it_is_now():
    """x' = F x + L ε, L = chol(Q), for [N, 4] and [B, N, 4] particles alike, after the
    model's dt and σ_ω were changed by a state dict."""
    model = TrackingModel()
    model.load_state_dict(TrackingModel(sigma_omega=0.5, dt=2.0).state_dict())
    F, L = model.F, torch.linalg.cholesky(model.process_cov(0))
    assert float(F[0, 1]) == 2.0 and float(L[1, 1]) > 0.3  # the loaded model's dt and σ_ω
    for shape in ((3, 5, 4), (5, 4)):
        x = torch.randn(shape, generator=_gen(1), dtype=F64)
        eps = torch.randn(shape, generator=_gen(2), dtype=F64)  # the draw the sampler makes
        got = model.sample_transition(x, None, 0, _gen(2))
        torch.testing.assert_close(got, x @ F.T + eps @ L.T, rtol=1e-12, atol=1e-12)


def test_an_assigned_process_noise_is_the_one_the_particles_draw_from():
    model = TrackingModel()
    model.process_noise = Gaussian(torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64))
    x = torch.zeros(2, 20000, 4, dtype=F64)
    draws = model.sample_transition(x, None, 0, _gen(3)).reshape(-1, 4)
    cov = torch.cov(draws.T)
    torch.testing.assert_close(cov, torch.eye(4, dtype=F64), rtol=0, atol=0.03)


def test_a_gaussian_measurement_noise_on_the_round_robin_mask_is_its_own_likelihood(runs):
    model = registry.get("tracking_rrp_deception").system()
    R = torch.diag(torch.tensor([8.2, 4.9e-4] * 4, dtype=F64))
    model.measurement_noise = Gaussian(torch.zeros(8, dtype=F64), R)
    x = torch.randn(2, 30, 4, generator=_gen(4), dtype=F64) * 3 + 20
    y, mask = runs.y_recv[:, 3], runs.mask[:, 3]
    got = model.measurement_log_prob(y.unsqueeze(-2), x, 4, mask.unsqueeze(-2))
    r = model.measurement_residual(y.unsqueeze(-2), model.observe(x, 4))
    var = R.diagonal()
    terms = -0.5 * (r.square() / var + torch.log(2 * math.pi * var))
    want = (terms * mask.unsqueeze(-2)).sum(-1)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_the_tracking_attack_probabilities_are_probabilities(dtype):
    sc = dataclasses.replace(registry.get("tracking_rrp_deception"), eta_bar=0.6).with_steps(60)
    tr = sc.simulate(8, Streams(2).simulation(), dtype=dtype)
    from difffilter.eval.suite import run_suite

    result = run_suite(sc, runs=8, estimators=["pf_da", "rrp_pf_da"], progress=False, dtype=dtype)
    for name in ("pf_da", "rrp_pf_da"):
        scores = result.outputs[name].detection.scores
        assert bool((scores >= 0).all()) and bool((scores <= 1).all()), name
    assert tr.flags.any()


def test_a_packet_outside_the_assumed_box_is_taken_as_clean():
    """p_ξ = 0 outside the box (eq. 14): the attack probability is exactly 0 there, the
    blind spot docs/papers.md states."""
    sc = registry.get("tracking_rrp_deception")
    model = sc.system()
    n = len(sc.sensors)
    box = UniformBox(
        torch.tensor(sc.box_low * n, dtype=F64), torch.tensor(sc.box_high * n, dtype=F64)
    )
    lik = fdi.DeceptionMixtureLikelihood(sc.eta_bar, fdi.ReplacementDeception(box))
    x = torch.tensor([[20.0, 0.3, 20.0, 0.3]], dtype=F64).expand(1, 16, 4)
    inside = model.observe(x[:, 0], 1).clone()
    inside[..., 0] = 79.0  # far from the particles' ~14: an attack if the box allows it
    outside = inside.clone()
    outside[..., 0] = 80.5
    lw = torch.zeros(1, 16, dtype=F64)
    first = torch.zeros(1, 8, dtype=torch.bool)
    first[..., :2] = True  # the Round-Robin packet of sensor 1 (its bearing, π/4, in the box)
    assert float(lik.attack_probability(model, inside, x, lw, 1, first)) > 0.99
    assert float(lik.attack_probability(model, outside, x, lw, 1, first)) == 0.0


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("sensors", ((10, 10, 99), (10, 60, 99)), "sensors must be one or more"),
        ("sensors", (), "sensors must be one or more"),
        ("box_low", (-10.0, -1.0, 0.0), "box_low must be one sensor's"),
        ("box_high", (80.0, float("nan")), "box_high must be one sensor's"),
        ("box_high", (-20.0, 1.0), "box_low must lie below box_high"),
        ("eta_bar", "0.2", "eta_bar must be a number"),
        ("eta_bar", True, "eta_bar must be a number"),
    ],
)
def test_the_tracking_scenarios_fields_are_checked_by_name(field, value, match):
    with pytest.raises(ValueError, match=match):
        dataclasses.replace(registry.get("tracking_rrp_deception"), **{field: value})


def test_the_tracking_model_names_sensors_of_three_coordinates():
    with pytest.raises(ValueError, match="sensors must be one or more"):
        TrackingModel(sensors=((0.0, 0.0, 1.0),))


def test_a_simulation_that_draws_from_the_global_generator_says_so():
    """The tracking attack without an "attack" stream drew from torch's global generator:
    two identical calls differed, silently. It still runs (as documented), with a warning;
    with every stream it neither warns nor touches the global generator."""
    import warnings

    sc = registry.get("tracking_rrp_deception").with_steps(20)
    with pytest.warns(UserWarning, match="global generator: generators has no 'attack'"):
        sc.simulate(2, {"plant": _gen(0)})
    four_tank = registry.get("four_tank_bias").with_steps(20)  # a random (p_l) attack
    with pytest.warns(UserWarning, match="'attack' or 'schedule'"):
        four_tank.simulate(2, {"plant": _gen(0)})
    state = torch.random.get_rng_state()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        a = sc.simulate(2, Streams(0).simulation())
        b = sc.simulate(2, Streams(0).simulation())
    assert torch.equal(a.flags, b.flags) and torch.equal(a.y_recv, b.y_recv)
    assert torch.equal(state, torch.random.get_rng_state())


def test_a_threat_on_one_sensor_keeps_its_own_steps_for_the_detection_delay():
    """A library threat on one tracking sensor (entries 0 and 1 from k = 30): the
    trajectories keep the threat's own flags, as the generic simulation on the same model,
    schedule and streams does, so the detection delay's episodes are one a run (under the
    Round-Robin each received attacked reading had been an episode of its own: 22 a run,
    and a delay of 0 where the first alarm comes 20 steps into the attack)."""
    from difffilter.eval.scoring import episode_delay
    from difffilter.models import registry
    from difffilter.models.scenario import simulate
    from difffilter.models.streams import Streams
    from difffilter.threats import Bias

    sc = registry.get("tracking_rrp_deception")
    threat = Bias(value=[40.0, 0.3] + [0.0] * 6, entries=[0, 1], onset=30)
    tr = sc.with_threat(threat).simulate(4, Streams(0).simulation())
    generic = simulate(sc.system(), 4, sc.steps, generators=Streams(0).simulation(),
                       attack=threat, schedule=sc.schedule())  # fmt: skip
    assert torch.equal(tr.flags, generic.flags)
    assert torch.equal(tr.info["attack_flags"], generic.info["attack_flags"])
    alarms = tr.flags & (torch.arange(1, sc.steps + 1) >= 50)
    delay = episode_delay(alarms, tr)
    assert delay["episodes"] == 4 and delay["detected"] == 4
    first = [int(alarms[i].nonzero()[0]) + 1 for i in range(4)]  # k of each run's first alarm
    assert delay["mean_delay"] == pytest.approx(sum(k - 30 for k in first) / 4)
