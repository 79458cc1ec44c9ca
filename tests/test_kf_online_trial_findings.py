"""Findings of a red-team trial of the Kalman filter's online paths (each failed before its
fix)."""

from __future__ import annotations

import pytest
import torch

import difffilter as df

D = torch.float64


def _model():
    F = torch.tensor([[0.9, 0.2], [-0.1, 0.8]], dtype=D)
    H = torch.tensor([[1.0, 0.0]], dtype=D)
    return df.LinearGaussianModel(F, H, 0.05 * torch.eye(2, dtype=D), 0.3 * torch.eye(1, dtype=D),
                                  torch.zeros(2, dtype=D), torch.eye(2, dtype=D))  # fmt: skip


def _ys(model, steps=20):
    return model.simulate(steps, (), generator=torch.Generator().manual_seed(3))[1]


def _online(model, ys, change=None, at=5):
    kf, carry = df.KalmanFilter(), None
    carry = kf.init(model)
    total = 0.0
    for k, y in enumerate(ys):
        if k == at and change is not None:
            change(model)
        carry, out = kf.step(carry, y)
        total = total + out.log_likelihood
    return carry, total


def test_a_new_tensor_given_through_data_drops_the_gain_schedule():
    """F.data = new (as vector_to_parameters assigns) kept the version counter, and the
    online step went on with the old gains (0.67 off the mean)."""
    model = _model()
    ys = _ys(model)
    new = torch.tensor([[0.5, 0.3], [0.1, 0.6]], dtype=D)

    def data_assign(m):
        m.F.data = new.clone()

    def vector(m):
        torch.nn.utils.vector_to_parameters(new.reshape(-1), [m.F])

    for change in (data_assign, vector):
        model = _model()
        carry, _ = _online(model, ys, change)
        ref = _model()
        ref_carry, _ = _online(ref, ys, lambda m: setattr(m, "F", new.clone()))
        torch.testing.assert_close(carry.mean, ref_carry.mean)
        torch.testing.assert_close(carry.cov, ref_carry.cov)


def test_a_matrix_made_to_require_a_gradient_is_differentiated_through_the_covariances():
    """requires_grad_() after init kept the schedule computed without autograd: dLL/dF
    missed every path through the gains (1.5 off the whole-sequence filter's)."""
    model = _model()
    ys = _ys(model, 15)
    _, total = _online(model, ys, lambda m: m.F.requires_grad_(True), at=0)
    (online,) = torch.autograd.grad(total, model.F)
    whole = _model()
    whole.F.requires_grad_(True)
    (want,) = torch.autograd.grad(df.kalman_filter(whole, ys).log_likelihood.sum(), whole.F)
    torch.testing.assert_close(online, want)


def _textbook(F_of, H, Q, R, P0, ys, offset_of=lambda t: 0.0):
    """A plain float64 Kalman filter (numpy), ``F_of(t)`` and a process-noise mean per step."""
    import numpy as np

    m, P = np.zeros(P0.shape[0]), P0.copy()
    for t, y in enumerate(ys):
        m, P = F_of(t) @ m + offset_of(t), F_of(t) @ P @ F_of(t).T + Q
        K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
        m, P = m + K @ (y - H @ m), (np.eye(len(m)) - K @ H) @ P
    return m, P


def test_a_noise_of_non_zero_mean_assigned_between_steps_is_refused():
    """A second trial: ``init`` refuses it, but assigned between steps it triggered the full
    checks, which never looked at the mean: dropped without a word ([1.51, 0.87] where the
    textbook honouring E[w] = 1 gives [3.22, 2.95])."""
    import numpy as np

    d = torch.float64
    model = df.LinearGaussianModel(torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=d),
                                   torch.tensor([[1.0, 0.0]], dtype=d), 0.1 * torch.eye(2, dtype=d),
                                   torch.tensor([[0.5]], dtype=d), torch.zeros(2, dtype=d),
                                   torch.eye(2, dtype=d))  # fmt: skip
    kf, ys = df.KalmanFilter(), torch.tensor(np.random.default_rng(0).standard_normal((5, 1)))
    carry = kf.init(model)
    carry, _ = kf.step(carry, ys[0])
    model.process_noise = df.noise.Gaussian(torch.ones(2, dtype=d), 0.1 * torch.eye(2, dtype=d))
    with pytest.raises(ValueError, match=r"model.process_noise has mean \[1.0, 1.0\]"):
        kf.step(carry, ys[1])


def test_a_restored_schedule_sees_the_first_assignment_of_a_new_process(tmp_path):
    """A second trial: the schedule compared a process-wide count of assignments with the
    one it stored, and the count starts at 0 in each process: saved after one assignment,
    restored where ``model.F = F2`` was the first, the counts matched and the old gains
    went on (the mean 0.17 off the textbook)."""
    import ast
    import subprocess
    import sys

    import numpy as np

    F, F2 = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.9, 0.2], [-0.1, 0.95]])
    H, Q, R, P0 = np.array([[1.0, 0.0]]), 0.1 * np.eye(2), np.array([[0.5]]), np.eye(2)
    ys, path = np.random.default_rng(13).standard_normal((60, 1)), tmp_path / "carry.pt"
    saving = f"""
import numpy as np, torch
import difffilter as df
from difffilter.noise import Gaussian
d = torch.float64
model = df.LinearGaussianModel(*(torch.tensor(a, dtype=d) for a in
    ({F.tolist()}, {H.tolist()}, {Q.tolist()}, [[1.0]], [0.0, 0.0], {P0.tolist()})))
model.measurement_noise = Gaussian(torch.zeros(1, dtype=d), torch.tensor({R.tolist()}, dtype=d))
ys = np.random.default_rng(13).standard_normal((60, 1))
kf = df.KalmanFilter(); c = kf.init(model)
for t in range(30):
    c, _ = kf.step(c, torch.tensor(ys[t]))
torch.save(c, {str(path)!r})
"""
    resuming = f"""
import numpy as np, torch
import difffilter as df
ys = np.random.default_rng(13).standard_normal((60, 1))
c = torch.load({str(path)!r}, weights_only=False)
c.model.F = torch.tensor({F2.tolist()}, dtype=torch.float64)
kf = df.KalmanFilter()
for t in range(30, 60):
    c, out = kf.step(c, torch.tensor(ys[t]))
print(repr(out.mean.tolist()))
"""
    subprocess.run([sys.executable, "-c", saving], check=True, timeout=300)
    done = subprocess.run([sys.executable, "-c", resuming], check=True, timeout=300,
                          capture_output=True, text=True)  # fmt: skip
    mean, _ = _textbook(lambda t: F if t < 30 else F2, H, Q, R, P0, ys)
    got = ast.literal_eval(done.stdout.strip().splitlines()[-1])
    np.testing.assert_allclose(got, mean, rtol=1e-9)


class _DerivedF(df.LinearGaussianModel):
    """Time-invariant, ``F = expm(A dt)`` read from a buffer ``A`` at every call (a fresh
    tensor each time: nothing the schedule was handed is written when ``A`` is)."""

    def __init__(self, A, dt, *rest):
        super().__init__(torch.matrix_exp(A * dt), *rest)
        self.register_buffer("A", A)
        self.dt = dt

    def transition_matrix(self, k):
        return torch.matrix_exp(self.A * self.dt)


def test_a_buffer_the_transition_is_made_from_written_in_place_drops_the_gain_schedule():
    """A third trial: the schedule watched the tensors the model's methods returned and the
    noise models', not the model's own buffer ``A`` of ``F = expm(A dt)``: after
    ``model.A.copy_(A2)`` under ``no_grad`` the online step went on with the old ``F`` (the
    mean 0.1 and the covariance 0.40 off the textbook filter with the new one)."""
    import numpy as np

    A = torch.tensor([[0.0, 1.0], [-1.0, -0.2]], dtype=D)
    A2 = torch.tensor([[0.0, 2.0], [-3.0, -0.5]], dtype=D)
    H, Q, R, P0 = np.array([[1.0, 0.0]]), 0.1 * np.eye(2), np.array([[0.5]]), np.eye(2)
    model = _DerivedF(
        A.clone(), 0.1, *(torch.tensor(a, dtype=D) for a in (H, Q, R, [0.0, 0.0], P0))
    )
    ys = np.random.default_rng(12).standard_normal((100, 1))
    kf = df.KalmanFilter()
    carry = kf.init(model)
    for t, y in enumerate(ys):
        if t == 40:
            assert carry.gains is not None  # (the schedule's path until the write)
            with torch.no_grad():
                model.A.copy_(A2)
        carry, _ = kf.step(carry, torch.tensor(y))
    F_of = [torch.matrix_exp(a * 0.1).numpy() for a in (A, A2)]
    mean, cov = _textbook(lambda t: F_of[t >= 40], H, Q, R, P0, ys)
    np.testing.assert_allclose(carry.mean.numpy(), mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(carry.cov.numpy(), cov, rtol=1e-9, atol=1e-12)


def test_a_start_carry_reused_after_the_prior_covariance_written_in_place_filters_from_it():
    """A third trial: a ``k = 0`` carry kept as the start of each episode holds the prior's
    covariance tensor itself; after ``model.initial.cov.copy_(10 I)`` it held the new prior
    but stepped with the schedule computed from the old one (the first covariance 8.9 and
    the mean 0.29 off the textbook filter from the new prior)."""
    import numpy as np

    F, H = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[1.0, 0.0]])
    Q, R, P0 = 0.1 * np.eye(2), np.array([[0.5]]), np.eye(2)
    model = df.LinearGaussianModel(
        *(torch.tensor(a, dtype=D) for a in (F, H, Q, R, [0.0, 0.0], P0))
    )
    ys = np.random.default_rng(17).standard_normal((3, 1))
    kf = df.KalmanFilter()
    start = kf.init(model)

    def episode(carry):
        for y in ys:
            carry, _ = kf.step(carry, torch.tensor(y))
        return carry

    first = episode(start)
    assert first.gains is not None  # (the schedule's path: its moments computed and kept)
    with torch.no_grad():
        model.initial.cov.copy_(10 * torch.eye(2, dtype=D))
    second = episode(start)
    mean, cov = _textbook(lambda t: F, H, Q, R, 10 * np.eye(2), ys)
    np.testing.assert_allclose(second.mean.numpy(), mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(second.cov.numpy(), cov, rtol=1e-9, atol=1e-12)
    # and a new start from the model so changed takes a schedule of the new prior
    again = episode(kf.init(model))
    assert again.gains is not None
    np.testing.assert_allclose(again.cov.numpy(), cov, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("field", ["innovation_cov", "pred_cov"])
def test_a_step_outputs_s_or_prior_covariance_written_in_place_changes_no_later_step(field):
    """Once the gain has converged every step's output holds the schedule's own ``S`` and
    ``P⁻``, shared with the later steps: ``S = out.innovation_cov; S += 100`` (a caller's own
    inflated S, thought a copy) had become every later step's S (100.24 against 0.24) beside
    an unchanged log-likelihood (an online-step trial). The later steps now compute their
    own, equal (to round-off) to those of the run without the write; a write before convergence, to
    moments no later step shares, leaves the schedule on."""
    model = _model()
    ys = model.simulate(260, (), generator=torch.Generator().manual_seed(4))[1]
    kf = df.KalmanFilter()
    runs = {}
    for write in (False, True):
        carry, outs = kf.init(model), []
        for k, y in enumerate(ys):
            carry, out = kf.step(carry, y)
            outs.append(out)
            if write and k == 199:
                assert carry.gains is not None and carry.gains.converged
                getattr(out, field).add_(100.0)
        runs[write] = (carry, outs)
    (_, clean), (carry, written) = runs[False], runs[True]
    for a, b in zip(clean[200:], written[200:]):
        for name in ("mean", "cov", "pred_cov", "innovation_cov", "log_likelihood"):
            torch.testing.assert_close(getattr(b, name), getattr(a, name), rtol=1e-9, atol=1e-12)
    assert carry.gains is None  # (the general update from then on)
    # before convergence: step 3's S is step 3's alone, the schedule goes on
    carry = kf.init(model)
    for k, y in enumerate(ys[:5]):
        carry, out = kf.step(carry, y)
        if k == 2:
            assert not carry.gains.converged
            getattr(out, field).add_(100.0)
    assert carry.gains is not None
