"""Four findings of a closed-loop trial (difffilter/loop.py): a 2-D batch of parameter sets
recorded with time between its run axes, NaN unchecked in a loop without an estimator, a
fork's packet-loss schedule dropped on continuing it, and the docstring's account of the
attack records under input loss."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.attack import Channel, TabulatedAttack
from difffilter.loop import (
    DrawnNoise,
    InputLoss,
    KnownInputs,
    ReplayedNoise,
    StateFeedback,
    closed_loop,
)
from difffilter.threats import Bias

DT = torch.float64
F = torch.tensor([[1.0, 0.1], [0.0, 1.02]], dtype=DT)


def _plant(F=F):
    eye = torch.eye(2, dtype=DT)
    H, R = torch.tensor([[1.0, 0.0]], dtype=DT), 0.05 * torch.eye(1, dtype=DT)
    B = torch.tensor([[0.0], [0.1]], dtype=DT)
    return df.LinearGaussianModel(F, H, 0.01 * eye, R, torch.zeros(2, dtype=DT), eye, B=B)


def _draws(B, T, seed=0):
    g = torch.Generator().manual_seed(seed)
    w = 0.1 * torch.randn(B, T, 2, generator=g, dtype=DT)
    v = 0.2 * torch.randn(B, T, 1, generator=g, dtype=DT)
    x0 = torch.randn(B, 2, generator=g, dtype=DT)
    mask = torch.rand(B, T, 1, generator=g) > 0.3
    return ReplayedNoise(w, v), x0, mask


class _NaNAt(TabulatedAttack):
    """A sensor attack that injects NaN into run ``run``'s measurement at step ``k``."""

    channel = Channel.SENSOR

    def __init__(self, k, run):
        self.k, self.run = k, run

    def sample(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        values = torch.zeros(*batch_shape, num_steps, dim, dtype=dtype)
        values[self.run, self.k - 1, 0] = float("nan")
        flags = torch.zeros(*batch_shape, num_steps, dtype=torch.bool)
        flags[:, self.k - 1] = True
        return values, flags


# -- 1. a 2-D batch of parameter sets -----------------------------------------------------


def test_a_two_dimensional_batch_of_parameter_sets_is_refused_naming_its_shape():
    """F [2, 3, dx, dx] with x0 [1, dx] ran and recorded x [2, T, 3, dx] beside the
    estimator's means [2, 3, T, dx]; the same sets flattened to one axis run as six."""
    scales = torch.tensor([[0.9, 1.0, 1.05], [0.8, 0.95, 1.1]], dtype=DT)
    x0 = torch.ones(1, 2, dtype=DT)
    noise = DrawnNoise(torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=r"the plant has parameter sets of batch shape \(2, 3\)"):
        closed_loop(_plant(F * scales[..., None, None]), 4, noise=noise, x0=x0,
                    estimator=df.KalmanFilter(), attack=Bias(0.5, onset=2))  # fmt: skip
    # the estimator's model of a 2-D batch, on a plant of one set, is refused as well
    with pytest.raises(ValueError, match=r"model \(the estimator's\) has .* \(2, 3\)"):
        closed_loop(_plant(), 4, noise=noise, x0=torch.ones(3, 2, dtype=DT),
                    estimator=df.KalmanFilter(), model=_plant(F * scales[..., None, None]))  # fmt: skip
    flat = closed_loop(_plant((F * scales[..., None, None]).reshape(6, 2, 2)), 4, noise=noise,
                       x0=x0, estimator=df.KalmanFilter(), attack=Bias(0.5, onset=2))  # fmt: skip
    tr = flat.trajectories
    assert tr.x.shape == (6, 4, 2) and flat.output.means.shape == (6, 4, 2)
    assert tr.flags.shape == (6, 4) and tr.attack.shape == (6, 4, 1)


# -- 2. NaN without an estimator -----------------------------------------------------------


@pytest.mark.parametrize("with_estimator", [True, False])
def test_a_nan_from_the_controller_or_the_attack_is_named_without_an_estimator_too(
    with_estimator,
):
    """The controller's NaN u_3 (run 1) is named at step 4, the attacker's NaN in y_5 (run 1)
    at step 5, in the same words with and without an estimator (without one both had
    passed silently into x and y_recv)."""
    plant, B, T = _plant(), 3, 10
    est = df.KalmanFilter() if with_estimator else None
    us = torch.zeros(B, T, 1, dtype=DT)
    us[1, 3, 0] = float("nan")
    kw = dict(noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=torch.zeros(B, 2, dtype=DT))
    with pytest.raises(ValueError) as caught:
        closed_loop(plant, T, estimator=est, controller=KnownInputs(us), **kw)
    assert str(caught.value).startswith(
        "the input u_3 that drives step 4 contains NaN or Inf (first in run 1): the controller "
        "at step 3 returned it (KnownInputs)"
    )
    with pytest.raises(ValueError) as caught:
        closed_loop(plant, T, estimator=est, attack=_NaNAt(5, 1), **kw)
    assert str(caught.value).startswith(
        "the measurement received at step 5 contains NaN or Inf (first in run 1, entry 0): "
        "the attack (_NaNAt) or the plant produced it"
    )


def test_a_nan_on_a_dropped_entry_passes_and_a_forks_steps_are_named_absolutely():
    """Without an estimator as with one: a NaN the schedule drops is not received (y_recv
    keeps it, unread); a loop continued from a fork after step 3 names step 6, not 3. A
    state the plant itself overflows (x_2 = 1e200 · 1e200) is the simulation's truth,
    returned for its caller (scenario.simulate names the model's transition there)."""
    plant, B, T = _plant(), 3, 10
    noise, x0, _ = _draws(B, T)
    big = torch.tensor([[1e200, 0.0], [0.0, 0.5]], dtype=DT)
    own = closed_loop(_plant(big), 3, noise=noise, x0=torch.ones(B, 2, dtype=DT)).trajectories
    assert torch.isinf(own.x[:, 1, 0]).all() and torch.isfinite(own.x[:, 0]).all()
    mask = torch.ones(B, T, 1, dtype=torch.bool)
    mask[2, 4] = False
    r = closed_loop(plant, T, noise=noise, x0=x0, mask=mask, attack=_NaNAt(5, 2))
    assert torch.isnan(r.trajectories.y_recv[2, 4, 0]) and torch.isfinite(r.trajectories.x).all()
    forks = {3: None}
    closed_loop(plant, T, noise=noise, x0=x0, forks=forks)
    with pytest.raises(ValueError, match=r"received at step 6 .*first in run 0, entry 0"):
        closed_loop(plant, T - 3, noise=noise, fork=forks[3], attack=_NaNAt(6, 0))


# -- 3. a fork's schedule --------------------------------------------------------------------


def _forked(mask, **kw):
    plant = _plant()
    K, _ = df.control.dlqr(plant.F, plant.B)
    noise, x0, _ = _draws(3, 12)
    loop = dict(noise=noise, estimator=df.KalmanFilter(), controller=StateFeedback(K))
    forks = {5: None}
    closed_loop(plant, 12, x0=x0, mask=mask, forks=forks, **loop)
    return plant, x0, loop, forks[5]


def test_a_fork_kept_under_a_mask_continues_only_under_it():
    """A fork kept under a schedule and continued without it had filtered its 5 steps with
    entries dropped while the result said all were received; another mask over those
    steps is refused too, and a fork kept without a mask refuses one. A mask that differs
    only after the fork's steps is this loop's own, as in the whole loop under it."""
    _, _, mask = _draws(3, 12)
    assert not mask[:, :5].all()  # the fork's steps drop entries
    plant, x0, loop, fork = _forked(mask)
    attack = Bias(0.5, onset=6)
    with pytest.raises(ValueError, match="fork: continue a fork with the mask"):
        closed_loop(plant, 7, fork=fork, attack=attack, **loop)
    changed = mask.clone()
    changed[0, 2] = ~changed[0, 2]
    with pytest.raises(ValueError, match=r"fork: mask differs .* at steps 1 … 5"):
        closed_loop(plant, 7, fork=fork, attack=attack, mask=changed, **loop)
    _, _, _, unmasked = _forked(None)
    with pytest.raises(ValueError, match="fork: continue a fork with the mask"):
        closed_loop(plant, 7, fork=unmasked, attack=attack, mask=mask, **loop)
    later = mask.clone()
    later[:, 5:] = True  # the continuation's own steps: its choice
    cont = closed_loop(plant, 7, fork=fork, attack=attack, mask=later, **loop)
    whole = closed_loop(plant, 12, x0=x0, mask=later, attack=attack, **loop)
    assert torch.equal(cont.trajectories.mask, later) and torch.equal(
        cont.trajectories.x, whole.trajectories.x
    )
    assert torch.equal(cont.output.means, whole.output.means)
    assert torch.equal(cont.trajectories.flags, whole.trajectories.flags)


def test_a_fork_continues_only_on_the_draws_it_was_kept_on():
    """A fork continued on other noise had joined its 5 steps to steps on other draws, the
    result read as one loop; noise that differs only after the fork's steps (or a copy of
    the same draws) is this loop's own, as in the whole loop on it."""
    plant, x0, loop, fork = _forked(None)
    noise, attack = loop["noise"], Bias(0.5, onset=6)
    rest = {key: v for key, v in loop.items() if key != "noise"}
    for name in ("process", "measurement"):
        other = ReplayedNoise(noise.process.clone(), noise.measurement.clone())
        getattr(other, name)[1, 3] += 0.1
        with pytest.raises(
            ValueError, match=rf"fork: noise differs .*\({name} noise at steps 1 … 5"
        ):
            closed_loop(plant, 7, fork=fork, attack=attack, noise=other, **rest)
    later = ReplayedNoise(noise.process.clone(), noise.measurement.clone())
    later.process[:, 5:] *= 2.0
    cont = closed_loop(plant, 7, fork=fork, attack=attack, noise=later, **rest)
    whole = closed_loop(plant, 12, x0=x0, attack=attack, noise=later, **rest)
    assert torch.equal(cont.trajectories.x, whole.trajectories.x)
    assert torch.equal(cont.output.means, whole.output.means)


# -- 4. the attack records under input loss ----------------------------------------------


def test_under_input_loss_only_the_attack_is_as_it_reached_the_plant():
    """An actuator bias 0.5 at step 4 only, whose packet is lost and zeroed: nothing reached
    the plant (attack 0, applied input 0), while flags and attack_values are the attacker's
    own (step 4 flagged, value 0.5), as the docstring now says."""
    plant = _plant()
    K, _ = df.control.dlqr(plant.F, plant.B)
    arrived = torch.tensor([[True, True, True, False, True, True]])
    r = closed_loop(plant, 6, noise=DrawnNoise(torch.Generator().manual_seed(0)),
                    x0=torch.zeros(1, 2, dtype=DT), estimator=df.KalmanFilter(),
                    controller=StateFeedback(K), input_loss=InputLoss(arrived, "zero"),
                    attack=Bias(0.5, onset=4, duration=1, channel="actuator"))  # fmt: skip
    tr = r.trajectories
    assert torch.equal(tr.attack, torch.zeros(1, 6, 1, dtype=DT))
    assert tr.info["inputs_applied"][0, 3, 0] == 0.0
    assert tr.flags.tolist() == [[False, False, False, True, False, False]]
    assert tr.info["attack_values"][0, 3, 0] == 0.5
    doc = " ".join(closed_loop.__doc__.split())
    assert "under ``input_loss`` only ``attack`` is as it reached the plant" in doc


def test_an_actuator_attacks_nan_is_named_without_an_estimator():
    """From a review: the actuator attack's NaN made the state NaN, which was taken for the
    plant's own and passed silently without an estimator (with one, it was refused)."""
    D = torch.float64
    eye = torch.eye(2, dtype=D)
    plant = df.LinearGaussianModel(
        torch.tensor([[1.0, 0.1], [0.0, 1.02]], dtype=D), torch.tensor([[1.0, 0.0]], dtype=D),
        0.01 * eye, 0.05 * torch.eye(1, dtype=D), torch.zeros(2, dtype=D), eye,
        B=torch.tensor([[0.0], [0.1]], dtype=D),
    )  # fmt: skip

    class NaNOnTheActuator(TabulatedAttack):
        channel = Channel.ACTUATOR

        def sample(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
            v = torch.zeros(*batch_shape, num_steps, dim, dtype=dtype)
            v[1, 2, 0] = float("nan")
            f = torch.zeros(*batch_shape, num_steps, dtype=torch.bool)
            f[:, 2] = True
            return v, f

    kw = dict(noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=torch.zeros(3, 2, dtype=D),
              controller=KnownInputs(torch.zeros(3, 6, 1, dtype=D)))  # fmt: skip
    with pytest.raises(ValueError, match=r"the attack \(NaNOnTheActuator\) put NaN or Inf into "
                                         r"the input that drives step 3 \(first in run 1\)"):  # fmt: skip
        closed_loop(plant, 6, attack=NaNOnTheActuator(), **kw)
    clean = closed_loop(plant, 6, **kw)  # no attack: nothing said
    assert bool(torch.isfinite(clean.trajectories.x).all())


def _resumable_loop():
    """A small controlled plant with a Kalman filter and state feedback, its noise
    replayed (so that chunks and forks are the same loop)."""
    from difffilter.loop import ReplayedNoise, StateFeedback

    D = torch.float64
    F = torch.tensor([[1.0, 0.1], [0.0, 0.98]], dtype=D)
    plant = df.LinearGaussianModel(F, torch.eye(2, dtype=D), 0.01 * torch.eye(2, dtype=D),
                                   0.04 * torch.eye(2, dtype=D), torch.zeros(2, dtype=D),
                                   torch.eye(2, dtype=D), B=torch.tensor([[0.0], [0.1]], dtype=D))  # fmt: skip
    g = torch.Generator().manual_seed(0)
    w, v = (s * torch.randn(2, 20, 2, generator=g, dtype=D) for s in (0.1, 0.2))
    kw = dict(noise=ReplayedNoise(w, v), estimator=df.KalmanFilter(),
              controller=StateFeedback(torch.tensor([[0.5, 1.0]], dtype=D)))  # fmt: skip
    return plant, torch.zeros(2, 2, dtype=D), kw


def test_a_resumed_loop_goes_on_with_the_attack_it_kept():
    """``closed_loop(state=…)`` with another attack than the one the state was kept under
    is refused (a ramp resumed on a bias's state had injected the bias under the ramp's
    name); the same attack, or one equal to it, goes on as one loop; an attack on a loop
    kept without one is refused by name (a bare TypeError on None before)."""
    from difffilter.loop import closed_loop
    from difffilter.threats import Bias, Ramp

    plant, x0, kw = _resumable_loop()
    whole = closed_loop(plant, 20, x0=x0, attack=Bias(value=1.0, onset=2), **kw)
    first = closed_loop(plant, 10, x0=x0, horizon=20, attack=Bias(value=1.0, onset=2), **kw)
    with pytest.raises(ValueError, match="ran under Bias and this call gives Ramp"):
        closed_loop(plant, 10, state=first.state, attack=Ramp(slope=0.5, onset=12), **kw)
    with pytest.raises(ValueError, match="ran under Bias and this call gives Bias"):
        closed_loop(plant, 10, state=first.state, attack=Bias(value=2.0, onset=2), **kw)
    again = closed_loop(plant, 10, state=first.state, attack=Bias(value=1.0, onset=2), **kw)
    assert torch.equal(again.trajectories.attack, whole.trajectories.attack[:, 10:])
    assert torch.equal(again.trajectories.x, whole.trajectories.x[:, 10:])
    free = closed_loop(plant, 10, x0=x0, horizon=20, **kw)
    with pytest.raises(ValueError, match="the loop kept ran without attack"):
        closed_loop(plant, 10, state=free.state, attack=Bias(value=1.0, onset=12), **kw)
