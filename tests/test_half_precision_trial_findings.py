"""Models of half precision named (a module-operations trial): ``.half()``/``.bfloat16()``
of a model, or a LinearGaussianModel of a float16 F, had been accepted and failed at the
first draw or filter in torch's '"cholesky_cpu" not implemented for 'Half''."""

import pytest
import torch

import difffilter as df
from difffilter.models.four_tank import FourTankModel


def _linear(dtype=torch.float32):
    eye = torch.eye(2, dtype=dtype)
    return df.LinearGaussianModel(eye, eye, 0.1 * eye, eye, torch.zeros(2, dtype=dtype), eye)


@pytest.mark.parametrize("convert", ["half", "bfloat16"])
def test_a_model_converted_to_half_precision_is_named(convert):
    dtype = torch.float16 if convert == "half" else torch.bfloat16
    for model in (getattr(_linear(), convert)(), getattr(FourTankModel(), convert)()):
        with pytest.raises(ValueError, match=f"the model .its prior mean. is {dtype}"):
            model.simulate(3)
    with pytest.raises(ValueError, match="float32 or torch.float64"):
        df.kalman_filter(getattr(_linear(), convert)(), torch.zeros(5, 2, dtype=dtype))
    with pytest.raises(ValueError, match="float32 or torch.float64"):
        df.extended_kalman_filter(
            getattr(FourTankModel(), convert)(), torch.zeros(2, 5, 4, dtype=dtype)
        )
    with pytest.raises(ValueError, match=r"F \(which sets the model's dtype\) is"):
        _linear(dtype)


def test_float32_and_float64_models_still_run():
    for dtype in (torch.float32, torch.float64):
        model = _linear(dtype)
        ys = model.simulate(4, generator=torch.Generator().manual_seed(0))[1]
        assert df.kalman_filter(model, ys).means.dtype == dtype


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_noise_models_and_plants_of_half_precision_are_named_too(dtype):
    # a review: they had still failed in torch's Cholesky ("not implemented for 'Half'")
    from difffilter.models.lfc import LFCPlant
    from difffilter.models.robot import RobotModel
    from difffilter.models.tracking import TrackingModel
    from difffilter.noise import Gaussian

    with pytest.raises(ValueError, match=f"cov is {dtype}"):
        Gaussian(torch.zeros(2, dtype=dtype), torch.eye(2, dtype=dtype))
    for plant in (TrackingModel, RobotModel, LFCPlant):
        with pytest.raises(ValueError, match=f"dtype is {dtype}"):
            plant(dtype=dtype)


def test_an_integer_plant_dtype_and_a_complex_matrix_are_named():
    from difffilter.models.lfc import LFCPlant

    with pytest.raises(ValueError, match="dtype is torch.int64"):
        LFCPlant(dtype=torch.int64)  # (Ad had been truncated to 0 and ±1)
    F = torch.diag(torch.tensor([0.9 + 0.5j, 0.9 - 0.5j], dtype=torch.complex64))
    eye = torch.eye(2)
    with pytest.raises(ValueError, match="F is torch.complex64: the models are real"):
        df.LinearGaussianModel(F, eye, eye, eye, torch.zeros(2), eye)  # (imaginary part dropped)
