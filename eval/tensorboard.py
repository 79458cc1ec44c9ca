"""TensorBoard events of an evaluation: figures, per-step curves and an hparams table.

``<out>/<scenario>/tb`` gets, per estimator, curves over the step ``k = 1 … T`` (scalars at
step ``k``):

* ``state_rmse_per_step/<name>``: ``sqrt(mean over runs and state components of
  (x̂_k − x_k)²)``, whose root mean square over the steps is ``state_rmse``;
* ``attack_rmse_per_step/<name>``, where it estimates the attacked channel: the same of
  ``â_k − a_k`` at every step, attack-free ones included (``a_k = 0`` there), so not the
  ``attack_rmse`` of ``metrics.json``, which counts only the attacked steps;
* ``alarm_rate_per_step/<name>``, where it detects: the share of runs that alarm at ``k``
  at the estimator's own threshold, and ``alarm_rate_at_far_per_step/<name>`` at its
  calibrated ``threshold_at_far`` (the one every rate of a calibrated report is read at);

every report figure (the PNG the report saved); and one HPARAMS row per estimator
(scenario, estimator, runs, seed → the headline metrics, the calibrated ones and the
acceptance checks' ``holds_share``). The rows are sessions without an experiment summary
of their own: TensorBoard then builds the HPARAMS table from every session under its
``--logdir``, all columns of all estimators and scenarios (and of the leaderboard's rows,
:mod:`difffilter.eval.leaderboard`); with one summary per row it showed one row's columns
for all (a trial's detector rows hid the network's ``holds_share`` columns).
"""

from __future__ import annotations

import struct
from pathlib import Path

from .calibration import alarms_at
from .scoring import HEADLINE, comparable_attack, rmse_over_time

__all__ = ["add_session", "clear_events", "log_suite"]

#: The calibrated metrics of an HPARAMS row (where the study was calibrated, ``--far``).
AT_FAR = ("threshold_at_far", "tpr_at_far", "fpr_at_far", "detection_delay_at_far_s", "impact")


def clear_events(logdir: Path) -> None:
    """Remove the TensorBoard event files an earlier evaluation wrote under ``logdir`` (an
    evaluation's own folder): a second run into the same ``--out`` added its events to the
    first's, and TensorBoard drew two points a step and two values per HPARAMS row beside
    a ``metrics.json`` that held only the second. The folders this leaves empty go too
    (an estimator or scenario of the earlier run alone left an empty run in TensorBoard's
    list); other files, and the folders that hold them, are left."""
    logdir = Path(logdir)
    emptied = set()
    for old in logdir.rglob("events.out.tfevents.*"):
        old.unlink()
        emptied.add(old.parent)
    # the deepest first, so that a parent left empty by its children goes as well
    for folder in sorted(emptied, key=lambda p: len(p.parts), reverse=True):
        while folder != logdir and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
            folder = folder.parent


def log_suite(logdir: Path, result, doc: dict, images) -> None:
    """Write the events of one suite run under ``logdir`` (replacing an earlier run's,
    :func:`clear_events`); ``images`` ``[(file name, PNG bytes)]`` are the report's figures
    as saved."""
    from torch.utils.tensorboard import SummaryWriter

    clear_events(logdir)
    with SummaryWriter(str(logdir)) as w:
        curves: dict[str, list[float]] = {}
        for name, out in result.outputs.items():
            traj = result.traj_of(name)
            curves[f"state_rmse_per_step/{name}"] = rmse_over_time(out.means, traj.x).tolist()
            if out.detection is not None:
                rate = out.detection.alarms.double().mean(0)
                curves[f"alarm_rate_per_step/{name}"] = rate.tolist()
                # the study's own threshold, as the figures take it: the report's JSON has an
                # infinite one (calibrated on purpose where no finite one meets the rate) as
                # null, and the curve of such a detector had been left out (a red-team trial)
                at_far = result.metrics.get(name, {}).get("threshold_at_far")
                if at_far is not None and at_far == at_far:  # (a NaN: none)
                    rate = alarms_at(out.detection.scores, at_far).double().mean(0)
                    curves[f"alarm_rate_at_far_per_step/{name}"] = rate.tolist()
            # the attack estimate's error, where it estimates this channel
            if traj.attack.shape[-1] > 0 and comparable_attack(out, traj):
                curves[f"attack_rmse_per_step/{name}"] = rmse_over_time(
                    out.attack, traj.attack
                ).tolist()
        _write_curves(w, curves)
        for fname, png in images:
            _write_image(w, Path(fname).stem, png)
        sure = (doc.get("acceptance_intervals") or {}).get("estimators", {})
        for name, entry in doc["estimators"].items():
            metrics = {f"hparam/{m}": entry[m] for m in (*HEADLINE, *AT_FAR)
                       if entry.get(m) is not None}  # fmt: skip
            # how sure each acceptance check is (difffilter.eval.intervals), where judged
            metrics.update({f"hparam/holds_share/{m}": c["holds_share"]
                            for m, c in sure.get(name, {}).items() if c["holds_share"] is not None})  # fmt: skip
            hparams = {
                "scenario": doc["scenario"],
                "estimator": name,
                "runs": doc["runs"],
                "seed": doc["seed"],
            }
            add_session(w, f"hparams/{name}", hparams, metrics)


def add_session(writer, run_name: str, hparams: dict, metrics: dict) -> None:
    """One HPARAMS row under ``<writer's logdir>/<run_name>``: the session's hyperparameters
    and its ``metrics`` as scalars, as ``SummaryWriter.add_hparams`` writes them but without
    its experiment summary, so that TensorBoard takes the table's columns from every session
    (module docstring)."""
    from torch.utils.tensorboard import SummaryWriter
    from torch.utils.tensorboard.summary import hparams as hparams_summaries

    _, start, end = hparams_summaries(hparams, metrics)
    with SummaryWriter(str(Path(writer.get_logdir()) / run_name)) as session:
        session.file_writer.add_summary(start)
        session.file_writer.add_summary(end)
        for tag, value in metrics.items():
            # in double precision: a simple value is float32, and a particle filter's
            # calibrated threshold of 3.6e-234 was shown as 0, a detector alarming at 87 %
            # of the attack-free steps for the study's 1 % (a red-team trial)
            session.add_scalar(tag, value, new_style=True, double_precision=True)


def _write_image(writer, tag: str, png: bytes) -> None:
    """One image event holding ``png`` as encoded (what ``add_figure`` would write after
    drawing the figure again and encoding its pixels again)."""
    from tensorboard.compat.proto.summary_pb2 import Summary

    width, height = struct.unpack(">II", png[16:24])  # the PNG header's IHDR chunk
    image = Summary.Image(height=height, width=width, colorspace=4, encoded_image_string=png)
    writer._get_file_writer().add_summary(Summary(value=[Summary.Value(tag=tag, image=image)]))


def _write_curves(writer, curves: dict[str, list[float]]) -> None:
    """Every curve ``{tag: [value at k = 1, 2, …]}`` as scalars at steps ``k``: one event per
    step holding every tag's value there (TensorBoard reads each tag as with ``add_scalar``;
    one event per value made the evaluation's logging 10× slower: ~100 µs per event)."""
    from tensorboard.compat.proto.summary_pb2 import Summary

    steps = max((len(c) for c in curves.values()), default=0)
    file_writer = writer._get_file_writer()
    for k in range(steps):
        values = [Summary.Value(tag=tag, simple_value=c[k]) for tag, c in curves.items()
                  if k < len(c)]  # fmt: skip
        file_writer.add_summary(Summary(value=values), k + 1)
