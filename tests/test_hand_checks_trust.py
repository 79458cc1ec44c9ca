"""Hand checks of what is trusted without a second look: the online step's vouched carries
(a leaf replaced or a nested tensor written in place must be validated again), the
registry's names and plug-ins, the mixed training seeds, and the shapes and ranges of the
papers' tabulated attacks.

Each test failed on a mutant of mutation round 11 that the rest of the suite let through.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any, NamedTuple

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter import _vouched, fdi
from difffilter.models import registry

F64 = torch.float64


def _model_with_input():
    F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=F64)
    eye = torch.eye(2, dtype=F64)
    B = torch.tensor([[0.0], [0.1]], dtype=F64)
    return df.LinearGaussianModel(F, eye, 0.01 * eye, 0.1 * eye, torch.zeros(2, dtype=F64),
                                  eye, B=B)  # fmt: skip


# ---------------------------------------------------------------- vouched carries


class _Carry(NamedTuple):
    mean: torch.Tensor
    aux: Any


def test_a_carry_whose_dict_leaf_was_replaced_is_no_longer_vouched_for():
    """ "Unchanged is exact: the carry's leaves (through nested tuples, lists and dicts)
    must be the very objects vouched for" (the module docstring): the same carry object
    with one dict value swapped for another tensor is validated again."""
    owner = type("Owner", (), {})()
    established = _vouched.Established(owner, F64, "cpu", (3,), 2, 1)
    kept = torch.ones(3, 2, dtype=F64)  # still alive: its weak reference does not die
    carry = _Carry(torch.zeros(3, 2, dtype=F64), {"s": kept})
    _vouched.vouch(carry, established)
    assert _vouched.vouched(owner, carry) is established
    carry.aux["s"] = torch.full((3, 2), float("nan"), dtype=F64)
    assert _vouched.vouched(owner, carry) is None


def test_a_nested_carrys_tensor_written_in_place_is_validated_again():
    """The gated filter's carry holds the Kalman filter's: a NaN written into the inner
    mean is named at the next step, not filtered on."""
    model = _model_with_input()
    y, u = torch.zeros(3, 2, dtype=F64), torch.zeros(3, 1, dtype=F64)
    gated = fdi.GatedFilter(fdi.ChiSquareDetector(2))
    carry, _ = gated.step(gated.init(model, (3,)), y, u)
    gated.step(carry, y, u)  # trusted as it is
    carry.inner.mean[0, 0] = float("nan")
    with pytest.raises(ValueError, match="mean"):
        gated.step(carry, y, u)


@pytest.mark.parametrize("make", [df.KalmanFilter, df.ExtendedKalmanFilter,
                                  df.UnscentedKalmanFilter,
                                  lambda: fdi.GatedFilter(fdi.ChiSquareDetector(2))])  # fmt: skip
@pytest.mark.parametrize("how", ["add_", "load_state_dict"])
def test_a_noise_mean_written_in_place_is_refused_at_the_next_step(make, how):
    """The Gaussian filters take every noise as zero-mean and refuse one that is not, at
    init and in the full checks; a mean written in place between steps (``loc.add_``, or
    ``load_state_dict`` of a model whose noise has a mean, which copies in place) had been
    dropped by the lean step without a word (an online-step trial: the mean 3.5 off). Set
    back to zero, the carry steps again and is vouched for."""
    model = _model_with_input()
    est = make()
    y, u = torch.ones(2, dtype=F64), torch.zeros(1, dtype=F64)
    carry, _ = est.step(est.init(model), y, u)
    with torch.no_grad():
        if how == "add_":
            model.measurement_noise.loc.add_(5.0)
        else:
            state = {k: v.clone() for k, v in model.state_dict().items()}
            state["measurement_noise.loc"] += 5.0
            model.load_state_dict(state)
    with pytest.raises(ValueError, match=r"model.measurement_noise has mean \[5.0, 5.0\]"):
        est.step(carry, y, u)
    with torch.no_grad():
        model.measurement_noise.loc.zero_()  # back to zero: stepped again, validated in full
    carry, out = est.step(carry, y, u)
    assert _vouched.vouched(est, carry) is not None and torch.isfinite(out.mean).all()


class _Model:
    """A leaf that takes a weak reference (as the filters' models do)."""


def _same_ids(monkeypatch, pairs):
    """``_vouched``'s ``id`` answers each object of ``pairs`` ``(new, old)`` with the old
    one's: what CPython does when a freed carry's memory is given to a new one."""
    alias = {id(new): id(old) for new, old in pairs}
    monkeypatch.setattr(_vouched, "id", lambda obj: alias.get(id(obj), id(obj)), raising=False)


@pytest.mark.parametrize("freed", ["tensor", "model"])
def test_a_carry_that_reuses_a_freed_carrys_ids_is_not_trusted(monkeypatch, freed):
    """The registry keys carries by ``id`` and compares leaves by ``id``: a new carry made
    where a freed one lay may answer the same numbers. Its tensors' or its model's weak
    references are then dead, and that alone refuses it (a NaN mean would otherwise step
    unchecked). Checked with ``id`` standing in for the reuse; the live control is trusted."""
    owner = type("Owner", (), {})()
    established = _vouched.Established(owner, F64, "cpu", (3,), 2, 1)
    old = _Carry(torch.zeros(3, 2, dtype=F64), _Model())
    _vouched.vouch(old, established)
    assert _vouched.vouched(owner, old) is established
    new = _Carry(torch.full((3, 2), float("nan"), dtype=F64) if freed == "tensor" else old.mean,
                 _Model() if freed == "model" else old.aux)  # fmt: skip
    _same_ids(monkeypatch, [(new, old), (new.mean, old.mean), (new.aux, old.aux)])
    assert _vouched.vouched(owner, new) is established  # the old carry is still alive
    old_leaf = old.mean if freed == "tensor" else old.aux
    del old
    del old_leaf  # the last strong reference: the weak one dies
    assert _vouched.vouched(owner, new) is None


# ---------------------------------------------------------------- the registry


def test_registering_another_scenario_under_a_used_name_is_refused(isolated_registry):
    base = registry.get("four_tank_bias")
    assert registry.register(base) is base  # the same scenario again: nothing to say
    # (a contributor's trial: the error blamed the library's module that came second in
    # the import order, not the contributor's that took the name first)
    with pytest.raises(
        ValueError, match=r"'four_tank_bias' is already registered, by module "
        r"difffilter\.models\.four_tank, .*module \S*test_hand_checks_trust registers another"
        ".*in a new process"
    ):  # fmt: skip
        registry.register(dataclasses.replace(base, headline=not base.headline))
    assert registry.get("four_tank_bias") is base


@pytest.mark.parametrize("name", ["all", "robustness", "lfc", "four_tank"])
def test_a_scenario_named_like_a_selection_is_refused(isolated_registry, name):
    """``difffilter-eval all``/``robustness``/a family's name select many scenarios: a
    scenario so named registered without a word and could never be run by name."""
    base = registry.get("four_tank_bias")
    with pytest.raises(ValueError, match=f"scenario name '{name}' is .*could never be run by name"):
        registry.register(dataclasses.replace(base, name=name))
    with pytest.raises(ValueError, match="of family 'lfc_step', the name of a registered scenario"):
        registry.register(dataclasses.replace(base, name="mine", family="lfc_step"))
    assert name not in registry._REGISTRY and "mine" not in registry._REGISTRY


def test_an_estimator_registered_twice_names_both_modules():
    from difffilter.models import estimators

    first = estimators.get("chi_square_ekf")
    with pytest.raises(
        ValueError, match=r"'chi_square_ekf' is already registered, by module "
        r"difffilter\.models\.generic_estimators; module \S*test_hand_checks_trust registers"
    ):  # fmt: skip

        @estimators.register("chi_square_ekf", "mine")
        def _(ctx):
            return None

    assert estimators.get("chi_square_ekf") is first


def test_a_family_report_registered_twice_names_both_modules(monkeypatch):
    from difffilter.eval import report

    monkeypatch.setattr(report, "_FAMILIES", {})
    monkeypatch.setattr(report, "_FAMILY_ORIGINS", {"mine": "my_first_module"})
    first = report.register_family("mine", report.FamilyReport(report_cost=2.0))
    assert report.register_family("mine", report.FamilyReport(report_cost=2.0)) is not None
    with pytest.raises(ValueError, match="by module my_first_module; module \\S*test_hand_"):
        report.register_family("mine", report.FamilyReport(report_cost=3.0))
    assert report._FAMILIES["mine"] == first and first.report_cost == 2.0


def test_a_module_object_that_is_a_function_needing_arguments_is_named(isolated_registry, tmp_path,
                                                                      monkeypatch):  # fmt: skip
    """A user trial named the plant's model function (dtype -> model) as the scenario: a
    raw TypeError traceback from the call."""
    (tmp_path / "user_fn_plants.py").write_text(
        "from difffilter.models import registry\n"
        "def model(dtype):\n    raise AssertionError('never called')\n"
        "def scenarios():\n    return [registry.get('four_tank_bias')]\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(
        ValueError, match="'user_fn_plants:model' is a function that needs arguments"
    ):
        registry.get("user_fn_plants:model")
    assert registry.get("user_fn_plants:scenarios").name == "four_tank_bias"


def test_a_plug_in_that_fails_in_any_way_is_a_warning_and_the_built_ins_stay(
    isolated_registry, monkeypatch
):
    """A plug-in naming an object that is not a scenario fails with a ValueError, not an
    ImportError: it is reported as a warning all the same, as the module says."""
    from importlib.metadata import EntryPoint

    monkeypatch.setattr(registry, "_LOADED", False)  # load again: the plug-ins this time
    broken = EntryPoint("not_a_scenario", "os:sep", registry.PLUGIN_GROUP)
    monkeypatch.setattr(registry, "entry_points",
                        lambda group: [broken] if group == registry.PLUGIN_GROUP else [])  # fmt: skip
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        names = registry.names()
    messages = [str(w.message) for w in caught]
    assert any("'not_a_scenario' (os:sep) failed to load: ValueError" in m for m in messages)
    assert "four_tank_bias" in names


# ---------------------------------------------------------------- training seeds


def test_mixed_seeds_are_numpys_seed_sequence_of_the_parts_in_order():
    """``mix_seed(train_seed, epoch, index)``: epoch 1's batch 2 is not epoch 2's batch 1."""
    from difffilter.train.common import mix_seed

    state = np.random.SeedSequence([5, 1, 2]).generate_state(1, np.uint64)
    assert mix_seed(5, 1, 2) == int(state[0]) >> 1
    assert mix_seed(5, 1, 2) != mix_seed(5, 2, 1)


# ---------------------------------------------------------------- tabulated attacks


def test_replacement_draws_lie_in_their_box():
    """``ξ_k ~ U(low, high)`` per entry (the RRP paper, eqs 4–6), on a box away from 0."""
    from difffilter.models.attacks import Replacement

    attack = Replacement(rate=1.0, low=(10.0, -3.0), high=(11.0, -2.0))
    values, flags = attack.sample((200,), 4, 2, torch.Generator().manual_seed(0), dtype=F64)
    low, high = torch.tensor([10.0, -3.0], dtype=F64), torch.tensor([11.0, -2.0], dtype=F64)
    assert bool(((values >= low) & (values < high)).all()) and bool(flags.all())
    # uniform: the mean of 800 draws per entry within 4 standard errors (1/√12/√800)
    assert torch.allclose(values.mean((0, 1)), (low + high) / 2, atol=4 * 0.2887 / 800**0.5)


def test_a_signal_needs_a_value_for_every_step_and_entry():
    """``values [T, dim]`` or ``[B, T, dim]``: a one-step signal is not stretched over the
    horizon, nor a one-entry signal copied onto every entry."""
    from difffilter.models.attacks import Signal

    ramp = torch.arange(10.0, dtype=F64).reshape(5, 2)
    ramp[0] = 0.0  # nothing at the first step: not flagged there
    values, flags = Signal(ramp).sample((3,), 5, 2, dtype=F64)
    assert torch.equal(values, ramp.expand(3, 5, 2)) and flags[:, 0].logical_not().all()
    per_run = torch.ones(3, 5, 2, dtype=F64)
    assert torch.equal(Signal(per_run).sample((3,), 5, 2, dtype=F64)[0], per_run)
    for shape in ((1, 2), (5, 1), (4, 2), (6, 2), (2, 5, 2)):
        with pytest.raises(ValueError, match=r"the loop needs \[5, 2\] or \[3, 5, 2\]"):
            Signal(torch.ones(shape, dtype=F64)).sample((3,), 5, 2, dtype=F64)


def test_a_checkpoint_is_rewritten_in_place_only_with_force(tmp_path):
    from difffilter.train.common import check_checkpoint_out

    source = tmp_path / "est.ckpt"
    source.write_text("weights")
    with pytest.raises(ValueError, match="--force"):
        check_checkpoint_out(source, force=False, replacing=source)
    check_checkpoint_out(source, force=True, replacing=source)


# ---------------------------------------------------------------- the threat library


def test_a_random_walk_moves_at_its_onset():
    """``a_k = a_{k−1} + σ_w ε_k`` from ``a = 0`` before the onset: the first attacked
    measurement already carries ``σ_w ε``, the steps before carry nothing."""
    from difffilter.threats import RandomWalk

    values, flags = RandomWalk(step_std=1.0, onset=3).sample(
        (50,), 6, 1, torch.Generator().manual_seed(0), dtype=F64
    )
    assert not values[:, :2].any() and bool((values[:, 2] != 0).all())
    assert flags[:, 2:].all() and not flags[:, :2].any()
    # the increments are the unit normal draws: their spread over 50 runs × 4 steps ≈ 1
    assert (
        0.8 < float(values[:, 2:].diff(dim=1, prepend=torch.zeros(50, 1, 1, dtype=F64)).std()) < 1.2
    )


class _RecordingPlant:
    """``x_k = sin(x_{k−1}) + u_{k−1} + 0.1 t`` (``t = k − 1``), recording each ``t``."""

    dim_u = 1

    def __init__(self):
        self.times = []

    def transition(self, x, u, t):
        self.times.append(t)
        return torch.sin(x) + u + 0.1 * t

    def observe(self, x, k):
        return x


def test_the_covert_attackers_copies_follow_the_true_state_until_it_injects():
    """Eq. of :class:`~difffilter.threats.Covert` on a nonlinear plant: until the first
    injection both copies restart from the true ``x_{k−1}`` and step with the loop's
    ``t = k − 1``; from then on they run on their own, the attacked one with ``u + a``."""
    from difffilter.threats import Bias, Covert

    plant = _RecordingPlant()
    covert = Covert(Bias(1.0, channel="actuator", onset=3), plant)
    f = lambda x, u, t: torch.sin(x) + u + 0.1 * t  # noqa: E731
    u = torch.full((1, 1), 0.2, dtype=F64)
    xs = [torch.tensor([[v]], dtype=F64) for v in (0.3, 1.7, -0.4, 0.9)]  # x_0 … x_3
    state = covert.init((1,), 5, 1, dtype=F64)
    want = {}
    for k in (1, 2, 3, 4):
        state, value, flag = covert.step(state, k, x=xs[k - 1], u=u)
        if k <= 3:  # not injected before step 3: both from the true x_{k−1}
            base_a = base_n = xs[k - 1]
        else:
            base_a, base_n = want["attacked"], want["nominal"]
        a = 1.0 if k >= 3 else 0.0
        want = {"attacked": f(base_a, u + a, k - 1), "nominal": f(base_n, u, k - 1)}
        torch.testing.assert_close(state[1], want["attacked"])
        torch.testing.assert_close(state[2], want["nominal"])
        assert bool(flag.all()) == (k >= 3)
    assert plant.times == [0, 0, 1, 1, 2, 2, 3, 3]
    _, hidden = covert.conceal(state, 4, y=None, x=None)
    torch.testing.assert_close(hidden, want["nominal"] - want["attacked"])


def test_a_k_sigma_bias_without_k_is_one_and_a_half_noise_deviations():
    """``ksigma_bias`` written without ``k``: ``KSigmaBias``'s default ``k = 1.5``, times
    ``σ = √diag R`` of the model."""
    from difffilter.threats import threat_from_dict

    eye = torch.eye(2, dtype=F64)
    R = torch.diag(torch.tensor([0.04, 0.09], dtype=F64))
    model = df.LinearGaussianModel(eye, eye, eye, R, torch.zeros(2, dtype=F64), eye)
    bias = threat_from_dict({"kind": "ksigma_bias", "onset": 1}, model=model)
    values, _ = bias.sample((1,), 3, 2, dtype=F64)
    torch.testing.assert_close(values[0, 0], torch.tensor([1.5 * 0.2, 1.5 * 0.3], dtype=F64))


def test_an_attack_that_starts_after_the_last_step_is_refused():
    """A 1-based ``onset`` or a paper attack's 0-based ``start`` (``u_start`` acts on
    measurement ``start + 1``) after the last of ``num_steps`` measurements never acts."""
    from difffilter.models.attacks import ActuatorInjection
    from difffilter.threats import Bias, check_attack_fits

    eye = torch.eye(2, dtype=F64)
    model = df.LinearGaussianModel(eye, eye, eye, eye, torch.zeros(2, dtype=F64), eye,
                                   B=torch.ones(2, 1, dtype=F64))  # fmt: skip
    check_attack_fits(ActuatorInjection((1.0,), start=4), model, 5)
    check_attack_fits(Bias(1.0, onset=5), model, 5)
    for attack, first in ((ActuatorInjection((1.0,), start=5), 6), (Bias(1.0, onset=6), 6)):
        with pytest.raises(ValueError, match=rf"starts at step {first}, after the last step \(5\)"):
            check_attack_fits(attack, model, 5)


@pytest.mark.parametrize("kind", ["kf", "ekf", "pf"])
def test_a_dropped_carry_and_model_are_freed(kind):
    """From a deployment trial: the registry of vouched carries held the last 64 carries'
    models (and a Kalman filter's gain schedule, which holds its model) by plain references,
    so a process that rebuilt 40 MB models kept 1.2 GB alive after dropping them. It holds
    them weakly now: dropping the carry and the model frees the model."""
    import gc
    import weakref

    from conftest import online_pair

    F64 = torch.float64
    model, estimator, carry = online_pair(kind, num_particles=20)
    for _ in range(3):
        carry, out = estimator.step(carry, torch.ones(2, dtype=F64))
    again, _ = estimator.step(carry, torch.ones(2, dtype=F64))  # (still vouched for: lean)
    alive = weakref.ref(model)
    del model, carry, out, again
    gc.collect()
    assert alive() is None
