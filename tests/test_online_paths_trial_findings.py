"""The lean online step's dispatch and vouching (a red-team trial).

* A ParticleFilter subclass adjusting ``super()._step``'s output had it applied twice at
  batch ``(1,)``: the one-run dispatch called ``self._step``, the override, again.
* The lean step checked the mask's dtype and shape but not its device (torch's bare error).
* ``num_particles`` or ``cov_dims`` set after ``init`` went unseen by the lean step (a 0 × 0
  covariance, 50 particles stepped for 20).
"""

import pytest
import torch

import difffilter as df

d = torch.float64


def _model(dx=2, dy=2):
    return df.LinearGaussianModel(0.9 * torch.eye(dx, dtype=d), torch.eye(dy, dx, dtype=d),
                                  0.1 * torch.eye(dx, dtype=d), 0.5 * torch.eye(dy, dtype=d),
                                  torch.zeros(dx, dtype=d), torch.eye(dx, dtype=d))  # fmt: skip


class _Shifted(df.ParticleFilter):
    """Reports the mean shifted by +10, counting its steps."""

    calls = 0

    def _step(self, carry, y, u, mask):
        type(self).calls += 1
        carry, out = super()._step(carry, y, u, mask)
        return carry, out._replace(mean=out.mean + 10.0)


def test_a_subclass_step_is_applied_once_at_a_batch_of_one():
    y = torch.tensor([0.3, -0.2], dtype=d)
    means = {}
    for batch in [(), (1,)]:
        pf, _Shifted.calls = _Shifted(50), 0
        carry = pf.init(_model(), batch, torch.Generator().manual_seed(0))
        _, out = pf.step(carry, y.expand(*batch, 2))
        assert _Shifted.calls == 1
        means[batch] = out.mean.reshape(2)
    torch.testing.assert_close(means[(1,)], means[()], rtol=1e-12, atol=1e-12)  # was +10 off


@pytest.mark.parametrize("make", [lambda: df.ParticleFilter(20), df.KalmanFilter])
def test_a_mask_on_another_device_is_named_by_the_lean_step(make):
    estimator, y = make(), torch.tensor([0.3, -0.2], dtype=d)
    carry = estimator.init(_model(), (), torch.Generator().manual_seed(0))
    carry, _ = estimator.step(carry, y)  # vouched from here on
    mask = torch.ones(2, dtype=torch.bool, device="meta")
    with pytest.raises(ValueError, match="mask is on meta and y on cpu"):
        estimator.step(carry, y, mask=mask)


def test_settings_replaced_after_init_are_checked():
    y = torch.tensor([0.3, -0.2], dtype=d)
    pf = df.ParticleFilter(50)
    carry = pf.init(_model(3), (), torch.Generator().manual_seed(0))
    carry, _ = pf.step(carry, y)
    with pytest.raises(ValueError, match="cov_dims must be None or an integer"):
        pf.cov_dims = 0
    pf.cov_dims = 7  # a valid setting in general, not for this carry's 3 states
    with pytest.raises(ValueError, match="cov_dims"):
        pf.step(carry, y)
    pf.cov_dims = None
    pf.num_particles = 20
    with pytest.raises(ValueError, match="num_particles = 20"):
        pf.step(carry, y)
    pf.num_particles = 50
    _, out = pf.step(carry, y)
    assert out.cov.shape == (3, 3)
