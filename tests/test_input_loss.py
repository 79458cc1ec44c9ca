"""Packet loss between the controller and the actuators (difffilter.input_loss), checked
against the loop written out by hand: the actuators' hold or zero, what an acknowledged
(TCP-like) and an unacknowledged (UDP-like) estimator step with, an actuator attack on a
lost packet, chunks and forks, gradients and bad arguments."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.attack import Attack, Channel
from difffilter.loop import InputLoss, KnownInputs, ReplayedNoise, closed_loop, open_loop
from difffilter.models.attacks import Signal

B, T = 4, 25


def _plant():
    F = torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=torch.float64)
    eye = torch.eye(2, dtype=torch.float64)
    Bu = torch.tensor([[0.0, 0.05], [0.1, 0.02]], dtype=torch.float64)
    return df.LinearGaussianModel(F, eye, 1e-3 * eye, 1e-2 * eye,
                                  torch.zeros(2, dtype=torch.float64), eye, B=Bu)  # fmt: skip


def _setup(per_actuator=False, seed=0):
    gen = torch.Generator().manual_seed(seed)
    w = 0.03 * torch.randn(B, T, 2, generator=gen, dtype=torch.float64)
    v = 0.1 * torch.randn(B, T, 2, generator=gen, dtype=torch.float64)
    us = torch.randn(B, T, 2, generator=gen, dtype=torch.float64)
    shape = (B, T, 2) if per_actuator else (B, T)
    arrived = torch.rand(shape, generator=gen) < 0.6
    x0 = torch.randn(B, 2, generator=gen, dtype=torch.float64)
    return ReplayedNoise(w, v), us, arrived, x0


def _by_hand(plant, noise, us, arrived, x0, hold, attack=None):
    """The loop of the module docstring, step by step: (states, applied inputs, the attack
    in them, the attacked steps: its own, and where a held input carries it)."""
    x, held, xs, applied_all = x0, torch.zeros_like(us[:, 0]), [], []
    held_a, held_on, attacks, acting = (
        torch.zeros_like(held),
        torch.zeros_like(held, dtype=bool),
        [],
        [],
    )
    nu = arrived if arrived.dim() == 3 else arrived.unsqueeze(-1).expand_as(us)
    values = torch.zeros(T, us.shape[-1], dtype=us.dtype) if attack is None else attack
    for t in range(T):
        a = values[t].expand_as(held)
        on = (values[t] != 0).expand_as(held)  # (a per-run flag: the attacks here act on both)
        on = on.any(-1, keepdim=True).expand_as(held)
        content = us[:, t] + a
        arrive = nu[:, t]
        applied = torch.where(arrive, content, held if hold else torch.zeros_like(held))
        recorded = torch.where(arrive, a, held_a if hold else torch.zeros_like(a))
        carried = torch.where(arrive, on, held_on if hold else torch.zeros_like(on))
        held, held_a, held_on = applied, recorded, carried
        on = on | carried
        x = x @ plant.F.T + applied @ plant.B.T + noise.process[:, t]
        xs.append(x)
        applied_all.append(applied)
        attacks.append(recorded)
        acting.append(on)
    return (torch.stack(xs, 1), torch.stack(applied_all, 1), torch.stack(attacks, 1),
            torch.stack(acting, 1))  # fmt: skip


def _known(us, arrived, hold):
    """What an acknowledged estimator knows of the applied input (no attack seen)."""
    nu = arrived if arrived.dim() == 3 else arrived.unsqueeze(-1).expand_as(us)
    known, held = [], torch.zeros_like(us[:, 0])
    for t in range(T):
        held = torch.where(nu[:, t], us[:, t], held if hold else torch.zeros_like(held))
        known.append(held)
    return torch.stack(known, 1)


@pytest.mark.parametrize("per_actuator", [False, True])
@pytest.mark.parametrize("on_loss", ["hold", "zero"])
def test_the_plant_moves_under_the_input_the_actuators_apply(per_actuator, on_loss):
    plant = _plant()
    noise, us, arrived, x0 = _setup(per_actuator)
    got = closed_loop(plant, T, noise=noise, x0=x0, controller=KnownInputs(us),
                      input_loss=InputLoss(arrived, on_loss))  # fmt: skip
    xs, applied, _, _ = _by_hand(plant, noise, us, arrived, x0, on_loss == "hold")
    tr = got.trajectories
    torch.testing.assert_close(tr.x, xs, rtol=0, atol=1e-13)
    torch.testing.assert_close(tr.info["inputs_applied"], applied, rtol=0, atol=0)
    nu = arrived if per_actuator else arrived.unsqueeze(-1).expand(B, T, 2)
    assert torch.equal(tr.info["input_mask"], nu)
    # acknowledged by default: the estimator's inputs are the applied ones (no attack)
    torch.testing.assert_close(tr.us, applied, rtol=0, atol=0)
    # the loss made a difference: held and zeroed inputs differ from the sent ones
    assert not torch.equal(applied, us)


def test_an_acknowledged_kalman_filter_is_the_filter_on_the_applied_inputs():
    """TCP-like: the estimator knows every applied input, so the closed-loop Kalman filter
    is the open-loop one on those inputs; UDP-like it is the filter on the sent inputs, and
    further from the truth."""
    plant = _plant()
    noise, us, arrived, x0 = _setup(seed=1)
    runs = {}
    for acked in (True, False):
        runs[acked] = closed_loop(plant, T, noise=noise, x0=x0, controller=KnownInputs(us),
                                  estimator=df.KalmanFilter(),
                                  input_loss=InputLoss(arrived, "hold", acknowledged=acked))  # fmt: skip
    tcp, udp = runs[True], runs[False]
    torch.testing.assert_close(tcp.trajectories.x, udp.trajectories.x, rtol=0, atol=0)
    applied = tcp.trajectories.info["inputs_applied"]
    ref = open_loop(df.KalmanFilter(), plant, tcp.trajectories.y_recv, applied)
    torch.testing.assert_close(tcp.output.means, ref.means, rtol=0, atol=1e-12)
    assert torch.equal(udp.trajectories.us, us)
    ref_udp = open_loop(df.KalmanFilter(), plant, udp.trajectories.y_recv, us)
    torch.testing.assert_close(udp.output.means, ref_udp.means, rtol=0, atol=1e-12)
    x = tcp.trajectories.x
    err = {k: (r.output.means - x).square().mean().item() for k, r in runs.items()}
    assert err[True] < 0.5 * err[False]


def test_every_packet_arriving_is_the_loop_without_loss():
    plant = _plant()
    noise, us, arrived, x0 = _setup()
    kw = dict(noise=noise, x0=x0, controller=KnownInputs(us), estimator=df.KalmanFilter())
    plain = closed_loop(plant, T, **kw)
    for on_loss in ("hold", "zero"):
        lossless = closed_loop(plant, T, input_loss=InputLoss(torch.ones(B, T, dtype=torch.bool),
                                                              on_loss), **kw)  # fmt: skip
        assert torch.equal(plain.trajectories.x, lossless.trajectories.x)
        assert torch.equal(plain.output.means, lossless.output.means)


@pytest.mark.parametrize("on_loss", ["hold", "zero"])
def test_an_actuator_attack_travels_in_its_packet(on_loss):
    """The attack rides in the packet: lost with it where the actuators apply zero, and
    held with it where they hold (recorded where it is in the applied input; flagged on its
    own steps, lost packet or not, and where a held input carries it beyond them); an
    acknowledged estimator steps with the sent inputs that arrived, never the attack."""
    plant = _plant()
    noise, us, arrived, x0 = _setup(seed=2)
    values = torch.zeros(T, 2, dtype=torch.float64)
    values[8:12] = torch.tensor([0.7, -0.4], dtype=torch.float64)
    got = closed_loop(plant, T, noise=noise, x0=x0, controller=KnownInputs(us),
                      estimator=df.KalmanFilter(), attack=Signal(values, Channel.ACTUATOR),
                      input_loss=InputLoss(arrived, on_loss))  # fmt: skip
    hold = on_loss == "hold"
    xs, applied, attack, acting = _by_hand(plant, noise, us, arrived, x0, hold, attack=values)
    tr = got.trajectories
    torch.testing.assert_close(tr.x, xs, rtol=0, atol=1e-13)
    torch.testing.assert_close(tr.info["inputs_applied"], applied, rtol=0, atol=1e-15)
    torch.testing.assert_close(tr.attack, attack, rtol=0, atol=0)
    assert torch.equal(tr.flags, acting.any(-1))
    known = _known(us, arrived, hold)
    torch.testing.assert_close(tr.us, known, rtol=0, atol=0)
    torch.testing.assert_close(tr.info["inputs_applied"] - tr.us, attack, rtol=0, atol=1e-15)
    ref = open_loop(df.KalmanFilter(), plant, tr.y_recv, known)
    torch.testing.assert_close(got.output.means, ref.means, rtol=0, atol=1e-12)
    window = (values.abs().sum(-1) > 0).expand(B, T)
    if hold:  # the attack outlasts its window where the packets after it were lost
        assert bool((tr.flags & ~window).any())
    else:  # flagged on its own steps: one attack, not one per arrived packet
        assert torch.equal(tr.flags, window)
        assert bool((tr.attack[window & ~arrived] == 0).all())


def test_a_loop_with_input_loss_run_in_chunks_or_from_a_fork_is_the_loop_at_once():
    plant = _plant()
    noise, us, arrived, x0 = _setup(seed=3)
    loss = InputLoss(arrived, "hold")
    kw = dict(noise=noise, controller=KnownInputs(us), estimator=df.KalmanFilter(),
              input_loss=loss)  # fmt: skip
    forks = {10: None}
    whole = closed_loop(plant, T, x0=x0, forks=forks, **kw)
    first = closed_loop(plant, 10, x0=x0, horizon=T, **kw)
    second = closed_loop(plant, T - 10, state=first.state, **kw)
    assert torch.equal(torch.cat([first.trajectories.x, second.trajectories.x], 1),
                       whole.trajectories.x)  # fmt: skip
    forked = closed_loop(plant, T - 10, fork=forks[10], **kw)
    assert torch.equal(forked.trajectories.x, whole.trajectories.x)
    assert torch.equal(forked.trajectories.info["inputs_applied"],
                       whole.trajectories.info["inputs_applied"])  # fmt: skip
    with pytest.raises(ValueError, match="input_loss of the loop that kept it"):
        closed_loop(plant, T - 10, fork=forks[10], noise=noise, controller=KnownInputs(us),
                    estimator=df.KalmanFilter())  # fmt: skip
    plain = closed_loop(plant, 10, x0=x0, noise=noise, controller=KnownInputs(us))
    with pytest.raises(ValueError, match="without input_loss"):
        closed_loop(plant, 5, state=plain.state, noise=noise, controller=KnownInputs(us),
                    input_loss=loss)  # fmt: skip


def test_the_loop_under_input_loss_is_differentiable_in_the_controllers_gain():
    plant = _plant()
    noise, _, arrived, x0 = _setup(seed=4)
    K0 = torch.tensor([[0.2, 0.1], [0.0, 0.3]], dtype=torch.float64)

    def cost(K):
        out = closed_loop(plant, 12, noise=noise, x0=x0, estimator=df.KalmanFilter(),
                          controller=df.loop.StateFeedback(K), horizon=T,
                          input_loss=InputLoss(arrived, "hold"))  # fmt: skip
        return out.trajectories.x.square().sum()

    assert torch.autograd.gradcheck(cost, (K0.clone().requires_grad_(),))


def test_input_loss_names_a_bad_argument():
    plant = _plant()
    noise, us, arrived, x0 = _setup()
    kw = dict(noise=noise, x0=x0, controller=KnownInputs(us))
    with pytest.raises(ValueError, match="bool tensor"):
        InputLoss(arrived.float())
    with pytest.raises(ValueError, match=r"\[B, T\]"):
        InputLoss(arrived[0, 0])
    with pytest.raises(ValueError, match="is not a OnLoss"):
        InputLoss(arrived, "drop")
    with pytest.raises(ValueError, match="acknowledged"):
        InputLoss(arrived, acknowledged="yes")
    with pytest.raises(TypeError, match="input_loss must be"):
        closed_loop(plant, T, input_loss=arrived, **kw)
    with pytest.raises(ValueError, match=r"\[4, T >= 25\]"):
        closed_loop(plant, T, input_loss=InputLoss(arrived[:, :10]), **kw)
    with pytest.raises(ValueError, match="dim_u"):
        closed_loop(plant, T, input_loss=InputLoss(torch.ones(B, T, 3, dtype=torch.bool)), **kw)
    with pytest.raises(ValueError, match="no input to lose"):
        closed_loop(plant, T, noise=noise, x0=x0, input_loss=InputLoss(arrived))


class _FirstActuator(Attack):
    """``values[k − 1]`` on the actuators, flagged entry by entry where non-zero."""

    channel = Channel.ACTUATOR
    reads_state = False

    def __init__(self, values):
        self.values = values

    def init(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        return None

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        value = self.values[k - 1].expand_as(u)
        return state, value, value != 0


def test_an_attack_on_one_actuator_is_carried_by_that_actuators_held_input():
    """Flags entry by entry: under hold a step after the attack's own is attacked where the
    attacked actuator still holds an input that carries it (its own packets decide, not
    the other actuator's)."""
    plant = _plant()
    noise, us, arrived, x0 = _setup(per_actuator=True, seed=5)
    values = torch.zeros(T, 2, dtype=torch.float64)
    values[4:6, 0] = 0.9  # the first actuator alone
    got = closed_loop(plant, T, noise=noise, x0=x0, controller=KnownInputs(us),
                      attack=_FirstActuator(values), input_loss=InputLoss(arrived, "hold"))  # fmt: skip
    tr = got.trajectories
    own, carried, expected = values[:, 0] != 0, torch.zeros(B, dtype=torch.bool), []
    for t in range(T):
        carried = torch.where(arrived[:, t, 0], own[t].expand(B), carried)
        expected.append(own[t] | carried)
    expected = torch.stack(expected, 1)
    assert torch.equal(tr.flags, expected)
    assert bool((expected & ~own).any())  # carried beyond its window somewhere
    either = []  # had any actuator's arrival decided, the flags would differ
    carried = torch.zeros(B, dtype=torch.bool)
    for t in range(T):
        carried = torch.where(arrived[:, t].any(-1), own[t].expand(B), carried)
        either.append(own[t] | carried)
    assert not torch.equal(expected, torch.stack(either, 1))


def test_one_link_for_every_actuator_and_what_input_loss_refuses():
    """A schedule's [B, T, 1] mask is one packet for every actuator; a covert attack (its
    concealment assumes its packets arrive) and a holding loop resumed from a state that
    holds nothing are refused, naming why."""
    from difffilter.threats import Bias, Covert

    plant = _plant()
    noise, us, arrived, x0 = _setup()
    kw = dict(noise=noise, x0=x0, controller=KnownInputs(us))
    one = closed_loop(plant, T, input_loss=InputLoss(arrived.unsqueeze(-1)), **kw)
    two = closed_loop(plant, T, input_loss=InputLoss(arrived), **kw)
    assert torch.equal(one.trajectories.x, two.trajectories.x)
    covert = Covert(Bias(0.5, channel="actuator", onset=3), plant)
    with pytest.raises(ValueError, match="conceals"):
        closed_loop(plant, T, attack=covert, input_loss=InputLoss(arrived), **kw)
    zero = closed_loop(plant, 10, horizon=T, input_loss=InputLoss(arrived, "zero"), **kw)
    with pytest.raises(ValueError, match="on_loss='zero'"):
        closed_loop(plant, 5, state=zero.state, noise=noise, controller=KnownInputs(us),
                    input_loss=InputLoss(arrived, "hold"))  # fmt: skip
