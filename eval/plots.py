"""The figures every scenario's report gets (matplotlib, Agg backend; no files written here).

:func:`standard_figures` returns ``[(file name, Figure)]``; the report writer saves them
as PNG and logs them to TensorBoard with ``add_figure``.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from .scoring import rmse_over_time, roc  # noqa: E402

__all__ = ["standard_figures"]


def standard_figures(result) -> list[tuple[str, plt.Figure]]:
    """State RMSE over time, ROC curves, and run 0's alarms and attack estimates."""
    traj, outs = result.traj, result.outputs
    dt = result.scenario.dt
    T = traj.flags.shape[1]
    t = [dt * (k + 1) for k in range(T)]
    figs = []

    fig, ax = plt.subplots(figsize=(8, 4.5))
    for name, out in outs.items():
        truth = result.traj_of(name).x
        ax.plot(t, rmse_over_time(out.means, truth).numpy(), label=name, lw=1)
    ax.set(xlabel="time [s]", ylabel="state RMSE over runs", yscale="log")
    ax.set_title("State RMSE over time")
    ax.legend(fontsize=7, ncol=2)
    figs.append(("rmse_over_time.png", fig))

    detecting = {n: o for n, o in outs.items() if o.detection is not None}
    if detecting and bool(traj.flags.any()) and not bool(traj.flags.all()):
        fig, ax = plt.subplots(figsize=(5.5, 5))
        for name, out in detecting.items():
            if result.metrics[name].get("auc") is None:
                continue
            fpr, tpr = roc(out.detection.scores, traj.flags)
            label = f"{name} (AUC {result.metrics[name]['auc']:.3f})"
            ax.plot(fpr.numpy(), tpr.numpy(), label=label, lw=1)
        ax.plot([0, 1], [0, 1], "k:", lw=0.8)
        ax.set(xlabel="false-alarm rate", ylabel="detection rate", title="ROC, every run and step")
        ax.legend(fontsize=7)
        figs.append(("roc.png", fig))

        fig, ax = plt.subplots(figsize=(8, 0.45 * (len(detecting) + 1) + 1))
        ax.eventplot([[t[k] for k in range(T) if traj.flags[0, k]]], lineoffsets=0, colors="k")
        for i, out in enumerate(detecting.values(), start=1):
            ax.eventplot([[t[k] for k in range(T) if out.detection.alarms[0, k]]], lineoffsets=i)
        ax.set_yticks(range(len(detecting) + 1), ["attacked", *detecting], fontsize=7)
        ax.set(xlabel="time [s]", title="Run 0: attacked steps and alarms")
        figs.append(("alarms_run0.png", fig))

    estimating = {n: o for n, o in outs.items() if o.attack is not None}
    if estimating and traj.attack.shape[-1] > 0:
        fig, ax = plt.subplots(figsize=(8, 4))
        ax.plot(t, traj.attack[0, :, 0].numpy(), "k", lw=1.5, label="injected")
        for name, out in estimating.items():
            ax.plot(t, out.attack[0, :, 0].numpy(), lw=0.9, label=name)
        ax.set(xlabel="time [s]", ylabel="attack, channel 1", title="Run 0: attack estimates")
        ax.legend(fontsize=7)
        figs.append(("attack_estimates_run0.png", fig))
    return figs
