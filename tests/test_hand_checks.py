"""Hand-computed cases of lines a mutation review found no test pinned down: a headline
metric, the impact's unseen period, the acceptance judge's inclusive bounds, the PCRB's
Jacobian point, the LQR gain with R ≠ I and the input the closed loop's estimator reads."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import scipy.linalg as sla
import torch

import difffilter as df
from difffilter.control import lqr
from difffilter.estimator import Detection, EstimatorOutput
from difffilter.eval.acceptance import TOLERANCES, judge, judge_robustness
from difffilter.eval.calibration import calibrated_metrics
from difffilter.eval.scoring import score
from difffilter.loop import KnownInputs, ReplayedNoise, closed_loop, open_loop
from difffilter.threats import Bias

F64 = torch.float64


def _traj(x, flags, attack):
    return SimpleNamespace(x=x, flags=flags, attack=attack, info={})


def test_separable_scores_detect_everything_at_one_percent_and_false_alarms_count_per_step():
    """200 clean steps scoring 0…199, 20 attacked scoring 1000: TPR 1 at FPR 0 ≤ 1 %
    (max over τ, docs/metrics.md); alarms above 150 are 49 false alarms over 220 steps."""
    flags = torch.zeros(1, 220, dtype=torch.bool)
    flags[0, 200:] = True
    scores = torch.arange(220, dtype=F64).unsqueeze(0)
    scores[0, 200:] = 1000.0
    x = torch.zeros(1, 220, 1, dtype=F64)
    out = EstimatorOutput(x.clone(), detection=Detection(scores, scores > 150))
    s = score(out, _traj(x, flags, torch.zeros(1, 220, 0, dtype=F64)), dt=1.0, wall_s=1.0)
    assert s["tpr_at_1pct_fpr"] == 1.0
    assert math.isclose(s["false_alarms_per_1000_steps"], 1000 * 49 / 220)


def test_impact_is_the_error_until_the_first_alarm_on_an_attacked_step():
    """Run 0 attacked from t = 2, a false alarm at t = 0 (before the onset: it sees no
    attack), its first attacked alarm at t = 4: unseen t = 2, 3, error up to 4; run 1
    never alarmed: 10; run 2 not attacked: out. Impact = (4 + 10)/2 = 7."""
    flags = torch.zeros(3, 6, dtype=torch.bool)
    flags[0, 2:] = True
    flags[1, 3:] = True
    sc = torch.zeros(3, 6, dtype=F64)
    sc[0, 0] = sc[0, 4] = 5.0
    means = torch.zeros(3, 6, 1, dtype=F64)
    means[0, :, 0] = torch.arange(1, 7, dtype=F64)
    means[1], means[2] = 10.0, 100.0
    out = EstimatorOutput(means, detection=Detection(sc, sc > 1.0))
    x = torch.zeros(3, 6, 1, dtype=F64)
    assert (
        calibrated_metrics(out, _traj(x, flags, torch.zeros(3, 6, 0, dtype=F64)), 1.0)["impact"]
        == 7.0
    )


def test_the_judges_bounds_are_inclusive():
    """TPR ≥ best − 0.01, state ≤ 1.05 × best, FPR in [α/2, 2α], worst TPR ≥ the best
    analytic's worst: each exactly at its bound holds."""
    far = 0.01
    best = {"tpr_at_far": (0.5, "a"), "state_rmse": (2.0, "a")}
    low = far * TOLERANCES["fpr_band"][0]
    learned = {"tpr_at_far": 0.5 - TOLERANCES["tpr_margin"],
               "state_rmse": TOLERANCES["state_factor"] * 2.0, "fpr_at_far": low}  # fmt: skip
    assert all(c.holds for c in judge(learned, best, far))
    cells = {"t1": {"L": {"tpr_at_far": 0.3, "state_rmse": 1.0}, "A": {"tpr_at_far": 0.3, "state_rmse": 1.0}},
             "t2": {"L": {"tpr_at_far": 0.5, "state_rmse": 1.0}, "A": {"tpr_at_far": 0.6, "state_rmse": 1.0}}}  # fmt: skip
    assert (
        judge_robustness(cells, {"L": "learned", "A": "analytic"}, far=far)["L"]["tpr_holds"]
        is True
    )


def test_the_pcrb_of_a_nonlinear_model_takes_the_jacobian_at_the_state_it_leaves():
    """x_{k+1} = x_k + ½ sin x_k + w, y = x + v, 50 paths: Tichavský's recursion by hand
    with F̃_k at x_k (at x_{k+1} a linear test could not tell)."""
    q, r, p0 = 0.2, 0.5, 1.0

    def f(x):
        return x + 0.5 * torch.sin(x)

    model = df.NonlinearGaussianModel(f, lambda x: x, torch.tensor([[q]], dtype=F64),
                                      torch.tensor([[r]], dtype=F64), torch.zeros(1, dtype=F64),
                                      torch.tensor([[p0]], dtype=F64))  # fmt: skip
    g = torch.Generator().manual_seed(0)
    x0 = 2.0 * torch.randn(50, 1, generator=g, dtype=F64)
    xs, x = [], x0
    for _ in range(5):
        x = f(x) + math.sqrt(q) * torch.randn(50, 1, generator=g, dtype=F64)
        xs.append(x)
    xs = torch.stack(xs, 1)
    J, prev, expected = 1 / p0, x0[:, 0], []
    for t in range(5):
        Ft = 1 + 0.5 * torch.cos(prev)
        D11, D12, D22 = float((Ft**2).mean()) / q, -float(Ft.mean()) / q, 1 / q + 1 / r
        J = D22 - D12 * D12 / (J + D11)
        expected.append(J)
        prev = xs[:, t, 0]
    got = df.posterior_crb(model, xs, x0).information[:, 0, 0]
    torch.testing.assert_close(got, torch.tensor(expected, dtype=F64), rtol=1e-10, atol=0)


def test_lqr_gain_divides_by_r():
    """K = R⁻¹BᵀP (eqs 15–16) with R = diag(4, 0.5), against scipy's CARE (the LFC uses
    R = I, where a dropped R⁻¹ changes nothing)."""
    A = np.array([[0.0, 1.0, 0.0], [-2.0, -0.5, 1.0], [0.0, 0.0, -1.0]])
    B = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    Q, R = np.diag([1.0, 2.0, 3.0]), np.diag([4.0, 0.5])
    P = sla.solve_continuous_are(A, B, Q, R)
    K, _ = lqr(*(torch.tensor(v) for v in (A, B, Q, R)), method="direct")
    np.testing.assert_allclose(K.numpy(), np.linalg.solve(R, B.T @ P), atol=1e-9)


def test_the_closed_loops_estimator_reads_the_known_input_not_the_attacked_one():
    """Under an actuator bias the plant moves with u + a, the estimator knows u only: its
    estimates are the open loop's on the same received measurements and known inputs."""
    F = torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=F64)
    eye = torch.eye(2, dtype=F64)
    model = df.LinearGaussianModel(F, eye, 1e-3 * eye, 1e-2 * eye, torch.zeros(2, dtype=F64), eye,
                                   B=torch.tensor([[0.0], [0.1]], dtype=F64))  # fmt: skip
    us = 0.5 * torch.ones(2, 6, 1, dtype=F64)
    zeros = torch.zeros(2, 6, 2, dtype=F64)
    loop = closed_loop(model, 6, noise=ReplayedNoise(zeros, zeros), x0=torch.zeros(2, 2, dtype=F64),
                       estimator=df.KalmanFilter(), controller=KnownInputs(us),
                       attack=Bias(value=1.0, onset=3, channel="actuator"),
                       attack_generator=torch.Generator().manual_seed(0))  # fmt: skip
    reference = open_loop(df.KalmanFilter(), model, loop.trajectories.y_recv, us)
    torch.testing.assert_close(loop.output.means, reference.means, rtol=0, atol=1e-12)
    assert torch.equal(loop.trajectories.us, us)
