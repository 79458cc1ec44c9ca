"""Mutation review of ``train/task.py`` and ``train/adversarial.py``: the training loss, its
after-attack window, truncated backpropagation, the validation's threshold without
calibration runs, the EKF trainer's receptions and the adversary's budget and flags, each
against a truth written out by hand (numpy, or a mask set by hand) on stub tensors."""

from __future__ import annotations

import math
import types
import warnings

import numpy as np
import pytest
import torch

from difffilter.models import registry
from difffilter.train import adversarial
from difffilter.train.adversarial import Adversary
from difffilter.train.task import FilterEstimatorTask, training_batch

F64 = torch.float64


def _task(scenario="four_tank_bias", **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return FilterEstimatorTask(scenario, hidden=4, **kwargs)


def _bce(z, labels):
    """Per-entry BCE with logits, numpy float64."""
    z = np.asarray(z, dtype=np.float64)
    return labels * np.log1p(np.exp(-z)) + (1 - labels) * np.log1p(np.exp(z))


def test_the_loss_weighs_each_term_by_its_own_weight_and_each_gets_its_gradient():
    """``loss = w_a·mean(â−a)² + w_b·mean BCE + w_x·mean(x̂−x)²/σ_x²`` with three distinct
    weights (defaults 1, 0.1, 1 hid a swap of ``attack_weight`` and ``state_weight``), numpy;
    and ``∂loss/∂â = 2 w_a (â−a)/N`` (an attack error cut from the graph trained nothing of
    the attack estimate while the loss value stayed the same)."""
    wa, wb, wx = 2.0, 0.3, 0.7
    task = _task(num_particles=20, attack_weight=wa, bce_weight=wb, state_weight=wx)
    sig2 = float(np.diag(task.system.initial.cov.numpy()).mean())
    g = torch.Generator().manual_seed(1)
    B, T, dx, dy = 2, 6, task.system.dim_x, task.system.dim_y
    a = torch.randn(B, T, dy, generator=g)
    a[:, :2] = 0.0
    ah = (a + 0.3 * torch.randn(B, T, dy, generator=g)).requires_grad_(True)
    x = torch.randn(B, T, dx, generator=g)
    xh = x + 0.2 * torch.randn(B, T, dx, generator=g)
    logits = torch.randn(B, T, generator=g)
    flags = a.ne(0).any(-1)
    out = types.SimpleNamespace(attack=ah, means=xh, extras={"attack_logit": logits})
    losses = task._losses(out, {"attack": a, "x": x, "flags": flags})
    A, AH, X, XH = (t.detach().numpy().astype(np.float64) for t in (a, ah, x, xh))
    want = (
        wa * ((AH - A) ** 2).mean()
        + wb * _bce(logits.numpy(), flags.numpy().astype(np.float64)).mean()
        + wx * ((XH - X) ** 2).mean() / sig2
    )
    got = float(losses["loss"].detach())
    assert abs(got - want) < 1e-5 * want, f"loss {got}, want {want}"
    losses["loss"].backward()
    grad_want = 2 * wa * (AH - A) / AH.size
    assert np.allclose(ah.grad.numpy(), grad_want, rtol=1e-4, atol=1e-9), "∂loss/∂â"


def test_the_after_attack_window_is_each_runs_and_each_areas_own():
    """With two area logits, ``after_attack_steps = 2`` and ``ω = 5``: ω on the 2 steps after
    an attacked step of the SAME run and area only (mask written by hand: run 0 area 0
    attacked at steps 1 and 7 → 2, 3 (step 7 is the last: nothing spills into run 1), area 1
    at step 4 → 5, 6; run 1 area 1 at step 3 → 4, 5). A window shared by the areas, or one
    running from a run's end into the next run, was unpinned."""
    task = _task(num_particles=20, after_attack_weight=5.0, after_attack_steps=2)
    B, T, dx, dy = 2, 8, task.system.dim_x, task.system.dim_y
    assert dy == 4, dy
    a = torch.zeros(B, T, dy)
    a[0, 1, 0] = a[0, 7, 1] = 0.5  # area 0 (channels 0, 1)
    a[0, 4, 3] = -1.0  # area 1 (channels 2, 3)
    a[1, 3, 2] = 2.0
    labels = np.zeros((B, T, 2))
    labels[0, [1, 7], 0] = labels[0, 4, 1] = labels[1, 3, 1] = 1.0
    omega = np.ones((B, T, 2))
    omega[0, [2, 3], 0] = omega[0, [5, 6], 1] = omega[1, [4, 5], 1] = 5.0
    logits = torch.linspace(-3.0, 2.5, B * T * 2).reshape(B, T, 2)
    truth = {"attack": a, "x": torch.zeros(B, T, dx), "flags": a.ne(0).any(-1)}
    out = types.SimpleNamespace(attack=a, means=truth["x"], extras={"area_logits": logits})
    got = float(task._losses(out, truth)["bce"])
    want = float((omega * _bce(logits.numpy(), labels)).mean())
    assert abs(got - want) < 1e-6 * want, f"BCE {got}, want {want}"


def test_truncated_backpropagation_runs_chunks_from_a_detached_state():
    """``tbptt_steps = 5`` over 10 closed-loop steps: two chunks of 5 steps, the second from
    the first's final state cut from the graph (no tensor of it requires grad), and one
    optimizer step per chunk (a carry kept in the graph, or the chunking ignored, was
    unpinned by the fast tests)."""
    task = _task("lfc_random_attacks", filter="kf", tbptt_steps=5, monitor_scenarios=[])
    task.scenario = task.scenario.with_steps(10)
    batch = training_batch(task.scenario, 2, 3, torch.float32)
    stepped = []
    opt = torch.optim.SGD(task.estimator.parameters(), lr=0.0)
    real_step = opt.step
    opt.step = lambda *a, **k: (stepped.append(1), real_step(*a, **k))[1]
    task.optimizers, task.lr_schedulers = (lambda: opt), (lambda: None)
    task.manual_backward = lambda loss: loss.backward()
    task.log = lambda *a, **k: None
    calls, real_run = [], task.run

    def run(scenario, batch, est, seed, *, steps=None, state=None):
        calls.append((steps, state))
        return real_run(scenario, batch, est, seed, steps=steps, state=state)

    task.run = run
    task.training_step(batch, 0)
    assert [c[0] for c in calls] == [5, 5], [c[0] for c in calls]
    assert calls[0][1] is None and calls[1][1].k == 5
    carried, seen = [], set()

    def collect(v):
        if id(v) in seen:  # (objects may refer to each other: the loop's attacker)
            return
        seen.add(id(v))
        if isinstance(v, torch.Tensor):
            carried.append(v)
        elif isinstance(v, (tuple, list)):
            for w in v:
                collect(w)
        elif isinstance(v, dict):
            for w in v.values():
                collect(w)
        elif hasattr(v, "__dict__"):
            for w in vars(v).values():
                collect(w)

    collect(tuple(calls[1][1])[1:])
    assert carried, "the state carries tensors"
    assert not any(t.requires_grad for t in carried), "the carried state is detached"
    assert len(stepped) == 2, f"{len(stepped)} optimizer steps, want 2"


def test_without_calibration_runs_the_threshold_is_chosen_on_attack_free_steps_only():
    """No calibration runs (no data module): ``τ`` = the smallest attack-free score with
    ``#{s > τ} ≤ ⌊α n⌋`` over the ``n`` attack-free steps, its rate ``#{s > τ}/n`` (numpy);
    the attacked steps' high scores must not enter (choosing on every step was unpinned)."""
    task = _task(num_particles=20)
    g = torch.Generator().manual_seed(5)
    score = torch.rand(2, 200, generator=g, dtype=F64)
    flags = torch.zeros(2, 200, dtype=torch.bool)
    flags[:, 150:] = True
    score[flags] += 5.0
    tau, rate, on_calibration = task._choose_threshold(score, flags)
    quiet = np.sort(score[~flags].numpy())[::-1]
    allowed = math.floor(task.false_alarm_rate * quiet.size + 1e-9)
    assert on_calibration is False
    assert tau == quiet[allowed], f"τ {tau}, want {quiet[allowed]}"
    assert rate == float((quiet > quiet[allowed]).mean()), rate


def test_the_ekf_trainer_learns_nothing_from_a_step_not_received():
    """A sensor scenario's batch ``mask`` all false (nothing received): the EKF updates carry
    no information and ``W``, ``V`` stay as they were (the batch's receptions dropped, every
    entry counted as received, was unpinned)."""
    task = _task(trainer="ekf", filter="ekf", dtype="float64")
    net = task.estimator
    R, n_in, m = 3, net.in_dim, net.area_dim
    g = torch.Generator().manual_seed(0)
    deltas = torch.randn(R, 2, n_in, generator=g, dtype=F64)
    attack = torch.randn(R, 2, m, generator=g, dtype=F64)
    out = types.SimpleNamespace(extras={"network_inputs": deltas})
    task.run = lambda *a, **k: (out, {"attack": attack, "flags": None}, None)
    task.estimator_object = lambda **k: None
    opt = task.configure_optimizers()
    task.optimizers = lambda: opt
    task.log = lambda *a, **k: None
    W0, V0 = net.W.detach().clone(), net.V.detach().clone()
    mask = torch.zeros(R, 2, task.system.dim_y, dtype=torch.bool)
    task._ekf_step({"y_recv": torch.zeros(R, 2, task.system.dim_y), "mask": mask}, 0)
    assert torch.equal(net.W.detach(), W0) and torch.equal(net.V.detach(), V0)


def test_the_crafting_is_held_to_the_tasks_rate_under_its_current_threshold(monkeypatch):
    """The attacker's alarm budget: ``far`` = the task's target false-alarm rate, under
    ``task.current_threshold()`` (here the buffer: no data module), with ``iterations``
    Adam steps (the budget's rate was unpinned: ``2·far`` passed every test)."""
    task = _task(num_particles=20, adversarial_runs=2, adversarial_iterations=3,
                 adversarial_crafting_runs=2)  # fmt: skip
    task.alarm_threshold.fill_(0.37)
    seen = {}

    class Stop(Exception):
        pass

    def record(estimator, system, y, x, threshold, **kwargs):
        seen.update(kwargs, threshold=threshold, runs=y.shape[0])
        raise Stop

    monkeypatch.setattr(adversarial, "craft_stealthy_attack", record)
    with pytest.raises(Stop):
        task.adversary.craft(task, step=0)
    assert seen["far"] == task.false_alarm_rate, seen["far"]
    assert seen["threshold"] == pytest.approx(0.37)
    assert seen["settings"].iterations == 3 and seen["runs"] == 2
    assert all(p.requires_grad for p in task.estimator.parameters())


def test_per_channel_flags_of_the_crafted_runs_mark_only_attacked_channels_from_the_onset():
    """A batch whose flags are per channel ``[B, T, dy]``: the crafted runs' flags are
    ``k ≥ onset`` AND the channel's attack nonzero (set by hand: channel 2 never attacked;
    every channel flagged from the onset was unpinned)."""
    scenario = registry.get("four_tank_bias")
    adversary = Adversary(runs=2)
    adversary.attack = torch.zeros(100, 4)
    adversary.attack[9:] = torch.tensor([0.1, -0.2, 0.0, 0.3])
    adversary.onset = 10
    batch = training_batch(scenario, 2, 7, torch.float32)
    batch["flags"] = batch["attack"] != 0
    got = adversary.augment(batch, scenario, 5, torch.float32)["flags"][2:]
    want = np.zeros((2, 100, 4), dtype=bool)
    want[:, 9:, [0, 1, 3]] = True
    assert got.tolist() == want.tolist()
