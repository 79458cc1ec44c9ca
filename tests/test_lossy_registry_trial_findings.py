"""Findings of a trial of the registry's estimators on scenarios with a lossy network (each
failed before its fix): an estimator read measurements the receiver never got, or a
family ignored the schedule its scenario declared."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from difffilter.input_loss import InputLossSchedule
from difffilter.models import estimators as E
from difffilter.models import registry
from difffilter.models.four_tank import FourTankScenario
from difffilter.models.lfc import LFCScenario
from difffilter.models.robot import RobotScenario
from difffilter.models.robot_estimators import _compensated
from difffilter.models.schedules import PacketLoss
from difffilter.models.streams import Streams


def _lossy(cls, name: str, steps: int, *, inputs: bool = False):
    """The registry's scenario ``name`` as a subclass of ``cls`` whose network loses 30 % of
    the measurement entries (and, with ``inputs``, 30 % of the input packets)."""

    @dataclasses.dataclass(frozen=True)
    class Lossy(cls):
        def schedule(self):
            return PacketLoss(0.3)

        def input_loss_schedule(self):
            return InputLossSchedule(PacketLoss(0.3)) if inputs else None

    base = registry.get(name)
    fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(base)
              if f.init and f.name != "name"}  # fmt: skip
    return Lossy(**fields, name=f"{name}_lossy").with_steps(steps)


def _context(scenario, model, runs):
    options = E.check_options(scenario.estimator_options(), "s")
    return E.SuiteContext(scenario, model, runs, Streams(0), options, scenario.shipped_checkpoint())


def test_the_literal_pf_is_skipped_on_a_lossy_four_tank_scenario():
    """``normal_pf_literal`` dropped the mask that ``particle_filter_poa(literal=True)``
    refuses: on a lossy schedule it filtered values never received (0.177 cm, 40 alarms)."""
    scenario = _lossy(FourTankScenario, "four_tank_bias", 20)
    model = scenario.system(torch.float64)
    with pytest.raises(E.SkipEstimator, match="literal=True reads every measurement"):
        E.get("normal_pf_literal").build(_context(scenario, model, 2))


@pytest.mark.parametrize("inputs", [False, True])
def test_the_compensated_robot_loop_keeps_the_studys_network(inputs):
    """``mdpf_fused_ci_compensated`` ran its loop without the scenario's schedule and input
    loss: with ``compensate=False`` (the study's own runs) it was 11.9 cm off
    ``mdpf_fused_ci`` on a lossy robot scenario, where it is 0 on a lossless one."""
    scenario = _lossy(RobotScenario, "robot_actuator_attack", 45, inputs=inputs)
    model = scenario.system(torch.float64)
    runs = 2
    tr = scenario.simulate(runs, Streams(0).simulation(), dtype=torch.float64, model=model)
    with torch.no_grad():
        plain = E.get("mdpf_fused_ci").build(_context(scenario, model, runs))(tr)
        loop = _compensated(False)(_context(scenario, model, runs))(tr)
    assert torch.equal(loop.trajectories.mask, tr.mask)
    assert torch.equal(loop.trajectories.x, tr.x)
    torch.testing.assert_close(loop.output.means, plain.means, rtol=0, atol=1e-9)


def test_a_lossy_lfc_scenario_is_refused():
    """``LFCScenario.simulate`` never read ``schedule()`` or ``input_loss_schedule()``: a
    subclass with ``PacketLoss(0.3)`` ran 100 % received without a word."""
    scenario = _lossy(LFCScenario, "lfc_step", 20)
    with pytest.raises(ValueError, match="the LFC loops take every measurement and input"):
        scenario.simulate(2, Streams(0).simulation(), dtype=torch.float64)
