"""What a user reads after an evaluation, checked against truths computed here: the
TensorBoard curves and HPARAMS rows read back from the event files against float64 numpy
recomputations of ``difffilter.eval.tensorboard``'s docstring; the figures' line and bar
data read back from the matplotlib objects against step-by-step counts; the colour rule
against matplotlib's own palettes; the coverage labels against the module's table; and
the plant comparison against the docstring's point set, written out by hand.

Each test failed on a mutant of a mutation review that the rest of the suite let through.
"""

from __future__ import annotations

import colorsys
import hashlib
import io
import json
from types import SimpleNamespace as NS

import matplotlib.pyplot as plt
import numpy as np
import pytest
import torch
from matplotlib import colors as mcolors

from difffilter.attack import Channel

D = torch.float64


def _events(logdir):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(logdir), size_guidance={"scalars": 0, "images": 0})
    events.Reload()
    return events


def _tb_result():
    """Three runs, four steps, two states, one sensor attack entry: ``chi`` detects and
    estimates the sensor attack, ``act`` estimates an actuator attack of the same width
    (not comparable), ``zero`` detects with a calibrated threshold of exactly 0."""
    g = torch.Generator().manual_seed(147)
    B, T = 3, 4
    x = torch.randn(B, T, 2, generator=g, dtype=D)
    attack = torch.zeros(B, T, 1, dtype=D)
    attack[1, 2:, 0] = 2.0  # run 1 attacked at steps 3, 4
    flags = attack[..., 0] != 0
    traj = NS(x=x, attack=attack, flags=flags, info={"attack_channel": Channel.SENSOR})
    scores = torch.tensor([[0.5, 0.2, 0.7, -1.0], [0.1, 0.5, 0.9, float("nan")],
                           [0.5, 0.6, 0.0, 0.3]], dtype=D)  # fmt: skip
    det = NS(alarms=scores > 0.55, scores=scores)
    est = torch.randn(B, T, 1, generator=g, dtype=D)
    outputs = {
        "chi": NS(means=x + torch.randn(B, T, 2, generator=g, dtype=D), detection=det,
                  attack=est, attack_channel=Channel.SENSOR),
        "act": NS(means=x + 0.5, detection=None, attack=est, attack_channel=Channel.ACTUATOR),
        "zero": NS(means=x - 0.25, detection=NS(alarms=scores > 0.8, scores=scores),
                   attack=None, attack_channel=None),
    }  # fmt: skip
    # (the study's calibrated thresholds, which the curves take: an infinite one is null
    # in the report's JSON)
    metrics = {"chi": {"threshold_at_far": 0.5}, "act": {}, "zero": {"threshold_at_far": 0.0}}
    return NS(outputs=outputs, traj_of=lambda name: traj, metrics=metrics), traj


def test_tensorboard_curves_are_the_docstrings_equations_in_float64(tmp_path):
    """Every per-step curve against numpy: ``state_rmse_per_step`` the RMS over runs and
    components; ``attack_rmse_per_step`` the same of ``â − a`` at every step (attack-free
    ones included, ``a = 0``), only for a comparable estimate (a sensor estimate against a
    sensor attack, not an actuator one); ``alarm_rate_per_step`` the share of runs
    alarming; ``alarm_rate_at_far_per_step`` the share with ``score > τ`` (strictly, NaN
    never alarms), also for ``τ = 0``; scalars at steps ``k = 1 … T``."""
    from difffilter.eval.tensorboard import log_suite

    result, traj = _tb_result()
    doc = {"estimators": {"chi": {"threshold_at_far": 0.5}, "act": {},
                          "zero": {"threshold_at_far": 0.0}},
           "scenario": "s", "runs": 3, "seed": 0}  # fmt: skip
    log_suite(tmp_path, result, doc, [])
    events = _events(tmp_path)

    def curve(tag):
        got = events.Scalars(tag)
        assert [e.step for e in got] == [1, 2, 3, 4], tag
        return np.array([e.value for e in got])

    x = traj.x.numpy()
    a = traj.attack.numpy()
    scores = result.outputs["chi"].detection.scores.numpy()
    for name, out in result.outputs.items():
        want = np.sqrt(((out.means.numpy() - x) ** 2).mean(axis=(0, 2)))
        assert curve(f"state_rmse_per_step/{name}") == pytest.approx(want, rel=1e-6)
    want = np.sqrt(((result.outputs["chi"].attack.numpy() - a) ** 2).mean(axis=(0, 2)))
    assert curve("attack_rmse_per_step/chi") == pytest.approx(want, rel=1e-6)
    tags = events.Tags()["scalars"]
    assert "attack_rmse_per_step/act" not in tags and "attack_rmse_per_step/zero" not in tags
    safe = np.where(np.isnan(scores), -np.inf, scores)
    assert curve("alarm_rate_per_step/chi") == pytest.approx((scores > 0.55).mean(0))
    assert curve("alarm_rate_at_far_per_step/chi") == pytest.approx((safe > 0.5).mean(0))
    assert curve("alarm_rate_at_far_per_step/zero") == pytest.approx((safe > 0.0).mean(0))
    assert "alarm_rate_at_far_per_step/act" not in tags


def test_the_hparams_row_holds_its_settings_and_only_the_metrics_that_have_values(tmp_path):
    """One session ``hparams/<name>`` per estimator: its hyperparameters (scenario,
    estimator, runs, seed, as given in ``doc``), the headline and calibrated metrics that
    have a value (a calibrated threshold of 0 is one), and ``holds_share`` per judged
    check where it is a number; each as a scalar of its own name."""
    from tensorboard.plugins.hparams import plugin_data_pb2

    from difffilter.eval.tensorboard import log_suite

    result, _ = _tb_result()
    doc = {"estimators": {"chi": {"auc": 0.75, "state_rmse": 1.25, "threshold_at_far": 0.0,
                                  "impact": None, "other": 3.0},
                          "act": {"state_rmse": 0.5}, "zero": {}},
           "scenario": "plant", "runs": 5, "seed": 7,
           "acceptance_intervals": {"estimators": {"chi": {
               "state_rmse": {"holds_share": 0.8}, "auc": {"holds_share": None}}}}}  # fmt: skip
    log_suite(tmp_path, result, doc, [])
    for name in doc["estimators"]:
        events = _events(tmp_path / "hparams" / name)
        content = events.PluginTagToContent("hparams")["_hparams_/session_start_info"]
        start = plugin_data_pb2.HParamsPluginData.FromString(content).session_start_info
        hp = {k: (v.string_value or v.number_value) for k, v in start.hparams.items()}
        assert hp == {"scenario": "plant", "estimator": name, "runs": 5, "seed": 7}, name
    from conftest import session_scalars

    scalars = {t: v for t, (v,) in session_scalars(tmp_path / "hparams" / "chi").items()}
    assert scalars == pytest.approx({"hparam/auc": 0.75, "hparam/state_rmse": 1.25,
                                     "hparam/threshold_at_far": 0.0,
                                     "hparam/holds_share/state_rmse": 0.8})  # fmt: skip


def test_a_logged_figure_keeps_its_pngs_width_and_height(tmp_path):
    """The image event's width and height are the PNG's (as matplotlib decodes it), for a
    figure wider than tall."""
    import matplotlib.image as mpimg

    from difffilter.eval.tensorboard import log_suite

    fig, ax = plt.subplots(figsize=(3.0, 1.0))
    ax.plot([0, 1])
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=50)
    plt.close(fig)
    png = buffer.getvalue()
    height, width = mpimg.imread(io.BytesIO(png)).shape[:2]
    result = NS(outputs={}, traj_of=None)
    doc = {"estimators": {}, "scenario": "s", "runs": 1, "seed": 0}
    log_suite(tmp_path, result, doc, [("rmse_over_time.png", png)])
    (image,) = _events(tmp_path).Images("rmse_over_time")
    assert (image.width, image.height) == (width, height) == (150, 50)
    assert image.encoded_image_string == png


def test_colours_are_the_palettes_hues_and_a_family_spreads_over_lightness():
    """The first family keeps tab10's first colour, the second family's members share
    tab10's second hue at lightness 0.3, 0.5, 0.7 (the docstring's 0.3 … 0.7)."""
    from difffilter.eval.plots import estimator_colours

    colours = estimator_colours(["alpha_x", "beta_a", "beta_b", "beta_c"])
    tab10 = plt.get_cmap("tab10").colors
    assert colours["alpha_x"] == mcolors.to_hex(tab10[0])
    hue = colorsys.rgb_to_hls(*tab10[1])[0]
    for name, lightness in (("beta_a", 0.3), ("beta_b", 0.5), ("beta_c", 0.7)):
        h, li, _ = colorsys.rgb_to_hls(*mcolors.to_rgb(colours[name]))
        assert h == pytest.approx(hue, abs=0.01) and li == pytest.approx(lightness, abs=0.01)


def _roc_result(far=0.1):
    flags = torch.tensor([[False, False, True, True, False], [False, False, False, True, True]])
    scores = torch.tensor([[0.1, 0.4, 0.8, 0.9, 0.3], [0.2, 0.6, 0.5, 0.7, 0.95]])
    outputs = {n: NS(detection=NS(scores=scores)) for n in ("cal", "own")}
    metrics = {"cal": {"auc": 0.9, "fpr_at_far": 0.0, "tpr_at_far": 0.5},
               "own": {"auc": 0.9, "fpr": 0.2, "tpr": 0.75}}  # fmt: skip
    return NS(traj=NS(flags=flags), traj_of=lambda n: NS(flags=flags), metrics=metrics,
              calibration=NS(far=far)), outputs  # fmt: skip


def test_the_roc_clamps_to_half_a_false_alarm_and_marks_the_operating_points():
    """Six attack-free steps: the smallest non-zero rate a curve shows is 1/6, and a rate
    of 0 is drawn at half of it, 1/12, on its labelled line (it had been drawn at 1/6, where
    one false alarm is); the axis' left edge just beyond it; the calibrated dot at (max(0,
    1/12), 0.5), the uncalibrated one at its own (fpr, tpr) = (0.2, 0.75); the target rate a
    vertical line at 0.1. The curve's x values: each threshold's share of attack-free steps
    alarming, counted here."""
    from difffilter.eval.plots import _roc_figure

    result, outputs = _roc_result()
    fig = _roc_figure(result, outputs, {"cal": "C0", "own": "C1"})
    ax = fig.axes[0]
    assert ax.get_xlim()[0] == pytest.approx(0.8 / 12)
    curve = next(line for line in ax.lines if line.get_label().startswith("cal (AUC"))
    s, f = (v.numpy().ravel() for v in (outputs["cal"].detection.scores, result.traj.flags))
    fprs = {max((s[~f] >= th).mean(), 1 / 12) for th in s} | {1 / 12}
    assert set(np.round(curve.get_xdata(), 9)) <= set(np.round(list(fprs), 9))
    assert min(curve.get_xdata()) == pytest.approx(1 / 12)
    dots = [v for line in ax.lines if line.get_marker() == "o"
            for v in (float(line.get_xdata()[0]), float(line.get_ydata()[0]))]  # fmt: skip
    assert dots == pytest.approx([1 / 12, 0.5, 0.2, 0.75])
    (zero,) = [line for line in ax.lines if line.get_label().startswith("no false alarm")]
    assert list(zero.get_xdata()) == pytest.approx([1 / 12, 1 / 12])
    (target,) = [line for line in ax.lines if line.get_label().startswith("target")]
    assert list(target.get_xdata()) == pytest.approx([0.1, 0.1])
    plt.close(fig)


def test_false_alarms_after_an_attack_are_binned_in_each_estimators_own_loop():
    """Two detectors on trajectories of their own (closed loops): each point is counted
    here step by step in its own flags; a bin's step count is the larger of the two; bins
    without steps are left out, the last point is the steps before any attack; the floor
    is half an alarm in the largest bin shown; the ticks name ``[a, b)`` as ``a–(b−1)``."""
    from difffilter.eval.plots import AFTER_ATTACK_EDGES, FEW_STEPS, _after_attack_figure

    g = torch.Generator().manual_seed(3)
    B, T = 4, 30
    flags = {"a": torch.zeros(B, T, dtype=torch.bool), "b": torch.zeros(B, T, dtype=torch.bool)}
    flags["a"][:, 5:8] = True
    flags["b"][:, 10:12] = True
    flags["b"][0, 25] = True
    scores = {n: torch.rand(B, T, generator=g, dtype=D) for n in flags}
    metrics = {n: {"threshold_at_far": 0.6, "fpr_at_far_after_attack": 0.125} for n in flags}
    result = NS(traj=NS(flags=flags["a"]), traj_of=lambda n: NS(flags=flags[n]),
                outputs={n: NS(detection=NS(scores=scores[n])) for n in flags},
                metrics=metrics, calibration=NS(far=0.05))  # fmt: skip
    fig = _after_attack_figure(result, ["a", "b"], {"a": "C0", "b": "C1"})
    ax = fig.axes[0]
    edges = [*AFTER_ATTACK_EDGES, 10**9]
    nbins = len(edges)  # the after-attack bins and "before any attack"
    hits = {n: np.zeros(nbins) for n in flags}
    steps = {n: np.zeros(nbins, int) for n in flags}
    for n in flags:
        f, s = flags[n].numpy(), scores[n].numpy()
        for b in range(B):
            last = None
            for k in range(T):
                if f[b, k]:
                    last = k
                    continue
                i = nbins - 1 if last is None else next(
                    i for i in range(nbins - 1) if edges[i] <= k - last < edges[i + 1])  # fmt: skip
                steps[n][i] += 1
                hits[n][i] += s[b, k] > 0.6
    most = np.maximum(steps["a"], steps["b"])
    shown = most > 0
    floor = 0.5 / most[shown].max()
    lines = {line.get_label().split(" (")[0]: line for line in ax.lines}
    since = int(shown[:-1].sum())  # the bins after an attack; "before any attack" apart
    for n, colour in (("a", "C0"), ("b", "C1")):
        assert "12.5 % in steps 1–10" in lines[n].get_label()
        with np.errstate(invalid="ignore"):
            rate = hits[n] / steps[n]
        want = np.maximum(rate[shown], floor)  # NaN (no step of its own) stays NaN
        # the line joins the bins since an attack, not the point before any attack
        assert lines[n].get_ydata() == pytest.approx(want[:since], nan_ok=True)
        # every bin a marker, open where it has fewer than FEW_STEPS steps
        points = {}
        for line in ax.lines:
            if line.get_marker() == "o" and line.get_color() == colour:
                for x, y in zip(line.get_xdata(), line.get_ydata()):
                    points[int(x)] = (y, line.get_markerfacecolor() == "none")
        assert [points[i][0] for i in sorted(points)] == pytest.approx(want, nan_ok=True)
        assert [points[i][1] for i in sorted(points)] == list(most[shown] < FEW_STEPS)
    assert ax.get_ylim()[0] == pytest.approx(0.8 * floor)
    labels = ["1", "2", "3–4", "5–9", "10–19", "20–49", "50–99", "100–199", "≥ 200",
              "before any attack"]  # fmt: skip
    want_ticks = [f"{lab}\nn = {n:,}" for lab, n in zip(labels, most) if n > 0]
    assert [t.get_text() for t in ax.get_xticklabels()] == want_ticks
    plt.close(fig)


def _one_run_result(calibrated):
    """Run 0 clean, run 1 attacked at steps 2-3 of 5; detectors ``p`` and ``q``."""
    B, T = 2, 5
    flags = torch.zeros(B, T, dtype=torch.bool)
    flags[1, 1:3] = True
    attack = torch.zeros(B, T, 1, dtype=D)
    attack[1, 1:3, 0] = 3.0
    x = torch.zeros(B, T, 1, dtype=D)
    scores = torch.tensor([[0.9, 0.9, 0.0, 0.0, 0.9], [0.0, 0.0, 0.9, 0.9, 0.0]], dtype=D)
    info = {"attack_channel": Channel.SENSOR}
    traj = NS(flags=flags, attack=attack, x=x, info=info)
    own_alarms = torch.tensor([[False, True, False, False, False]] * 2)
    outputs = {n: NS(means=x + 0.1, detection=NS(scores=scores, alarms=own_alarms),
                     attack=attack + 0.5, attack_channel=Channel.SENSOR) for n in ("p", "q")}  # fmt: skip
    metrics = {n: {"threshold_at_far": calibrated.get(n), "auc": 0.5} for n in outputs}
    return NS(traj=traj, outputs=outputs, scenario=NS(dt=1.0, state_unit="m", attack_unit="V"),
              traj_of=lambda n: traj, metrics=metrics, calibration=None)  # fmt: skip


def _spans(collection):
    return [tuple(np.round(p.get_extents().intervalx, 9)) for p in collection.get_paths()]


def test_the_one_run_figures_show_the_first_attacked_run_at_the_right_rows():
    """Run 0 is clean: the attack figure's injected line is run 1's attack, the alarm
    figure's top row run 1's attacked steps (2-3, bars of width dt centred on k·dt), each
    detector's alarms run 1's ``score > τ`` (τ = 0 is a calibrated threshold: steps 3-4)
    or, uncalibrated, its own alarms of run 1; each bar row centred on its label's tick;
    the title says some, not all, are calibrated."""
    from difffilter.eval.plots import standard_figures

    result = _one_run_result({"p": 0.0})
    figs = dict(standard_figures(result))
    attack = figs["attack_estimates_run0.png"].axes[0]
    injected = next(line for line in attack.lines if line.get_label() == "injected")
    assert list(injected.get_ydata()) == [0.0, 3.0, 3.0, 0.0, 0.0]
    assert list(next(line for line in attack.lines if line.get_label() == "p").get_ydata()) == [
        0.5, 3.5, 3.5, 0.5, 0.5]  # fmt: skip
    ax = figs["alarms_run0.png"].axes[0]
    top, p, q = ax.collections
    assert _spans(top) == [(1.5, 3.5)]
    assert _spans(p) == [(2.5, 4.5)]  # run 1's scores above 0: steps 3, 4
    assert _spans(q) == [(1.5, 2.5)]  # q's own alarm at step 2 of run 1
    ticks = {t.get_text(): y for t, y in zip(ax.get_yticklabels(), ax.get_yticks())}
    for label, bars in (("attacked", top), ("p", p), ("q", q)):
        (y0, y1) = bars.get_paths()[0].get_extents().intervaly
        assert (y0 + y1) / 2 == pytest.approx(ticks[label]), label
    assert "where calibrated, else each detector's own" in ax.get_title()
    for fig in figs.values():
        plt.close(fig)


def _card(tmp_path, name, card):
    path = tmp_path / f"{name}.ckpt"  # the checkpoint itself is never read for coverage
    path.with_suffix(".json").write_text(json.dumps(card))
    return path


def test_coverage_lists_every_entry_of_a_channel_from_the_scenarios_model(tmp_path):
    """``entries: null`` (every entry) and the list of all of them are the same threat
    once the model gives the channel's width (a four-sensor plant): "within" with the
    model, "kind only" without; a threat of a user's class beside a network trained on a
    library attack is placed by the distribution ("held out"), not "not known"."""
    from difffilter.eval.coverage import training_coverage
    from difffilter.threats import Bias

    threats = {"bias_all": {"weight": 1.0, "kind": "bias", "value": 0.5, "onset": 21,
                            "entries": [0, 1, 2, 3]}}  # fmt: skip
    path = _card(tmp_path, "net", {"data_config": {"threats": threats}, "model_config": {}})
    study = {"bias": {"kind": "bias", "value": 0.5, "onset": 21, "entries": None}}
    model = NS(dim_y=4, dim_u=2)
    assert training_coverage(path, study, model=model)["threats"] == {"bias": "within"}
    assert training_coverage(path, study)["threats"] == {"bias": "kind only"}
    plain = _card(tmp_path, "plain", {"data_config": {}, "model_config": {}})
    mine = {"scale": {"kind": "my_attacks:Scaling", "alpha": 0.3}}
    own = Bias(value=0.5, onset=21)
    assert training_coverage(plain, mine, own=own)["threats"] == {"scale": "held out"}


def _fake_plant(calls, *, mean, cov, du=1, scale=1.0, h_shape=None):
    """A plant of the interface ``plant_difference`` reads, recording its calls."""

    def transition(x, u, k):
        calls.append(("f", x.clone(), None if u is None else u.clone(), k))
        return x * scale

    def observe(x, k):
        calls.append(("h", x.clone(), None, k))
        y = x[:, :1] if h_shape is None else torch.ones(len(x), 1, dtype=x.dtype)
        return y if h_shape is None else y.reshape(h_shape)

    return NS(dim_x=2, dim_y=1, dim_u=du, initial=NS(mean=mean, cov=cov),
              transition=transition, observe=observe)  # fmt: skip


def test_plants_are_compared_at_the_docstrings_points_input_and_times():
    """``f(x_j, u, k)`` and ``h(x_j, k)`` at ``m₀``, ``m₀ + σ_i e_i``, ``m₀ − σ`` with
    ``σ = √diag P₀`` and ``u = 0.1``, and ``f(m₀, 0.1 e_l, 0)`` for each input ``l``,
    written out for m₀ = (1, −2), P₀ = diag(4, 9) (a prior per run: its first); a relative
    difference of 1e-5 is one (rtol 1e-6); an output of another shape is one."""
    from difffilter.models.plant_match import plant_difference

    want = np.array([[1.0, -2.0], [3.0, -2.0], [1.0, 1.0], [-1.0, -5.0]])
    with_inputs = np.concatenate([want, [[1.0, -2.0]]])  # m₀ with u = 0.1 e_1 (du = 1)
    mean = torch.tensor([[1.0, -2.0], [5.0, 5.0]], dtype=D)  # per run: the first
    cov = torch.stack([torch.diag(torch.tensor([4.0, 9.0], dtype=D)), 100 * torch.eye(2, dtype=D)])
    calls = []
    a = _fake_plant(calls, mean=mean, cov=cov)
    b = _fake_plant(calls, mean=mean, cov=cov)
    assert plant_difference(a, b) is None
    # each at k = 0, 1, 2, 7 (h: 1, 2, 7): a plant reading k can differ from k = 1 on only
    assert [(c[0], c[3]) for c in calls] == [
        *((w, k) for w, ks in (("f", (0, 1, 2, 7)), ("h", (1, 2, 7))) for k in ks for _ in "ab")
    ]
    for what, x, u, _ in calls:
        assert x.numpy() == pytest.approx(with_inputs if what == "f" else want), what
        if what == "f":
            assert u.numpy() == pytest.approx(np.full((5, 1), 0.1))
    off = _fake_plant([], mean=mean, cov=cov, scale=1 + 1e-5)
    assert "transition" in plant_difference(a, off)
    column = _fake_plant([], mean=mean, cov=cov, h_shape=(-1, 1))
    flat = _fake_plant([], mean=mean, cov=cov, h_shape=(-1,))
    assert "measurement" in plant_difference(column, flat)


def test_a_scenario_file_with_other_bytes_than_training_read_is_named(tmp_path):
    """The card's sha256 against the file's bytes now (hashlib here): equal, no note;
    different, a note naming both digests' first 12 characters, also among the notes
    the command prints (where the file's plant cannot be built: that note alone)."""
    from difffilter.models.plant_match import scenario_file_change, training_plant_notes

    plant = tmp_path / "p.yaml"
    plant.write_text("name: p\n")
    digest = hashlib.sha256(b"name: p\n").hexdigest()
    card = {"model_config": {"scenario": str(plant)}, "scenario_file_sha256": digest}
    path = _card(tmp_path, "net", card)
    assert scenario_file_change("net.ckpt", path) is None
    plant.write_text("name: q\n")
    note = scenario_file_change("net.ckpt", path)
    now = hashlib.sha256(b"name: q\n").hexdigest()
    assert note is not None and digest[:12] in note and now[:12] in note
    (printed,) = training_plant_notes([("net.ckpt", path)], [])
    assert printed.startswith("note: --ckpt net.ckpt was trained on the scenario file")
    assert digest[:12] in printed and now[:12] in printed


def test_three_grey_families_still_get_distinct_colours():
    """28 two-member families: the 8th, 18th and 28th families all take a grey (tab10's
    grey, tab20's light grey, tab10's grey again; a grey has no hue to shift), so their
    members clash three ways at the same lightness; no two estimators may share a colour
    (the module docstring), which takes nudging a colour more than once."""
    from difffilter.eval.plots import estimator_colours

    names = [f"f{i}_{m}" for i in range(28) for m in ("a", "b")]
    colours = estimator_colours(names)
    assert len(set(colours.values())) == len(names)


def test_a_study_attacked_at_every_step_draws_no_roc():
    """Without an attack-free step there is no false-alarm rate: no ROC and no alarm
    figure (the RMSE figure only)."""
    from difffilter.eval.plots import standard_figures

    flags = torch.ones(2, 3, dtype=torch.bool)
    x = torch.zeros(2, 3, 1, dtype=D)
    traj = NS(flags=flags, attack=torch.zeros(2, 3, 0), x=x)
    out = NS(means=x + 1.0, detection=NS(scores=torch.rand(2, 3), alarms=flags), attack=None)
    result = NS(traj=traj, outputs={"chi": out}, scenario=NS(dt=1.0, state_unit="m"),
                traj_of=lambda n: traj, metrics={"chi": {"auc": None}}, calibration=None)  # fmt: skip
    figs = standard_figures(result)
    assert [name for name, _ in figs] == ["rmse_over_time.png"]
    for _, fig in figs:
        plt.close(fig)


def test_the_attack_figure_draws_the_most_attacked_channel_of_the_shown_run():
    """Two attack entries, the second attacked by more (by magnitude): the injected line
    and each estimate are that entry's, and the axis names channel 2."""
    from difffilter.eval.plots import standard_figures

    B, T = 1, 3
    attack = torch.tensor([[[1.0, 0.0], [1.0, -4.0], [0.0, -4.0]]], dtype=D)
    x = torch.zeros(B, T, 1, dtype=D)
    traj = NS(flags=attack.ne(0).any(-1), attack=attack, x=x,
              info={"attack_channel": Channel.SENSOR})  # fmt: skip
    out = NS(means=x + 0.5, detection=None, attack=2 * attack, attack_channel=Channel.SENSOR)
    result = NS(traj=traj, outputs={"est": out}, traj_of=lambda n: traj, metrics={"est": {}},
                scenario=NS(dt=1.0, state_unit="m", attack_unit="V"))  # fmt: skip
    figs = dict(standard_figures(result))
    ax = figs["attack_estimates_run0.png"].axes[0]
    lines = {line.get_label(): list(line.get_ydata()) for line in ax.lines}
    assert lines == {"injected": [0.0, -4.0, -4.0], "est": [0.0, -8.0, -8.0]}
    assert ax.get_ylabel() == "attack, channel 2 [V]"
    for fig in figs.values():
        plt.close(fig)
