"""Section 10 of ``make bench``: the batched filters on a CUDA device beside the CPU.

The same workloads as sections 1b, 2 and 3b, each timed on the CPU (every intra-op thread
of the machine, the CPU's best case at these sizes) and on the GPU (``torch.cuda.
synchronize`` inside the timed call, so that a figure is the work done, not the launch),
alternating in one process, with the ratio. Skipped with a message when no CUDA device is
present (CI, the developers' 2-core machines); ``python benchmarks/bench.py --only-cuda``.
"""

from __future__ import annotations

import copy
import os

import torch
from timing import best_times

import difffilter as df
from difffilter.models.four_tank import FourTankModel
from difffilter.resampling import OptimalTransport

__all__ = ["bench_cuda", "print_cuda"]


def _synced(fn, device: torch.device):
    """``fn`` whose call returns only once the device's queued kernels have run."""
    if device.type != "cuda":
        return fn

    def call():
        fn()
        torch.cuda.synchronize(device)

    return call


def _pair(make_call, repeats: int = 3, min_time: float = 0.2) -> dict:
    """Seconds per call of ``make_call(device)`` on the CPU and on the GPU, alternating."""
    cuda = torch.device("cuda")
    times = best_times(
        {"cpu": make_call(torch.device("cpu")), "cuda": _synced(make_call(cuda), cuda)},
        repeats=repeats, min_time=min_time,
    )  # fmt: skip
    return {"cpu_s": times["cpu"], "cuda_s": times["cuda"]}


def _kf_rows(B: int = 100_000, steps: int = 200) -> list[dict]:
    from bench import tracking_cv_model

    rows = []
    for dtype in (torch.float64, torch.float32):
        model = tracking_cv_model(dtype)
        _, ys, _ = model.simulate(steps, (B,), generator=torch.Generator().manual_seed(0))

        def make(device, model=model, ys=ys):
            m, y = copy.deepcopy(model).to(device), ys.to(device)
            return lambda: df.kalman_filter(m, y)

        t = _pair(make, repeats=3, min_time=0.0)
        rows.append({"what": f"KF fast path, B = {B:.0e}, T = {steps}", "dtype": str(dtype)[6:],
                     "work": B * steps, "unit": "run-steps/s", **t})  # fmt: skip
    return rows


def _pf_rows(steps: int = 50) -> list[dict]:
    model = FourTankModel(dtype=torch.float32)
    rows = []
    for B, N in ((1, 100), (100, 1000), (100, 10_000), (1000, 1000)):
        _, ys, _ = model.simulate(steps, (B,), generator=torch.Generator().manual_seed(0))

        def make(device, ys=ys, N=N):
            m, y = copy.deepcopy(model).to(device), ys.to(device)
            gen = torch.Generator(device).manual_seed(0)
            return lambda: df.particle_filter(m, y, num_particles=N, generator=gen)

        t = _pair(make, repeats=2, min_time=0.0)
        rows.append({"what": f"bootstrap PF, B = {B}, N = {N}, T = {steps}", "dtype": "float32",
                     "work": B * N * steps, "unit": "particle-steps/s", **t})  # fmt: skip
    return rows


def _ot_row(batch: int = 32, n: int = 1000) -> dict:
    from bench import _ot_cloud

    x, log_w = _ot_cloud(batch, n)

    def make(device):
        xd, wd = x.to(device), log_w.to(device)
        ot = OptimalTransport()

        def call():
            xg = xd.clone().requires_grad_(True)
            ot(xg, wd).particles.sum().backward()

        return call

    t = _pair(make, repeats=2, min_time=0.0)
    return {"what": f"OT resampling + backward, B = {batch}, N = {n}, d = 4", "dtype": "float32",
            "work": 1, "unit": "resamplings/s", **t}  # fmt: skip


def bench_cuda() -> list[dict]:
    """Every row of section 10 (needs a CUDA device)."""
    with torch.no_grad():
        rows = _kf_rows() + _pf_rows()
    return rows + [_ot_row()]


def print_cuda(figures: dict) -> None:
    if not torch.cuda.is_available():
        print("\n10. CUDA: no CUDA device here; section skipped")
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(os.cpu_count() or threads)  # every core: the CPU's best case
    try:
        name = torch.cuda.get_device_name()
        print(
            f"\n10. CUDA ({name}) beside the CPU ({torch.get_num_threads()} threads), alternating"
        )
        print(
            f"   {'workload':<46s} {'dtype':>8s}  {'CPU':>10s}  {'CUDA':>10s}  {'ratio':>7s}  unit"
        )
        rows = bench_cuda()
    finally:
        torch.set_num_threads(threads)
    figures["cuda"] = {"device": name, "rows": rows}
    for r in rows:
        cpu, gpu = r["work"] / r["cpu_s"], r["work"] / r["cuda_s"]
        print(f"   {r['what']:<46s} {r['dtype']:>8s}  {cpu:10.3g}  {gpu:10.3g}  "
              f"{gpu / cpu:6.1f}×  {r['unit']}")  # fmt: skip
