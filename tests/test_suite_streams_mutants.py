"""Mutation review of eval/suite.py, models/streams.py and models/calibration_cache.py.

Each test checks one behaviour against an independent truth: a draw recomputed by hand
from the documented seed (``torch.Generator().manual_seed(Streams(s).seed_of(name))``),
two runs that must be bit-identical or must differ, or a count of calibrations computed.
"""

from __future__ import annotations

import time
from types import SimpleNamespace as NS

import pytest
import torch

SCENARIO = "four_tank_bias"
STEPS = 30


def _scenario():
    from difffilter.models import registry

    return registry.get(SCENARIO).with_steps(STEPS)


def _first_draw(seed: int, name: str, n: int = 4) -> torch.Tensor:
    """The first ``n`` normals of stream ``name``, seeded by hand as documented."""
    from difffilter.models.streams import Streams

    return torch.randn(n, generator=torch.Generator().manual_seed(Streams(seed).seed_of(name)))


# ---------------------------------------------------------------- streams


def test_asking_twice_for_a_stream_gives_a_fresh_generator_each_time():
    """A second ``streams(name)`` starts where the documented seed does, however far the
    first was drawn (truth: the draw recomputed by hand); so an estimator built after
    another never sees the other's used-up generator."""
    from difffilter.models.streams import Streams

    streams = Streams(7)
    first = streams("particles/propagate")
    torch.randn(100, generator=first)
    second = streams("particles/propagate")
    assert second is not first
    assert torch.equal(torch.randn(4, generator=second), _first_draw(7, "particles/propagate"))


def test_a_negative_or_boolean_seed_is_refused():
    """``Streams`` takes integers >= 0 only (its documented contract)."""
    from difffilter.models.streams import Streams

    for bad in (-1, True, 1.0):
        with pytest.raises(ValueError, match="seed"):
            Streams(bad)


def test_an_estimator_sees_the_same_particles_whatever_ran_before_it():
    """Common random numbers: ``normal_pf``'s output is bit-identical alone and after two
    other particle filters in the same suite (truth: the run alone)."""
    from difffilter.eval.suite import run_suite

    sc = _scenario()
    alone = run_suite(sc, runs=2, seed=3, estimators=["normal_pf"], progress=False)
    after = run_suite(sc, runs=2, seed=3, estimators=["modified_pf", "mixture_likelihood_pf",
                                                      "normal_pf"], progress=False)  # fmt: skip
    assert list(after.outputs) == ["modified_pf", "mixture_likelihood_pf", "normal_pf"]
    assert torch.equal(alone.outputs["normal_pf"].means, after.outputs["normal_pf"].means)


def test_the_particle_streams_are_the_documented_names_under_the_prefix():
    """``particle_kwargs``: propagation from ``<prefix>particles/propagate``, resampling
    from ``<prefix>particles/resample`` (two purposes, two streams; truth: draws by hand)."""
    from difffilter.models.estimators import SuiteContext
    from difffilter.models.streams import Streams

    sc = _scenario()
    for prefix in ("", "adversary/"):
        ctx = SuiteContext(sc, sc.system(), 2, Streams(5), particle_prefix=prefix)
        kw = ctx.particle_kwargs()
        for key, name in (("generator", "propagate"), ("resample_generator", "resample")):
            got = torch.randn(4, generator=kw[key])
            assert torch.equal(got, _first_draw(5, f"{prefix}particles/{name}")), (prefix, key)


# ---------------------------------------------------------------- the suite's draws


def test_the_study_simulates_from_the_unprefixed_simulation_streams():
    """``run_suite``'s trajectories are ``scenario.simulate`` on ``Streams(seed)
    .simulation()`` (truth: that simulation by hand, bit for bit)."""
    from difffilter.eval.suite import run_suite
    from difffilter.models.streams import Streams

    sc = _scenario()
    result = run_suite(sc, runs=2, seed=4, estimators=["chi_square_ekf"], progress=False)
    want = sc.simulate(2, Streams(4).simulation(), model=sc.system())
    assert torch.equal(result.traj.x, want.x) and torch.equal(result.traj.y_true, want.y_true)


def test_the_detectors_calibration_runs_have_their_own_streams_seed_and_count():
    """``SuiteContext.calibration``: attack-free runs from ``calibration/<k>`` of the
    detector seed (else the study's), ``max(detector_runs or runs, 50)`` of them (truth:
    the simulation by hand); never the study's own noise."""
    from difffilter.eval.suite import run_suite
    from difffilter.models.streams import Streams

    sc = _scenario()
    result = run_suite(sc, runs=2, seed=4, estimators=["chi_square_ekf"], progress=False,
                       detector_seed=9, detector_runs=60)  # fmt: skip
    cal = result.context.calibration
    gens = {k: Streams(9)(f"calibration/{k}") for k in ("plant", "schedule", "input_schedule")}
    want = sc.simulate(60, gens, attack=None, model=sc.system())
    assert torch.equal(cal.y_true, want.y_true)
    short = run_suite(sc, runs=2, seed=4, estimators=["chi_square_ekf"], progress=False)
    assert short.context.calibration.y_true.shape[0] == 50
    free = sc.simulate(2, Streams(4).simulation(), attack=None, model=sc.system())
    assert not torch.equal(short.context.calibration.y_true[:2], free.y_true)


# ---------------------------------------------------------------- the CUSUM calibration cache


@pytest.fixture
def cusum_calls(monkeypatch, tmp_path):
    """Counts the CUSUM calibrations computed (neither in memory nor on disk)."""
    from difffilter import fdi
    from difffilter.models import estimators

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    monkeypatch.setattr(estimators, "_CUSUM_CACHE", {})
    calls = []
    real = fdi.cusum_detector_for
    monkeypatch.setattr(fdi, "cusum_detector_for", lambda *a, **k: calls.append(1) or real(*a, **k))
    return calls


def _cusum(sc, **kw):
    from difffilter.eval.suite import run_suite

    kw = {"runs": 2, **kw}
    return run_suite(sc, estimators=["cusum_ekf"], progress=False, **kw).metrics["cusum_ekf"]


def test_the_cusum_cache_tells_apart_runs_dtype_detector_seed_and_horizon(cusum_calls):
    """One calibration per distinct (runs ≥ 50, dtype, detector seed, horizon); a repeat is
    a hit (truth: the count of calibrations computed)."""
    sc = _scenario()
    _cusum(sc)
    _cusum(sc)
    assert len(cusum_calls) == 1  # a hit
    _cusum(sc, detector_runs=60)
    assert len(cusum_calls) == 2  # 60 calibration runs, not 50
    _cusum(sc, dtype=torch.float32)
    assert len(cusum_calls) == 3
    _cusum(sc, detector_seed=11)
    assert len(cusum_calls) == 4
    _cusum(sc.with_steps(STEPS + 5))
    assert len(cusum_calls) == 5


# ---------------------------------------------------------------- calibration_cache


def test_the_fingerprint_sees_closures_dict_keys_and_deep_tensors():
    """Models that compute other numbers get other fingerprints (truth: they differ)."""
    from difffilter.models.calibration_cache import model_fingerprint as fp

    def gain(k):
        return lambda x: k * x

    assert fp(NS(f=gain(1.0))) != fp(NS(f=gain(2.0)))
    assert fp({"Q": torch.ones(1)}) != fp({"R": torch.ones(1)})
    deep = [[[[[torch.zeros(2)]]]]]
    other = [[[[[torch.ones(2)]]]]]
    assert fp(NS(parts=(deep,))) != fp(NS(parts=(other,)))


def test_the_fingerprint_ignores_memos_named_cache():
    """Attributes ending in ``_cache`` (memos holding addresses) do not change the
    fingerprint (truth: two models equal but for a memo hash alike)."""
    from difffilter.models.calibration_cache import model_fingerprint as fp

    assert fp(NS(Q=torch.eye(2), jac_cache=object())) == fp(NS(Q=torch.eye(2), jac_cache=[1]))


def test_a_cache_turned_off_computes_every_time_and_writes_nothing(tmp_path, monkeypatch):
    """``DIFFFILTER_CACHE=off``: no folder, each call computes (truth: a call count)."""
    from difffilter.models import calibration_cache

    monkeypatch.setenv("DIFFFILTER_CACHE", "off")
    monkeypatch.chdir(tmp_path)
    assert calibration_cache.cache_folder() is None
    calls = []
    for _ in range(2):
        calibration_cache.cached("cusum", ("k",), NS(a=1), lambda: calls.append(1) or {"v": 1})
    assert len(calls) == 2 and not list(tmp_path.rglob("*.json"))


# ---------------------------------------------------------------- skips, timing, cache


def test_a_skipped_estimator_is_listed_with_its_reason():
    """An estimator whose need is unmet (a KF on the nonlinear four-tank plant) and one
    whose factory raises ``SkipEstimator`` (a learned one without checkpoint) are both in
    ``skipped`` with a reason, not silently dropped."""
    from difffilter.eval.suite import run_suite

    result = run_suite(_scenario(), runs=2, estimators=["chi_square_kf", "chi_square_ekf"],
                       progress=False)  # fmt: skip
    assert set(result.outputs) == {"chi_square_ekf"}
    assert result.skipped.get("chi_square_kf")


def test_the_wall_time_is_the_run_alone_and_the_shared_cache_gets_seconds_per_run(monkeypatch):
    """``wall_s`` times the estimator's run, not its factory (truth: a factory that sleeps
    1 s, a run of well under 1 s); the shared ``cache`` gets ``wall / runs`` per estimator."""
    from difffilter.eval import suite
    from difffilter.models import estimators

    spec = estimators.get("chi_square_ekf")
    real = type(spec).build

    def slow_build(self, ctx):
        time.sleep(1.0)
        return real(self, ctx)

    monkeypatch.setattr(type(spec), "build", slow_build)
    cache: dict = {}
    result = suite.run_suite(_scenario(), runs=2, estimators=["chi_square_ekf"],
                             progress=False, cache=cache)  # fmt: skip
    wall = result.wall_s["chi_square_ekf"]
    assert wall < 1.0
    assert cache[suite.SECONDS_PER_RUN]["chi_square_ekf"] == pytest.approx(wall / 2, rel=1e-12)


def test_traj_of_is_an_estimators_own_loop_where_it_ran_one():
    """``traj_of``: the estimator's own closed loop's trajectories, else the study's."""
    from difffilter.eval.suite import SuiteResult

    own, shared = object(), object()
    result = SuiteResult(None, 1, 0, shared, trajectories={"loop": own})
    assert result.traj_of("loop") is own and result.traj_of("open") is shared


# ---------------------------------------------------------------- the LFC attack-free loop cache


def _free_loops(monkeypatch):
    """``_attack_free`` with its loop replaced by a counter: ``(call, calls)``."""
    from difffilter.models import lfc_estimators as lfc
    from difffilter.models.streams import Streams

    calls: list = []
    monkeypatch.setattr(lfc, "_loop", lambda *a, **k: calls.append(1) or len(calls))
    monkeypatch.setattr(lfc, "_fork_steps", lambda scenario, draws: [])
    cache: dict = {}

    def call(scenario, seed: int, runs: int):
        ctx = NS(
            scenario=scenario, streams=Streams(seed), cache=cache, checkpoint_for=lambda name: None
        )
        tr = NS(x=torch.zeros(runs, scenario.steps, 10), info={})
        return lfc._attack_free(ctx, "uncompensated", None, tr, False)

    return call, calls


def test_the_attack_free_loop_cache_tells_apart_seed_and_runs(monkeypatch):
    """The loop without attack is shared by a repeat of the same draws, not by another
    seed or run count (truth: the count of loops run)."""
    from difffilter.models import registry

    call, calls = _free_loops(monkeypatch)
    sc = registry.get("lfc_step").with_steps(50)
    call(sc, 0, 2)
    call(registry.get("lfc_sine").with_steps(50), 0, 2)  # same draws: shared
    assert len(calls) == 1
    call(sc, 1, 2)
    assert len(calls) == 2
    call(sc, 0, 3)
    assert len(calls) == 3


def test_the_attack_free_loop_cache_tells_apart_random_loads(monkeypatch):
    """``lfc_random_attacks`` draws a load per run (``load_range``), ``lfc_step`` has one
    load: their loops without attack differ (``attack_free_key`` says so) and must not be
    shared (truth: the count of loops run)."""
    from difffilter.models import registry

    call, calls = _free_loops(monkeypatch)
    step, random = (registry.get(n).with_steps(50) for n in ("lfc_step", "lfc_random_attacks"))
    assert step.attack_free_key() != random.attack_free_key()
    call(step, 0, 2)
    call(random, 0, 2)
    assert len(calls) == 2


def test_an_estimator_whose_factory_skips_is_listed_with_the_factorys_reason(monkeypatch):
    """A factory raising ``SkipEstimator`` leaves the estimator out with that reason
    (truth: the message raised), the others run."""
    from difffilter.eval.suite import run_suite
    from difffilter.models import estimators

    spec = estimators.get("cusum_ekf")
    real = type(spec).build

    def build(self, ctx):
        if self.name == "cusum_ekf":
            raise estimators.SkipEstimator("no checkpoint here")
        return real(self, ctx)

    monkeypatch.setattr(type(spec), "build", build)
    result = run_suite(_scenario(), runs=2, estimators=["cusum_ekf", "chi_square_ekf"],
                       progress=False)  # fmt: skip
    assert result.skipped == {"cusum_ekf": "no checkpoint here"}
    assert list(result.outputs) == ["chi_square_ekf"]


def test_an_open_loop_estimator_under_an_adaptive_attack_is_listed_as_skipped(monkeypatch):
    """Under an adaptive attack an estimator that ran on the shared loop is left out with
    :data:`ADAPTIVE_SKIP` (truth: the documented constant), not dropped unsaid."""
    from difffilter.eval import suite

    monkeypatch.setattr(suite, "meets_adaptive_attack", lambda scenario: True)
    result = suite.run_suite(_scenario(), runs=2, estimators=["chi_square_ekf"], progress=False)
    assert result.skipped == {"chi_square_ekf": suite.ADAPTIVE_SKIP} and not result.outputs


def test_the_process_warms_up_before_the_first_estimator_is_timed(monkeypatch):
    """A trial: the first estimator of a process carried its one-time costs (torch's first
    ``broadcast_shapes`` imports sympy, 0.45 s) in its ``time_per_step_s``, the linearised
    KF of ``four_tank_filters`` ten times the EKF's. ``_warm_up`` runs before any
    estimator is timed, once per process."""
    from difffilter.eval import suite
    from difffilter.models import registry

    order = []
    monkeypatch.setattr(suite, "_WARM", False)
    warm = suite._warm_up
    monkeypatch.setattr(suite, "_warm_up", lambda: (order.append("warm"), warm()))
    real = suite.time.perf_counter
    monkeypatch.setattr(suite.time, "perf_counter", lambda: (order.append("timed"), real())[1])
    suite.run_suite(registry.get("four_tank_bias"), runs=2, seed=0, estimators=["chi_square_ekf"],
              progress=False)  # fmt: skip
    assert order.index("warm") < order.index("timed")
    assert suite._WARM
