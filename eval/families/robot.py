"""Robot family (Tan et al., lidar robot): Figs B1–B3, fusion against the locals with a
paired test, the attack estimate, NEES, the compensated loop and the paper's claims.

Position RMSE(k) is (B8): per step, the root of the mean over runs of the squared
position error. "Better local" is the local estimator with the lower RMSE over all steps.
The paired test compares, run by run, the fused and the better local's position RMSE over
``k ≥ 40`` (Wilcoxon signed-rank, two-sided).
"""

from __future__ import annotations

import math

import matplotlib.pyplot as plt
import torch
from scipy.stats import chi2, wilcoxon

from difffilter.consistency import nees
from difffilter.models.robot import DEG
from difffilter.runtime import one_thread

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

LATE = 40  # the "k ≥ 40"


def _wilcoxon_p(a, b) -> float:
    """The two-sided Wilcoxon signed-rank p-value of the per-run pairs ``a``, ``b`` ``[B]``;
    1 where they are equal on every run (no difference to test: SciPy 1.10, the lowest
    declared, raised there, later ones give 1)."""
    if not bool((a != b).any()):
        return 1.0
    return float(wilcoxon(a.numpy(), b.numpy()).pvalue)


def _share_lower(a, b) -> float:
    """The share of the runs with both numbers (``a``, ``b`` ``[B]`` finite) where ``a < b``;
    NaN where no run has both (a diverged run had counted as not lower: a trial)."""
    both = torch.isfinite(a) & torch.isfinite(b)
    if not bool(both.any()):
        return math.nan
    return float((a[both] < b[both]).double().mean())


def _pos_rmse_t(means, x) -> torch.Tensor:  # (B8) per step [T]
    return (means[..., :2] - x[..., :2]).square().sum(-1).mean(0).sqrt()


def _per_run(means, x, start: int) -> torch.Tensor:  # per run over k > start [B]
    return (means[:, start:, :2] - x[:, start:, :2]).square().sum(-1).mean(-1).sqrt()


def distance_to_path(points: torch.Tensor, path: torch.Tensor) -> torch.Tensor:
    """Each point's distance to a polyline, run by run: ``min_s ‖p − seg_s‖`` over the
    segments ``seg_s = [path_s, path_{s+1}]`` (the closest point of a segment is ``path_s + t
    (path_{s+1} − path_s)``, ``t`` the projection clamped to [0, 1]).

    ``points`` ``[B, P, 2]``, ``path`` ``[B, T, 2]`` (``T ≥ 2``) → ``[B, P]``. The distance to
    the path as a shape, whenever the robot passes there: beside the time-aligned distance,
    it tells a robot that drives the same circle faster (a phase lag) from one off it."""
    start, end = path[:, None, :-1], path[:, None, 1:]  # [B, 1, S, 2]
    along = end - start
    length2 = along.square().sum(-1).clamp_min(torch.finfo(path.dtype).tiny)
    t = ((points[:, :, None] - start) * along).sum(-1).div(length2).clamp(0.0, 1.0)  # [B, P, S]
    nearest = start + t[..., None] * along
    return (points[:, :, None] - nearest).norm(dim=-1).amin(-1)


def _on(attacked: list[bool], values: torch.Tensor) -> list[float | None]:
    """``values [2]`` as a list, ``None`` on an actuator the attack leaves (no relative
    error there)."""
    return [float(v) if on else None for on, v in zip(attacked, values.tolist())]


def _nees(out, x) -> float | None:
    """The mean over runs and steps of ``difffilter.consistency.nees``."""
    if out.covs is None:
        return None
    return float(nees(out.means - x, out.covs).mean())


@one_thread()
@torch.no_grad()
def _extra(result) -> dict:
    tr, outs, sc = result.traj, result.outputs, result.scenario
    x, B = tr.x, tr.x.shape[0]
    k0 = LATE - 1  # index of k = 40
    # each estimator against the states it ran on (its own closed loop, or the study's)
    curves = {n: _pos_rmse_t(o.means, result.traj_of(n).x) for n, o in outs.items()}
    for n, o in outs.items():
        m = result.metrics[n]
        m.update(position_rmse=float(curves[n].square().mean().sqrt()),
                 position_rmse_late=float(curves[n][k0:].square().mean().sqrt()),
                 nees=_nees(o, result.traj_of(n).x),
                 nan_runs=int((~o.means.isfinite()).flatten(1).any(1).sum()))  # fmt: skip
    extra: dict = {"rmse_curves": {n: c.tolist() for n, c in curves.items()}}
    locals_ = [n for n in ("mdpf_local_1", "mdpf_local_2") if n in outs]
    finite = [n for n in locals_ if math.isfinite(result.metrics[n]["position_rmse"])]
    if len(locals_) == 2 and finite:
        # of the locals with a number (min() had kept a diverged NaN local when it came
        # first, and every ratio read "—": a trial)
        better = min(finite, key=lambda n: result.metrics[n]["position_rmse"])
        fusion = {"better_local": better}
        for f in ("mdpf_fused_ci", "mdpf_fused_naive"):
            if f not in outs:
                continue
            a, b = _per_run(outs[f].means, x, k0), _per_run(outs[better].means, x, k0)
            fusion[f] = {
                "ratio_all": result.metrics[f]["position_rmse"] / result.metrics[better]["position_rmse"],
                "ratio_late": result.metrics[f]["position_rmse_late"] / result.metrics[better]["position_rmse_late"],
                "runs_lower_late": _share_lower(a, b),
                "wilcoxon_p_late": _wilcoxon_p(a, b),
            }  # fmt: skip
        extra["fusion"] = fusion
    if "mdpf_fused_ci" in outs:
        a_hat, a_true = outs["mdpf_fused_ci"].attack, tr.attack[0, -1]
        rel = (a_hat - a_true).abs() / a_true.abs()  # [B, T, 2]
        k44 = sc.attack_from + 14 - 1
        # a relative error of the attacked actuators alone: an actuator the attack leaves
        # (a = (20, 0)) has none (|â|/0 had been inf and the verdict "partly" for any â)
        attacked = (a_true != 0).tolist()
        extra["attack"] = {
            "mean_rel_error_k44": _on(attacked, rel.mean(0)[k44]),
            "mean_attack_k44": (a_hat.mean(0)[k44] / torch.tensor([1.0, DEG])).tolist(),
            "all_runs_within_10pct_at_end": bool((rel[:, -1, a_true != 0] < 0.1).all()),
            "max_rel_error_at_end": _on(attacked, rel[:, -1].amax(0)),
            "mean_curve": (a_hat.mean(0) / torch.tensor([1.0, DEG])).tolist(),
            "attacked_channels": attacked,
        }
    if "mdpf_fused_ci" in outs and "mdpf_fused_ci_compensated" in outs:
        ctx, name = result.context, "mdpf_fused_ci_compensated"
        loop, est = result.traj_of(name), outs[name].means  # its own closed loop
        applied = loop.us + loop.attack  # the sent input u − â plus the attack
        free = sc.simulate(B, ctx.streams.simulation(), attack=None, model=ctx.model)
        units = torch.tensor([1.0, DEG], dtype=applied.dtype)
        full = (applied - tr.us) / units  # a − â of the previous step, cm/s and deg/s
        a0 = sc.attack_from - 1  # index of the attack's first step
        err = full[:, k0:]
        # the uncompensated fused estimate's error a − â on the same steps, with the â of
        # step k itself (the estimator alone; the loop's error above uses the previous â)
        open_err = (tr.attack - a_hat)[:, k0:] / units
        extra["compensation"] = {
            "input_error": _input_error_readings(err, LATE),
            "open_loop_attack_error": _input_error_readings(open_err, LATE),
            "input_error_curves": {"mean": full.mean(0).tolist(), "rms": full.square().mean(0).sqrt().tolist()},
            "deviation_from_attack_free_cm": float((loop.x[..., :2] - free.x[..., :2]).norm(dim=-1)[:, -1].mean()),
            # over the steps from the attack on, beside the uncompensated robot's (at its end
            # alone the uncompensated robot, circling, had ended nearer: a trial)
            "mean_deviation_from_attack_free_cm": float(
                (loop.x[:, a0:, :2] - free.x[:, a0:, :2]).norm(dim=-1).mean()),
            "uncompensated_mean_deviation_from_attack_free_cm": float(
                (x[:, a0:, :2] - free.x[:, a0:, :2]).norm(dim=-1).mean()),
            # the same steps' distance to the attack-free path as a shape: on the straight
            # scenario the attacked robot drives nearly the attack-free circle, faster, and
            # its time-aligned distance is mostly that lag (a trial)
            "mean_distance_to_attack_free_path_cm": float(
                distance_to_path(loop.x[:, a0:, :2], free.x[..., :2]).mean()),
            "uncompensated_mean_distance_to_attack_free_path_cm": float(
                distance_to_path(x[:, a0:, :2], free.x[..., :2]).mean()),
            "position_rmse_closed_loop": float(_pos_rmse_t(est, loop.x).square().mean().sqrt()),
            "paths": {"attack_free": free.x[0, :, :2].tolist(), "attacked": x[0, :, :2].tolist(),
                      "compensated": loop.x[0, :, :2].tolist(), "estimate": est[0, :, :2].tolist()},
        }  # fmt: skip
    pos = result.context.model.sensor_pos
    dist = torch.cdist(x[..., :2], pos.to(x))  # [B, T, 6]
    extra["sensor_distance_cm"] = {"min_over_runs": dist.amin((0, 1)).tolist(),
                                   "median_run_min": dist.amin(1).median(0).values.tolist()}  # fmt: skip
    return extra


#: The input-error bound of issue 11 (cm/s, deg/s) and the reading it is checked on: (a),
#: the RMS over runs and steps k ≥ 40 (a per-step bound would contradict the issue's own
#: allowance of 10 % = 2 cm/s at k = 44; docs/scenarios.md §4).
INPUT_BOUND = 1.0
INPUT_READING = "pooled_rms"


def _input_error_readings(err: torch.Tensor, first_k: int) -> dict:
    """Every reading of an input error ``err [B, K, 2]`` (runs, steps ``k ≥ first_k``,
    channels in cm/s and deg/s), each per channel:

    * ``pooled_rms``: √(mean over runs and steps of e²);
    * ``max_step_rms``: max over k of √(mean over runs of e²(k)) (the RMS(k) curve's peak);
    * ``max_step_mean``: max over k of |mean over runs of e(k)| (the ensemble's error at
      every step);
    * ``worst_run_step``: max over runs and k of |e|;
    * ``share_within``: share of run-steps with |e| ≤ 1;
    * ``bias``, ``spread``: mean and standard deviation of e over runs and steps
      (``pooled_rms² = bias² + spread²``);
    * ``argmax_k``: the k of each per-step maximum; ``settle_k``: the first k from which
      the per-step RMS / |mean| stays ≤ 1 (:func:`_settle`).
    """
    rms_k, mean_k = err.square().mean(0).sqrt(), err.mean(0)  # [K, 2]
    flat = err.reshape(-1, 2)
    return {
        "pooled_rms": err.square().mean((0, 1)).sqrt().tolist(),
        "max_step_rms": rms_k.amax(0).tolist(),
        "max_step_mean": mean_k.abs().amax(0).tolist(),
        "worst_run_step": err.abs().amax((0, 1)).tolist(),
        "share_within": (err.abs() <= INPUT_BOUND).double().mean((0, 1)).tolist(),
        "bias": flat.mean(0).tolist(),
        "spread": flat.std(0, correction=0).tolist(),
        "argmax_k": {"max_step_rms": (rms_k.argmax(0) + first_k).tolist(),
                     "max_step_mean": (mean_k.abs().argmax(0) + first_k).tolist()},
        "settle_k": {"max_step_rms": _settle(rms_k, first_k), "max_step_mean": _settle(mean_k.abs(), first_k)},
    }  # fmt: skip


def _settle(curve: torch.Tensor, first_k: int) -> list:
    """Per channel of ``curve [K, 2]`` (steps ``k = first_k …``): the first ``k`` from which
    the curve stays ≤ the bound to the end (``None`` if its last step exceeds it)."""
    out = []
    for c in curve.unbind(-1):
        above = (c > INPUT_BOUND).nonzero()
        if len(above) == 0:
            out.append(first_k)
        elif int(above[-1]) == len(c) - 1:
            out.append(None)
        else:
            out.append(int(above[-1]) + 1 + first_k)
    return out


_READINGS = (
    ("pooled_rms", "(a) pooled RMS over runs and steps"),
    ("max_step_rms", "(b) per-step RMS over runs, max over k"),
    ("max_step_mean", "(c) per-step mean over runs, max over k of its magnitude"),
    ("worst_run_step", "(d) worst single run-step"),
)


def _input_error_table(ie: dict, oe: dict | None) -> str:
    f = format_number
    rows = []
    for key, label in _READINGS:
        ok = all(v <= INPUT_BOUND for v in ie[key])
        row = [label, f(ie[key][0]), f(ie[key][1]), "yes" if ok else "no"]
        if oe is not None:
            row += [f(oe[key][0]), f(oe[key][1])]
        rows.append(row)
    head = ["reading (k ≥ 40)", "cm/s", "deg/s", "≤ 1 and ≤ 1"]
    return markdown_table(
        head + (["a − â without compensation, cm/s", "deg/s"] if oe else []), rows
    )


def _figures(result, doc, out) -> list[str]:
    t = list(range(1, doc["steps"] + 1))
    files = []
    comp = doc.get("compensation")
    if comp:
        fig, ax = plt.subplots(figsize=(6, 6))
        # the compensated path wide beneath the estimate's dashes: the two nearly coincide,
        # and at one width the estimate had hidden the path it compensates
        styles = {"attack_free": ("b-", 1), "attacked": ("g-", 1), "compensated": ("k-", 3),
                  "estimate": ("r--", 1)}  # fmt: skip
        for k, p in comp["paths"].items():
            p = torch.tensor(p)
            fmt, width = styles[k]
            ax.plot(p[:, 0], p[:, 1], fmt, lw=width, label=k.replace("_", " "))
        s = result.context.model.sensor_pos
        ax.plot(s[:, 0], s[:, 1], "m^", label="lidars")
        ax.set(xlabel="s_x (cm)", ylabel="s_y (cm)", title="Fig. B1: run 0", aspect="equal")
        ax.legend(fontsize=7)
        save_figure(fig, out / "fig_b1_trajectories.png", dpi=110, bbox_inches="tight")
        plt.close(fig)
        files.append("fig_b1_trajectories.png")
    from ..plots import estimator_looks, legend_beside, mark_off_scale

    looks = estimator_looks(result.outputs)  # each in its colour of the report's figures
    fig, ax = plt.subplots(figsize=(8, 4))
    for n, c in doc["rmse_curves"].items():
        ax.plot(t, c, lw=1, label=n, **looks.get(n, {}))
    ax.set(xlabel="k", ylabel="position RMSE (cm)", yscale="log", title="Fig. B2: RMSE(k), (B8)")
    legend_beside(ax)
    save_figure(fig, out / "fig_b2_rmse.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    files.append("fig_b2_rmse.png")
    att = doc.get("attack")
    if att:
        curve = torch.tensor(att["mean_curve"])
        a = result.scenario.attack
        fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
        for i, (lab, unit) in enumerate((("a_p", "cm/s"), ("a_r", "deg/s"))):
            truth = [0.0 if k < result.scenario.attack_from else a[i] for k in t]
            ax[i].plot(t, truth, "k-", lw=1, label="a")
            ax[i].plot(t, curve[:, i], "r--", lw=1, label="mean fused â")
            ax[i].set(xlabel="k", ylabel=f"{lab} ({unit})")
            ax[i].legend(fontsize=7)
        fig.suptitle("Fig. B3: attack and its fused estimate")
        save_figure(fig, out / "fig_b3_attack.png", dpi=110, bbox_inches="tight")
        plt.close(fig)
        files.append("fig_b3_attack.png")
    curves = (comp or {}).get("input_error_curves")
    if curves:
        mean, rms = torch.tensor(curves["mean"]), torch.tensor(curves["rms"])
        fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
        for i, unit in enumerate(("cm/s", "deg/s")):
            ax[i].plot(t, mean[:, i], "r-", lw=1, label="mean over runs")
            ax[i].plot(t, rms[:, i], "b--", lw=1, label="RMS over runs")
            for b in (-INPUT_BOUND, INPUT_BOUND):
                ax[i].axhline(b, color="k", lw=0.5, ls=":")
            ax[i].axvline(LATE, color="k", lw=0.5)
            ax[i].set(xlabel="k", ylabel=f"a − â ({unit})")
            mark_off_scale(ax[i], t, (mean[:, i], rms[:, i]), (-2, 6), f" {unit}")
            ax[i].legend(fontsize=7)
        fig.suptitle("Effective input error with compensation (bound ±1 from k = 40)")
        save_figure(fig, out / "fig_input_error.png", dpi=110, bbox_inches="tight")
        plt.close(fig)
        files.append("fig_input_error.png")
    return files


def _sections(result, doc: dict, out, prepared=None) -> list[Section]:
    f, est, runs = format_number, doc["estimators"], doc["runs"]
    lo, hi = chi2.ppf([0.025, 0.975], 3 * runs) / runs
    rows = [[f"`{n}`", f(e["position_rmse"]), f(e["position_rmse_late"]), f(e["attack_rmse"]), f(e["nees"]),
             e["nan_runs"]] for n, e in est.items()]  # fmt: skip
    body = markdown_table(
        [
            "estimator",
            "position RMSE (cm)",
            "k ≥ 40",
            "attack RMSE",
            "NEES (dx = 3)",
            "runs with NaN",
        ],
        rows,
    )
    body += (f"\nNEES: mean over runs and steps of eᵀP⁻¹e; a consistent filter gives 3, the 95 % band of one "
             f"step's mean over {runs} runs is [{lo:.2f}, {hi:.2f}]. Attack RMSE mixes cm/s and rad/s (scoring's "
             "definition); the attack table below is per channel.\n")  # fmt: skip
    secs = [Section("Position RMSE and consistency", body, _figures(result, doc, out))]
    fus = doc.get("fusion")
    if fus:
        rows = [[f"`{n}`", f(v["ratio_all"]), f(v["ratio_late"]), f(v["runs_lower_late"]), f(v["wilcoxon_p_late"])]
                for n, v in fus.items() if n != "better_local"]  # fmt: skip
        body = markdown_table(
            [
                "fused",
                "RMSE / better local (all k)",
                "k ≥ 40",
                "share of runs lower (k ≥ 40)",
                "Wilcoxon p",
            ],
            rows,
        )
        body += (
            f"\nBetter local: `{fus['better_local']}`. Targets: ≤ 0.98 (all k), ≤ 0.92 (k ≥ 40).\n"
        )
        secs.append(Section("Fusion against the locals (paired)", body))
    att, comp = doc.get("attack"), doc.get("compensation")
    if att:
        k44 = result.scenario.attack_from + 14
        attacked = att.get("attacked_channels", [True, True])
        rel, worst = ([f(e) if on else "— (not attacked)" for on, e in zip(attacked, att[key])]
                      for key in ("mean_rel_error_k44", "max_rel_error_at_end"))  # fmt: skip
        body = (f"Mean fused â at k = {k44}: {f(att['mean_attack_k44'][0])} cm/s, {f(att['mean_attack_k44'][1])} deg/s "
                f"(mean over runs of |â − a|/|a| {rel[0]}, {rel[1]}; target < 0.1). "
                f"Every run within 10 % at k = {doc['steps']}: {att['all_runs_within_10pct_at_end']} (largest relative errors "
                f"{worst[0]}, {worst[1]}).\n")  # fmt: skip
        if comp:
            ie, oe = comp["input_error"], comp["open_loop_attack_error"]
            reading = ie[INPUT_READING]
            input_bound = verdict(None if any(v is None for v in reading)
                                  else all(v <= INPUT_BOUND for v in reading))  # fmt: skip
            lam = result.scenario.forgetting
            body += ("\nCompensated loop (u ← u − â_f with the fused estimate of the previous step, same plant "
                     "noise): the effective input error e = a − â for k ≥ 40 by every reading, beside the "
                     "uncompensated fused estimate's error a − â on the same steps (its â of the "
                     "same step k: the estimator alone, where the loop applies the previous one):\n\n"
                     + _input_error_table(ie, oe)
                     + f"\nCriterion (issue 11: ≤ 1 cm/s and ≤ 1 deg/s after k = 40), read as (a), the RMS over "
                     f"runs and steps (a per-step bound would contradict the 10 % = 2 cm/s the issue allows at "
                     f"k = 44): **{input_bound}**. The stricter per-step reading (c), the ensemble's error at every "
                     f"step, peaks at {f(ie['max_step_mean'][0])} cm/s (k = {ie['argmax_k']['max_step_mean'][0]}) "
                     f"and {f(ie['max_step_mean'][1])} deg/s (k = {ie['argmax_k']['max_step_mean'][1]}) and stays "
                     f"≤ 1 from k = {ie['settle_k']['max_step_mean'][0]} / {ie['settle_k']['max_step_mean'][1]} on "
                     f"(the RMS over runs from k = {ie['settle_k']['max_step_rms'][0]} / "
                     f"{ie['settle_k']['max_step_rms'][1]}): the tail of â's convergence after the onset at k = "
                     f"{result.scenario.attack_from} (the uncompensated mean fused â at k = {LATE} is "
                     f"{f(att['mean_curve'][LATE - 1][0])} cm/s, {f(att['mean_curve'][LATE - 1][1])} deg/s). "
                     f"Over all run-steps the error has bias {f(ie['bias'][0])} cm/s, {f(ie['bias'][1])} deg/s "
                     f"and spread (s.d.) {f(ie['spread'][0])} cm/s, {f(ie['spread'][1])} deg/s: the spread, the "
                     f"noise of â (forgetting λ = {f(lam)}, a memory of about 1/(1 − λ) = {f(1 / (1 - lam))} "
                     f"steps), is what (b) and (d) add; {f(100 * ie['share_within'][0])} % / "
                     f"{f(100 * ie['share_within'][1])} % of run-steps are within 1 cm/s / 1 deg/s. Final "
                     f"distance to the attack-free path {f(comp['deviation_from_attack_free_cm'])} cm; "
                     f"closed-loop fused position RMSE {f(comp['position_rmse_closed_loop'])} cm.\n")  # fmt: skip
        secs.append(Section("Attack estimate and compensation (Figs B1, B3)", body))
    d = doc["sensor_distance_cm"]
    body = markdown_table(["lidar", *range(1, 7)], [["closest approach, all runs (cm)", *map(f, d["min_over_runs"])],
                                                    ["median over runs (cm)", *map(f, d["median_run_min"])]])  # fmt: skip
    secs.append(Section("How close the attacked robot comes to the lidars", body))
    secs.append(Section("The paper's claims", _claims(doc)))
    return secs


def _claims(doc) -> str:
    est, fus, att = doc["estimators"], doc.get("fusion") or {}, doc.get("attack") or {}
    lines = []
    ci = fus.get("mdpf_fused_ci")
    if ci:
        pooled, late = less(ci["ratio_all"], 1), less(ci["ratio_late"], 1)
        holds = None if pooled is None or late is None else pooled and late
        ra, rl = format_number(ci["ratio_all"]), format_number(ci["ratio_late"])
        lines.append(
            f"- Fusion below both locals (Fig. B2): {verdict(holds)} for the position, pooled "
            f"over the steps (CI/better local {ra}, k ≥ 40: {rl})."
        )
        attack = {n: est.get(n, {}).get("attack_rmse") for n in
                  ("mdpf_fused_ci", "mdpf_local_1", "mdpf_local_2")}  # fmt: skip
        if all(v is not None for v in attack.values()):
            fused, best = attack.pop("mdpf_fused_ci"), min(attack, key=attack.get)
            below = "below" if fused < attack[best] else "not below"
            lines.append(
                f"- The fused attack estimate is {below} the better local's: attack RMSE "
                f"{format_number(fused)} against `{best}`'s {format_number(attack[best])}."
            )
    if "zhang_akf" in est and "mdpf_fused_ci" in est:
        z, fz = est["zhang_akf"]["position_rmse"], est["mdpf_fused_ci"]["position_rmse"]
        # the group filters that ran and have a number (none: no clause; a 1e9 stand-in had
        # been reported as a win "against Zhang on one group (1.000e+09 cm)")
        groups = [est[g]["position_rmse"] for g in ("zhang_akf_group1", "zhang_akf_group2")
                  if est.get(g, {}).get("position_rmse") is not None]  # fmt: skip
        zg = min(groups) if groups else None
        group = "" if zg is None else (f"; against Zhang on one group ({format_number(zg)} cm) it "
                                       f"{verdict(less(fz, zg))}")  # fmt: skip
        lines.append(f"- Fusion below Zhang's filter (Fig. B2): {verdict(less(fz, z))} against Zhang "
                     f"with all six lidars ({format_number(fz)} vs {format_number(z)} cm){group}. One EKF on all twelve "
                     "measurements uses the joint information exactly, while the fusion combines two 3-lidar "
                     "estimates conservatively (CI) from particle approximations, so the six-lidar Zhang filter "
                     "is the stronger baseline; the paper does not say which sensors its Zhang run used.")  # fmt: skip
    if att:
        # the attacked actuators' errors (an unattacked one has no relative error)
        attacked = att.get("attacked_channels", [True, True])
        errors = [e for on, e in zip(attacked, att["mean_rel_error_k44"]) if on]
        if not errors or any(e is None for e in errors):
            said = NOT_JUDGED
        else:
            ok = max(errors) < 0.1 and att["all_runs_within_10pct_at_end"]
            said = "holds" if ok else "partly"
        lines.append(f"- â(k) converges to a (Fig. B3): {said}.")
    comp = doc.get("compensation")
    if comp:
        near = comp.get("mean_deviation_from_attack_free_cm")
        far = comp.get("uncompensated_mean_deviation_from_attack_free_cm")
        said = "" if near is None or far is None else (
            f"{verdict(less(near, far))}: from the attack on it is "
            f"{format_number(near)} cm from it on average against the uncompensated robot's "
            f"{format_number(far)} cm; ")  # fmt: skip
        shape_near = comp.get("mean_distance_to_attack_free_path_cm")
        shape_far = comp.get("uncompensated_mean_distance_to_attack_free_path_cm")
        shape = "" if shape_near is None or shape_far is None else (
            f" From the path as a shape (wherever the robot passes there, not when): "
            f"{format_number(shape_near)} cm against {format_number(shape_far)} cm.")  # fmt: skip
        lines.append("- Compensation keeps the robot near the attack-free path (Fig. B1): "
                     f"{said}the compensated robot ends "
                     f"{format_number(comp['deviation_from_attack_free_cm'])} cm from it on average.{shape}")  # fmt: skip
    return "\n".join(lines) + "\n"


register_family("robot", FamilyReport(extra=_extra, sections=_sections))
