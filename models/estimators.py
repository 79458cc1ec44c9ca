"""The estimator registry: name → factory → a run on trajectories → an EstimatorOutput.

An estimator is registered once, by a stable snake_case name::

    @register("chi_square_ekf", "EKF gated by a chi-square test on its innovations")
    def _(ctx: SuiteContext):
        detector = fdi.ChiSquareDetector(ctx.model.dim_y, ctx.scenario.false_alarm_rate)
        return lambda traj: fdi.gated_extended_kalman_filter(
            ctx.model, traj.y_recv, traj.us, mask=traj.mask, detector=detector)

The factory gets a :class:`SuiteContext` (scenario, model, runs, named random streams,
attack-free calibration runs) and returns a function of
:class:`~difffilter.models.scenario.Trajectories`. Everything stochastic draws from
``ctx.streams``, so every estimator sees the same random numbers. The registry lives in
``difffilter.models`` beside the scenario registry: a family registers its estimators in
``models/<family>_estimators.py`` (the generic ones, which run on any scenario whose model
fits them, are in :mod:`difffilter.models.generic_estimators`); evaluation
(``difffilter.eval``) and training (``difffilter.train``) read it, and nothing here imports
them.
"""

from __future__ import annotations

import difflib
import math
import numbers
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import torch

from difffilter import fdi
from difffilter.attack import Channel
from difffilter.estimator import EstimatorOutput
from difffilter.particle import particle_init
from difffilter.resampling import Systematic

from . import calibration_cache
from .attacks import SensorBias
from .needs import Need, first_unmet, scenario_of
from .streams import Streams

__all__ = [
    "EstimatorSpec",
    "SuiteContext",
    "SkipEstimator",
    "register",
    "family_register",
    "register_option",
    "check_options",
    "OPTIONS",
    "get",
    "names",
    "ESTIMATORS",
    "poa_detector_for_scenario",
    "split_checkpoints",
]

Run = Callable[[Any], EstimatorOutput]


@dataclass(frozen=True)
class EstimatorSpec:
    """A registered estimator.

    Attributes:
        name: stable snake_case name (``metrics.json`` key).
        factory: ``SuiteContext → (Trajectories → EstimatorOutput)``.
        description: one line for reports.
        clean_input: the estimator reads the attack-free ``y_true`` (a reference); its
            alarms are all false alarms.
        reference: the scenario's attack-free reference (``state_rmse_vs_attack_free``).
        needs: what it needs of a scenario (:mod:`difffilter.models.needs`); the suite
            skips it, with the reason, where one is not met.
        estimates: the channel its attack estimate is on (its outputs are marked so and
            scored only against an attack on the same side), or ``None``: what its
            outputs say (``EstimatorOutput.attack_channel``, the sensors by default).
        oracle: it reads the true attack (an oracle γ̂, as the papers' tables do): a bound,
            never a competitor.
        learned: it runs a neural network, trained offline (a checkpoint) or online.
        more_data: it reads data the scenario's receiver does not get (tracking's
            ``pf_da``: every sensor at every step, where the Round-Robin protocol delivers
            one): what more data would buy, not a competitor on the scenario's data.
        reads_measurements: ``False`` for an open-loop prediction that reads no measurement
            (the four-tank paper's account of method [31]): still a competitor, but under
            any sensor attack its error is its attack-free error, so the robustness report
            names it where it sets a threat's bar and gives the best estimator that reads
            the sensors beside it (:func:`difffilter.eval.acceptance.judge_robustness`).
    """

    name: str
    factory: Callable[[SuiteContext], Run]
    description: str
    clean_input: bool = False
    reference: bool = False
    needs: tuple[Need, ...] = ()
    estimates: Channel | None = None
    oracle: bool = False
    learned: bool = False
    more_data: bool = False
    reads_measurements: bool = True

    @property
    def role(self) -> str:
        """``"reference"`` (attack-free input), ``"oracle"``, ``"more_data"``, ``"learned"``
        or ``"analytic"``: what it may be compared with. "The best analytic" of a study is
        the best of the estimators whose role is ``"analytic"``
        (:func:`difffilter.eval.acceptance.best_analytic`)."""
        if self.reference or self.clean_input:
            return "reference"
        if self.oracle:
            return "oracle"
        if self.more_data:
            return "more_data"
        return "learned" if self.learned else "analytic"

    def build(self, ctx: SuiteContext) -> Run:
        """The run of this estimator in the study ``ctx``: ``factory(ctx)``, checked to be a
        function (a factory that returned its output, or nothing, failed later in scoring)."""
        run = self.factory(ctx)
        if not callable(run):
            raise TypeError(
                f"estimator {self.name!r} ({_origin(self)}): its factory returned "
                f"{type(run).__name__}; it returns a function of the Trajectories (e.g. "
                "lambda traj: ...) that returns an EstimatorOutput"
            )
        return run

    def checked(self, out):
        """``out``, what this estimator's run returned, if it is an
        :class:`~difffilter.estimator.EstimatorOutput` (or a closed loop's
        :class:`~difffilter.loop.LoopResult`); ``TypeError`` naming the estimator else."""
        from difffilter.loop import LoopResult
        from difffilter.results import FilterResult

        if isinstance(out, (EstimatorOutput, LoopResult)):
            return out
        hint = (" (a filter's FilterResult becomes one by difffilter.estimator.output_of(result))"
                if isinstance(out, FilterResult) else "")  # fmt: skip
        raise TypeError(
            f"estimator {self.name!r} ({_origin(self)}): its run returned {type(out).__name__}; "
            f"it returns a difffilter.EstimatorOutput{hint}"
        )

    def unmet(self, scenario, model) -> str | None:
        """Why this estimator does not fit ``scenario`` (its first unmet need), or ``None``."""
        return first_unmet(self.needs, scenario, model)


ESTIMATORS: dict[str, EstimatorSpec] = {}


#: What a scenario's ``estimator_options()`` may set, ``{key: what it sets}``: a study refuses
#: any other key (a misspelt one was silently ignored). A family whose estimators read a
#: setting of their own declares it with :func:`register_option`.
OPTIONS: dict[str, str] = {
    "poa_eta": "the PoA detector's threshold eta (a paper's value; with poa_zeta), instead of "
    "Theorem 1's",
    "poa_zeta": "the PoA detector's zeta (with poa_eta)",
    "cusum_bias": "the CUSUM detector's bias b (default: dy + 2, the attack-free NIS mean plus "
    "a margin; its τ is chosen on the attack-free runs)",
    "gamma_hat_noise_var": "variance of the noise on the oracle attack estimate of "
    "modified_pf_noisy_gamma",
}
#: Options that are given together or not at all.
_TOGETHER = (("poa_eta", "poa_zeta"),)


def _real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


#: What the built-in options' values must be, ``{key: (test, expected)}``: checked when a
#: scenario is read (a YAML file's ``cusum_bias: big`` failed mid-study with a traceback,
#: and ``-1`` with the detector's words, naming neither the file nor the option).
_VALUES = {
    # one number: η bounds the norm of a residual (a list "one per measurement entry" had
    # been applied one per run: run i judged at entry i's η, or refused for another count)
    "poa_eta": (lambda v: _real(v) and v >= 0, "a finite number >= 0"),
    "poa_zeta": (lambda v: _real(v) and 0 <= v < 1, "a number in [0, 1)"),
    "cusum_bias": (lambda v: _real(v) and v > 0, "a finite number > 0"),
    "gamma_hat_noise_var": (lambda v: _real(v) and v >= 0, "a finite number >= 0"),
}  # fmt: skip


def register_option(key: str, description: str) -> str:
    """Declare ``key`` a setting that a family's estimators read from ``ctx.options`` (the
    scenario's ``estimator_options()``); ``description``: one line for the error that lists
    the known keys. Declaring a key again with the same description is harmless."""
    if OPTIONS.get(key, description) != description:
        raise ValueError(f"estimator option {key!r} is already declared: {OPTIONS[key]}")
    OPTIONS[key] = description
    return key


def check_options(options: Mapping[str, Any], where: str) -> dict[str, Any]:
    """``options`` as a dict, if every key is declared (:data:`OPTIONS`) and the keys that go
    together come together; ``ValueError`` naming ``where`` (the scenario) and the key else."""
    _load_families()
    options = dict(options)
    for key in options:
        if key not in OPTIONS:
            close = difflib.get_close_matches(str(key), OPTIONS, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            known = "; ".join(f"{k}: {d}" for k, d in sorted(OPTIONS.items()))
            raise ValueError(
                f"{where}: unknown estimator option {key!r}{hint}; the estimators read "
                f"{known} (a family of one's own declares its settings with "
                "difffilter.models.estimators.register_option)"
            )
    for key, value in options.items():
        test, expected = _VALUES.get(key, (None, ""))
        if test is not None and not test(value):
            raise ValueError(f"{where}: estimator option {key} must be {expected}; got {value!r}")
    for keys in _TOGETHER:
        given = [k for k in keys if k in options]
        if given and len(given) < len(keys):
            missing = [k for k in keys if k not in options]
            raise ValueError(
                f"{where}: estimator option {' and '.join(given)} without "
                f"{' and '.join(missing)}: they are given together"
            )
    return options


class SkipEstimator(Exception):
    """Raised by a factory that cannot run in this study (e.g. no checkpoint was given);
    the suite records the message in ``SuiteResult.skipped`` and the report lists it."""


def register(
    name: str,
    description: str,
    *,
    clean_input: bool = False,
    reference: bool = False,
    needs: tuple[Need, ...] = (),
    estimates: Channel | str | None = None,
    oracle: bool = False,
    learned: bool = False,
    more_data: bool = False,
    reads_measurements: bool = True,
):
    """Decorator registering ``factory`` under ``name`` (twice is an error); ``needs``,
    ``estimates``, ``oracle``, ``learned``, ``more_data`` and ``reads_measurements`` as in
    :class:`EstimatorSpec`."""
    estimates = None if estimates is None else Channel(estimates)
    needs = _needs_tuple(name, needs)

    def wrap(factory):
        if name in ESTIMATORS and ESTIMATORS[name].factory is not factory:
            earlier = ESTIMATORS[name]
            if _of_library(factory) and not _of_library(earlier):
                # the built-ins register when first needed: a module of one's own imported
                # before them took the name first, and the error blamed the library's module
                # (an estimator-registration trial)
                raise ValueError(
                    f"estimator {name!r} of {_origin(earlier)} takes the name of a built-in "
                    f"estimator (of {_origin(factory)}): give yours another name"
                )
            raise ValueError(
                f"estimator {name!r} is already registered, by {_origin(earlier)}; "
                f"{_origin(factory)} registers another under that name: give it another name"
            )
        ESTIMATORS[name] = EstimatorSpec(name, factory, description, clean_input, reference,
                                         needs, estimates, oracle, learned, more_data,
                                         reads_measurements)  # fmt: skip
        return factory

    return wrap


def _needs_tuple(name: str, needs) -> tuple[Need, ...]:
    """``needs`` as a tuple of :class:`Need`: one ``Need`` alone is one need (``needs=(X)``
    without the comma had failed as "'Need' object is not iterable", naming neither the
    estimator nor ``needs``: an adding-a-scenario trial)."""
    if isinstance(needs, Need):
        return (needs,)
    try:
        needs = tuple(needs)
    except TypeError:
        needs = None
    if needs is None or not all(isinstance(n, Need) for n in needs):
        raise TypeError(
            f"estimator {name!r}: needs must be a Need of difffilter.models.needs or a tuple "
            f"of them (needs=(LINEAR_MODEL,)); got {needs!r}"
        )
    return needs


def _of_library(factory) -> bool:
    """Whether a factory (or a spec's) is one of the library's own estimators."""
    module = getattr(getattr(factory, "factory", factory), "__module__", "") or ""
    return module.split(".")[0] == "difffilter"


def _origin(factory) -> str:
    """The module a factory (or a spec's) was written in."""
    factory = getattr(factory, "factory", factory)
    return f"module {getattr(factory, '__module__', '?')}"


def family_register(scenario_class: type, family: str, **defaults):
    """:func:`register` for the estimators of one family: each needs a ``scenario_class``
    (:func:`~difffilter.models.needs.scenario_of`) besides its own ``needs``, and takes
    ``defaults`` (e.g. ``estimates="actuator"``)."""
    family_need = scenario_of(scenario_class, family)

    def register_in_family(name: str, description: str, *, needs=(), **kwargs):
        needs = (family_need, *_needs_tuple(name, needs))
        return register(name, description, needs=needs, **{**defaults, **kwargs})

    return register_in_family


def get(name: str) -> EstimatorSpec:
    """The estimator called ``name``; ``ValueError`` listing the known names otherwise."""
    _load_families()
    try:
        return ESTIMATORS[name]
    except KeyError:
        known = ", ".join(sorted(ESTIMATORS))
        close = difflib.get_close_matches(str(name), ESTIMATORS, n=1)
        hint = (f" (did you mean {close[0]!r}?)" if close else
                " (an estimator of your own is known once the module that registers it is "
                "imported: --import MODULE on the command line)")  # fmt: skip
        raise ValueError(f"unknown estimator {name!r}{hint}; known estimators: {known}") from None


def names() -> list[str]:
    _load_families()
    return sorted(ESTIMATORS)


def _load_families() -> None:
    # every module of difffilter.models is imported once: family modules register their
    # estimators beside their scenarios
    from .registry import all_scenarios

    all_scenarios()


def loaded_checkpoint(ctx, path, dtype=torch.float64):
    """``(network, card)`` of the checkpoint at ``path`` in ``dtype``, loaded once per
    evaluation (``ctx.cache``: a :class:`SuiteContext`'s, or any object with a ``cache``
    dict), with the sha256 of the file as it was when that network was loaded and the
    scenario its card says it was trained on, which the study's report records
    (:attr:`SuiteContext.loaded_checkpoints`): read at the report's end, a file replaced
    during a study of several scenarios (an export's ``--force``) had been recorded while its
    scenarios ran the network loaded before (a provenance trial; a review: its training
    scenario too)."""
    from difffilter.models.neural_estimator import checkpoint_sha256, load_estimator_checkpoint

    key = ("checkpoint", str(path), dtype)
    record = ("checkpoint/provenance",) + key[1:]
    if key not in ctx.cache:
        digest = checkpoint_sha256(path)  # (before the load: a file changed after it no
        # longer matches its card, which the load checks)
        _, card = ctx.cache[key] = load_estimator_checkpoint(path, dtype=dtype)
        trained = None if card.scenario is None else str(card.scenario)
        ctx.cache[record] = {"sha256": digest,
                             **({"training_scenario": trained} if trained else {})}  # fmt: skip
    loaded = getattr(ctx, "loaded_checkpoints", None)
    if loaded is not None and record in ctx.cache:  # (per study: this dtype's network ran)
        loaded[str(path)] = ctx.cache[record]
    return ctx.cache[key]


@dataclass
class SuiteContext:
    """What an estimator factory may use.

    Attributes:
        scenario: the :class:`~difffilter.models.scenario.Scenario`.
        model: the estimators' model (``scenario.system(dtype)``).
        runs: number of Monte Carlo runs.
        streams: the study's :class:`~difffilter.models.streams.Streams`.
        options: the scenario's ``estimator_options()`` (family settings).
        checkpoint: path of a trained estimator checkpoint (``difffilter-eval --ckpt``,
            else the scenario's shipped one) or ``None``; factories that need one read
            :meth:`checkpoint_for`, raise :class:`SkipEstimator` without, and add their
            name to ``checkpoint_users``.
        cache: shared by the scenarios of one evaluation (e.g. attack-free runs that
            several scenarios have in common).
        named_checkpoints: ``{estimator: path}``, checkpoints of one estimator each
            (``difffilter-eval --ckpt name=path``), ahead of ``checkpoint``.
        particle_prefix: put before the particle filters' stream names
            (:meth:`particle_kwargs`): ``""`` for the study's common random numbers; an
            attacker crafting against a particle filter runs it on draws of its own
            (:func:`difffilter.eval.stealthy.craft_threat`), not the defender's.
        detector_streams: the streams of the detectors' own attack-free runs
            (:attr:`calibration`: a CUSUM's τ), ``None``: :attr:`streams`. The false-alarm
            calibration's suite runs on a seed of its own with the study's detectors (their
            τ from the study's seed): the threshold it picks is for the detector judged (a
            threat-model trial: a CUSUM calibrated on the calibration seed's runs had another
            τ, and the threshold picked on its scores moved the study's false-alarm rate
            by −0.13 to +0.23 points).
        loaded_checkpoints: ``{path: {"sha256", "training_scenario"}}`` of the checkpoints
            this study's estimators loaded (:func:`loaded_checkpoint`), as the files were
            when loaded.
        detector_runs: the study's runs, whose count sets the detectors' own attack-free
            runs (``max(runs, 50)``), ``None``: :attr:`runs` (a calibration on more runs
            than the study had built a CUSUM of another τ: a review).
    """

    scenario: Any
    model: Any
    runs: int
    streams: Streams
    options: dict[str, Any] = field(default_factory=dict)
    checkpoint: Any = None
    cache: dict[Any, Any] = field(default_factory=dict)
    checkpoint_users: list[str] = field(default_factory=list)
    named_checkpoints: dict[str, Any] = field(default_factory=dict)
    particle_prefix: str = ""
    detector_streams: Streams | None = None
    detector_runs: int | None = None
    loaded_checkpoints: dict[str, dict] = field(default_factory=dict)

    def checkpoint_for(self, name: str):
        """The checkpoint estimator ``name`` uses: its own (``--ckpt name=path``), else
        :attr:`checkpoint`."""
        return self.named_checkpoints.get(name, self.checkpoint)

    def particle_kwargs(self, runs: int | None = None) -> dict[str, Any]:
        """Common random numbers for particle filters: identically seeded initial particles,
        propagation noise and resampling uniforms, systematic resampling at every step."""
        n = self.scenario.num_particles
        b = self.runs if runs is None else runs
        name = f"{self.particle_prefix}particles/"
        return {
            "num_particles": n,
            "initial_state": particle_init(self.model, n, (b,), self.streams(name + "init")),
            "generator": self.streams(name + "propagate"),
            "resample_generator": self.streams(name + "resample"),
            "resampler": Systematic(),
            "ess_threshold": 1.0,
        }

    @cached_property
    def calibration(self):
        """Attack-free runs of the plant from their own streams (at least 50 runs)."""
        own = self.detector_streams or self.streams
        streams = {k: own(f"calibration/{k}")
                   for k in ("plant", "schedule", "input_schedule")}  # fmt: skip
        runs = max(self.detector_runs or self.runs, 50)
        return self.scenario.simulate(
            runs, streams, dtype=self.dtype, attack=None, model=self.model
        )

    @property
    def dtype(self) -> torch.dtype:
        return self.model.initial.mean.dtype

    def option(self, key: str, default: Any) -> Any:
        return self.options.get(key, default)

    def poa_detector(self) -> fdi.PoADetector:
        """PoA thresholds of the scenario (:func:`poa_detector_for_scenario`);
        :class:`SkipEstimator` where eq. (53) has none (an attack on almost every step)."""
        try:
            return poa_detector_for_scenario(self.scenario, self.model, self.options)
        except fdi.InfeasibleThreshold as exc:
            raise SkipEstimator(f"no PoA threshold for this scenario: {exc}") from None

    def cusum(self, filter) -> fdi.CusumDetector:
        """CUSUM calibrated on the attack-free calibration runs with the Gaussian ``filter``.

        Calibrated once for the same attack-free scenario, seed, runs, dtype, filter, rate,
        bias and model parameters: kept for the process (:data:`_CUSUM_CACHE`) and on disk
        under the cache folder (:mod:`difffilter.models.calibration_cache`), so a second
        ``run_suite`` of the scenario, in this process or a later one, reuses it."""
        bias, far = self.options.get("cusum_bias"), self.scenario.false_alarm_rate
        runs = max(self.detector_runs or self.runs, 50)
        key = (self.scenario.attack_free_key(), type(self.scenario).__name__,
               (self.detector_streams or self.streams).seed, runs, str(self.dtype),
               _filter_key(filter), far, bias)  # fmt: skip
        # what the calibration runs depend on beyond the key: the plant, its schedule and
        # its known inputs (a user who edits them gets a new calibration, in this process
        # as on disk: the process's cache is keyed on their fingerprint too)
        parts = (self.model, self.scenario.schedule(), self.scenario.inputs(runs, self.dtype))
        loss = self.scenario.input_loss_schedule()
        # (no loss: the keys cached before it; with one, a mark of the arrivals drawn from
        # calibration/input_schedule, not the global generator as before 2026-12-01)
        parts += () if loss is None else (loss, "calibration/input_schedule")
        process_key = (key, calibration_cache.model_fingerprint(parts))
        if process_key not in _CUSUM_CACHE:
            if len(_CUSUM_CACHE) >= 64:  # a long session of many scenarios: drop the oldest
                _CUSUM_CACHE.pop(next(iter(_CUSUM_CACHE)))
            cached = calibration_cache.cached(
                "cusum", key, parts, lambda: self._calibrate_cusum(filter, bias, far),
                valid=_is_cusum_calibration,
            )  # fmt: skip
            _CUSUM_CACHE[process_key] = fdi.CusumDetector(cached["bias"], cached["threshold"])
        return _CUSUM_CACHE[process_key]

    def _calibrate_cusum(self, filter, bias, far) -> dict[str, float]:
        cal = self.calibration
        det = fdi.cusum_detector_for(
            self.model, false_alarm_rate=far, filter=filter, bias=bias, ys=cal.y_true,
            us=cal.us, mask=cal.mask,
        )  # fmt: skip
        return {"bias": float(det.bias), "threshold": float(det.threshold)}


def _is_cusum_calibration(value) -> bool:
    """A CUSUM calibration read from disk: finite ``bias > 0`` and ``threshold >= 0`` (what
    :class:`~difffilter.fdi.CusumDetector` takes: a file edited to a bias of 0 had passed
    here and failed the evaluation in the detector's words, naming no cache file)."""
    return isinstance(value, dict) and all(
        isinstance(value.get(k), (int, float)) and not isinstance(value.get(k), bool)
        and math.isfinite(value[k]) for k in ("bias", "threshold")
    ) and value["bias"] > 0 and value["threshold"] >= 0  # fmt: skip


def _filter_key(filter) -> str:
    """The filter in a calibration's key: its ``repr`` where the class writes one with its
    settings (two ExpectedInputKalmanFilter settings had shared one CUSUM τ, 5.71 where the
    second's own is 12.5: a review), else its class's name and the fingerprint of its
    settings (:func:`~difffilter.models.calibration_cache.model_fingerprint`: a UKF of other
    sigma points had been served the default UKF's τ, in memory and on disk: a cache
    trial)."""
    if type(filter).__repr__ is not object.__repr__:
        return repr(filter)
    return f"{type(filter).__name__}:{calibration_cache.model_fingerprint(filter)}"


#: CUSUM detectors calibrated in this process (:meth:`SuiteContext.cusum`).
_CUSUM_CACHE: dict[tuple, fdi.CusumDetector] = {}


def poa_detector_for_scenario(scenario, model, options=None) -> fdi.PoADetector:
    """The PoA detector of ``scenario`` on ``model``: ``η, ζ`` from the scenario's options
    (``poa_eta``, ``poa_zeta``: a paper's values) or else from the model by Theorem 1
    (eq. 53) with ``‖γ‖_min = scenario.attack_norm_floor(model)``, ``p_l`` of its attack (0.5
    when it has none) and its particle count. Evaluation and training share it."""
    if options is None:
        options = check_options(scenario.estimator_options(), f"scenario {scenario.name!r}")
    if "poa_eta" in options:
        return fdi.PoADetector(options["poa_eta"], options["poa_zeta"])
    return fdi.poa_detector_for(
        model,
        gamma_min=scenario.attack_norm_floor(model),
        p_l=_attack_rate(scenario.attack_model()),
        num_particles=scenario.num_particles,
    )


def _attack_rate(attack) -> float:
    """``p_l`` of eq. (3) where the attack is the paper's (:class:`SensorBias`), else 0.5
    [DEF]: another attack's field of that name is its own."""
    return float(attack.p_l) if isinstance(attack, SensorBias) else 0.5


def split_checkpoints(checkpoint) -> tuple[Any, dict[str, Any]]:
    """``(default, {estimator: path})`` of a ``checkpoint`` argument: a path (every
    estimator that uses one), ``None``, or a mapping ``{estimator: path}`` whose ``"*"``
    entry, if any, is the default."""
    if isinstance(checkpoint, Mapping):
        named = {k: v for k, v in checkpoint.items() if k != "*"}
        return checkpoint.get("*"), named
    return checkpoint, {}
