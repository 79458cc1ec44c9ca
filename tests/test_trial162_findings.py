"""Findings of a user trial: a security researcher's detector of their own (trial 162)."""

from typing import Any, NamedTuple

import pytest
import torch

import difffilter as df
from difffilter._imports import import_plugin
from difffilter.estimator import Estimator
from difffilter.loop import open_loop


class _Carry(NamedTuple):
    inner: Any
    z: torch.Tensor
    model: Any


class _EwmaNis(Estimator):
    """An EWMA of a Kalman filter's NIS whose carry holds the filter's as ``inner`` (no
    ``mean`` of its own) and that does not override ``batch_of``."""

    carry_type = _Carry

    def __init__(self):
        self.filter = df.KalmanFilter()

    def _init(self, model, batch_shape, generators):
        inner = self.filter._init(model, batch_shape, generators)
        return _Carry(inner, torch.zeros(tuple(batch_shape), dtype=inner.mean.dtype), model)

    def _check_carry(self, carry):
        self.filter._check_carry(carry.inner)

    def _step(self, carry, y, u, mask):
        new, out = self.filter._step(carry.inner, y, u, mask)
        z = 0.8 * carry.z + 0.2 * df.fdi.normalized_innovation_squared(
            out.innovation, out.innovation_cov
        )
        return _Carry(new, z, carry.model), out._replace(score=z, alarm=z > 10.0)


def _model():
    f64 = dict(dtype=torch.float64)
    return df.LinearGaussianModel(
        torch.eye(2, **f64), torch.eye(2, **f64), 1e-2 * torch.eye(2, **f64),
        1e-2 * torch.eye(2, **f64), torch.zeros(2, **f64), torch.eye(2, **f64),
    )  # fmt: skip


def test_estimator_without_mean_in_its_carry_is_told_to_override_batch_of():
    # the default batch_of read carry.mean: a bare AttributeError ("'_Carry' object has no
    # attribute 'mean'") from inside init, naming neither batch_of nor the fix
    with pytest.raises(TypeError, match=r"_EwmaNis\.batch_of.*override batch_of"):
        _EwmaNis().init(_model(), (3,))


def test_estimator_that_overrides_batch_of_runs():
    class Fixed(_EwmaNis):
        def batch_of(self, carry):
            return carry.inner.mean.shape[:-1]

    model = _model()
    _, ys, _ = model.simulate(10, (3,), generator=torch.Generator().manual_seed(0))
    out = open_loop(Fixed(), model, ys)
    assert out.detection.scores.shape == (3, 10)


def test_import_of_a_file_path_says_to_give_a_module_name():
    # "--import trial/my_detectors.py" had said only "No module named 'trial/my_detectors'"
    with pytest.raises(ValueError, match=r"module's name, not a file's path.*'my_detectors'"):
        import_plugin("trial/my_detectors.py", "--import trial/my_detectors.py")


def test_stealthy_threat_against_an_unknown_detector_names_the_python_route():
    # the threat set refuses a registered detector of one's own (no step object): the error
    # listed the craftable names only, not how to craft against one's own
    from difffilter.eval.stealthy import StealthySpec

    with pytest.raises(ValueError, match=r"got 'ewma_nis_ekf'.*craft_stealthy_attack"):
        StealthySpec(against="ewma_nis_ekf")


class _WindowCarry(NamedTuple):
    inner: Any
    window: torch.Tensor  # [..., W]: the last W NIS values
    k: int
    model: Any


class _WindowNis(Estimator):
    """A Kalman filter scored by its NIS summed over the last ``W`` steps, NaN while the
    window is not full (docs/adding-a-scenario.md, "A warm-up of several steps is best NaN")."""

    carry_type = _WindowCarry
    W = 3

    def __init__(self):
        self.filter = df.KalmanFilter()

    def batch_of(self, carry):
        return carry.inner.mean.shape[:-1]

    def _init(self, model, batch_shape, generators):
        inner = self.filter._init(model, batch_shape, generators)
        window = torch.zeros((*batch_shape, self.W), dtype=inner.mean.dtype)
        return _WindowCarry(inner, window, 0, model)

    def _check_carry(self, carry):
        self.filter._check_carry(carry.inner)

    def _step(self, carry, y, u, mask):
        new, out = self.filter._step(carry.inner, y, u, mask)
        g = df.fdi.normalized_innovation_squared(out.innovation, out.innovation_cov)
        window = torch.cat([carry.window[..., 1:], g.unsqueeze(-1)], -1)
        s = window.sum(-1)
        if carry.k + 1 < self.W:
            s = torch.full_like(s, float("nan"))
        carry = _WindowCarry(new, window, carry.k + 1, carry.model)
        return carry, out._replace(score=s, alarm=s > 20.0)


@pytest.mark.parametrize("onset", [1, 2])
def test_stealthy_crafting_takes_a_nan_score_as_no_score(onset):
    # a NaN score is a step without a score (calibration, scoring: never alarms); the
    # crafting took the spread of the attacked steps' scores with the NaN warm-up in it and
    # refused: "needs ... at least two attacked (run, step) pairs, all finite ...; got 80"
    from difffilter.stealthy import StealthySettings, craft_stealthy_attack

    model = _model()
    xs, ys, _ = model.simulate(20, (4,), generator=torch.Generator().manual_seed(1))
    attack = craft_stealthy_attack(
        _WindowNis(), model, ys, xs, 12.0, far=0.01, onset=onset,
        settings=StealthySettings(iterations=3, slack=0.05),
    )  # fmt: skip
    assert len(attack.history) == 3
    for _, error, excess, rate, _ in attack.history:  # J, p̃(a) − p̃(0), p(a): all finite
        assert all(map(torch.isfinite, map(torch.tensor, (error, excess, rate))))
