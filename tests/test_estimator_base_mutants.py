"""Mutation review of the estimator contract (difffilter.estimator), the result types
(difffilter.results) and the Gaussian core (difffilter.gaussian).

Every number is checked against an independent truth: a literal float64 numpy Kalman
recursion on the received entries alone (``ν_k = y_k − H(F x̂_{k−1} + B u_{k−1})``,
``S_k = H P⁻ Hᵀ + R``, ``K = P⁻Hᵀ S⁻¹``, ``P⁺ = P⁻ − K S Kᵀ``, increments
``−½(νᵀS⁻¹ν + log det 2πS)``), or a tensor stacked by hand in numpy.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter import gaussian
from difffilter.attack import Channel
from difffilter.estimator import (
    Detection,
    EstimatorOutput,
    Generators,
    stack_steps,
)
from difffilter.loop import open_loop
from difffilter.results import FilterResult, GaussianState, StepOutput

DX, DY, DU, T = 2, 3, 1, 5
F = np.array([[1.0, 0.2], [-0.1, 0.9]])
B = np.array([[0.0], [0.3]])
H = np.array([[1.0, 0.0], [0.5, 1.0], [0.0, 2.0]])
Q = np.array([[0.05, 0.01], [0.01, 0.04]])
R = np.array([[0.2, 0.05, 0.0], [0.05, 0.3, 0.02], [0.0, 0.02, 0.25]])
M0 = np.array([0.5, -0.3])
P0 = np.array([[1.0, 0.2], [0.2, 0.5]])


def model():
    t = torch.tensor
    return df.LinearGaussianModel(t(F), t(H), t(Q), t(R), t(M0), t(P0), B=t(B))


def numpy_kf(ys, us, mask):
    """The literal recursion for one run on its received entries: per step ``(m⁺, P⁺, m⁻,
    P⁻, ν, S, ℓ)`` with ``ν`` zero and ``S`` the identity on unreceived entries."""
    m, P, rows = M0.copy(), P0.copy(), []
    for t in range(len(ys)):
        mp = F @ m + B @ us[t]
        Pp = F @ P @ F.T + Q
        idx = np.flatnonzero(mask[t])
        Hr, Rr = H[idx], R[np.ix_(idx, idx)]
        nu = ys[t][idx] - Hr @ mp
        S = Hr @ Pp @ Hr.T + Rr
        K = Pp @ Hr.T @ np.linalg.inv(S) if len(idx) else np.zeros((DX, 0))
        m, P = mp + K @ nu, Pp - K @ S @ K.T
        ll = -0.5 * (nu @ np.linalg.solve(S, nu) + np.linalg.slogdet(2 * np.pi * S)[1])
        nu_full, S_full = np.zeros(DY), np.eye(DY)
        nu_full[idx] = nu
        S_full[np.ix_(idx, idx)] = S
        rows.append((m, P, mp, Pp, nu_full, S_full, ll if len(idx) else 0.0))
    return [np.stack(c) for c in zip(*rows)]


def data(batch, seed):
    gen = torch.Generator().manual_seed(seed)
    ys = torch.randn(*batch, T, DY, generator=gen, dtype=torch.float64)
    us = torch.randn(*batch, T, DU, generator=gen, dtype=torch.float64)
    mask = torch.rand(*batch, T, DY, generator=gen) < 0.7
    mask[..., 0, :] = True  # the first step received in full
    return ys, us, mask


KEYS = ("means", "covs", "pred_means", "pred_covs", "innovations", "innovation_covs",
        "log_likelihood_increments")  # fmt: skip


def check_against_numpy(out, ys, us, mask, batch):
    got = {"means": out.means, "covs": out.covs, **out.extras}
    for key in KEYS:
        assert got[key].shape[: len(batch) + 1] == (*batch, T), key
    flat = {k: got[k].detach().reshape(-1, *got[k].shape[len(batch) :]) for k in KEYS}
    lls = got["log_likelihood"].reshape(-1)
    y2, u2, m2 = (a.reshape(-1, *a.shape[len(batch) :]).numpy() for a in (ys, us, mask))
    for r in range(y2.shape[0]):
        truth = numpy_kf(y2[r], u2[r], m2[r])
        for key, want in zip(KEYS, truth):
            np.testing.assert_allclose(flat[key][r].numpy(), want, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(float(lls[r]), truth[-1].sum(), rtol=1e-10)


@pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
def test_stepped_kalman_filter_with_a_mask_is_the_literal_recursion(batch):
    """The step-by-step KF (``collect`` forces the steps; a mask forces the general Gaussian
    update of difffilter.gaussian) stacked by ``stack_steps`` equals, per run, the float64
    numpy recursion on the received entries (dx=2 ≠ dy=3, with an input), for batch
    shapes (), (3,) and (2, 3)."""
    ys, us, mask = data(batch, seed=len(batch))
    out = open_loop(df.KalmanFilter(), model(), ys, us, mask=mask, collect=lambda c, o: {})
    check_against_numpy(out, ys, us, mask, batch)
    res = FilterResult.from_output(out)
    for key in KEYS:
        assert getattr(res, key) is (out.covs if key == "covs" else
                                     out.means if key == "means" else out.extras[key])  # fmt: skip


@pytest.mark.parametrize("mask_kind", ["none", "one schedule"])
def test_the_kalman_fast_paths_through_output_of_are_the_literal_recursion(mask_kind):
    """``open_loop`` without ``collect`` takes the KF's whole-sequence path and
    :func:`output_of`: every stacked statistic (pred_covs and the increments included)
    equals the numpy recursion, and FilterResult.from_output reads pred_covs back."""
    ys, us, mask = data((2, 3), seed=7)
    if mask_kind == "none":
        mask = torch.ones_like(mask)
        out = open_loop(df.KalmanFilter(), model(), ys, us)
    else:
        mask = mask[:1, :1].expand_as(mask)  # every run the same entries
        out = open_loop(df.KalmanFilter(), model(), ys, us, mask=mask)
    check_against_numpy(out, ys, us, mask, (2, 3))
    assert FilterResult.from_output(out).pred_covs is out.extras["pred_covs"]


def test_nonfinite_skipped_and_to_dict_keep_every_field():
    """``nonfinite="skip"``: one NaN entry is counted (1 in its run, 0 elsewhere, counted by
    hand) and reaches FilterResult.from_output; ``to_dict`` names every dataclass field."""
    ys, us, _ = data((3,), seed=3)
    ys[1, 2, 0] = float("nan")
    out = open_loop(df.KalmanFilter(), model(), ys, us, nonfinite="skip")
    res = FilterResult.from_output(out)
    np.testing.assert_array_equal(res.nonfinite_skipped.numpy(), [0, 1, 0])
    d = res.to_dict()
    assert list(d) == [
        "means", "covs", "pred_means", "pred_covs", "innovations", "innovation_covs",
        "log_likelihood_increments", "log_likelihood", "nonfinite_skipped",
    ]  # fmt: skip
    assert d["nonfinite_skipped"] is res.nonfinite_skipped


# ------------------------------------------------------------------- the Gaussian core


def rng_mats(seed, *batch):
    g = np.random.default_rng(seed)
    A = g.standard_normal((*batch, DX, DX))
    P = A @ np.swapaxes(A, -1, -2) + 0.5 * np.eye(DX)
    C = g.standard_normal((*batch, DY, DY))
    Rm = C @ np.swapaxes(C, -1, -2) + 0.5 * np.eye(DY)
    return g, P, Rm


def test_linear_update_with_a_mask_is_the_update_on_the_received_entries():
    """``linear_update`` with a batch of masks: ``m⁺``, ``P⁺``, ``r'`` (zero where
    unreceived), ``S`` (identity rows there) and ``log N`` equal the numpy update on the
    received entries alone, run by run."""
    g, P, Rm = rng_mats(0, 4)
    m = g.standard_normal((4, DX))
    Hs = g.standard_normal((4, DY, DX))
    r = g.standard_normal((4, DY))
    mask = np.array([[1, 1, 1], [1, 0, 1], [0, 1, 0], [0, 0, 1]], dtype=bool)
    t = torch.tensor
    mean, cov, res, S, ll = gaussian.linear_update(t(m), t(P), t(r), t(Hs), t(Rm), t(mask))
    for i in range(4):
        idx = np.flatnonzero(mask[i])
        Hr, Rr, rr = Hs[i][idx], Rm[i][np.ix_(idx, idx)], r[i][idx]
        Sr = Hr @ P[i] @ Hr.T + Rr
        K = P[i] @ Hr.T @ np.linalg.inv(Sr)
        np.testing.assert_allclose(mean[i].numpy(), m[i] + K @ rr, rtol=1e-10)
        np.testing.assert_allclose(cov[i].numpy(), P[i] - K @ Sr @ K.T, rtol=1e-9, atol=1e-12)
        want_r, want_S = np.zeros(DY), np.eye(DY)
        want_r[idx], want_S[np.ix_(idx, idx)] = rr, Sr
        np.testing.assert_allclose(res[i].numpy(), want_r, rtol=1e-12)
        np.testing.assert_allclose(S[i].numpy(), want_S, rtol=1e-10, atol=1e-12)
        want_ll = -0.5 * (rr @ np.linalg.solve(Sr, rr) + np.linalg.slogdet(2 * np.pi * Sr)[1])
        np.testing.assert_allclose(float(ll[i]), want_ll, rtol=1e-10)
    # linear_innovation: the same r', S, C = P⁻H'ᵀ and the count of received entries
    r2, S2, C2, H2, R2, obs = gaussian.linear_innovation(t(P), t(r), t(Hs), t(Rm), t(mask))
    torch.testing.assert_close(r2, res, rtol=0, atol=0)
    torch.testing.assert_close(S2, S, rtol=1e-12, atol=1e-12)
    Hm = Hs * mask[..., None]
    np.testing.assert_allclose(C2.numpy(), P @ np.swapaxes(Hm, -1, -2), rtol=1e-12)
    np.testing.assert_array_equal(obs.numpy(), mask.sum(-1))
    # the evidence alone agrees with the update's
    torch.testing.assert_close(gaussian.innovation_log_prob(r2, S2, obs), ll)


def test_joseph_form_for_a_suboptimal_gain():
    """``joseph_covariance`` for an arbitrary (not optimal) gain is the literal
    ``(I − KH) P (I − KH)ᵀ + K R Kᵀ`` (the short form differs there)."""
    g, P, Rm = rng_mats(1)
    K = g.standard_normal((DX, DY))
    Hm = g.standard_normal((DY, DX))
    A = np.eye(DX) - K @ Hm
    want = A @ P @ A.T + K @ Rm @ K.T
    t = torch.tensor
    got = gaussian.joseph_covariance(t(P), t(K), t(Hm), t(Rm))
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-12)


def test_gain_and_evidence_symmetrise_s_first():
    """``kalman_gain``, ``innovation_log_prob`` and ``gaussian_update`` symmetrise ``S``
    (documented): with an asymmetric ``S`` (or ``H P Hᵀ``) they give the numbers of
    ``(S + Sᵀ)/2``, computed in numpy."""
    g, P, Rm = rng_mats(2)
    Hm = g.standard_normal((DY, DX))
    C = P @ Hm.T
    skew = np.array([[0.0, 0.3, -0.2], [-0.3, 0.0, 0.1], [0.2, -0.1, 0.0]])
    S_sym = Hm @ P @ Hm.T + Rm
    S_asym = S_sym + skew
    r = g.standard_normal(DY)
    m = g.standard_normal(DX)
    t = torch.tensor
    K, chol = gaussian.kalman_gain(t(C), t(S_asym))
    np.testing.assert_allclose(K.numpy(), C @ np.linalg.inv(S_sym), rtol=1e-10)
    np.testing.assert_allclose((chol @ chol.T).numpy(), S_sym, rtol=1e-12)
    want_ll = -0.5 * (r @ np.linalg.solve(S_sym, r) + np.linalg.slogdet(2 * np.pi * S_sym)[1])
    np.testing.assert_allclose(float(gaussian.innovation_log_prob(t(r), t(S_asym), DY)), want_ll)
    mean, cov, S, ll = gaussian.gaussian_update(
        t(m), t(P), t(r), t(C), t(Hm @ P @ Hm.T + skew), t(Hm), t(Rm), DY
    )
    np.testing.assert_allclose(S.numpy(), S_sym, rtol=1e-12)
    Kt = C @ np.linalg.inv(S_sym)
    np.testing.assert_allclose(mean.numpy(), m + Kt @ r, rtol=1e-10)
    np.testing.assert_allclose(float(ll), want_ll, rtol=1e-12)
    _, _, _, none = gaussian.gaussian_update(
        t(m), t(P), t(r), t(C), t(Hm @ P @ Hm.T), t(Hm), t(Rm), DY, evidence=False
    )
    assert none is None


def test_linear_predict_is_f_m_plus_b_u():
    """``linear_predict``: ``m⁻ = F m + B u`` and ``P⁻ = F P Fᵀ + Q`` in numpy, for a
    non-symmetric ``F``; without ``u`` the input term is absent."""
    g, P, _ = rng_mats(3)
    m, u = g.standard_normal(DX), g.standard_normal(DU)
    t = torch.tensor
    pm, pc = gaussian.linear_predict(t(m), t(P), t(F), t(Q), t(B), t(u))
    np.testing.assert_allclose(pm.numpy(), F @ m + B @ u, rtol=1e-12)
    np.testing.assert_allclose(pc.numpy(), F @ P @ F.T + Q, rtol=1e-12)
    pm0, _ = gaussian.linear_predict(t(m), t(P), t(F), t(Q), t(B), None)
    np.testing.assert_allclose(pm0.numpy(), F @ m, rtol=1e-12)


# --------------------------------------------------------------------- stack_steps


def _t(a):
    return torch.tensor(a, dtype=torch.float64)


def test_stack_steps_broadcasts_mixed_step_shapes_like_numpy():
    """Steps whose fields are shared (no batch dims) at some steps and per run at others
    stack to ``[*batch, T, ·]`` exactly as numpy's broadcast-then-stack; the log-likelihood
    is the sum of the increments over T; the steps' extras stack after the batch."""
    g = np.random.default_rng(4)
    batch = (2, 3)
    shapes = {
        "mean": [(DX,), (*batch, DX), (3, DX)],
        "cov": [(DX, DX), (*batch, DX, DX), (3, DX, DX)],
        "pred_mean": [(*batch, DX), (DX,), (DX,)],
        "pred_cov": [(DX, DX), (DX, DX), (*batch, DX, DX)],
        "innovation": [(DY,), (*batch, DY), (DY,)],
        "innovation_cov": [(DY, DY), (3, DY, DY), (DY, DY)],
        "log_likelihood": [(), batch, (3,)],
        "attack": [(*batch, DY), (DY,), (*batch, DY)],
        "score": [batch, (), (3,)],
    }
    vals = {k: [g.standard_normal(s) for s in v] for k, v in shapes.items()}
    alarms = [g.standard_normal(batch) > 0 for _ in range(3)]
    ess = [g.standard_normal(batch) for _ in range(3)]
    outs = [
        StepOutput(
            **{k: _t(v[i]) for k, v in vals.items()},
            alarm=torch.tensor(alarms[i]),
            threshold=1.5,
            extras={"ess": _t(ess[i])},
        )
        for i in range(3)
    ]
    collected = {"extra": torch.zeros(*batch, 3)}
    out = stack_steps(outs, torch.Size(batch), collected, Channel.ACTUATOR)

    def want(key, tail):
        return np.stack([np.broadcast_to(v, batch + tail) for v in vals[key]], axis=len(batch))

    np.testing.assert_array_equal(out.means.numpy(), want("mean", (DX,)))
    np.testing.assert_array_equal(out.covs.numpy(), want("cov", (DX, DX)))
    np.testing.assert_array_equal(out.attack.numpy(), want("attack", (DY,)))
    x = out.extras
    np.testing.assert_array_equal(x["pred_means"].numpy(), want("pred_mean", (DX,)))
    np.testing.assert_array_equal(x["pred_covs"].numpy(), want("pred_cov", (DX, DX)))
    np.testing.assert_array_equal(x["innovations"].numpy(), want("innovation", (DY,)))
    np.testing.assert_array_equal(x["innovation_covs"].numpy(), want("innovation_cov", (DY, DY)))
    inc = want("log_likelihood", ())
    np.testing.assert_array_equal(x["log_likelihood_increments"].numpy(), inc)
    np.testing.assert_allclose(x["log_likelihood"].numpy(), inc.sum(-1), rtol=1e-15)
    np.testing.assert_array_equal(x["ess"].numpy(), np.stack(ess, axis=-1))
    assert x["extra"] is collected["extra"]
    np.testing.assert_array_equal(out.scores.numpy(), want("score", ()))
    np.testing.assert_array_equal(out.alarms.numpy(), np.stack(alarms, axis=-1))
    assert out.detection.threshold == 1.5 and isinstance(out.detection.threshold, float)
    assert out.attack_channel is Channel.ACTUATOR


def test_stack_steps_expands_what_every_run_shares():
    """Fields shared by every run at every step (``[dx]``, ``[dx, dx]``, ``[]``) come back
    with the batch, ``[*batch, T, ·]``, each run holding the hand-stacked ``[T, ·]``."""
    covs = [_t(np.eye(DX) * (i + 1)) for i in range(T)]
    pms = [_t(np.arange(DX) + 10.0 * i) for i in range(T)]
    lls = [_t(-1.0 - i) for i in range(T)]
    outs = [
        StepOutput(pm, cov=c, pred_mean=pm, log_likelihood=ll) for pm, c, ll in zip(pms, covs, lls)
    ]
    out = stack_steps(outs, torch.Size((2, 3)))
    want = np.broadcast_to(np.stack([c.numpy() for c in covs]), (2, 3, T, DX, DX))
    np.testing.assert_array_equal(out.covs.numpy(), want)
    want = np.broadcast_to(np.stack([v.numpy() for v in pms]), (2, 3, T, DX))
    np.testing.assert_array_equal(out.means.numpy(), want)
    np.testing.assert_array_equal(out.extras["pred_means"].numpy(), want)
    want = np.broadcast_to(np.arange(-1.0, -1.0 - T, -1), (2, 3, T))
    np.testing.assert_array_equal(out.extras["log_likelihood_increments"].numpy(), want)
    np.testing.assert_array_equal(out.extras["log_likelihood"].numpy(), want.sum(-1))


def _detect(thresholds, batch=(3,), score_shape=(3,), mean_shape=(3, DX)):
    outs = [
        StepOutput(
            torch.zeros(mean_shape, dtype=torch.float64),
            score=torch.full(score_shape, float(i), dtype=torch.float64),
            alarm=torch.zeros(score_shape, dtype=torch.bool),
            threshold=th,
        )
        for i, th in enumerate(thresholds)
    ]
    return stack_steps(outs, torch.Size(batch)).detection


def test_per_step_thresholds_stack_in_the_scores_dtype():
    """A threshold that changes with the step becomes ``[*batch, T]`` in the scores' dtype
    (float64 here) with the hand-stacked values, however it changes (a change in the
    middle, tensors of the runs' shape); one number for all steps stays that float."""
    det = _detect([1.0, 2.0, 1.0])
    assert det.threshold.dtype == torch.float64
    np.testing.assert_array_equal(det.threshold.numpy(), np.tile([1.0, 2.0, 1.0], (3, 1)))
    runs = [torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)] * 2
    det = _detect(runs)
    np.testing.assert_array_equal(det.threshold.numpy(), np.array([[1.0, 1.0], [2, 2], [3, 3]]))
    det = _detect([torch.tensor(0.25), 0.25])
    assert det.threshold == 0.25 and isinstance(det.threshold, float)
    assert _detect([None, None]).threshold is None


def test_a_learnable_threshold_keeps_its_gradient():
    """A constant threshold that requires grad (a learnable one) stays a tensor ``[*batch,
    T]``: its gradient through the stacked thresholds is T (one per step and run summed,
    ``d/dτ Σ τ = T·B``), where collapsing it to a float would leave no gradient at all."""
    tau = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    det = _detect([tau, tau, tau, tau])
    assert isinstance(det.threshold, torch.Tensor) and det.threshold.shape == (3, 4)
    det.threshold.sum().backward()
    assert tau.grad.item() == 12.0


def test_detection_of_runs_from_the_models_parameter_sets():
    """``batch=()`` on a model of 3 parameter sets: the steps' means are ``[3, dx]``, so a
    per-step threshold of one number per step, and an alarm shared by the runs, are
    stacked ``[3, T]`` (the runs of the means), not ``[T]``."""
    det = _detect([1.0, 2.0], batch=(), score_shape=(3,), mean_shape=(3, DX))
    assert det.scores.shape == (3, 2)
    np.testing.assert_array_equal(det.threshold.numpy(), np.tile([1.0, 2.0], (3, 1)))
    # a decision shared by the runs (alarm ``[]``) broadcasts to them as well
    outs = [
        StepOutput(torch.zeros(3, DX), score=torch.zeros(3), alarm=torch.tensor(i == 1))
        for i in range(2)
    ]
    det = stack_steps(outs, torch.Size(())).detection
    np.testing.assert_array_equal(det.alarms.numpy(), np.tile([False, True], (3, 1)))


def test_stack_steps_refuses_no_steps():
    """``T = 0``: a ValueError naming T >= 1."""
    with pytest.raises(ValueError, match="T >= 1"):
        stack_steps([], torch.Size(()))


# ----------------------------------------------------------------- validation & plumbing


def test_detection_and_output_validate_their_shapes():
    """Detection refuses scores/alarms of different shapes, non-bool and non-torch alarms;
    EstimatorOutput refuses 1-d means, an attack of another ``[..., T]`` and scores not
    shaped like the means without ``dx``, and turns a channel's name into its Channel."""
    s = torch.zeros(3, T)
    with pytest.raises(ValueError, match="same shape"):
        Detection(s, torch.zeros(3, T + 1, dtype=torch.bool))
    with pytest.raises(ValueError, match="bool"):
        Detection(s, torch.zeros(3, T))
    with pytest.raises(TypeError, match="alarms must be a torch tensor"):
        Detection(s, np.zeros((3, T), dtype=bool))
    with pytest.raises(ValueError, match="means must have shape"):
        EstimatorOutput(torch.zeros(DX))
    means = torch.zeros(3, T, DX)
    with pytest.raises(ValueError, match="attack must have shape"):
        EstimatorOutput(means, attack=torch.zeros(3, T + 1, DY))
    with pytest.raises(ValueError, match="detection scores"):
        EstimatorOutput(means, detection=Detection(s[:, :-1], s[:, :-1].bool()))
    assert EstimatorOutput(means, attack_channel="actuator").attack_channel is Channel.ACTUATOR


def test_detection_refuses_a_threshold_that_is_not_a_number_or_the_scores_shape():
    """A trial: a threshold ``"25"`` was reported as 25.0, a list or a ``[B]`` tensor (one
    per run, not ``[..., T]``) was taken without a word, complex scores were cast to real
    with torch's warning. Each is refused, naming the argument; a number, a 0-d tensor, a
    ``[B, T]`` tensor and one that broadcasts to it (``[T]``) are taken, and ``None`` too."""
    s = torch.zeros(3, T)
    alarms = s > 0
    for bad in ("25", [0.5], True, np.array([0.5])):
        with pytest.raises(TypeError, match="threshold must be a number"):
            Detection(s, alarms, bad)
    with pytest.raises(ValueError, match=r"threshold must be .* got shape \(3,\)"):
        Detection(s, alarms, torch.ones(3))
    with pytest.raises(ValueError, match="scores must be real"):
        Detection(torch.zeros(3, T, dtype=torch.complex64), alarms)
    for good in (0.5, np.float64(0.5), 2, torch.tensor(0.5), torch.ones(3, T), torch.ones(T), None):
        assert Detection(s, alarms, good).threshold is good
    with pytest.raises(TypeError, match="means must be a torch tensor .* only detects"):
        EstimatorOutput(None, detection=Detection(s, alarms))


def test_detach_detaches_thresholds_and_extras():
    """``detach`` leaves no tensor of the output (the threshold and extras included) on the
    autograd graph, with the same values."""
    w = torch.ones((), requires_grad=True)
    th = torch.full((3, T), 2.0) * w
    out = EstimatorOutput(
        torch.zeros(3, T, DX) * w,
        detection=Detection(torch.zeros(3, T) * w, torch.zeros(3, T, dtype=torch.bool), th),
        extras={"ess": torch.ones(3, T) * w},
    )
    d = out.detach()
    assert not d.detection.threshold.requires_grad and not d.extras["ess"].requires_grad
    assert not d.means.requires_grad and not d.scores.requires_grad
    torch.testing.assert_close(d.detection.threshold, th.detach())


def test_generators_of():
    """One generator serves all three purposes; a Generators holding a non-generator is a
    TypeError naming the field."""
    g = torch.Generator()
    assert tuple(Generators.of(g)) == (g, g, g)
    with pytest.raises(TypeError, match="Generators.propagate"):
        Generators.of(Generators(None, 5, None))


def test_init_validates_its_carry_and_batch_shape():
    """``init`` calls ``_check_carry`` on the carry it makes, and refuses a batch shape with
    a zero; ``batch_of`` is the runs' shape."""

    class Refusing(df.KalmanFilter):
        def _check_carry(self, carry):
            raise ValueError("refused carry")

    with pytest.raises(ValueError, match="refused carry"):
        Refusing().init(model())
    with pytest.raises(ValueError, match="batch_shape"):
        df.KalmanFilter().init(model(), (2, 0))
    kf = df.KalmanFilter()
    assert kf.batch_of(kf.init(model(), (2, 3))) == (2, 3)


def test_step_refuses_measurements_of_other_runs():
    """A carry of 3 runs refuses ``y`` of runs ``(2, 3)`` (ValueError), while a carry of
    ``()`` on a model of 3 parameter sets takes one measurement per set and steps each as
    the numpy recursion of its own ``F``."""
    kf = df.KalmanFilter()
    carry = kf.init(model(), (3,))
    with pytest.raises(ValueError):
        kf.step(carry, torch.zeros(2, 3, DY, dtype=torch.float64))
    scales = np.array([0.5, 1.0, 1.5])
    Fs = F * scales[:, None, None]
    t = torch.tensor
    batched = df.LinearGaussianModel(t(Fs), t(H), t(Q), t(R), t(M0), t(P0))
    y = torch.randn(3, DY, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    _, out = kf.step(kf.init(batched, ()), y)
    for i in range(3):
        mp = Fs[i] @ M0
        Pp = Fs[i] @ P0 @ Fs[i].T + Q
        S = H @ Pp @ H.T + R
        want = mp + Pp @ H.T @ np.linalg.solve(S, y[i].numpy() - H @ mp)
        np.testing.assert_allclose(out.mean[i].numpy(), want, rtol=1e-10)


def test_a_step_reads_no_unreceived_entry():
    """A step's unreceived entries carry no information, even a NaN (under ``full_checks``
    and on the lean path of a vouched carry): the step is the numpy update on the received
    entries alone (entries 0 and 2 of 3; no input)."""
    y = torch.tensor([[0.3, float("nan"), -0.2]], dtype=torch.float64)
    mask = torch.tensor([[True, False, True]])
    idx = [0, 2]
    mp, Pp = F @ M0, F @ P0 @ F.T + Q
    Hr, Rr = H[idx], R[np.ix_(idx, idx)]
    S = Hr @ Pp @ Hr.T + Rr
    want = mp + Pp @ Hr.T @ np.linalg.solve(S, np.array([0.3, -0.2]) - Hr @ mp)
    for full in (True, False):  # the full checks, and the lean step of a vouched carry
        kf = df.KalmanFilter()
        kf.full_checks = full
        _, out = kf.step(kf.init(model(), (1,)), y, mask=mask)
        np.testing.assert_allclose(out.mean[0].numpy(), want, rtol=1e-10)


def test_result_types_follow_their_docstrings():
    """StepOutput's fields in the documented order (positional construction) and a
    GaussianState's default ``k = 0`` (the prior of ``x_0``)."""
    assert StepOutput._fields == (
        "mean", "cov", "pred_mean", "pred_cov", "innovation", "innovation_cov",
        "log_likelihood", "attack", "score", "alarm", "threshold", "extras",
    )  # fmt: skip
    assert GaussianState(torch.zeros(DX), torch.eye(DX)).k == 0


def test_records_of_a_model_of_parameter_sets_stack_runs_first_like_the_means():
    """A model of three parameter sets makes three runs of unbatched measurements: what
    ``collect`` records (and the steps' own extras) stacks runs first, as the means do
    (they had stacked time first, ``[T, 3, dx]`` beside means ``[3, T, dx]``: a review);
    each set's records are the means of that set's own filter, and a given carry agrees."""
    from difffilter.loop import open_loop

    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    base = t([[1.0, 0.2], [-0.1, 0.9]])
    Fs = torch.stack([base * s for s in (0.5, 1.0, 1.5)])

    def model(F):
        return df.LinearGaussianModel(F, t([[1.0, 0.0]]), 0.05 * torch.eye(2, dtype=torch.float64),
                                      t([[0.2]]), t([0.5, -0.3]), torch.eye(2, dtype=torch.float64))  # fmt: skip

    ys = torch.randn(6, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    record = lambda c, o: {"x": c.mean, "ll": o.log_likelihood}  # noqa: E731
    for est in (df.KalmanFilter(), df.ExtendedKalmanFilter()):
        out = open_loop(est, model(Fs), ys, collect=record)
        assert out.extras["x"].shape == (3, 6, 2) and out.extras["ll"].shape == (3, 6)
        for i in range(3):  # set i alone, filtered on its own
            alone = open_loop(est, model(Fs[i]), ys)
            torch.testing.assert_close(out.extras["x"][i], alone.means, rtol=1e-12, atol=1e-12)
            torch.testing.assert_close(out.extras["ll"][i], alone.extras["log_likelihood_increments"],
                                       rtol=1e-12, atol=1e-12)  # fmt: skip
        sets = model(Fs)
        given = open_loop(est, sets, ys, carry=est.init(sets), collect=record)
        assert given.extras["x"].shape == (3, 6, 2)
