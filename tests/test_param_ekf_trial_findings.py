"""Findings of a red-team trial of the EKF over a network's weights (each failed before
its fix)."""

from __future__ import annotations

import pytest
import torch

from difffilter.models.neural_estimator import AreaNetwork
from difffilter.param_ekf import (
    EKFRule,
    GradientRule,
    OnlineGradientDescent,
    ParamEKF,
)


def _data(steps: int, N: int = 2):
    g = torch.Generator().manual_seed(1)
    return [(torch.randn(N, 3, generator=g, dtype=torch.float64),
             torch.randn(N, 2, generator=g, dtype=torch.float64)) for _ in range(steps)]  # fmt: skip


def test_params_of_another_dtype_than_the_network_are_refused_by_name():
    """float32 weights given to a float64 network failed deep in the factored Jacobian
    ("expected scalar type Float but found Double"), or learned in float32 unsaid."""
    net = AreaNetwork(4, 3, 2)
    params = {n: torch.rand(3, *p.shape) for n, p in net.named_parameters()}  # float32
    for learner in (ParamEKF, OnlineGradientDescent):
        with pytest.raises(ValueError, match=r"params\['\w+'\] must be of the module's dtype "
                                             r"torch.float64; got torch.float32"):  # fmt: skip
            learner(net, (3,), params=params)
    same = {n: v.double() for n, v in params.items()}
    ParamEKF(net, (3,), params=same).step(torch.randn(3, 4, dtype=torch.float64),
                                          torch.randn(3, 2, dtype=torch.float64))  # fmt: skip


@pytest.mark.parametrize("rule", [EKFRule(), GradientRule()], ids=["ekf", "gradient"])
def test_a_rules_residual_of_other_runs_is_refused(rule):
    """A residual [m] or [1, m] for N = 2 runs had broadcast: run 1 updated with run 0's."""
    g = torch.Generator().manual_seed(0)
    H = torch.randn(2, 3, 4, generator=g, dtype=torch.float64)
    e = torch.randn(2, 3, generator=g, dtype=torch.float64)
    state = rule.init(torch.zeros(2, 4, dtype=torch.float64))
    rule.step(state, H, e)
    for bad in (e[0], e[:1]):
        with pytest.raises(ValueError, match=r"e must be the residual \[N, m\] = \[2, 3\]"):
            rule.step(state, H, bad)
    with pytest.raises(ValueError, match=r"H must be \[N, m, P\] = \[2, m, 4\]"):
        rule.step(state, H[:1], e)
