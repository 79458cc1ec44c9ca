"""Findings of a trial of copies, pickles and saves of carries and estimators, each checked
against the run that was never copied."""

from __future__ import annotations

import copy
import gc
import io
import pickle
import weakref

import pytest
import torch
from torch import nn

import difffilter as df
from difffilter.fdi.mdpf import AdaptiveParticleFilter
from difffilter.noise import Gaussian

F64 = torch.float64


def _linear(a: float = 0.98, inputs: bool = False) -> df.LinearGaussianModel:
    eye = torch.eye(2, dtype=F64)
    B = torch.tensor([[0.0], [0.1]], dtype=F64) if inputs else None
    return df.LinearGaussianModel(
        torch.tensor([[1.0, 0.1], [0.0, a]], dtype=F64), torch.tensor([[1.0, 0.0]], dtype=F64),
        0.01 * eye, 0.25 * torch.eye(1, dtype=F64), torch.zeros(2, dtype=F64), eye, B=B,
    )  # fmt: skip


def _saved(obj):
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    buffer.seek(0)
    return torch.load(buffer, weights_only=False)


COPIES = {
    "deepcopy": copy.deepcopy,
    "pickle": lambda obj: pickle.loads(pickle.dumps(obj)),
    "torch.save": _saved,
}


@pytest.mark.parametrize("how", COPIES)
@pytest.mark.parametrize("steps", [1, 5])
def test_a_kalman_carry_on_its_gain_schedule_continues_after_a_copy(how, steps):
    """The gain schedule stamps each covariance it hands out with its version counter;
    a copy's tensors count from 0 again, and a restored carry had been refused at its next
    step as "written in place". Now it continues bit for bit."""
    model = _linear()
    _, ys, _ = model.simulate(20, (1,), generator=torch.Generator().manual_seed(0))
    kf, ys = df.KalmanFilter(), ys[0]
    carry = kf.init(model, ())
    for k in range(steps):
        carry, _ = kf.step(carry, ys[k])
    copied, reference = COPIES[how](carry), carry
    for k in range(steps, 20):
        reference, expected = kf.step(reference, ys[k])
        copied, got = kf.step(copied, ys[k])
        assert torch.equal(got.mean, expected.mean) and torch.equal(got.cov, expected.cov)


def test_a_copy_keeps_what_was_written_before_it():
    """The copy stamps anew only what was unchanged when it was made: a covariance written
    in place before the copy is still refused, and a model written in place before it is
    still read again (the general update of the new model)."""
    model = _linear()
    ys = torch.randn(8, 1, generator=torch.Generator().manual_seed(1), dtype=F64)
    kf = df.KalmanFilter()
    carry = kf.init(model, ())
    for k in range(3):
        carry, _ = kf.step(carry, ys[k])
    written = carry._replace()
    written.cov.mul_(1.0)  # (in place: the schedule's own covariance)
    with pytest.raises(ValueError, match="carry.cov was written in place"):
        kf.step(copy.deepcopy(written), ys[3])
    with torch.no_grad():
        model.F[1, 1] = 0.5
    copied = copy.deepcopy(kf.init(model, ()))
    general = kf.init(model, ())._replace(gains=None)
    for k in range(8):
        copied, got = kf.step(copied, ys[k])
        general, expected = kf.step(general, ys[k])
    torch.testing.assert_close(got.mean, expected.mean, rtol=0, atol=1e-12)


def test_a_particle_carry_of_large_log_likelihoods_passes_its_own_checks():
    """On the tracking plant a step's log-weights carry round-off of ε·|log-likelihood|
    (2.2e-13 relative): the full check of a carry's cached weights (1e3 ε) had refused the
    step's own carry, after a copy (which loses the step's vouching) and under
    ``full_checks`` at every few steps. Now the copy continues bit for bit."""
    from difffilter.models import registry
    from difffilter.models.streams import Streams

    scenario = registry.get("tracking_rrp_deception")
    model = scenario.system()
    ys = scenario.simulate(1, Streams(0).simulation()).y_recv[0, :12]
    pf, strict = df.ParticleFilter(500), df.ParticleFilter(500)
    strict.full_checks = True
    with torch.no_grad():
        carry = pf.init(model, (), torch.Generator().manual_seed(1))
        checked = strict.init(model, (), torch.Generator().manual_seed(1))
        for k in range(12):
            carry, out = pf.step(carry, ys[k])
            checked, checked_out = strict.step(checked, ys[k])
            if k < 11:  # a copy steps on as the carry itself does (its generators copied)
                copied_out = pf.step(copy.deepcopy(carry), ys[k + 1])[1]
                own = carry._replace(generators=copy.deepcopy(carry.generators))
                assert torch.equal(copied_out.mean, pf.step(own, ys[k + 1])[1].mean)
        assert torch.equal(out.mean, checked_out.mean)


def test_the_adaptive_particle_filter_holds_no_model_it_has_stepped():
    """``AdaptiveParticleFilter`` had kept a filter per model in a dict (strong references,
    never emptied): every model stepped stayed alive with the estimator and was pickled with
    it. Now only the last one's filter is kept, and a pickle holds the options alone; two
    models stepped in turn equal each stepped alone."""
    est = AdaptiveParticleFilter(50)
    y, u = torch.zeros(1, dtype=F64), torch.zeros(1, dtype=F64)
    refs, size = [], None
    with torch.no_grad():
        for _ in range(10):
            model = _linear(inputs=True)
            carry, _ = est.step(est.init(model, (), torch.Generator().manual_seed(0)), y, u)
            refs.append(weakref.ref(model))
            size = size or len(pickle.dumps(est))
            del model, carry
    gc.collect()
    assert sum(r() is not None for r in refs) <= 1
    assert len(pickle.dumps(est)) == size

    ys = torch.randn(6, 1, generator=torch.Generator().manual_seed(0), dtype=F64)
    us = torch.randn(6, 1, generator=torch.Generator().manual_seed(1), dtype=F64)
    models = (_linear(0.98, True), _linear(0.9, True))

    def alone(model):
        est = AdaptiveParticleFilter(50)
        carry, means = est.init(model, (), torch.Generator().manual_seed(0)), []
        for k in range(6):
            carry, out = est.step(carry, ys[k], us[k])
            means.append(out.mean)
        return torch.stack(means)

    shared = AdaptiveParticleFilter(50)
    carries = [shared.init(m, (), torch.Generator().manual_seed(0)) for m in models]
    means = [[], []]
    for k in range(6):
        for i in (0, 1):
            carries[i], out = shared.step(carries[i], ys[k], us[k])
            means[i].append(out.mean)
    for i, model in enumerate(models):
        assert torch.equal(torch.stack(means[i]), alone(model))


class _Pendulum(df.StateSpaceModel):
    dim_x, dim_y, dim_u = 2, 1, 0

    def __init__(self):
        super().__init__()
        self.damping = nn.Parameter(torch.tensor(0.1, dtype=F64))
        eye = torch.eye(2, dtype=F64)
        self.initial = Gaussian(torch.tensor([1.0, 0.0], dtype=F64), 0.1 * eye)
        self.process_noise = Gaussian(torch.zeros(2, dtype=F64), 1e-3 * eye)
        self.measurement_noise = Gaussian(torch.zeros(1, dtype=F64), 1e-2 * torch.eye(1, dtype=F64))

    def transition(self, x, u, k):
        p, v = x[..., 0], x[..., 1]
        return torch.stack([p + 0.05 * v, v + 0.05 * (-torch.sin(p) - self.damping * v)], -1)

    def observe(self, x, k):
        return torch.sin(x[..., :1])


def test_an_ekf_carry_from_inference_mode_steps_on_with_gradients():
    """A carry stepped under ``torch.inference_mode()`` and then with gradients on (a model
    with a parameter) had failed with an error that blamed the user's transition ("must be
    written in torch operations"); the UKF stepped it. Now the EKF steps it as it steps the
    same values from a normal carry, and the gradient reaches the parameter."""
    model, y = _Pendulum(), torch.tensor([0.3], dtype=F64)
    ekf = df.ExtendedKalmanFilter()
    with torch.inference_mode():
        inference_carry, _ = ekf.step(ekf.init(model, ()), y)
    normal = inference_carry._replace(mean=inference_carry.mean.clone(),
                                      cov=inference_carry.cov.clone())  # fmt: skip
    _, got = ekf.step(inference_carry, y)
    _, expected = ekf.step(normal, y)
    assert torch.equal(got.mean, expected.mean)
    (grad,) = torch.autograd.grad(got.log_likelihood, model.damping)
    (expected_grad,) = torch.autograd.grad(expected.log_likelihood, model.damping)
    assert torch.isfinite(grad) and torch.equal(grad, expected_grad)
