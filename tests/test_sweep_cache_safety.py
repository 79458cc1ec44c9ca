"""What ``difffilter-train sweep`` keeps in its ``--out`` survives an interrupt or a file cut
short, and Ctrl-C ends ``fit`` and ``sweep`` with exit code 130 (a red-team run's findings
05, 06 and 08).

- The analytic baselines (``baselines/<scenario>.json`` and ``<scenario>.totals.pt``): a
  sweep interrupted while the totals were saved had left its new key beside another
  study's totals, which the next sweep read as its own; a cut totals file gave a raw
  traceback and a cut table an error naming no file. Both files now hold the key, are
  written whole or not at all, the totals first, and one that cannot be read is computed
  again with a warning naming it.
- A seed's ``sweep_settings.json`` (not a cache: it guards the resume) cut short is an
  error naming the file and what to do; it is written whole or not at all.
- Ctrl-C: ``difffilter-train fit`` and ``sweep`` exited 1, an ordinary failure's code;
  now 130 with one line, as ``difffilter-eval``, the fit's ``last.ckpt`` kept.
"""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest
import torch

from difffilter.train import sweep

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = "four_tank_bias"
MONITORED = (
    "trainer:\n  logger:\n    class_path: lightning.pytorch.loggers.CSVLogger\n"
    "    init_args: {name: net}\n"
    "  callbacks:\n  - class_path: lightning.pytorch.callbacks.ModelCheckpoint\n"
    "    init_args: {monitor: val/auc, mode: max}\n"
)


def _runs_of(totals: dict) -> set[int]:
    """The run counts of every per-run total (one tensor per estimator and metric)."""
    return {value.shape[0] for metrics in totals.values() for value in metrics.values()}


def _stand_in(monkeypatch) -> list:
    """``_calibrated_metrics`` replaced by a fast one whose totals have one entry per run
    (``runs`` of them, valued ``runs``): which study's totals came back is then plain."""
    computed = []

    def calibrated_metrics(scenario, names, runs, far, progress, checkpoint=None):
        computed.append(runs)
        return {"kf": {"runs_seen": runs}}, {"kf": {"se": torch.full((runs,), float(runs))}}

    monkeypatch.setattr(sweep, "_calibrated_metrics", calibrated_metrics)
    return computed


def _files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


# ---------------------------------------------------------------- 05: the baselines' pair


def test_an_interrupt_while_the_totals_are_saved_leaves_no_other_studys_totals(tmp_path):
    """The red team's repro on the real analytic estimators: 3 runs cached, then a sweep of
    4 runs interrupted inside ``torch.save`` of its totals; the next 4-run sweep had read
    the 3-run totals under the 4-run key. Now it computes them again: 4 runs each."""
    folder = tmp_path / "baselines"
    table_a, totals_a = sweep._baseline(SCENARIO, 3, 0.01, False, folder)
    assert _runs_of(totals_a) == {3}

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(torch, "save", interrupted)
        with pytest.raises(KeyboardInterrupt):
            sweep._baseline(SCENARIO, 4, 0.01, False, folder)
    # nothing half-written is left behind, and the 3-run pair is as it was
    assert _files(folder) == [f"{SCENARIO}.json", f"{SCENARIO}.totals.pt"]
    table_b, totals_b = sweep._baseline(SCENARIO, 4, 0.01, False, folder)
    assert _runs_of(totals_b) == {4}
    assert json.loads((folder / f"{SCENARIO}.json").read_text())["key"]["runs"] == 4
    # and read back as written: the 4-run study's own totals
    table_c, totals_c = sweep._baseline(SCENARIO, 4, 0.01, False, folder)
    assert table_c == table_b
    assert all(torch.equal(totals_c[e][m], totals_b[e][m]) for e in totals_b for m in totals_b[e])


def test_an_interrupt_between_the_totals_and_the_table_is_computed_again(tmp_path, monkeypatch):
    """Interrupted after the new totals and before their table: the table still holds the
    old key, the totals the new one; neither study reads the other's totals."""
    computed = _stand_in(monkeypatch)
    folder = tmp_path / "baselines"
    sweep._baseline(SCENARIO, 3, 0.01, False, folder)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sweep, "write_json_atomically", interrupted)
        with pytest.raises(KeyboardInterrupt):
            sweep._baseline(SCENARIO, 5, 0.01, False, folder)
    assert computed == [3, 5]
    # the table vouches for 3 runs, the totals are 5 runs': computed again, 3 runs
    table, totals = sweep._baseline(SCENARIO, 3, 0.01, False, folder)
    assert computed == [3, 5, 3]
    assert table == {"kf": {"runs_seen": 3}} and _runs_of(totals) == {3}
    # and cached again
    assert _runs_of(sweep._baseline(SCENARIO, 3, 0.01, False, folder)[1]) == {3}
    assert computed == [3, 5, 3]


def test_totals_without_their_key_are_not_trusted(tmp_path, monkeypatch):
    """A totals file that does not carry the table's key (a sweep's from before they held
    one, here another study's totals beside this study's table) is computed again."""
    computed = _stand_in(monkeypatch)
    folder = tmp_path / "baselines"
    sweep._baseline(SCENARIO, 3, 0.01, False, folder)
    torch.save({"kf": {"se": torch.zeros(7)}}, folder / f"{SCENARIO}.totals.pt")
    table, totals = sweep._baseline(SCENARIO, 3, 0.01, False, folder)
    assert computed == [3, 3] and _runs_of(totals) == {3}
    assert torch.equal(totals["kf"]["se"], torch.full((3,), 3.0))


# ---------------------------------------------------------------- 06: files cut short


@pytest.mark.parametrize("suffix", [".totals.pt", ".json"])
def test_a_baseline_file_cut_short_is_computed_again_with_a_warning(
    suffix, tmp_path, monkeypatch, capsys
):  # fmt: skip
    """A cache cut in half (an interrupt or a full disk): one warning line naming the file,
    the baselines computed again (the right run count), and the file whole again."""
    computed = _stand_in(monkeypatch)
    folder = tmp_path / "baselines"
    sweep._baseline(SCENARIO, 4, 0.01, False, folder)
    cut = folder / f"{SCENARIO}{suffix}"
    whole = cut.read_bytes()
    cut.write_bytes(whole[: len(whole) // 2])
    capsys.readouterr()
    table, totals = sweep._baseline(SCENARIO, 4, 0.01, False, folder)
    assert computed == [4, 4]
    assert table == {"kf": {"runs_seen": 4}} and _runs_of(totals) == {4}
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and str(cut) in err[0] and "warning" in err[0], err
    assert "computing them again" in err[0] and "Traceback" not in err[0]
    # written whole again: the next call reads it, silently
    assert sweep._baseline(SCENARIO, 4, 0.01, False, folder)[0] == table
    assert computed == [4, 4] and not capsys.readouterr().err


def _settings_file(tmp_path: Path) -> tuple[Path, Path]:
    """A sweep's config and its seed 0's settings file, as ``_fit`` writes it."""
    config = tmp_path / "c.yaml"
    config.write_text(MONITORED)
    folder = tmp_path / "out" / "runs" / "net" / "seed_0"
    folder.mkdir(parents=True)
    (folder / sweep._SETTINGS).write_text(json.dumps(sweep._settings(config, []), indent=2))
    return config, folder / sweep._SETTINGS


def test_a_damaged_settings_file_is_an_error_naming_it(tmp_path, monkeypatch, capsys):
    """``sweep_settings.json`` cut short: the sweep had stopped on "Unterminated string"
    naming no file. It is no cache (it guards the resume): an error naming the file and
    what to do, exit 2, no traceback, nothing trained."""
    config, settings = _settings_file(tmp_path)
    sweep._check_same_settings(settings.parent, sweep._settings(config, []), 0)  # whole: fine
    whole = settings.read_bytes()
    settings.write_bytes(whole[: len(whole) // 2])
    with pytest.raises(ValueError) as error:
        sweep._check_same_settings(settings.parent, sweep._settings(config, []), 0)
    assert str(settings) in str(error.value)
    assert "delete that folder" in str(error.value) and "another --out" in str(error.value)

    trained = []
    monkeypatch.setattr("difffilter.train.cli.main", lambda args: trained.append(args) or 0)
    code = sweep.main(["--config", str(config), "--seeds", "0", "--out", str(tmp_path / "out"),
                       "--no-progress"])  # fmt: skip
    assert code == 2 and not trained
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("difffilter-train sweep: error: seed 0: ")
    assert str(settings) in err[0]
    # a file that is JSON but no record (a list) is refused the same way
    settings.write_text("[1, 2]\n")
    with pytest.raises(ValueError, match="cannot be read"):
        sweep._check_same_settings(settings.parent, sweep._settings(config, []), 0)


def test_the_settings_are_written_whole_or_not_at_all(tmp_path, monkeypatch):
    """Interrupted half-way through writing a seed's settings, the file it replaces is
    left as it was (written in place, it was left cut short, and refused every rerun)."""
    config, settings = _settings_file(tmp_path)
    before = settings.read_text()
    write_text = Path.write_text

    def cut_short(self, text, *args, **kwargs):
        write_text(self, text[: len(text) // 2], *args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr("difffilter.train.cli.main", lambda args: 0)
    monkeypatch.setattr(Path, "write_text", cut_short)
    with pytest.raises(KeyboardInterrupt):
        sweep._fit(config, 0, tmp_path / "out" / "runs", [], progress=False)
    monkeypatch.setattr(Path, "write_text", write_text)
    assert settings.read_text() == before
    assert _files(settings.parent) == [sweep._SETTINGS]  # no partial file left
    sweep._check_same_settings(settings.parent, sweep._settings(config, []), 0)


# ---------------------------------------------------------------- 08: Ctrl-C exits 130


def test_an_interrupted_fit_exits_130_in_one_line_and_keeps_its_last_checkpoint(
    tmp_path, monkeypatch, capsys
):  # fmt: skip
    """Ctrl-C in the second epoch (a ``KeyboardInterrupt`` from the training step's hook,
    caught by Lightning, which exited 1): exit code 130, one line on stderr as
    ``difffilter-eval``'s, ``last.ckpt`` of the first epoch kept with its resume hint, and
    SIGINT no longer ignored in the process that goes on."""
    from difffilter.train.cli import main
    from difffilter.train.task import FilterEstimatorTask

    def interrupt(self, outputs, batch, batch_idx):
        if self.current_epoch == 1:
            raise KeyboardInterrupt

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    monkeypatch.setattr(FilterEstimatorTask, "on_train_batch_end", interrupt, raising=False)
    small = ["fit", "--config", str(ROOT / "train" / "configs" / "four_tank.yaml"),
             "--data.init_args.batch_size=2", "--data.init_args.batches_per_epoch=2",
             "--data.init_args.val_runs=4", "--data.init_args.steps=20",
             "--model.init_args.hidden=4", "--model.init_args.num_particles=20",
             "--trainer.max_epochs=3", "--no-progress"]  # fmt: skip
    handler = signal.getsignal(signal.SIGINT)
    try:
        try:
            code = main(small)
        except SystemExit as exit_:  # (Lightning's own exit 1 before)
            code = exit_.code
        restored = signal.getsignal(signal.SIGINT)
    finally:
        signal.signal(signal.SIGINT, handler)
    assert code == 130
    assert restored == handler  # Lightning had left SIGINT ignored
    captured = capsys.readouterr()
    said = [line for line in captured.err.splitlines() if "interrupted" in line]
    assert said == [said[0]] and said[0].startswith("difffilter-train: interrupted: ")
    assert "--ckpt_path" in said[0] and "Traceback" not in captured.err
    run = tmp_path / "lightning_logs" / "four_tank_nn_grad" / "version_0"
    last = run / "checkpoints" / "last.ckpt"
    assert last.is_file()
    assert torch.load(last, weights_only=False, map_location="cpu")["epoch"] == 0
    assert "--ckpt_path" in captured.out and "last.ckpt" in captured.out  # its hint, as before


def test_a_fit_that_returns_interrupted_exits_130_too(tmp_path, monkeypatch, capsys):
    """Lightning 2.2 returned from ``fit`` with ``trainer.interrupted`` set (exit 1 was
    given for it): the same 130 and line."""
    import lightning.pytorch as pl
    from lightning.pytorch.trainer.states import TrainerStatus

    from difffilter.train.cli import main

    def returns_interrupted(self, *args, **kwargs):
        self.state.status = TrainerStatus.INTERRUPTED

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    monkeypatch.setattr(pl.Trainer, "fit", returns_interrupted)
    config = str(ROOT / "train" / "configs" / "four_tank.yaml")
    assert main(["fit", "--config", config, "--trainer.max_epochs=1"]) == 130
    err = capsys.readouterr().err
    assert [line for line in err.splitlines() if "interrupted" in line][0].startswith(
        "difffilter-train: interrupted: the training did not finish"
    )


def test_ctrl_c_of_another_command_exits_130_and_a_sweeps_seed_leaves_it_to_the_sweep(
    monkeypatch, capsys
):  # fmt: skip
    """Any command: 130 and one line. Inside a sweep (its resume hint set) the interrupt goes
    on to the sweep, which says it once."""
    from difffilter.train import cli
    from difffilter.train.last_checkpoint import RESUME_HINT

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_main", interrupted)
    monkeypatch.delenv(RESUME_HINT, raising=False)
    assert cli.main(["validate", "--config", "x.yaml"]) == 130
    assert capsys.readouterr().err.strip().splitlines() == [
        "difffilter-train: interrupted: validate did not finish; rerun the same command"
    ]
    monkeypatch.setenv(RESUME_HINT, "rerun the sweep")
    with pytest.raises(KeyboardInterrupt):
        cli.main(["fit", "--config", "x.yaml"])
    assert not capsys.readouterr().err


@pytest.mark.parametrize("how", ["raises", "returns 130"])
def test_an_interrupted_sweep_exits_130_in_one_line(how, tmp_path, monkeypatch, capsys):
    """A seed's fit interrupted (raising, as cli.main does inside a sweep, or its 130): the
    sweep ends with 130 and one line (it had said "fit failed" or exited 1), the seed's
    settings forgotten when it trained nothing."""
    config = tmp_path / "c.yaml"
    config.write_text(MONITORED)

    def fit(args):
        if how == "raises":
            raise KeyboardInterrupt
        return 130

    monkeypatch.setattr("difffilter.train.cli.main", fit)
    out = tmp_path / "out"
    try:
        code = sweep.main(["--config", str(config), "--seeds", "0", "1", "--out", str(out),
                           "--no-progress"])  # fmt: skip
    except KeyboardInterrupt:  # (a traceback of the console script; here, pytest's own stop)
        pytest.fail("the interrupt escaped difffilter-train sweep")
    assert code == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("difffilter-train sweep: interrupted: ")
    assert "rerun the same command" in err[0]
    assert not (out / "runs" / "net" / "seed_0" / sweep._SETTINGS).exists()
