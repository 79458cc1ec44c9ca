"""Tests from a mutation review of the scenario type (``models/scenario.py``), the scenario
registry (``models/registry.py``) and the estimators' needs (``models/needs.py``).

Every number is checked against an independent truth: the simulated runs are recomputed in
numpy float64 from the model's matrices and the standard normal draws of the generators the
module docstring names (``"plant"``: ``x_0``, then per step the process and the measurement
noise); the attack-norm floor against its docstring's formula evaluated by hand; the
registry and the needs against their documented rules.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter.input_loss import InputLossSchedule
from difffilter.models import needs
from difffilter.models.attacks import ActuatorInjection, SensorBias
from difffilter.models.scenario import OWN_ATTACK, CustomScenario, Scenario, simulate
from difffilter.models.schedules import PacketLoss
from difffilter.threats import Bias, Covert, KSigmaBias, Ramp

F = np.array([[0.9, 0.2], [-0.1, 0.8]])
B = np.array([[0.5], [1.0]])
H = np.array([[1.0, 0.0], [0.5, 1.0]])
Q = np.array([[0.2, 0.05], [0.05, 0.1]])
R = np.array([[0.3, 0.1], [0.1, 0.4]])
M0 = np.array([1.0, -1.0])
P0 = np.array([[0.5, 0.1], [0.1, 0.3]])


def _model(dtype=torch.float64, r=R):
    t = lambda a: torch.tensor(a, dtype=dtype)  # noqa: E731
    return df.LinearGaussianModel(t(F), t(H), t(Q), t(r), t(M0), t(P0), B=t(B))


def _by_hand(seed, runs, us, *, random_initial, bias=None, r=R):
    """``(x0, x, y_true)`` in numpy float64: ``x_0 = m₀ + L₀ ε`` (or ``m₀``), then per step
    ``x_k = F x_{k−1} + B (u_{k−1} + bias) + L_Q ε``, ``y_k = H x_k + L_R ε``, every ``ε`` a
    standard normal draw of ``torch.Generator().manual_seed(seed)`` in that order."""
    g = torch.Generator().manual_seed(seed)
    draw = lambda: torch.randn(runs, 2, generator=g, dtype=torch.float64).numpy()  # noqa: E731
    lp, lq, lr = (np.linalg.cholesky(a) for a in (P0, Q, r))
    x = M0 + draw() @ lp.T if random_initial else np.tile(M0, (runs, 1))
    x0, xs, ys = x.copy(), [], []
    for t in range(us.shape[1]):
        u = us[:, t] + (0.0 if bias is None else bias)
        x = x @ F.T + u @ B.T + draw() @ lq.T
        xs.append(x)
        ys.append(x @ H.T + draw() @ lr.T)
    return x0, np.stack(xs, 1), np.stack(ys, 1)


def _gens(plant=1, attack=2, schedule=3, input_schedule=4):
    seeds = {"plant": plant, "attack": attack, "schedule": schedule}
    seeds["input_schedule"] = input_schedule
    return {k: torch.Generator().manual_seed(v) for k, v in seeds.items()}


def _scenario(**kw):
    base = dict(name="mut_review_plant", family="mut_review", description="test", steps=6)
    return CustomScenario(**{"model_fn": _model, **base, **kw})


def _u_of_k(k):
    return torch.sin(0.7 * k) + 0.1 * k  # u_k at k = 0 … T−1


# -- simulation against numpy ----------------------------------------------------------------


@pytest.mark.parametrize("random_initial", [True, False])
def test_simulate_matches_numpy(random_initial):
    """``Scenario.simulate`` reproduces the docstring's recursion (prior draw of ``x_0`` only
    with ``random_initial``; the known inputs a function of ``k = 0 … T−1``; the sensor bias
    added to the received measurement on its entries from its onset), recomputed in numpy
    from the ``"plant"`` generator's normal draws; ``info["x0"]`` is the initial state."""
    sc = _scenario(random_initial=random_initial, known_inputs=_u_of_k,
                   attack=Bias(value=0.7, onset=3, entries=(1,)))  # fmt: skip
    runs = 3
    tr = sc.simulate(runs, _gens(plant=11))
    us = np.tile(np.sin(0.7 * np.arange(6.0)) + 0.1 * np.arange(6.0), (runs, 1))[..., None]
    x0, x, y = _by_hand(11, runs, us, random_initial=random_initial)
    np.testing.assert_allclose(tr.us.numpy(), us, rtol=0, atol=1e-12)
    np.testing.assert_allclose(tr.info["x0"].numpy(), x0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(tr.x.numpy(), x, rtol=0, atol=1e-10)
    np.testing.assert_allclose(tr.y_true.numpy(), y, rtol=0, atol=1e-10)
    a = np.zeros((6, 2))
    a[2:, 1] = 0.7  # onset k = 3 ↔ t = 2, entry 1 only
    np.testing.assert_allclose((tr.y_recv - tr.y_true).numpy(), np.broadcast_to(a, y.shape),
                               rtol=0, atol=1e-12)  # fmt: skip


def test_actuator_attack_without_inputs_drives_zero_commands():
    """An actuator attack on a scenario without known inputs: the commanded inputs are
    zeros (``us`` all 0) and the plant is driven by ``B a`` alone (numpy recursion)."""
    sc = _scenario(attack=ActuatorInjection(value=(0.4,)))
    tr = sc.simulate(2, _gens(plant=5))
    zeros = np.zeros((2, 6, 1))
    _, x, y = _by_hand(5, 2, zeros, random_initial=False, bias=0.4)
    np.testing.assert_array_equal(tr.us.numpy(), zeros)
    np.testing.assert_allclose(tr.x.numpy(), x, rtol=0, atol=1e-10)
    np.testing.assert_allclose(tr.y_recv.numpy(), y, rtol=0, atol=1e-10)


def test_with_steps_gives_first_steps_of_same_draws():
    """``with_steps(n)``: the first ``n`` steps of the same draws (per-step order of the
    plant stream), with the first ``n`` rows of a longer table of known inputs, and the
    threat kept."""
    table = torch.arange(8.0, dtype=torch.float64).reshape(8, 1) * 0.3 - 1.0
    sc = _scenario(steps=8, known_inputs=table, attack=Bias(value=1.0)).with_threat(None)
    short = sc.with_steps(5)
    assert short.steps == 5 and short.simulated_attack() is None
    full, part = sc.simulate(2, _gens()), short.simulate(2, _gens())
    for name in ("x", "y_true", "y_recv", "us"):
        np.testing.assert_array_equal(getattr(part, name).numpy(),
                                      getattr(full, name)[:, :5].numpy())  # fmt: skip
    np.testing.assert_array_equal(part.us[0, :, 0].numpy(), table[:5, 0].numpy())
    np.testing.assert_array_equal(part.y_recv.numpy(), part.y_true.numpy())


def test_with_threat_none_and_other_threat():
    """``with_threat(None)``: received = true measurements (attack-free), the plant's
    realisation the same as under the own sensor attack; another threat's injection is
    ``ỹ − y`` = its value; the defender's ``attack_model`` never changes."""
    own = Bias(value=2.0)
    sc = _scenario(attack=own)
    mine, free = sc.simulate(2, _gens()), sc.with_threat(None).simulate(2, _gens())
    np.testing.assert_array_equal(free.y_recv.numpy(), free.y_true.numpy())
    assert not bool(free.flags.any())
    np.testing.assert_array_equal(free.x.numpy(), mine.x.numpy())
    np.testing.assert_allclose((mine.y_recv - mine.y_true).numpy(), 2.0, rtol=0, atol=1e-12)
    other = sc.with_threat(Bias(value=-0.5))
    tr = other.simulate(2, _gens())
    np.testing.assert_allclose((tr.y_recv - tr.y_true).numpy(), -0.5, rtol=0, atol=1e-12)
    for s in (sc.with_threat(None), other):
        assert s.attack_model() is own
    assert sc.with_threat(None).with_threat(OWN_ATTACK).simulated_attack() is own


def test_with_threat_refusals():
    """``with_threat`` refuses what is not an attack, and an attack that reads the
    estimator's output on a scenario simulated without an estimator (not closed-loop)."""

    class Reader(Bias):
        reads_view = True

    with pytest.raises(TypeError, match="Attack"):
        _scenario().with_threat("bias")
    with pytest.raises(ValueError, match="reads_view"):
        _scenario().with_threat(Reader(value=1.0))


def test_streams_independent():
    """The three named streams: the packet-loss mask depends on the ``"schedule"`` seed only,
    the attacked runs (``share``) on the ``"attack"`` seed only, the input losses on
    ``"input_schedule"`` only; the plant on ``"plant"`` only."""
    sc = _scenario(attack=Bias(value=1.0, share=0.5), protocol=PacketLoss(0.4),
                   known_inputs=_u_of_k,
                   input_loss=InputLossSchedule(PacketLoss(0.5), acknowledged=True))  # fmt: skip
    ref = sc.simulate(16, _gens())
    info = lambda tr: tr.info["attack_flags"]  # noqa: E731
    for stream, seed in (("plant", 21), ("attack", 22), ("schedule", 23), ("input_schedule", 24)):
        tr = sc.simulate(16, _gens(**{stream: seed}))
        assert torch.equal(tr.mask, ref.mask) is (stream != "schedule"), stream
        assert torch.equal(info(tr), info(ref)) is (stream != "attack"), stream
        assert torch.equal(tr.us, ref.us) is (stream != "input_schedule"), stream


def test_simulate_refusals():
    """``simulate`` refuses 0 runs or steps, a non-attack, and inputs of the wrong shape."""
    m = _model()
    for runs, steps in ((0, 3), (2, 0)):
        with pytest.raises(ValueError, match=">= 1"):
            simulate(m, runs, steps, generators=_gens())
    with pytest.raises(TypeError, match="Attack"):
        simulate(m, 2, 3, generators=_gens(), attack="bias")
    with pytest.raises(ValueError, match="us must have shape"):
        simulate(m, 2, 3, generators=_gens(), us=torch.zeros(2, 4, 1, dtype=torch.float64))


def test_non_finite_state_named_at_its_step():
    """A state that overflows at ``k = 2`` (``x_2 = 10²⁰⁰ · 10²⁰⁰``) in one entry only is
    reported as the state (not the measurement) at step ``k = 2``."""
    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    m = df.LinearGaussianModel(t([[1e200, 0.0], [0.0, 0.5]]), t([[1.0, 0.0]]), t(np.eye(2)),
                               t([[1.0]]), t([1.0, 1.0]), t(np.eye(2)))  # fmt: skip
    with pytest.raises(ValueError, match=r"plant's state is NaN or Inf at step k = 2 of run 0"):
        simulate(m, 1, 4, generators=_gens())


def test_unreceived_non_finite_measurement_is_not_an_error():
    """A measurement entry that is NaN but never received (mask False) is not reported: only
    received measurements are checked."""

    class HalfBlind(df.LinearGaussianModel):
        def observe(self, x, k):
            y = super().observe(x, k)
            return torch.stack([y[..., 0], torch.full_like(y[..., 1], math.nan)], -1)

    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    m = HalfBlind(t(F), t(H), t(Q), t(R), t(M0), t(P0))

    class FirstOnly:
        def mask(self, batch_shape, num_steps, dim, generator=None, *, device=None):
            out = torch.zeros(*batch_shape, num_steps, dim, dtype=torch.bool, device=device)
            out[..., 0] = True
            return out

    tr = simulate(m, 2, 3, generators=_gens(), schedule=FirstOnly())
    assert bool(torch.isnan(tr.y_true[..., 1]).all()) and bool(torch.isfinite(tr.x).all())


# -- derived quantities ------------------------------------------------------------------------


def test_attack_free_key_rule():
    """The attack-free key: ``(name, steps)``, plus the marker of drawn initial states."""
    sc = _scenario()
    assert sc.attack_free_key() == ("mut_review_plant", 6)
    assert sc.with_steps(4).attack_free_key() == ("mut_review_plant", 4)
    assert _scenario(random_initial=True).attack_free_key() == ("mut_review_plant", 6,
                                                                 "x0 ~ prior")  # fmt: skip


def test_shipped_checkpoint():
    """``shipped_checkpoint``: the file relative to the repository root, ``None`` when the
    path is not a file (a folder, absent)."""
    from pathlib import Path

    import difffilter

    root = Path(difffilter.__file__).resolve().parents[1]
    assert _scenario(checkpoint="pyproject.toml").shipped_checkpoint() == root / "pyproject.toml"
    assert _scenario(checkpoint="tests").shipped_checkpoint() is None
    assert _scenario(checkpoint="no/such.ckpt").shipped_checkpoint() is None
    assert _scenario().shipped_checkpoint() is None


@pytest.mark.parametrize(
    ("attack", "expected"),
    [
        (Bias(value=2.0), 0.5 * math.sqrt(2 * 2.0**2)),  # one value broadcast over dy = 2
        (Bias(value=2.0, entries=(1,)), 0.5 * 2.0),  # zero outside entries
        (Bias(value=(3.0, 4.0), entries=(0,)), 0.5 * 3.0),
        (Bias(value=(3.0, 4.0)), 0.5 * 5.0),
        (Bias(value=2.0, channel="replacement"), 0.5 * math.sqrt(8.0)),
        (KSigmaBias(k=2.0, sigma=(0.5, 1.5)), 0.5 * math.sqrt(1.0**2 + 3.0**2)),
        (SensorBias(gamma_bar=(0.6, 0.8)), 0.5 * 1.0),
        (Ramp(slope=1.0), math.sqrt(2.0 + 7.0)),  # no steady state: ‖√diag R‖
        (Bias(value=5.0, channel="actuator"), math.sqrt(2.0 + 7.0)),  # input units
        (None, math.sqrt(2.0 + 7.0)),
    ],
)
def test_attack_norm_floor(attack, expected):
    """``attack_norm_floor`` against the docstring: half the norm of the injected vector for
    a sensor-side attack with a steady state, else ``‖√diag R‖`` (``R = diag(2, 7)``)."""
    sc = _scenario(attack=attack)
    model = _model(r=np.array([[2.0, 0.3], [0.3, 7.0]]))
    assert sc.attack_norm_floor(model) == pytest.approx(expected, rel=1e-12)
    assert _scenario(attack=attack, gamma_min=0.25).attack_norm_floor(model) == 0.25


def test_attack_norm_floor_largest_over_batch():
    """Over a batch of models (``R [B, dy, dy]``) the floor is the largest ``‖√diag R_b‖``."""
    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    rs = t(np.stack([np.diag([1.0, 3.0]), np.diag([4.0, 5.0]), np.diag([0.5, 0.5])]))
    m = df.LinearGaussianModel(t(F), t(H), t(Q), rs, t(M0), t(P0))
    assert _scenario().attack_norm_floor(m) == pytest.approx(3.0, rel=1e-12)


# -- CustomScenario ---------------------------------------------------------------------------


def test_custom_scenario_refusals():
    """``CustomScenario`` refuses a non-bool ``random_initial``, ``steps`` < 1, a dt <= 0,
    input loss with a covert attack, and a model built in another dtype."""
    with pytest.raises(TypeError, match="random_initial"):
        _scenario(random_initial=1)
    with pytest.raises(ValueError, match="steps"):
        _scenario(steps=0)
    with pytest.raises(ValueError, match="dt"):
        _scenario(dt=-1.0)
    covert = Covert(Bias(value=1.0, channel="actuator"), _model())
    with pytest.raises(ValueError, match="covert"):
        _scenario(attack=covert, input_loss=InputLossSchedule(PacketLoss(0.1)))
    bad = CustomScenario(name="x", family="y", description="z",
                         model_fn=lambda dtype: _model(torch.float32))  # fmt: skip
    with pytest.raises(ValueError, match="dtype"):
        bad.system(torch.float64)


def test_custom_scenario_inputs_shapes():
    """``inputs``: a function returning ``[T]`` is one input; a table of ``R`` runs serves
    run ``i`` its row ``i mod R``; ``estimator_options`` returns the options."""
    sc = _scenario(steps=4, known_inputs=lambda k: 2.0 * k, options={"cusum_bias": 0.5})
    np.testing.assert_array_equal(sc.inputs(2, torch.float64).numpy(),
                                  np.tile([0.0, 2.0, 4.0, 6.0], (2, 1))[..., None])  # fmt: skip
    table = torch.tensor([[[1.0]] * 4, [[2.0]] * 4, [[3.0]] * 4], dtype=torch.float64)
    got = _scenario(steps=4, known_inputs=table).inputs(7, torch.float64)
    np.testing.assert_array_equal(got[:, 0, 0].numpy(), [1, 2, 3, 1, 2, 3, 1])
    assert sc.estimator_options() == {"cusum_bias": 0.5}


# -- needs ------------------------------------------------------------------------------------


def test_needs_read_the_right_attack():
    """The data needs read the attack the plant meets (the threat); the assumption needs
    read the scenario's own attack (``attack_model``)."""
    m = _model()
    sensor_own = _scenario(attack=Bias(value=1.0))
    act = sensor_own.with_threat(ActuatorInjection(value=(1.0,)))
    assert needs.SENSOR_ATTACK.unmet(sensor_own, m) is None
    assert "actuators" in needs.SENSOR_ATTACK.unmet(act, m)
    assert needs.ATTACK_FREE_MEASUREMENTS.unmet(sensor_own, m) is None
    assert "attack-free" in needs.ATTACK_FREE_MEASUREMENTS.unmet(act, m)
    assert needs.ASSUMES_SENSOR_ATTACK.unmet(act, m) is None
    act_own = _scenario(attack=ActuatorInjection(value=(1.0,)))
    assert "actuators" in needs.ASSUMES_SENSOR_ATTACK.unmet(act_own.with_threat(None), m)
    covert = _scenario().with_threat(Covert(Bias(value=1.0, channel="actuator"), _model()))
    assert needs.ATTACK_FREE_MEASUREMENTS.unmet(covert, m) is not None
    no_own = _scenario().with_threat(SensorBias(gamma_bar=(1.0, 1.0)))
    assert "no attack" in needs.ASSUMES_DECEPTION_DENSITY.unmet(no_own, m)
    bias_own = _scenario(attack=SensorBias(gamma_bar=(1.0, 1.0))).with_threat(Ramp())
    assert needs.ASSUMES_DECEPTION_DENSITY.unmet(bias_own, m) is None
    assert "Bias" in needs.ASSUMES_DECEPTION_DENSITY.unmet(_scenario(attack=Bias()), m)


def test_needs_default_channel_and_instances():
    """An attack object without a ``channel`` counts as a sensor attack; ``scenario_of``
    checks the scenario's class, ``model_of`` the model's; ``first_unmet`` gives the first
    unmet need's reason; a scenario without input loss does not meet the UDP need."""

    class NoChannel:
        pass

    sc, m = _scenario(), _model()
    sc_bare = _scenario().with_threat(None)
    object.__setattr__(sc_bare, "threat", NoChannel())
    assert needs.SENSOR_ATTACK.unmet(sc_bare, m) is None
    assert needs.scenario_of(CustomScenario, "x").unmet(sc, m) is None
    assert needs.scenario_of(type(m), "x").unmet(sc, m) is not None
    assert needs.model_of(type(m)).unmet(sc, m) is None
    assert needs.model_of(CustomScenario).unmet(sc, m) is not None
    first = needs.Need("a", lambda s, mo: "first")
    second = needs.Need("b", lambda s, mo: "second")
    assert needs.first_unmet((needs.LINEAR_MODEL, first, second), sc, m) == "first"
    assert needs.UNACKNOWLEDGED_INPUT_LOSS.unmet(sc, m) is not None


# -- registry ---------------------------------------------------------------------------------


def _named(name, family="mut_review_fam", **kw):
    return _scenario(name=name, family=family, **kw)


def test_register_rules(isolated_registry):
    """``register``: the same scenario twice is fine and keeps its first origin; another
    scenario under a taken name is refused naming the first origin; reserved words, a
    family's name (its own or another's), a family named like a scenario and a family
    named like a reserved word are refused."""
    reg = isolated_registry
    a = _named("mut_a")
    reg.register(a, origin="first place")
    reg.register(a, origin="second place")
    with pytest.raises(ValueError, match="by first place.*third place registers"):
        reg.register(_named("mut_a", steps=9), origin="third place")
    for bad in (_named("all"), _named("mut_review_fam", family="mut_other_fam"),
                _named("mut_b", family="mut_b"), _named("mut_c", family="mut_a")):  # fmt: skip
        with pytest.raises(ValueError, match="another name"):
            reg.register(bad)
    for word in ("all", "robustness"):  # the family could never be selected alone
        with pytest.raises(ValueError, match=f"of family '{word}', a word of the command"):
            reg.register(_named("mut_d", family=word))
    assert reg.get("mut_a") is a and "mut_d" not in reg.names()


def test_a_plant_inputs_or_options_of_their_own_under_a_taken_name_are_refused(
    isolated_registry, tmp_path, monkeypatch
):
    """The review's bug: a CustomScenario's plant, inputs and options are left out of its
    ``==`` (a YAML file read again builds fresh functions), so another plant under a taken
    name replaced the first without a word, while another ``steps`` was refused. Now a
    plant of other matrices (R read 4x), other known inputs or other options is refused;
    the same plant by another function, and a YAML file read again unchanged, are not."""
    reg = isolated_registry
    first = reg.register(_named("mut_p"), origin="first")
    reg.register(_named("mut_p", model_fn=lambda dtype: _model(dtype)), origin="same plant")
    others = (_named("mut_p", model_fn=lambda dtype: _model(dtype, r=4 * R)),
              _named("mut_p", known_inputs=torch.ones(1, 6, 1, dtype=torch.float64)),
              _named("mut_p", options={"num_particles": 10}))  # fmt: skip
    for other in others:
        with pytest.raises(ValueError, match="by first.*registers another under that name"):
            reg.register(other, origin="other")
    kept = reg.get("mut_p")  # the first plant (or its equal registered again), untouched
    assert kept == first and kept.known_inputs is None and not kept.options
    for key, value in _model().state_dict().items():
        assert torch.equal(kept.system().state_dict()[key], value), key
    monkeypatch.chdir(tmp_path)
    text = ("name: mut_yaml\nsteps: 10\nplant:\n  F: [[0.95, 0.04], [-0.02, 0.8]]\n"
            "  H: [[1.0, 0.0]]\n  Q: 1.0e-4\n  R: 1.0e-3\n  P0: 1.0e-2\n")  # fmt: skip
    (tmp_path / "p.yaml").write_text(text)
    assert reg.get("p.yaml").name == reg.get("p.yaml").name == "mut_yaml"
    (tmp_path / "p.yaml").write_text(text.replace("0.95", "0.5"))
    with pytest.raises(ValueError, match="or a file edited since it was loaded"):
        reg.get("p.yaml")
    assert float(reg.get("mut_yaml").system().transition_matrix(0)[0, 0]) == 0.95


def test_register_all_tuple_and_origin(isolated_registry):
    """A function returning a tuple registers every scenario; the origin named in a clash is
    the plug-in's ``where``."""
    reg = isolated_registry
    a, b = _named("mut_t1"), _named("mut_t2")
    assert reg._register_all(lambda: (a, b), "plug") == [a, b]
    assert reg.get("mut_t2") is b
    with pytest.raises(ValueError, match="by plug"):
        reg.register(_named("mut_t1", steps=3))


def test_lookup_and_listing(isolated_registry):
    """``get`` of an unknown name lists every known name, sorted; ``names`` filters by family
    and by headline; ``families`` is sorted."""
    reg = isolated_registry
    reg.register(_named("mut_z", family="mut_fz", headline=False))
    reg.register(_named("mut_y", family="mut_fz"))
    with pytest.raises(ValueError) as info:
        reg.get("mut_nope")
    listed = str(info.value).split("known scenarios: ")[1].split(", ")
    assert listed == sorted(reg._REGISTRY) and len(listed) == len(reg._REGISTRY)
    # the nearest names first, as difffilter-eval gives them (difffilter-train did not)
    with pytest.raises(ValueError, match=r"unknown scenario 'mut_yy'; did you mean mut_y\b"):
        reg.get("mut_yy")
    with pytest.raises(ValueError, match=r"unknown scenario 'qqqqqqqq'; known scenarios: "):
        reg.get("qqqqqqqq")  # nothing near: no suggestion
    assert reg.names("mut_fz") == ["mut_y", "mut_z"]
    assert reg.names("mut_fz", headline_only=True) == ["mut_y"]
    assert len(reg.names()) == len(reg._REGISTRY)
    assert reg.families() == sorted({s.family for s in reg._REGISTRY.values()})
    assert "mut_fz" in reg.families()


def test_path_refuses_list(isolated_registry, monkeypatch):
    """A ``module:object`` path naming a list is refused (one scenario per path)."""
    import sys
    import types

    mod = types.ModuleType("mut_review_mod")
    mod.SCENARIOS = [_named("mut_l1")]
    monkeypatch.setitem(sys.modules, "mut_review_mod", mod)
    with pytest.raises(ValueError, match="not a module or list"):
        isolated_registry.get("mut_review_mod:SCENARIOS")


def test_scenario_base_is_abstract():
    """The base ``Scenario`` has no system; ``unit_of`` maps the metric units."""
    sc = Scenario(name="b", family="f", description="d")
    with pytest.raises(NotImplementedError):
        sc.system()
    assert sc.unit_of("state units") == "state units" and sc.unit_of("s") == "s"


def test_simulate_attack_none_and_given_model():
    """``simulate(attack=None)`` runs attack-free whatever the scenario's attack, and a
    ``model`` passed in is the plant simulated (numpy recursion with its ``R``)."""
    r2 = np.array([[1.0, -0.2], [-0.2, 0.6]])
    sc = _scenario(attack=Bias(value=3.0))
    tr = sc.simulate(2, _gens(plant=9), attack=None, model=_model(r=r2))
    _, x, y = _by_hand(9, 2, np.zeros((2, 6, 1)), random_initial=False, r=r2)
    np.testing.assert_allclose(tr.x.numpy(), x, rtol=0, atol=1e-10)
    np.testing.assert_allclose(tr.y_recv.numpy(), y, rtol=0, atol=1e-10)


def test_linear_model_need():
    """``LINEAR_MODEL`` is met by a linear-Gaussian model, not by a nonlinear one."""
    eye = torch.eye(2, dtype=torch.float64)
    nonlinear = df.NonlinearGaussianModel(lambda x: 0.9 * x, lambda x: x, eye, eye,
                                          torch.zeros(2, dtype=torch.float64), eye)  # fmt: skip
    assert needs.LINEAR_MODEL.unmet(_scenario(), _model()) is None
    assert "linear" in needs.LINEAR_MODEL.unmet(_scenario(), nonlinear)


def test_default_origin_is_the_calling_module(isolated_registry):
    """Without ``origin`` the registering module (this test module) is named in a clash."""
    isolated_registry.register(_named("mut_o"))
    with pytest.raises(ValueError, match=f"by module {__name__}"):
        isolated_registry.register(_named("mut_o", steps=2), origin="x")
    names = [s.name for s in isolated_registry.all_scenarios()]
    assert names == sorted(names) and "mut_o" in names


def test_broken_builtin_module_fails_every_call(isolated_registry, monkeypatch):
    """A module of ``difffilter.models`` that fails to import fails every later lookup too
    (module docstring of ``_load_builtin``), not only the first."""
    import pkgutil
    import sys

    reg = isolated_registry
    real = pkgutil.iter_modules
    extra = pkgutil.ModuleInfo(None, "zz_mut_review_broken", False)
    monkeypatch.setattr(reg.pkgutil, "iter_modules", lambda path: [*real(path), extra])
    monkeypatch.setitem(sys.modules, "difffilter.models.zz_mut_review_broken", None)
    monkeypatch.setattr(reg, "_LOADED", False)
    for _ in range(2):
        with pytest.raises(ImportError):
            reg.names()


def test_plugin_that_registers_nothing_warns(isolated_registry, monkeypatch):
    """An entry-point module loaded fresh that registers nothing is warned about; one that
    registers a scenario is not, nor one imported before the registry loaded it."""
    import sys
    import types
    import warnings

    reg = isolated_registry

    class Point:
        def __init__(self, value, scenario):
            self.name, self.value, self.scenario = value, value, scenario

        def load(self):
            mod = types.ModuleType(self.value)
            monkeypatch.setitem(sys.modules, self.value, mod)
            if self.scenario is not None:
                reg.register(self.scenario)
            return mod

    points = [Point("mut_empty_plugin", None), Point("mut_full_plugin", _named("mut_p"))]
    old = Point("mut_old_plugin", None)  # imported before: it registered then, not now
    monkeypatch.setitem(sys.modules, old.value, types.ModuleType(old.value))
    points.append(old)
    monkeypatch.setattr(reg, "entry_points", lambda group: points)
    monkeypatch.setattr(reg, "_LOADED", False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        reg.names()
    said = [str(w.message) for w in caught if "registered no scenario" in str(w.message)]
    assert len(said) == 1 and "mut_empty_plugin" in said[0]
    assert "mut_p" in reg.names()


def test_a_scenarios_known_inputs_are_made_on_its_models_device(monkeypatch):
    """``Scenario.simulate`` asks :meth:`inputs` for the model's device (it asked for none,
    so a model moved to a GPU got its known inputs on the CPU); CI has no GPU, so the
    device asked for is what is checked, and the inputs the run then holds."""
    from difffilter.models import registry
    from difffilter.models.streams import Streams

    sc = registry.get("robot_actuator_attack").with_steps(44)
    asked = []
    real = type(sc).inputs

    def spy(self, runs, dtype, device=None):
        asked.append(device)
        return real(self, runs, dtype, device)

    monkeypatch.setattr(type(sc), "inputs", spy)
    model = sc.system(torch.float64)
    tr = sc.simulate(2, Streams(0).simulation(), model=model)
    assert asked == [model.initial.mean.device] and tr.us.device == model.initial.mean.device


# -- red-team trial findings (registry and needs) ---------------------------------------------


def test_a_function_path_is_called_once_so_an_attack_without_value_equality_reads_the_same(
    isolated_registry, monkeypatch
):
    """A ``module:function`` path was called on every ``get``; a :class:`Signal` attack
    compares by identity, so the same scenario built again read as "another under that
    name" and difffilter-train (which asks twice) stopped. Truth: the function builds one
    scenario; every ``get`` of its path, and an entry point naming the same function,
    give that scenario, and the function runs once. Another scenario under the name, from
    another function, is still refused."""
    import sys
    import types

    from difffilter.models.attacks import Signal

    calls = []

    def make():
        calls.append(1)
        values = torch.zeros(6, 2, dtype=torch.float64)
        values[3:, 0] = 0.3
        return _named("mut_signal", attack=Signal(values))

    mod = types.ModuleType("mut_review_signal_mod")
    mod.make, mod.other = make, lambda: _named("mut_signal", steps=5)
    monkeypatch.setitem(sys.modules, "mut_review_signal_mod", mod)
    assert Signal(torch.zeros(6, 2)) != Signal(torch.zeros(6, 2))  # (why a second call failed)
    reg = isolated_registry
    (plugged,) = reg._register_all(mod.make, "entry point 'mut_sig'")  # a plug-in's load
    first = reg.get("mut_review_signal_mod:make")
    assert reg.get("mut_review_signal_mod:make") is first is plugged
    assert reg.get("mut_signal") is first and len(calls) == 1
    with pytest.raises(ValueError, match="by entry point 'mut_sig'.*registers another"):
        reg.get("mut_review_signal_mod:other")


def test_an_edit_of_any_row_of_a_known_inputs_table_is_refused(isolated_registry):
    """The "same scenario again?" test compared 2 runs' inputs, so a table ``[R, T, du]``
    edited in row 2 replaced the registered scenario without a word. Run ``i`` takes row
    ``i mod R``: truth is whether the two agree on every run. ``[a, b, c]`` against
    ``[a, b, c']`` differ on run 2; ``[a, b]`` against ``[a, b, a]`` on run 3 (row 1 = b
    against row 0 = a); ``[a, b]`` against ``[a, b, a, b]`` on none."""
    reg = isolated_registry

    def table(*rows):
        return torch.tensor([[[r]] * 6 for r in rows], dtype=torch.float64)

    first = reg.register(_named("mut_rows", known_inputs=table(0.0, 1.0, 2.0)), origin="first")
    for edited in (table(0.0, 1.0, -50.0), table(0.0, 1.0, 2.0, 7.0)):
        with pytest.raises(ValueError, match="by first.*registers another under that name"):
            reg.register(_named("mut_rows", known_inputs=edited), origin="edit")
    assert reg.get("mut_rows") is first
    reg.register(_named("mut_two", known_inputs=table(0.0, 1.0)), origin="two")
    with pytest.raises(ValueError, match="by two.*registers another under that name"):
        reg.register(_named("mut_two", known_inputs=table(0.0, 1.0, 0.0)), origin="three")
    same = reg.register(_named("mut_two", known_inputs=table(0.0, 1.0, 0.0, 1.0)))
    assert reg.get("mut_two") is same  # the same inputs on every run: the same scenario


def test_the_kalman_proposals_need_is_unmet_by_a_process_noise_that_is_not_gaussian():
    """KalmanProposal refuses a process noise that is not Gaussian (its weights take
    ``p = N(f, Q)``), and its need had passed such a plant: the study stopped instead of
    skipping the estimator. Truth: the need says no exactly where the proposal refuses
    (a UniformBox), and yes where the proposal runs (the same plant, Gaussian); a study
    skips kalman_proposal_pf with that reason and runs bootstrap_pf."""
    from difffilter.eval.suite import run_suite
    from difffilter.noise import UniformBox

    def plant(dtype=torch.float64, box=True):
        m = df.NonlinearGaussianModel(
            lambda x: 0.9 * x, lambda x: x, 1e-3 * torch.eye(2, dtype=dtype),
            1e-2 * torch.eye(2, dtype=dtype), torch.zeros(2, dtype=dtype),
            0.1 * torch.eye(2, dtype=dtype))  # fmt: skip
        if box:
            m.process_noise = UniformBox(torch.full((2,), -0.05, dtype=dtype),
                                         torch.full((2,), 0.05, dtype=dtype))  # fmt: skip
        return m

    ys = torch.zeros(1, 3, 2, dtype=torch.float64)
    run = lambda m: df.particle_filter(m, ys, num_particles=8, proposal=df.KalmanProposal(),  # noqa: E731
                                       generator=torch.Generator().manual_seed(0))  # fmt: skip
    with pytest.raises(ValueError, match="needs a Gaussian process noise"):
        run(plant())
    reason = needs.TRANSITION_IS_PROCESS_NOISE.unmet(None, plant())
    assert reason == ("weighs its particles by N(f, Q), and the process noise is a "
                      "UniformBox, not Gaussian")  # fmt: skip
    assert run(plant(box=False)).means.shape == (1, 3, 2)
    assert needs.TRANSITION_IS_PROCESS_NOISE.unmet(None, plant(box=False)) is None
    sc = CustomScenario(name="mut_box", family="mut_box_fam", description="d", model_fn=plant,
                        attack=Bias(value=0.3, entries=(0,), onset=3), runs=2, steps=6,
                        dt=1.0, num_particles=20)  # fmt: skip
    result = run_suite(sc, estimators=["kalman_proposal_pf", "bootstrap_pf"], progress=False)
    assert result.skipped == {"kalman_proposal_pf": reason} and "bootstrap_pf" in result.outputs


def test_a_yaml_file_read_again_with_an_attack_without_value_equality_is_the_same(
    isolated_registry, tmp_path, monkeypatch
):
    """A YAML file is read again on every ``get`` (an edit since must be seen), and an attack
    of one's own returning a :class:`Signal` compared by identity: the unchanged file read
    as "another scenario". Truth: the same file gives the same scenario (its Signal's values
    equal); the file edited to another level is refused, and the first stays registered."""
    import sys
    import types

    from difffilter.models.attacks import Signal

    def sig(level=0.3):
        values = torch.zeros(5, 1)
        values[2:, 0] = level
        return Signal(values)

    mod = types.ModuleType("mut_review_own_attack")
    mod.sig = sig
    monkeypatch.setitem(sys.modules, "mut_review_own_attack", mod)
    monkeypatch.chdir(tmp_path)
    text = ("name: mut_yaml_signal\nsteps: 5\nplant:\n  F: [[0.95, 0.04], [-0.02, 0.8]]\n"
            "  H: [[1.0, 0.0]]\n  Q: 1.0e-4\n  R: 1.0e-3\n  P0: 1.0e-2\n"
            "attack: {kind: 'mut_review_own_attack:sig', level: 0.3}\n")  # fmt: skip
    (tmp_path / "s.yaml").write_text(text)
    reg = isolated_registry
    first = reg.get("s.yaml")
    again = reg.get("s.yaml")  # a fresh Signal of the same values
    assert again.attack is not first.attack and reg.get("mut_yaml_signal") is again
    assert torch.equal(again.attack.values, first.attack.values)
    assert torch.equal(again.attack.values, sig(0.3).values)
    (tmp_path / "s.yaml").write_text(text.replace("level: 0.3", "level: 0.4"))
    with pytest.raises(ValueError, match="or a file edited since it was loaded"):
        reg.get("s.yaml")
    assert torch.equal(reg.get("mut_yaml_signal").attack.values, sig(0.3).values)
