"""The two drivers: the open loop and the closed loop, with the attacker inside the loop."""

from __future__ import annotations

import pytest
import torch

import difffilter as df
from difffilter.attack import Attack, Channel
from difffilter.loop import DrawnNoise, KnownInputs, ReplayedNoise, closed_loop, open_loop
from difffilter.models import registry
from difffilter.models.attacks import Replay, SensorBias, Signal
from difffilter.models.lfc import LFCPlant, lfc_loop
from difffilter.models.streams import Streams


def _linear(dtype=torch.float64):
    F = torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=dtype)
    eye = torch.eye(2, dtype=dtype)
    B = torch.tensor([[0.0], [0.1]], dtype=dtype)
    return df.LinearGaussianModel(F, eye, 1e-3 * eye, 1e-2 * eye, torch.zeros(2, dtype=dtype),
                                  eye, B=B)  # fmt: skip


def test_replay_delivers_the_plants_own_delayed_output_in_the_open_loop():
    """Four-tank, the same Replay object as in the LFC loop below: from k₀ on, the d
    measurements before k₀ in order, cycled (ỹ_k = y_{k−d} over the first d steps)."""
    sc = registry.get("four_tank_bias")
    streams = Streams(0)
    d, k0 = 7, 20
    gens = {k: streams(k) for k in ("plant", "attack", "schedule")}
    tr = sc.simulate(4, gens, attack=REPLAY)
    t0 = k0 - 1  # time index of k0
    assert torch.equal(tr.y_recv[:, :t0], tr.y_true[:, :t0])
    recorded = t0 - d + torch.arange(tr.y_true.shape[1] - t0) % d  # cycling its recording
    assert torch.equal(tr.y_recv[:, t0:], tr.y_true[:, recorded])  # bit for bit
    assert not tr.flags[:, :t0].any() and tr.flags[:, t0:].all()
    torch.testing.assert_close(tr.attack, tr.y_recv - tr.y_true, rtol=0, atol=0)
    assert REPLAY.delay == d and REPLAY.onset == k0


REPLAY = Replay(delay=7, onset=20)


def test_replay_delivers_the_plants_own_delayed_output_in_the_lfc_closed_loop():
    """In the closed loop the plant's output depends on the estimator through the controller:
    the replayed measurements are this loop's own outputs before the onset, cycled; a live
    replay (a time-delay attack) hands this loop's own output of d steps before, also
    those of the attacked steps."""
    plant = LFCPlant()
    xi, theta = plant.sample_noise(3, 60, torch.Generator().manual_seed(2))
    load = torch.tensor([[0.01, 0.0]], dtype=torch.float64)
    loop = lfc_loop(plant, df.KalmanFilter(), xi, theta, load, attack=REPLAY)
    tr, d, t0 = loop.trajectories, REPLAY.delay, REPLAY.onset - 1
    recorded = t0 - d + torch.arange(60 - t0) % d
    assert torch.equal(tr.y_recv[:, t0:], tr.y_true[:, recorded])
    assert torch.equal(tr.y_recv[:, :t0], tr.y_true[:, :t0]) and tr.flags[:, t0:].all()
    live = lfc_loop(plant, df.KalmanFilter(), xi, theta, load,
                    attack=Replay(delay=d, onset=REPLAY.onset, live=True)).trajectories  # fmt: skip
    assert torch.equal(live.y_recv[:, t0:], live.y_true[:, t0 - d : -d])
    # the replayed data fool the observer: its estimate follows the old measurements
    free = lfc_loop(plant, df.KalmanFilter(), xi, theta, load)
    assert not torch.equal(loop.trajectories.x, free.trajectories.x)


def test_the_closed_loop_with_known_inputs_is_the_simulation_plus_the_open_loop():
    """An estimator inside the closed loop (the known inputs as the controller) sees what it
    would see on the simulated data: the same states, the same estimates."""
    model = _linear()
    us = 0.3 * torch.randn(
        5, 30, 1, generator=torch.Generator().manual_seed(1), dtype=torch.float64
    )
    attack = SensorBias(gamma_bar=(0.5, -0.2), p_l=0.5)
    x0 = model.initial.mean.expand(5, 2).clone()
    inside = closed_loop(model, 30, noise=DrawnNoise(torch.Generator().manual_seed(3)), x0=x0,
                         estimator=df.KalmanFilter(), controller=KnownInputs(us), attack=attack,
                         attack_generator=torch.Generator().manual_seed(4))  # fmt: skip
    sim = closed_loop(model, 30, noise=DrawnNoise(torch.Generator().manual_seed(3)), x0=x0,
                      controller=KnownInputs(us), attack=attack,
                      attack_generator=torch.Generator().manual_seed(4))  # fmt: skip
    tr = sim.trajectories
    assert torch.equal(inside.trajectories.x, tr.x) and torch.equal(
        inside.trajectories.y_recv, tr.y_recv
    )
    assert torch.equal(tr.us, us) and sim.output is None
    out = open_loop(df.KalmanFilter(), model, tr.y_recv, tr.us)
    torch.testing.assert_close(inside.output.means, out.means, rtol=0, atol=1e-12)
    # the bias attack: recorded as injected (up to the sum's round-off), flagged where injected
    torch.testing.assert_close(tr.attack, tr.y_recv - tr.y_true, rtol=0, atol=1e-15)
    assert torch.equal(tr.flags, tr.attack.abs().sum(-1) > 0)


def test_a_loop_run_in_chunks_is_the_loop_run_at_once():
    """Truncated backpropagation runs the loop in chunks from its LoopState: the same loop."""
    plant = LFCPlant()
    xi, theta = plant.sample_noise(2, 40, torch.Generator().manual_seed(5))
    load = torch.tensor([[0.01, 0.0]], dtype=torch.float64)
    alpha = torch.zeros(40, 10, dtype=torch.float64)
    alpha[10:25, 2] = 0.4
    whole = lfc_loop(plant, df.KalmanFilter(), xi, theta, load, attack=Signal(alpha))
    first = lfc_loop(plant, df.KalmanFilter(), xi, theta, load, attack=Signal(alpha), steps=15)
    second = lfc_loop(plant, df.KalmanFilter(), xi, theta, load, attack=Signal(alpha), steps=25,
                      state=first.state.detach())  # fmt: skip
    joined = torch.cat([first.trajectories.x, second.trajectories.x], 1)
    assert torch.equal(joined, whole.trajectories.x)
    means = torch.cat([first.output.means, second.output.means], 1)
    assert torch.equal(means, whole.output.means) and second.state.k == 40


def _forked_pair(attack, k=12, T=30, runs=3):
    """The loop with ``attack`` run at once, and continued from the fork after step ``k`` of
    the same loop without attack (a particle filter: its generators are in the carry)."""
    model = _linear()
    gen = torch.Generator().manual_seed(7)
    noise = ReplayedNoise(0.03 * torch.randn(runs, T, 2, generator=gen, dtype=torch.float64),
                          0.1 * torch.randn(runs, T, 2, generator=gen, dtype=torch.float64))  # fmt: skip
    us = 0.3 * torch.randn(runs, T, 1, generator=gen, dtype=torch.float64)
    x0 = model.initial.mean.expand(runs, 2).clone()

    def loop(**kw):
        return closed_loop(model, kw.pop("steps", T), noise=noise, x0=x0, controller=KnownInputs(us),
                           estimator=df.ParticleFilter(num_particles=64),
                           generator=torch.Generator().manual_seed(11), **kw)  # fmt: skip

    forks = {k: None}
    free = loop(forks=forks)
    return (
        loop(attack=attack),
        loop(attack=attack, fork=forks[k], steps=T - k),
        free,
        forks[k],
        loop,
    )


def test_a_loop_continued_from_the_fork_of_its_loop_without_attack_is_the_loop_at_once():
    """The attacked loop from the fork at its onset: the same states, draws, estimates and
    records, bit for bit; the fork is unchanged by the loops that went on from it."""
    alpha = torch.zeros(30, 2, dtype=torch.float64)
    alpha[12:20, 1] = 0.5
    whole, forked, free, fork, loop = _forked_pair(Signal(alpha))
    for field in ("x", "y_true", "y_recv", "us", "attack", "flags"):
        assert torch.equal(getattr(forked.trajectories, field), getattr(whole.trajectories, field))
    assert torch.equal(
        forked.trajectories.info["attack_values"], whole.trajectories.info["attack_values"]
    )
    assert torch.equal(forked.output.means, whole.output.means) and forked.state.k == 30
    assert torch.equal(forked.output.extras["ess"], whole.output.extras["ess"])
    assert torch.equal(free.output.means[:, :12], whole.output.means[:, :12])  # before the onset
    assert not torch.equal(free.output.means[:, 12:], whole.output.means[:, 12:])
    again = loop(attack=Signal(alpha), fork=fork, steps=18)  # the fork's generators are copies
    assert torch.equal(again.output.means, whole.output.means)
    assert fork.state.k == 12 and len(fork.outputs) == 12 and fork.records["attack"][0] is None


def test_a_fork_refuses_what_it_cannot_replay():
    alpha = torch.zeros(30, 2, dtype=torch.float64)
    alpha[5, 0] = 1.0  # acts before the fork at 12
    with pytest.raises(ValueError, match="acts at step 6, at or before the fork.s step 12"):
        _forked_pair(Signal(alpha))
    with pytest.raises(ValueError, match="must read nothing"):
        _forked_pair(Replay(delay=3, onset=20))
    model = _linear()
    x0 = model.initial.mean.expand(2, 2).clone()
    with pytest.raises(ValueError, match="need ReplayedNoise"):
        closed_loop(model, 5, noise=DrawnNoise(torch.Generator().manual_seed(1)), x0=x0,
                    forks={2: None})  # fmt: skip
    fork = _forked_pair(None)[3]
    noise = ReplayedNoise(
        torch.zeros(2, 30, 2, dtype=torch.float64), torch.zeros(2, 30, 2, dtype=torch.float64)
    )
    with pytest.raises(ValueError, match="either state= or fork="):
        closed_loop(model, 5, noise=noise, fork=fork, state=fork.state)


def test_the_lfc_attack_onset_is_the_first_step_any_run_is_attacked():
    """Read off the attack's own table as the loop draws it; unknown for attacks that read
    the loop (a replay) and for none."""
    from difffilter.eval.robustness import load_threat_set

    sc = registry.get("lfc_step")
    draws = sc.exogenous(
        3, {"plant": torch.Generator().manual_seed(0), "attack": torch.Generator().manual_seed(1)}
    )
    threats = load_threat_set(
        sc, ["bias", "bias_all_channels_half_runs", "replay", "covert"]
    ).threats
    assert sc.attack_onset(draws) == 299 == registry.get("lfc_sine").attack_onset(draws)
    assert registry.get("lfc_sawtooth").attack_onset(draws) == 0
    assert sc.with_threat(threats["bias"]).attack_onset(draws) == 299  # onset: 300 (k)
    assert sc.with_threat(threats["bias_all_channels_half_runs"]).attack_onset(draws) == 299
    for none in (threats["replay"], threats["covert"], None):
        assert sc.with_threat(none).attack_onset(draws) is None


class _Adaptive(Attack):
    """An adaptive attacker: pushes the received measurement against the estimator's last
    estimate (it reads the view), from step 2 on."""

    channel = Channel.SENSOR
    reads_view = True

    def init(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        return []

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        seen = state + [None if view is None else view.mean.clone()]
        value = torch.zeros_like(y) if view is None else -view.mean
        return seen, value, torch.full(y.shape[:-1], view is not None)


def test_an_adaptive_attack_reads_the_estimators_previous_output():
    model = _linear()
    x0 = model.initial.mean.expand(2, 2).clone()
    attack = _Adaptive()
    loop = closed_loop(model, 6, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                       estimator=df.KalmanFilter(), attack=attack)  # fmt: skip
    seen = loop.state.attack
    assert seen[0] is None  # nothing to read before the first estimate
    for k in range(1, 6):  # at step k + 1 it read the estimate of step k
        torch.testing.assert_close(seen[k], loop.output.means[:, k - 1], rtol=0, atol=0)
    torch.testing.assert_close(loop.trajectories.attack[:, 1:], -loop.output.means[:, :-1])


class _Poison(Attack):
    """Injects ``value`` on entry 1 of every run at step 3 (``width``: the value's entries)."""

    channel = Channel.SENSOR

    def __init__(self, value, width=None):
        self.value, self.width = value, width

    def init(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        return None

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        width = y.shape[-1] if self.width is None else self.width
        value = torch.zeros(*y.shape[:-1], width, dtype=y.dtype)
        value[..., min(1, width - 1)] = self.value
        return state, value, torch.full(y.shape[:-1], k == 3)


def test_a_nan_or_inf_injected_into_the_loop_is_refused_where_it_is_received():
    """The estimator's step takes the received measurement unchecked: the loop refuses a
    non-finite received entry as open_loop refuses it in ys (an EKF filtered it into NaN
    estimates); an entry the schedule drops may hold anything."""
    model = _linear()
    x0 = model.initial.mean.expand(3, 2).clone()

    def run(value, mask=None, estimator=None):
        estimator = estimator or df.ExtendedKalmanFilter()
        return closed_loop(model, 5, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                           estimator=estimator, attack=_Poison(value), mask=mask)  # fmt: skip

    for value in (float("nan"), float("inf"), -float("inf")):
        with pytest.raises(ValueError, match=r"received at step 3 .*run 0, entry 1.*\(_Poison\)"):
            run(value)
    dropped = torch.ones(3, 5, 2, dtype=torch.bool)
    dropped[:, 2, 1] = False  # entry 1 of step 3 never arrives
    loop = run(float("nan"), dropped, df.KalmanFilter())
    assert loop.trajectories.y_recv[:, 2, 1].isnan().all() and loop.output.means.isfinite().all()

    # without an estimator (the simulation) the same: refused where received (README, "Input
    # validation"; it had been recorded silently), recorded where the schedule drops it
    def sim(mask=None):
        return closed_loop(model, 5, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                           attack=_Poison(float("nan")), mask=mask)  # fmt: skip

    with pytest.raises(ValueError, match=r"received at step 3 .*run 0, entry 1.*\(_Poison\)"):
        sim()
    assert sim(dropped).trajectories.y_recv[:, 2, 1].isnan().all()


def test_the_loop_names_a_wrong_attack_estimator_or_attack_value():
    model = _linear()
    x0 = model.initial.mean.expand(2, 2).clone()
    loop = lambda **kw: closed_loop(model, 4, noise=DrawnNoise(None), x0=x0, **kw)  # noqa: E731
    with pytest.raises(TypeError, match="attack must be a difffilter.attack.Attack.*got dict"):
        loop(attack={"kind": "bias"})
    with pytest.raises(TypeError, match="estimator must be a difffilter.estimator.Estimator"):
        loop(estimator=df.kalman_step)
    with pytest.raises(
        ValueError, match=r"_Poison.step returned a value of shape \(2, 3\) at step 1"
    ):
        loop(attack=_Poison(1.0, width=3), estimator=df.KalmanFilter())
    # one value for two sensors: refused, not broadcast to both (a trial's attack on sensor 0)
    with pytest.raises(
        ValueError, match=r"_Poison.step returned a value of shape \(2, 1\) at step 1.*2 entries"
    ):
        loop(attack=_Poison(1.0, width=1), estimator=df.KalmanFilter())
    # an adaptive attack without an estimator to read
    with pytest.raises(ValueError, match="_Adaptive reads the estimator's output.*no estimator"):
        loop(attack=_Adaptive())


class _Returns(Attack):
    """Returns ``make(y, k) -> (value, flag)`` at every step; counts the views it got."""

    channel = Channel.SENSOR

    def __init__(self, make):
        self.make, self.views = make, 0

    def init(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        return None

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        self.views += view is not None
        return (state, *self.make(y, k))


def test_an_attacks_flag_and_value_are_checked_and_one_value_for_every_run_is_expanded():
    """A user trial: a value [dy] for every run beside a per-run flag [B] was read per entry
    where B = dy (runs flagged clean were attacked, and the recorded attack lost its
    entries); a Python bool, float or int flag, or one of the wrong batch, failed in torch."""
    model = _linear()
    x0 = model.initial.mean.expand(2, 2).clone()  # B = dy = 2

    def loop(make):
        return closed_loop(model, 3, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                           estimator=df.KalmanFilter(), attack=_Returns(make))  # fmt: skip

    one = loop(lambda y, k: (torch.tensor([0.5, 0.25], dtype=y.dtype), torch.tensor([True, False])))
    traj = one.trajectories
    assert traj.attack.shape == (2, 3, 2)  # [B, T, dy]
    torch.testing.assert_close(traj.attack[0], torch.tensor([[0.5, 0.25]] * 3, dtype=torch.float64))
    assert traj.attack[1].eq(0).all() and traj.flags[:, 0].tolist() == [True, False]
    full = lambda y: torch.zeros_like(y)  # noqa: E731
    for make, why in (
        (lambda y, k: (full(y), True), "a flag of bool at step 1; a flag is a bool tensor"),
        (lambda y, k: (full(y), torch.ones(2)), "a flag of dtype torch.float32 at step 1"),
        (lambda y, k: (full(y), torch.ones(2, dtype=torch.long)), "a flag of dtype torch.int64"),
        (lambda y, k: (full(y), torch.ones(3, dtype=torch.bool)),
         r"a flag of shape \(3,\) at step 1; the signal it attacks is \(2, 2\)"),
        (lambda y, k: (full(y).float(), torch.ones(2, dtype=torch.bool)),
         "a value of dtype torch.float32 at step 1; the signal it attacks is torch.float64"),
        (lambda y, k: (torch.zeros(3, 2, dtype=y.dtype), torch.ones(2, dtype=torch.bool)),
         r"a value of shape \(3, 2\) at step 1"),
    ):  # fmt: skip
        with pytest.raises(ValueError, match=f"attack _Returns.step returned {why}"):
            loop(make)
    # a flag [1] for the two runs (a closed-loop trial: recorded as flags [1, T] beside runs
    # [2, T]) and a per-entry flag [1, 2] are expanded to the runs, as a value [1, 2] is; a
    # value [2, 1] is refused (one entry for two: a trial's attack on sensor 0 hit both)
    ones = loop(lambda y, k: (torch.ones(1, 2, dtype=y.dtype), torch.ones(1, dtype=torch.bool)))
    assert ones.trajectories.flags.shape == (2, 3) and bool(ones.trajectories.flags.all())
    assert ones.trajectories.attack.eq(1).all()
    entry = loop(lambda y, k: (full(y) + 1, torch.tensor([[False, True]])))
    assert entry.trajectories.info["attack_flags"].shape == (2, 3, 2)
    assert (
        entry.trajectories.attack[..., 0].eq(0).all()
        and entry.trajectories.attack[..., 1].eq(1).all()
    )

    class AsList(_Returns):  # a list or a namedtuple of three is three values
        def step(self, state, k, *, y=None, x=None, u=None, view=None):
            return [state, torch.zeros_like(y), torch.zeros(y.shape[:-1], dtype=torch.bool)]

    closed_loop(model, 3, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                estimator=df.KalmanFilter(), attack=AsList(None))  # fmt: skip

    class Two(_Returns):
        def step(self, state, k, *, y=None, x=None, u=None, view=None):
            return state, torch.zeros_like(y)  # no flag

    with pytest.raises(ValueError, match=r"attack Two.step returned 2 values at step 1; it "
                       r"returns \(state, value, flag\)"):  # fmt: skip
        closed_loop(model, 3, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                    estimator=df.KalmanFilter(), attack=Two(None))  # fmt: skip


def test_an_actuator_attacks_broadcast_flag_and_its_count_of_values_are_checked_too():
    """The actuator branch of the loop (a mutation review: the flag's expansion to the runs
    and the check of three values had been tested on the sensor branch alone)."""

    class OnInputs(Attack):
        channel = Channel.ACTUATOR

        def init(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
            return None

        def step(self, state, k, *, y=None, x=None, u=None, view=None):
            return state, torch.ones_like(u), torch.ones(1, dtype=torch.bool)

    class Two(OnInputs):
        def step(self, state, k, *, y=None, x=None, u=None, view=None):
            return state, torch.ones_like(u)

    model = _linear()
    x0 = model.initial.mean.expand(2, 2).clone()
    inputs = KnownInputs(torch.zeros(2, 3, 1, dtype=torch.float64))

    def run(attack):
        return closed_loop(model, 3, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                           controller=inputs, attack=attack)  # fmt: skip

    flags = run(OnInputs()).trajectories.flags
    assert flags.shape == (2, 3) and bool(flags.all())
    with pytest.raises(ValueError, match=r"attack Two.step returned 2 values at step 1"):
        run(Two())


def test_only_an_attack_that_reads_the_view_gets_it():
    """An attack without ``reads_view`` read the estimator's output in closed_loop, and got
    None under an open-loop scenario's with_threat (a user trial: it silently injected
    nothing there): it gets None in both."""
    model = _linear()
    x0 = model.initial.mean.expand(2, 2).clone()
    quiet = _Returns(lambda y, k: (torch.zeros_like(y), torch.zeros(2, dtype=torch.bool)))
    closed_loop(model, 4, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                estimator=df.KalmanFilter(), attack=quiet)  # fmt: skip
    assert quiet.views == 0
    quiet.reads_view = True
    closed_loop(model, 4, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                estimator=df.KalmanFilter(), attack=quiet)  # fmt: skip
    assert quiet.views == 3  # steps 2, 3, 4 read the output of the step before


def test_an_adaptive_attack_is_refused_where_no_estimator_is_in_the_loop():
    """An open-loop scenario simulates its runs once, without an estimator: an attack that
    reads the estimator's output would read None there (it silently acted as a plain
    attack). A closed-loop scenario runs each estimator in its own loop: accepted."""
    with pytest.raises(
        ValueError, match="_Adaptive reads the estimator's output.*'four_tank_bias'"
    ):
        registry.get("four_tank_bias").with_threat(_Adaptive())
    assert registry.get("lfc_step").with_threat(_Adaptive()).threat is not None


def test_replay_and_the_loop_refuse_bad_arguments():
    with pytest.raises(ValueError, match="onset must exceed delay"):
        Replay(delay=5, onset=5)
    with pytest.raises(ValueError, match="steps"):
        closed_loop(_linear(), 0, noise=DrawnNoise(None), x0=torch.zeros(1, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="x0"):
        closed_loop(_linear(), 3, noise=DrawnNoise(None))
    with pytest.raises(TypeError, match="Estimator"):
        open_loop(df.kalman_step, _linear(), torch.zeros(1, 3, 2, dtype=torch.float64))
    f64 = torch.float64
    x0 = torch.zeros(3, 2, dtype=f64)
    with pytest.raises(ValueError, match=r"x0 \[B, 2\]"):  # two batch dimensions: time misplaced
        closed_loop(_linear(), 3, noise=DrawnNoise(None), x0=torch.zeros(2, 3, 2, dtype=f64))
    with pytest.raises(ValueError, match="horizon"):
        closed_loop(_linear(), 6, noise=DrawnNoise(None), x0=x0, horizon=3)
    with pytest.raises(ValueError, match="mask must be"):
        closed_loop(_linear(), 6, noise=DrawnNoise(None), x0=x0,
                    mask=torch.ones(3, 4, 2, dtype=torch.bool))  # fmt: skip
    for process, measurement in [
        (torch.zeros(3, 6, 1, dtype=f64), torch.zeros(3, 6, 2, dtype=f64)),  # width 1, dx = 2
        (torch.zeros(1, 6, 2, dtype=f64), torch.zeros(1, 6, 2, dtype=f64)),  # one run of three
        (torch.zeros(3, 4, 2, dtype=f64), torch.zeros(3, 4, 2, dtype=f64)),  # 4 rows, 6 steps
    ]:
        with pytest.raises(ValueError, match="ReplayedNoise's process noise must be"):
            closed_loop(_linear(), 6, noise=ReplayedNoise(process, measurement), x0=x0)
    us = torch.ones(3, 3, 1, dtype=f64)
    with pytest.raises(ValueError, match="known inputs"):  # it repeated u_2 for u_3 … u_5
        closed_loop(_linear(), 6, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                    controller=KnownInputs(us))  # fmt: skip


def test_a_step_is_attacked_where_an_attacked_entry_was_received():
    """A per-entry attack under a schedule: the attack on entry 1 counts at the steps entry
    1 arrives, not wherever any entry arrives, and a lost entry records no attack (the flags
    were reduced over entries before the mask: every step counted)."""
    from difffilter.models.scenario import simulate
    from difffilter.models.schedules import RoundRobin
    from difffilter.threats import Bias

    tr = simulate(_linear(), 2, 6, generators={"plant": torch.Generator().manual_seed(0)},
                  attack=Bias(value=1.0, onset=1, entries=(1,)),
                  schedule=RoundRobin(groups=((0,), (1,))))  # fmt: skip
    assert tr.mask[0, :, 1].tolist() == [False, True] * 3
    assert tr.flags.tolist() == [[False, True] * 3] * 2
    expected = torch.zeros(2, 6, 2, dtype=torch.float64)
    expected[:, 1::2, 1] = 1.0
    assert torch.equal(tr.attack, expected)
    assert bool(tr.info["attack_flags"][..., 1].all())  # the attack's own flags, before the mask


def test_an_unflagged_non_finite_value_is_not_injected():
    from difffilter.attack import inject

    y = torch.zeros(2, dtype=torch.float64)
    value = torch.tensor([float("inf"), 1.0], dtype=torch.float64)
    received, change = inject(Channel.SENSOR, y, value, torch.tensor([False, True]))
    assert received.tolist() == [0.0, 1.0] and change.tolist() == [0.0, 1.0]


def test_an_actuator_attack_needs_an_input_to_attack():
    """A docs check: without a controller the loop has no u, and the attack's step failed in
    the loop's own checks (AttributeError on None)."""

    class Push(Attack):
        channel = Channel.ACTUATOR

        def init(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
            return None

        def step(self, state, k, *, y=None, x=None, u=None, view=None):
            return state, torch.ones_like(u), torch.ones(u.shape[:-1], dtype=torch.bool)

    model = _linear()
    x0 = model.initial.mean.expand(2, 2).clone()
    with pytest.raises(ValueError, match="Push acts on the actuators, and this loop has no input"):
        closed_loop(model, 3, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                    attack=Push())  # fmt: skip
    us = torch.zeros(2, 3, 1, dtype=torch.float64)
    loop = closed_loop(model, 3, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                       controller=KnownInputs(us), attack=Push())  # fmt: skip
    assert loop.trajectories.attack.eq(1).all()
    # a plant without inputs: no controller helps (a trial was told to give it one)
    eye = torch.eye(2, dtype=torch.float64)
    still = df.LinearGaussianModel(eye, eye, 1e-3 * eye, 1e-2 * eye,
                                   torch.zeros(2, dtype=torch.float64), eye)  # fmt: skip
    with pytest.raises(ValueError, match=r"Push acts on the actuators, and the plant has no "
                       r"input \(dim_u = 0\): an actuator attack needs a model with inputs"):  # fmt: skip
        closed_loop(still, 3, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                    attack=Push())  # fmt: skip


class _Feedback:
    """``u_k = −K x̂_k`` on the estimate, or what ``make(k, out)`` returns where given."""

    def __init__(self, make=None, first=None):
        self.make, self.first = make, first

    def init(self, batch_shape, dtype, device):
        if self.first is not None:
            return self.first(batch_shape, dtype, device)
        return torch.zeros(*batch_shape, 1, dtype=dtype, device=device)

    def __call__(self, k, y, out):
        if self.make is not None:
            return self.make(k, out)
        return -0.5 * out.mean[..., 1:]


def test_the_closed_loop_checks_the_controllers_input_and_names_it():
    """A controller's input of the wrong shape grew the plant's state by an axis a step
    (memory ×B a step, then an error at the final stack naming nothing); a ``None`` from
    ``init`` on a plant with inputs dropped the record of the inputs; a NaN input was
    blamed on the plant a step later, or ran through the loop where the measurements it
    spoiled were dropped."""
    model = _linear()
    x0 = model.initial.mean.expand(4, 2).clone()

    def loop(controller, **kw):
        return closed_loop(model, 6, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                           estimator=df.KalmanFilter(), controller=controller, **kw)  # fmt: skip

    good = loop(_Feedback())
    assert good.trajectories.us.shape == (4, 6, 1) and good.output.means.isfinite().all()
    for make, match in (
        (lambda k, out: -0.5 * out.mean[..., 1:, None], r"__call__ returned an input of shape "
                                                        r"\(4, 1, 1\) at step 1 \(u_1\)"),
        (lambda k, out: torch.zeros(1, dtype=torch.float64), r"shape \(1,\) at step 1.*\[4, 1\]"),
        (lambda k, out: torch.zeros(4, 2, dtype=torch.float64), r"shape \(4, 2\).*dim_u = 1"),
        (lambda k, out: torch.zeros(4, 1, dtype=torch.float32), "dtype torch.float32"),
        (lambda k, out: 0.0, "returned a float at step 1"),
    ):  # fmt: skip
        with pytest.raises((ValueError, TypeError), match=match):
            loop(_Feedback(make))
    with pytest.raises(ValueError, match=r"_Feedback.init returned None \(u_0\).*1 input"):
        loop(_Feedback(first=lambda *a: None))

    def nan_from(step):
        return lambda k, out: torch.full((4, 1), float("nan") if k >= step else 0.0,
                                         dtype=torch.float64)  # fmt: skip

    with pytest.raises(ValueError, match=r"u_3 that drives step 4 .*the controller at step 3"):
        loop(_Feedback(nan_from(3)))
    dropped = torch.zeros(4, 6, 2, dtype=torch.bool)  # nothing arrives: the NaN hid before
    with pytest.raises(ValueError, match=r"u_3 that drives step 4"):
        loop(_Feedback(nan_from(3)), mask=dropped)
    nan_first = lambda b, dtype, device: torch.full((*b, 1), float("nan"), dtype=dtype)  # noqa: E731
    with pytest.raises(ValueError, match=r"u_0 that drives step 1 .*controller.init"):
        loop(_Feedback(first=nan_first))


def test_the_closed_loop_refuses_a_mask_or_dtypes_it_would_misread():
    """A mask wider than ``dy`` or of floats ran (a float mask weighted the update: 0.32
    off a masked filter's estimates; 0.54 with extra columns); dtypes that differ failed
    deep in torch naming no argument."""
    model = _linear()
    x0 = model.initial.mean.expand(3, 2).clone()

    def loop(**kw):
        kw = {"x0": x0, "estimator": df.KalmanFilter(), **kw}
        return closed_loop(model, 5, noise=DrawnNoise(torch.Generator().manual_seed(0)), **kw)

    with pytest.raises(ValueError, match=r"mask must be \[3, T >= 5, 2\].*got \(3, 5, 3\)"):
        loop(mask=torch.ones(3, 5, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"mask must be \[3, T >= 5, 2\].*got \(1, 5, 2\)"):
        loop(mask=torch.ones(1, 5, 2, dtype=torch.bool))
    with pytest.raises(ValueError, match="mask must be a bool tensor.*torch.float64"):
        loop(mask=torch.full((3, 5, 2), 0.5, dtype=torch.float64))
    with pytest.raises(ValueError, match="x0 is torch.float32 and the plant is torch.float64"):
        loop(x0=x0.float())
    with pytest.raises(ValueError, match="the estimator's model is torch.float32"):
        loop(model=_linear(torch.float32))
    noise = ReplayedNoise(torch.zeros(3, 5, 2), torch.zeros(3, 5, 2))
    with pytest.raises(ValueError, match="process noise is torch.float32, the loop's state"):
        closed_loop(model, 5, noise=noise, x0=x0)


def test_the_closed_loop_refuses_an_estimator_model_that_does_not_fit_the_plant():
    """From a closed-loop design trial: an estimator model of another ``dim_y`` was fed the
    plant's one measurement broadcast into both entries (estimates 0.90 off, silently), one
    without an input ignored every ``u`` (0.92 off), one of another ``dim_u`` failed inside
    torch ("mat1 and mat2 shapes cannot be multiplied")."""
    plant = _linear()
    F, H, Q, R = plant.F, plant.H, plant.process_noise.cov, plant.measurement_noise.cov
    x0 = plant.initial.mean.expand(2, 2).clone()

    def loop(model):
        return closed_loop(plant, 4, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                           estimator=df.KalmanFilter(), model=model, controller=_Feedback())  # fmt: skip

    prior = (plant.initial.mean, plant.initial.cov)
    one_sensor = df.LinearGaussianModel(F, H[:1], Q, R[:1, :1], *prior, B=plant.B)
    with pytest.raises(ValueError, match="measures 1 entries and the plant 2"):
        loop(one_sensor)
    blind = df.LinearGaussianModel(F, H, Q, R, *prior)
    with pytest.raises(ValueError, match=r"has 0 input\(s\) \(dim_u\) and the plant 1"):
        loop(blind)
    two_inputs = df.LinearGaussianModel(F, H, Q, R, *prior, B=plant.B.expand(2, 2))
    with pytest.raises(ValueError, match=r"has 2 input\(s\)"):
        loop(two_inputs)
    sweep = df.LinearGaussianModel(F.expand(3, 2, 2), H, Q, R, *prior, B=plant.B)
    with pytest.raises(
        ValueError,
        match=r"the loop's runs \(x0 broadcast.*\(2,\) does not "
        r"broadcast with the batch shape \(3,\)",
    ):
        loop(sweep)
    # without a controller the estimator gets no input: a model that knows none is right
    free = closed_loop(plant, 4, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                       estimator=df.KalmanFilter(), model=blind)  # fmt: skip
    assert free.output.means.shape == (2, 4, 2)


def test_a_sweep_loop_from_one_initial_state_runs_one_loop_per_parameter_set():
    """``x0 [1, dx]`` on a plant of 3 parameter sets with a controller ran every step and
    failed in a torch stack at the end (the controller's ``u_0`` had x0's one run); it is
    the loop from x0 repeated for every set, and a batch that fits neither is named."""
    plant = _linear()
    gains = torch.tensor([0.9, 1.0, 1.05], dtype=torch.float64)
    sweep = df.LinearGaussianModel(plant.F * gains[:, None, None], plant.H,
                                   plant.process_noise.cov, plant.measurement_noise.cov,
                                   plant.initial.mean, plant.initial.cov, B=plant.B)  # fmt: skip
    gen = torch.Generator().manual_seed(1)
    noise = ReplayedNoise(0.03 * torch.randn(3, 5, 2, dtype=torch.float64, generator=gen),
                          0.1 * torch.randn(3, 5, 2, dtype=torch.float64, generator=gen))  # fmt: skip
    x0 = torch.tensor([[0.3, -0.2]], dtype=torch.float64)

    def loop(x0):
        return closed_loop(sweep, 5, noise=noise, x0=x0, estimator=df.KalmanFilter(),
                           controller=_Feedback())  # fmt: skip

    one, each = loop(x0), loop(x0.expand(3, 2).clone())
    assert one.trajectories.x.shape == (3, 5, 2) and one.trajectories.us.shape == (3, 5, 1)
    torch.testing.assert_close(one.trajectories.x, each.trajectories.x, rtol=0, atol=0)
    torch.testing.assert_close(one.output.means, each.output.means, rtol=0, atol=0)
    with pytest.raises(
        ValueError,
        match=r"x0's runs \(4,\) does not broadcast with the batch "
        r"shape \(3,\)",
    ):
        loop(x0.expand(4, 2).clone())


def test_the_closed_loop_names_a_controller_that_is_not_one():
    """A plain function or a gain tensor as ``controller`` failed with "'function' object
    has no attribute 'init'"."""
    plant = _linear()
    x0 = plant.initial.mean.expand(2, 2).clone()
    for controller, name in ((lambda k, y, out: -out.mean[..., 1:], "function"),
                             (torch.ones(1, 2, dtype=torch.float64), "Tensor")):  # fmt: skip
        with pytest.raises(TypeError, match=rf"controller must be a difffilter.loop.Controller.*"
                                            rf"got {name}"):  # fmt: skip
            closed_loop(plant, 3, noise=DrawnNoise(torch.Generator().manual_seed(0)), x0=x0,
                        estimator=df.KalmanFilter(), controller=controller)  # fmt: skip


class _WritesInPlace(Attack):
    """Writes into what the loop hands it at step 3 and reports no attack (a trial's)."""

    channel, reads_view = Channel.SENSOR, True

    def __init__(self, what):
        self.what = what

    def init(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        return None

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        if k == 3 and self.what != "nothing":
            {"x": x, "y": y, "u": u, "view": None if view is None else view.mean}[self.what].add_(
                1.0
            )
        return state, torch.zeros_like(y), torch.zeros(y.shape[:-1], dtype=torch.bool)


@pytest.mark.parametrize("what", ["x", "y", "u", "view"])
def test_an_attack_that_writes_into_the_loops_tensors_is_refused(what):
    """An attack writing x, y, u or the estimator's output in place moved the plant, the
    recorded measurement or the estimator's carry (by 12.8, 10 and 10 in a trial) while
    the loop recorded no attack and flagged no step: named at the step it did it."""
    from difffilter.loop import StateFeedback

    F64 = torch.float64
    model = df.LinearGaussianModel(torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=F64),
                                   torch.tensor([[1.0, 0.0]], dtype=F64), 0.01 * torch.eye(2, dtype=F64),
                                   0.04 * torch.eye(1, dtype=F64), torch.zeros(2, dtype=F64),
                                   0.1 * torch.eye(2, dtype=F64), B=torch.tensor([[0.0], [0.1]], dtype=F64))  # fmt: skip
    g = torch.Generator().manual_seed(1)
    noise = ReplayedNoise(0.1 * torch.randn(2, 6, 2, dtype=F64, generator=g),
                          0.2 * torch.randn(2, 6, 1, dtype=F64, generator=g))  # fmt: skip

    def run(attack):
        return closed_loop(model, 6, noise=noise, x0=torch.zeros(2, 2, dtype=F64),
                           estimator=df.KalmanFilter(), controller=StateFeedback(torch.tensor([[1.0, 1.0]], dtype=F64)),
                           attack=attack)  # fmt: skip

    with pytest.raises(ValueError, match=r"attack _WritesInPlace.step wrote in place into a tensor "
                       r"the loop handed it at step 3.*compute out of place"):  # fmt: skip
        run(_WritesInPlace(what))
    reads = run(_WritesInPlace("nothing")).trajectories  # reading alone: the attack-free loop
    torch.testing.assert_close(reads.x, run(None).trajectories.x, rtol=0, atol=0)


class _Records(Attack):
    """Records the x it is handed; injects nothing."""

    def __init__(self, channel, reads_state):
        self.channel, self.reads_state, self.seen = Channel(channel), reads_state, []

    def init(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        return None

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        self.seen.append(x)
        signal = u if self.channel is Channel.ACTUATOR else y
        return state, torch.zeros_like(signal), torch.zeros(signal.shape[:-1], dtype=torch.bool)


@pytest.mark.parametrize("channel", ["sensor", "actuator"])
def test_only_an_attack_that_declares_it_reads_the_true_state(channel):
    """From a threat-model trial: every attack got the true x_k beside y_k, so the noise
    v_k = y_k − h(x_k) exactly (an attack subtracting it carried twice the bias with fewer
    alarms than no attack), undeclared. Attack.reads_state declares it (True by default: an
    attack of one's own keeps reading x); one that sets it False gets x=None."""
    from difffilter.threats import Bias, Covert, Replay

    model = _linear()
    us = torch.zeros(2, 5, 1, dtype=torch.float64)
    for reads, none in ((True, False), (False, True)):
        attack = _Records(channel, reads)
        closed_loop(model, 5, noise=DrawnNoise(torch.Generator().manual_seed(0)),
                    x0=torch.zeros(2, model.dim_x, dtype=torch.float64), controller=KnownInputs(us),
                    attack=attack)  # fmt: skip
        assert len(attack.seen) == 5 and all((x is None) == none for x in attack.seen)
    assert Attack.reads_state and not Bias(0.1, onset=2).reads_state
    assert not Replay(delay=2, onset=3).reads_state
    assert Covert(Bias(0.1, onset=2, channel="actuator"), plant=model).reads_state


class _ReadsX(_Records):
    """Reads the true state without declaring it (reads_state = False)."""

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        shift = x[..., :1]  # a TypeError where the loop hands it x=None
        return state, torch.zeros_like(y) + 0 * shift, torch.zeros(y.shape[:-1], dtype=torch.bool)


class _ReadsView(_Records):
    """Reads the estimator's output without declaring it (reads_view = False)."""

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        return (
            state,
            torch.zeros_like(y) + 0 * view.mean[..., :1],
            torch.zeros(y.shape[:-1], dtype=torch.bool),
        )


class _ReadsViewAtFirst(_Records):
    """Declares reads_view and reads view.mean at every step, the first (view None) too."""

    reads_view = True

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        shift = view.mean[..., :1]
        return state, torch.zeros_like(y) + 0 * shift, torch.zeros(y.shape[:-1], dtype=torch.bool)


class _ReadsScore(_Records):
    """Declares reads_view and backs off where the detector's score is high: a plain filter's
    output has no score."""

    reads_view = True

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        quiet = view is None or view.score > 3.0
        return state, torch.zeros_like(y) + 0.0 * quiet, torch.zeros(y.shape[:-1], dtype=torch.bool)


class _GuardsViewOwnBug(_Records):
    """Guards its read of view; its own ``gain`` is None (its bug)."""

    reads_view, gain = True, None

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        shift = 0.0 if view is None else view.mean[..., :1]
        own = self.gain * shift
        return state, torch.zeros_like(y) + own, torch.zeros(y.shape[:-1], dtype=torch.bool)


class _TestsScoreOwnBug(_Records):
    """Tests ``view.score is not None``; its own ``level`` is None (its bug)."""

    reads_view, level = True, None

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        quiet = k > 1 and self.level > 3 and view.score is not None
        return state, torch.zeros_like(y) * quiet, torch.zeros(y.shape[:-1], dtype=torch.bool)


class _ReadsU(_Records):
    """Reads u, which a loop without a controller hands it as None."""

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        return (
            state,
            torch.zeros_like(y) + 0 * u[..., :1],
            torch.zeros(y.shape[:-1], dtype=torch.bool),
        )


class _ReadsXOverLines(_Records):
    """Reads x undeclared in a call written over several lines, and its own self.x."""

    x = None

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        if self.seen:  # (_Records' list: its own self.x on the first call)
            return state, torch.zeros_like(
                y
            ) + 0 * self.x[..., :1], None  # fmt: skip
        self.seen.append(k)
        return state, torch.zeros_like(
            y
        ) + 0 * x[..., :1], None  # fmt: skip


class _ReadsXAfterGreek(_Records):
    """Reads x undeclared after a non-ASCII name (traceback columns count UTF-8 bytes), and
    passes x= as a keyword, which reads nothing, when told to."""

    def __init__(self, channel, reads_state, keyword=False):
        super().__init__(channel, reads_state)
        self.keyword = keyword

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        if self.keyword:
            return state, self.shifted(x=None, y=y), None
        δ = x[..., :1]  # noqa: PLC2401
        return state, torch.zeros_like(y) + 0 * δ, None

    def shifted(self, *, x, y):
        return y + None


class _OwnBug(_Records):
    """Fails by a TypeError of its own."""

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        return state, y + "oops", None


def test_what_a_power_systems_trial_could_not_tell_from_the_errors():
    """A gain of another width failed in a torch matmul, or named the input's shape alone;
    an attack that reads x or the view undeclared failed with "'NoneType' object is not
    subscriptable" alone (a note names the declaration now; an attack's own TypeError gets
    none). An onset after the last step runs and never acts (training draws such onsets);
    check_attack_fits names it."""
    from difffilter.loop import StateFeedback
    from difffilter.threats import Ramp, check_attack_fits

    model = _linear()
    x0 = torch.zeros(2, model.dim_x, dtype=torch.float64)
    noise = DrawnNoise(torch.Generator().manual_seed(0))
    late = closed_loop(model, 50, noise=noise, x0=x0, attack=Ramp(0.1, onset=80))
    assert not bool(late.trajectories.flags.any())
    with pytest.raises(ValueError, match="starts at step 80, after the last step \\(50\\)"):
        check_attack_fits(Ramp(0.1, onset=80), model, 50)
    wide = StateFeedback(torch.ones(1, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"gain K is \(1, 3\).*\[du, 2\]"):
        closed_loop(model, 5, noise=noise, x0=x0, estimator=df.KalmanFilter(), controller=wide)
    transposed = StateFeedback(torch.ones(2, 1, dtype=torch.float64))
    with pytest.raises(
        ValueError, match=r"its gain K is \(2, 1\): K must be \[du, dx\] = \[1, 2\]"
    ):
        closed_loop(model, 5, noise=noise, x0=x0, estimator=df.KalmanFilter(),
                    controller=transposed)  # fmt: skip

    def notes(attack, **kw):
        with pytest.raises((TypeError, AttributeError)) as error:
            closed_loop(model, 5, noise=noise, x0=x0, attack=attack, **kw)
        return "".join(getattr(error.value, "__notes__", []))

    assert "x=None because reads_state = False" in notes(_ReadsX("sensor", False))
    said = notes(_ReadsView("sensor", True), estimator=df.KalmanFilter())
    assert "view=None because reads_view = False" in said and "reads_state" not in said
    assert notes(_OwnBug("sensor", False)) == ""
    # declared, and read where the loop has none: the first step, a field the estimator
    # leaves None (a closed-loop trial: bare AttributeError and TypeError)
    said = notes(_ReadsViewAtFirst("sensor", False), estimator=df.KalmanFilter())
    assert "view=None: at the first step the estimator has no output yet" in said
    said = notes(_ReadsScore("sensor", False), estimator=df.KalmanFilter())
    assert "read view.score, which this estimator's output leaves None" in said
    # its own bug beside a guarded read: no note (a review)
    assert notes(_GuardsViewOwnBug("sensor", False), estimator=df.KalmanFilter()) == ""
    assert notes(_TestsScoreOwnBug("sensor", False), estimator=df.KalmanFilter()) == ""
    assert notes(_ReadsU("sensor", False)) == ""  # x and view were None too, but not read
    assert "x=None because reads_state" in notes(_ReadsXOverLines("sensor", False))
    assert "x=None because reads_state" in notes(_ReadsXAfterGreek("sensor", False))
    assert notes(_ReadsXAfterGreek("sensor", False, keyword=True)) == ""
    own = _ReadsXOverLines("sensor", False)
    own.seen.append(0)  # fails on its own self.x: no note
    assert notes(own) == ""


def test_forks_outside_the_loop_and_a_fractional_horizon_are_named():
    """An API trial: fork keys the loop never reaches stayed None, unsaid; horizon=6.5 was
    taken and "8" failed in a comparison."""
    F = torch.tensor([[0.9]], dtype=torch.float64)
    eye = torch.eye(1, dtype=torch.float64)
    plant = df.LinearGaussianModel(
        F, eye, 0.01 * eye, 0.01 * eye, torch.zeros(1, dtype=torch.float64), eye
    )
    noise = ReplayedNoise(
        torch.zeros(2, 3, 1, dtype=torch.float64), torch.zeros(2, 3, 1, dtype=torch.float64)
    )
    x0 = torch.zeros(2, 1, dtype=torch.float64)
    with pytest.raises(
        ValueError, match=r"forks: its keys must be steps this loop runs \(1 … 3\).*\[0, 99\]"
    ):
        closed_loop(plant, 3, noise=noise, x0=x0, forks={0: None, 2: None, 99: None})
    kept = {3: None}
    closed_loop(plant, 3, noise=noise, x0=x0, forks=kept)
    assert kept[3] is not None
    for bad in (6.5, "8", True):
        with pytest.raises(ValueError, match="horizon must be an integer"):
            closed_loop(plant, 3, noise=noise, x0=x0, horizon=bad)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_state_feedback_refuses_a_gain_or_reference_that_is_not_finite(bad):
    """From a fuzzing trial of the constructors: a NaN gain had run, every input and so
    every state NaN from the first step on; a gain or reference with a NaN or infinite
    entry is refused at construction, naming it."""
    from difffilter.loop import StateFeedback

    gain = torch.ones(1, 2, dtype=torch.float64)
    gain[0, 1] = bad
    with pytest.raises(ValueError, match="gain contains NaN or Inf"):
        StateFeedback(gain)
    with pytest.raises(ValueError, match="reference contains NaN or Inf"):
        StateFeedback(torch.ones(1, 2, dtype=torch.float64),
                      torch.tensor([0.0, bad], dtype=torch.float64))  # fmt: skip


def test_a_flag_of_the_entries_size_one_rank_short_is_per_run_and_the_error_says_so():
    """A flag ``[dy]`` beside a value ``[dy]`` for every run reads per run (the documented
    rank rule): with as many runs as entries it is taken so, with others refused, and the
    error now names the per-entry form for every run, ``[1, dy]`` (a trial's ``[dy]``
    flag had left a run unattacked where the runs were as many as the entries)."""
    F64 = torch.float64
    eye = torch.eye(3, dtype=F64)
    H = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]], dtype=F64)
    plant = df.LinearGaussianModel(0.9 * eye, H, 1e-2 * eye, 0.04 * torch.eye(2, dtype=F64),
                                   torch.zeros(3, dtype=F64), eye)  # fmt: skip

    class EntryZero(Attack):
        channel, reads_state = Channel.SENSOR, False

        def __init__(self, flag):
            self.flag = flag

        def init(self, batch_shape, T, dim, generator=None, *, dtype, device=None):
            return None

        def step(self, state, k, *, y=None, x=None, u=None, view=None):
            return state, torch.tensor([0.5, 0.0], dtype=y.dtype), self.flag

    def run(flag, runs):
        return closed_loop(plant, 3, noise=DrawnNoise(torch.Generator().manual_seed(0)),
                           x0=torch.zeros(runs, 3, dtype=F64), attack=EntryZero(flag))  # fmt: skip

    with pytest.raises(ValueError, match=r"a flag per entry for every run is \[1, 2\], not \[2\]"):
        run(torch.tensor([True, False]), 3)
    per_entry = run(torch.tensor([[True, False]]), 3).trajectories  # [1, dy]: every run
    torch.testing.assert_close((per_entry.y_recv - per_entry.y_true)[:, :, 0],
                               torch.full((3, 3), 0.5, dtype=F64))  # fmt: skip
    per_run = run(torch.tensor([True, False]), 2).trajectories  # [B] with B = dy: per run
    assert per_run.flags[:, 0].tolist() == [True, False]


def test_a_fork_kept_under_an_input_loss_is_continued_under_the_same_channel():
    """A trial: another arrival mask, ``on_loss`` or ``acknowledged`` had been taken when
    continuing a fork, stitching the fork's steps of one channel to the rest of another
    (as a sensor mask of another schedule is refused). The same channel gives the whole loop."""
    from difffilter.input_loss import InputLoss
    from difffilter.loop import ReplayedNoise, StateFeedback, closed_loop

    d = torch.float64
    g = torch.Generator().manual_seed(39)
    T, B = 20, 2
    model = df.LinearGaussianModel(torch.tensor([[1.0, 0.1], [0.0, 0.98]], dtype=d),
                                   torch.tensor([[1.0, 0.0]], dtype=d), 0.01 * torch.eye(2, dtype=d),
                                   0.05 * torch.eye(1, dtype=d), torch.zeros(2, dtype=d),
                                   0.1 * torch.eye(2, dtype=d), B=torch.tensor([[0.0], [0.1]], dtype=d))  # fmt: skip
    w = 0.1 * torch.randn(B, T, 2, generator=g, dtype=d)
    v = 0.2 * torch.randn(B, T, 1, generator=g, dtype=d)
    x0 = torch.randn(B, 2, generator=g, dtype=d)
    m1 = torch.rand(B, T, generator=g) > 0.5
    kw = dict(noise=ReplayedNoise(w, v), estimator=df.KalmanFilter(),
              controller=StateFeedback(torch.tensor([[0.5, 1.0]], dtype=d)))  # fmt: skip
    forks = {10: None}
    whole = closed_loop(model, T, x0=x0, forks=forks, input_loss=InputLoss(m1, "hold"), **kw)
    same = closed_loop(model, T - 10, fork=forks[10], input_loss=InputLoss(m1, "hold"), **kw)
    assert torch.equal(same.trajectories.x, whole.trajectories.x)
    with pytest.raises(ValueError, match="input_loss's arrivals differ .* steps 1 … 10"):
        closed_loop(model, T - 10, fork=forks[10], input_loss=InputLoss(~m1, "hold"), **kw)
    for other in (InputLoss(m1, "zero"), InputLoss(m1, "hold", acknowledged=False)):
        with pytest.raises(ValueError, match="is not the channel of the loop that kept the fork"):
            closed_loop(model, T - 10, fork=forks[10], input_loss=other, **kw)
    # after the fork's steps the arrivals may be another loop's: that is the point of a fork
    later = m1.clone()
    later[:, 12:] = ~later[:, 12:]
    closed_loop(model, T - 10, fork=forks[10], input_loss=InputLoss(later, "hold"), **kw)
