"""Mutation-review tests of difffilter.control, difffilter.input_loss and
models.yaml_scenario: each checks a behaviour against an independent truth (numpy's
rank of the written-out Kalman matrix, the eigenvalues written out, the InputLoss
docstring's shape contract, a YAML file's own numbers and documented defaults and error
messages) that the existing fast tests left unchecked."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difffilter.control import controllability_rank, observer_poles
from difffilter.input_loss import InputLoss


def test_controllability_rank_of_an_integrator_chain_needs_every_power():
    """A chain of three integrators driven at its end needs ``A²B`` for full rank: the rank
    is numpy's rank of ``[B, AB, A²B]`` written out (3), and 2 with the last input cut."""
    A = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    B = torch.tensor([[0.0], [0.0], [1.0]], dtype=torch.float64)
    An, Bn = A.numpy(), B.numpy()
    kalman = np.hstack([Bn, An @ Bn, An @ An @ Bn])
    assert controllability_rank(A, B) == np.linalg.matrix_rank(kalman) == 3
    B2 = torch.tensor([[0.0], [1.0], [0.0]], dtype=torch.float64)  # only two reached
    assert controllability_rank(A, B2) == 2


def test_observer_poles_move_the_zero_eigenvalue_to_the_slowest_other_one():
    """``observer_poles``'s default moves a zero eigenvalue of ``A − BK₁`` to the slowest
    of the other scaled eigenvalues (docstring): for ``diag(0, −1, −2)``, factor 3, dt 0.1,
    the poles are ``exp(0.1·[−3, −3, −6])`` written out."""
    A_closed = torch.diag(torch.tensor([0.0, -1.0, -2.0], dtype=torch.float64))
    got = np.sort(observer_poles(A_closed, 0.1, factor=3.0).numpy().real)
    want = np.sort(np.exp(0.1 * np.array([-3.0, -3.0, -6.0])))
    np.testing.assert_allclose(got, want, rtol=1e-12)
    # an explicit zero_pole is used as given
    got = np.sort(observer_poles(A_closed, 0.1, factor=3.0, zero_pole=-10.0).numpy().real)
    np.testing.assert_allclose(got, np.sort(np.exp(0.1 * np.array([-10.0, -3.0, -6.0]))))


def test_an_input_loss_mask_one_step_short_is_refused_by_check():
    """``InputLoss.check`` needs a mask row for every step up to ``end`` (its docstring):
    a mask of ``end − 1`` steps is a ``ValueError`` naming the shape it needs, not an
    ``IndexError`` at the last step."""
    loss = InputLoss(torch.ones(2, 4, dtype=torch.bool))
    loss.check(2, 1, 4)  # exactly long enough
    with pytest.raises(ValueError, match=r"T >= 5"):
        loss.check(2, 1, 5)


def _yaml_scenario(text: str, tmp_path):
    from difffilter.models.yaml_scenario import scenario_from_yaml

    path = tmp_path / "plant.yaml"
    path.write_text(text)
    return scenario_from_yaml(path)


def test_a_yaml_plants_matrices_are_the_numbers_written_in_it(tmp_path):
    """A YAML linear plant (F, B, H not symmetric; Q a diagonal; R a number; P0 a matrix)
    becomes the model with exactly the numbers in the file: F and H row by row, Q's list
    its diagonal (a variance, not a standard deviation), R times I."""
    scenario = _yaml_scenario(
        """
name: yaml_numbers
plant:
  F: [[0.9, 0.2], [-0.1, 0.8]]
  B: [[0.0, 1.0], [0.5, 0.0]]
  H: [[1.0, 0.3], [0.0, 2.0]]
  Q: [1.0e-2, 4.0e-2]
  R: 0.25
  m0: [1.0, 2.0]
  P0: [[2.0, 0.5], [0.5, 3.0]]
""",
        tmp_path,
    )
    m = scenario.model_fn(torch.float64)
    t = lambda rows: torch.tensor(rows, dtype=torch.float64)  # noqa: E731
    assert torch.equal(m.F, t([[0.9, 0.2], [-0.1, 0.8]]))
    assert torch.equal(m.B, t([[0.0, 1.0], [0.5, 0.0]]))
    assert torch.equal(m.H, t([[1.0, 0.3], [0.0, 2.0]]))
    assert torch.equal(m.process_cov(1), t([[1e-2, 0.0], [0.0, 4e-2]]))
    assert torch.equal(m.measurement_cov(1), t([[0.25, 0.0], [0.0, 0.25]]))
    assert torch.equal(m.initial.mean, t([1.0, 2.0]))
    assert torch.equal(m.initial.cov, t([[2.0, 0.5], [0.5, 3.0]]))


def test_a_yaml_plants_defaults_are_the_documented_ones(tmp_path):
    """Without m0 and P0 the prior is ``N(0, I)`` (module docstring: "default zeros",
    "default I"); a scalar Q is that number times I; input_loss defaults to ``on_loss:
    hold`` and ``acknowledged: true``, its rate the number written."""
    scenario = _yaml_scenario(
        """
name: yaml_defaults
plant:
  F: [[1.0, 0.1], [0.0, 1.0]]
  B: [[0.0], [1.0]]
  H: [[1.0, 0.0]]
  Q: 1.0e-3
  R: 1.0e-2
inputs: {kind: constant, value: 1.0}
input_loss: {kind: packet_loss, rate: 0.3}
""",
        tmp_path,
    )
    m = scenario.model_fn(torch.float64)
    assert torch.equal(m.initial.mean, torch.zeros(2, dtype=torch.float64))
    assert torch.equal(m.initial.cov, torch.eye(2, dtype=torch.float64))
    assert torch.equal(m.process_cov(1), 1e-3 * torch.eye(2, dtype=torch.float64))
    loss = scenario.input_loss
    assert loss.on_loss.value == "hold" and loss.acknowledged is True
    assert loss.schedule.rate == 0.3


def test_a_yaml_sinusoids_inputs_are_the_formula_in_seconds(tmp_path):
    """``inputs: {kind: sinusoid, amplitude, frequency (Hz), phase (rad)}`` with ``dt`` is
    ``A sin(2π f dt k + φ)`` at step ``k`` (written out), one input or one per input."""
    one = _yaml_scenario(
        """
name: yaml_sine
dt: 0.05
steps: 20
plant: {F: [[0.9]], B: [[1.0]], H: [[1.0]], Q: 1.0e-3, R: 1.0e-2}
inputs: {kind: sinusoid, amplitude: 2.0, frequency: 1.5, phase: 0.3}
""",
        tmp_path,
    )
    k = torch.arange(20, dtype=torch.float64)
    want = 2.0 * torch.sin(2 * np.pi * 1.5 * 0.05 * k + 0.3)
    got = one.known_inputs(k)
    torch.testing.assert_close(got.reshape(-1), want, rtol=0, atol=1e-12)
    two = _yaml_scenario(
        """
name: yaml_sine2
dt: 0.05
steps: 20
plant: {F: [[0.9]], B: [[1.0, 0.5]], H: [[1.0]], Q: 1.0e-3, R: 1.0e-2}
inputs: {kind: sinusoid, amplitude: [2.0, 1.0], frequency: [1.5, 0.5], phase: [0.3, -0.7]}
""",
        tmp_path,
    )
    got = two.known_inputs(k)
    want = torch.stack(
        [
            2.0 * torch.sin(2 * np.pi * 1.5 * 0.05 * k + 0.3),
            1.0 * torch.sin(2 * np.pi * 0.5 * 0.05 * k - 0.7),
        ],
        -1,
    )
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


_PLANT = "plant: {F: [[0.9, 0.1], [0.0, 0.8]], B: [[0.0], [1.0]], H: [[1.0, 0.0]], "


@pytest.mark.parametrize(
    "text, message",
    [
        # Q and R are required (no silent default; _plant's message)
        (f"name: e\n{_PLANT}R: 1.0e-2}}\n", r"plant\.Q is required"),
        (f"name: e\n{_PLANT}Q: 1.0e-2}}\n", r"plant\.R is required"),
        # an unknown top-level field is named, not ignored
        (f"name: e\nstep: 20\n{_PLANT}Q: 1.0e-2, R: 1.0e-2}}\n", r"unknown field\(s\) step"),
        # a false-alarm rate outside (0, 1) is refused by the file
        (f"name: e\nfalse_alarm_rate: 1.5\n{_PLANT}Q: 1.0e-2, R: 1.0e-2}}\n",
         r"false_alarm_rate must be a rate in \(0, 1\)"),
        # B's rows must match the state
        ("name: e\nplant: {F: [[0.9, 0.1], [0.0, 0.8]], B: [[1.0]], H: [[1.0, 0.0]], "
         "Q: 1.0e-2, R: 1.0e-2}\n", r"plant\.B must have dx = 2 rows"),
        # inputs of the wrong width
        (f"name: e\n{_PLANT}Q: 1.0e-2, R: 1.0e-2}}\ninputs: {{kind: constant, value: [1.0, 2.0]}}\n",
         r"inputs: they give 2 value\(s\) per step and the plant has 1 input"),
        # input loss on a plant without inputs
        ("name: e\nplant: {F: [[0.9]], H: [[1.0]], Q: 1.0e-2, R: 1.0e-2}\n"
         "input_loss: {kind: packet_loss, rate: 0.1}\n", r"input_loss: the plant has no input"),
    ],
)  # fmt: skip
def test_a_yaml_scenarios_mistakes_are_named(tmp_path, text, message):
    """Each mistake the module docstring and ``_plant`` promise to name raises a
    ``ValueError`` with that message (no default silently filled, no field ignored)."""
    with pytest.raises(ValueError, match=message):
        _yaml_scenario(text, tmp_path)


def test_a_yaml_round_robin_starts_at_group_zero_by_default(tmp_path):
    """``schedule: {kind: round_robin, groups}`` without ``start`` serves ``groups[0]``
    at step 0, ``groups[1]`` at step 1 (written out: the mask of the schedule)."""
    scenario = _yaml_scenario(
        f"name: rr\n{_PLANT.replace('H: [[1.0, 0.0]]', 'H: [[1.0, 0.0], [0.0, 1.0]]')}"
        "Q: 1.0e-2, R: 1.0e-2}\nschedule: {kind: round_robin, groups: [[0], [1]]}\n",
        tmp_path,
    )
    mask = scenario.schedule().mask((1,), 4, 2, torch.Generator().manual_seed(0))
    want = torch.tensor([[True, False], [False, True]] * 2)
    assert torch.equal(mask.reshape(4, 2), want)


def test_a_yaml_scenario_takes_an_attack_of_ones_own_as_a_threat_set_names_it(tmp_path):
    """``attack: {kind: package.module:object, …}`` builds the attack the path names with its
    arguments, as a threat set's entry does (a user trial's YAML scenario refused the
    ``module:object`` kind its own threat set accepted): here the library's Ramp by its
    path, the same attack as ``kind: ramp``; a path that does not import is named."""
    from difffilter.threats import Ramp

    plant = f"{_PLANT.replace('B: [[0.0], [1.0]], ', '')}Q: 1.0e-2, R: 1.0e-2}}\n"
    by_path = _yaml_scenario(
        f"name: own\nsteps: 30\n{plant}"
        "attack: {kind: 'difffilter.threats:Ramp', slope: 0.02, onset: 5}\n",
        tmp_path,
    )
    assert by_path.attack_model() == Ramp(slope=0.02, onset=5)
    with pytest.raises(ValueError, match=r"attack.*no_such_module"):
        _yaml_scenario(f"name: own\n{plant}attack: {{kind: 'no_such_module:Thing'}}\n", tmp_path)


def test_the_control_design_helpers_refuse_a_nan_or_infinite_setting():
    """From a fuzzing trial of the public functions: ``observer_poles`` had given NaN or
    infinite poles for a NaN or infinite ``factor`` and slower ones for a negative one
    (``luenberger_gain`` checked only the sign), ``uncontrollable_direction`` had called a
    controllable pair uncontrollable under a NaN ``tol``, and ``lqr`` had taken an
    infinite ``shift``; each is refused now, naming the argument."""
    from difffilter.control import LQRMethod, lqr, luenberger_gain, uncontrollable_direction

    d = torch.float64
    A_closed = torch.diag(torch.tensor([0.0, -1.0, -2.0], dtype=d))
    for bad in (float("nan"), float("inf"), -1.0, 0.0):
        with pytest.raises(ValueError, match=r"factor must be a finite number > 0"):
            observer_poles(A_closed, 0.1, factor=bad)
        with pytest.raises(ValueError, match=r"factor must be a finite number > 0"):
            luenberger_gain(torch.eye(3, dtype=d), A_closed, 0.1, factor=bad)
        with pytest.raises(ValueError, match="dt must be a finite number > 0"):
            observer_poles(A_closed, bad)
    with pytest.raises(ValueError, match="zero_pole must be a finite number; got nan"):
        observer_poles(A_closed, 0.1, zero_pole=float("nan"))
    for bad in (0.0, 1.0):
        with pytest.raises(ValueError, match="zero_pole must be None or a finite number < 0"):
            observer_poles(A_closed, 0.1, zero_pole=bad)
    A = torch.tensor([[0.0, 1.0], [0.0, 0.0]], dtype=d)
    B = torch.tensor([[0.0], [1.0]], dtype=d)
    assert uncontrollable_direction(A, B) is None  # a double integrator: controllable
    for bad in (float("nan"), float("inf"), -1.0):
        with pytest.raises(ValueError, match="tol must be a finite number >= 0"):
            uncontrollable_direction(A, B, tol=bad)
    with pytest.raises(ValueError, match="shift must be a finite number > 0"):
        lqr(A, B, method=LQRMethod.SHIFT, shift=float("inf"))


def test_a_yaml_sinusoid_or_chirp_attack_reads_the_files_sampling_period(tmp_path):
    """A sinusoid's ``omega`` (rad per unit of ``dt``) and a chirp's frequencies are in the
    file's time unit, as the inputs' frequency is: the attack's ``dt`` is the file's unless
    it sets its own (a trial: ``omega: π`` at ``dt: 0.01`` had been read per step,
    ``A sin(π s)``, zero at every step). A covert attack's nested signal too; a threat set
    on the scenario reads it so."""
    import math

    from difffilter.threats import with_sampling_period

    head = """
name: yaml_sine{n}
dt: 0.01
plant:
  F: [[0.9, 0.0], [0.0, 0.8]]
  B: [[0.0], [0.2]]
  H: [[1.0, 0.0]]
  Q: 1.0e-4
  R: 1.0e-3
"""
    cases = {
        "": (f"attack: {{kind: sinusoid, amplitude: 1.0, omega: {math.pi}, onset: 3}}", 0.01),
        "_own": ("attack: {kind: sinusoid, amplitude: 1.0, omega: 3.0, dt: 0.5, onset: 3}", 0.5),
        "_chirp": ("attack: {kind: chirp, f0: 0.1, f1: 1.0, sweep: 10, onset: 3}", 0.01),
    }
    for n, (line, dt) in cases.items():
        attack = _yaml_scenario(head.format(n=n) + line, tmp_path).attack
        assert attack.dt == dt
    covert = with_sampling_period(
        {"kind": "covert", "signal": {"kind": "sinusoid", "omega": 1.0}}, 0.01
    )
    assert covert["signal"]["dt"] == 0.01 and "dt" not in covert
    assert with_sampling_period({"kind": "bias", "value": 1.0}, 0.01) == {
        "kind": "bias",
        "value": 1.0,
    }
    assert with_sampling_period({"kind": "sinusoid"}, None) == {"kind": "sinusoid"}


def test_the_control_design_helpers_take_a_setting_written_as_a_one_element_tensor():
    """A review: ``factor=torch.tensor(3.0)`` and ``tol=torch.tensor(1e-9)`` ran before the
    checks above, which refused them as "not a positive number"; they are read as their
    numbers."""
    from difffilter.control import uncontrollable_direction

    d = torch.float64
    A_closed = torch.diag(torch.tensor([0.0, -1.0, -2.0], dtype=d))
    torch.testing.assert_close(observer_poles(A_closed, 0.1, factor=torch.tensor(3.0)),
                               observer_poles(A_closed, 0.1, factor=3.0))  # fmt: skip
    A = torch.tensor([[0.0, 1.0], [0.0, 0.0]], dtype=d)
    B = torch.tensor([[0.0], [1.0]], dtype=d)
    assert uncontrollable_direction(A, B, tol=torch.tensor(1e-9)) is None
