"""What a trial of the core filters found: a model built under ``torch.inference_mode()``
and written in place kept its old gains in an online Kalman filter, and a transition that
takes an input on a model built without ``dim_u`` failed inside the user's function."""

import pytest
import torch

import difffilter as df

F64 = torch.float64
F = torch.tensor([[0.9, 0.2], [0.0, 0.8]], dtype=F64)
H = torch.tensor([[1.0, 0.0], [0.5, 1.0]], dtype=F64)
EYE = torch.eye(2, dtype=F64)


def _exact(ys, change_at: int, F_after, R_after):
    """The Kalman filter written out, the model changed before step ``change_at`` (0-based)."""
    m, P = torch.zeros(2, dtype=F64), EYE.clone()
    for t in range(ys.shape[0]):
        A, R = (F, 0.5 * EYE) if t < change_at else (F_after, R_after)
        m, P = A @ m, A @ P @ A.T + 0.3 * EYE
        S = H @ P @ H.T + R
        K = P @ H.T @ torch.linalg.inv(S)
        m, P = m + K @ (ys[t] - H @ m), P - K @ S @ K.T
    return m, P


@pytest.mark.parametrize("written", ["F", "R"])
@pytest.mark.parametrize("mode", ["no_grad", "inference_mode"])
def test_an_online_kf_follows_a_model_written_in_place_under_inference_mode(written, mode):
    """A model made under ``inference_mode`` has tensors without a version counter: the
    gain schedule now compares their values (it had left them out, and the filter went on
    with the old ``F`` or ``R``: a covariance 0.26 off, equal to the unchanged filter's)."""
    ys = torch.randn(8, 2, generator=torch.Generator().manual_seed(41), dtype=F64)
    F_after = 1.1 * F if written == "F" else F
    R_after = 2.0 * EYE if written == "R" else 0.5 * EYE
    with getattr(torch, mode)():
        model = df.LinearGaussianModel(F.clone(), H, 0.3 * EYE, 0.5 * EYE,
                                       torch.zeros(2, dtype=F64), EYE)  # fmt: skip
        kf = df.KalmanFilter()
        carry = kf.init(model, ())
        for t in range(8):
            if t == 3:
                if written == "F":
                    model.F.copy_(F_after)
                else:
                    model.measurement_noise.cov.mul_(4.0)
            carry, _ = kf.step(carry, ys[t])
    mean, cov = _exact(ys, 3, F_after, R_after)
    torch.testing.assert_close(carry.mean, mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(carry.cov, cov, rtol=0, atol=1e-12)


def test_a_model_unchanged_under_inference_mode_keeps_its_schedule():
    """The comparison finds nothing changed: the converged gains are the same tensors."""
    with torch.inference_mode():
        model = df.LinearGaussianModel(F, H, 0.3 * EYE, 0.5 * EYE, torch.zeros(2, dtype=F64), EYE)
        kf = df.KalmanFilter()
        carry = kf.init(model, ())
        ys = torch.randn(300, 2, generator=torch.Generator().manual_seed(0), dtype=F64)
        covs = []
        for y in ys:
            carry, _ = kf.step(carry, y)
            covs.append(carry.cov)
    assert covs[-1] is covs[-2]  # the converged schedule's one covariance, handed out again


def test_a_transition_that_takes_an_input_names_a_forgotten_dim_u():
    B = torch.tensor([[0.0], [1.0]], dtype=F64)

    def f(x, u):
        return x @ F.T + u @ B.T

    with pytest.raises(ValueError, match=r"transition takes an input u but fails on u=None.*"
                                         r"give dim_u=<width of u>"):  # fmt: skip
        df.NonlinearGaussianModel(f, lambda x: x, 0.01 * EYE, EYE, torch.zeros(2, dtype=F64), EYE)
    model = df.NonlinearGaussianModel(f, lambda x: x, 0.01 * EYE, EYE,
                                      torch.zeros(2, dtype=F64), EYE, dim_u=1)  # fmt: skip
    out = df.extended_kalman_filter(model, torch.zeros(4, 2, dtype=F64),
                                    torch.ones(4, 1, dtype=F64))  # fmt: skip
    assert out.means.shape == (4, 2)

    def ignores_none(x, u):  # a transition that takes u where there is one stays accepted
        return x @ F.T if u is None else x @ F.T + u @ B.T

    df.NonlinearGaussianModel(ignores_none, lambda x: x, 0.01 * EYE, EYE,
                              torch.zeros(2, dtype=F64), EYE)  # fmt: skip


def test_us_on_a_model_without_input_says_both_fixes():
    model = df.LinearGaussianModel(F, H, 0.3 * EYE, 0.5 * EYE, torch.zeros(2, dtype=F64), EYE)
    with pytest.raises(ValueError, match=r"pass us=None, or give the model its input width"):
        df.kalman_filter(model, torch.zeros(3, 2, dtype=F64), torch.zeros(3, 1, dtype=F64))
