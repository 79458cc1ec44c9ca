"""Findings of a trial of estimators of one's own in the evaluation: their errors name them,
and a clash with a built-in's name names the module that took it."""

from __future__ import annotations

import traceback

import pytest
import torch

from difffilter.eval.suite import run_suite
from difffilter.models import estimators, registry
from difffilter.models.estimators import register
from difffilter.models.needs import Need


@pytest.fixture
def own_estimators(monkeypatch):
    """The registry with the built-ins loaded, restored after the test."""
    estimators.names()
    monkeypatch.setattr(estimators, "ESTIMATORS", dict(estimators.ESTIMATORS))


def _run_shape_bug(ctx):
    def run(traj):
        return torch.zeros(3, 4) @ torch.zeros(5, 6)  # torch's RuntimeError

    return run


def _factory_key_error(ctx):
    return {}["missing_option"]


def _factory_value_error(ctx):
    int("not a number")


@pytest.mark.parametrize(
    "name,factory,needs",
    [
        ("trial_run_runtimeerror", _run_shape_bug, ()),
        ("trial_factory_keyerror", _factory_key_error, ()),
        ("trial_factory_valueerror", _factory_value_error, ()),
        ("trial_need_attributeerror", lambda ctx: (lambda traj: None),
         Need("reads F", lambda scenario, model: None if model.F is not None else "no F")),
    ],
)  # fmt: skip
def test_an_error_of_ones_own_estimator_names_it(own_estimators, name, factory, needs):
    """Only a ValueError of an estimator's run had been named ("name on scenario: …"): a
    factory's error, a need's check's or torch's RuntimeError came bare, and the command
    line printed a factory's ValueError as one line naming nothing."""
    register(name, "a trial's", needs=needs)(factory)
    scenario = registry.get("four_tank_bias").with_steps(20)
    with pytest.raises(Exception) as caught:
        run_suite(scenario, runs=2, estimators=["chi_square_ekf", name], progress=False)
    text = "".join(traceback.format_exception_only(caught.value))
    assert name in text and "four_tank_bias" in text


def test_a_built_in_name_taken_first_blames_the_module_that_took_it(own_estimators):
    """The built-ins register when first needed: a module of one's own imported before them
    had the clash reported as the library's module registering "another under that name"."""

    def mine(ctx):
        return lambda traj: None

    def builtin(ctx):
        return lambda traj: None

    builtin.__module__ = "difffilter.models.generic_estimators"
    register("trial_clash", "mine")(mine)
    with pytest.raises(ValueError, match=rf"of module {__name__} takes the name of a built-in"):
        register("trial_clash", "the library's")(builtin)
