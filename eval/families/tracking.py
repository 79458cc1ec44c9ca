"""Tracking family report (RRP particle filter with deception attacks, Song et al.): Table 1
beside ours, the posterior Cramér–Rao bound, the η̄ sweep and the EKF proposal. The
family's estimators are registered in ``difffilter.models.tracking_estimators``.

RMSE_p / RMSE_v follow the paper: per step, the RMSE over runs of the position (velocity)
error norm, then the mean over steps. The bound is :func:`difffilter.posterior_crb` along
the true trajectories (the runs are the Monte Carlo paths of its expectations): on the
Round-Robin mask for the clean-data filter, and with the attacked packets removed from the
mask (an attack oracle, a valid floor for a filter that does not know them) for the others.
"""

from __future__ import annotations

import time
from dataclasses import replace

import matplotlib.pyplot as plt
import torch
from torch import Tensor

from difffilter.bounds import posterior_crb
from difffilter.models.attacks import Replacement
from difffilter.models.estimators import SuiteContext, get
from difffilter.models.tracking import communication_counts
from difffilter.runtime import one_thread

from ..intervals import register_stepwise
from ..report import (
    NOT_JUDGED,
    FamilyReport,
    Section,
    format_number,
    less,
    markdown_table,
    register_family,
    save_figure,
    verdict,
)
from ..scoring import auc
from ..suite import single_run_time_per_step

TABLE1 = ("rrp_pf_da", "rrp_spf_da", "rrp_spf_nm", "pf_da")
SWEEP = (0.0, 0.2, 0.4, 0.6)


# ------------------------------------------------------------------------- family numbers


def _position_velocity_sq(means, x) -> tuple[torch.Tensor, torch.Tensor]:
    """Squared position and velocity error norms ``[B, T]`` each (state ``[px, vx, py, vy]``)."""
    e = (means - x).square()
    return e[..., 0] + e[..., 2], e[..., 1] + e[..., 3]


def _rmse_pv(means, x) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-step RMSE over runs of the position and velocity error norms ``[T]`` each."""
    p, v = _position_velocity_sq(means, x)
    return p.mean(0).sqrt(), v.mean(0).sqrt()


# the acceptance's state metric (RMSE_p) resamples runs per step (difffilter.eval.intervals)
register_stepwise("rmse_p", lambda means, x: _position_velocity_sq(means, x)[0])


def _bounds(result) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """PCRB of position and velocity ``[T]``: Round-Robin or all sensors, clean or attack oracle."""
    tr, ctx = result.traj, result.context
    groups = result.scenario.groups
    recv_attacked = Replacement.entry_flags(tr.info["sensor_flags"], groups)
    masks = {"rr_clean": tr.mask[0], "rr_oracle": tr.mask & ~recv_attacked, "all_clean": None,
             "all_oracle": ~recv_attacked}  # fmt: skip
    out = {}
    for name, mask in masks.items():
        b = posterior_crb(
            ctx.model,
            tr.x,
            tr.info["x0"],
            mask=mask,
            generator=ctx.streams("pcrb"),
            num_samples=100_000,
        )
        cov = b.bound if b.bound.dim() == 3 else b.bound.mean(0)  # mean over runs' flag patterns
        out[name] = ((cov[:, 0, 0] + cov[:, 2, 2]).sqrt(), (cov[:, 1, 1] + cov[:, 3, 3]).sqrt())
    return out


def _bound_for(name: str) -> str:
    return {"rrp_spf_nm": "rr_clean", "pf_da": "all_oracle"}.get(name, "rr_oracle")


def _sweep(result) -> list[dict]:
    """``rrp_pf_da`` at η̄ ∈ SWEEP on the same plant and random numbers (``rrp_spf_nm``
    reads no η̄: its figures are the study's own)."""
    sc, ctx, rows = result.scenario, result.context, []
    for eta in SWEEP:
        s = replace(sc, eta_bar=eta)
        tr = s.simulate(result.runs, ctx.streams.simulation(), model=ctx.model)
        sctx = SuiteContext(s, ctx.model, result.runs, ctx.streams, ctx.options)
        out = get("rrp_pf_da").factory(sctx)(tr)
        p, v = _rmse_pv(out.means, tr.x)
        rows.append({"eta_bar": eta, "rmse_p": float(p.mean()), "rmse_v": float(v.mean()),
                     "auc": auc(out.detection.scores, tr.flags), "rmse_p_t": p.tolist()})  # fmt: skip
    return rows


def _extra(result) -> dict:
    with one_thread(), torch.no_grad():
        return _numbers(result)


def _transmissions(out, tr):
    """Packets per run: the estimator's own count, else those of the scenario's schedule."""
    if "transmissions" in out.extras:
        return out.extras["transmissions"]
    return communication_counts(tr.mask, *tr.flags.shape, len(tr.info["sensor_flags"][0, 0]))


def _position_velocity_rmse(result, name: str) -> dict:
    """``rmse_p`` and ``rmse_v`` of estimator ``name``: the acceptance's state metric."""
    p, v = _rmse_pv(result.outputs[name].means, result.traj.x)
    return {"rmse_p": float(p.mean()), "rmse_v": float(v.mean())}


def _share_at_or_above(p: Tensor, v: Tensor, bp: Tensor, bv: Tensor) -> float:
    """The share of steps whose position and velocity RMSE (``[T]``) are at or above their
    bound's; NaN where a bound or an RMSE is not finite at some step (a NaN step compared
    False, and half the steps had read as beating a lower bound: a trial; a diverged
    estimate's NaN RMSE, the same: another)."""
    if not all(bool(torch.isfinite(t).all()) for t in (p, v, bp, bv)):
        return float("nan")
    return float(((p >= bp) & (v >= bv)).double().mean())


def _numbers(result) -> dict:
    tr, ctx, sc = result.traj, result.context, result.scenario
    bounds = _bounds(result)
    for name, out in result.outputs.items():
        p, v = _rmse_pv(out.means, tr.x)
        bp, bv = bounds[_bound_for(name)]
        m = result.metrics[name]
        m.update(rmse_p=float(p.mean()), rmse_v=float(v.mean()), bound=_bound_for(name),
                 bound_rmse_p=float(bp.mean()), bound_rmse_v=float(bv.mean()),
                 ratio_p=float(p.mean() / bp.mean()), ratio_v=float(v.mean() / bv.mean()),
                 steps_at_or_above_bound=_share_at_or_above(p, v, bp, bv),
                 communication=float(_transmissions(out, tr).double().mean()),
                 time_per_run_batched_s=result.wall_s[name] / result.runs,
                 time_per_run_single_s=single_run_time_per_step(get(name), ctx, tr) * sc.steps)  # fmt: skip
    if "pf_da" in result.outputs:
        per = result.outputs["pf_da"].extras["sensor_attack_probability"]
        result.metrics["pf_da"]["auc_all_sensors"] = auc(
            per.flatten(1), tr.info["sensor_flags"].flatten(1)
        )
    extra = {"pcrb": {k: {"rmse_p": float(p.mean()), "rmse_v": float(v.mean())} for k, (p, v) in bounds.items()},
             "eta_sweep": _sweep(result)}  # fmt: skip
    if {"rrp_pf_da", "rrp_pf_da_ekf_proposal"} <= set(result.outputs):
        extra["equal_wall_time"] = _equal_wall_time(result)
    extra["bound_curves"] = {k: [p.tolist(), v.tolist()] for k, (p, v) in bounds.items()}
    return extra


def _equal_wall_time(result) -> dict:
    """``rrp_pf_da`` with as many particles as fit in ``rrp_pf_da_ekf_proposal``'s wall time.

    The count scales the 500-particle time; the time per particle grows with the cloud
    (cache), so one correction by the measured time follows when it is off by over 20 %.
    """
    sc, ctx, tr = result.scenario, result.context, result.traj
    target = result.wall_s["rrp_pf_da_ekf_proposal"]
    n_eq = max(1, round(sc.num_particles * target / result.wall_s["rrp_pf_da"]))
    for _ in range(2):
        sctx = SuiteContext(
            replace(sc, num_particles=n_eq), ctx.model, result.runs, ctx.streams, ctx.options
        )
        start = time.perf_counter()
        out = get("rrp_pf_da").factory(sctx)(tr)
        wall = time.perf_counter() - start
        if _equal_times(wall, target):
            break
        n_eq = max(1, round(n_eq * target / wall))
    p, v = _rmse_pv(out.means, tr.x)
    return {"num_particles": sctx.scenario.num_particles, "rmse_p": float(p.mean()), "rmse_v": float(v.mean()),
            "time_per_run_batched_s": wall / result.runs}  # fmt: skip


# ------------------------------------------------------------------------------ sections


def _sections(result, doc: dict, out, prepared=None) -> list[Section]:
    secs = [_table1(doc), _bound_section(result, doc, out), _eta_section(doc, out)]
    proposal = _proposal_section(result, doc)
    return secs + ([] if proposal is None else [proposal])


def _table1(doc: dict) -> Section:
    """Table 1 of the paper beside ours."""
    f, est, paper = format_number, doc["estimators"], (doc["paper"].get("table1") or {})
    head = ["estimator", "paper RMSE_p", "ours RMSE_p", "paper RMSE_v", "ours RMSE_v", "paper time",
            "ours s/run (batched / single run)", "paper comm.", "ours comm."]  # fmt: skip
    rows = []
    for n in est:
        e, pp = est[n], paper.get(n, {})
        rows.append([f"`{n}`", f(pp.get("rmse_p")), f(e["rmse_p"]), f(pp.get("rmse_v")), f(e["rmse_v"]),
                     f(pp.get("running_time")), f"{f(e['time_per_run_batched_s'])} / {f(e['time_per_run_single_s'])}",
                     pp.get("communication", "—"), f(e["communication"])])  # fmt: skip
    body = markdown_table(head, rows) + (
        "\nThe paper does not state the unit of its running time; ours is seconds per run, batched over the "
        "runs (throughput) and for one run alone (latency). Communication: packets sent per run.\n"
    )
    return Section("Table 1 beside the paper", body)


def _bound_section(result, doc: dict, out) -> Section:
    """The RMSEs beside the PCRB, with the curves plotted."""
    f, est = format_number, doc["estimators"]

    head = [
        "estimator",
        "bound",
        "RMSE_p",
        "PCRB_p",
        "ratio_p",
        "RMSE_v",
        "PCRB_v",
        "ratio_v",
        "fraction of steps ≥ bound",
    ]
    rows = [[f"`{n}`", e["bound"], f(e["rmse_p"]), f(e["bound_rmse_p"]), f(e["ratio_p"]), f(e["rmse_v"]),
             f(e["bound_rmse_v"]), f(e["ratio_v"]), f(e["steps_at_or_above_bound"])] for n, e in est.items()]  # fmt: skip
    body = markdown_table(head, rows) + (
        "\nPosterior Cramér–Rao bound (Tichavský recursion, glint Fisher information by Monte Carlo) along the "
        "simulated trajectories; `rr_clean`: Round-Robin mask; `rr_oracle` / `all_oracle`: the attacked packets "
        "removed (an attack oracle, so a floor for filters that must infer them). Time-averaged like the RMSEs.\n"
    )
    from ..plots import estimator_looks, legend_beside

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    t = list(range(1, doc["steps"] + 1))
    looks = estimator_looks(result.outputs)  # each in its colour of the report's figures
    for n, o in result.outputs.items():
        p, v = _rmse_pv(o.means, result.traj.x)
        ax[0].plot(t, p.numpy(), lw=1, label=n, **looks[n])
        ax[1].plot(t, v.numpy(), lw=1, label=n, **looks[n])
    styles = {"rr_clean": ":", "rr_oracle": "--", "all_oracle": "-."}
    # which estimators each bound is the floor of (the table's "bound" column)
    bounded: dict[str, list[str]] = {}
    for n, e in est.items():
        bounded.setdefault(e["bound"], []).append(n)
    for k, (bp, bv) in doc["bound_curves"].items():
        if k in styles:
            of = f" (of {', '.join(bounded[k])})" if bounded.get(k) else ""
            ax[0].plot(t, bp, "k", ls=styles[k], lw=1, label=f"PCRB {k}{of}")
            ax[1].plot(t, bv, "k", ls=styles[k], lw=1)
    ax[0].set(xlabel="k", ylabel="RMSE_p [length (paper's, unstated)]", yscale="log",
              title="Position RMSE and bound")  # fmt: skip
    ax[1].set(xlabel="k", ylabel="RMSE_v [length/s (paper's, unstated)]", yscale="log",
              title="Velocity RMSE and bound")  # fmt: skip
    # (the bounds alone where no estimator ran)
    legend_beside(ax[1], handles=ax[0].get_legend_handles_labels()[0])
    save_figure(fig, out / "rmse_vs_bound.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return Section("RMSE next to the posterior Cramér–Rao bound", body, ["rmse_vs_bound.png"])


def _eta_section(doc: dict, out) -> Section:
    """The η̄ sweep of Fig. 5 and the deception-detection AUC."""
    f, est = format_number, doc["estimators"]
    t, sw = list(range(1, doc["steps"] + 1)), doc["eta_sweep"]
    body = markdown_table(["η̄", "rrp_pf_da RMSE_p", "RMSE_v", "AUC of P(attack)"],
                          [[r["eta_bar"], f(r["rmse_p"]), f(r["rmse_v"]), f(r["auc"])] for r in sw])  # fmt: skip
    fig, ax = plt.subplots(figsize=(7, 4))
    for r in sw:
        ax.plot(t, r["rmse_p_t"], lw=1, label=f"η̄ = {r['eta_bar']}")
    ax.set(xlabel="k", ylabel="RMSE_p [length (paper's, unstated)]", yscale="log",
           title="rrp_pf_da position RMSE versus η̄ (Fig. 5)")  # fmt: skip
    ax.legend(fontsize=8)
    save_figure(fig, out / "eta_sweep.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    body += (
        "\nSame plant, schedule and particle random numbers; the attack uniforms are shared, "
        "so the attacked sets are nested in η̄.\n"
    )
    if "auc_all_sensors" in est.get("pf_da", {}):
        auc_all = f(est["pf_da"]["auc_all_sensors"])
        body += f"\n`pf_da`'s per-sensor attack posterior over all four sensors' packets: AUC {auc_all}.\n"
    return Section("η̄ sweep and deception detection", body, ["eta_sweep.png"])


def _proposal_section(result, doc: dict) -> Section | None:
    """The EKF proposal against the bootstrap filter at equal particles and equal wall time."""
    f, est = format_number, doc["estimators"]
    eq = doc.get("equal_wall_time")
    if not eq:
        return None
    a, b = est["rrp_pf_da"], est["rrp_pf_da_ekf_proposal"]
    n = result.scenario.num_particles

    def row(label, particles, e):
        return [
            label,
            particles,
            f(e["rmse_p"]),
            f(e["rmse_v"]),
            f(e["time_per_run_batched_s"]),
        ]

    rows = [row("`rrp_pf_da`", n, a), row("`rrp_pf_da_ekf_proposal`", n, b),
            row("`rrp_pf_da`, particles for the proposal's wall time", eq["num_particles"], eq)]  # fmt: skip
    body = markdown_table(["filter", "particles", "RMSE_p", "RMSE_v", "s/run (batched)"], rows)
    same_n = verdict(less(b["rmse_p"], a["rmse_p"]), "lower", "higher")
    body += (f"\nAt {n} particles the EKF proposal's RMSE_p is {same_n} than the bootstrap filter's "
             f"({f(b['rmse_p'])} vs {f(a['rmse_p'])}); for its wall time the bootstrap filter runs "
             f"{eq['num_particles']} particles (measured time in the last column): "
             + _equal_time_verdict(eq, b) + "\n")  # fmt: skip
    return Section("EKF proposal (the paper's Remark 2 leaves a UKF one to future work)", body)


def _equal_times(seconds: float, target: float) -> bool:
    """Whether ``seconds`` is ``target``'s wall time within 20 %: where the particle count's
    correction stops, and what the report calls equal (a review: the two had differed)."""
    return abs(seconds / target - 1) <= 0.2


def _equal_time_verdict(eq: dict, proposal: dict) -> str:
    """Whether the EKF proposal helps at equal wall time, said as measured: the particle
    count scales timings taken as the study runs, and under load the bootstrap filter's
    measured time can end far from the proposal's (a demo's 6405 particles ran in 0.18 s
    against 0.46 s, reported as "equal wall time"); equal as the count's correction takes
    it (:func:`_equal_times`), else the verdict holds only where the time favours the
    loser."""
    seconds, target = eq["time_per_run_batched_s"], proposal["time_per_run_batched_s"]
    ratio = seconds / target
    better = less(proposal["rmse_p"], eq["rmse_p"])
    if better is None:  # (a diverged run: its RMSE_p is null, and None < x had stopped the report)
        return f"whether the EKF proposal helps {NOT_JUDGED}."
    if _equal_times(seconds, target):
        return f"at equal wall time the EKF proposal {'helps' if better else 'does not help'}."
    times = f"{ratio:#.3g}" if ratio < 10 else f"{ratio:.0f}"  # (1.20, not 1.2; 123, not 123.)
    took = (f"not equal wall time: the bootstrap filter took {times}× the EKF proposal's "
            "(the count scales timings that moved under load)")  # fmt: skip
    if not better and ratio < 1:
        return f"{took}, and it is better in less time: the EKF proposal does not help."
    if better and ratio > 1:
        return f"{took}, and the EKF proposal is better still: it helps."
    return f"{took}: this run does not settle whether the EKF proposal helps."


# its report times every estimator on one run and runs the equal-wall-time study: about
# 20 s against 2.4 s for a plain report (2026-11-27, difffilter-eval all --devices 2)
register_family(
    "tracking",
    FamilyReport(extra=_extra, sections=_sections, estimator_metrics=_position_velocity_rmse,
                 report_cost=8.0),
)  # fmt: skip
