"""The figures a training run logs to TensorBoard (matplotlib, Agg backend)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

__all__ = ["attack_figure"]


def attack_figure(attack: torch.Tensor, estimate: torch.Tensor, dt: float, channels=None,
                  *, actuator: bool = False):  # fmt: skip
    """One run's injected attack and its estimate on the most attacked channels.

    ``attack``, ``estimate``: ``[T, d]``; ``channels``: which to draw (default the two with
    the most attack energy, so the curve shows where the attack is); ``actuator``: an
    attack on the inputs (``d = du``), labelled in input units (an actuator attack had
    been labelled in measurement units, its inputs read as sensor channels). Returns the
    figure (TensorBoard's ``add_figure`` closes it).
    """
    if channels is None:
        energy = attack.abs().sum(0)
        channels = [int(c) for c in torch.argsort(energy, descending=True)[:2]]
    t = dt * torch.arange(1, attack.shape[0] + 1)
    fig, ax = plt.subplots(figsize=(7, 3))
    kind, units = ("input", "input units") if actuator else ("ch", "measurement units")
    for c in channels:
        (line,) = ax.plot(t, attack[:, c].float().cpu(), label=f"attack {kind}{c + 1}")
        ax.plot(t, estimate[:, c].float().cpu(), "--", color=line.get_color(),
                label=f"estimate {kind}{c + 1}")  # fmt: skip
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"attack [{units}]")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()
    return fig
