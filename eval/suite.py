"""One Monte Carlo suite for every scenario: simulate once, run every estimator, score.

:func:`run_suite` simulates ``runs`` runs of a scenario from the named streams of one
master seed, runs each estimator on the same trajectories with the same random numbers
(one batched tensor program per estimator, no gradients), times it and scores it with
:mod:`difffilter.eval.scoring`. The result feeds the report writer.
"""

from __future__ import annotations

import contextlib
import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import torch

from difffilter._checks import add_note, check_integer
from difffilter.estimator import EstimatorOutput
from difffilter.linalg import NumericalBreakdown
from difffilter.loop import LoopResult, Trajectories
from difffilter.models import estimators as registry
from difffilter.models.generic_estimators import DEFAULT_SUITE, meets_adaptive_attack
from difffilter.models.streams import Streams
from difffilter.runtime import one_thread

from .calibration import calibrated_metrics
from .scoring import score

__all__ = ["SuiteResult", "run_suite", "process_group", "single_run_time_per_step", "broken_down"]


@dataclass
class SuiteResult:
    """What one suite run produced.

    Attributes:
        scenario: the scenario object; runs, seed: the study's size and master seed.
        traj: the simulated :class:`~difffilter.loop.Trajectories` (the data of the
            open-loop estimators).
        outputs: ``{estimator: EstimatorOutput}`` in run order.
        trajectories: ``{estimator: Trajectories}`` of the estimators that ran their own
            closed loop (their estimate changed the plant): the truth they are scored
            against (:meth:`traj_of`).
        wall_s: ``{estimator: wall time of its batched run}``.
        metrics: ``{estimator: {metric: value}}`` (:data:`~difffilter.eval.scoring.METRICS`).
        reference: name of the attack-free reference estimator, or ``None``.
        context: the :class:`~difffilter.models.estimators.SuiteContext` the factories saw.
        skipped: ``{estimator: why}`` for those left out: a need the scenario does not
            meet (:mod:`difffilter.models.needs`), or a factory that raised
            ``SkipEstimator`` (no checkpoint, a checkpoint of another family).
        checkpoint: ``{"path", "sha256", "source", "used_by"}`` of the checkpoint the
            study was given (or the scenario's shipped one), or ``None``.
        checkpoints: ``{estimator: {"path", "sha256"}}`` of the checkpoints given to one
            estimator each (``--ckpt name=path``).
        calibration: the :class:`~difffilter.eval.calibration.Calibration` the
            detectors were judged at, or ``None``.
        progress: whether the study shows progress bars (its family's extra studies too).
    """

    scenario: Any
    runs: int
    seed: int
    traj: Any
    outputs: dict[str, EstimatorOutput] = field(default_factory=dict)
    trajectories: dict[str, Trajectories] = field(default_factory=dict)
    wall_s: dict[str, float] = field(default_factory=dict)
    metrics: dict[str, dict[str, Any]] = field(default_factory=dict)
    reference: str | None = None
    context: Any = None
    skipped: dict[str, str] = field(default_factory=dict)
    checkpoint: dict[str, Any] | None = None
    calibration: Any = None
    progress: bool = False
    checkpoints: dict[str, dict[str, Any]] = field(default_factory=dict)

    def traj_of(self, name: str) -> Trajectories:
        """The trajectories estimator ``name`` ran on: its own closed loop's, or the study's."""
        return self.trajectories.get(name, self.traj)


def run_suite(
    scenario,
    *,
    runs: int | None = None,
    seed: int = 0,
    estimators: tuple[str, ...] | list[str] | None = None,
    add: tuple[str, ...] | list[str] = (),
    progress: bool = True,
    dtype: torch.dtype = torch.float64,
    checkpoint=None,
    cache: dict | None = None,
    calibration=None,
    label: str | None = None,
    detector_seed: int | None = None,
    detector_runs: int | None = None,
) -> SuiteResult:
    """Simulate ``runs`` runs of ``scenario`` and run every estimator on them.

    Args:
        scenario: a :class:`~difffilter.models.scenario.Scenario`.
        runs: Monte Carlo runs (default ``scenario.runs``).
        seed: master seed of every random draw (:class:`~difffilter.models.streams.Streams`).
        estimators: registered estimator names (default ``scenario.estimators``, else
            :data:`~difffilter.models.generic_estimators.DEFAULT_SUITE`). Those whose
            needs the scenario does not meet (:mod:`difffilter.models.needs`: a KF on a
            nonlinear model, an attack-free reference under an actuator attack, another
            family's estimator) are skipped, with the reason, in ``skipped``.
        add: more registered estimators to run after those (``estimators=[]``: these
            alone; an empty list with nothing added is an error).
        progress: show a progress bar, labelled ``label`` (default the scenario's name;
            the calibration's says it is the calibration).
        dtype: of the model and the simulation.
        checkpoint: a trained estimator checkpoint for the estimators that use one
            (default: the scenario's shipped checkpoint, if it has one), or
            ``{estimator: path}`` (with ``"*"``: the others' default): each named estimator
            runs with its own checkpoint, added to the run if it is not in it, and one
            its checkpoint does not fit is an error, not a skip.
        cache: a dict shared by the suites of one evaluation (``SuiteContext.cache``).
        calibration: a :class:`~difffilter.eval.calibration.Calibration` (thresholds
            from attack-free runs of their own seed): adds the metrics at the target
            false-alarm rate (``tpr_at_far``, ``fpr_at_far``, ``impact``), or ``None``.
        detector_seed: the seed of the detectors' own attack-free runs (a CUSUM's τ;
            default ``seed``): the false-alarm calibration gives the study's, so that it
            picks its threshold on the scores of the detector the study judges.
        detector_runs: the study's runs, which set how many attack-free runs the detectors'
            own calibrations use (default ``runs``; given by the false-alarm calibration).

    Runs with one intra-op thread unless the scenario says otherwise
    (:func:`difffilter.runtime.one_thread`). Inside a torch.distributed process group
    (``difffilter-eval --devices N``) each process runs its share of the estimators
    (:func:`shares`: longest first onto the least loaded process, by the seconds measured
    so far) and the outputs are gathered: the same numbers as one process, since every
    estimator sees the same trajectories and named streams wherever it runs. An estimator
    whose factory raises :class:`~difffilter.models.estimators.SkipEstimator` is left out
    and listed in ``skipped``; so is one whose run breaks down on the study's data
    (:class:`~difffilter.linalg.NumericalBreakdown`: an EKF whose Jacobian is undefined at
    its estimate, a covariance no longer positive definite), with a warning and the
    reason prefixed :data:`BROKE_DOWN`, and the others run. Any other error of an
    estimator stops the suite, naming the estimator and the scenario.
    """
    runs = scenario.runs if runs is None else runs
    runs = check_integer(runs, "runs", 1)
    if dtype not in (torch.float32, torch.float64):  # (float16 met torch's cholesky error)
        raise ValueError(f"dtype must be torch.float32 or torch.float64; got {dtype!r}")
    estimators, add = estimator_names(estimators, "estimators"), estimator_names(add, "add")
    _check_calibration(calibration, scenario)
    options = registry.check_options(scenario.estimator_options(), f"scenario {scenario.name!r}")
    streams = Streams(seed)
    model = scenario.system(dtype)
    _check_threat_fits(scenario, model)
    gens = streams.simulation()
    traj = scenario.simulate(runs, gens, dtype=dtype, model=model)
    if scenario.simulated_attack() is not None and not bool(traj.flags.any()):
        # (a scenario's own signal past its horizon: a study with no attacked step, every
        # detection metric None, without a word; a library threat's onset is refused above)
        warnings.warn(f"{scenario.name}: its attack flags no step of these {runs} runs of "
                      f"{scenario.steps} steps: the detection metrics have nothing to detect",
                      stacklevel=2)  # fmt: skip
    source = "--ckpt"
    checkpoint, named = registry.split_checkpoints(checkpoint)
    if checkpoint is None and scenario.shipped_checkpoint() is not None:
        # (--ckpt NAME=PATH for some estimators: the others read the shipped one)
        why = "--ckpt named other estimators only" if named else "no --ckpt given"
        checkpoint, source = scenario.shipped_checkpoint(), f"shipped default ({why})"
    ctx = registry.SuiteContext(scenario, model, runs, streams, options, checkpoint,
                                named_checkpoints=dict(named),
                                detector_streams=None if detector_seed is None
                                else Streams(detector_seed), detector_runs=detector_runs)  # fmt: skip
    if cache is not None:
        ctx.cache = cache
    names = tuple(scenario.estimators or DEFAULT_SUITE) if estimators is None else estimators
    names += tuple(n for n in (*add, *named) if n not in names)
    if not names:  # [] ran the scenario's whole suite (and calibrate(estimators=[], add=…) too)
        raise ValueError(
            "estimators is empty and nothing is added: nothing to run; name estimators, or "
            "give None for the scenario's own"
        )
    specs = [registry.get(n) for n in names]  # unknown names fail before any work
    built = {}  # asked for by name: a misfit fails here, before any work, not as a skip
    for name, path in named.items():
        unmet = registry.get(name).unmet(scenario, model)
        if unmet is not None:
            raise ValueError(f"--ckpt {name}={path}: {name} does not fit {scenario.name}: {unmet}")
        try:
            built[name] = registry.get(name).build(ctx)
        except registry.SkipEstimator as exc:
            raise ValueError(f"--ckpt {name}={path}: {exc}") from None
        if name not in ctx.checkpoint_users:  # built without reading it: the report would
            # say it used the file
            raise ValueError(f"--ckpt {name}={path}: {name} reads no checkpoint")
    result = SuiteResult(scenario, runs, seed, traj, context=ctx, calibration=calibration,
                         progress=progress)  # fmt: skip
    rank, world = process_group()
    seconds = ctx.cache.setdefault(SECONDS_PER_RUN, {})  # measured by the earlier suites
    ranks = ctx.cache.setdefault(RANK_OF, {})  # where the earlier suites ran each estimator
    parts = shares(specs, world, seconds, runs, ranks)
    ranks.update({spec.name: r for r, part in enumerate(parts) for spec in part})
    mine = parts[rank]  # each process runs its share
    with one_thread(scenario.single_thread), torch.no_grad():
        _run_estimators(result, mine, progress and rank == 0, built, label)
    if world > 1:
        _gather(result, ctx, specs, world)
    seconds.update({name: wall / runs for name, wall in result.wall_s.items()})
    result.reference = _reference_of(scenario, [s.name for s in specs
                                                if s.reference and s.name in result.outputs])  # fmt: skip
    from difffilter.models.neural_estimator import checkpoint_sha256, checkpoint_training_scenario

    def provenance(path) -> dict:  # (the scenario it was trained on: another plant of the
        # family runs without a word, so the report says what the network was trained on)
        loaded = ctx.loaded_checkpoints.get(str(path))
        if loaded is not None:  # the file as the estimators loaded it (replaced since, it
            return dict(loaded)  # would name another network)
        trained = checkpoint_training_scenario(path)
        return {"sha256": checkpoint_sha256(path),
                **({"training_scenario": trained} if trained is not None else {})}  # fmt: skip

    for name, path in named.items():
        result.checkpoints[name] = {"path": str(path), **provenance(path)}
    users = [n for n in ctx.checkpoint_users if n not in named]
    if checkpoint is not None and (users or not named or source == "--ckpt"):
        result.checkpoint = {
            "path": str(checkpoint),
            **provenance(checkpoint),
            "source": source,
            "used_by": users,
        }
    _score(result, specs)
    return result


@contextlib.contextmanager
def _naming(name: str, scenario: str):
    """Errors of estimator ``name`` name it and ``scenario``: a ``ValueError`` (what the
    command line prints in one line) by its message, ``"name on scenario: …"``, any other
    by a note on its traceback. Only a run's ``ValueError`` had been named: a factory's, a
    need's check's or a torch ``RuntimeError`` (a shape mismatch, a user's commonest bug)
    came bare, and the command line printed a factory's ValueError as one line naming
    nothing (an estimator-registration trial). Skips and breakdowns pass as they are."""
    try:
        yield
    except (registry.SkipEstimator, NumericalBreakdown):
        raise
    except ValueError as exc:
        raise ValueError(f"{name} on {scenario}: {exc}") from exc
    except Exception as exc:
        add_note(exc, f"(raised by estimator {name!r} on scenario {scenario!r})")
        raise


def _check_threat_fits(scenario, model) -> None:
    """The attack the plant meets acts within the horizon and fits its channel
    (:func:`~difffilter.threats.check_attack_fits`): an onset past the last step ran a
    whole study with no attacked step, every detection metric ``None``, without a word."""
    from difffilter.threats import check_attack_fits

    try:
        check_attack_fits(scenario.simulated_attack(), model, scenario.steps)
    except ValueError as exc:
        raise ValueError(f"scenario {scenario.name!r}: its attack does not fit: {exc}") from None


def _check_calibration(calibration, scenario) -> None:
    """``calibration`` is ``None`` or what :func:`~difffilter.eval.calibration.calibrate`
    returns: a rate (``calibration=0.01``) failed after the study as "'float' object has no
    attribute 'thresholds'". One made on another scenario (another name or horizon:
    :func:`~difffilter.eval.calibration.calibration_mismatch`) warns: a calibration trial's
    thresholds of 100 steps met 2.0 % on runs of 50, 0.34 % on runs of 300, unsaid (an
    error would forbid judging a plant at another's thresholds, which may be the study)."""
    from .calibration import Calibration, calibration_mismatch

    if calibration is not None and not isinstance(calibration, Calibration):
        raise ValueError(
            "calibration must be None or the Calibration calibrate(scenario, far=…) returns "
            f"(the thresholds, not the rate); got {type(calibration).__name__} {calibration!r}"
        )
    why = calibration_mismatch(calibration, scenario) if calibration is not None else None
    if why:
        warnings.warn(f"calibration: {why}", stacklevel=3)


def estimator_names(names, arg: str) -> tuple[str, ...] | None:
    """``names`` (a list or tuple of estimator names, or ``None``) as a tuple. A single
    string is refused: iterated, ``"chi_square_ekf"`` named the estimators ``'c'``, ``'h'``, …"""
    if names is None:
        return None
    if not isinstance(names, str):  # (a generator was emptied by the check below)
        names = tuple(names)
    if isinstance(names, str) or not all(isinstance(n, str) for n in names):
        hint = f" (e.g. [{names!r}])" if isinstance(names, str) else ""
        raise ValueError(f"{arg} must be a list of estimator names{hint}; got {names!r}")
    return tuple(names)


def _warm_up() -> None:
    """The process's one-time costs, paid once before any estimator is timed: torch's
    ``broadcast_shapes`` imports sympy at its first call (0.45 s), and the linear-algebra
    kernels load at theirs. The first estimator of a process had carried them in its
    ``time_per_step_s`` (a trial: the linearised KF of ``four_tank_filters`` reported 73×
    its own time, ten times the EKF's, where it takes 0.14 of it)."""
    global _WARM
    if _WARM:
        return
    with torch.no_grad():
        torch.broadcast_shapes((2, 1), (1, 3))
        a = torch.eye(2, dtype=torch.float64) * 2.0
        for t in (a, a.float()):
            torch.linalg.solve_triangular(torch.linalg.cholesky(t), t, upper=False)
            torch.linalg.solve(t, t)
            torch.linalg.eigvalsh(t)
    _WARM = True


#: Whether :func:`_warm_up` ran in this process.
_WARM = False


def _run_estimators(result: SuiteResult, specs, progress: bool, built=None,
                    label: str | None = None) -> None:  # fmt: skip
    """Run every estimator of ``specs`` on the study's trajectories into ``result``
    (outputs, wall times, the trajectories of those that run their own closed loop, and
    those skipped with the reason); ``built``: ``{name: run}`` already made by their
    factories."""
    built = built or {}
    from tqdm.auto import tqdm

    _warm_up()  # (before the first estimator's wall time is taken)
    bar = tqdm(specs, desc=label or result.scenario.name, disable=not progress, leave=False)
    ctx = result.context
    adaptive = meets_adaptive_attack(ctx.scenario)
    for spec in bar:
        bar.set_postfix_str(spec.name)
        with _naming(spec.name, result.scenario.name):
            unmet = spec.unmet(ctx.scenario, ctx.model)  # (a user's Need(check) may raise)
        if unmet is not None and spec.name not in built:
            result.skipped[spec.name] = unmet
            continue
        try:
            with _naming(spec.name, result.scenario.name):
                run = built[spec.name] if spec.name in built else spec.build(result.context)
        except registry.SkipEstimator as why:
            result.skipped[spec.name] = str(why)
            continue
        except NumericalBreakdown as exc:  # (a factory's own runs: a CUSUM's calibration)
            _broke_down(result, spec.name, exc, label)
            continue
        start = time.perf_counter()
        try:
            with _naming(spec.name, result.scenario.name):
                out = spec.checked(run(result.traj))
        except NumericalBreakdown as exc:  # this estimator cannot run here; the others can
            _broke_down(result, spec.name, exc, label)
            continue
        if adaptive and not isinstance(out, LoopResult):
            result.skipped[spec.name] = ADAPTIVE_SKIP
            continue
        result.wall_s[spec.name] = time.perf_counter() - start
        if isinstance(out, LoopResult):  # a closed loop of its own: its truth
            result.trajectories[spec.name] = out.trajectories
            out = out.output
        if spec.estimates is not None:
            out.attack_channel = spec.estimates
        _check_fits(spec.name, result.scenario.name, out, result.traj_of(spec.name))
        result.outputs[spec.name] = out


def _reference_of(scenario, references: list[str]) -> str | None:
    """The attack-free reference of a study among the ``references`` that ran: the first of
    the scenario's own estimators, else the first by name; never the order the estimators
    were listed in (a generic reference listed first had become the LFC study's, and every
    ``state_rmse_vs_attack_free`` moved: 0.0898 against 0.0949)."""
    if not references:
        return None
    own = [n for n in (getattr(scenario, "estimators", None) or ()) if n in references]
    chosen = own[0] if own else min(references)
    if len(references) > 1:
        warnings.warn(
            f"{scenario.name}: several attack-free references ran ({', '.join(references)}); "
            f"{chosen} is the reference of state_rmse_vs_attack_free (the scenario's own, "
            "else the first by name)",
            stacklevel=3,
        )
    return chosen


def _broke_down(result: SuiteResult, name: str, exc: NumericalBreakdown,
                label: str | None = None) -> None:  # fmt: skip
    """List ``name`` in ``result.skipped`` as broken down on the study's data, and warn,
    naming the study by its ``label`` where it has one (the calibration's runs)."""
    result.skipped[name] = f"{BROKE_DOWN}: {exc}"
    where = label or result.scenario.name  # (a label begins with the scenario's name)
    warnings.warn(f"{name} broke down on {where} and is left out: {exc}", stacklevel=3)


def _check_fits(name: str, scenario: str, out, traj) -> None:
    """``out`` estimates the study's runs and steps: means ``[B, T, dx]`` like the true
    states, scores ``[B, T]``. A state estimate of one component on a four-state plant was
    scored against all four by broadcasting (a state RMSE of 7.76, without a word), and a
    step too few failed inside the scoring."""
    want = tuple(traj.x.shape)
    if tuple(out.means.shape) != want:
        raise ValueError(
            f"estimator {name!r} on {scenario}: its means have shape {tuple(out.means.shape)}; "
            f"the study's states are {want} [runs, steps, dx]: one estimate per run and step"
        )
    for what, estimate in (("state", out.means), ("attack", out.attack)):
        if estimate is None:
            continue
        bad = ~torch.isfinite(estimate).all(-1)
        if not bool(bad.any()):
            continue
        # the attack RMSE reads the attacked steps only (the state RMSE every step): a NaN
        # on an attack-free step had been said to null an attack RMSE that metrics.json gave
        scored = bad if what == "state" else bad & traj.flags
        if bool(scored.any()):  # a diverged estimate: its RMSE is NaN, null in metrics.json
            warnings.warn(
                f"estimator {name!r} on {scenario}: its {what} estimate is NaN or infinite "
                f"at {int(bad.sum())} of {bad.numel()} run-steps, so its {what} RMSE is "
                "null (not 'does not apply': it diverged)", stacklevel=2,
            )  # fmt: skip
        else:
            warnings.warn(
                f"estimator {name!r} on {scenario}: its attack estimate is NaN or infinite "
                f"at {int(bad.sum())} of {bad.numel()} run-steps, all attack-free: its attack "
                "RMSE (over the attacked steps) is given, though the estimate diverged there",
                stacklevel=2,
            )  # fmt: skip
    if out.detection is not None and out.detection.scores.shape != traj.flags.shape:
        raise ValueError(  # (the output's own check ties scores to its means; kept for clarity)
            f"estimator {name!r} on {scenario}: its detection scores have shape "
            f"{tuple(out.detection.scores.shape)}; the study's steps are "
            f"{tuple(traj.flags.shape)} [runs, steps]"
        )


def _score(result: SuiteResult, specs) -> None:
    """Every run estimator's metrics against the trajectories it ran on."""
    ref = result.outputs[result.reference].means if result.reference else None
    for spec in (s for s in specs if s.name in result.outputs):
        out, traj = result.outputs[spec.name], result.traj_of(spec.name)
        result.metrics[spec.name] = score(
            out, traj, dt=result.scenario.dt, wall_s=result.wall_s[spec.name],
            reference_means=ref, attacked_input=not spec.clean_input,
        )  # fmt: skip
    apply_calibration(result, result.calibration)


def detectors(result: SuiteResult) -> list[str]:
    """The estimators of ``result`` that report detection scores (those a calibration
    gives a threshold), in the order they ran."""
    return [name for name, out in result.outputs.items()
            if out.detection is not None and out.detection.scores is not None]  # fmt: skip


def apply_calibration(result: SuiteResult, calibration) -> None:
    """Judge ``result``'s detectors at the thresholds of ``calibration`` (``None``: none):
    sets ``result.calibration`` and (re)computes every estimator's calibrated metrics
    (:func:`~difffilter.eval.calibration.calibrated_metrics`). A study can so run before its
    calibration, which then runs only the estimators that detect (:func:`detectors`)."""
    if calibration is not result.calibration:  # (run_suite checked its own)
        _check_calibration(calibration, result.scenario)
    result.calibration = calibration
    thresholds = calibration.thresholds if calibration is not None else {}
    for name, out in result.outputs.items():
        clean = registry.get(name).clean_input
        result.metrics[name].update(calibrated_metrics(
            out, result.traj_of(name), thresholds.get(name), attacked_input=not clean,
            dt=result.scenario.dt,
        ))  # fmt: skip


#: How ``skipped`` begins the reason of an estimator that ran and broke down on the study's
#: data (:class:`~difffilter.linalg.NumericalBreakdown`), not one that does not apply.
BROKE_DOWN = "broke down on this study's data"


def broken_down(skipped: dict[str, str]) -> dict[str, str]:
    """``{estimator: why}`` of the estimators of ``skipped`` (a suite's, or metrics.json's)
    that broke down on the study's data, ``why`` without :data:`BROKE_DOWN`'s prefix."""
    prefix = f"{BROKE_DOWN}: "
    return {n: why[len(prefix) :] for n, why in skipped.items() if why.startswith(prefix)}


#: Why an estimator is left out of a closed-loop study under an adaptive attack
#: (:func:`~difffilter.models.generic_estimators.meets_adaptive_attack`) where it ran on the
#: study's shared trajectories instead of a loop of its own.
ADAPTIVE_SKIP = (
    "the attack is adaptive (reads_view) and this estimator ran on the scenario's shared "
    "loop, where the attack read another estimator's outputs: it is judged only in a loop "
    "of its own"
)

#: The ``SuiteContext.cache`` key of ``{estimator: wall seconds per run}`` measured by the
#: suites of one evaluation so far (the same on every process: measured after the gather).
SECONDS_PER_RUN = "suite/seconds_per_run"
#: The ``SuiteContext.cache`` key of ``{estimator: rank}``: the process that ran each
#: estimator in the latest suite that had it (the same on every process).
RANK_OF = "suite/rank_of"


def shares(
    specs, world: int, seconds: dict[str, float], runs: int, previous: dict[str, int] | None = None
) -> list[list]:
    """``specs`` divided between ``world`` processes: longest first onto the least loaded
    (ties to the lower rank), each estimator's cost its ``seconds`` per run × ``runs``, and
    one not timed yet the mean of those that are (1 when none is: round robin). The same
    on every process, given the same ``seconds``; the outputs do not depend on it.

    ``previous`` (``{name: rank}``, the ranks of the earlier suites of the evaluation): an
    estimator goes back to its rank where that keeps the rank's load within the largest
    load of the plain assignment, because what a process caches for an estimator serves it
    only there (the LFC loops without attack, shared by every scenario of the same draws:
    computed on two processes, each paid for twice)."""
    known = [seconds[s.name] for s in specs if s.name in seconds]
    default = sum(known) / len(known) if known else 1.0
    cost = [seconds.get(s.name, default) * runs for s in specs]
    order = sorted(range(len(specs)), key=lambda i: -cost[i])  # stable: registry order
    out, bound = _longest_first(specs, cost, order, world, {}, 0.0)
    if previous:
        out, _ = _longest_first(specs, cost, order, world, previous, bound)
    return [sorted(part, key=specs.index) for part in out]


def _longest_first(specs, cost, order, world: int, previous: dict, bound: float):
    """:func:`shares`' assignment and its largest load: in ``order``, each onto its
    ``previous`` rank where that rank's load stays within ``bound``, else onto the least
    loaded."""
    load, out = [0.0] * world, [[] for _ in range(world)]
    for i in order:
        rank = previous.get(specs[i].name)
        if rank is None or rank >= world or load[rank] + cost[i] > bound:
            rank = min(range(world), key=lambda r: load[r])
        out[rank].append(specs[i])
        load[rank] += cost[i]
    return out, max(load)


def process_group() -> tuple[int, int]:
    """``(rank, world size)`` of the torch.distributed group, ``(0, 1)`` without one."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


class PeerLost(RuntimeError):
    """Another process of ``difffilter-eval --devices N`` left before a gather: it failed,
    and says why itself (its peers exit quietly: :func:`difffilter.eval.cli._launch`)."""


def gather_objects(mine, world: int) -> list:
    """``[each process's mine]`` of the ``world`` processes of the group (rank order); a
    collective that fails, a peer having left, raises :class:`PeerLost` (gloo's "Connection
    closed by peer" traceback had been printed for the peer, and could hide the failed
    process's own error and exit code: a CLI trial). ``mine`` is pickled first, outside the
    collective: an object of this process that cannot be pickled (a plug-in's scripted
    module) is this process's own error, with its traceback, not a lost peer (gloo raises
    a plain ``RuntimeError`` either way: a review)."""
    import pickle

    import torch.distributed as dist

    data = pickle.dumps(mine, protocol=pickle.HIGHEST_PROTOCOL)
    parts: list = [None] * world
    try:
        dist.all_gather_object(parts, data)
    except RuntimeError as exc:
        raise PeerLost(str(exc)) from exc
    return [pickle.loads(part) for part in parts]


def _gather(result: SuiteResult, ctx, specs, world: int) -> None:
    """Give every process every estimator's output, in the registry order of ``specs``.

    Each estimator ran in one process on the same trajectories and named streams as it
    would in one process, so the gathered outputs are those of a single-process run.
    """
    mine = (result.outputs, result.wall_s, result.skipped, ctx.checkpoint_users,
            result.trajectories, ctx.loaded_checkpoints)  # fmt: skip
    parts = gather_objects(mine, world)
    outputs, walls, skipped, users, trajs = {}, {}, {}, [], {}
    for out, wall, skip, used, own, loaded in parts:
        outputs.update(out)
        walls.update(wall)
        skipped.update(skip)
        users += used
        trajs.update(own)
        # the files as the process that ran their estimators loaded them (a review: rank 0
        # had hashed a file it never loaded at the report's end)
        ctx.loaded_checkpoints.update(loaded)
    order = [s.name for s in specs]
    result.outputs = {n: outputs[n] for n in order if n in outputs}
    result.trajectories = {n: trajs[n] for n in order if n in trajs}
    result.wall_s = {n: walls[n] for n in order if n in walls}
    result.skipped = {n: skipped[n] for n in order if n in skipped}
    ctx.checkpoint_users[:] = [n for n in order if n in users]


def single_run_time_per_step(spec, ctx, traj, repeats: int = 3) -> float:
    """Best wall time per step of estimator ``spec`` on run 0 alone (after a warm-up run).

    The real-time figure a paper's per-step CPU time compares with; the batched
    ``time_per_step_s`` of :mod:`~difffilter.eval.scoring` is the throughput figure.
    """
    run, one = spec.factory(ctx), traj.runs(1)
    with one_thread(), torch.no_grad():
        run(one)
        walls = []
        for _ in range(repeats):
            start = time.perf_counter()
            run(one)
            walls.append(time.perf_counter() - start)
    return min(walls) / traj.flags.shape[1]
