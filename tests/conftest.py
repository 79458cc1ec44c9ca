"""Shared fixtures: small models with known closed forms."""

from __future__ import annotations

import pytest
import torch

import difffilter as df

# Lightning attaches a stderr log handler when it is first imported; the command lines now
# import it only when a command needs it, so import it here, at collection, or the handler
# would hold the stream one test captured and fail on the next ("I/O operation on closed file")
import difffilter.train.lightning_cli  # noqa: E402, F401


@pytest.fixture(scope="session", autouse=True)
def _calibration_cache(tmp_path_factory):
    """Calibrations cached on disk go to a folder of this test session, not the user's."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("DIFFFILTER_CACHE", str(tmp_path_factory.mktemp("calibration-cache")))
        yield


def constant_velocity(
    dtype=torch.float64, q: float = 0.1, r: float = 0.5, with_input: bool = False
):
    """2-D constant-velocity model (tracking paper, eqs 16–17) with position measurements."""
    T = 1.0
    F = torch.tensor([[1, T, 0, 0], [0, 1, 0, 0], [0, 0, 1, T], [0, 0, 0, 1.0]], dtype=dtype)
    block = torch.tensor([[T**3 / 3, T**2 / 2], [T**2 / 2, T]], dtype=dtype)
    Q = q * torch.block_diag(block, block)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1, 0]], dtype=dtype)
    R = r * torch.eye(2, dtype=dtype) + 0.1 * r * torch.tensor([[0.0, 1], [1, 0]], dtype=dtype)
    B = torch.tensor([[0.5], [1.0], [0.2], [-0.3]], dtype=dtype) if with_input else None
    return df.LinearGaussianModel(
        F, H, Q, R, torch.tensor([0.0, 1, 0, -1], dtype=dtype), torch.eye(4, dtype=dtype), B=B
    )


@pytest.fixture
def cv_model():
    return constant_velocity()


@pytest.fixture
def generator():
    return torch.Generator().manual_seed(1234)
