"""Mutation review of the leaderboard (eval/leaderboard.py), the ``predict`` writer
(train/predictions.py) and the LFC tuning record (train/lfc_tuning.py): each test checks
the code against a truth built independently of it (a row or colour recomputed by hand
from the module docstring's rule, tensors handed to the writer, a record's fields read
from its docstring)."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from difffilter.attack import Channel
from difffilter.eval import leaderboard
from difffilter.eval.leaderboard import COLUMNS, cell_goodness, leaderboard_rows, write_leaderboard

# ------------------------------------------------------------------------- leaderboard


def _doc(entries, **extra):
    """A metrics.json of ``{estimator: {metric: value}}`` and the fields of ``extra``."""
    return {"estimators": entries, "checkpoint": None} | extra


def test_the_columns_are_the_headline_metrics_with_the_calibrated_rates_in_place():
    """The columns of the module docstring, written out by hand: the headline metrics
    without the per-scenario vs-attack-free RMSE, the ROC's TPR followed by the calibrated
    TPR and FPR, and the delay at the calibrated threshold in place of the own-alarm one."""
    assert COLUMNS == ("attack_rmse", "auc", "tpr_at_1pct_fpr", "tpr_at_far", "fpr_at_far",
                       "detection_delay_at_far_s", "state_rmse", "time_per_step_s")  # fmt: skip


def test_a_row_holds_its_own_checkpoint_units_target_step_and_zero_values():
    """Each row against the metrics.json it was built from: an estimator's own ``--ckpt
    NAME=PATH`` file gives its checkpoint (the first 12 hex digits of its sha256), the
    attack unit is the study's attack unit (not its state unit), the false-alarm target
    and ``dt_s`` are carried, and a value of 0 stays 0 (not missing)."""
    own = {"net": {"sha256": "0123456789abcdef" * 4, "path": "mine.ckpt"}}
    shared = {"sha256": "fedcba9876543210" * 4, "used_by": ["pf"]}
    doc = _doc({"net": {"detection_delay_at_far_s": 0.0, "auc": 0.75}, "kf": {}, "pf": {}},
               checkpoints=own, checkpoint=shared, scenario_units={"state": "cm", "attack": "V"},
               far={"target": 0.005}, dt_s=0.25)  # fmt: skip
    rows = {r["estimator"]: r for r in leaderboard_rows({"tank": doc})}
    assert rows["net"]["checkpoint"] == "0123456789ab" and rows["kf"]["checkpoint"] is None
    assert rows["pf"]["checkpoint"] == "fedcba987654"  # the shared file, used by pf
    assert rows["net"]["units"] == {"state": "cm", "attack": "V"}
    assert rows["net"]["far_target"] == 0.005 and rows["net"]["dt_s"] == 0.25
    assert rows["net"]["detection_delay_at_far_s"] == 0.0 and rows["net"]["auc"] == 0.75
    assert rows["kf"]["auc"] is None


def test_units_that_differ_on_one_side_only_are_given_per_row(tmp_path):
    """Two scenarios sharing the state unit but not the attack unit: the attack column has
    no single unit, so each row says its units (the header rule: one unit per column only
    where every scenario shares it)."""
    results = {"a": _doc({"kf": {"state_rmse": 1.0}}, scenario_units={"state": "cm", "attack": "V"}),
               "b": _doc({"kf": {"state_rmse": 2.0}}, scenario_units={"state": "cm", "attack": "A"})}  # fmt: skip
    md = write_leaderboard(tmp_path, results).read_text()
    assert "units (state; attack)" in md and "| a | `kf` | cm; V |" in md
    assert "| b | `kf` | cm; A |" in md and "state_rmse [cm]" in md


def test_a_robustness_study_keeps_its_worst_case_and_detection_columns_with_a_value(tmp_path):
    """A robustness study whose worst case lists one of its estimators and whose one row has
    a detection value: the worst-case columns are there (some row has them), a column that
    any row fills is kept, and a diverged worst case reads ``diverged`` in its cell."""
    drawn = {}
    study = _doc({"kf": {"state_rmse": 0.5, "tpr_at_far": 0.4}, "net": {"state_rmse": 0.7}},
                 worst_case={"kf": {"tpr_at_far": 0.3, "state_error_ratio": None,
                                    "state_error_ratio_diverged": True}})  # fmt: skip
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(leaderboard, "_heatmaps", lambda path, rows, units: drawn.update(units))
        md = write_leaderboard(tmp_path, {"tank": study}).read_text()
    assert list(drawn) == ["tpr_at_far", "state_rmse", "worst_tpr_at_far",
                           "worst_state_error_ratio"]  # fmt: skip
    kf = next(line for line in md.splitlines() if line.startswith("| tank | `kf` |"))
    assert kf.rstrip(" |").endswith("| diverged")


def test_every_skipped_estimator_is_listed(tmp_path):
    """Two estimators a scenario left out: both lines, with their reasons."""
    results = {"s": _doc({"kf": {"state_rmse": 1.0}}, skipped={"a": "why a", "b": "why b"})}
    md = write_leaderboard(tmp_path, results).read_text()
    assert "- s: `a` (why a)\n- s: `b` (why b)\n" in md


def test_an_empty_leaderboard_removes_an_earlier_figure(tmp_path):
    """A leaderboard of no rows written over one with rows: the earlier figure is removed
    (its markdown says no estimator ran, so no figure may remain beside it)."""
    write_leaderboard(tmp_path, {"s": _doc({"kf": {"state_rmse": 1.0}})})
    assert (tmp_path / "leaderboard.png").is_file()
    write_leaderboard(tmp_path, {"s": _doc({})})
    assert not (tmp_path / "leaderboard.png").exists()


def test_the_figure_gets_missing_as_nan_diverged_as_inf_and_the_roles_ranked(tmp_path):
    """What the figure's colouring receives, against the rows built by hand: a missing value
    is NaN (not 0), a diverged worst case +inf, and only the rows neither oracle nor
    reference are ranked; the TensorBoard row carries the checkpoint's short sha256."""
    seen, sessions = {}, {}

    def spy(grid, scenarios, columns, ranked, targets, steps_s, off_band=None):
        seen.update(grid=grid.copy(), columns=list(columns), ranked=ranked.tolist())
        return np.full_like(grid, np.nan)

    ckpt = {"sha256": "ab" * 32, "used_by": ["net"]}
    study = _doc({"oracle": {"state_rmse": 1.0}, "ref": {"state_rmse": 2.0},
                  "net": {"state_rmse": 3.0}},
                 checkpoint=ckpt, estimator_roles={"oracle": "oracle", "ref": "reference"},
                 worst_case={n: {"state_error_ratio": 2.0, "tpr_at_far": 0.5}
                             for n in ("oracle", "ref")}
                 | {"net": {"state_error_ratio": None, "state_error_ratio_diverged": True,
                            "tpr_at_far": None}})  # fmt: skip
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(leaderboard, "cell_goodness", spy)
        mp.setattr(
            "difffilter.eval.tensorboard.add_session",
            lambda w, run, hparams, metrics: sessions.update({run: hparams}),
        )
        write_leaderboard(tmp_path, {"tank": study})
    col = {m: i for i, m in enumerate(seen["columns"])}
    assert seen["ranked"] == [False, False, True]
    assert np.isposinf(seen["grid"][2, col["worst_state_error_ratio"]])
    assert np.isnan(seen["grid"][2, col["worst_tpr_at_far"]])
    assert sessions["tank/net"] == {"scenario": "tank", "estimator": "net", "checkpoint": "ab" * 6}
    assert sessions["tank/ref"]["checkpoint"] == "none"


def test_colours_against_a_hand_evaluation_of_the_docstring_rule():
    """``cell_goodness`` against the docstring's formulas evaluated in float64 by hand: the
    floor is 5 % of the scenario's largest value (an unranked row's included), the false-
    alarm band's lower edge is α/2, a worst-case TPR no one lifts above 2α is uncoloured,
    a scenario without a recorded target falls back to 0.02, and −inf is no divergence."""
    # floor from all rows: the unranked oracle's 10 is the largest, f = 0.5; best 1
    g = np.array([[10.0], [1.0], [2.0]])
    good = cell_goodness(g, ["s"] * 3, ["state_rmse"], ranked=np.array([False, True, True]))
    f = 0.05 * 10.0
    hand = [1 - math.log10((v + f) / (1 + f)) for v in (10.0, 1.0, 2.0)]
    assert good[:, 0] == pytest.approx(hand, abs=1e-12)
    # below the band [α/2, 2α]: 1 − log10((α/2)/v)
    v = np.array([[0.004], [0.0025]])
    good = cell_goodness(v, ["s"] * 2, ["fpr_at_far"], targets=np.full(2, 0.01))[:, 0]
    assert good == pytest.approx([1 - math.log10(0.005 / 0.004), 1 - math.log10(2.0)], abs=1e-12)
    # a worst-case detection rate whose best (0.015) is below 2α = 0.02: no colour
    w = np.array([[0.015], [0.0]])
    assert np.isnan(
        cell_goodness(w, ["s"] * 2, ["worst_tpr_at_far"], targets=np.full(2, 0.01))
    ).all()
    # no target at all: the band is 0.02, so a best of 0.015 is uncoloured
    assert np.isnan(cell_goodness(w, ["s"] * 2, ["tpr_at_far"])).all()
    # no finite target: the band is 0.02, so a best of 0.5 is coloured by 1 − (best − v)/0.1
    t = np.array([[0.5], [0.45]])
    good = cell_goodness(t, ["s"] * 2, ["tpr_at_far"], targets=np.full(2, np.nan))[:, 0]
    assert good == pytest.approx([1.0, 0.5], abs=1e-12)
    # −inf in a lower-is-better column is not a diverged (red) cell
    assert np.isnan(cell_goodness(np.array([[-np.inf], [1.0]]), ["s"] * 2, ["state_rmse"])[0, 0])


# ------------------------------------------------------------------------- predictions


class _Trainer:
    def __init__(self, log_dir, dm):
        self.log_dir, self.datamodule = str(log_dir), dm


class _Module:
    """What the writer reads of the module: the data's scenario (a shorter horizon of the
    configured one, here with another dt), the threshold and the channel."""

    def __init__(self):
        self.scenario = SimpleNamespace(name="configured", dt=9.0)
        self.alarm_threshold = torch.tensor(0.25, dtype=torch.float64)
        self.channel = Channel.ACTUATOR

    def scenario_of_data(self):
        return SimpleNamespace(name="of_data", dt=0.5)


def _prediction(gen, B, T, dx=3, da=2, grad=False):
    p = torch.rand(B, T, generator=gen, dtype=torch.float64)
    means = torch.randn(B, T, dx, generator=gen, dtype=torch.float64).requires_grad_(grad)
    return {"means": means * 2 if grad else means,
            "attack_estimate": torch.randn(B, T, da, generator=gen, dtype=torch.float64),
            "attack_probability": p, "alarms": p > 0.25, "extra": torch.zeros(1)}  # fmt: skip


def test_the_writer_saves_each_batch_and_the_index_of_the_module_docstring(
    tmp_path, monkeypatch, capsys
):
    """Two batches of B×T = 2×5 and 3×5 handed to the writer: ``batch_00000.pt`` and
    ``batch_00001.pt`` under ``<log_dir>/predictions`` hold exactly those tensors (the four
    fields only, detached), and the index holds the data's scenario and dt, the threshold,
    the channel's name, the data module's ``test_seed`` and per file its runs and steps."""
    from difffilter.train.predictions import FIELDS, PredictionFiles

    monkeypatch.chdir(tmp_path)  # a writer that ignored log_dir would write ./predictions
    gen = torch.Generator().manual_seed(3)
    batches = [_prediction(gen, 2, 5, grad=True), _prediction(gen, 3, 5)]
    dm = SimpleNamespace(hparams={"test_seed": 7, "seed": 1})
    trainer, module, writer = _Trainer(tmp_path / "logs", dm), _Module(), PredictionFiles()
    for i, p in enumerate(batches):
        writer.write_on_batch_end(trainer, module, p, None, None, i, 0)
    writer.on_predict_end(trainer, module)
    folder = tmp_path / "logs" / "predictions"
    for i, p in enumerate(batches):
        saved = torch.load(folder / f"batch_{i:05d}.pt", weights_only=True)
        assert set(saved) == set(FIELDS)
        for k in FIELDS:
            assert torch.equal(saved[k], p[k].detach()) and not saved[k].requires_grad
    index = json.loads((folder / "predictions.json").read_text())
    assert index["scenario"] == "of_data" and index["dt_s"] == 0.5 and index["threshold"] == 0.25
    assert index["channel"] == "actuator" and index["seed"] == 7
    assert index["files"] == [{"file": "batch_00000.pt", "runs": 2, "steps": 5},
                              {"file": "batch_00001.pt", "runs": 3, "steps": 5}]  # fmt: skip
    assert "predictions of 5 runs" in capsys.readouterr().out


def test_no_batch_writes_no_index(tmp_path):
    """A predict run of no batch writes no ``predictions.json`` (it would index nothing)."""
    from difffilter.train.predictions import PredictionFiles

    writer = PredictionFiles(tmp_path / "p")
    writer.on_predict_end(_Trainer(tmp_path, None), _Module())
    assert not (tmp_path / "p" / "predictions.json").exists()


# ------------------------------------------------------------------------- LFC tuning


def test_score_is_the_rmse_of_the_docstring_evaluated_by_hand(monkeypatch):
    """``score`` on a stand-in loop against numpy: the attack RMSE over all channels and
    steps, the RMSE over the attacked entries (negative attacks too), the RMSE of state 5
    (index 4), the init stream seeded with ``init_seed``; a NaN estimate scores ``inf``."""
    from difffilter.train import lfc_tuning

    gen = torch.Generator().manual_seed(11)
    attack = torch.randn(2, 6, 3, generator=gen, dtype=torch.float64)
    attack[attack.abs() < 0.5] = 0.0
    estimate = torch.randn(2, 6, 3, generator=gen, dtype=torch.float64)
    x = torch.randn(2, 6, 7, generator=gen, dtype=torch.float64)
    seeds = []

    def loop(estimator, batch, generator):
        seeds.append(generator.init.initial_seed())
        return SimpleNamespace(output=SimpleNamespace(attack=estimator),
                               trajectories=SimpleNamespace(x=x))  # fmt: skip

    monkeypatch.setattr(lfc_tuning.registry, "get", lambda name: SimpleNamespace(loop=loop))
    res = lfc_tuning.score(estimate, {"attack": attack}, init_seed=5)
    a, e = attack.numpy(), estimate.numpy()
    assert res["attack_rmse"] == pytest.approx(np.sqrt(np.mean((e - a) ** 2)), rel=1e-12)
    on = a != 0
    assert (a < 0).any() and res["attack_rmse_attacked"] == pytest.approx(
        np.sqrt(np.mean((e[on] - a[on]) ** 2)), rel=1e-12
    )
    assert res["state5_rmse"] == pytest.approx(np.sqrt(np.mean(x.numpy()[..., 4] ** 2)), rel=1e-12)
    assert seeds == [5]
    estimate[0, 0, 0] = float("nan")
    assert lfc_tuning.score(estimate, {"attack": attack})["attack_rmse"] == math.inf


def test_tune_scores_every_grid_point_and_chooses_the_least_rmse(monkeypatch):
    """``tune`` on a stand-in grid whose scores are a known function of the setting: one
    row per point of the product (setting and scores), the chosen setting is the argmin
    found by hand, with its RMSE, and the validation record names the seed the batch was
    drawn from."""
    from difffilter.train import lfc_tuning

    calls = []
    monkeypatch.setattr(lfc_tuning, "GRIDS", {"traditional_ad": {"a": [1, 2, 3], "b": ["x", "y"]}})
    batch = {"attack": torch.zeros(3, 7, 10)}  # a stand-in batch of 7 steps
    monkeypatch.setattr(lfc_tuning, "validation_batch", lambda runs, seed=lfc_tuning.VALIDATION_SEED:
                        calls.append((runs, seed)) or batch)  # fmt: skip
    monkeypatch.setattr(lfc_tuning, "_estimator", lambda name, setting, ctx, ck: dict(setting))
    rmse = {
        (1, "x"): 3.0,
        (1, "y"): 2.0,
        (2, "x"): 0.5,
        (2, "y"): 4.0,
        (3, "x"): 1.0,
        (3, "y"): 9.0,
    }
    monkeypatch.setattr(lfc_tuning, "score", lambda est, batch: {"attack_rmse": rmse[est["a"], est["b"]],
                                                               "wall_s": 0.0})  # fmt: skip
    out = lfc_tuning.tune(("traditional_ad",), runs=3, progress=False)
    rows = out["grids"]["traditional_ad"]
    assert [(r["a"], r["b"], r["attack_rmse"]) for r in rows] == [(*k, v) for k, v in rmse.items()]
    assert out["chosen"]["traditional_ad"] == {"a": 2, "b": "x", "attack_rmse": 0.5}
    assert out["validation"]["runs"] == 3 and calls == [(3, out["validation"]["seed"])]
    assert out["validation"]["steps"] == 7  # the batch's horizon, not a constant
    with pytest.raises(ValueError, match="--ckpt"):
        lfc_tuning.tune(("kf_nn_grad_ekf",), progress=False)


def test_the_estimator_of_a_grid_point_gets_its_settings(monkeypatch):
    """``_estimator`` translates a grid point into the rule's and the estimator's arguments:
    the learning rate reaches the gradient rule, ``subtract: prior`` turns ``posterior``
    off, the process noise reaches the EKF rule."""
    from difffilter.train import lfc_tuning

    made = []
    monkeypatch.setattr(lfc_tuning, "lfc_estimator", lambda ctx, **kw: made.append(kw) or kw)
    monkeypatch.setattr(lfc_tuning, "paper_network", lambda s: ("net", s))
    monkeypatch.setattr(lfc_tuning, "GradientRule", lambda **kw: ("gd", kw))
    monkeypatch.setattr(lfc_tuning, "EKFRule", lambda **kw: ("ekf", kw))
    kw = lfc_tuning._estimator("traditional_ad", {"init_scale": 0.1, "lr": 0.123,
                                                   "luenberger_design": "modal"}, None, None)  # fmt: skip
    assert kw["rule"][1]["lr"] == 0.123 and kw["init_scale"] == 0.1
    kw = lfc_tuning._estimator("kf_nn_ekf", {"init_scale": 1.0, "process_noise": 1e-5,
                                              "subtract": "prior"}, None, None)  # fmt: skip
    assert kw["posterior"] is False and kw["rule"][1]["process_noise"] == 1e-5
    kw = lfc_tuning._estimator("kf_nn_ekf", {"init_scale": 1.0, "process_noise": 0.0,
                                              "subtract": "posterior"}, None, None)  # fmt: skip
    assert kw["posterior"] is True


def test_main_writes_the_validation_and_the_fixed_ekf_settings_and_checks_runs(
    monkeypatch, tmp_path, capsys
):
    """The record ``main`` writes over an older one: this run's validation replaces the
    old, ``ekf_fixed`` holds the EKF settings that are not searched (every default but the
    process noise, a grid axis); ``--runs`` defaults to the docstring's 16, and ``--runs 0``
    is refused."""
    from difffilter.models.lfc_estimators import EKF_DEFAULTS
    from difffilter.train import lfc_tuning

    out = tmp_path / "t.json"
    out.write_text(json.dumps({"validation": {"runs": 99}, "grids": {}, "chosen": {}}))
    monkeypatch.setattr(lfc_tuning, "tune", lambda estimators, runs, ckpt: {
        "grids": {}, "chosen": {}, "validation": {"runs": runs}})  # fmt: skip
    lfc_tuning.main(["--out", str(out)])
    assert json.loads(out.read_text())["validation"] == {"runs": 16}  # the docstring's --runs 16
    lfc_tuning.main(["--runs", "2", "--out", str(out)])
    record = json.loads(out.read_text())
    assert record["validation"] == {"runs": 2}
    expected = dict(EKF_DEFAULTS)
    del expected["process_noise"]
    assert record["ekf_fixed"] == expected and expected
    with pytest.raises(SystemExit):
        lfc_tuning.main(["--runs", "0", "--out", str(out)])


def test_a_diverged_worst_case_is_null_in_strict_json(tmp_path):
    """A review: a diverged worst case (inf in the rows, where the heatmap paints it) was
    written as the bare token ``Infinity``, which strict JSON readers refuse; the file
    parses with non-finite constants refused, the value is null and its
    ``worst_<metric>_diverged`` says why (as robustness.json writes it)."""
    import json

    from difffilter.eval.leaderboard import write_leaderboard

    doc = {"estimators": {"kf": {"state_rmse": 1.0}},
           "worst_case": {"kf": {"state_error_ratio": None,
                                 "state_error_ratio_diverged": True}}}  # fmt: skip
    write_leaderboard(tmp_path, {"s": doc})

    def refuse(constant):
        raise ValueError(f"non-finite constant {constant} in leaderboard.json")

    rows = json.loads((tmp_path / "leaderboard.json").read_text(), parse_constant=refuse)
    assert rows[0]["worst_state_error_ratio"] is None
    assert rows[0]["worst_state_error_ratio_diverged"] is True
