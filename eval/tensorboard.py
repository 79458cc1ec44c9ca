"""TensorBoard events of an evaluation: figures, per-step curves and an hparams table.

``<out>/<scenario>/tb`` gets, per estimator, the state RMSE at every step (a curve over
``k``, not a single point), when it estimates the attacked channel the RMSE of its attack
estimate at every step, and, when it detects, its alarm rate per step; every report
figure with ``add_figure``; and one hparams row per estimator (scenario, estimator, runs,
seed → the headline metrics), so ``tensorboard --logdir <out>`` compares estimators and
scenarios side by side in its HPARAMS tab.
"""

from __future__ import annotations

from pathlib import Path

from .scoring import HEADLINE, comparable_attack, rmse_over_time

__all__ = ["log_suite"]


def log_suite(logdir: Path, result, doc: dict, figures) -> None:
    """Write the events of one suite run under ``logdir``."""
    from torch.utils.tensorboard import SummaryWriter

    with SummaryWriter(str(logdir)) as w:
        for name, out in result.outputs.items():
            traj = result.traj_of(name)
            curve = rmse_over_time(out.means, traj.x)
            alarm_rate = None
            if out.detection is not None:
                alarm_rate = out.detection.alarms.double().mean(0)
            attack_curve = None  # the attack estimate's error, where it estimates this channel
            if traj.attack.shape[-1] > 0 and comparable_attack(out, traj):
                attack_curve = rmse_over_time(out.attack, traj.attack)
            for k in range(curve.shape[0]):
                w.add_scalar(f"state_rmse_per_step/{name}", float(curve[k]), k + 1)
                if alarm_rate is not None:
                    w.add_scalar(f"alarm_rate_per_step/{name}", float(alarm_rate[k]), k + 1)
                if attack_curve is not None:
                    w.add_scalar(f"attack_rmse_per_step/{name}", float(attack_curve[k]), k + 1)
        for fname, fig in figures:
            w.add_figure(Path(fname).stem, fig, close=False)
        for name, entry in doc["estimators"].items():
            metrics = {f"hparam/{m}": entry[m] for m in HEADLINE if entry.get(m) is not None}
            hparams = {
                "scenario": doc["scenario"],
                "estimator": name,
                "runs": doc["runs"],
                "seed": doc["seed"],
            }
            w.add_hparams(hparams, metrics, run_name=f"hparams/{name}")
