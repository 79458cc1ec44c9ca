"""Findings of a trial of the neural compensation wrapper (``difffilter.fdi.neural``):

* the lagged residual ``e = ν − â`` of a lost entry held ``−â`` (the estimate before it was
  masked) where the docstring promises 0 for what was not received, and ``standardize``
  did nothing to it. Truth: the step's reported compensated innovation ``ν − â`` (0 where
  lost), divided by ``√diag S`` under ``standardize``, is the next step's input;
* ``load_estimator`` of a non-path named no argument, and a JSON table was told to give a
  ``.ckpt`` that does not exist.
"""

from __future__ import annotations

import math

import pytest
import torch

import difffilter
from difffilter.fdi.neural import NeuralCompensation
from difffilter.models.neural_estimator import NeuralFDIEstimator
from difffilter.ssm import LinearGaussianModel

D = torch.float64
T = 8


def _model():
    eye = torch.eye(2, dtype=D)
    return LinearGaussianModel(torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=D), eye, 0.01 * eye,
                               0.04 * eye, torch.zeros(2, dtype=D), eye)  # fmt: skip


def _steps(standardize, mask):
    net = NeuralFDIEstimator(num_areas=1, area_dim=2, a=1, b=2, hidden=5, init_scale=0.5,
                             init="symmetric", detection_head=False, seed=1)  # fmt: skip
    est = NeuralCompensation(net, difffilter.KalmanFilter(), residual="lagged",
                             standardize=standardize, record_inputs=True)  # fmt: skip
    ys = 0.3 * torch.randn(1, T, 2, dtype=D, generator=torch.Generator().manual_seed(0))
    outs = []
    with torch.no_grad():
        carry = est.init(_model(), (1,))
        for k in range(T):
            carry, out = est.step(carry, ys[:, k], None, mask[:, k])
            outs.append(out)
    return outs


@pytest.mark.parametrize("standardize", [False, True])
def test_the_lagged_residual_is_the_compensated_innovation_standardised_and_masked(standardize):
    mask = torch.ones(1, T, 2, dtype=torch.bool)
    mask[:, 4, 1] = False  # entry 1 lost at step 4
    outs = _steps(standardize, mask)
    for k in range(T - 1):
        e = outs[k].innovation  # ν − â: the compensated innovation the step reports
        if standardize:
            e = e / outs[k].innovation_cov.diagonal(dim1=-2, dim2=-1).sqrt()
        e = e * mask[:, k].to(D)
        # δ_{k+1} = [â_k (2), e_k (2), e_{k−1} (2)]
        torch.testing.assert_close(outs[k + 1].extras["network_inputs"][:, 2:4], e,
                                   rtol=1e-12, atol=1e-15)  # fmt: skip
    assert float(outs[5].extras["network_inputs"][0, 3]) == 0.0  # the lost entry's e_4


def test_load_estimator_names_a_path_that_is_none_and_a_json_without_its_checkpoint(tmp_path):
    for bad in (3, None):
        with pytest.raises(TypeError, match="ckpt: the checkpoint's path must be a str or"):
            difffilter.load_estimator(bad)
    table = tmp_path / "table.json"
    table.write_text("{}")
    with pytest.raises(ValueError, match=r"is JSON \(a card or a table\) with no checkpoint "
                                         r"beside it, not a checkpoint$"):  # fmt: skip
        difffilter.load_estimator(table)
    (tmp_path / "table.ckpt").write_bytes(b"")
    with pytest.raises(ValueError, match=r"is a checkpoint's card \(JSON\), not the checkpoint: "
                                         r"give .*table\.ckpt"):  # fmt: skip
        difffilter.load_estimator(table)


@pytest.mark.parametrize("dim_u", [1, 3])
def test_an_actuator_network_on_a_plant_of_another_input_width_is_refused(dim_u):
    """A checkpoint trial: the estimate is added to the input, ``u + â``; a 2-wide network on
    a 1-input plant had broadcast the input to 2 without a word (or failed in torch's raw
    matmul error on a linear plant), where the sensor twin is refused by name."""
    net = NeuralFDIEstimator(num_areas=1, area_dim=2, a=1, b=1, hidden=3, resid_dim=2,
                             detection_head=False, seed=0)  # fmt: skip
    est = NeuralCompensation(net, difffilter.KalmanFilter(), channel="actuator",
                             residual="innovation")  # fmt: skip
    eye = torch.eye(2, dtype=D)
    B = torch.ones(2, dim_u, dtype=D)
    plant = LinearGaussianModel(0.9 * eye, eye, 0.01 * eye, 0.04 * eye, torch.zeros(2, dtype=D),
                                eye, B=B)  # fmt: skip
    with pytest.raises(ValueError, match=f"dim_u = {dim_u}: the network was made for another"):
        est.init(plant, (1,))
    fits = LinearGaussianModel(0.9 * eye, eye, 0.01 * eye, 0.04 * eye, torch.zeros(2, dtype=D),
                               eye, B=eye)  # fmt: skip
    carry = est.init(fits, (1,))
    _, out = est.step(carry, torch.zeros(1, 2, dtype=D), torch.zeros(1, 2, dtype=D))
    assert out.attack.shape == (1, 2)


@pytest.mark.parametrize("bad", [float("nan"), True, "0.5", None])
def test_the_alarm_threshold_is_checked_when_made_and_when_set_later(bad):
    """A NaN threshold built and ran and never alarmed (``score > nan``), ``True`` read as
    1.0 and ``"0.5"`` as 0.5; the LFC entries set it after construction, unchecked."""
    dt = torch.float64
    eye = torch.eye(2, dtype=dt)
    model = LinearGaussianModel(0.9 * eye, eye, 0.1 * eye, 0.2 * eye, torch.zeros(2, dtype=dt), eye)
    net = NeuralFDIEstimator(num_areas=1, area_dim=2, a=1, b=1, hidden=4, init_scale=0.8,
                             init="symmetric", seed=0)  # fmt: skip
    with pytest.raises(ValueError, match="threshold must be a number"):
        NeuralCompensation(net, difffilter.KalmanFilter(), threshold=bad)
    estimator = NeuralCompensation(net, difffilter.KalmanFilter(), threshold=0.5)
    with pytest.raises(ValueError, match="threshold must be a number"):
        estimator.threshold = bad
    estimator.threshold = torch.tensor(0.25, dtype=dt)  # a one-entry tensor is a number
    assert estimator.threshold == 0.25 and isinstance(estimator.threshold, float)
    ys = torch.randn(2, 6, 2, generator=torch.Generator().manual_seed(0), dtype=dt)
    out = difffilter.open_loop(estimator, model, ys)
    assert torch.equal(out.detection.alarms, out.detection.scores > 0.25)
    estimator.threshold = -math.inf  # ±inf allowed, as on a card: every step alarms
    assert bool(difffilter.open_loop(estimator, model, ys).detection.alarms.all())
