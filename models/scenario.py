"""Scenarios as data: a system, an attack, a schedule, and how to simulate them.

A scenario is a frozen dataclass (subclass of :class:`Scenario`) registered by name in
:mod:`difffilter.models.registry`. It builds its system (a
:class:`~difffilter.StateSpaceModel`) and simulates a batch of runs as
:class:`Trajectories`; the evaluation suite, the reports and the training data modules
consume nothing else. A family (four-tank, LFC, …) is one module of ``models/`` that
defines a subclass and registers its instances; nothing lists the families by hand.

Simulation (:func:`simulate`, the closed loop of :mod:`difffilter.loop` without an
estimator), time index ``t`` ↔ ``k = t + 1``::

    x_0 ~ prior (or its mean)
    u_applied,k−1 = inject_actuator(u_{k−1})            actuator attack, if any
    x_k ~ p(x_k | x_{k−1}, u_applied,k−1),  y_k ~ p(y_k | x_k)
    ỹ_k = inject_sensor(y_k)                             sensor attack, if any
    mask_k = schedule(k)                                 received entries

Random draws come from named generators: ``"plant"`` (initial state, process and
measurement noise, in that order per step), ``"attack"``, ``"schedule"`` and, under an
input loss, ``"input_schedule"``; the plant realisation therefore does not depend on the
attack, and vice versa.
"""

from __future__ import annotations

import contextlib
import dataclasses
import inspect
import math
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, ClassVar

import torch
from torch import Tensor

from difffilter._checks import (
    check_finite_number,
    check_integer,
    check_positive_int,
    model_dtype_device,
)
from difffilter.attack import Attack, Channel
from difffilter.input_loss import InputLossSchedule
from difffilter.loop import DrawnNoise, KnownInputs, Trajectories, closed_loop
from difffilter.ssm import StateSpaceModel
from difffilter.threats import Bias, KSigmaBias

from .attacks import SensorBias
from .schedules import AllSensors

__all__ = [
    "Trajectories",
    "Scenario",
    "CustomScenario",
    "simulate",
    "OWN_ATTACK",
    "warn_on_global_draws",
]


@contextlib.contextmanager
def warn_on_global_draws(generators: Mapping, names=("attack", "schedule")) -> Iterator[None]:
    """Warn when the block drew from torch's global generator because ``generators`` lacks
    one of ``names`` (a random attack or packet loss without its stream): two identical
    calls then differ (a trial: a tracking study seeded with ``{"plant": g}`` alone drew
    other attacks every time). Nothing is checked when every name has its generator."""
    missing = [n for n in names if generators.get(n) is None]
    before = torch.random.get_rng_state() if missing else None
    yield
    if before is not None and not torch.equal(before, torch.random.get_rng_state()):
        warnings.warn(
            f"the simulation drew from torch's global generator: generators has no "
            f"{' or '.join(repr(n) for n in missing)} stream, so the attack or schedule "
            "that draws is not reproducible; pass them (Streams(seed).simulation() gives "
            "every stream)",
            stacklevel=4,  # (the caller of the function that drew)
        )


class _Own(Enum):
    ATTACK = "the scenario's own attack"


#: ``attack=OWN_ATTACK`` (the default of :meth:`Scenario.simulate` and ``loop``): the
#: scenario's own attack; ``attack=None`` runs attack-free, an ``Attack`` runs that one.
OWN_ATTACK = _Own.ATTACK


@torch.no_grad()
def simulation_dtype(dtype: torch.dtype | None, model) -> torch.dtype:
    """A scenario's simulation dtype: ``dtype`` if given, else ``model``'s where one is
    given, else float64 (:meth:`Scenario.simulate`)."""
    if dtype is not None:
        return dtype
    return model.initial.mean.dtype if model is not None else torch.float64


def simulate(
    model,
    runs: int,
    steps: int,
    *,
    generators: Mapping[str, torch.Generator],
    attack=None,
    schedule=None,
    us: Tensor | None = None,
    random_initial: bool = False,
    input_loss=None,
) -> Trajectories:
    """Simulate ``runs`` runs of ``steps`` steps of ``model`` under ``attack`` and ``schedule``:
    the closed loop of :func:`difffilter.loop.closed_loop` without an estimator, driven by
    the known inputs.

    Args:
        model: any :class:`~difffilter.StateSpaceModel` (its noise models draw the noise).
        generators: ``{"plant", "attack", "schedule"}`` → ``torch.Generator``: ``"plant"``
            always; ``"attack"`` and ``"schedule"`` where the attack or the schedule draws
            (a random attack without its stream draws from torch's global generator, with a
            warning; a packet loss without its stream is refused).
        attack: an :class:`~difffilter.attack.Attack` (:mod:`difffilter.models.attacks`) or
            ``None``.
        schedule: :mod:`difffilter.models.schedules` object (default all sensors).
        us: commanded inputs ``[runs, steps, du]`` or ``None`` (zero inputs under an
            actuator attack or ``input_loss``).
        random_initial: draw ``x_0`` from the prior instead of taking its mean.
        input_loss: a :class:`~difffilter.input_loss.InputLossSchedule` (the controller's
            packets lost on the way to the actuators, drawn from ``generators
            ["input_schedule"]``) or ``None``; the trajectories' ``us`` are then the inputs
            the estimators know (applied as acknowledged, or sent).
    """
    runs, steps = check_integer(runs, "runs", 1), check_integer(steps, "steps", 1)
    if attack is not None and not isinstance(attack, Attack):
        raise TypeError(
            "attack must be a difffilter.attack.Attack (e.g. difffilter.models.attacks."
            f"SensorBias); got {type(attack).__name__}"
        )
    schedule = schedule if schedule is not None else AllSensors()
    dtype, device = model.initial.mean.dtype, model.initial.mean.device
    if not isinstance(generators, Mapping):  # a bare generator failed on `.get` unexplained
        raise TypeError(
            "generators must be a mapping {'plant': torch.Generator, ...} (e.g. "
            f"difffilter.models.streams.Streams(seed).simulation()); got {type(generators).__name__}"
        )
    plant = generators.get("plant")
    if plant is None:  # (never torch's global generator: every draw has its seed)
        raise ValueError("generators must hold 'plant': the plant's noise is drawn from it")
    actuated = attack is not None and Channel(attack.channel) is Channel.ACTUATOR
    if (actuated or input_loss is not None) and us is None:
        if model.dim_u == 0:
            what = "an actuator attack" if actuated else "input_loss"
            raise ValueError(f"{what} needs a model with inputs (dim_u > 0)")
        us = torch.zeros(runs, steps, model.dim_u, dtype=dtype, device=device)
    if us is not None and tuple(us.shape) != (runs, steps, model.dim_u):
        raise ValueError(
            f"us must have shape [{runs}, {steps}, {model.dim_u}]; got {tuple(us.shape)}"
        )
    if random_initial:
        x0 = model.sample_initial((runs,), plant)
    else:
        x0 = model.initial.mean.expand(runs, model.dim_x).clone()
    # (an input loss's own stream too: one left out had drawn from the global generator
    # without the warning a measurement schedule's gets, a schedules trial)
    streams = ("attack", "schedule") + (() if input_loss is None else ("input_schedule",))
    with warn_on_global_draws(generators, streams):
        mask = schedule.mask((runs,), steps, model.dim_y, generators.get("schedule"),
                             device=device)  # fmt: skip
        if input_loss is not None:
            input_loss = input_loss.draw(runs, steps, model.dim_u,
                                         generators.get("input_schedule"), device=device)  # fmt: skip
        loop = closed_loop(
            model, steps, noise=DrawnNoise(plant), x0=x0,
            controller=None if us is None else KnownInputs(us), attack=attack,
            attack_generator=generators.get("attack"), mask=mask, input_loss=input_loss,
        )  # fmt: skip
    traj = loop.trajectories
    _check_simulated(traj, model)
    return traj._replace(info={**traj.info, "x0": x0})


def _check_simulated(traj, model) -> None:
    """``ValueError`` naming the plant where its simulated states or (received)
    measurements are NaN or Inf: a user trial's transition took ``sqrt`` of a negative
    number, and every estimator then blamed the measurements it was handed."""
    bad_x = ~torch.isfinite(traj.x).all(-1)
    bad_y = ~torch.isfinite(traj.y_true)
    if traj.mask is not None:
        bad_y = bad_y & traj.mask
    bad_y = bad_y.any(-1)
    for bad, what, function in ((bad_x, "state", "transition"), (bad_y, "measurement",
                                                                 "measurement function")):  # fmt: skip
        if bool(bad.any()):
            run, t = (int(i) for i in bad.nonzero()[0])
            raise ValueError(
                f"the simulated plant's {what} is NaN or Inf at step k = {t + 1} of run {run} "
                f"(of {traj.x.shape[0]}): the model's {function} ({type(model).__name__}) gave "
                "it, from finite states; check it there (e.g. sqrt or log of a negative "
                "number, a division by zero, a plant that diverges)"
            )


@dataclass(frozen=True)
class Scenario:
    """Common fields and the simulation of every scenario.

    Attributes:
        name: stable snake_case identifier used by the CLIs and in reports.
        family: which system/paper the scenario belongs to (``"four_tank"``, ``"lfc"``).
        description: one line for ``difffilter-eval --list`` and report headers.
        paper: short citation of the paper the scenario reproduces.
        notes: provenance of non-paper values (``[DEF]`` defaults) for the report.
        runs, steps: default Monte Carlo runs and horizon.
        dt: sampling period in seconds (detection delays are reported in steps and s).
        headline: run by ``difffilter-eval all`` and by its family's name.
        estimators: names (in the evaluation's estimator registry) run by default.
        num_particles: ``N`` of the particle-filter estimators.
        false_alarm_rate: target per-step false-alarm rate of the residual detectors.
        gamma_min: smallest attack norm the PoA detector must catch (Theorem 1 of the
            modified-PF paper); ``None``: half the attack's steady-state norm [DEF].
        single_thread: run the suite with one intra-op thread (small tensors; ``False``
            for estimators with large matrices).
        checkpoint: the shipped trained estimator its learned estimators use when no
            checkpoint is given (a path relative to the repository, e.g.
            ``"checkpoints/lfc_nn_grad.ckpt"``), or ``None``.
        threat: the attack the plant meets instead of the scenario's own
            (:meth:`with_threat`; ``None``: attack-free). The estimators' assumptions
            about attacks (``gamma_min``, a deception density) still come from
            :meth:`attack_model`: a threat study changes the attacker, not the defender.
    """

    name: str
    family: str
    description: str
    paper: str = ""
    notes: tuple[str, ...] = field(default_factory=tuple)
    runs: int = 100
    steps: int = 100
    dt: float = 1.0
    headline: bool = True
    estimators: tuple[str, ...] = ()
    num_particles: int = 100
    false_alarm_rate: float = 0.005
    gamma_min: float | None = None
    single_thread: bool = True
    checkpoint: str | None = None
    threat: Any = field(default=OWN_ATTACK, compare=False, repr=False)

    #: Whether the scenario's estimators run in its own closed loop (their estimate feeds
    #: back into the plant through a controller): :meth:`exogenous` and :meth:`loop`.
    closed_loop: ClassVar[bool] = False
    #: The units of the state and of the attack, for reports and plots (a family says
    #: them; pooled metrics over components of several units name each).
    state_unit: ClassVar[str] = "state units"
    attack_unit: ClassVar[str] = "attack units"
    #: The names of the attacked signal's entries (``None``: numbered only), for plots: a
    #: reader of "channel 3 [p.u. (Δf in Hz)]" took the LFC's turbine power for a frequency.
    attack_entry_names: ClassVar[tuple[str, ...] | None] = None

    def unit_of(self, metric_unit: str) -> str:
        """``metric_unit`` of :data:`~difffilter.eval.scoring.METRICS` in this scenario's
        units (``"state units"`` → :attr:`state_unit`, …; others as they are)."""
        return {"state units": self.state_unit, "attack units": self.attack_unit}.get(
            metric_unit, metric_unit
        )

    # -- what a family defines --------------------------------------------------------
    def system(self, dtype: torch.dtype = torch.float64, device=None):
        """The plant (and the estimators' model) of this scenario."""
        raise NotImplementedError(f"scenario {self.name!r} does not define system()")

    def attack_model(self):
        """The attack (:mod:`difffilter.models.attacks`) or ``None``."""
        return None

    def _on_device(self, model, device):
        """``model``, refused where ``device`` is given and the model was not built there:
        a family whose plant is built on the CPU alone returned a CPU model for
        ``system(device="cuda")``, and the first step failed far from the cause (or a
        study ran on the CPU while its user believed it ran on the GPU)."""
        if device is None:
            return model
        want, got = torch.device(device), model_dtype_device(model)[1]
        if got is not None and (got.type, got.index) != (want.type, want.index or got.index):
            raise ValueError(
                f"scenario {self.name!r}: system(device={str(device)!r}) built its model on "
                f"{got}: this scenario's plant is built on the CPU only (device=None)"
            )
        return model

    def schedule(self):
        """The communication schedule (:mod:`difffilter.models.schedules`)."""
        return AllSensors()

    def inputs(self, runs: int, dtype: torch.dtype, device=None) -> Tensor | None:
        """Commanded inputs ``[runs, steps, du]`` or ``None`` (no input)."""
        return None

    # -- derived ----------------------------------------------------------------------
    def with_threat(self, attack) -> Scenario:
        """This scenario with the plant under ``attack`` (an
        :class:`~difffilter.attack.Attack`, ``None`` for none, or :data:`OWN_ATTACK`) while
        every estimator keeps the assumptions it draws from :meth:`attack_model`."""
        if attack is not OWN_ATTACK and attack is not None and not isinstance(attack, Attack):
            raise TypeError(
                f"attack must be a difffilter.attack.Attack, None or OWN_ATTACK; got "
                f"{type(attack).__name__}"
            )
        if isinstance(attack, Attack) and attack.reads_view and not self.closed_loop:
            raise ValueError(
                f"attack {type(attack).__name__} reads the estimator's output (reads_view = "
                f"True), and scenario {self.name!r} simulates its runs once, without an "
                "estimator, for every estimator to run on: the attack would read nothing. Run "
                "it in difffilter.loop.closed_loop with the estimator, or on a closed-loop "
                "scenario (each estimator in a loop of its own)"
            )
        return dataclasses.replace(self, threat=attack)

    def attack_free_key(self) -> tuple:
        """What the scenario's attack-free runs depend on: scenarios with the same key share
        their attack-free calibration (:mod:`difffilter.eval.calibration`). Default: the
        scenario itself (and whether its initial states are drawn: the keys of those that
        are not are as before the option); a family whose scenarios differ only in the
        attack says so."""
        key = (self.name, self.steps)
        return key + ("x0 ~ prior",) if self.draws_initial_state() else key

    def simulated_attack(self):
        """The attack the plant meets: the threat (:meth:`with_threat`) or the scenario's own."""
        return self.attack_model() if self.threat is OWN_ATTACK else self.threat

    def simulate(
        self,
        runs: int,
        generators: Mapping[str, torch.Generator],
        *,
        dtype: torch.dtype | None = None,
        attack: Any = OWN_ATTACK,
        model=None,
    ) -> Trajectories:
        """``runs`` runs of this scenario (``attack``: :data:`OWN_ATTACK`, ``None`` or another)
        in ``dtype``: by default ``model``'s where one is given (the evaluation's side studies
        of a float32 study had simulated float64 inputs for its float32 model and failed:
        a float32 trial), else float64."""
        dtype = simulation_dtype(dtype, model)
        model = model if model is not None else self.system(dtype)
        return simulate(
            model,
            runs,
            self.steps,
            generators=generators,
            attack=self.simulated_attack() if attack is OWN_ATTACK else attack,
            schedule=self.schedule(),
            # on the model's device: a model moved to a GPU had its known inputs on the CPU
            us=self.inputs(runs, dtype, model.initial.mean.device),
            random_initial=self.draws_initial_state(),
            input_loss=self.input_loss_schedule(),
        )

    def draws_initial_state(self) -> bool:
        """Whether each run's ``x_0`` is drawn from the model's prior ``N(m₀, P₀)`` (from the
        ``"plant"`` stream) instead of being ``m₀`` itself (default: ``m₀``, where the papers'
        plants start; the estimators' prior ``P₀`` is then their uncertainty only)."""
        return False

    def input_loss_schedule(self):
        """The loss of the controller's packets on their way to the actuators
        (:class:`~difffilter.input_loss.InputLossSchedule`), or ``None`` (default: none)."""
        return None

    def with_steps(self, steps: int) -> Scenario:
        """The same scenario over a horizon of ``steps`` steps (tests, quick runs)."""
        return dataclasses.replace(self, steps=steps)

    # -- a closed-loop scenario defines these ----------------------------------------------
    def exogenous(self, runs: int, generators: Mapping[str, torch.Generator], *, dtype) -> dict:
        """The draws every estimator's closed loop replays (noise, inputs, attack)."""
        raise NotImplementedError(f"scenario {self.name!r} is not a closed loop")

    def loop(self, estimator, draws: dict, *, generator=None, steps=None, state=None):
        """``estimator`` in this scenario's closed loop on ``draws`` (:meth:`exogenous`):
        a :class:`~difffilter.loop.LoopResult` (``steps``/``state``: a chunk of it)."""
        raise NotImplementedError(f"scenario {self.name!r} is not a closed loop")

    def feedback_gain(self, dtype=torch.float64) -> Tensor:
        """The controller's gain ``K`` through which an attack-estimate error enters the
        plant (``U = −K(Z − â)``) of a closed-loop scenario."""
        raise NotImplementedError(f"scenario {self.name!r} is not a closed loop")

    def shipped_checkpoint(self) -> Path | None:
        """The file of ``checkpoint`` in this repository, or ``None`` (unset or absent)."""
        if self.checkpoint is None:
            return None
        path = Path(__file__).resolve().parents[1] / self.checkpoint
        return path if path.is_file() else None

    def attack_norm_floor(self, model=None) -> float:
        """``‖γ‖_min`` for the PoA threshold (Theorem 1 of the modified-PF paper): the
        smallest attack norm the detector must catch.

        ``gamma_min`` if set; else half the steady-state norm of a sensor attack that has
        one (``γ̄`` of eq. 4, a bias's value, as injected: one value on every entry, zero
        outside ``entries``; a :class:`~difffilter.threats.KSigmaBias`'s ``k σ``) [DEF];
        else (a ramp or a random walk, which have no steady state, an actuator attack,
        whose size is in input units, or no attack) one measurement-noise standard
        deviation, ``‖√diag R‖`` of ``model`` [DEF]: an attack as large as the noise (so
        too for a bias of size 0). ``ValueError`` when that is needed and no
        ``model`` is given.
        """
        if self.gamma_min is not None:
            return float(self.gamma_min)
        attack = self.attack_model()
        # the steady state of the biases named above only: another attack's field of that
        # name is its own (a trial's attack of its own had its ``tau`` read as eq. 4's)
        values = (attack.gamma_bar if isinstance(attack, SensorBias)
                  else attack.value if isinstance(attack, Bias) else None)  # fmt: skip
        if isinstance(attack, KSigmaBias):  # a bias too: k σ on every attacked entry
            values = tuple(float(attack.k) * float(v) for v in attack.sigma)
        on_sensors = Channel(getattr(attack, "channel", Channel.SENSOR)) is not Channel.ACTUATOR
        if values is not None and on_sensors:
            values = [float(v) for v in ((values,) if isinstance(values, (int, float)) else values)]
            entries = getattr(attack, "entries", None)
            if len(values) == 1 or entries is not None:  # the vector the attack injects
                if model is None:
                    raise ValueError(
                        f"scenario {self.name!r}: pass the model (its attack's value is "
                        "broadcast over the measurement's entries) or set gamma_min"
                    )
                dy = model.dim_y
                values = values * dy if len(values) == 1 else values
                if entries is not None:
                    values = [v if i in entries else 0.0 for i, v in enumerate(values)]
            floor = 0.5 * math.sqrt(sum(v**2 for v in values))
            # a bias of size 0 (a null attack, a control run) takes the noise default below:
            # its γ_min of 0 had stopped the whole study at the PoA detector (a trial)
            if floor > 0:
                return floor
        if model is None:
            raise ValueError(
                f"scenario {self.name!r}: set gamma_min (its attack has no nonzero steady-state value "
                "on the sensors) or pass the model (one noise standard deviation is the default)"
            )
        noise_var = torch.diagonal(model.measurement_noise.cov, dim1=-2, dim2=-1)
        return float(noise_var.sum(-1).max().sqrt())  # the largest over a batch of models

    def estimator_options(self) -> dict[str, Any]:
        """Settings the estimators read (family-specific; empty by default)."""
        return {}

    def paper_numbers(self) -> dict[str, Any]:
        """The paper's reference numbers for metrics.json's ``"paper"`` (empty by default)."""
        return {}


def check_folder_name(value, field_name: str) -> None:
    """``ValueError`` unless ``value`` can name one folder of its own under a reports folder
    (``<out>/<scenario>/``, ``<out>/<family>_summary.md``): a non-empty string that is no
    path (no ``/`` or ``\\``, not ``.`` or ``..``). A YAML scenario named ``/abs/dir`` or
    ``../x`` wrote its reports outside ``--out``, and one named ``''`` over the leaderboard's
    folder (a fuzzing trial)."""
    if (not isinstance(value, str) or not value.strip() or value in (".", "..")
            or "/" in value or "\\" in value):  # fmt: skip
        raise ValueError(
            f"{field_name} must be a non-empty name without '/' or '\\' (it names the "
            f"scenario's report folder); got {value!r}"
        )


@dataclass(frozen=True)
class CustomScenario(Scenario):
    """A scenario from plain parts, for a user's own plant (no subclass needed).

    Attributes:
        model_fn: ``dtype → StateSpaceModel``, the plant and the estimators' model.
        attack: any :class:`~difffilter.attack.Attack`: the threat library's
            (:mod:`difffilter.threats`: bias, ramp, random walk, pulses, sinusoid, chirp,
            replay, covert; each with ``onset``, ``duration``, ``share`` of the runs,
            ``entries`` and ``channel`` "sensor", "actuator" or "replacement"), the
            papers' (:mod:`difffilter.models.attacks`), one of your own, or ``None``.
        protocol: a schedule of :mod:`difffilter.models.schedules` (default all sensors).
        input_loss: a :class:`~difffilter.input_loss.InputLossSchedule` (the known inputs'
            packets lost on the way to the actuators: held or zeroed there; the estimators
            told of each arrival or not) or ``None``.
        known_inputs: the commanded inputs ``u_0 … u_{T−1}`` the plant is driven with and
            every estimator knows: a tensor ``[T, du]`` (every run) or ``[R, T, du]`` (run
            ``i`` its row ``i mod R``: :meth:`inputs`), or
            a function of the step index ``k`` (a tensor ``[T]`` of ``0 … T−1`` in the
            model's dtype) returning ``[T, du]`` (or ``[T]`` for one input); ``None``: no
            inputs (zeros under an actuator attack).
        options: settings the estimators read (``cusum_bias``, ``poa_eta`` with ``poa_zeta``,
            …: :data:`difffilter.models.estimators.OPTIONS`; a study refuses other keys).
        state_unit, attack_unit: the units reports and plots name (e.g. ``"cm"``).
        random_initial: ``True`` draws each run's initial state ``x_0 ~ N(m₀, P₀)``, the
            estimators' prior, from the plant's stream; ``False`` (default) starts every run
            at ``m₀`` (:meth:`Scenario.draws_initial_state`; a trial's own numpy re-simulation
            drew ``x_0`` and its attack-free error came out 5 % off the study's).

    Register it (:func:`difffilter.models.registry.register`) to run it from the CLI, or
    pass it to :func:`difffilter.eval.suite.run_suite` directly; a
    ``package.module:object`` path or a YAML file (:mod:`difffilter.models.yaml_scenario`)
    names it on the command line.
    """

    model_fn: Any = field(default=None, compare=False)
    attack: Any = None
    protocol: Any = None
    known_inputs: Any = field(default=None, compare=False)
    options: Mapping[str, Any] = field(default_factory=dict, compare=False)
    input_loss: Any = None
    state_unit: str = "state units"
    attack_unit: str = "attack units"
    random_initial: bool = False

    def __post_init__(self):
        check_folder_name(self.name, "name")
        check_folder_name(self.family, "family")
        if not isinstance(self.random_initial, bool):
            raise TypeError(f"random_initial must be True or False; got {self.random_initial!r}")
        if not isinstance(self.options, Mapping):  # (a list failed in dict(), naming no field)
            raise ValueError(
                f"scenario {self.name!r}: options must be a mapping of option: value (e.g. "
                f"{{cusum_bias: 2.0}}); got {type(self.options).__name__}"
            )
        if not callable(self.model_fn) or isinstance(self.model_fn, torch.nn.Module):
            # (a model itself is callable, as every nn.Module, and took the dtype as its
            # input: "missing the required forward function", from deep in torch)
            given = (f"a {type(self.model_fn).__name__} model itself: pass the function that "
                     "builds it, e.g. model_fn=my_plant, not my_plant(torch.float64)"
                     if isinstance(self.model_fn, torch.nn.Module)
                     else type(self.model_fn).__name__)  # fmt: skip
            raise ValueError(
                f"model_fn must be a callable dtype -> StateSpaceModel (the suite builds float64 "
                f"and float32 models); got {given}"
            )
        try:  # (a function of no argument failed later as "<lambda>() takes 0 positional …")
            inspect.signature(self.model_fn).bind(torch.float64)
        except TypeError:
            raise TypeError(
                f"scenario {self.name!r}: model_fn must take the dtype, model_fn(dtype) -> "
                f"StateSpaceModel (the suite builds float64 and float32 models); got a "
                f"function of signature {inspect.signature(self.model_fn)}"
            ) from None
        except ValueError:  # no signature to read (a builtin): the call will tell
            pass
        if self.attack is not None and not isinstance(self.attack, Attack):
            raise TypeError(
                "attack must be a difffilter.attack.Attack (e.g. difffilter.threats.Ramp) or "
                f"None; got {type(self.attack).__name__}"
            )
        protocol = self.protocol
        if protocol is not None and (
            isinstance(protocol, type) or not callable(getattr(protocol, "mask", None))
        ):  # (a string or a class failed at the first simulate, on a missing attribute)
            raise TypeError(
                "protocol must be a schedule object with a mask(...) method (e.g. "
                "difffilter.models.schedules.RoundRobin(((0,), (1,))) or PacketLoss(0.2)) or "
                f"None; got {protocol!r}"
            )
        for name in ("runs", "steps"):
            check_positive_int(getattr(self, name), name)
        check_finite_number(self.dt, "dt (the sampling period, s)", positive=True)  # (-0 s delays)
        if self.input_loss is not None and not isinstance(self.input_loss, InputLossSchedule):
            raise TypeError(
                "input_loss must be a difffilter.input_loss.InputLossSchedule(schedule, on_loss, "
                f"acknowledged) or None; got {type(self.input_loss).__name__}"
            )
        if self.input_loss is not None and getattr(self.attack, "conceals", False):
            raise ValueError(
                f"attack {type(self.attack).__name__} conceals its effect by simulating it as if "
                "its input packets arrived, and input_loss loses some: a covert attack runs "
                "without input_loss"
            )
        actuated = Channel(getattr(self.attack, "channel", Channel.SENSOR)) is Channel.ACTUATOR
        if self.input_loss is not None and self.known_inputs is None and not actuated:
            # (as the YAML form refuses it: the report announced a loss that changed nothing)
            raise ValueError(
                f"scenario {self.name!r}: input_loss needs inputs to lose: without known_inputs "
                "the plant runs on zero inputs, which a lost packet leaves as they are, and no "
                "actuator attack rides in them; give known_inputs (for a threat study of "
                "actuator attacks, torch.zeros(steps, du)), or drop input_loss"
            )
        known = self.known_inputs
        if known is not None and not callable(known) and not isinstance(known, Tensor):
            raise TypeError(
                "known_inputs must be a tensor [T, du] or [runs, T, du], a function of the "
                f"step index k, or None; got {type(known).__name__}"
            )

    def system(self, dtype: torch.dtype = torch.float64, device=None):
        """``model_fn(dtype)``, checked: a state-space model of that dtype (one of another
        failed ten calls deep in a matrix product, ``None`` as a missing attribute)."""
        model = self.model_fn(dtype)
        if not isinstance(model, StateSpaceModel):
            raise TypeError(
                f"scenario {self.name!r}: model_fn must return a difffilter StateSpaceModel "
                f"(e.g. LinearGaussianModel); it returned {type(model).__name__}"
            )
        got = model_dtype_device(model)[0]
        if got is not None and got != dtype:
            raise ValueError(
                f"scenario {self.name!r}: model_fn({dtype}) returned a model of {got}: build it "
                "in the dtype it is given (e.g. torch.tensor(..., dtype=dtype))"
            )
        return self._on_device(model, device)

    def draws_initial_state(self) -> bool:
        return self.random_initial

    def attack_model(self):
        return self.attack

    def schedule(self):
        return self.protocol if self.protocol is not None else AllSensors()

    def input_loss_schedule(self):
        return self.input_loss

    def inputs(self, runs: int, dtype: torch.dtype, device=None) -> Tensor | None:
        """``known_inputs`` as ``[runs, steps, du]`` (their first ``steps`` rows when they
        hold more: a shorter horizon of the scenario; a clear error when they do not fit).

        A table of ``R`` runs ``[R, steps, du]`` serves any number of runs: run ``i`` takes
        its row ``i mod R`` (a study of fewer runs its first rows; the attack-free runs that
        calibrate a detector, at least 50, cycle through it)."""
        known = self.known_inputs
        if known is None:
            return None
        if callable(known):
            k = torch.arange(self.steps, dtype=dtype, device=device)
            known = torch.as_tensor(known(k), dtype=dtype, device=device)
            known = known.unsqueeze(-1) if known.dim() == 1 else known
        known = known.to(dtype=dtype, device=device)
        du = getattr(self.system(dtype), "dim_u", None)
        wanted = (runs, self.steps, du)
        if known.dim() == 2:
            known = known.unsqueeze(0)
        if known.dim() == 3 and known.shape[1] > self.steps:  # a shorter horizon (with_steps)
            known = known[:, : self.steps]
        if known.dim() != 3 or known.shape[1] != self.steps or known.shape[2] != du:
            raise ValueError(
                f"known_inputs of scenario {self.name!r} must give [steps, du] = "
                f"[{self.steps}, {du}] or [runs, steps, du] = [R, {self.steps}, {du}]; got "
                f"{list(known.shape)}"
            )
        if known.shape[0] not in (1, runs):  # a table of other runs: row i mod R
            known = known[torch.arange(runs, device=known.device) % known.shape[0]]
        return known.expand(wanted).clone()

    def estimator_options(self) -> dict[str, Any]:
        return dict(self.options)


def plant_entries(value, name: str, count: int, dtype, *, positive: bool = False) -> Tensor:
    """A plant constructor's vector argument ``value`` as ``count`` finite numbers (``> 0``
    where ``positive``: variances), a tensor of ``dtype``, named in its errors (``Gaussian``
    had named a wrong-length prior "loc", torch a ragged one in its own words: the robot
    and tracking trials)."""
    try:
        t = torch.as_tensor(value, dtype=dtype)
    except (TypeError, ValueError, RuntimeError):
        t = None
    if t is None or t.shape != (count,):
        got = tuple(t.shape) if t is not None else repr(value)
        raise ValueError(f"{name} must be {count} numbers; got {got}")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains NaN or Inf values; every entry must be finite")
    if positive and not bool((t > 0).all()):
        raise ValueError(f"{name} must be {count} numbers > 0 (variances); got {value!r}")
    return t
