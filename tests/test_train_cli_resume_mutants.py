"""A mutation review of the Lightning side of ``difffilter-train``
(``difffilter.train.lightning_cli``, ``difffilter.train.last_checkpoint``,
``difffilter.train.common``): each test checks what a user sees (files on disk after a tiny
fit, TensorBoard events read back with EventAccumulator, a resumed run's weights against an
uninterrupted one's, seeds against the docstrings' formulas computed by hand), never the
code under test against itself."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import lightning.pytorch as pl
import numpy as np
import pytest
import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from test_last_checkpoint import _Worsening  # one weight pulled to 1, two batches
from torch.utils.data import DataLoader, TensorDataset

from difffilter.train import common, lightning_cli
from difffilter.train.cli import main
from difffilter.train.last_checkpoint import add_last_every_epoch

ROOT = Path(__file__).resolve().parents[1]
SMALL = [
    "--config", str(ROOT / "train" / "configs" / "four_tank.yaml"),
    "--data.init_args.batch_size=2", "--data.init_args.batches_per_epoch=2",
    "--data.init_args.val_runs=4", "--data.init_args.steps=20",
    "--model.init_args.hidden=4", "--model.init_args.num_particles=20",
    "--trainer.enable_progress_bar=false", "--trainer.log_every_n_steps=1",
]  # fmt: skip


# --- common.py ------------------------------------------------------------------------


def test_dtype_names_and_train_seed_follow_their_docstrings():
    """``dtype_of``: the two names → torch dtypes, anything else a ValueError naming the
    setting; ``train_seed_of(s) = 1 + 10 s`` evaluated by hand (never 0 or 2)."""
    assert common.dtype_of("float32") is torch.float32
    assert common.dtype_of("float64") is torch.float64
    for bad in ("float16", "Float32", "double"):
        with pytest.raises(ValueError, match=r"dtype must be one of \['float32', 'float64'\]"):
            common.dtype_of(bad)
    assert [common.train_seed_of(s) for s in (0, 1, 7, 12)] == [1, 11, 71, 121]


def test_mix_seed_is_seed_sequence_state_shifted_right_by_one():
    """The docstring's formula by hand: numpy's SeedSequence of the parts in order, its first
    64-bit word, halved (integer division) to 63 bits."""
    for parts in ((3,), (5, 1, 2), (2**40, 0, 9)):
        word = np.random.SeedSequence(list(parts)).generate_state(1, np.uint64)[0]
        assert common.mix_seed(*parts) == int(word) // 2
    assert common.mix_seed(5, 1, 2) != common.mix_seed(5, 2, 1)


def test_an_exported_checkpoint_goes_to_a_new_ckpt_file_only(tmp_path):
    """``check_checkpoint_out``: a folder, another suffix, an existing file or card is refused
    unless ``force``; the source itself only with ``force``; the folder is made."""
    check = common.check_checkpoint_out
    with pytest.raises(ValueError, match="is a folder"):
        check(tmp_path, force=True)
    with pytest.raises(ValueError, match=r"--out must name a \.ckpt file"):
        check(tmp_path / "x.pt", force=True)
    out = tmp_path / "deep" / "er" / "x.ckpt"
    check(out, force=False)
    assert out.parent.is_dir()  # made before any work
    out.with_suffix(".json").write_text("{}")  # a card alone is enough to refuse
    with pytest.raises(ValueError, match=r"x\.json exists; pass --force"):
        check(out, force=False)
    check(out, force=True)
    out.with_suffix(".json").unlink()
    out.write_bytes(b"")
    with pytest.raises(ValueError, match=r"x\.ckpt exists; pass --force"):
        check(out, force=False)
    with pytest.raises(ValueError, match="is the source itself"):
        check(out, force=False, replacing=out)
    check(out, force=True, replacing=out)


# --- lightning_cli.py: config checks, seeds, folders --------------------------------------


def test_seed_everything_fills_only_the_unset_seeds():
    """``_seeds_from_seed_everything``: ``model_seed = s`` and ``train_seed = 1 + 10 s``
    where they are ``None``; a given seed, an absent key, ``seed_everything: false`` and a
    config without subcommand as documented."""
    fill = lightning_cli._seeds_from_seed_everything
    cfg = {"seed_everything": 4, "model": {"class_path": "M", "init_args": {"model_seed": None}},
           "data": {"class_path": "D", "init_args": {"train_seed": None, "val_seed": None}}}  # fmt: skip
    fill({"fit": cfg}, "fit")
    assert cfg["model"]["init_args"] == {"model_seed": 4}
    assert cfg["data"]["init_args"] == {"train_seed": 41, "val_seed": None}
    given = {"seed_everything": 4, "model": {"model_seed": 3}, "data": {"val_seed": None}}
    fill(given, None)  # no subcommand: the config itself; not in subclass mode
    assert given["model"] == {"model_seed": 3} and given["data"] == {"val_seed": None}
    off = {"seed_everything": True, "model": {"model_seed": None}, "data": {"train_seed": None}}
    fill(off, None)  # a bool is no seed
    assert off["model"]["model_seed"] is None and off["data"]["train_seed"] is None


def test_the_config_checks_refuse_mixed_scenarios_dtypes_and_precisions():
    """``_check_config``: the model's and data's scenario or dtype differing, and a mixed
    precision, are refused; the true precisions pass."""
    check = lightning_cli._check_config

    def cfg(model, data, precision=None, ckpt=None):
        return {"model": {"class_path": "M", "init_args": model},
                "data": {"class_path": "D", "init_args": data},
                "trainer": {"precision": precision}, "ckpt_path": ckpt}  # fmt: skip

    check({"fit": cfg({"scenario": "a", "dtype": "float64"}, {"scenario": "a"})}, "fit")
    with pytest.raises(ValueError, match=r"the model's dtype \('float64'\) and the data's "
                       r"\('float32'\) differ: give both"):  # fmt: skip
        check({"fit": cfg({"dtype": "float64"}, {"dtype": "float32"})}, "fit")
    with pytest.raises(ValueError, match=r"scenario .* differ \(the model's from --ckpt_path\)"):
        check(cfg({"scenario": "a"}, {"scenario": "b"}, ckpt="x.ckpt"), None)
    for ok in (None, 32, 64, "32", "64", "32-true", "64-true"):
        check(cfg({}, {}, ok), None)
    for bad in (16, "16-mixed", "bf16-mixed", "bf16-true", "transformer-engine"):
        with pytest.raises(ValueError, match=f"--trainer.precision {bad}: "):
            check(cfg({}, {}, bad), None)


def test_ckpt_path_values_and_config_files_are_read_in_both_spellings(tmp_path, monkeypatch):
    """``_ckpt_paths_in``: ``--ckpt_path=x`` and ``--ckpt_path x``, a trailing flag without
    value ignored; ``_check_config_files`` checks every ``--config``/``-c`` spelling."""
    assert lightning_cli._ckpt_paths_in(["--ckpt_path=a", "--ckpt_path", "b", "--ckpt_path"]) == [
        "a",
        "b",
    ]
    assert lightning_cli._ckpt_paths_in(None) == []
    seen = []
    monkeypatch.setattr(lightning_cli, "check_config_keys", lambda p: seen.append(p.name))
    names = ["a.yaml", "b.yaml", "c.yaml", "d.yaml"]
    for name in names:
        (tmp_path / name).write_text("x: 1\n")
    p = [str(tmp_path / n) for n in names]
    lightning_cli._check_config_files([f"--config={p[0]}", f"-c={p[1]}", "--config", p[2],
                                       "-c", p[3], "-c"])  # fmt: skip
    assert sorted(seen) == names


def test_ckpt_path_kinds_and_the_judges_that_need_one(tmp_path):
    """``_check_ckpt_path``: none for ``validate``/``test``/``predict`` refused (``fit``
    and no subcommand pass), a folder named with (at most three of) the checkpoints it
    holds, a file torch cannot load, a missing file and a dict of neither kind refused; a
    name Lightning resolves is its own (``last``)."""
    check = lightning_cli._check_ckpt_path
    for judge, verb in (("validate", "validate"), ("test", "test"), ("predict", "predict with")):
        with pytest.raises(ValueError, match=f"{judge} needs the weights to {verb}: "):
            check({"ckpt_path": None}, judge)
    assert check({"ckpt_path": None}, "fit") is None and check({}, None) is None
    assert check({"ckpt_path": "last"}, "test") is None
    with pytest.raises(
        ValueError,
        match=r"--ckpt_path: no checkpoint file at .*nope\.ckpt; a "
        r"training run's Lightning checkpoint",
    ):
        check({"ckpt_path": str(tmp_path / "nope.ckpt")}, "fit")  # (before any run folder)
    folder = tmp_path / "run"
    (folder / "checkpoints").mkdir(parents=True)
    for name in "abcd":
        (folder / "checkpoints" / f"{name}.ckpt").write_bytes(b"")
    with pytest.raises(ValueError, match=r"is a folder; give a checkpoint file \(it holds "
                       r".*a\.ckpt, .*b\.ckpt, .*c\.ckpt, …\)$"):  # fmt: skip
        check({"ckpt_path": str(folder)}, "fit")
    (tmp_path / "junk.ckpt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="no checkpoint torch can load with weights_only"):
        check({"ckpt_path": str(tmp_path / "junk.ckpt")}, "fit")
    torch.save({"weights": torch.zeros(1)}, tmp_path / "plain.ckpt")
    with pytest.raises(ValueError, match=r"neither .* \(a dict of torch.save"):
        check({"ckpt_path": str(tmp_path / "plain.ckpt")}, "fit")


def test_a_checkpoint_rewritten_in_place_is_read_again(tmp_path):
    """``_kind_of_file`` is cached per version of the file: the same name rewritten from an
    exported-looking dict to junk (other size and time) is judged again, not by the cache."""
    import os

    path = tmp_path / "x.ckpt"
    torch.save({"weights": torch.zeros(1)}, path)
    os.utime(path, ns=(10**18, 10**18))
    with pytest.raises(ValueError, match="neither"):
        lightning_cli._check_ckpt_path({"ckpt_path": str(path)}, "fit")
    path.write_bytes(b"junk")
    os.utime(path, ns=(2 * 10**18, 2 * 10**18))
    with pytest.raises(ValueError, match="no checkpoint torch can load"):
        lightning_cli._check_ckpt_path({"ckpt_path": str(path)}, "fit")


def test_the_source_is_recognised_under_another_spelling(tmp_path, monkeypatch):
    """``check_checkpoint_out(replacing=…)``: ``x.ckpt`` and ``/abs/…/x.ckpt`` are one file
    (the in-place rewrite needs ``--force``, not a 'exists' error naming the card)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "x.ckpt").write_bytes(b"")
    with pytest.raises(ValueError, match="is the source itself"):
        common.check_checkpoint_out(Path("x.ckpt"), force=False, replacing=tmp_path / "x.ckpt")


def _fit_cli(ckpt, logger, **trainer):
    return SimpleNamespace(subcommand="fit", config={"fit": {"ckpt_path": ckpt, "trainer": {
        "logger": logger, **trainer}}})  # fmt: skip


def test_a_resume_takes_its_runs_version_only_from_its_own_save_dir_and_name(
    tmp_path, monkeypatch
):  # fmt: skip
    """``before_instantiate_classes``: a relative ``save_dir`` becomes absolute, a checkpoint
    at ``<save_dir>/<name>/version_3/checkpoints/x.ckpt`` sets version 3 (relative
    ``save_dir`` resolved from the working folder), and none of another save_dir, another
    layout or an explicit version; ``--trainer.logger false`` needs a folder."""
    monkeypatch.chdir(tmp_path)
    # (the paths name no file: the check of the file itself, which refuses a missing one)
    monkeypatch.setattr(lightning_cli, "_check_ckpt_path", lambda cfg, subcommand: "lightning")
    before = lightning_cli.DifffilterCLI.before_instantiate_classes
    ckpt = tmp_path / "logs" / "mass" / "version_3" / "checkpoints" / "last.ckpt"
    cases = (
        ({"save_dir": "logs", "name": "mass"}, ckpt, 3),
        ({"save_dir": str(tmp_path / "other"), "name": "mass"}, ckpt, None),
        ({"save_dir": "logs", "name": "mass", "version": 7}, ckpt, 7),
        ({"save_dir": "logs", "name": "mass"}, ckpt.parent.parent / "ckpts" / "last.ckpt", None),
        ({"save_dir": "logs", "name": "mass"}, ckpt.parent.parent.parent / "v3" / "checkpoints"
         / "last.ckpt", None),
    )  # fmt: skip
    for args, path, version in cases:
        cli = _fit_cli(str(path), {"init_args": dict(args)})
        before(cli)
        got = cli.config["fit"]["trainer"]["logger"]["init_args"]
        assert got.get("version") == version, (args, path)
        assert Path(got["save_dir"]).is_absolute()
        assert Path(got["save_dir"]) == (tmp_path / args["save_dir"])
    with pytest.raises(ValueError, match="--trainer.logger false leaves the run no folder"):
        before(_fit_cli(None, False))
    before(_fit_cli(None, False, default_root_dir=str(tmp_path / "r")))
    before(_fit_cli(None, False, fast_dev_run=True))


@pytest.mark.parametrize("name", [None, "", "runs", "absent"])
def test_the_fixed_run_folder_is_where_tensorboard_logs(tmp_path, name):
    """The folder a fit with an explicit version writes into is TensorBoardLogger's own
    ``log_dir`` (the truth: Lightning's logger), a ``name`` of ``null`` or ``""`` included,
    which logs straight under ``save_dir`` (a review: read as ``lightning_logs`` there, a
    second fit of ``name: null, version: 0`` was not refused and replaced the first run)."""
    from lightning.pytorch.loggers import TensorBoardLogger

    from difffilter.train.lightning_cli import _fixed_run_folder

    args = {"save_dir": str(tmp_path), "version": 0}
    kwargs = {}
    if name != "absent":
        args["name"] = kwargs["name"] = name
    want = TensorBoardLogger(str(tmp_path), version=0, **kwargs).log_dir
    assert _fixed_run_folder({"trainer": {}}, {}, args) == Path(want)


def test_a_new_fit_names_the_newest_checkpoint_where_the_run_has_no_last(tmp_path):
    """``_refuse_a_used_run_folder``: without ``last.ckpt`` the advice names the newest
    checkpoint (by modification time, not by name)."""
    import os

    folder = tmp_path / "run"
    (folder / "checkpoints").mkdir(parents=True)
    newer, older = folder / "checkpoints" / "a.ckpt", folder / "checkpoints" / "b.ckpt"
    for path in (newer, older):  # training checkpoints (only those resume)
        torch.save({"pytorch-lightning_version": "2.6.0", "state_dict": {}}, path)
    os.utime(older, ns=(10**18, 10**18))
    os.utime(newer, ns=(2 * 10**18, 2 * 10**18))
    with pytest.raises(ValueError, match=r"resume it with --ckpt_path .*a\.ckpt, or give"):
        lightning_cli._refuse_a_used_run_folder(folder)


def test_validate_test_and_predict_log_apart_from_a_fit_runs_folder(tmp_path):
    """``_log_apart_from_a_fit_run``: a version naming a folder with checkpoints is dropped
    (the logger's next free one), one naming an empty folder kept; a logger-less run and a
    logger list untouched."""
    run = tmp_path / "mass" / "version_2"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "best.ckpt").write_bytes(b"")
    (tmp_path / "mass" / "fresh").mkdir()
    for version, kept in ((2, False), ("version_2", False), ("fresh", True), (5, True)):
        args = {"save_dir": str(tmp_path), "name": "mass", "version": version}
        lightning_cli._log_apart_from_a_fit_run({"trainer": {"logger": {"init_args": args}}})
        assert args["version"] == (version if kept else None), version
    for logger in (False, [{"init_args": {}}], None):
        lightning_cli._log_apart_from_a_fit_run({"trainer": {"logger": logger}})


def test_each_stage_writes_its_own_config_file_name(monkeypatch):
    """``_SaveConfigOfItsStage``: ``config.yaml`` for ``fit``, ``config_<stage>.yaml``
    otherwise (a TrainerFn by its value), ``<name>_<stage>`` for a name without a dot."""
    from lightning.pytorch.cli import SaveConfigCallback
    from lightning.pytorch.trainer.states import TrainerFn

    names = []
    monkeypatch.setattr(SaveConfigCallback, "setup",
                        lambda self, *a: names.append(self.config_filename))  # fmt: skip
    cls = lightning_cli._SaveConfigOfItsStage
    for stage, filename in (("fit", "config.yaml"), (TrainerFn.FITTING, "config.yaml"),
                            ("validate", "config.yaml"), (TrainerFn.TESTING, "config.yaml"),
                            ("predict", "run.config.yml"), ("test", "config")):  # fmt: skip
        cls(None, None, config_filename=filename).setup(None, None, stage)
    assert names == ["config.yaml", "config.yaml", "config_validate.yaml", "config_test.yaml",
                     "run.config_predict.yml", "config_test"]  # fmt: skip


def test_a_user_error_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    """``run``: a ValueError of the checks (logger false without a folder) is one line on
    stderr, ``difffilter-train: error: …``, exit 2; a ``test`` without ``--ckpt_path`` too."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    assert main(["fit", *SMALL, "--trainer.logger=false"]) == 2
    assert main(["test", *SMALL]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(e.startswith("difffilter-train: error: ") for e in err)
    assert "--trainer.logger false" in err[0] and "test needs the weights" in err[1]
    assert not (tmp_path / "lightning_logs").exists() and not (tmp_path / "checkpoints").exists()


# --- TensorBoard purge of the interrupted events -----------------------------------------


def _steps_written(folder: Path, tag: str) -> list[int]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    return [e.step for e in EventAccumulator(str(folder)).Reload().Scalars(tag)]


def test_a_resume_into_its_own_folder_purges_the_interrupted_steps(tmp_path):
    """``_hide_the_interrupted_events`` against TensorBoard itself: an interrupted process
    logged steps 0..5, the checkpoint counts 3 stepped batches (and 30 optimizer steps: the
    curves' steps are the batches), the resumed process logs
    3..6: read back, each step once. Another folder's checkpoint, a user's own
    ``purge_step`` and a started writer are left alone."""
    from lightning.pytorch.loggers import TensorBoardLogger

    def logger(**kw):
        return TensorBoardLogger(str(tmp_path), name="mass", version=0, **kw)

    first = logger()
    for step in range(6):
        first.log_metrics({"loss": float(step)}, step=step)
    first.finalize("success")
    run = Path(first.log_dir)
    ckpt = run / "checkpoints" / "last.ckpt"
    ckpt.parent.mkdir()
    state = {"epoch_loop.state_dict": {"_batches_that_stepped": 3}}
    # (an EKF trainer steps its optimizer once a time step: 30 steps for 3 logged batches)
    torch.save({"global_step": 30, "loops": {"fit_loop": state}}, ckpt)
    elsewhere = tmp_path / "x" / "checkpoints" / "last.ckpt"
    elsewhere.parent.mkdir(parents=True)
    torch.save({"loops": {"fit_loop": state}}, elsewhere)
    hide = lightning_cli._hide_the_interrupted_events

    other = logger(purge_step=None)
    hide(SimpleNamespace(logger=other), str(elsewhere))
    assert other._kwargs["purge_step"] is None  # another folder's checkpoint
    own = logger(purge_step=5)
    hide(SimpleNamespace(logger=own), str(ckpt))
    assert own._kwargs["purge_step"] == 5  # the user's own kept
    started = logger(purge_step=None)
    started.experiment  # noqa: B018 (the writer exists: too late)
    hide(SimpleNamespace(logger=started), str(ckpt))
    assert started._kwargs["purge_step"] is None
    started.finalize("success")

    resumed = logger(purge_step=None)
    hide(SimpleNamespace(logger=resumed), str(ckpt))
    for step in range(3, 7):
        resumed.log_metrics({"loss": 10.0 + step}, step=step)
    resumed.finalize("success")
    assert _steps_written(run, "loss") == list(range(7))


# --- last.ckpt every whole epoch ----------------------------------------------------------


def _trainer(folder, **kwargs):
    best = ModelCheckpoint(dirpath=folder, monitor="val/metric", mode="min", save_last=True,
                           filename="best-{epoch:02d}")  # fmt: skip
    trainer = pl.Trainer(callbacks=[best], logger=False, enable_progress_bar=False,
                         enable_model_summary=False, accelerator="cpu", devices=1,
                         **{"num_sanity_val_steps": 0, **kwargs})  # fmt: skip
    add_last_every_epoch(trainer)
    return trainer


def _sgd_by_hand(targets):
    """The weight after SGD (lr 0.1) on (w − target)² from w = 0, one step per target."""
    w = 0.0
    for target in targets:
        w -= 0.1 * 2 * (w - target)
    return w


def _saved(path):
    return torch.load(path, map_location="cpu", weights_only=True)


def test_last_follows_the_epochs_without_validation_too(tmp_path):
    """Validation every second epoch: ``last.ckpt`` still holds the epoch reached (2 of
    0..2, its 6 steps) and the weight SGD gives by hand: w ← w − 0.1·2(w − 1), six times."""
    _trainer(tmp_path, max_epochs=3, check_val_every_n_epoch=2).fit(_Worsening())
    last = _saved(tmp_path / "last.ckpt")
    assert last["epoch"] == 2 and last["global_step"] == 6
    assert last["state_dict"]["w"].item() == pytest.approx(_sgd_by_hand([1.0] * 6), rel=1e-6)


@pytest.mark.parametrize("sanity", [0, 1])
def test_a_cut_first_epoch_leaves_no_last_checkpoint(tmp_path, sanity):
    """``max_steps`` ending the first epoch after one of its two batches: no whole epoch, so
    no ``last.ckpt`` to resume from (a resume from it skipped the epoch's second batch),
    whether or not a sanity check validated first (its validation is no epoch's end)."""
    trainer = _trainer(tmp_path, max_epochs=3, max_steps=1, num_sanity_val_steps=sanity)
    trainer.fit(_Worsening())
    assert trainer.global_step == 1
    assert not (tmp_path / "last.ckpt").exists()


class _Stream(torch.utils.data.IterableDataset):
    """Two batches of ones, no ``__len__``: Lightning counts an epoch of ``inf`` batches."""

    def __iter__(self):
        return iter([torch.ones(1), torch.ones(1)])


class _Streaming(_Worsening):
    def train_dataloader(self):
        return DataLoader(_Stream(), batch_size=None)


def test_an_epoch_of_unknown_length_is_a_whole_epoch(tmp_path):
    """An iterable dataset without length (``num_training_batches`` is ``inf``): each epoch
    runs to its end, so ``last.ckpt`` follows it (epoch 1, four SGD steps by hand)."""
    _trainer(tmp_path, max_epochs=2).fit(_Streaming())
    last = _saved(tmp_path / "last.ckpt")
    assert last["epoch"] == 1 and last["global_step"] == 4
    assert last["state_dict"]["w"].item() == pytest.approx(_sgd_by_hand([1.0] * 4), rel=1e-6)


def test_a_validation_outside_fit_writes_no_last_checkpoint(tmp_path):
    """``trainer.validate`` on a trainer that carries the callback ends no training epoch:
    no ``last.ckpt`` appears."""
    _trainer(tmp_path).validate(_Worsening(), verbose=False)
    assert not (tmp_path / "last.ckpt").exists()


def test_a_cut_epoch_keeps_the_last_whole_epochs_file(tmp_path):
    """Cut in epoch 2 (``max_steps=5``) after a resume from epoch 1: ``last.ckpt`` still
    says epoch 1, step 4, with the weight of four SGD steps by hand, not of five."""
    _trainer(tmp_path, max_epochs=2).fit(_Worsening())
    again = _trainer(tmp_path, max_epochs=4, max_steps=5)
    again.fit(_Worsening(), ckpt_path=tmp_path / "last.ckpt")
    assert again.global_step == 5
    last = _saved(tmp_path / "last.ckpt")
    assert last["epoch"] == 1 and last["global_step"] == 4
    assert last["state_dict"]["w"].item() == pytest.approx(_sgd_by_hand([1.0] * 4), rel=1e-6)


class _TwoBatches(_Worsening):
    """Batches 1 and 3: the order of the SGD steps matters, so a resume that skips or
    repeats a batch ends at another weight."""

    def train_dataloader(self):
        return DataLoader(TensorDataset(torch.tensor([[1.0], [3.0]])), batch_size=1)


class _Improving(_TwoBatches):
    """Its validation metric improves at every validation: the checkpoint callback writes
    ``last.ckpt`` itself at each, inside the epoch too."""

    def validation_step(self, batch, batch_idx):
        self.log("val/metric", -float(self.global_step))


def _crashing(cls):
    class Crashing(cls):
        def training_step(self, batch, batch_idx):
            if self.current_epoch == 1 and batch_idx == 1:
                raise RuntimeError("crash in epoch 1")
            return super().training_step(batch, batch_idx)

    return Crashing


def _w_by_hand(steps):
    return _sgd_by_hand([1.0, 3.0] * (steps // 2))


@pytest.mark.parametrize("cls", [_TwoBatches, _Improving])
def test_a_validation_inside_the_epoch_leaves_last_at_the_last_whole_epoch(tmp_path, cls):
    """A review: with ``val_check_interval=0.5`` the callback wrote ``last.ckpt`` at the
    validation inside the epoch, and a crash after it left part of an epoch there (a
    resume reached w 1.30 against the uninterrupted 1.56); where the metric improves the
    checkpoint callback writes it there itself. After a crash in epoch 1 the file holds
    epoch 0 (two SGD steps by hand), and the resume ends at the uninterrupted run's weight
    (six steps by hand, batches 1, 3 in order)."""
    with pytest.raises(RuntimeError, match="crash in epoch 1"):
        _trainer(tmp_path, max_epochs=3, val_check_interval=0.5).fit(_crashing(cls)())
    last = _saved(tmp_path / "last.ckpt")
    assert last["epoch"] == 0 and last["global_step"] == 2
    assert last["state_dict"]["w"].item() == pytest.approx(_w_by_hand(2), rel=1e-6)
    resumed = cls()
    _trainer(tmp_path, max_epochs=3, val_check_interval=0.5).fit(
        resumed, ckpt_path=tmp_path / "last.ckpt"
    )
    assert resumed.w.item() == pytest.approx(_w_by_hand(6), rel=1e-6)


def test_a_crash_before_the_first_epoch_leaves_a_resumed_runs_file_alone(tmp_path):
    """A resume that fails in its sanity check, before any epoch began, keeps the
    ``last.ckpt`` it was given, byte for byte."""
    _trainer(tmp_path, max_epochs=1).fit(_TwoBatches())
    before = (tmp_path / "last.ckpt").read_bytes()

    class FailsToValidate(_TwoBatches):
        def validation_step(self, batch, batch_idx):
            raise RuntimeError("no validation")

    with pytest.raises(RuntimeError, match="no validation"):
        _trainer(tmp_path, max_epochs=2, num_sanity_val_steps=1).fit(
            FailsToValidate(), ckpt_path=tmp_path / "last.ckpt"
        )
    assert (tmp_path / "last.ckpt").read_bytes() == before


# --- a tiny fit through the command -----------------------------------------------------


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Three tiny four-tank fits of two batches an epoch: one of two epochs, one of one epoch
    resumed to two from its ``last.ckpt`` (in another folder), and a ``validate`` of the
    resumed run's best checkpoint with its ``config.yaml``."""
    mp = pytest.MonkeyPatch()
    root = tmp_path_factory.mktemp("runs")
    try:
        mp.setattr("sys.argv", ["difffilter-train"])
        for name, epochs in (("whole", 2), ("cut", 1)):
            (root / name).mkdir()
            mp.chdir(root / name)
            assert main(["fit", *SMALL, f"--trainer.max_epochs={epochs}"]) == 0
        cut = root / "cut" / "lightning_logs" / "four_tank_nn_grad" / "version_0"
        assert main(["fit", *SMALL, "--trainer.max_epochs=2",
                     f"--ckpt_path={cut / 'checkpoints' / 'last.ckpt'}"]) == 0  # fmt: skip
        whole = root / "whole" / "lightning_logs" / "four_tank_nn_grad" / "version_0"
        config_before = (cut / "config.yaml").read_text()
        best = next((cut / "checkpoints").glob("best*.ckpt"))
        assert main(["validate", "--config", str(cut / "config.yaml"),
                     f"--ckpt_path={best}"]) == 0  # fmt: skip
        yield SimpleNamespace(whole=whole, cut=cut, config_before=config_before)
    finally:
        mp.undo()


def test_a_fit_leaves_its_run_folder_as_documented(runs):
    """On disk after a 2-epoch fit: ``config.yaml``, the export and its card, and
    ``checkpoints/`` with ``last.ckpt`` at the last epoch (1) after 4 batches and a best."""
    names = sorted(p.name for p in runs.whole.iterdir() if not p.name.startswith("events"))
    assert names == ["checkpoints", "config.yaml", "four_tank_nn_grad.ckpt",
                     "four_tank_nn_grad.json", "hparams.yaml"]  # fmt: skip
    last = _saved(runs.whole / "checkpoints" / "last.ckpt")
    assert last["epoch"] == 1 and last["global_step"] == 4
    assert any(p.name.startswith("best") for p in (runs.whole / "checkpoints").iterdir())


def test_a_resumed_run_trains_the_uninterrupted_runs_weights_in_its_own_folder(runs):
    """Resumed from epoch 0's ``last.ckpt``, the run logs into its own ``version_0`` (the
    later ``version_1`` is the validate's) and ends with the uninterrupted run's weights,
    bit for bit."""
    assert sorted(p.name for p in runs.cut.parent.iterdir()) == ["version_0", "version_1"]
    a = _saved(runs.whole / "checkpoints" / "last.ckpt")["state_dict"]
    b = _saved(runs.cut / "checkpoints" / "last.ckpt")["state_dict"]
    assert sorted(a) == sorted(b)
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert _steps_written(runs.cut, "train/loss") == [0, 1, 2, 3]


def test_validate_of_a_resumed_runs_config_logs_apart_and_writes_config_validate(runs):
    """``validate --config <run>/config.yaml`` of a resumed run (whose config pins its
    version 0): a new ``version_1`` holding ``config_validate.yaml`` and no checkpoints; the
    run's ``config.yaml`` unchanged."""
    assert "version: 0" in runs.config_before  # the premise: the resume pinned it
    assert (runs.cut / "config.yaml").read_text() == runs.config_before
    assert not (runs.cut / "config_validate.yaml").exists()
    other = runs.cut.parent / "version_1"
    assert (other / "config_validate.yaml").is_file()
    assert not (other / "checkpoints").exists() and not (other / "config.yaml").exists()
