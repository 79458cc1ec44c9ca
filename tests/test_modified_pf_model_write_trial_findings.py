"""The modified particle filter follows a model written in place mid-run (an aliasing trial:
its carry had kept eq. (35)'s ``(G, K)`` from ``init``, ``G`` the model's own ``H`` and ``K``
computed then, so that after ``H ← 2H`` the step met the new ``G`` with the old ``K``, β 0.11
off). Truth: the same filter given a mask of all ``True``, whose step computes ``(G, K)``
from the model at every step."""

import torch

import difffilter as df
import difffilter.fdi as fdi
from difffilter.estimator import Generators

F64 = torch.float64


def _run(masked: bool, write_h: bool):
    eye = torch.eye(2, dtype=F64)
    F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=F64)
    model = df.LinearGaussianModel(F, eye.clone(), 0.01 * eye, 0.1 * eye,
                                   torch.zeros(2, dtype=F64), eye)  # fmt: skip
    ys = torch.randn(3, 8, 2, dtype=F64, generator=torch.Generator().manual_seed(0))
    est = fdi.ModifiedParticleFilter(64, fdi.PoADetector(0.3, 0.5), torch.full((3, 8, 2), 0.3,
                                                                               dtype=F64))  # fmt: skip
    carry = est.init(model, (3,), Generators(*(torch.Generator().manual_seed(i) for i in range(3))))
    means, scores = [], []
    for k in range(8):
        if k == 2 and write_h:
            with torch.no_grad():
                model.H.mul_(2.0)
        mask = torch.ones(3, 2, dtype=torch.bool) if masked else None
        carry, out = est.step(carry, ys[:, k], mask=mask)
        means.append(out.mean)
        scores.append(out.score)
    return torch.stack(means), torch.stack(scores)


def test_a_model_written_mid_run_is_followed_as_the_per_step_gain_follows_it():
    plain, masked = _run(False, True), _run(True, True)
    torch.testing.assert_close(plain[1], masked[1], rtol=0, atol=1e-12)
    torch.testing.assert_close(plain[0], masked[0], rtol=0, atol=1e-12)


def test_an_unchanged_model_gives_the_masked_steps_numbers():
    plain, masked = _run(False, False), _run(True, False)
    torch.testing.assert_close(plain[0], masked[0], rtol=0, atol=1e-12)
    assert not torch.equal(_run(False, True)[0], plain[0])  # the write changes the run
