"""Speed of the modified particle filter of the four-tank paper (Table 2).

``bench_modified_pf()`` returns one dict per figure (``make bench`` prints them):

* batched throughput at B = 100 runs, N = 100 particles, T = 100 steps, in
  particle-steps per second (target ≥ 1e7), float32 and float64;
* single-run time per step at N = 100 (target < 1e-4 s; the paper's MATLAB figure,
  Table 4, is 6.9782e-4 s), float64 (as MATLAB) and float32;
* for reference, the single-run step time of the composed implementation
  (:func:`difffilter.fdi.modified_particle_filter`), which the fused one reproduces.

Timings are the best of several rounds (wall clock); on a shared CPU they vary with load.
Run alone: ``python benchmarks/bench_four_tank.py``.
"""

from __future__ import annotations

import torch
from timing import best_time

from difffilter import fdi
from difffilter.fdi.fused import FusedModifiedPF
from difffilter.models import registry
from difffilter.models.scenario import simulate

__all__ = ["bench_modified_pf"]

PAPER_STEP_S = 6.9782e-4  # Table 4, "the proposed method", MATLAB tic-toc per step
TARGET_RATE = 1e7  # particle-steps per second at B = N = 100
TARGET_STEP_S = 1e-4  # single run, N = 100


def _setup(batch: int, steps: int, dtype: torch.dtype):
    sc = registry.get("four_tank_bias")
    model = sc.model(dtype)
    gens = {"plant": torch.Generator().manual_seed(0), "attack": torch.Generator().manual_seed(1)}
    traj = simulate(model, batch, steps, generators=gens, attack=sc.attack_model())
    G, Q = model.G, model.process_cov(0)
    eta = float(
        fdi.attack_threshold(G, fdi.modified_pf_gain(G, Q, model.measurement_cov(1)), sc.gamma_min)
    )
    zeta = fdi.detection_threshold(sc.p_l, sc.num_particles)
    return sc, model, traj, eta, zeta


def bench_modified_pf(
    *, rounds: int = 5, num_particles: int = 100, steps: int = 100, threads: int = 1
) -> list[dict]:
    """Throughput and single-run latency of the fused modified PF (see the module docstring).

    Runs with ``threads`` intra-op threads (default 1, restored afterwards): the kernels
    here are too small to gain from threading, and on a shared 2-core machine a second
    thread mostly waits for the other processes (measured 3–6× slower).
    """
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return _bench(rounds, num_particles, steps, threads)
    finally:
        torch.set_num_threads(before)


def _bench(rounds: int, num_particles: int, steps: int, threads: int) -> list[dict]:
    rows: list[dict] = []
    for dtype in (torch.float32, torch.float64):
        B = 100
        sc, model, traj, eta, zeta = _setup(B, steps, dtype)
        pf = FusedModifiedPF(model, num_particles=num_particles, eta=eta, zeta=zeta)

        def batched(pf=pf, traj=traj):
            pf.run(
                traj.y_recv,
                traj.info["attack_values"],
                generator=torch.Generator().manual_seed(2),
                resample_generator=torch.Generator().manual_seed(3),
            )

        t = best_time(batched, rounds)
        rate = B * num_particles * steps / t
        rows.append(
            {
                "figure": "batched",
                "dtype": str(dtype).replace("torch.", ""),
                "B": B,
                "N": num_particles,
                "T": steps,
                "particle_steps_per_s": rate,
                "target": TARGET_RATE,
                "met": rate >= TARGET_RATE,
                "threads": threads,
            }
        )
    for dtype in (torch.float64, torch.float32):
        sc, model, traj, eta, zeta = _setup(1, steps, dtype)
        pf = FusedModifiedPF(model, num_particles=num_particles, eta=eta, zeta=zeta)

        def single(pf=pf, traj=traj):
            pf.run(
                traj.y_recv,
                traj.info["attack_values"],
                generator=torch.Generator().manual_seed(2),
                resample_generator=torch.Generator().manual_seed(3),
            )

        step = best_time(single, rounds) / steps
        rows.append(
            {
                "figure": "single_run",
                "dtype": str(dtype).replace("torch.", ""),
                "N": num_particles,
                "step_s": step,
                "paper_step_s": PAPER_STEP_S,
                "speedup_vs_paper": PAPER_STEP_S / step,
                "target_s": TARGET_STEP_S,
                "met": step < TARGET_STEP_S,
                "threads": threads,
            }
        )
    sc, model, traj, eta, zeta = _setup(1, steps, torch.float64)
    detector = fdi.PoADetector(eta, zeta)

    def composed():
        with torch.inference_mode():
            fdi.modified_particle_filter(
                model,
                traj.y_recv,
                num_particles=num_particles,
                detector=detector,
                gamma_hat=traj.info["attack_values"],
                generator=torch.Generator().manual_seed(2),
                resample_generator=torch.Generator().manual_seed(3),
            )

    step = best_time(composed, max(2, rounds // 2)) / steps
    rows.append(
        {
            "figure": "single_run_composed_reference",
            "dtype": "float64",
            "N": num_particles,
            "step_s": step,
            "paper_step_s": PAPER_STEP_S,
            "threads": threads,
        }
    )
    return rows


if __name__ == "__main__":  # pragma: no cover
    for row in bench_modified_pf():
        print(
            "  ".join(
                f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()
            )
        )
