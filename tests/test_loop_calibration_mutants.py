"""Mutation review of the closed loop, the false-alarm calibration and the leaderboard.

Each test checks numbers against an independent truth: a hand-written numpy loop of a
one-state closed-loop system, an order statistic and counts worked out by hand on a small
list of scores, or a leaderboard's colours read back against the metrics it was made of.
"""

from __future__ import annotations

import json
import math
import types
import warnings

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter.eval import calibration as cal_mod
from difffilter.eval.leaderboard import COLUMNS
from difffilter.loop import ReplayedNoise, StateFeedback, closed_loop
from difffilter.models.attacks import Signal

A, BU, Q, R, M0, P0 = 0.9, 0.5, 0.01, 0.04, 0.2, 1.0
COLUMNS_INDEX = {m: i for i, m in enumerate(COLUMNS)}


def _scalar_plant():
    def t(v):
        return torch.tensor([[v]], dtype=torch.float64)

    return df.LinearGaussianModel(
        t(A), t(1.0), t(Q), t(R), torch.tensor([M0], dtype=torch.float64), t(P0), B=t(BU)
    )


class _MeanAndMeasurement:
    """``u_k = −0.6 x̂_k − 0.3 ỹ_k``: reads the estimate and the received measurement."""

    def init(self, batch_shape, dtype, device):
        return torch.zeros(*batch_shape, 1, dtype=dtype, device=device)

    def __call__(self, k, y, out):
        return -0.6 * out.mean - 0.3 * y


def _numpy_loop(x0, w, v, sensor, actuator, mask, control):
    """The scalar closed loop by hand: x_k = A x_{k−1} + B (u_{k−1} + a^u_k) + w_k,
    y_k = x_k + v_k, ỹ_k = y_k + a^y_k, a Kalman filter that knows u_{k−1} (not the attack)
    and skips lost measurements, u_k = control(x̂_k, ỹ_k)."""
    runs, steps = w.shape
    rec = {key: np.zeros((runs, steps)) for key in ("x", "y", "recv", "mean", "u")}
    for b in range(runs):
        x, u, m, p = x0[b], 0.0, M0, P0
        for t in range(steps):
            x = A * x + BU * (u + actuator[t]) + w[b, t]
            y = x + v[b, t]
            recv = y + sensor[t]
            mp, pp = A * m + BU * u, A * A * p + Q
            if mask[b, t]:
                gain = pp / (pp + R)
                m, p = mp + gain * (recv - mp), (1 - gain) * pp
            else:
                m, p = mp, pp
            for key, val in (("x", x), ("y", y), ("recv", recv), ("mean", m), ("u", u)):
                rec[key][b, t] = val
            u = control(m, recv)
    return rec


def _noise(runs, steps, seed=0):
    g = torch.Generator().manual_seed(seed)
    w = 0.1 * torch.randn(runs, steps, 1, generator=g, dtype=torch.float64)
    v = 0.2 * torch.randn(runs, steps, 1, generator=g, dtype=torch.float64)
    return w, v


def test_sensor_attack_under_a_schedule_matches_a_numpy_closed_loop():
    """A sensor attack on steps 3–5, a schedule that loses run 0's step 4 and run 1's step
    6, a controller reading x̂_k and ỹ_k: states, received measurements, estimates, the
    inputs known (u_{k−1}), the recorded attack (zero where the packet was lost) and the
    flags equal a hand-written numpy loop. Kills: the attack stepped at k − 1, the controller
    reading the true y, the schedule row off by one, an attack or flag not masked by a lost
    packet."""
    T, runs = 8, 2
    w, v = _noise(runs, T)
    alpha = torch.zeros(T, 1, dtype=torch.float64)
    alpha[2:5, 0] = torch.tensor([1.0, -2.0, 3.0])
    mask = torch.ones(runs, T, 1, dtype=torch.bool)
    mask[0, 3, 0] = False
    mask[1, 5, 0] = False
    x0 = torch.tensor([[0.5], [-1.0]], dtype=torch.float64)
    res = closed_loop(_scalar_plant(), T, noise=ReplayedNoise(w, v), x0=x0,
                      estimator=df.KalmanFilter(), controller=_MeanAndMeasurement(),
                      attack=Signal(alpha), mask=mask)  # fmt: skip
    ref = _numpy_loop(x0[:, 0].numpy(), w[..., 0].numpy(), v[..., 0].numpy(),
                      alpha[:, 0].numpy(), np.zeros(T), mask[..., 0].numpy(),
                      lambda m, y: -0.6 * m - 0.3 * y)  # fmt: skip
    tr = res.trajectories
    got = {"x": tr.x, "y": tr.y_true, "recv": tr.y_recv, "mean": res.output.means, "u": tr.us}
    for key, value in got.items():
        np.testing.assert_allclose(value[..., 0].numpy(), ref[key], rtol=1e-12, atol=1e-12)
    attacked = np.zeros((runs, T))
    attacked[:, 2:5] = [1.0, -2.0, 3.0]
    attacked[0, 3] = 0.0  # lost: no attack reached the estimator
    np.testing.assert_array_equal(tr.attack[..., 0].numpy(), attacked)
    np.testing.assert_array_equal(tr.flags.numpy(), attacked != 0)


def test_actuator_attack_with_state_feedback_matches_a_numpy_closed_loop():
    """An actuator attack on steps 2–4 under u_k = −K (x̂_k − x_ref): the plant is driven by
    u_{k−1} + a_k, the estimator knows u_{k−1} alone. Equal to the numpy loop. Kills: the
    attack left out of the transition, the estimator handed the attacked input, the
    reference's sign flipped."""
    T, runs, K, ref_x = 7, 2, 0.8, 0.4
    w, v = _noise(runs, T, seed=1)
    alpha = torch.zeros(T, 1, dtype=torch.float64)
    alpha[1:4, 0] = torch.tensor([0.7, -0.4, 1.1])
    x0 = torch.tensor([[0.3], [0.0]], dtype=torch.float64)
    ctrl = StateFeedback(torch.tensor([[K]], dtype=torch.float64),
                         torch.tensor([ref_x], dtype=torch.float64))  # fmt: skip
    res = closed_loop(_scalar_plant(), T, noise=ReplayedNoise(w, v), x0=x0,
                      estimator=df.KalmanFilter(), controller=ctrl,
                      attack=Signal(alpha, channel="actuator"))  # fmt: skip
    ref = _numpy_loop(x0[:, 0].numpy(), w[..., 0].numpy(), v[..., 0].numpy(), np.zeros(T),
                      alpha[:, 0].numpy(), np.ones((runs, T), bool),
                      lambda m, y: -K * (m - ref_x))  # fmt: skip
    tr = res.trajectories
    got = {"x": tr.x, "y": tr.y_true, "recv": tr.y_recv, "mean": res.output.means, "u": tr.us}
    for key, value in got.items():
        np.testing.assert_allclose(value[..., 0].numpy(), ref[key], rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(tr.flags.numpy()[0], alpha[:, 0].numpy() != 0)


# ------------------------------------------------------------------ the calibration


class _Scenario:
    """What :func:`calibrate` reads of a scenario (its runs come from the fake suite)."""

    name, runs = "fake", 1

    def attack_free_key(self):
        return ("fake", 0)

    def with_threat(self, attack):
        return self


def _calibrate(monkeypatch, scores, far):
    """:func:`calibrate` on attack-free ``scores [runs, T]`` of one detector ``"d"`` (the
    suite that would run the estimators replaced by one that returns them)."""
    import difffilter.eval.suite as suite

    def run_suite(scenario, **kw):
        det = types.SimpleNamespace(scores=torch.as_tensor(scores, dtype=torch.float64))
        out = types.SimpleNamespace(detection=det)
        return types.SimpleNamespace(outputs={"d": out}, skipped={})

    monkeypatch.setattr(suite, "run_suite", run_suite)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return cal_mod.calibrate(_Scenario(), far=far, progress=False)


def test_threshold_rate_and_steps_are_the_order_statistic_by_hand(monkeypatch):
    """15 steps (one NaN, ranked lowest and counted in n), α = 0.2: ⌊α n⌋ = 3, so τ is the
    4th largest score, 0.7; at most 3 scores exceed it (0.2 of n; a score equal to τ never
    alarms); 14 steps have a score, 15 count in n. Kills: alarms counted as s ≥ τ, NaN steps counted as
    scored."""
    nan = math.nan
    scores = [[0.5, 0.1, 0.2, 0.9, 0.3], [0.4, nan, 0.7, 0.6, 0.8], [1.5, 0.05, 0.25, 0.35, 0.45]]
    cal = _calibrate(monkeypatch, scores, 0.2)
    flat = sorted((s for row in scores for s in row if s == s), reverse=True)
    assert cal.thresholds == {"d": flat[3]} == {"d": 0.7}
    assert cal.measured == {"d": pytest.approx(3 / 15)}
    assert cal.steps == {"d": 15} and cal.scored == {"d": 14}  # n counts the NaN step
    assert cal.tied == {} and cal.startup == {} and cal.at_floor == {} and cal.concentrated == {}


def test_a_rate_of_exactly_half_the_target_is_below_it_and_not_at_floor(monkeypatch):
    """10 steps, nine at 1.0 and one 5.0, α = 0.2: τ = 1.0 (the 3rd largest), one alarm,
    a rate of 0.1 = α/2 exactly: listed as tied (90 % of scores at τ), and so not again as
    "at floor" although τ is the lowest score. Kills: ``measured < far/2``, at_floor listing
    a tied detector."""
    scores = [[1.0, 1.0, 5.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0, 1.0]]
    cal = _calibrate(monkeypatch, scores, 0.2)
    assert cal.thresholds["d"] == 1.0 and cal.measured["d"] == pytest.approx(0.1)
    assert cal.tied == {"d": pytest.approx(0.9)}
    assert cal.at_floor == {}
    assert cal.summary()["below_target"]["d"]["cause"] == "ties"


def test_at_floor_and_startup_are_read_off_the_alarms_by_hand(monkeypatch):
    """(a) α = 0.2 on 10 steps, eight at 0 and two above (steps 3, 4): τ = 0 = the lowest
    score, rate 0.2 (met): at floor with 80 % of the scores there. (b) two of 20 steps
    alarm, both at step 1: a start-up share of 1 and no alarm after step 1. Kills: the floor
    compared with the highest score, the start-up read at the last step."""
    floor = [[0.0, 0.0, 3.0, 0.0, 0.0], [0.0, 0.0, 0.0, 4.0, 0.0]]
    cal = _calibrate(monkeypatch, floor, 0.2)
    assert cal.thresholds["d"] == 0.0 and cal.at_floor == {"d": pytest.approx(0.8)}
    assert cal.startup == {} and cal.tied == {}
    start = torch.arange(20, dtype=torch.float64).reshape(4, 5) / 100
    start[0, 0], start[1, 0] = 9.0, 8.0
    cal = _calibrate(monkeypatch, start, 0.1)
    assert cal.thresholds["d"] == pytest.approx(0.19)  # the 3rd largest
    assert cal.startup == {"d": {"alarms_at_first_step": 1.0, "rate_after_first_step": 0.0}}


def _one_run_alarms(runs, steps, alarming):
    """Scores ``[runs, steps]``: ``alarming`` ones (value 10 + i) at steps 2, 3, … of run
    0, the rest distinct and below 1."""
    s = torch.arange(runs * steps, dtype=torch.float64).reshape(runs, steps) / (runs * steps)
    s[0, 1 : 1 + alarming] = 10.0 + torch.arange(alarming, dtype=torch.float64)
    return s


def test_clustered_alarms_by_the_dispersion_statistic_by_hand(monkeypatch):
    """10 runs × 20 steps at α = 0.05: the 10 alarms all in run 0. c = (10, 0, …, 0),
    c̄ = 1, (R − 1) D = Σ (c_r − c̄)² / c̄ = 81 + 9 = 90, worth N k / 90 = 10 · 9 / 90 = 1
    independent alarm; α n = 10 is resolved (not listed as unresolved). With 9 such alarms
    at α = 0.05 on 10 × 18 steps (α n = 9 < 10) it is unresolved and not listed again.
    Kills: c̄ over R − 1 runs, an unresolved detector listed as concentrated too, the
    resolution bound taken as ≤."""
    cal = _calibrate(monkeypatch, _one_run_alarms(10, 20, 10), 0.05)
    assert cal.measured["d"] == pytest.approx(0.05)
    assert cal.concentrated == {"d": {"alarms": 10, "effective_alarms": pytest.approx(1.0)}}
    assert "unresolved" not in cal.summary()
    cal = _calibrate(monkeypatch, _one_run_alarms(10, 18, 9), 0.05)
    assert cal.measured["d"] == pytest.approx(0.05)
    assert cal.concentrated == {} and cal.summary()["unresolved"] == {"d": 180}


def test_a_dispersion_that_chance_gives_is_not_clustered():
    """Alarms per run (4, 2, 1, 1, 1, 1, 0, 0, 0, 0): (R − 1) D = 9 + 1 + 4 · 0 + 4 · 1 = 14,
    worth 10 · 9 / 14 ≈ 6.4 alarms (below 10) but under the χ²₉ bound at 1e-4 (≈ 33.7,
    Wilson–Hilferty by hand): not clustered. 10 alarms in one run (statistic 90) are.
    Kills: the test's two conditions joined by "and" instead of "or"."""
    counts = [4, 2, 1, 1, 1, 1, 0, 0, 0, 0]
    s = torch.zeros(10, 5, dtype=torch.float64)
    for r, c in enumerate(counts):
        s[r, :c] = 1.0
    z = 3.719016485455709  # Φ⁻¹(1 − 1e-4)
    k = 9
    assert 14 < k * (1 - 2 / (9 * k) + z * math.sqrt(2 / (9 * k))) ** 3 < 90
    assert cal_mod.alarm_clustering(s, 0.5) is None
    one = torch.zeros(10, 10, dtype=torch.float64)
    one[0] = 1.0
    got = cal_mod.alarm_clustering(one, 0.5)
    assert got == {"alarms": 10, "effective_alarms": pytest.approx(1.0)}


def test_the_resolution_note_states_the_expected_rate_by_hand():
    """9 scored steps at α = 0.05: ⌊0.45⌋ = 0, so the rate on fresh runs is (0 + 1)/(9 + 1)
    = 10 % in expectation. Kills: the expectation's denominator n instead of n + 1."""
    note = cal_mod.resolution_note(0.05, 9, "--calibration-runs")
    assert "about 10 % in expectation" in note


def test_a_fork_continued_under_a_schedule_records_every_steps_mask():
    """A loop under a schedule, forked after step 4 without attack and continued with a
    sensor attack from step 6: its trajectories cover steps 1 … 10 with the schedule's rows
    1 … 10 (by the absolute step), and equal the attacked loop run at once; the lost
    attacked entry (run 1, step 7) records no attack. Kills: the fork's recorded steps
    dropped from the mask's slice (rows 5 … 10 beside 10 steps)."""
    T, runs, k = 10, 2, 4
    w, v = _noise(runs, T, seed=2)
    alpha = torch.zeros(T, 1, dtype=torch.float64)
    alpha[5:8, 0] = 2.0
    mask = torch.ones(runs, T, 1, dtype=torch.bool)
    mask[1, 6, 0] = mask[0, 2, 0] = False
    x0 = torch.zeros(runs, 1, dtype=torch.float64)

    def loop(steps, **kw):
        return closed_loop(_scalar_plant(), steps, noise=ReplayedNoise(w, v), x0=x0,
                           estimator=df.KalmanFilter(), controller=_MeanAndMeasurement(),
                           mask=mask, **kw)  # fmt: skip

    forks = {k: None}
    loop(T, forks=forks)
    whole = loop(T, attack=Signal(alpha)).trajectories
    forked = loop(T - k, attack=Signal(alpha), fork=forks[k]).trajectories
    assert torch.equal(forked.mask, mask) and torch.equal(whole.mask, mask)
    for field in ("x", "y_recv", "attack", "flags"):
        assert torch.equal(getattr(forked, field), getattr(whole, field))
    expected = (alpha[:, 0] != 0).expand(runs, T).clone()
    expected[1, 6] = False
    assert torch.equal(forked.flags, expected)


# ------------------------------------------------------------------ the leaderboard


def test_the_leaderboard_figure_ranks_neither_an_oracle_nor_the_reference(tmp_path, monkeypatch):
    """A study of an oracle (attack RMSE 0.01), the attack-free reference (0.02) and two
    analytic estimators (0.1, 1.0): the colours the figure is drawn with, read back, set the
    best at the analytic 0.1 (1.0 there, and 1 for the better oracle and reference), and
    the 1.0 at 1 − log10((1.0 + f) / (0.1 + f)) with f = 5 % of the largest, 0.05; the rows
    read back carry the metrics they were built from. Kills: every row ranked in the
    figure, the oracle left out of the unranked roles."""
    from difffilter.eval import leaderboard as lb
    from difffilter.eval.scoring import METRICS

    values = {"oracle_kf": 0.01, "reference_kf": 0.02, "kf": 0.1, "ekf": 1.0}
    roles = {"oracle_kf": "oracle", "reference_kf": "reference", "kf": "analytic",
             "ekf": "analytic"}  # fmt: skip
    study = {"estimators": {n: dict.fromkeys(METRICS) | {"attack_rmse": v}
                            for n, v in values.items()},
             "checkpoint": None, "estimator_roles": roles}  # fmt: skip
    seen = {}
    real = lb.cell_goodness

    def spy(grid, scenarios, columns, ranked=None, *args, **kw):
        seen["cols"], seen["grid"] = list(columns), grid.copy()
        seen["good"] = real(grid, scenarios, columns, ranked, *args, **kw)
        return seen["good"]

    monkeypatch.setattr(lb, "cell_goodness", spy)
    lb.write_leaderboard(tmp_path, {"s": study})
    rows = json.loads((tmp_path / "leaderboard.json").read_text())
    assert {r["estimator"]: r["attack_rmse"] for r in rows} == values
    j = seen["cols"].index("attack_rmse")
    np.testing.assert_allclose(seen["grid"][:, j], list(values.values()))
    expected = [1.0, 1.0, 1.0, 1 - math.log10(1.05 / 0.15)]
    np.testing.assert_allclose(seen["good"][:, j], expected, rtol=1e-12)


def test_the_colour_floor_is_five_percent_of_the_scenarios_largest_value():
    """An oracle with the largest attack RMSE (10, unranked) beside ranked 0.1 and 1.0: the
    floor is 5 % of the scenario's largest value, 0.5 (docstring of cell_goodness), so the
    1.0 reads 1 − log10(1.5 / 0.6) and the oracle 0 (clipped). Kills: the floor taken from
    the ranked rows alone (0.05)."""
    from difffilter.eval.leaderboard import cell_goodness

    col = COLUMNS_INDEX["attack_rmse"]
    grid = np.full((3, len(COLUMNS_INDEX)), np.nan)
    grid[:, col] = [10.0, 0.1, 1.0]
    good = cell_goodness(grid, ["s"] * 3, ranked=np.array([False, True, True]))
    np.testing.assert_allclose(good[:, col], [0.0, 1.0, 1 - math.log10(1.5 / 0.6)], rtol=1e-12)
