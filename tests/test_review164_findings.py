"""Findings of review 164 (an audit of the numbers and statements the docs make).

docs/adding-a-scenario.md §2 and docs/architecture.md ("Estimator registry"): a scenario
named like a family is refused at ``register``. The registry loads the built-in families
on first use, so a user's module that registers before anything had asked the registry (a
fresh process: ``difffilter-eval --import my_module``) found no family to clash with: the
scenario was accepted, and every later call of the registry then failed, blaming the
built-in family's module. Each case runs in a fresh interpreter, where nothing has loaded
the built-in families yet.
"""

import os
import subprocess
import sys
import textwrap

import pytest

_SCRIPT = textwrap.dedent(
    """
    import torch

    import difffilter as df
    from difffilter.models import registry
    from difffilter.models.scenario import CustomScenario


    def plant(dtype):
        e = torch.eye(1, dtype=dtype)
        return df.LinearGaussianModel(e, e, e, e, torch.zeros(1, dtype=dtype), e)


    try:
        registry.register(
            CustomScenario(name={name!r}, family={family!r}, description="", model_fn=plant)
        )
    except ValueError as error:
        print("REFUSED", error)
    else:
        print("ACCEPTED")
    print("BUILTIN", registry.get("robot_actuator_attack").family)
    """
)


def _fresh(name: str, family: str) -> str:
    done = subprocess.run(
        [sys.executable, "-c", _SCRIPT.format(name=name, family=family)],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "OMP_NUM_THREADS": "1", "DIFFFILTER_CACHE": "off"},
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


@pytest.mark.parametrize(
    "name, family, said",
    [
        ("robot", "mine", "'robot' is the name of a family"),
        ("mine", "four_tank_bias", "of family 'four_tank_bias', the name of a registered"),
    ],
)
def test_a_name_that_clashes_with_a_builtin_family_is_refused_in_a_fresh_process(
    name, family, said
):
    out = _fresh(name, family)
    assert "REFUSED" in out and said in out, out
    assert "BUILTIN robot" in out, out  # the built-in scenarios still load


def test_the_residual_detectors_print_their_settings():
    """``print(ChiSquareDetector(3))`` showed an object's address, where the PoA detector
    prints its settings (an audit's friction): a detector is told by what it prints."""
    from difffilter import fdi

    assert repr(fdi.ChiSquareDetector(2, 0.005, window=4)) == (
        "ChiSquareDetector(dim=2, false_alarm_rate=0.005, window=4)"
    )
    assert repr(fdi.CusumDetector(2.0)) == "CusumDetector(bias=2, threshold=None)"
    assert repr(fdi.CusumDetector(1.5, 11.2146)) == "CusumDetector(bias=1.5, threshold=11.2146)"
