"""Findings of a red-team trial of the EKF over a network's weights (each failed before
its fix)."""

from __future__ import annotations

import pytest
import torch

from difffilter.models.neural_estimator import AreaNetwork
from difffilter.param_ekf import (
    DeferredCovariance,
    EKFOptimizer,
    EKFRule,
    GradientRule,
    LearnerState,
    OnlineGradientDescent,
    ParamEKF,
    WeightTemplate,
    dense_reference,
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


# -- a second trial (2026-12-07) ------------------------------------------------------------


def _learner_run(first, then, steps, template, theta0, data):
    state = first.init(theta0.clone())
    for k, (x, target) in enumerate(data[:steps]):
        prediction, H = template.jacobian(state.theta, x)
        state = (first if k < 3 else then).step(state, H, target - prediction)
    return state.theta, EKFRule.covariance(state)


@pytest.mark.parametrize(
    "first, then",
    [
        (EKFRule(donate=False), EKFRule(donate=True)),
        (EKFRule(donate=True, fold_every=8), EKFRule(donate=True, fold_every=2)),
        (EKFRule(donate=True, fold_every=2), EKFRule(donate=True, fold_every=8)),
    ],
    ids=["plain-then-donating", "wider-then-narrower", "narrower-then-wider"],
)
def test_a_donating_rule_keeps_the_downdates_of_a_state_another_rule_stepped(first, then):
    """A donating rule (the LFC entries') took over a state whose pending buffer had another
    width with a fresh buffer that held none of the earlier rows: ρ 99.9 off the dense
    recursion after one step, then S indefinite (or a raw shape error)."""
    template = WeightTemplate(AreaNetwork(3, 4, 2))
    g = torch.Generator().manual_seed(0)
    theta0 = 0.3 * torch.randn(2, template.num_params, generator=g, dtype=torch.float64)
    data = _data(12)
    for steps in (4, 12):
        with dense_reference():  # the truth: eq. (14) in place at every step
            want = _learner_run(EKFRule(), EKFRule(), steps, template, theta0, data)
        got = _learner_run(first, then, steps, template, theta0, data)
        torch.testing.assert_close(got[0], want[0], rtol=0, atol=1e-12)
        torch.testing.assert_close(got[1], want[1], rtol=0, atol=1e-12)


def test_a_hand_built_first_step_covariance_is_read_in_thetas_order():
    """A ``DeferredCovariance`` of ``θ``'s order (as documented) with a non-scalar ρ(0) was
    relabelled into the Kronecker Jacobian's order, not permuted: the first weights 0.14
    off one step of eqs (11)–(12) worked by hand. ``init``'s ``c·I`` is still relabelled
    without a copy (a permutation of ``[N, P, P]`` costs about 0.2 s at P = 560)."""
    template = WeightTemplate(AreaNetwork(3, 2, 2))  # W [2, 2], V [2, 3]: P = 10, factored
    g = torch.Generator().manual_seed(0)
    P = template.num_params
    theta = 0.3 * torch.randn(1, P, generator=g, dtype=torch.float64)
    P0 = torch.diag(torch.linspace(0.1, 5.0, P, dtype=torch.float64))[None]
    x = torch.randn(1, 3, generator=g, dtype=torch.float64)
    target = torch.randn(1, 2, generator=g, dtype=torch.float64)
    prediction, H_kron = template.jacobian(theta, x)
    _, H = template.jacobian(theta, x, factored=False)
    e = (target - prediction)[0]
    S = H[0] @ P0[0] @ H[0].T + (e @ e) * torch.eye(2, dtype=torch.float64)  # Υ_1 = eᵀe
    want = theta[0] + P0[0] @ H[0].T @ torch.linalg.solve(S, e)
    for donate in (False, True):
        cov = DeferredCovariance(P0.clone(), theta.new_empty(1, 0, P), 0, 0.0)
        state = LearnerState(theta.clone(), cov, torch.full((1,), 1e-3, dtype=torch.float64), 0)
        for jacobian in (H_kron, H):
            step = EKFRule(donate=donate).step(state, jacobian, target - prediction)
            torch.testing.assert_close(step.theta[0], want, rtol=0, atol=1e-14)
            rho = P0[0] - P0[0] @ H[0].T @ torch.linalg.solve(S, H[0] @ P0[0])
            torch.testing.assert_close(EKFRule.covariance(step)[0], rho, rtol=0, atol=1e-13)
    rule = EKFRule(donate=True)
    start = rule.init(theta.clone())
    after = rule.step(start, H_kron, target - prediction)
    assert after.rho.base is start.rho.base and after.rho.order is not None


@pytest.mark.parametrize("where", ["residual", "jacobian"])
def test_a_refused_optimizer_step_leaves_the_optimizer_as_it_was(where):
    """``EKFOptimizer.step`` advanced k and Υ before the update refused a NaN residual or
    Jacobian: Υ = NaN after a NaN residual refused every later step, and after a NaN
    Jacobian the next good step moved the weights to [0.054, -0.118, -0.142] where a fresh
    optimizer's same step gives [-0.099, -0.529, -0.194]."""
    g = torch.Generator().manual_seed(0)
    H = torch.randn(1, 2, 3, generator=g, dtype=torch.float64)
    e = torch.randn(1, 2, generator=g, dtype=torch.float64)
    bad_H, bad_e = H.clone(), e.clone()
    (bad_H if where == "jacobian" else bad_e)[0, 0, ...] = float("nan")
    refused, fresh = (torch.nn.Parameter(torch.zeros(3, dtype=torch.float64)) for _ in range(2))
    opt = EKFOptimizer([refused])
    with pytest.raises(ValueError, match=f"{where} must be finite where received"):
        opt.step(bad_H, bad_e)
    opt.step(H, e)
    EKFOptimizer([fresh]).step(H, e)
    torch.testing.assert_close(refused.detach(), fresh.detach(), rtol=0, atol=0)
    assert opt.state[refused]["k"] == 1


@pytest.mark.parametrize(
    ("key", "value", "need"),
    [
        ("lr", float("nan"), "> 0"),
        ("process_noise", -5.0, ">= 0"),
        ("init_cov", float("inf"), "> 0"),
    ],
)
def test_an_optimizers_group_settings_are_checked_at_every_step(key, value, need):
    """Settings written into ``param_groups[0]`` (as LR schedulers and Lightning write them)
    were never checked: a NaN lr made every weight NaN, a negative Q_ρ ran as 0, an infinite
    ρ(0) was blamed on "the model's Q, R and P0"."""
    p = torch.nn.Parameter(torch.zeros(3, dtype=torch.float64))
    opt = EKFOptimizer([p])
    opt.param_groups[0][key] = value
    with pytest.raises(
        ValueError, match=rf"param_groups\[0\]\['{key}'\] must be a finite number {need}"
    ):
        opt.step(torch.ones(1, 2, 3, dtype=torch.float64), torch.ones(1, 2, dtype=torch.float64))
    assert torch.equal(p.detach(), torch.zeros(3, dtype=torch.float64)) and not opt.state[p]


def test_an_optimizer_refuses_a_second_parameter_group():
    """``add_param_group`` added a group that ``step`` never read (its weights fixed)."""
    opt = EKFOptimizer([torch.nn.Parameter(torch.zeros(3, dtype=torch.float64))])
    with pytest.raises(ValueError, match="takes one parameter group"):
        opt.add_param_group({"params": [torch.nn.Parameter(torch.zeros(2, dtype=torch.float64))]})
    assert len(opt.param_groups) == 1


@pytest.mark.parametrize("learner", [ParamEKF, OnlineGradientDescent])
def test_a_learners_settings_assigned_later_are_its_rules(learner):
    """``ekf.lr = 0.1`` had made a plain attribute beside the rule, never read (the weights
    those of the constructor's lr, 1.17 away from a learner built with 0.1; NaN taken);
    ``init_cov``/``init_noise`` made the state and cannot change it later."""
    net = AreaNetwork(3, 4, 2)
    later, built = learner(net, (2,)), learner(net, (2,), lr=0.1)
    later.lr = 0.1
    if learner is ParamEKF:
        later.process_noise = built.process_noise = 1e-2
        with pytest.raises(AttributeError, match="init_cov makes the initial state"):
            later.init_cov = 1.0
        assert later.init_noise == 1e-3
    for x, y in _data(5):
        later.step(x, y)
        built.step(x, y)
    torch.testing.assert_close(later.theta, built.theta, rtol=0, atol=0)
    with pytest.raises(ValueError, match="lr must be a finite number > 0"):
        later.lr = float("nan")


@pytest.mark.parametrize("width", [1, 5])
def test_a_factored_learners_input_width_is_checked(width):
    """A width-1 input to a 3-input tanh network was learned from as three equal features
    (x / in_scale broadcast); width 5 failed inside torch without naming ``inputs``."""
    ekf = ParamEKF(AreaNetwork(3, 4, 2), (2,))
    with pytest.raises(
        ValueError, match=r"inputs must have shape \[2, 3\] \(the network's input width\)"
    ):
        ekf.step(torch.zeros(2, width, dtype=torch.float64), torch.zeros(2, 2, dtype=torch.float64))


@pytest.mark.parametrize("key", ["init_cov", "init_noise"])
def test_an_optimizers_initial_values_written_after_its_first_step_are_refused(key):
    """ρ(0) and Υ(0) are read at the first step: ``param_groups[0]["init_cov"] = 1.0`` written
    later had been kept in the group and never used (noted last session; :class:`ParamEKF`
    refuses the same assignment). A state loaded into a new optimizer carries them along,
    and a cleared state starts from the group's values."""
    p = torch.nn.Parameter(torch.zeros(3, dtype=torch.float64))
    opt = EKFOptimizer([p])
    H, e = torch.ones(1, 2, 3, dtype=torch.float64), torch.ones(1, 2, dtype=torch.float64)
    opt.step(H, e)
    saved = opt.state_dict()
    opt.param_groups[0][key] = 0.5
    with pytest.raises(ValueError, match=rf"\['{key}'\] = 0.5 but this optimizer started from"):
        opt.step(H, e)
    resumed = EKFOptimizer([p])
    resumed.load_state_dict(saved)
    resumed.step(H, e)  # the saved group and state agree
    assert resumed.state[p]["k"] == 2
    opt.state.clear()
    opt.step(H, e)
    assert opt.state[p]["started_from"][key] == 0.5
    # the cleared state started from the group's value: as an optimizer built with it
    q = torch.nn.Parameter(p.detach().clone())
    fresh = EKFOptimizer([q], **{key: 0.5})
    fresh.step(H, e)
    torch.testing.assert_close(opt.state[p]["rho"], fresh.state[q]["rho"], rtol=0, atol=0)
    torch.testing.assert_close(opt.state[p]["upsilon"], fresh.state[q]["upsilon"], rtol=0, atol=0)
