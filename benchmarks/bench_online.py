"""``make bench`` sections 1c and 2b (the public online step) and 9 (one thread or two).

1c. The Kalman filter of section 1 through its public online step at B = 1
    (``carry, out = KalmanFilter().step(carry, y)``, one measurement at a time, as an
    estimator deployed on one plant runs it), beside the same numpy loop:

    * *online*: a long run on one plant (the carry of the previous round goes on: the gains
      have converged, every step is the fused step of :meth:`difffilter.GainSchedule.filter_step`);
    * *cold start*: ``init`` and the first T = 200 steps of a fresh carry, the covariance
      recursion (until its gain converges, 110 steps here) included;
    * *online, full_checks*: the first figure with every step validated in full (what every
      step paid before the carries were vouched for, :mod:`difffilter._vouched`);
    * *20 % lost*: init and T steps with a mask at every step (each entry lost with
      probability 0.2): the general update, on host arrays (:mod:`difffilter._kf_host_step`),
      beside the same stream through the torch update (its yardstick).

2b. The bootstrap PF of section 2 at (B, N) = (1, 100) through its public online step
    (``init`` then T = 50 steps per run, as the numpy loop draws its prior per run), with
    the default outputs and with ``innovations=False`` (no predictive measurement moments:
    the numpy loop computes none), and with ``full_checks``; under ``torch.no_grad()``, so
    the step is the host-array one (:mod:`difffilter._pf_host_step`). *20 % lost*: the
    same with a mask at every step (each entry lost with probability 0.2), on the host-array
    step since 2026-12-04, beside the same stream through the general particle step (its
    yardstick, where every masked step went before).

9. Each KF and bootstrap-PF workload of sections 1, 1b, 1c, 2 and 2b with one intra-op
   thread and with two, alternating in one process: which is faster.

Every ratio is of two figures timed in the same process, their rounds alternating
(:func:`timing.best_times`), so that both see the same load: each figure with rounds of the
numpy loop of its own (:func:`_paired`). Alternating with all of a section's workloads at once
made the numpy loop itself slower (its rounds followed the torch ones: 10 k against 15–17 k
steps/s for 1c on 2026-11-29), which flattered every ratio.
"""

from __future__ import annotations

import math
import os

import numpy as np
import torch
from timing import best_times

import difffilter as df
from difffilter.models.four_tank import FourTankModel
from difffilter.particle import _particle_step

__all__ = [
    "bench_online_kf",
    "bench_online_pf",
    "bench_threads",
    "print_online_kf",
    "print_online_pf",
    "print_threads",
]

#: The acceptance figures of issue 24 (ratio of the public online step to the numpy loop).
KF_TARGET, PF_TARGET = 1.0, 0.5


def _kf_setup(steps: int):
    from bench import numpy_kf_run, numpy_matrices, tracking_cv_model

    model = tracking_cv_model()
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        _, ys, _ = model.simulate(steps, (1,), generator=gen)
    ys = ys[0]
    mats, y_np = numpy_matrices(model), ys.numpy()
    return model, list(ys.unbind(0)), lambda: numpy_kf_run(*mats, y_np)


def _lost_packets(steps: int, dim: int) -> list[torch.Tensor]:
    """``steps`` masks ``[dim]`` of received entries, each entry lost with probability 0.2
    (seeded: a mask at every step of the lossy rows)."""
    lost = torch.rand(steps, dim, generator=torch.Generator().manual_seed(2)) < 0.2
    return list((~lost).unbind(0))


def bench_online_kf(steps: int = 200) -> dict:
    """Steps per second of :class:`~difffilter.KalmanFilter`'s public ``step`` at B = 1 and
    of the numpy loop (module docstring, 1c), and the largest difference of their means."""
    model, rows, numpy_run = _kf_setup(steps)
    kf, checked = df.KalmanFilter(), df.KalmanFilter()
    checked.full_checks = True

    def run_from(est, carry):
        for y in rows:
            carry, out = est.step(carry, y)
        return carry, out

    live = {"online": run_from(kf, kf.init(model))[0],
            "checked": run_from(checked, checked.init(model))[0]}  # fmt: skip

    def online(name, est):
        def run():
            live[name] = run_from(est, live[name])[0]

        return run

    def cold():
        run_from(kf, kf.init(model))

    masks = _lost_packets(steps, rows[0].shape[-1])
    torch_update = _TorchUpdateKalmanFilter()

    def lossy(est):
        def run():
            carry = est.init(model)
            for y, mask in zip(rows, masks):
                carry, out = est.step(carry, y, None, mask)
            return out

        return run

    with torch.no_grad():
        seconds, ratios = _paired(numpy_run, {"online": online("online", kf), "cold": cold,
                                              "checked": online("checked", checked),
                                              "masked": lossy(kf),
                                              "masked_torch": lossy(torch_update)})  # fmt: skip
        # equal filters: the cold run's last mean against the numpy loop's
        (_, out), (ref, _) = run_from(kf, kf.init(model)), numpy_run()
        diff = float(np.abs(out.mean.numpy() - ref).max())
        host, torch_out = lossy(kf)(), lossy(torch_update)()
        masked_diff = float((host.mean - torch_out.mean).abs().max())
    return {"B": 1, "T": steps, **{f"{k}_rate": steps / v for k, v in seconds.items()},
            **{f"{k}_ratio": v for k, v in ratios.items()},
            "masked_speedup": seconds["masked_torch"] / seconds["masked"],
            "max_abs_diff_vs_numpy": diff, "masked_max_abs_diff_host_vs_torch": masked_diff,
            "load_average": os.getloadavg()[0]}  # fmt: skip


class _TorchUpdateKalmanFilter(df.KalmanFilter):
    """The Kalman filter with its general update in torch at every step (its own
    ``predict``, the same, keeps it off the host-array step of
    :mod:`difffilter._kf_host_step`): the yardstick of the masked rows."""

    def predict(self, carry, u):
        return super().predict(carry, u)


def _paired(numpy_run, fns: dict, **timing) -> tuple[dict, dict]:
    """``({name: seconds per call}, {name: ratio})`` of each of ``fns`` timed alternating
    with rounds of ``numpy_run`` of its own (:func:`timing.best_times` of the pair), its
    ratio the numpy time over its time; ``seconds["numpy"]`` the best numpy time over the
    pairs."""
    seconds, ratios = {"numpy": math.inf}, {}
    for name, fn in fns.items():
        pair = best_times({"numpy": numpy_run, name: fn}, **timing)
        seconds[name], ratios[name] = pair[name], pair["numpy"] / pair[name]
        seconds["numpy"] = min(seconds["numpy"], pair["numpy"])
    return seconds, ratios


def _pf_setup(steps: int, n: int):
    from bench import numpy_bootstrap_pf_run

    model = FourTankModel(dtype=torch.float32)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        _, ys, _ = model.simulate(steps, (1,), generator=gen)
    ys, rng = ys[0], np.random.default_rng(0)
    y_np = ys.numpy()
    return model, list(ys.unbind(0)), lambda: numpy_bootstrap_pf_run(model, y_np, n, rng)


def bench_online_pf(steps: int = 50, n: int = 100) -> dict:
    """Particle-steps per second of :class:`~difffilter.ParticleFilter`'s public ``step``
    at (B, N) = (1, ``n``) and of the numpy loop (module docstring, 2b)."""
    model, rows, numpy_run = _pf_setup(steps, n)
    gen = torch.Generator().manual_seed(1)
    checked = df.ParticleFilter(n)
    checked.full_checks = True
    filters = {"default": df.ParticleFilter(n), "lean": df.ParticleFilter(n, innovations=False),
               "checked": checked}  # fmt: skip
    masks = _lost_packets(steps, rows[0].shape[-1])

    def run(est, lossy=False):
        def go():
            carry = est.init(model, (), gen)
            for k, y in enumerate(rows):
                carry, out = est.step(carry, y, None, masks[k] if lossy else None)
            return out

        return go

    jobs = {k: run(v) for k, v in filters.items()}
    jobs.update(masked=run(filters["default"], True), masked_general=run(_GeneralStepPF(n), True))
    with torch.no_grad():
        seconds, ratios = _paired(numpy_run, jobs, repeats=3, min_time=0.3)
        # the same draws on both paths: the last means apart by round-off alone
        gen.manual_seed(3)
        host = jobs["masked"]()
        gen.manual_seed(3)
        general = jobs["masked_general"]()
    return {"B": 1, "N": n, "T": steps, **{f"{k}_rate": n * steps / v for k, v in seconds.items()},
            **{f"{k}_ratio": v for k, v in ratios.items()},
            "masked_speedup": seconds["masked_general"] / seconds["masked"],
            "masked_max_abs_diff_host_vs_general": float((host.mean - general.mean).abs().max()),
            "load_average": os.getloadavg()[0]}  # fmt: skip


class _GeneralStepPF(df.ParticleFilter):
    """The particle filter with every step through the general particle step (none of the
    one-run steps): the yardstick of the masked rows."""

    def _step(self, carry, y, u, mask):
        return _particle_step(self, carry, y, u, mask)


def _verdict(ratio: float, target: float) -> str:
    return "met" if ratio >= target else f"MISSED ({ratio / target:.2f} of target)"


def _fmt(x: float) -> str:
    return f"{x:,.3g}" if x < 1e3 else f"{x:,.0f}"


def print_online_kf(figures: dict) -> None:
    r = bench_online_kf()
    figures["kf_online"] = r
    print(
        "\n1c. Kalman filter through the public online step, B = 1 (KalmanFilter().step, one "
        f"measurement at a time), T = {r['T']}, float64 (steps/s; load {r['load_average']:.1f})"
    )
    rows = (("online (gains converged)", "online", True), ("cold start (init + T steps)", "cold", True),
            ("online, full_checks = True", "checked", False),
            ("20 % lost (a mask every step)", "masked", False),
            ("  the same, torch update", "masked_torch", False))  # fmt: skip
    _print_rates(r, rows, KF_TARGET)
    print(f"   (max |difference| of the last mean to numpy: {r['max_abs_diff_vs_numpy']:.2g}; "
          f"with lost packets the host-array step {r['masked_speedup']:.2f}× the torch update, "
          f"max |difference| {r['masked_max_abs_diff_host_vs_torch']:.2g})")  # fmt: skip


def print_online_pf(figures: dict) -> None:
    r = bench_online_pf()
    figures["pf_online"] = r
    print(
        f"\n2b. Bootstrap PF through the public online step, B = 1, N = {r['N']} "
        f"(ParticleFilter(N).step, init + T = {r['T']} steps per run), float32 "
        f"(particle-steps/s; load {r['load_average']:.1f})"
    )
    rows = (("default outputs", "default", True), ("innovations = False", "lean", True),
            ("default, full_checks = True", "checked", False),
            ("20 % lost (a mask every step)", "masked", False),
            ("  the same, general step", "masked_general", False))  # fmt: skip
    _print_rates(r, rows, PF_TARGET)
    print(
        f"   (with lost packets the host-array step {r['masked_speedup']:.2f}× the general "
        f"step, last means max |difference| {r['masked_max_abs_diff_host_vs_general']:.2g})"
    )


def _print_rates(r: dict, rows, target: float) -> None:
    """The numpy loop's best rate, then each ``(label, key, judged)`` row's rate and its
    ratio to the numpy rounds timed beside it (:func:`_paired`; with the verdict against
    ``target`` where ``judged``)."""
    print(f"   numpy loop (best of its rounds) {_fmt(r['numpy_rate']):>10s}")
    for label, key, judged in rows:
        ratio = r[f"{key}_ratio"]
        verdict = f"  target ≥ {target:g}× numpy: {_verdict(ratio, target)}" if judged else ""
        print(f"   {label:<30s}  {_fmt(r[f'{key}_rate']):>10s}  {ratio:6.2f}×{verdict}")


# ------------------------------------------------------------------------- threads ----
def _thread_workloads() -> dict:
    """``{name: (work per call, function)}``: the KF and bootstrap-PF workloads of the bench."""
    from bench import tracking_cv_model

    from difffilter.particle import particle_filter

    out = {}
    model = tracking_cv_model()
    gen = torch.Generator().manual_seed(0)
    kf_model, kf_rows, _ = _kf_setup(200)
    kf = df.KalmanFilter()

    def kf_online():
        carry = kf.init(kf_model)
        for y in kf_rows:
            carry, _ = kf.step(carry, y)

    out["KF online step, B = 1 (1c)"] = (200, kf_online)
    for B in (1, 1000, 100_000):
        with torch.no_grad():
            _, ys, _ = model.simulate(200, (B,), generator=gen)
        out[f"KF kalman_filter, B = {B:,} (1, 1b)"] = (
            B * 200,
            lambda ys=ys: df.kalman_filter(model, ys),
        )
    pf_model, pf_rows, _ = _pf_setup(50, 100)
    pf = df.ParticleFilter(100)

    def pf_online():
        carry = pf.init(pf_model, (), gen)
        for y in pf_rows:
            carry, _ = pf.step(carry, y)

    out["PF online step, B = 1, N = 100 (2b)"] = (100 * 50, pf_online)
    four_tank = FourTankModel(dtype=torch.float32)
    for B, N in ((1, 100), (100, 1000), (10, 10000)):
        with torch.no_grad():
            _, ys, _ = four_tank.simulate(50, (B,), generator=gen)
        out[f"PF particle_filter, B = {B}, N = {N:,} (2)"] = (
            B * N * 50,
            lambda ys=ys, N=N: particle_filter(four_tank, ys, num_particles=N, generator=gen),
        )
    return out


def bench_threads() -> list[dict]:
    """Work per second of every workload of :func:`_thread_workloads` with one intra-op
    thread and with two, alternating in one process (``torch.set_num_threads`` before each
    call); the thread count in use before is restored."""
    before = torch.get_num_threads()
    rows = []
    try:
        for name, (work, fn) in _thread_workloads().items():

            def threads(n, fn=fn):
                def run():
                    torch.set_num_threads(n)
                    fn()

                return run

            big = work >= 1e7
            with torch.no_grad():
                t = best_times({1: threads(1), 2: threads(2)}, repeats=3 if big else 5,
                               min_time=0.0 if big else 0.2)  # fmt: skip
            rows.append({"workload": name, "one": work / t[1], "two": work / t[2],
                         "faster": 1 if t[1] <= t[2] else 2, "load_average": os.getloadavg()[0]})  # fmt: skip
    finally:
        torch.set_num_threads(before)
    return rows


def print_threads(figures: dict) -> None:
    print(
        f"\n9. One intra-op thread or two ({os.cpu_count()} CPUs), alternating in one process "
        "(work per second: run-steps or particle-steps)"
    )
    print(f"   {'workload':<38s}  {'1 thread':>12s}  {'2 threads':>12s}  {'2 / 1':>6s}  faster")
    rows = bench_threads()
    figures["threads"] = rows
    for r in rows:
        print(
            f"   {r['workload']:<38s}  {_fmt(r['one']):>12s}  {_fmt(r['two']):>12s}  "
            f"{r['two'] / r['one']:6.2f}  {r['faster']} (load {r['load_average']:.1f})"
        )
