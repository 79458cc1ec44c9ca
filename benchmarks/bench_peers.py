"""``make bench`` section 8: our Kalman filter beside a peer library's, in one process.

The peer is torch-kf (``pip install torch-kf``, or ``pip install -e ".[bench]"``): a
batched Kalman filter in PyTorch (``torch_kf.KalmanFilter(F, H, Q, R).filter``). Both
filter the same runs of the same model: the constant-velocity model of section 1 (dx = 4,
dy = 2), at B = 1, 1,000 and 100,000 runs, float32 and float64. torch-kf runs with
``joseph_update=True`` (our covariance update; its default is the shorter ``(I − K H) P``)
and ``update_first=False`` (a prediction before the first update, as ours); its initial
covariance is the unbatched ``P_0``, so it too keeps one covariance for all runs, as our
shared-covariance path does. Ours is :func:`difffilter.kalman_filter` (whole sequences:
the shared-covariance fast path is picked by itself); it also returns the innovations,
their covariances and the log-likelihood, torch-kf the means and covariances only.

The two run alternately (:func:`timing.best_times`); the ratio is ours / torch-kf (above
1: ours is faster), and the largest difference of their filtered means says they computed
the same filter.
"""

from __future__ import annotations

import os

import torch
from timing import best_times

import difffilter as df

__all__ = ["bench_torch_kf", "print_peers"]

#: (runs B, steps T): T shorter at B = 1e5, where one torch-kf run takes seconds.
SIZES = ((1, 200), (1000, 200), (100_000, 50))


def bench_torch_kf(sizes=SIZES, dtypes=(torch.float32, torch.float64)) -> list[dict] | None:
    """Run-steps per second of ours and of torch-kf on every size and dtype (module
    docstring); ``None`` when torch-kf is not installed."""
    try:
        import torch_kf
    except ImportError:
        return None
    from bench import tracking_cv_model

    rows = []
    for dtype in dtypes:
        model = tracking_cv_model(dtype)
        peer = torch_kf.KalmanFilter(model.F, model.H, model.process_noise.cov,
                                     model.measurement_noise.cov, joseph_update=True)  # fmt: skip
        gen = torch.Generator().manual_seed(0)
        for B, T in sizes:
            with torch.no_grad():
                _, ys, _ = model.simulate(T, (B,), generator=gen)
                # torch-kf's layout, made once outside the timing: [T, B, dy, 1]
                measures = ys.transpose(0, 1).unsqueeze(-1).contiguous()
                prior = torch_kf.GaussianState(
                    model.initial.mean.expand(B, -1).unsqueeze(-1), model.initial.cov
                )

                def theirs(peer=peer, prior=prior, measures=measures):
                    return peer.filter(prior, measures, update_first=False, return_all=True)

                def ours(model=model, ys=ys):
                    return df.kalman_filter(model, ys)

                big = B * T >= 1e6
                t = best_times({"ours": ours, "theirs": theirs}, repeats=3,
                               min_time=0.0 if big else 0.2)  # fmt: skip
                diff = float((ours().means - theirs().mean.squeeze(-1).transpose(0, 1)).abs().max())
            rows.append({
                "dtype": str(dtype).replace("torch.", ""), "B": B, "T": T,
                "ours": B * T / t["ours"], "torch_kf": B * T / t["theirs"],
                "ratio": t["theirs"] / t["ours"], "max_abs_mean_diff": diff,
                "load_average": os.getloadavg()[0],
            })  # fmt: skip
    return rows


def _fmt(x: float) -> str:
    return f"{x:,.3g}" if x < 1e3 else f"{x:,.0f}"


def print_peers(figures: dict) -> None:
    print(
        "\n8. Peers: torch-kf's batched Kalman filter beside difffilter.kalman_filter, "
        "constant-velocity model, alternating in one process (run-steps/s)"
    )
    rows = bench_torch_kf()
    if rows is None:
        print(
            '   skipped: torch-kf is not installed (pip install -e ".[bench]" or '
            "pip install torch-kf)"
        )
        figures["peers"] = {"skipped": "torch-kf not installed"}
        return
    import torch_kf

    figures["peers"] = {"torch_kf_version": torch_kf.__version__, "rows": rows}
    print(f"   torch-kf {torch_kf.__version__}, {torch.get_num_threads()} thread(s)")
    print(
        f"   {'dtype':>7s}  {'runs B':>7s}  {'T':>4s}  {'ours':>12s}  {'torch-kf':>12s}  "
        f"{'ours / torch-kf':>15s}  {'max |Δ mean|':>12s}"
    )
    for r in rows:
        print(
            f"   {r['dtype']:>7s}  {r['B']:>7,d}  {r['T']:>4d}  {_fmt(r['ours']):>12s}  "
            f"{_fmt(r['torch_kf']):>12s}  {r['ratio']:14.2f}×  {r['max_abs_mean_diff']:12.2g}"
            f"  (load {r['load_average']:.1f})"
        )
