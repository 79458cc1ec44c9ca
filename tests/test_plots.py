"""The report's generic figures: one colour per estimator across every figure (a family
shares a hue, no two estimators share a colour), legends beside the data, a logarithmic
ROC with the operating points, and the attack plot on the attacked channel."""

from __future__ import annotations

import colorsys

import matplotlib.pyplot as plt
import pytest
from matplotlib import colors as mcolors

from difffilter.eval.plots import (
    LINE_STYLES,
    estimator_colours,
    estimator_line_styles,
    estimator_looks,
    standard_figures,
)
from difffilter.eval.suite import run_suite
from difffilter.models import registry


def test_every_estimator_gets_its_own_colour_and_a_family_shares_a_hue():
    names = ["modified_pf", "modified_pf_est", "modified_pf_unknown_pl", "normal_pf",
             "normal_pf_literal", "chi_square_ekf", "cusum_ekf", "pf_nn_grad",
             *(f"family{i}_x" for i in range(30))]  # fmt: skip
    colours = estimator_colours(names)
    assert len(set(colours.values())) == len(names)

    def hue(name):
        return colorsys.rgb_to_hls(*mcolors.to_rgb(colours[name]))[0]

    assert hue("modified_pf") == pytest.approx(hue("modified_pf_unknown_pl"), abs=0.02)
    assert hue("modified_pf") != pytest.approx(hue("normal_pf"), abs=0.02)
    assert estimator_colours(names[:5]) == {n: colours[n] for n in names[:5]}  # stable


def test_a_familys_members_differ_in_line_style_in_order():
    names = ["traditional_ad", "kf_nn_grad", "traditional_ad_robust", "kf_nn_grad_ekf",
             "traditional_ad_diagonal", "chi_square_kf", "kf_a", "kf_b", "kf_c"]  # fmt: skip
    styles = estimator_line_styles(names)
    assert [styles[n] for n in ("traditional_ad", "traditional_ad_robust",
                                "traditional_ad_diagonal")] == ["-", "--", ":"]  # fmt: skip
    # a fifth member has a style of its own (it wrapped round to the first's solid line)
    assert [styles[n] for n in ("kf_nn_grad", "kf_nn_grad_ekf", "kf_a", "kf_b", "kf_c")] == [
        "-", "--", ":", "-.", LINE_STYLES[4]]  # fmt: skip
    assert len(set(map(str, LINE_STYLES))) == 6
    assert styles["chi_square_kf"] == "-"  # a family of one is solid


def test_a_familys_own_figure_draws_each_estimator_as_the_reports_figures_do(monkeypatch, tmp_path):
    """The four-tank Fig. 9 (and the LFC, robot and tracking figures) took matplotlib's own
    colour cycle: modified_pf was green there and brown elsewhere (a figure review)."""
    from test_family_tables_mutants import _four_tank_doc  # (tests/ is on sys.path)

    from difffilter.eval.families.four_tank import SWEPT, _fig9_section

    names = ["modified_pf", "normal_pf", "normal_pf_literal", "chi_square_ekf", "cusum_ekf"]
    looks = estimator_looks(names)
    assert looks["normal_pf_literal"] == {
        "color": estimator_colours(names)["normal_pf_literal"],
        "ls": estimator_line_styles(names)["normal_pf_literal"],
    }
    closed, close = [], plt.close
    monkeypatch.setattr(plt, "close", closed.append)
    _fig9_section(_four_tank_doc(), tmp_path, names)
    (ax,) = closed[0].axes
    drawn = {line.get_label(): line for line in ax.get_lines()}
    for name in SWEPT:
        assert mcolors.to_hex(drawn[name].get_color()) == looks[name]["color"], name
        assert drawn[name].get_linestyle() == looks[name]["ls"], name
    assert "‖γ‖ = 0.28 cm (small attacks, below)" in drawn  # the dotted line is named
    close(closed[0])


def test_a_log_axis_only_for_curves_that_span_a_decade_and_rates_in_three_figures():
    import torch

    from difffilter.eval.plots import _percent, spans_a_decade

    assert not spans_a_decade([torch.tensor([0.024, 0.026]), torch.tensor([0.03, float("nan")])])
    assert spans_a_decade([torch.tensor([0.01, 0.5]), torch.tensor([0.0, 0.02])])
    assert not spans_a_decade([])
    # 2.06e-4 was printed "0.0 %", as if no alarm
    assert (_percent(2.06e-4), _percent(0.0), _percent(0.125)) == ("0.0206 %", "0 %", "12.5 %")


@pytest.fixture(scope="module")
def figures():
    suite = run_suite(registry.get("four_tank_bias"), runs=3, progress=False)
    figs = dict(standard_figures(suite))
    yield suite, figs
    for fig in figs.values():
        plt.close(fig)


def _name(label: str) -> str:
    """The estimator of a legend label (``name (oracle) (AUC …)``: its first word)."""
    return label.split(" (")[0]


def _line_colours(fig) -> dict[str, str]:
    ax = fig.axes[0]
    return {_name(line.get_label()): mcolors.to_hex(line.get_color()) for line in ax.get_lines()
            if not line.get_label().startswith("_")}  # fmt: skip


def test_a_twelve_estimator_report_keeps_one_distinct_colour_per_estimator(figures):
    suite, figs = figures
    assert len(suite.outputs) >= 12
    rmse = _line_colours(figs["rmse_over_time.png"])
    assert set(rmse) == set(suite.outputs) and len(set(rmse.values())) == len(rmse)
    roc = {name: c for name, c in _line_colours(figs["roc.png"]).items() if name in rmse}
    attack = _line_colours(figs["attack_estimates_run0.png"])
    for name, colour in {**roc, **{n: c for n, c in attack.items() if n != "injected"}}.items():
        assert colour == rmse[name], name  # the same colour in every figure
    # and the same line style: two members of a family whose curves coincide both show
    styles = estimator_line_styles(suite.outputs)
    assert len(set(styles.values())) > 1
    for fig in (figs["rmse_over_time.png"], figs["roc.png"]):
        for line in fig.axes[0].get_lines():
            name = _name(line.get_label())
            if name in styles:
                assert line.get_linestyle() == styles[name], name
    for fig in figs.values():
        legend = fig.axes[0].get_legend()
        if legend is not None:  # beside the axes, not over the data
            assert legend.get_bbox_to_anchor().x0 >= fig.axes[0].get_window_extent().x1


def test_the_attack_is_drawn_as_steps_and_the_alarm_grid_lies_under_the_bars(figures):
    """An attack switching on and off drew triangles between the steps; the alarm raster's
    grid over its bars read as one-step gaps in the attack (a figure review)."""
    _, figs = figures
    lines = figs["attack_estimates_run0.png"].axes[0].get_lines()
    assert lines and all(line.get_drawstyle() == "steps-mid" for line in lines)
    assert figs["alarms_run0.png"].axes[0].get_axisbelow() is True


def test_legends_mark_the_oracles_the_reference_and_the_learned_as_the_leaderboard_does(figures):
    """modified_pf, given the true attack, sat on the injected signal by construction with
    nothing in the legend to say so (a figure review)."""
    _, figs = figures
    rmse = [line.get_label() for line in figs["rmse_over_time.png"].axes[0].get_lines()]
    assert "modified_pf (oracle)" in rmse and "normal_pf_attack_free (reference)" in rmse
    assert "pf_nn_grad (learned)" in rmse and "chi_square_ekf" in rmse  # analytic: unmarked
    roc = [line.get_label() for line in figs["roc.png"].axes[0].get_lines()]
    assert any(label.startswith("modified_pf (oracle) (AUC ") for label in roc)


def test_the_roc_has_a_log_false_alarm_axis_and_marks_operating_points(figures):
    _, figs = figures
    ax = figs["roc.png"].axes[0]
    assert ax.get_xscale() == "log"
    markers = [line for line in ax.get_lines() if line.get_marker() == "o"]
    assert markers  # one dot per detector with an operating point


def test_the_roc_is_drawn_as_steps_the_best_rate_at_each_false_alarm_rate(figures):
    """A reviewer: straight segments on the log axis crossed the 1 % line at 0.298 for a
    detector whose ``tpr_at_1pct_fpr`` is 0 (its scores tie from (0, 0) to (0.37, 0.97)).
    Drawn as steps, the curve at 1 % reads ``tpr_at_1pct_fpr``."""
    import numpy as np

    suite, figs = figures
    ax = figs["roc.png"].axes[0]
    curves = {_name(line.get_label()): line for line in ax.get_lines()
              if "(AUC" in line.get_label()}  # fmt: skip
    assert curves and all(c.get_drawstyle() == "steps-post" for c in curves.values())
    for name, line in curves.items():
        x, y = (np.asarray(v, float) for v in line.get_data())
        at = y[np.searchsorted(x, 0.01, side="right") - 1]  # the step in force at 1 %
        assert at == pytest.approx(suite.metrics[name]["tpr_at_1pct_fpr"]), name


def test_the_alarm_raster_is_at_the_calibrated_thresholds_and_says_so():
    """The alarm figure drew each detector's own alarms beside the calibrated rates of the
    other figures (0.378 against 0.6 for one detector), without saying which."""
    import numpy as np

    from difffilter.eval.calibration import calibrate
    from difffilter.eval.suite import apply_calibration

    sc, names = registry.get("four_tank_bias"), ["chi_square_ekf", "cusum_ekf"]
    suite = run_suite(sc, runs=3, estimators=names, progress=False)
    own = dict(standard_figures(suite))["alarms_run0.png"]
    assert "at each detector's own threshold" in own.axes[0].get_title()
    apply_calibration(suite, calibrate(sc, far=0.2, runs=3, estimators=names, progress=False))
    fig = dict(standard_figures(suite))["alarms_run0.png"]
    assert "at the calibrated thresholds" in fig.axes[0].get_title()
    bars = fig.axes[0].collections  # the attacked row, then one per detector
    run = int(suite.traj.flags.any(1).nonzero()[0])
    for name, bar in zip(names, bars[1:]):
        alarms = suite.outputs[name].detection.scores[run] > suite.metrics[name]["threshold_at_far"]
        widths = np.array([p.get_extents().width for p in bar.get_paths()])
        assert len(widths) == int((alarms[1:] & ~alarms[:-1]).sum() + alarms[0]), name
    for f in (own, fig):
        plt.close(f)


def test_the_alarm_raster_has_a_row_per_detector(figures):
    suite, figs = figures
    ax = figs["alarms_run0.png"].axes[0]
    detecting = [n for n, o in suite.outputs.items() if o.detection is not None]
    assert [t.get_text() for t in ax.get_yticklabels()] == ["attacked", *detecting]


def test_a_calibrated_study_shows_its_false_alarms_after_an_attack(figures):
    """Each calibrated detector's alarm rate by the steps since the run's last attack,
    each point counted again here step by step; an uncalibrated study has no such figure."""
    from difffilter.eval.calibration import calibrate
    from difffilter.eval.plots import AFTER_ATTACK_EDGES
    from difffilter.eval.suite import apply_calibration

    assert "false_alarms_after_attack.png" not in figures[1]
    sc, names = registry.get("four_tank_bias"), ["chi_square_ekf", "cusum_ekf"]
    suite = run_suite(sc, runs=3, estimators=names, progress=False)
    apply_calibration(suite, calibrate(sc, far=0.05, runs=3, estimators=names, progress=False))
    fig = dict(standard_figures(suite))["false_alarms_after_attack.png"]
    lines = {line.get_label().split(" (")[0]: line for line in fig.axes[0].get_lines()}
    assert set(names) <= set(lines)
    edges = [*AFTER_ATTACK_EDGES, 10**9]
    for name in names:
        flags = suite.traj.flags
        alarms = suite.outputs[name].detection.scores > suite.metrics[name]["threshold_at_far"]
        hits, steps = [0] * (len(edges) - 1), [0] * (len(edges) - 1)
        for b in range(flags.shape[0]):
            last = None
            for k in range(flags.shape[1]):
                if flags[b, k]:
                    last = k
                elif last is not None:
                    i = next(
                        i for i in range(len(edges) - 1) if edges[i] <= k - last < edges[i + 1]
                    )
                    steps[i] += 1
                    hits[i] += int(alarms[b, k])
        drawn = lines[name].get_ydata()
        floor = fig.axes[0].get_ylim()[0] / 0.8
        expected = [max(h / s, floor) for h, s in zip(hits, steps) if s > 0]
        assert list(drawn[: len(expected)]) == pytest.approx(expected)
    # the floor where a rate of 0 is drawn is a line the legend names (a user trial read a
    # detector without false alarms as one with 0.2 % of them)
    zero = lines["no alarm at all"]
    assert list(zero.get_ydata()) == pytest.approx([floor, floor])


def test_the_one_run_figures_show_the_first_attacked_run():
    """A user trial's scenario attacked half its runs, run 0 not: its figures showed an
    injected signal of zeros and an empty attacked row."""
    import torch

    from difffilter.eval.plots import shown_run

    flags = torch.zeros(4, 6, dtype=torch.bool)
    assert shown_run(flags) == 0  # nothing attacked: run 0
    flags[2, 3] = True
    flags[3, 1] = True
    assert shown_run(flags) == 2
    per_entry = torch.zeros(3, 6, 2, dtype=torch.bool)
    per_entry[1, 4, 1] = True
    assert shown_run(per_entry) == 1


def test_the_robustness_heat_map_stacks_its_panels_and_reads_ratios_on_a_log_scale(
    monkeypatch, tmp_path
):
    """Side by side the three panels made a 24-inch figure whose text was unreadable at a
    page's width, and the ratio's colour bar read log10 of what its cells printed, clipped
    at 10 (22 and 32 the same red as 10: a figure review)."""
    from matplotlib.colors import LogNorm

    from difffilter.eval.robustness import _heatmap

    cells = {t: {e: {"tpr_at_far": 0.5, "state_error_ratio": r, "impact": 0.1}
                 for e, r in (("a", 1.0), ("b", 32.0))} for t in ("bias", "ramp")}  # fmt: skip
    doc = {"scenario": "s", "threats": list(cells), "estimators": {"a": {}, "b": {}},
           "cells": cells, "far": {"target": 0.01}}  # fmt: skip
    closed, close = [], plt.close
    monkeypatch.setattr(plt, "close", closed.append)
    _heatmap(tmp_path / "robustness.png", doc, registry.get("four_tank_bias"))
    fig = closed[0]
    panels = [ax for ax in fig.axes if ax.get_title()]
    assert len(panels) == 3 and fig.get_size_inches()[0] < 10  # stacked, a page wide
    ratio = panels[1].images[0]
    assert isinstance(ratio.norm, LogNorm) and ratio.norm.vmax == 32.0  # not clipped at 10
    bar_labels = [t.get_text() for t in ratio.colorbar.ax.get_yticklabels()]
    assert bar_labels == ["1", "2", "5", "10", "20"]
    assert (tmp_path / "robustness.png").stat().st_size > 10_000
    close(fig)


def test_the_attack_figure_has_a_panel_per_attacked_channel(figures):
    """One panel of the largest channel left the others out (the robot's heading attack,
    the LFC's second attacked area: a figure review)."""
    from difffilter.eval.plots import MAX_ATTACK_PANELS, _attacked_channels, shown_run

    suite, figs = figures
    r = shown_run(suite.traj.flags)
    channels = _attacked_channels(suite.traj.attack, r)[:MAX_ATTACK_PANELS]
    axes = figs["attack_estimates_run0.png"].axes
    assert len(axes) == len(channels)
    for ax, c in zip(axes, channels):
        (injected,) = [line for line in ax.get_lines() if line.get_label() == "injected"]
        assert list(injected.get_ydata()) == suite.traj.attack[r, :, c].tolist()


def test_the_roc_has_a_miss_rate_panel_on_a_log_axis(figures):
    """Most detectors sit near a detection rate of 1, squeezed into the ROC's top pixels (a
    figure review): below it the same curves as misses, 1 − TPR, on a log axis (a DET plot)."""
    import numpy as np

    suite, figs = figures
    roc_ax, det = figs["roc.png"].axes[:2]
    assert det.get_yscale() == "log" and det.get_xscale() == "log"
    curves = [line for line in roc_ax.get_lines() if "(AUC" in line.get_label()]
    misses = [line for line in det.get_lines() if line.get_drawstyle() == "steps-post"]
    assert len(curves) == len(misses)
    floor = det.get_lines()[-1].get_ydata()[0]  # the "no miss" line
    for curve, miss in zip(curves, misses):
        np.testing.assert_allclose(miss.get_ydata(), np.maximum(1 - curve.get_ydata(), floor))


def test_heat_map_text_is_white_on_the_darkest_shades_alone():
    from difffilter.eval.plots import text_colour

    assert [text_colour(v) for v in (0.0, 0.1, 0.15, 0.5, 0.85, 0.9, 1.0, float("nan"))] == [
        "white", "white", "black", "black", "black", "white", "white", "black"]  # fmt: skip


def test_a_zoomed_axis_says_what_it_cuts_off_and_where():
    """The robot's input-error figure is zoomed on its ±1 bound, and its peak of about 20
    (the steps after the attack starts) was cut off at the edge without a word."""
    import torch

    from difffilter.eval.plots import mark_off_scale

    t = list(range(1, 11))
    mean = torch.tensor([0.0, 0.1, 7.5, 25.0, 3.0, 0.2, -3.5, 0.0, 0.0, 0.0])
    rms = torch.tensor([0.5, 0.5, 8.0, 24.0, 3.1, 0.6, 3.5, 0.4, 0.4, float("nan")])
    fig, ax = plt.subplots()
    mark_off_scale(ax, t, (mean, rms), (-2, 6), " cm/s")
    notes = {a.get_text(): a.xy for a in ax.texts}
    assert ax.get_ylim() == (-2, 6)
    assert notes == {"↑ off scale: 25 cm/s at k = 4": (4, 6),
                     "↓ off scale: -3.5 cm/s at k = 7": (7, -2)}  # fmt: skip
    plt.close(fig)
    fig, ax = plt.subplots()
    mark_off_scale(ax, t, (torch.zeros(10),), (-2, 6))  # nothing beyond: nothing said
    assert len(ax.texts) == 0 and ax.get_ylim() == (-2, 6)
    plt.close(fig)


def test_robot_fig_b1_draws_the_compensated_path_beneath_the_estimate(monkeypatch, tmp_path):
    """Fig. B1's compensated path and the estimate nearly coincide; at one width the
    estimate's dashes had hidden the path (a figure review). Fig. input error names its
    off-scale peak."""
    from types import SimpleNamespace as NS

    import torch

    from difffilter.eval.families.robot import _figures

    steps = 6
    path = [[float(k), float(k)] for k in range(steps)]
    curves = {"mean": [[0.0, 0.0]] * 3 + [[20.0, 9.0]] + [[0.0, 0.0]] * 2,
              "rms": [[0.5, 0.5]] * steps}  # fmt: skip
    doc = {"steps": steps, "rmse_curves": {"ekf": [1.0] * steps},
           "compensation": {"paths": {"attack_free": path, "attacked": path,
                                      "compensated": path, "estimate": path},
                            "input_error_curves": curves}}  # fmt: skip
    result = NS(context=NS(model=NS(sensor_pos=torch.zeros(2, 2))), outputs={"ekf": None})
    figures, close = [], plt.close
    monkeypatch.setattr(plt, "close", figures.append)
    assert _figures(result, doc, tmp_path)[0] == "fig_b1_trajectories.png"
    lines = {line.get_label(): (i, line) for i, line in enumerate(figures[0].axes[0].get_lines())}
    (below, path_line), (above, estimate) = lines["compensated"], lines["estimate"]
    assert below < above and path_line.get_linewidth() > 2 * estimate.get_linewidth()
    errors = figures[-1].axes
    assert [a.get_text() for a in errors[0].texts] == ["↑ off scale: 20 cm/s at k = 4"]
    assert [a.get_text() for a in errors[1].texts] == ["↑ off scale: 9 deg/s at k = 4"]
    for fig in figures:
        close(fig)
