"""Findings of a red-team trial of thread safety: carries branched from one start carry
stepped from several threads, the process-wide forward-mode level another thread's
Jacobian holds, the registry's first load, and the calibration cache's class digests.
Each test failed on the code before its fix."""

from __future__ import annotations

import sys
import threading
from concurrent.futures import ThreadPoolExecutor

import pytest
import torch

import difffilter as df
from difffilter.linalg import under_transform

D = torch.float64


def _model() -> df.LinearGaussianModel:
    eye = torch.eye(2, dtype=D)
    F = torch.tensor([[1.0, 0.1], [0.0, 0.999]], dtype=D)
    return df.LinearGaussianModel(
        F, eye[:1], 1e-4 * eye, 0.1 * eye[:1, :1], torch.zeros(2, dtype=D), eye
    )


def test_branches_of_one_start_carry_step_in_threads_as_each_alone():
    # they share the start carry's gain schedule, whose handing out and trimming had
    # interleaved: IndexError, or means 1.6 off the run alone
    model, kf, T, n = _model(), df.KalmanFilter(), 1000, 4
    ys = [torch.randn(T, 1, dtype=D, generator=torch.Generator().manual_seed(s)) for s in range(n)]

    def run(carry, s):
        means = []
        for t in range(T):
            carry, out = kf.step(carry, ys[s][t])
            means.append(out.mean)
        return torch.stack(means)

    alone = [run(kf.init(model, ()), s) for s in range(n)]
    start = kf.init(model, ())
    barrier = threading.Barrier(n)

    def branch(s):
        barrier.wait()
        return run(start, s)

    with ThreadPoolExecutor(n) as pool:
        got = list(pool.map(branch, range(n)))
    for s in range(n):
        assert torch.equal(got[s], alone[s])


def test_a_copied_schedule_has_its_own_lock():
    import copy
    import pickle

    carry = df.KalmanFilter().init(_model(), ())
    for copied in (copy.deepcopy(carry.gains), pickle.loads(pickle.dumps(carry.gains))):
        assert copied.lock is not carry.gains.lock
        with copied.lock:  # (a working RLock)
            pass


def test_another_threads_jacobian_is_not_this_threads_transform():
    # torch.func.jacfwd sets the process's forward-mode level: every other thread had taken
    # its traced paths meanwhile (a one-run PF 0.73 off), and a model's width check skipped
    entered, release = threading.Event(), threading.Event()

    def h(x, k):
        if torch._C._functorch.maybe_current_level() is not None:  # (inside the Jacobian)
            entered.set()
            release.wait(10)
        return x[..., :1] ** 2

    eye = torch.eye(2, dtype=D)
    slow = df.NonlinearGaussianModel(lambda x, u, k: x, h, 0.1 * eye, 0.1 * eye[:1, :1],
                                     torch.zeros(2, dtype=D), eye)  # fmt: skip
    ys = torch.zeros(1, 1, dtype=D)
    worker = threading.Thread(target=lambda: df.extended_kalman_filter(slow, ys))
    worker.start()
    try:
        assert entered.wait(10)
        assert torch.autograd.forward_ad._current_level >= 0  # (the other thread's level)
        assert not under_transform()
        assert not under_transform(torch.ones(2))
        with pytest.raises(ValueError):  # (one-state functions, refused as when alone)
            df.NonlinearGaussianModel(lambda x, u, k: torch.stack([x[0], x[1]]), lambda x, k: x[:1],
                                      0.1 * eye, 0.1 * eye[:1, :1], torch.zeros(2, dtype=D), eye)  # fmt: skip
    finally:
        release.set()
        worker.join(10)


def test_threads_making_the_first_registry_call_wait_for_the_loader(monkeypatch):
    # the first marked the registry loaded before importing the families: the others read
    # it empty ("unknown scenario 'four_tank_bias'; known scenarios: (none)")
    from difffilter.models import registry

    monkeypatch.setattr(registry, "_LOADED", False)
    entered, release, done = threading.Event(), threading.Event(), threading.Event()
    real = registry.importlib.import_module

    class _Shim:
        def __getattr__(self, name):
            return getattr(registry.importlib_real, name)

        @staticmethod
        def import_module(name, *args):
            if name != "difffilter.models":
                entered.set()
                release.wait(10)
            return real(name, *args)

    monkeypatch.setattr(registry, "importlib_real", registry.importlib, raising=False)
    monkeypatch.setattr(registry, "importlib", _Shim())
    loader = threading.Thread(target=lambda: (registry._load_builtin(), done.set()))
    loader.start()
    try:
        assert entered.wait(10)
        waiting = threading.Thread(target=registry._load_builtin)
        waiting.start()
        waiting.join(0.5)
        assert waiting.is_alive()  # (it waits for the loader instead of reading early)
        release.set()
        waiting.join(10)
        loader.join(10)  # (done is set after the loader returns: read before it, under load
        # the check had raced the loader's last statement, a CI run beside a demo)
        assert done.is_set() and registry._LOADED
    finally:
        release.set()
        loader.join(10)


def test_concurrent_fingerprints_are_each_the_true_one():
    # the "(in progress)" mark of a class being hashed had been shared: another thread took
    # it for the class's code (33 of 80 digests wrong at a 1 µs switch interval)
    from difffilter.models import calibration_cache as cc
    from difffilter.models import registry

    models = [registry.get(n).system() for n in ("four_tank_bias", "robot_actuator_attack")]
    truth = [cc.model_fingerprint(m) for m in models]
    interval, wrong = sys.getswitchinterval(), 0
    sys.setswitchinterval(1e-6)
    try:
        for _ in range(10):
            cc._CLASS_CODE.clear()
            barrier = threading.Barrier(4)

            def work(i, barrier=barrier):
                barrier.wait()
                return cc.model_fingerprint(models[i % 2])

            with ThreadPoolExecutor(4) as pool:
                got = list(pool.map(work, range(4)))
            wrong += sum(g != truth[i % 2] for i, g in enumerate(got))
    finally:
        sys.setswitchinterval(interval)
    assert wrong == 0
