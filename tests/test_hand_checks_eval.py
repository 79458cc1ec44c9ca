"""Hand checks of the evaluation's and the sweep's plumbing: the numbers they pick and pass on.

The robustness study's worst case (which metrics, ties, non-finite values) and its run
counts, the suite's per-step time and cost shares and the trajectories it scores on, the
report's strict JSON and table columns, the sweep's mean, NaN and median seed and its
baseline cache, the calibration cache's key and fingerprint, the threat distribution's
``covers`` and ``choice``, the scenarios' input time index, norm floor and YAML defaults,
and ``one_thread``; each against its docstring, computed by hand.
"""

from __future__ import annotations

import json
import math
from types import SimpleNamespace as NS

import numpy as np
import pytest
import torch

from difffilter.ssm import LinearGaussianModel
from difffilter.threats import Bias

F64 = torch.float64

# ---------------------------------------------------------------- robustness


def test_robustness_worst_case_by_hand():
    """Lowest TPR and AUC, highest state-error ratio and impact over the threats; a state
    error that is not finite (a diverged estimate) is the worst, a TPR that is not finite no
    worst case; a tie names the first threat by name, whatever the order the threats were
    listed in."""
    from difffilter.eval.robustness import _cell, _worst_cases

    cell = _cell({"state_rmse": 3.0, "tpr_at_far": 0.5, "impact": 1.0}, {"state_rmse": 2.0})
    assert cell["state_error_ratio"] == 1.5
    cells = {
        "a": {"kf": {"tpr_at_far": 0.2, "auc": 0.9, "state_error_ratio": 1.1, "impact": 4.0}},
        "b": {"kf": {"tpr_at_far": 0.2, "auc": 0.7, "state_error_ratio": math.inf, "impact": 9.0}},
        "c": {"kf": {"tpr_at_far": 0.6, "auc": 0.8, "state_error_ratio": 3.0, "impact": 2.0}},
    }
    worst = _worst_cases(cells)["kf"]
    assert (worst["impact"], worst["impact_threat"]) == (9.0, "b")
    assert (worst["auc"], worst["auc_threat"]) == (0.7, "b")
    assert (worst["state_error_ratio"], worst["state_error_ratio_threat"]) == (math.inf, "b")
    assert worst["state_error_ratio_diverged"] and "impact_diverged" not in worst
    assert (worst["tpr_at_far"], worst["tpr_at_far_threat"]) == (0.2, "a")
    # b ties a at the lowest TPR: counted, and the table says so
    assert worst["tpr_at_far_tied"] == 1 and "impact_tied" not in worst
    from difffilter.eval.robustness import _worst_text

    assert _worst_text(worst, "tpr_at_far") == "0.2 (a; 1 more tied)"
    assert _worst_text(worst, "impact") == "9 (b)"
    listed_otherwise = _worst_cases(dict(reversed(cells.items())))["kf"]
    assert listed_otherwise == worst
    cells["c"]["kf"]["state_error_ratio"] = math.nan  # diverged on two: the first by name
    assert _worst_cases(cells)["kf"]["state_error_ratio_threat"] == "b"
    cells["a"]["kf"]["tpr_at_far"] = math.nan  # no attacked step: no worst case
    assert _worst_cases(cells)["kf"]["tpr_at_far_threat"] == "b"


def test_robustness_takes_the_runs_it_is_given(monkeypatch):
    """An explicit ``runs`` wins over the threat set's; ``calibration_runs`` sets the
    calibration's."""
    from difffilter.eval import robustness

    seen = {"suite": []}

    def calibrate(scenario, **kw):
        seen["calibration"] = kw["runs"]
        return "calibration"

    def run_suite(scenario, **kw):
        seen["suite"].append(kw["runs"])
        return NS(metrics={})

    monkeypatch.setattr(robustness, "calibrate", calibrate)
    monkeypatch.setattr(robustness, "run_suite", run_suite)
    scenario = NS(name="s", runs=100, with_threat=lambda threat: None)
    threat_set = robustness.ThreatSet(threats={"b": object()}, specs={"b": {"kind": "b"}}, runs=40)
    threat_set.threats.clear()  # (the sizes alone: no threat's run to fake)
    threat_set.specs.clear()
    result = robustness.run_robustness(
        scenario, threat_set, runs=7, calibration_runs=13, progress=False
    )
    assert result.runs == 7
    assert seen == {"suite": [7], "calibration": 13}


# ---------------------------------------------------------------- suite


def test_single_run_time_per_step_is_the_best_wall_over_the_steps(monkeypatch):
    """``min`` of the timed repeats (after a warm-up) over T steps, on a fake clock."""
    from difffilter.eval import suite

    clock = iter([0.0, 0.5, 1.0, 1.25, 2.0, 3.0])  # repeats of 0.5, 0.25 and 1 s
    monkeypatch.setattr(suite.time, "perf_counter", lambda: next(clock))
    runs_seen = []

    class Traj:
        flags = torch.zeros(5, 20, dtype=torch.bool)

        def runs(self, n):
            runs_seen.append(n)
            return self

    spec = NS(factory=lambda ctx: lambda traj: None)
    assert suite.single_run_time_per_step(spec, None, Traj()) == 0.25 / 20
    assert runs_seen == [1]


def test_an_untimed_estimator_costs_the_mean_of_the_timed_ones():
    """a = 2, b = 4, c unknown = 3: two processes get [b] and [a, c] (largest first)."""
    from difffilter.eval.suite import shares

    a, b, c = NS(name="a"), NS(name="b"), NS(name="c")
    parts = shares([a, b, c], 2, {"a": 2.0, "b": 4.0}, 1)
    assert [[s.name for s in part] for part in parts] == [["b"], ["a", "c"]]


def test_an_estimator_is_scored_on_the_trajectories_it_ran_on(monkeypatch):
    """One that ran its own closed loop is scored on that loop, not the study's."""
    from difffilter.eval import suite

    scored_on = []
    monkeypatch.setattr(suite, "score", lambda out, traj, **kw: scored_on.append(traj) or {})
    monkeypatch.setattr(suite, "apply_calibration", lambda result, calibration: None)
    result = suite.SuiteResult(scenario=NS(dt=1.0), runs=1, seed=0, traj="study")
    result.outputs = {"loop_estimator": NS(means=None)}
    result.trajectories = {"loop_estimator": "own loop"}
    result.wall_s = {"loop_estimator": 0.1}
    suite._score(result, [NS(name="loop_estimator", clean_input=False)])
    assert scored_on == ["own loop"]


# ---------------------------------------------------------------- report


def test_report_writes_strict_json_and_keeps_a_column_any_estimator_has():
    from difffilter.eval.report import _table_section, json_safe
    from difffilter.eval.scoring import METRICS

    cleaned = json_safe({"x": math.inf, "y": -math.inf, "z": math.nan, "w": 1.5})
    assert cleaned == {"x": None, "y": None, "z": None, "w": 1.5}
    json.dumps(cleaned, allow_nan=False)
    # (a mutation trial: tuples and non-string keys were untested) tuples become lists,
    # keys strings, and the rule holds at any depth, numpy and torch scalars included
    nested = json_safe({1: (math.nan, np.float32(2.5)), (2, 3): [torch.tensor(math.inf)],
                        "t": torch.tensor([1.0, math.nan])})  # fmt: skip
    assert nested == {"1": [None, 2.5], "(2, 3)": [None], "t": [1.0, None]}
    json.dumps(nested, allow_nan=False)
    doc = {"estimators": {"a": {"state_rmse": 1.0, "auc": 0.8},
                          "b": {"state_rmse": 2.0, "auc": None}},
           "units": {n: m.unit for n, m in METRICS.items()}, "estimator_roles": {},
           "estimator_descriptions": {"a": "A", "b": "B"}}  # fmt: skip
    header = _table_section(doc).body.splitlines()[0]
    assert "auc" in header
    assert "state_rmse" in header


# ---------------------------------------------------------------- sweep


def test_sweep_summary_is_the_mean_and_spread_and_nan_where_no_scenario_has_it():
    from difffilter.train import sweep

    per_seed = {s: {"scenarios": {"s": {"auc": v}}} for s, v in enumerate((0.1, 0.2, 0.9))}
    auc = sweep._summary(per_seed)["s"]["auc"]
    assert math.isclose(auc["mean"], 0.4, abs_tol=1e-12)
    assert math.isclose(auc["spread"], 0.8, abs_tol=1e-12)
    scores = sweep._test_scores(
        {
            0: {"scenarios": {"s": {"tpr_at_far": None}}},
            1: {"scenarios": {"s": {"tpr_at_far": 0.5}}},
        },
        "tpr_at_far",
    )
    assert math.isnan(scores[0]) and scores[1] == 0.5


def _sweep_config(tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text(
        "trainer:\n  callbacks:\n  - class_path: lightning.pytorch.callbacks.ModelCheckpoint\n"
        "    init_args: {monitor: val/loss}\n"
    )
    return config


def test_sweep_monitor_mode_defaults_to_min(tmp_path):
    from difffilter.train import sweep

    assert sweep._config_monitor(_sweep_config(tmp_path)) == {"metric": "val/loss", "mode": "min"}


def test_sweep_on_test_scores_ships_the_worse_middle_of_two_seeds(tmp_path, monkeypatch):
    from difffilter.train import sweep

    tpr = {0: 0.9, 1: 0.5}

    def fit(config, seed, runs_dir, extra, progress=True):
        path = tmp_path / f"s{seed}.ckpt"
        path.write_text("x")
        path.with_suffix(".json").write_text("{}")
        return path

    def evaluate(path, scenarios, runs, far, progress):
        row = dict.fromkeys(sweep.METRICS) | {"tpr_at_far": tpr[int(path.stem[1:])]}
        return {"estimator": "e", "scenarios": {"s": row}}, {"s": {}}

    monkeypatch.setattr(sweep, "_fit", fit)
    monkeypatch.setattr(sweep, "_evaluate", evaluate)
    monkeypatch.setattr(sweep, "_scenarios_of", lambda path, scenarios: ("e", ["s"]))
    monkeypatch.setattr(sweep, "_baseline", lambda *a, **k: ({}, {}))
    monkeypatch.setattr(sweep, "_acceptance", lambda *a, **k: {})
    doc = sweep.sweep(
        _sweep_config(tmp_path), seeds=(0, 1), out=tmp_path / "out", select_on="test",
        progress=False,
    )  # fmt: skip
    assert doc["median_seed"] == 1


def test_sweep_baselines_are_cached_per_false_alarm_rate(tmp_path, monkeypatch):
    from difffilter.models import registry
    from difffilter.train import sweep

    def calibrated_metrics(scenario, names, runs, far, progress, checkpoint=None):
        return {"kf": {"far_seen": far}}, {}

    monkeypatch.setattr(sweep, "_calibrated_metrics", calibrated_metrics)
    name = registry.names()[0]
    assert sweep._baseline(name, 3, 0.01, False, tmp_path)[0] == {"kf": {"far_seen": 0.01}}
    assert sweep._baseline(name, 3, 0.05, False, tmp_path)[0] == {"kf": {"far_seen": 0.05}}
    assert sweep._baseline(name, 3, 0.01, False, tmp_path)[0] == {"kf": {"far_seen": 0.01}}


# ---------------------------------------------------------------- calibration cache


def test_calibration_cache_is_keyed_by_key_and_fingerprint(tmp_path, monkeypatch):
    from difffilter.models.calibration_cache import cached, model_fingerprint

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    model = NS(Q=torch.eye(2, dtype=F64))
    assert cached("cusum", ("s", 0, 50), model, lambda: {"tau": 1.0}) == {"tau": 1.0}
    assert cached("cusum", ("s", 1, 50), model, lambda: {"tau": 2.0}) == {"tau": 2.0}
    assert cached("cusum", ("s", 0, 50), model, lambda: {"tau": 3.0}) == {"tau": 1.0}
    flat = torch.tensor([1.0, 0.0, 0.0, 1.0], dtype=F64)
    assert model_fingerprint(NS(Q=flat)) != model_fingerprint(NS(Q=flat.reshape(2, 2)))


# ---------------------------------------------------------------- threat distribution


def test_threat_distribution_covers_by_positive_weight_sign_and_defaults():
    from difffilter.threat_distribution import HELD_OUT, KIND_ONLY, WITHIN, ThreatDistribution

    zero = ThreatDistribution(
        {"none": {"weight": 1.0}, "bias": {"weight": 0.0, "kind": "bias", "value": 1.0}}
    )
    assert zero.covers({"kind": "bias", "value": 1.0}) == HELD_OUT
    unsigned = ThreatDistribution(
        {"bias": {"weight": 1.0, "kind": "bias", "value": {"uniform": [0.5, 1.5]}}}
    )
    assert unsigned.covers({"kind": "bias", "value": 1.0}) == WITHIN
    assert unsigned.covers({"kind": "bias", "value": -1.0}) == KIND_ONLY
    late = ThreatDistribution({"bias": {"weight": 1.0, "kind": "bias", "value": 1.0, "onset": 30}})
    assert late.covers({"kind": "bias", "value": 1.0}) == KIND_ONLY  # its onset 1 by default


def test_threat_distribution_choice_draws_every_value():
    from difffilter.threat_distribution import ThreatDistribution

    choice = ThreatDistribution(
        {"bias": {"weight": 1.0, "kind": "bias", "value": {"choice": [0.5, 2.0]}}}
    )
    g = torch.Generator().manual_seed(0)
    assert {tuple(choice.sample(g)[1].value) for _ in range(200)} == {(0.5,), (2.0,)}


# ---------------------------------------------------------------- scenarios


def _plant(dtype=F64):
    eye = torch.eye(2, dtype=dtype)
    return LinearGaussianModel(
        0.9 * eye, eye, 0.01 * eye, 0.04 * eye, torch.zeros(2, dtype=dtype), eye,
        B=torch.ones(2, 1, dtype=dtype),
    )  # fmt: skip


def test_custom_scenario_inputs_key_and_norm_floor_by_hand():
    """``known_inputs(k)`` at k = 0 … T − 1; the attack-free key depends on the horizon; the
    norm floor ½‖γ‖ with γ zero off ``entries``."""
    from difffilter.models.scenario import CustomScenario

    scenario = CustomScenario(
        name="c", family="custom", description="d", model_fn=_plant,
        known_inputs=lambda k: k, steps=5, attack=Bias(value=1.0, entries=(0,)),
    )  # fmt: skip
    assert scenario.inputs(1, F64)[0, :, 0].tolist() == [0, 1, 2, 3, 4]
    assert scenario.with_steps(3).attack_free_key() != scenario.attack_free_key()
    assert math.isclose(scenario.attack_norm_floor(_plant()), 0.5, abs_tol=1e-12)


def test_norm_floor_without_attack_is_the_largest_over_a_batch_of_models():
    """‖√diag R‖ of the batch's largest R: √(0.25 + 0.25)."""
    from difffilter.models.scenario import CustomScenario

    eye = torch.eye(2, dtype=F64)
    batch = LinearGaussianModel(
        0.9 * eye, eye, 0.01 * eye, torch.stack([0.04 * eye, 0.25 * eye]),
        torch.zeros(2, dtype=F64), eye,
    )  # fmt: skip
    scenario = CustomScenario(name="c", family="custom", description="d", model_fn=lambda d: batch)
    assert math.isclose(scenario.attack_norm_floor(batch), math.sqrt(0.5), abs_tol=1e-12)


def test_yaml_sinusoid_input_is_in_hertz_and_p0_defaults_to_identity():
    from difffilter.models.yaml_scenario import scenario_from_dict

    doc = {"name": "y", "dt": 0.1, "steps": 4,
           "plant": {"F": [[0.9]], "B": [[1.0]], "H": [[1.0]], "Q": 0.01, "R": 0.01},
           "inputs": {"kind": "sinusoid", "amplitude": 2.0, "frequency": 1.0}}  # fmt: skip
    scenario = scenario_from_dict(doc)
    u = scenario.inputs(1, F64)[0, :, 0]
    expected = [2 * math.sin(2 * math.pi * 1.0 * 0.1 * k) for k in range(4)]
    torch.testing.assert_close(u, torch.tensor(expected, dtype=F64))
    assert torch.equal(scenario.system(F64).initial.cov, torch.eye(1, dtype=F64))


# ---------------------------------------------------------------- runtime


def test_one_thread_only_when_enabled():
    from difffilter.runtime import one_thread

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with one_thread(False):
            assert torch.get_num_threads() == 2
        with one_thread(True):
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


# ------------------------------------------- what a contributor's estimator or options give


def _tiny_scenario(**kw):
    from difffilter.models.scenario import CustomScenario

    return CustomScenario(name="tiny", family="custom", description="d", model_fn=_plant,
                          steps=6, runs=2, attack=Bias(value=1.0, entries=(0,)), **kw)  # fmt: skip


def test_a_factory_or_run_that_returns_something_else_is_named(monkeypatch):
    """A contributor's trial: a factory returning its output, or a run returning the
    filter's FilterResult, failed in scoring with no estimator named."""
    import pytest

    import difffilter as df
    from difffilter.eval.suite import run_suite
    from difffilter.models import estimators

    estimators.names()  # the built-ins loaded first: a copy of the unloaded registry takes them away
    monkeypatch.setattr(estimators, "ESTIMATORS", dict(estimators.ESTIMATORS))

    @estimators.register("returns_nothing", "a factory that forgot its lambda")
    def _(ctx):
        return None

    @estimators.register("returns_filter_result", "a run returning the filter's result")
    def _(ctx):
        return lambda traj: df.kalman_filter(ctx.model, traj.y_recv, traj.us, mask=traj.mask)

    with pytest.raises(TypeError, match="'returns_nothing' .*its factory returned NoneType"):
        run_suite(_tiny_scenario(), estimators=["returns_nothing"], progress=False)
    with pytest.raises(
        TypeError, match="'returns_filter_result' .*returned FilterResult.*output_of"
    ):
        run_suite(_tiny_scenario(), estimators=["returns_filter_result"], progress=False)


def test_estimator_options_are_checked_by_name_and_together(monkeypatch):
    """A misspelt option was ignored; ``poa_eta`` without ``poa_zeta`` was a KeyError."""
    import pytest

    from difffilter.eval.suite import run_suite
    from difffilter.models import estimators

    run = ["kf"]
    with pytest.raises(ValueError, match="'tiny': unknown estimator option 'cusum_bais' "
                       r"\(did you mean 'cusum_bias'\?\)"):  # fmt: skip
        run_suite(_tiny_scenario(options={"cusum_bais": 1.0}), estimators=run, progress=False)
    with pytest.raises(ValueError, match="'tiny': estimator option poa_eta without poa_zeta"):
        run_suite(_tiny_scenario(options={"poa_eta": 0.5}), estimators=run, progress=False)
    monkeypatch.setattr(estimators, "OPTIONS", dict(estimators.OPTIONS))
    estimators.register_option("my_gain", "the gain of my estimator")
    result = run_suite(_tiny_scenario(options={"my_gain": 2.0}), estimators=run, progress=False)
    assert result.context.options == {"my_gain": 2.0}
    with pytest.raises(ValueError, match="'my_gain' is already declared: the gain of my"):
        estimators.register_option("my_gain", "another meaning")


def test_a_threat_that_did_not_act_is_left_out_of_the_worst_case_and_the_acceptance():
    """A 50 % draw that attacked none of 3 runs, and a value of 0 under its flags, were
    judged as threats the learned estimator withstood (a threat-library audit)."""
    import torch

    from difffilter.eval.robustness import RobustnessResult, _activity
    from difffilter.loop import Trajectories

    x = torch.zeros(3, 4, 1)
    flags = torch.zeros(3, 4, dtype=torch.bool)
    none = Trajectories(x, x, x, None, None, torch.zeros(3, 4, 1), flags, {})
    flags2 = flags.clone()
    flags2[1, 2:] = True
    zero = Trajectories(x, x, x, None, None, torch.zeros(3, 4, 1), flags2, {})
    acts = torch.zeros(3, 4, 1)
    acts[1, 2:] = 0.5
    acting = Trajectories(x, x, x, None, None, acts, flags2, {})
    result = RobustnessResult(None, 3, 0, None, None, None)
    result.activity = {"none": _activity(none), "zero": _activity(zero), "bias": _activity(acting)}
    assert result.activity["bias"] == {"attacked_runs": 1, "runs": 3, "attacked_steps": 2,
                                       "injected": True}  # fmt: skip
    assert result.idle() == ["none", "zero"]
    assert list(result.acting({"none": 1, "zero": 2, "bias": 3})) == ["bias"]


def test_an_attack_of_ones_own_lends_no_field_to_the_papers_settings():
    """A user's attack with fields named ``tau``, ``p_l`` and ``value`` (a trial: the
    docs' own ``Drift(scale, tau=20.0)``) lends none of them to the settings of the
    modified-PF paper: ``modified_pf_est``'s τ of eq. (4) stays 0.9 (20 had stopped every
    study, 0.5 ran as τ), the PoA detector's ``p_l`` 0.5, and the norm floor is one noise
    standard deviation, as for any attack without a steady state. The paper's attack still
    gives its own."""
    from dataclasses import dataclass

    from difffilter.models import estimators
    from difffilter.models.attacks import SensorBias
    from difffilter.models.scenario import CustomScenario
    from difffilter.threats import Shaped

    @dataclass(frozen=True)
    class Drift(Shaped):
        scale: float = 0.01
        tau: float = 0.5
        p_l: float = 0.9
        value: float = 7.0

        def shape(self, s, dim, batch, generator, dtype):
            return (
                (self.scale * torch.expm1(s.clamp(min=0) / self.tau))
                .unsqueeze(-1)
                .expand(s.shape[0], dim)
            )

    def scenario(attack):
        return CustomScenario(name="tiny", family="custom", description="d", model_fn=_plant,
                              steps=6, runs=2, attack=attack)  # fmt: skip

    own, paper = (
        scenario(Drift(onset=2)),
        scenario(SensorBias(gamma_bar=(1.0, 2.0), tau=0.7, p_l=0.3)),
    )
    assert estimators._attack_rate(own.attack_model()) == 0.5
    assert estimators._attack_rate(paper.attack_model()) == 0.3
    assert own.attack_norm_floor(_plant()) == pytest.approx(math.sqrt(2 * 0.04))  # ‖√diag R‖
    assert paper.attack_norm_floor(_plant()) == pytest.approx(0.5 * math.sqrt(5.0))
    from difffilter.models.generic_estimators import _eq4_tau

    assert _eq4_tau(own.attack_model()) == 0.9 and _eq4_tau(paper.attack_model()) == 0.7
