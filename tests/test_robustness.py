"""The robustness study: threat sets as data, every estimator × threat at one calibrated
false-alarm rate, the files it writes and the CLI that runs it."""

from __future__ import annotations

import json

import jsonschema
import pytest
import torch

from difffilter.eval.cli import main
from difffilter.eval.report import format_number, metrics_schema
from difffilter.eval.robustness import (
    ThreatSet,
    load_threat_set,
    robustness_scenarios,
    run_robustness,
    write_robustness,
)
from difffilter.kalman import KalmanFilter
from difffilter.models import registry
from difffilter.models.streams import Streams
from difffilter.threats import Bias, RandomWalk, Replay

ESTIMATORS = ("chi_square_ekf", "cusum_ekf", "pf_nn_grad")


def test_every_headline_scenario_has_a_threat_set_that_builds():
    for name in registry.names(headline_only=True):
        threat_set = load_threat_set(registry.get(name))
        assert threat_set.threats, name
        assert all(spec["kind"] for spec in threat_set.specs.values())


def test_scenarios_that_differ_only_in_their_attack_share_one_study():
    lfc = registry.names("lfc", headline_only=True)
    assert len(lfc) == 4 and robustness_scenarios(lfc) == lfc[:1]
    both = ["four_tank_bias", "robot_actuator_attack", "robot_actuator_attack_turning"]
    assert robustness_scenarios(both) == both  # the turning robot has other inputs


def test_unknown_threats_and_bad_specs_are_named(tmp_path):
    sc = registry.get("four_tank_bias")
    with pytest.raises(ValueError, match="unknown threat.*spoof.*valid: bias"):
        load_threat_set(sc, ["spoof"])
    # the command line's form, one name or several (a string had been read as its letters:
    # "unknown threat(s) b, i, a, s")
    assert list(load_threat_set(sc, "ramp").threats) == ["ramp"]
    assert list(load_threat_set(sc, "bias, ramp").threats) == ["bias", "ramp"]
    bad = tmp_path / "bad.yaml"
    bad.write_text("threats:\n  slow: {kind: ramp, slop: 1.0}\n")
    with pytest.raises(ValueError, match="threat 'slow'.*slop"):
        load_threat_set(sc, path=bad)
    late = tmp_path / "late.yaml"  # a threat that would never act is named, not run
    late.write_text("threats:\n  late: {kind: bias, value: 0.5, onset: 61}\n")
    with pytest.raises(
        ValueError, match=r"threat 'late': it starts at step 61, after the last step \(60\)"
    ):
        load_threat_set(sc.with_steps(60), path=late)
    assert load_threat_set(sc.with_steps(61), path=late).threats["late"].onset == 61


def test_a_study_scores_every_estimator_against_every_threat_at_the_calibrated_rate(tmp_path):
    sc = registry.get("four_tank_bias").with_steps(60)
    spec = tmp_path / "t.yaml"
    spec.write_text(
        "threats:\n  bias: {kind: bias, value: 0.5, onset: 21}\n"
        "  replay: {kind: replay, delay: 10, onset: 31}\n"
        "  tiny: {kind: bias, value: 0.001, onset: 21}\n"
    )
    threat_set = load_threat_set(sc, path=spec)
    assert isinstance(threat_set.threats["bias"], Bias)
    assert isinstance(threat_set.threats["replay"], Replay)
    threat_set.estimators = [*ESTIMATORS, "kf"]  # (kf: a linear model only, not run here)
    result = run_robustness(sc, threat_set, runs=20, progress=False)
    assert set(result.cells) == {"bias", "replay", "tiny"}
    for threat, row in result.cells.items():
        assert set(row) == set(ESTIMATORS), threat
    # a bias of 16 noise std is caught at once; one of 0.03 std is invisible and harmless
    for est in ESTIMATORS:
        assert result.cells["bias"][est]["tpr_at_far"] > 0.9
        assert result.cells["tiny"][est]["tpr_at_far"] < 0.05
        assert result.cells["tiny"][est]["state_error_ratio"] == pytest.approx(1.0, abs=0.02)
        assert result.cells["bias"][est]["state_error_ratio"] > 1.0
        worst = result.worst_case[est]
        assert worst["tpr_at_far"] == min(r[est]["tpr_at_far"] for r in result.cells.values())
        assert worst["tpr_at_far_threat"] in ("tiny", "replay")
    assert result.cells["bias"]["chi_square_ekf"]["state_error_ratio"] > 1.5  # gating ≠ undoing
    doc = write_robustness(tmp_path / "out", result)
    written = json.loads((tmp_path / "out" / "robustness.json").read_text())
    jsonschema.validate(written, metrics_schema())
    assert written["cells"] == json.loads(json.dumps(doc["cells"]))
    assert written["far"]["target"] == 0.01
    text = (tmp_path / "out" / "robustness.md").read_text()
    assert "tpr_at_far" in text and "| `cusum_ekf` |" in text
    assert "Not run on this scenario: `kf` (" in text  # (a trial found it in the JSON alone)
    # each threat's false-alarm rate (a threat-set trial found it in robustness.json only)
    fpr = text.split("## False-alarm rate under each threat")[1]
    row = next(line for line in fpr.splitlines() if line.startswith("| `cusum_ekf` |"))
    want = format_number(written["cells"]["bias"]["cusum_ekf"]["fpr_at_far"], 3)
    assert f"| {want} |" in row
    # the learned estimator against the best analytic, threat by threat, from the cells
    mine = written["acceptance"]["pf_nn_grad"]
    analytic = ("chi_square_ekf", "cusum_ekf")  # the study's analytic estimators
    for threat, row in result.cells.items():
        best = min(row[n]["state_rmse"] for n in analytic)
        assert mine["state"][threat]["best"] == pytest.approx(best)
        assert mine["state"][threat]["holds"] == (row["pf_nn_grad"]["state_rmse"] <= 1.1 * best)
        interval = mine["state"][threat]["interval"]  # the ratio over resampled runs
        assert interval["estimate"] == pytest.approx(mine["state"][threat]["ratio"], rel=1e-9)
        assert interval["low"] <= interval["high"] and 0.0 <= interval["holds_share"] <= 1.0
    worst = {n: min(r[n]["tpr_at_far"] for r in result.cells.values()) for n in analytic}
    assert mine["best_analytic_worst_tpr"][0] == pytest.approx(max(worst.values()))
    gap = mine["worst_tpr_interval"]  # the worst cases again in every resample of the runs
    assert gap["estimate"] == pytest.approx(mine["worst_tpr"][0] - max(worst.values()), abs=1e-12)
    assert gap["low"] <= gap["high"] and "it holds in" in text
    assert mine["tpr_holds"] == (
        result.worst_case["pf_nn_grad"]["tpr_at_far"] >= max(worst.values())
    )
    assert "## `pf_nn_grad` against the best analytic over the threats" in text
    # the shipped card: trained on the scenario's eq. (4) attack alone, so every threat is new
    assert mine["training"] == {"trained_on": "its scenario's attack", "adversarial": False,
                                "threats": dict.fromkeys(result.cells, "held out")}  # fmt: skip
    assert "- Trained on its scenario's attack:" in text and "| held out |" in text
    unseen = max(worst.values()) <= 2 * 0.01  # the worst threat inside the false-alarm band
    assert mine["worst_threat_undetected"] is unseen
    assert ("compares false-alarm rates on it" in text) is unseen
    assert (tmp_path / "out" / "robustness.png").stat().st_size > 10_000


def test_the_cli_runs_the_study_and_names_an_unknown_threat(tmp_path, capsys):
    assert main(["four_tank_bias", "--threats", "spoof", "--out", str(tmp_path)]) == 2
    assert "valid: bias" in capsys.readouterr().err
    args = ["four_tank_bias", "--threats", "bias,ramp", "--runs", "4", "--out", str(tmp_path),
            "--no-progress"]  # fmt: skip
    # an evaluation's verdicts in this --out: they go with its leaderboard, and now say so
    (tmp_path / "acceptance.md").write_text("# an evaluation's acceptance\n")
    assert main(args) == 0
    assert not (tmp_path / "acceptance.md").exists()
    assert "the evaluation's acceptance.md went with the leaderboard" in capsys.readouterr().out
    doc = json.loads((tmp_path / "four_tank_bias" / "robustness.json").read_text())
    assert list(doc["threats"]) == ["bias", "ramp"]
    board = (tmp_path / "leaderboard.md").read_text()
    assert "worst_tpr_at_far" in board and "worst_state_error_ratio" in board
    summary = (tmp_path / "robustness.md").read_text()
    assert "worst tpr_at_far" in summary
    # the learned estimator's robustness verdict, with how sure, across the scenarios
    mine = doc["acceptance"]["pf_nn_grad"]
    section = summary.split("## Learned against the best analytic over the threats")[1]
    row = next(
        line for line in section.splitlines() if line.startswith("| four_tank_bias | `pf_nn_grad`")
    )
    cells = [c.strip() for c in row.split("|")]
    checks = mine["state"].values()
    # open_loop_pf reads no measurement: where it sets a threat's bar (the ramp drags every
    # filter that reads the sensors), the best analytic that reads them is named beside it
    assert doc["reads_no_measurements"] == ["open_loop_pf"]
    for c in checks:
        blind = c["best_estimator"] == "open_loop_pf"
        assert c.get("best_reads_no_measurements", False) is blind
        if blind:
            assert c["best_reading_estimator"] != "open_loop_pf"
            assert c["best_reading"] >= c["best"]
            assert c["ratio_reading"] == pytest.approx(c["value"] / c["best_reading"])
            assert c["holds_reading"] == (c["value"] <= 1.1 * c["best_reading"])
    within = [c["value"] <= 1.1 * c.get("best_reading", c["best"]) for c in checks]
    readers = (f" ({sum(within)} within the best that reads the sensors)"
               if any(c.get("best_reads_no_measurements") for c in checks) else "")  # fmt: skip
    assert cells[4] == f"{sum(c['holds'] for c in checks)} of 2" + readers
    assert cells[6] == ("holds" if mine["holds"] else "**fails**")
    unseen = mine["worst_threat_undetected"]  # said in the row and under the table
    assert ("worst threat undetected†" in cells[3]) is unseen
    assert ("† No analytic detector sees the worst threat" in section) is unseen


def test_a_stealthy_threat_is_data_crafted_when_the_study_runs():
    from difffilter.eval.stealthy import StealthySpec

    threat_set = load_threat_set(registry.get("four_tank_bias"), ["stealthy_chi_square"])
    spec = threat_set.threats["stealthy_chi_square"]
    assert isinstance(spec, StealthySpec) and spec.against == "chi_square_ekf"
    assert spec.onset == 21 and spec.settings.iterations == 250
    with pytest.raises(ValueError, match="no field.*target.*valid"):
        StealthySpec.from_dict({"kind": "stealthy", "target": "x"})
    # named when the set loads (a trial's entries failed after the calibration had run,
    # as "runs must be an integer >= 1", naming neither the threat nor the field)
    for change, why in (({"onset": 0}, "onset must be an integer >= 1; got 0"),
                        ({"train_runs": 0}, "train_runs must be an integer >= 1"),
                        ({"against": "nope"}, "against must be a detector .*chi_square_ekf"),
                        ({"entries": ["a"]}, "entries must be a list of measurement indices")):  # fmt: skip
        with pytest.raises(ValueError, match=why):
            StealthySpec.from_dict({"kind": "stealthy", **change})
    with pytest.raises(ValueError, match=r"entries \[9\] name entries beyond the 4 measurements"):
        StealthySpec.from_dict({"kind": "stealthy", "entries": [9]}).check_fits(
            registry.get("four_tank_bias").system()
        )


def test_a_random_threat_meets_every_lfc_estimator_with_the_same_draws():
    """Every LFC estimator runs its own closed loop: a random threat (a random walk on a
    random half of the runs) must draw the same values in each, from the study's seed."""
    threat = RandomWalk(0.02, entries=(2,), onset=5, share=0.5)
    sc = registry.get("lfc_step").with_steps(40).with_threat(threat)

    def draws(seed):
        streams = Streams(seed)
        return sc.exogenous(8, {k: streams(k) for k in ("plant", "attack")})

    first = sc.loop(KalmanFilter(), draws(0)).trajectories
    torch.manual_seed(123)  # the global generator must not matter
    again = sc.loop(KalmanFilter(), draws(0)).trajectories
    other = sc.loop(KalmanFilter(), draws(1)).trajectories
    assert torch.equal(first.info["attack_values"], again.info["attack_values"])
    assert torch.equal(first.flags, again.flags) and 0 < int(first.flags.any(-1).sum()) < 8
    assert not torch.equal(first.info["attack_values"], other.info["attack_values"])


def test_a_crafted_threat_against_an_estimator_that_does_not_run_says_why(tmp_path):
    """A trial's threat set listed its target among the estimators, and the error said to
    add it there: the target had been skipped (no checkpoint of its kind)."""
    from difffilter.eval.robustness import run_robustness

    spec = tmp_path / "set.yaml"
    spec.write_text("estimators: [chi_square_ekf, gaussian_nn_grad]\nthreats:\n"
                    "  crafted: {kind: stealthy, against: gaussian_nn_grad, onset: 5}\n")  # fmt: skip
    sc = registry.get("four_tank_bias").with_steps(10)
    with pytest.raises(ValueError, match=r"threat 'crafted' is crafted against "
                       r"'gaussian_nn_grad', which does not run in this study: the checkpoint "
                       r"was trained with filter 'pf'"):  # fmt: skip
        run_robustness(sc, load_threat_set(sc, path=spec), runs=2, progress=False)


def test_a_crafted_attack_is_kept_in_robustness_json_and_judged_the_same_again(tmp_path):
    """A trial had to craft the study's attack anew to judge it on other runs: its values
    and onset are in robustness.json, and the attack rebuilt from them meets the study's
    detector on the study's runs with the same rate and error."""
    import json

    from difffilter.eval.robustness import run_robustness, write_robustness
    from difffilter.eval.suite import run_suite
    from difffilter.stealthy import CraftedAttack

    spec = tmp_path / "set.yaml"
    spec.write_text("estimators: [chi_square_ekf]\nthreats:\n  crafted: {kind: stealthy, "
                    "against: chi_square_ekf, onset: 5, iterations: 3, train_runs: 4, "
                    "selection_runs: 4}\n")  # fmt: skip
    sc = registry.get("four_tank_bias").with_steps(12)
    # (enough calibration steps that the threshold alarms: a review found tpr_at_far 0 on
    # both sides at 4 runs, so only the state error was compared)
    result = run_robustness(sc, load_threat_set(sc, path=spec), runs=8, calibration_runs=40,
                            progress=False)  # fmt: skip
    write_robustness(tmp_path / "out", result)
    kept = json.loads((tmp_path / "out" / "robustness.json").read_text())["stealthy"]["crafted"]
    values = torch.tensor(kept["values"], dtype=torch.float64)
    assert values.shape == (12, 4) and kept["onset"] == 5 and bool(values[:4].eq(0).all())
    assert bool(values[4:].ne(0).any())  # an attack was chosen
    again = run_suite(sc.with_threat(CraftedAttack(values, kept["onset"])), runs=8, seed=0,
                      estimators=["chi_square_ekf"], calibration=result.calibration,
                      progress=False)  # fmt: skip
    cell = result.cells["crafted"]["chi_square_ekf"]
    assert cell["tpr_at_far"] > 0  # a rate that can differ
    for key in ("tpr_at_far", "fpr_at_far", "state_rmse"):
        assert again.metrics["chi_square_ekf"][key] == pytest.approx(cell[key], rel=1e-12), key


_PEEKING = '''
import torch
from difffilter.attack import Attack, Channel


class Peeking(Attack):
    """Adds the estimator's last mean to the measurement (reads the view)."""

    channel = Channel.SENSOR
    reads_view = True

    def init(self, batch_shape, num_steps, dim, generator=None, *, dtype, device=None):
        return None

    def step(self, state, k, *, y=None, x=None, u=None, view=None):
        value = torch.zeros_like(y) if view is None else view.mean[..., : y.shape[-1]]
        return state, value, torch.full(y.shape[:-1], view is not None)
'''


def test_an_adaptive_threat_on_an_open_loop_scenario_is_refused_before_anything_runs(
    tmp_path, monkeypatch
):
    """A threat that reads the estimator's output cannot act on a scenario simulated once
    for every estimator: the threat set naming it is refused when read, and a ThreatSet
    built in Python before the calibration (a trial's third threat was refused only after
    the calibration and two threats had run)."""
    import difffilter.eval.robustness as robustness

    (tmp_path / "peeking_attack.py").write_text(_PEEKING)
    monkeypatch.syspath_prepend(str(tmp_path))
    sc = registry.get("four_tank_bias")
    path = tmp_path / "set.yaml"
    path.write_text("threats:\n  bias: {kind: bias, value: 0.5}\n"
                    "  peek: {kind: 'peeking_attack:Peeking'}\n")  # fmt: skip
    with pytest.raises(ValueError, match=r"threat 'peek': attack Peeking reads the estimator's"):
        load_threat_set(sc, path=path)
    assert list(load_threat_set(sc, "bias", path=path).threats) == ["bias"]

    from peeking_attack import Peeking

    def no_calibration(*args, **kwargs):
        raise AssertionError("calibrated before refusing the threat")

    monkeypatch.setattr(robustness, "calibrate", no_calibration)
    threats = robustness.ThreatSet({"bias": Bias(value=0.5), "peek": Peeking()})
    with pytest.raises(ValueError, match=r"threat 'peek': attack Peeking reads the estimator's"):
        robustness.run_robustness(sc, threats, runs=2, progress=False)


@pytest.mark.filterwarnings("ignore:Below the 1 % target")  # 2 runs of 40 steps calibrate
def test_the_report_marks_an_adaptive_threat(tmp_path, monkeypatch):
    """On a closed-loop scenario an adaptive threat runs, and robustness.json and .md say
    which threats read the estimator's output (as they say which read the true state)."""
    (tmp_path / "peeking_attack.py").write_text(_PEEKING)
    monkeypatch.syspath_prepend(str(tmp_path))
    from peeking_attack import Peeking

    sc = registry.get("lfc_step").with_steps(40)
    threats = ThreatSet({"peek": Peeking(), "bias": Bias(value=0.05, onset=10)}, runs=2,
                        estimators=("chi_square_kf",))  # fmt: skip
    doc = write_robustness(tmp_path / "out", run_robustness(sc, threats, progress=False))
    assert doc["threat_reads_view"] == {"peek": True, "bias": False}
    assert doc["threat_reads_state"] == {"peek": True, "bias": False}
    text = (tmp_path / "out" / "robustness.md").read_text()
    (peek,) = [line for line in text.splitlines() if line.startswith("- `peek`")]
    (bias,) = [line for line in text.splitlines() if line.startswith("- `bias`")]
    assert "adaptive: reads each estimator's last output" in peek
    assert "adaptive" not in bias and "insider" not in bias
