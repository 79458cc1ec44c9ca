"""The figures every scenario's report gets (matplotlib, Agg backend; no files written here).

:func:`standard_figures` returns ``[(file name, Figure)]``; the report writer draws each
once to PNG (:func:`png_bytes`), saves it and logs the same image to TensorBoard.

Every estimator keeps one colour across the figures of a report
(:func:`estimator_colours`): estimators of one family (the first word of their name:
``modified_pf``, ``modified_pf_est``, … are ``modified``) share a hue in shades, and no
two estimators share a colour. The members of a family also differ in line style
(:func:`estimator_line_styles`: solid, dashed, dotted, dash-dot, dash-dot-dot, long dashes,
in the family's order), so that two curves which coincide, as two variants of one detector
often do, still show as two. A family's own figures (:mod:`difffilter.eval.families`) draw
each estimator in the same colour and style (:func:`estimator_looks`). Legends sit outside
the axes, beside the data (:func:`legend_beside`). The state RMSE is on a logarithmic axis
where its curves span a decade or more. The ROC (with the same curves below it as misses,
1 − the detection rate, on a log axis: a DET plot, where detectors near a detection rate of
1 are told apart)
uses a logarithmic false-alarm axis, where the operating points of a 1 % budget live, and
marks each detector's operating point at its calibrated threshold (or its own threshold
when the study is not calibrated). A calibrated study also shows where the false alarms
fall in time: each detector's alarm rate on attack-free steps by the steps since the run's
last attacked step (``false_alarms_after_attack.png``; an estimator whose alarms outlast
the attack stands out there, while ``fpr_at_far`` pools those steps with the rest).
"""

from __future__ import annotations

import colorsys
import io
import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from matplotlib import colors as mcolors  # noqa: E402

from difffilter.metrics import alarm_rate_since_attack  # noqa: E402

from .calibration import alarms_at  # noqa: E402
from .report import format_number  # noqa: E402
from .scoring import comparable_attack, rmse_over_time, roc  # noqa: E402

__all__ = [
    "standard_figures",
    "estimator_colours",
    "estimator_line_styles",
    "estimator_looks",
    "legend_beside",
    "png_bytes",
]

# one hue per family, in this order (matplotlib's tab10, then tab20's light half)
_HUES = [mcolors.to_rgb(c) for c in plt.get_cmap("tab10").colors] + [
    mcolors.to_rgb(c) for c in plt.get_cmap("tab20").colors[1::2]
]


def _family(name: str) -> str:
    return name.split("_")[0]


def estimator_colours(names) -> dict[str, str]:
    """``{name: hex colour}``: one hue per family (the first word of the name), shades of
    it for the family's members (lightness 0.3 … 0.7), all distinct."""
    families: dict[str, list[str]] = {}
    for name in names:
        families.setdefault(_family(name), []).append(name)
    colours: dict[str, str] = {}
    for i, members in enumerate(families.values()):
        h, lightness, s = colorsys.rgb_to_hls(*_HUES[i % len(_HUES)])
        shades = len(members)
        for j, name in enumerate(members):
            if shades > 1:  # spread the family over lightness 0.3 … 0.7
                lightness = 0.3 + 0.4 * j / (shades - 1)
            rgb = colorsys.hls_to_rgb(h + (i // len(_HUES)) * 0.05, lightness, s)
            colours[name] = mcolors.to_hex(rgb)
    seen: set[str] = set()
    for name, colour in colours.items():  # a clash (many families): nudge the lightness
        while colour in seen:
            h, lightness, s = colorsys.rgb_to_hls(*mcolors.to_rgb(colour))
            colour = mcolors.to_hex(colorsys.hls_to_rgb(h, (lightness + 0.07) % 0.9 + 0.05, s))
        colours[name] = colour
        seen.add(colour)
    return colours


#: The line styles of a family's members, in order (cycled beyond six; a fifth member had
#: wrapped round to solid, as the first: a figure review read the LFC family's fifth
#: variant as its reference).
LINE_STYLES = ("-", "--", ":", "-.", (0, (5, 1.5, 1, 1.5, 1, 1.5)), (0, (9, 2.5)))


def estimator_line_styles(names) -> dict[str, str]:
    """``{name: matplotlib line style}``: the ``j``-th member of a family (the first word of
    the name, as :func:`estimator_colours` groups them) gets ``LINE_STYLES[j % 6]``. Shades
    of one hue are hard to tell apart, and two variants of one estimator often draw the same
    curve (the later one hides the earlier): a dash shows the earlier beneath it."""
    seen: dict[str, int] = {}
    styles: dict[str, str] = {}
    for name in names:
        j = seen.get(_family(name), 0)
        seen[_family(name)] = j + 1
        styles[name] = LINE_STYLES[j % len(LINE_STYLES)]
    return styles


def estimator_looks(names) -> dict[str, dict]:
    """``{name: {"color": …, "ls": …}}`` of every estimator of a report (``names``: all of
    them, in the report's order): :func:`estimator_colours` and :func:`estimator_line_styles`
    as keyword arguments of ``plot``, for a family's own figures of some of them (they had
    taken matplotlib's colour cycle, so an estimator changed colour between the figures
    of one report: a figure review)."""
    colour, style = estimator_colours(names), estimator_line_styles(names)
    return {name: {"color": colour[name], "ls": style[name]} for name in colour}


def role_marks(names) -> dict[str, str]:
    """``{name: " (oracle)"}`` beside an estimator whose registered role is not analytic (an
    oracle, the reference, a learned one), as the leaderboard marks it; ``""`` for an analytic
    or unregistered one (a figure review: estimators given the true attack sat on the
    injected signal by construction, unmarked)."""
    from difffilter.models import estimators as registry

    from .acceptance import role_mark

    marks = {}
    for name in names:
        try:
            role = registry.get(name).role
        except ValueError:  # not registered
            role = None
        marks[name] = role_mark(role)
    return marks


def text_colour(shade: float) -> str:
    """The colour of a heat map cell's text on a red–yellow–green shade in [0, 1] (NaN: no
    colour): white on the darkest ends, where black could hardly be read (a figure review),
    black elsewhere."""
    return "white" if shade == shade and not 0.15 <= shade <= 0.85 else "black"


def legend_beside(ax, **kw) -> None:
    """The legend beside ``ax``, where it has labelled artists or ``handles`` are given
    (none: no legend, where matplotlib's "No artists with labels found" warning had reached
    the console)."""
    if kw.get("handles") or ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, frameon=False, **kw)


def mark_off_scale(ax, t, curves, ylim: tuple[float, float], unit: str = "", at: str = "k") -> None:
    """Set ``ylim`` on ``ax`` and write, at its top (bottom) edge, the largest (smallest)
    value of ``curves`` (1-D tensors over ``t``) beyond it, with its ``at = t``: a figure
    zoomed on a bound had cut off its peak without a word (the robot's input error rises to
    20 cm/s at the attack's first step, drawn as a wall at the edge)."""
    lo, hi = ylim
    ax.set_ylim(lo, hi)
    values = torch.stack([c.detach().double().reshape(-1) for c in curves])
    for edge, beyond, pick, other in ((hi, values > hi, torch.argmax, -math.inf),
                                      (lo, values < lo, torch.argmin, math.inf)):  # fmt: skip
        if not bool(beyond.any()):  # (a NaN is neither: nothing to say of it)
            continue
        masked = torch.where(beyond, values, other)
        row, col = divmod(int(pick(masked)), values.shape[1])
        extreme = float(masked[row, col])
        ax.annotate(
            f"{'↑' if edge == hi else '↓'} off scale: {extreme:.3g}{unit} at {at} = {t[col]:g}",
            xy=(t[col], edge),
            xytext=(4, -3 if edge == hi else 3),
            textcoords="offset points",
            fontsize=7,
            va="top" if edge == hi else "bottom",
            ha="left",
            bbox={"fc": "white", "ec": "none", "alpha": 0.8, "pad": 1},  # over the grid lines
        )


def _alarm_spans(alarms: torch.Tensor, t: list[float], dt: float) -> list[tuple[float, float]]:
    """Consecutive alarmed steps of one run as ``(start, width)`` bars in seconds."""
    spans, start = [], None
    for k, on in enumerate(alarms.tolist()):
        if on and start is None:
            start = k
        if start is not None and (not on or k == len(t) - 1):
            end = k if on else k - 1
            spans.append((t[start] - dt / 2, dt * (end - start + 1)))
            start = None
    return spans


def shown_run(flags: torch.Tensor) -> int:
    """The run the one-run figures show: the first with an attacked step (0 if none). A
    scenario attacking a share of its runs may leave run 0 clean, and a user trial's
    figures then showed an injected signal of zeros and no attacked step."""
    attacked = flags.reshape(flags.shape[0], -1).any(-1).nonzero()
    return int(attacked[0]) if attacked.numel() else 0


def png_bytes(fig: plt.Figure, dpi: int = 110) -> bytes:
    """``fig`` as PNG (cropped to its artists): what the report saves and TensorBoard shows."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, bbox_inches="tight")
    return buffer.getvalue()


def standard_figures(result) -> list[tuple[str, plt.Figure]]:
    """State RMSE over time, ROC curves, and one run's alarms and attack estimates (the
    first attacked run, :func:`shown_run`; the files keep their names ``*_run0.png``)."""
    traj, outs = result.traj, result.outputs
    dt = result.scenario.dt
    T = traj.flags.shape[1]
    t = [dt * (k + 1) for k in range(T)]
    colour, style = estimator_colours(outs), estimator_line_styles(outs)
    mark = role_marks(outs)
    figs = []

    fig, ax = plt.subplots(figsize=(8, 4.5))
    curves = {name: rmse_over_time(out.means, result.traj_of(name).x) for name, out in outs.items()}
    for name, curve in curves.items():
        ax.plot(t, curve.numpy(), label=f"{name}{mark[name]}", lw=1, color=colour[name],
                ls=style[name])  # fmt: skip
    state_unit = result.scenario.state_unit
    log = spans_a_decade(curves.values())
    ax.set(xlabel="time [s]", yscale="log" if log else "linear",
           ylabel=f"state RMSE over runs [{state_unit}]{' (log)' if log else ''}")  # fmt: skip
    ax.set_title("State RMSE over time")
    legend_beside(ax)
    figs.append(("rmse_over_time.png", fig))

    detecting = {n: o for n, o in outs.items() if o.detection is not None}
    if detecting and bool(traj.flags.any()) and not bool(traj.flags.all()):
        figs.append(("roc.png", _roc_figure(result, detecting, colour, style)))
        figs.append(("alarms_run0.png", _alarm_figure(result, detecting, colour, t, dt)))
    after = [n for n in detecting if result.metrics[n].get("fpr_at_far_after_attack") is not None]
    if after:
        figs.append(
            ("false_alarms_after_attack.png", _after_attack_figure(result, after, colour, style))
        )

    estimating = {n: o for n, o in outs.items() if o.attack is not None}
    if estimating and traj.attack.shape[-1] > 0:
        figs.append(("attack_estimates_run0.png",
                     _attack_figure(result, estimating, t, colour, style, mark)))  # fmt: skip
    return figs


#: At most this many attacked channels get a panel of their own in the attack figure.
MAX_ATTACK_PANELS = 4


def _attack_figure(result, estimating, t, colour, style, mark) -> plt.Figure:
    """One run's injected attack and each estimate, a panel per attacked channel (the most
    attacked first, at most :data:`MAX_ATTACK_PANELS`), each in its own unit where the
    scenario gives one per entry (:func:`_entry_units`). One panel of the largest channel
    had compared cm/s with rad/s and left the robot's heading attack and the LFC's second
    attacked area out (a figure review)."""
    traj = result.traj
    r = shown_run(traj.flags)
    channels = _attacked_channels(traj.attack, r)[:MAX_ATTACK_PANELS]
    names = getattr(result.scenario, "attack_entry_names", None)
    units = _entry_units(result.scenario, traj.attack.shape[-1])
    fig, axes = plt.subplots(len(channels), 1, figsize=(8, 1.2 + 2.8 * len(channels)),
                             sharex=True, squeeze=False)  # fmt: skip
    for ax, c in zip(axes[:, 0], channels):
        injected = traj.attack[r, :, c]
        # as steps: an attack that switches on and off from one step to the next drew
        # triangles between the steps, and its attacked steps could not be read off
        ax.plot(t, injected.numpy(), "k", lw=1.5, label="injected", drawstyle="steps-mid")
        for name, out in estimating.items():
            own = result.traj_of(name)
            if own.attack.shape[-1] != traj.attack.shape[-1] or not comparable_attack(out, own):
                continue
            if not torch.equal(own.attack[r, :, c], injected):  # its own closed loop's attack
                # a wide pale band in its colour: the estimate's own style draws over it
                ax.plot(t, own.attack[r, :, c].numpy(), lw=4, alpha=0.3, color=colour[name],
                        solid_capstyle="butt", label=f"injected in {name}'s loop",
                        drawstyle="steps-mid")  # fmt: skip
            ax.plot(t, out.attack[r, :, c].numpy(), lw=0.9, label=f"{name}{mark[name]}",
                    color=colour[name], ls=style[name], drawstyle="steps-mid")  # fmt: skip
        entry = f"channel {c + 1}" if not names else f"channel {c + 1}, {names[c]}"
        ax.set_ylabel(f"attack, {entry} [{units[c]}]", fontsize=8)
    legend_beside(axes[0, 0])  # (the same lines in every panel)
    axes[0, 0].set_title(f"Run {r}: attack estimates on its attacked channels (the most "
                         "attacked first)")  # fmt: skip
    axes[-1, 0].set_xlabel("time [s]")
    return fig


def _attacked_channels(attack: torch.Tensor, run: int) -> list[int]:
    """The channels of ``run`` with an injected attack, the largest first (channel 0 where
    none is attacked)."""
    size = attack[run].abs().amax(dim=0)
    order = torch.argsort(size, descending=True, stable=True)
    return order[size[order] > 0].tolist() or [0]


def _entry_units(scenario, width: int) -> list[str]:
    """Each attack entry's unit: the scenario's ``attack_unit`` where it is one, or its
    comma-separated units where there is one per entry (the robot's ``"cm/s, rad/s"``)."""
    unit = str(scenario.attack_unit)
    parts = [p.strip() for p in unit.split(",")]
    return parts if len(parts) == width and width > 1 else [unit] * width


def _roc_figure(result, detecting, colour, style=None) -> plt.Figure:
    """ROC curves on a logarithmic false-alarm axis, each operating point marked; each
    estimator's against the flags of the trajectories it ran on (its own closed loop's,
    as its AUC and operating point are scored).

    Drawn as steps: at each false-alarm rate the best detection rate of a threshold that
    alarms on no more (``tpr_at_1pct_fpr`` at 1 %). Straight segments between the points,
    on a log axis, crossed the 1 % line at 0.298 for a detector whose scores tie from
    (0, 0) to (0.372, 0.968), whose ``tpr_at_1pct_fpr`` is 0 (a trapezoid, as the AUC
    sums, would read 0.026 there, and no threshold gives it)."""
    style, mark = style or estimator_line_styles(detecting), role_marks(detecting)
    flags = {name: result.traj_of(name).flags for name in detecting}
    # half the smallest non-zero false-alarm rate and miss any curve can show: the lines
    # where 0 is drawn (the smallest rate itself, one false alarm, had been where a rate
    # of 0 was drawn, unlabelled: a figure trial)
    floor = 0.5 / max(1, max(int((~f).sum()) for f in flags.values()))
    no_miss = 0.5 / max(1, max(int(f.sum()) for f in flags.values()))
    fig, (ax, det) = plt.subplots(2, 1, figsize=(7.5, 8), sharex=True,
                                  gridspec_kw={"height_ratios": (3, 2)})  # fmt: skip
    for name, out in detecting.items():
        metrics = result.metrics[name]
        if metrics.get("auc") is None:
            continue
        fpr, tpr = roc(out.detection.scores, flags[name])
        auc = format_number(metrics["auc"], 3)
        look = {"color": colour[name], "ls": style[name], "drawstyle": "steps-post", "lw": 1}
        ax.plot(fpr.clamp_min(floor).numpy(), tpr.numpy(), **look,
                label=f"{name}{mark[name]} (AUC {auc})")  # fmt: skip
        det.plot(fpr.clamp_min(floor).numpy(), (1.0 - tpr).clamp_min(no_miss).numpy(), **look)
        point = (metrics.get("fpr_at_far"), metrics.get("tpr_at_far"))
        if point[1] is None:  # not calibrated: its own threshold
            point = (metrics.get("fpr"), metrics.get("tpr"))
        if point[0] is not None and point[1] is not None:
            ax.plot(max(point[0], floor), point[1], "o", ms=4, color=colour[name])
            det.plot(max(point[0], floor), max(1.0 - point[1], no_miss), "o", ms=4,
                     color=colour[name])  # fmt: skip
    far = getattr(result.calibration, "far", None)
    if far is not None:
        ax.axvline(far, color="0.5", ls="--", lw=0.8, label=f"target false-alarm rate {far:g}")
        det.axvline(far, color="0.5", ls="--", lw=0.8)
    for panel in (ax, det):
        panel.axvline(floor, color="0.7", ls="-.", lw=0.8,
                      label="no false alarm at all (0, drawn on this line)")  # fmt: skip
    det.axhline(no_miss, color="0.7", ls=":", lw=0.8,
                label="no miss at all (0, drawn on this line)")  # fmt: skip
    aucs = [result.metrics[n].get("auc") for n in detecting]
    # every curve on the top edge: said, or the figure read as one curve (a figure review)
    top = all(a is not None and a >= 0.999 for a in aucs) and any(a is not None for a in aucs)
    title = ("ROC, every run and step: the best detection rate at each false-alarm rate\n"
             "(dots: operating points, at the calibrated thresholds where calibrated)")  # fmt: skip
    if top:
        title += "\nevery AUC ≥ 0.999: the curves lie on the top edge, one over another"
    ax.set(xscale="log", xlim=(0.8 * floor, 1.0), ylim=(0.0, 1.02), ylabel="detection rate",
           title=title)  # fmt: skip
    # the same curves as misses on a log axis (a DET plot): near a detection rate of 1,
    # where most detectors are, the ROC squeezes them into its top pixels (a figure review)
    det.set(yscale="log", ylim=(no_miss * 0.8, 1.2), xlabel="false-alarm rate (log)",
            ylabel="miss rate, 1 − detection rate (log)")  # fmt: skip
    legend_beside(ax)
    legend_beside(det)
    return fig


#: The bins of the steps since the last attack in ``false_alarms_after_attack.png``.
AFTER_ATTACK_EDGES = (1, 2, 3, 5, 10, 20, 50, 100, 200)
#: A bin of fewer attack-free steps is drawn with open markers (one alarm in 31 steps is
#: 3 %: a figure review read such a bin as the figure's largest feature).
FEW_STEPS = 100


def _after_attack_figure(result, names, colour, style=None) -> plt.Figure:
    """Each calibrated detector's alarm rate on the attack-free steps, by the steps since
    the run's last attacked step (:func:`difffilter.metrics.alarm_rate_since_attack`, in
    each estimator's own trajectory), then on the steps before a run's first attack; each
    bin labelled with its number of steps (the most of any estimator: closed loops differ),
    bins without steps left out, the target rate dashed. A rate of 0 sits on the axis'
    floor (half of one alarm in the largest bin shown), a dotted line the legend names."""
    style, mark = style or estimator_line_styles(names), role_marks(names)
    edges = AFTER_ATTACK_EDGES
    labels = [f"{a}" if b == a + 1 else f"{a}–{b - 1}" for a, b in zip(edges, edges[1:])]
    labels += [f"≥ {edges[-1]}", "before any attack"]
    curves = {}
    for name in names:
        flags = result.traj_of(name).flags
        alarms = alarms_at(result.outputs[name].detection.scores,
                           result.metrics[name]["threshold_at_far"])  # fmt: skip
        curves[name] = alarm_rate_since_attack(alarms, flags, edges, before=True)
    steps = torch.stack([c for _, c in curves.values()]).amax(0)  # the same in open loop
    shown = steps > 0
    floor = 0.5 / float(steps[shown].max())
    fig, ax = plt.subplots(figsize=(8, 4.5))
    x = torch.arange(int(shown.sum()))
    # the bins since an attack as one line, "before any attack" as a point of its own: a
    # line into it drew a start-up transient as a rise after the attacks (a figure review)
    since = shown.clone()
    since[-1] = False
    n_since = int(since.sum())
    few = (steps[shown] < FEW_STEPS).numpy()
    for name, (rates, _) in curves.items():
        y = rates[shown].clamp_min(floor).numpy()
        ax.plot(x[:n_since], y[:n_since], ls=style[name], lw=1, color=colour[name],
                label=f"{name}{mark[name]} "
                      f"({_percent(result.metrics[name]['fpr_at_far_after_attack'])} "
                      "in steps 1–10)")  # fmt: skip
        # a bin of few steps as an open marker: one alarm there is a large rate
        for hollow in (False, True):
            at = (few == hollow).nonzero()[0]
            ax.plot(x[at], y[at], ls="none", marker="o", ms=3.5, color=colour[name],
                    mfc="none" if hollow else colour[name])  # fmt: skip
    if bool(shown[-1]) and n_since:  # the points before and after any attack apart
        ax.axvline(n_since - 0.5, color="0.6", lw=0.6)
    far = getattr(result.calibration, "far", None)
    if far is not None:
        ax.axhline(far, color="0.5", ls="--", lw=0.8, label=f"target false-alarm rate {far:g}")
    # a log axis has no 0: said on the figure, or a detector without false alarms there
    # read as one with a few
    ax.axhline(floor, color="0.7", ls=":", lw=0.8, label="no alarm at all (0, drawn on this line)")
    ticks = [f"{label}\nn = {n:,}" for label, n in zip(labels, steps.tolist()) if n > 0]
    ax.set_xticks(range(len(ticks)), ticks, fontsize=7)
    ax.set(yscale="log", ylim=(floor * 0.8, 1.2),
           xlabel=f"steps since the run's last attacked step (n: attack-free steps in the bin; "
                  f"open markers: fewer than {FEW_STEPS})",
           ylabel="alarm rate on attack-free steps (log)",
           title="False alarms after an attack (at the calibrated thresholds)")  # fmt: skip
    legend_beside(ax)
    return fig


def _alarm_figure(result, detecting, colour, t, dt) -> plt.Figure:
    """One run's attacked steps and each detector's alarms as bars of consecutive steps
    (the first attacked run, :func:`shown_run`).

    The top row is the study's attacked steps. A detector that ran on trajectories of its
    own (its closed loop, :meth:`~difffilter.eval.suite.SuiteResult.traj_of`) whose run
    was attacked at other steps gets its own attacked steps as a grey band behind its
    alarms: each row reads against the attack it faced. The alarms are at the calibrated
    threshold where the study was calibrated (as the ROC's dots and the after-attack
    figure), else at each detector's own; the title says which (a reviewer read a
    detector's own alarms beside its calibrated rates, 0.378 against 0.6)."""
    r = shown_run(result.traj.flags)
    calibrated = {name: result.metrics[name].get("threshold_at_far") for name in detecting}
    study = result.traj.flags[r]
    rows = len(detecting) + 1
    fig, ax = plt.subplots(figsize=(8, 0.32 * rows + 1.2))
    ax.broken_barh(_alarm_spans(study, t, dt), (rows - 1 - 0.35, 0.7), color="k")
    for i, (name, out) in enumerate(detecting.items(), start=1):
        own = result.traj_of(name).flags[r]
        if not torch.equal(own, study):
            ax.broken_barh(_alarm_spans(own, t, dt), (rows - 1 - i - 0.5, 1.0), color="0.85")
        tau = calibrated[name]
        if tau is not None and out.detection.scores is not None:
            alarms = alarms_at(out.detection.scores[r], tau)
        else:
            alarms = out.detection.alarms[r]
        spans = _alarm_spans(alarms, t, dt)
        ax.broken_barh(spans, (rows - 1 - i - 0.35, 0.7), color=colour[name])
    ax.set_yticks(range(rows - 1, -1, -1), ["attacked", *detecting], fontsize=7)
    every = all(v is not None for v in calibrated.values())
    some = any(v is not None for v in calibrated.values())
    which = ("at the calibrated thresholds" if every else
             "at the calibrated thresholds where calibrated, else each detector's own" if some
             else "at each detector's own threshold")  # fmt: skip
    ax.set(xlabel="time [s]", xlim=(0, t[-1] + dt), ylim=(-0.6, rows - 0.4),
           title=f"Run {r}: attacked steps and alarms ({which})")  # fmt: skip
    ax.grid(axis="x", lw=0.3, color="0.85")
    ax.set_axisbelow(True)  # (over the bars it read as one-step gaps in the attack)
    return fig


def _percent(rate: float) -> str:
    """``rate`` in percent to three significant figures (``0.0206 %``: ``.1f`` printed a
    rate of 2.06e-4 as ``0.0 %``, as if there had been no alarm)."""
    return "0 %" if rate == 0 else f"{100 * rate:.3g} %"


def spans_a_decade(curves) -> bool:
    """Whether the finite positive values of ``curves`` (tensors) span a factor of 10 or more:
    where a logarithmic axis shows them better than a linear one (five filters within a
    factor of 2 of each other got ticks of 2.4×10⁻², 2.6×10⁻², … on a log axis)."""
    curves = list(curves)
    if not curves:
        return False
    values = torch.cat([c.detach().reshape(-1).double() for c in curves])
    values = values[torch.isfinite(values) & (values > 0)]
    return bool(values.numel()) and float(values.max() / values.min()) >= 10.0
