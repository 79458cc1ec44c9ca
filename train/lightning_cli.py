"""The Lightning side of ``difffilter-train``: :class:`DifffilterCLI` (LightningCLI) and
:func:`run`, which runs ``fit``, ``validate``, ``test`` and ``predict`` with one-line
errors. :mod:`difffilter.train.cli` dispatches here (and answers ``--help`` without
importing Lightning)."""

from __future__ import annotations

import functools
import re
import sys
from pathlib import Path

import lightning.pytorch as pl
import torch
from lightning.pytorch.cli import LightningCLI, SaveConfigCallback

from difffilter.runtime import tune_cpu_allocator
from difffilter.train.common import check_config_keys, jsonargparse_yaml_loader, train_seed_of
from difffilter.train.last_checkpoint import add_last_every_epoch

__all__ = ["DifffilterCLI", "run"]


class _SaveConfigOfItsStage(SaveConfigCallback):
    """``config.yaml`` is the ``fit``'s: another subcommand writes ``config_<stage>.yaml``
    in the folder it logs to (its own, :func:`_log_apart_from_a_fit_run`; a ``test
    --config <run>/config.yaml`` of a run's best checkpoint had rewritten the run's
    ``config.yaml`` as its own, ``verbose: true`` and all, and the README's resume from it
    then failed: "Subcommand 'fit' does not accept option 'verbose'")."""

    def setup(self, trainer, pl_module, stage: str) -> None:
        name = getattr(stage, "value", stage)  # (a TrainerFn: formatted, 'TrainerFn.TESTING')
        if name != "fit":
            stem, dot, ext = self.config_filename.rpartition(".")
            self.config_filename = f"{stem}_{name}{dot}{ext}" if dot else f"{ext}_{name}"
        super().setup(trainer, pl_module, stage)


class DifffilterCLI(LightningCLI):
    """LightningCLI whose ``validate``, ``test`` and ``predict`` also take an exported
    estimator file (``difffilter-train export``, ``checkpoints/*.ckpt``) as ``--ckpt_path``:
    its weights are loaded into the configured module, whose estimator settings must match."""

    def _set_seed(self) -> None:
        """Lightning's seeding, after a check that names the option (a docs trial:
        ``--seed_everything -1`` said only "-1 is not in bounds, numpy accepts from 0 to
        4294967295", where the other commands say ``--seed must be an integer >= 0``)."""
        cfg = self.config[self.subcommand] if self.subcommand else self.config
        seed = cfg.get("seed_everything")
        if not isinstance(seed, bool) and isinstance(seed, int) and not 0 <= seed < 2**32:
            raise ValueError(
                f"--seed_everything must be an integer from 0 to {2**32 - 1} (or true: a "
                f"random seed; false: none); got {seed}"
            )
        super()._set_seed()

    def before_instantiate_classes(self):
        """``fit`` logs under an absolute ``save_dir`` (the checkpoints then record absolute
        paths: a run resumed from another folder found its best checkpoint by a path
        relative to the first run's folder, and exported another run's network or failed),
        and resuming from ``<save_dir>/<name>/version_<n>/checkpoints/*.ckpt`` logs into
        that same ``version_<n>`` (TensorBoard curves continue) instead of a new folder.
        Every subcommand: ``seed_everything`` seeds the network and the training batches
        where the config leaves ``model_seed`` or ``train_seed`` unset
        (:func:`_seeds_from_seed_everything`)."""
        _seeds_from_seed_everything(self.config, self.subcommand)
        _check_config(self.config, self.subcommand)
        kind = _check_ckpt_path(self.config[self.subcommand] if self.subcommand else self.config,
                                self.subcommand)  # fmt: skip
        if self.subcommand:
            _refuse_a_name_with_nothing_behind(self.config[self.subcommand], self.subcommand)
        if self.subcommand in ("validate", "test", "predict"):
            _log_apart_from_a_fit_run(self.config[self.subcommand])
        if self.subcommand != "fit":
            return
        cfg = self.config["fit"]
        ckpt, logger = cfg.get("ckpt_path"), cfg["trainer"].get("logger")
        if logger is False and not cfg["trainer"].get("fast_dev_run"):
            if not cfg["trainer"].get("default_root_dir"):
                # (a trial: two runs wrote ./<name>.ckpt, the second replacing the first, and
                # Lightning's checkpoints went to ./checkpoints/, the shipped files' folder
                # when run from the repository)
                raise ValueError(
                    "--trainer.logger false leaves the run no folder of its own: its "
                    "checkpoints and export would go to the working folder (./checkpoints/ and "
                    "./<estimator>.ckpt, replacing an earlier run's); give "
                    "--trainer.default_root_dir DIR, or keep the logger"
                )
        if ckpt:
            if kind == "exported":
                raise ValueError(
                    f"--ckpt_path: {ckpt} is an exported estimator (weights only), not a "
                    "training run's Lightning checkpoint to resume; start a training from its "
                    "weights with --model.init_args.init_from"
                )
        args = _logger_args(logger)
        if not ckpt and not cfg["trainer"].get("fast_dev_run"):
            _refuse_a_used_run_folder(_fixed_run_folder(cfg, logger, args))
        if args is None:
            return
        if args.get("save_dir"):
            args["save_dir"] = str(Path(args["save_dir"]).resolve())
        if not ckpt:
            return
        path = Path(ckpt).resolve()
        run = path.parent.parent  # .../version_<n>/checkpoints/x.ckpt → .../version_<n>
        # the same save_dir and name only: a checkpoint of another folder's run set this
        # run's version, and the resumed fit overwrote that version's export and card here
        if (
            path.parent.name == "checkpoints"
            and run.name.startswith("version_")
            and args.get("version") is None
            and run.parent == _runs_folder(args).resolve()
        ):
            args["version"] = int(run.name.removeprefix("version_"))

    def _parse_ckpt_path(self) -> None:
        """Lightning (from 2.5.5) reads a Lightning ``--ckpt_path``'s model settings into the
        config before any hook, so a resumed ``fit`` (or a ``test`` of that checkpoint) ran
        with the checkpoint's settings where the command gave others, without a word, and
        :func:`_check_resumed_settings` compared the checkpoint with itself (a training
        trial: ``--model.init_args.hidden 32 --model.init_args.filter ukf`` on resume kept 16
        and ekf; ``test --model.init_args.restart 0.01`` scored the network without it):
        ``ValueError`` naming each model setting of the command (its config's, given or by
        default; unset ``None`` ones aside) that is not the checkpoint's, and, for ``fit``,
        a ``--seed_everything`` other than the one the network was seeded with. Lightning
        releases without this step (2.2 to 2.5.4) leave the config as the command gave it,
        and :func:`_check_resumed_settings` compares it."""
        parse = getattr(super(), "_parse_ckpt_path", None)
        subcommand = self.config.get("subcommand")
        if parse is None or not subcommand:
            return
        cfg = self.config[subcommand]
        given = _settings_given(cfg)
        parse()
        ckpt = cfg.get("ckpt_path")
        merged = _plain(_init_args(self.config[subcommand], "model") or {})
        changed = [f"--model.init_args.{key}: {merged.get(key)!r} → {value!r}"
                   for key, value in sorted(given.items())
                   if _in_order(merged.get(key)) != _in_order(value)]  # fmt: skip
        seed, trained = cfg.get("seed_everything"), merged.get("model_seed")
        if (subcommand == "fit" and isinstance(seed, int) and not isinstance(seed, bool)
                and trained is not None and "model_seed" not in given and seed != trained):  # fmt: skip
            # (the data's train_seed differs too, and the data check names that alone)
            changed.append(f"--seed_everything {seed}: the run's network was seeded {trained}")
        if changed:
            raise _settings_refused(
                ckpt, "this command's model settings are not the checkpoint's", changed,
                "Lightning would run the checkpoint's (each shown first); resume or score it "
                "with its own (the same command, or its run's config.yaml: --config "
                "<run>/config.yaml --ckpt_path …)",
            )  # fmt: skip

    def before_fit(self):
        """A ``fast_dev_run`` writes no checkpoint (its ``last.ckpt`` landed in
        ``./checkpoints/``, beside the shipped files); otherwise a checkpoint callback that
        keeps a ``last.ckpt`` keeps it at every epoch, not only at its improvements
        (:mod:`difffilter.train.last_checkpoint`): an interrupted run resumes where it was."""
        if self.trainer.fast_dev_run:
            for cb in self.trainer.checkpoint_callbacks:
                cb.save_last, cb.save_top_k = False, 0
            return
        _check_processes(self.trainer, getattr(self, "model", None))
        config = getattr(self, "config_init", None)
        ckpt = config["fit"].get("ckpt_path") if config is not None else None
        _check_resumed_settings(ckpt, getattr(self, "model", None),
                                getattr(self, "datamodule", None))  # fmt: skip
        _hide_the_interrupted_events(self.trainer, ckpt)
        _expect_no_validation_at_the_resumed_epochs_end(ckpt)
        add_last_every_epoch(self.trainer)

    def before_validate(self):
        self._load_exported("validate")

    def before_test(self):
        self._load_exported("test")

    def before_predict(self):
        """Load an exported file, and write what is predicted (a
        :class:`~difffilter.train.predictions.PredictionFiles` unless one is configured)."""
        from .predictions import PredictionFiles

        self._load_exported("predict")
        if not any(isinstance(cb, PredictionFiles) for cb in self.trainer.callbacks):
            self.trainer.callbacks.append(PredictionFiles())

    def _load_exported(self, subcommand: str) -> None:
        from difffilter.models.neural_estimator import load_estimator_checkpoint
        from difffilter.models.plant_match import training_plant_notes

        path = self.config_init[subcommand].get("ckpt_path")
        if not path or _check_ckpt_path({"ckpt_path": path}, None) != "exported":
            return  # a Lightning checkpoint: Lightning restores it
        mine = self.model.estimator
        dtype = next(mine.parameters()).dtype
        estimator, card = load_estimator_checkpoint(path, dtype=dtype)
        if estimator.config() != mine.config():
            family = self.model.card().scenario_family
            if card.scenario_family != family:  # (the settings alone did not say it)
                raise ValueError(
                    f"--ckpt_path: {path} is an estimator of the {card.scenario_family} family "
                    f"(trained on {card.scenario}); the config trains a {family} one: give "
                    f"a {family} checkpoint, or the {card.scenario_family} config"
                )
            theirs, ours = estimator.config(), mine.config()
            differ = "; ".join(f"{k} {theirs.get(k)!r} against {ours.get(k)!r}"
                               for k in sorted(theirs.keys() | ours.keys())
                               if theirs.get(k) != ours.get(k))  # fmt: skip
            raise ValueError(
                f"--ckpt_path: the network in {path} has other settings than the configured "
                f"model's ({differ}); pass the matching --config/--model.* options"
                f"{_trainer_hint(card, self.model.card())}"
            )
        self.model.check_exported(card, path)  # the filter it was trained for
        # another plant of its family, or its training plant edited since: said, as
        # difffilter-eval says it (a test on another plant had logged its scores unsaid)
        for line in training_plant_notes([(str(path), Path(path))], [self.model.scenario.name],
                                         flag="--ckpt_path"):  # fmt: skip
            print(line, file=sys.stderr)
        mine.load_state_dict(estimator.state_dict())
        self.config_init[subcommand]["ckpt_path"] = None  # weights are in; nothing to restore
        print(f"loaded the exported estimator {path}")


#: What ``validate``, ``test`` and ``predict`` do with the weights of ``--ckpt_path``.
_JUDGES = {"validate": "validate", "test": "test", "predict": "predict with"}


#: The ``--ckpt_path`` values Lightning resolves to a file itself.
_LIGHTNING_CKPT_NAMES = frozenset({"best", "last", "hpc"})


def _check_processes(trainer, model) -> None:
    """Training on several processes (``--trainer.strategy ddp --trainer.devices 2``) keeps
    one network: its gradients are averaged, also where the loss leaves a parameter unused
    (the tracking network's attack head under ``attack_weight: 0``: DDP's reducer had
    waited for its gradient, the first step went unaveraged and the second died in
    Lightning's "parameters that were not used" error; a training trial), so such a
    parameter is left out of the average, as one process leaves it without a gradient. The
    EKF over the weights takes no gradient to average: each process would train a network
    of its own on its half of the batches (a trial: two digests after every epoch, the
    export process 0's), so it is refused on more than one process."""
    world = getattr(trainer, "world_size", 1)
    if world <= 1:
        return
    hparams = getattr(model, "hparams", {})
    if hparams.get("trainer") == "ekf":
        raise ValueError(
            f"--trainer.devices: the EKF over the weights (trainer: ekf) trains on one process "
            f"({world} asked): it updates the weights step by step from each batch, with no "
            "gradient for DDP to average, so every process would train a network of its own; "
            "drop --trainer.strategy/--trainer.devices, or train with trainer: grad"
        )
    from lightning.pytorch.strategies import DDPStrategy

    strategy = trainer.strategy
    kwargs = getattr(strategy, "_ddp_kwargs", None)  # (the DistributedDataParallel options)
    if isinstance(strategy, DDPStrategy) and isinstance(kwargs, dict):
        kwargs.setdefault("find_unused_parameters", True)


def _check_ckpt_path(cfg, subcommand: str | None) -> str | None:
    """``--ckpt_path`` read before any work: ``"exported"``, ``"lightning"`` or ``None``
    (none given, or a name Lightning resolves itself, e.g. ``last``). ``ValueError`` naming
    the option for a file torch cannot read with ``weights_only=True`` or one that is
    neither kind (both failed in Lightning with a traceback, the first advising an unsafe
    load, and left a run folder behind), and for ``validate``, ``test`` or ``predict``
    without one (they judged the configured network's initial weights, without a word)."""
    ckpt = cfg.get("ckpt_path")
    if not ckpt:
        if subcommand in _JUDGES:
            raise ValueError(
                f"--ckpt_path: {subcommand} needs the weights to {_JUDGES[subcommand]}: a "
                "training run's Lightning checkpoint (<run>/checkpoints/*.ckpt) or an exported "
                "estimator (checkpoints/*.ckpt); without one it would judge the configured "
                "network's initial weights"
            )
        return None
    path = Path(ckpt)
    if path.is_dir():  # (Lightning failed with an IsADirectoryError traceback)
        inside = sorted(str(p) for p in path.glob("**/*.ckpt"))[:3]
        raise ValueError(
            f"--ckpt_path: {ckpt} is a folder; give a checkpoint file"
            + (f" (it holds {', '.join(inside)}" + (", …)" if len(inside) == 3 else ")")
               if inside else "")
        )  # fmt: skip
    if not path.is_file():
        # the names Lightning resolves itself ("last", "best", …) and remote paths are its;
        # a missing local file is refused here, before any work (Lightning named it after the
        # run folder had been made: an empty run in TensorBoard at every try, a docs trial)
        if ckpt in _LIGHTNING_CKPT_NAMES or str(ckpt).startswith("registry") or "://" in ckpt:
            return None
        raise ValueError(
            f"--ckpt_path: no checkpoint file at {ckpt}; a training run's Lightning checkpoint "
            "(<run>/checkpoints/*.ckpt) or an exported estimator (checkpoints/*.ckpt) is "
            "expected (Lightning's names, last and hpc, read the run folder this command "
            "writes)"
        )
    kind, what = _kind_of(path)
    if kind is not None:
        return kind
    if what is None:  # (torch's own text advises weights_only=False, an arbitrary-code load)
        raise ValueError(
            f"--ckpt_path: {ckpt} is no checkpoint torch can load with weights_only=True; a "
            "training run's Lightning checkpoint or an exported estimator is expected"
        )
    raise ValueError(
        f"--ckpt_path: {ckpt} is neither a training run's Lightning checkpoint nor an exported "
        f"estimator (a {what} of torch.save without their keys)"
    )


def _kind_of(path: Path) -> tuple[str | None, str | None]:
    """:func:`_kind_of_file` of ``path``, read once per version of the file."""
    stat = path.stat()
    return _kind_of_file(str(path.resolve()), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=8)
def _kind_of_file(path: str, mtime_ns: int, size: int) -> tuple[str | None, str | None]:
    """``(checkpoint_kind, type name of what was loaded)`` of the file ``path``, ``(None,
    None)`` where torch cannot load it with ``weights_only=True``; read once per version of
    the file (the command line's check and the configuration's, before any hook, ask for
    the same file)."""
    import torch

    from difffilter.models.neural_estimator import checkpoint_kind

    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # unpickling errors come in many types
        return None, None
    return checkpoint_kind(blob), type(blob).__name__


def _values_of(argv, *options: str) -> list[str]:
    """The values of ``options`` in the command line ``argv``, in both spellings
    (``--option=value`` and ``--option value``)."""
    argv = list(argv or ())
    found = [a.split("=", 1)[1] for a in argv if a.startswith(tuple(f"{o}=" for o in options))]
    found += [argv[i + 1] for i, a in enumerate(argv[:-1]) if a in options]
    return found


def _ckpt_paths_in(argv) -> list[str]:
    """The values of ``--ckpt_path`` in the command line ``argv`` (both spellings)."""
    return _values_of(argv, "--ckpt_path")


def _hide_the_interrupted_events(trainer, ckpt) -> None:
    """A run resumed into its own folder from a checkpoint written after ``n`` training
    batches goes on at step ``n`` (Lightning's ``_batches_that_stepped``, plus one for a
    checkpoint written inside its epoch, before its last batch was counted): the TensorBoard
    events the interrupted process wrote from step ``n`` on (the cut epoch's points, which
    the resumed run logs again) are hidden, as
    ``SummaryWriter(purge_step=n)`` hides them; TensorBoard had drawn those points twice (a
    trial). Nothing for another logger, another folder, or a checkpoint without the count."""
    from lightning.pytorch.loggers import TensorBoardLogger

    logger = trainer.logger
    if not ckpt or not Path(ckpt).is_file() or not isinstance(logger, TensorBoardLogger):
        return
    kwargs = getattr(logger, "_kwargs", None)
    if getattr(logger, "_experiment", True) is not None or not isinstance(kwargs, dict):
        return  # (its writer exists already: too late to purge; or a Lightning without)
    if Path(logger.log_dir).resolve() != Path(ckpt).resolve().parent.parent:
        return
    loop = _fit_loop_state(ckpt)
    try:
        step = loop["epoch_loop.state_dict"]["_batches_that_stepped"]
    except (KeyError, TypeError):  # (a checkpoint of another layout: its curves as they are)
        return
    if _written_inside_its_epoch(loop):
        # (LastCheckpointEveryEpoch at the epoch's validation's end, in an epoch that did not
        # improve the monitored metric) before Lightning counted the batch that stepped last;
        # the resumed run counts it, and goes on at n + 1 (at n, the epoch's validation and
        # last training point were hidden: a trial)
        step += 1
    if kwargs.get("purge_step") is None:  # (the CLI passes an explicit None; a user's own kept)
        kwargs["purge_step"] = int(step)


def _fit_loop_state(ckpt) -> dict | None:
    """The ``fit_loop`` state of checkpoint ``ckpt``, or ``None`` (no file, another layout)."""
    try:
        blob = torch.load(ckpt, map_location="cpu", weights_only=True, mmap=True)
        return blob["loops"]["fit_loop"]
    except Exception:
        return None


def _written_inside_its_epoch(loop: dict | None) -> bool:
    """Whether a checkpoint's ``fit_loop`` state was saved before its epoch ended (its
    epoch started and not yet processed)."""
    epoch = (loop or {}).get("epoch_progress", {}).get("current", {})
    return epoch.get("processed", 0) < epoch.get("started", 0)


def _expect_no_validation_at_the_resumed_epochs_end(ckpt) -> None:
    """A run resumed from a checkpoint written inside its epoch (after its validation) first
    ends that epoch without validating again, and Lightning's ``ModelCheckpoint`` warns that
    it "could not find the monitored key … HINT: Did you call `log(...)`": a bug of the
    user's, it says, where there is none (a trial). That warning alone is left out; a key
    really never logged still fails, as Lightning raises once a validation has run."""
    if not ckpt or not Path(ckpt).is_file():
        return
    if _written_inside_its_epoch(_fit_loop_state(ckpt)):
        import warnings

        warnings.filterwarnings("ignore", r"`ModelCheckpoint\(monitor=.*\)` could not find the "
                                "monitored key")  # fmt: skip


def _fixed_run_folder(cfg, logger, args) -> Path | None:
    """The folder a ``fit`` writes its run into where the command fixes it (``--trainer.logger
    false`` with ``default_root_dir``; a logger given an explicit ``version``), else ``None``
    (the logger's next free ``version_<n>``)."""
    if logger is False:
        root = cfg["trainer"].get("default_root_dir")
        return Path(root) if root else None
    if args is None or args.get("version") is None:
        return None
    version = args["version"]
    folder = version if isinstance(version, str) else f"version_{version}"
    return _runs_folder(args) / folder


def _logger_args(logger):
    """The ``init_args`` of a configured logger, ``None`` for none, ``False`` or a list."""
    return None if logger is None or isinstance(logger, (bool, list)) else logger.get("init_args")


def _runs_folder(args) -> Path:
    """The folder of a TensorBoard logger's ``version_<n>`` runs: ``save_dir/name``, or
    ``save_dir`` itself for a ``name`` of ``null`` or ``""`` (as TensorBoardLogger logs;
    read as ``lightning_logs`` there, a second fit of ``name: null, version: 0`` replaced the
    first's run unrefused: a review)."""
    root = Path(args.get("save_dir") or ".")
    name = args.get("name", "lightning_logs")
    return root / name if name else root


def _refuse_a_name_with_nothing_behind(cfg, subcommand: str) -> None:
    """``--ckpt_path last`` or ``best`` where Lightning would find nothing behind the name.

    Lightning resolves ``last`` in the folder of this command's own checkpoint callback: a
    new run's ``version_<n>`` holds none, so ``fit --ckpt_path last`` trained from scratch
    and ``test --ckpt_path last`` judged the initial weights, each with a warning only (a
    training trial; the missing-file error had listed these names). ``best`` is the best
    checkpoint of a ``fit`` in the same process, which a command line never has. ``last``
    stays Lightning's where this fit's checkpoint folder is fixed and holds one (``--trainer
    .logger false --trainer.default_root_dir DIR``, an explicit logger version, a
    ``ModelCheckpoint`` ``dirpath``). ``ValueError`` otherwise, with the newest
    ``last.ckpt`` under the logger's runs as the path to give."""
    ckpt = cfg.get("ckpt_path")
    if ckpt not in ("last", "best"):
        return
    logger = cfg["trainer"].get("logger")
    args = _logger_args(logger)
    if ckpt == "last" and subcommand == "fit":
        folders = [Path(d) for d in _checkpoint_dirpaths(cfg)]
        fixed = _fixed_run_folder(cfg, logger, args)
        if fixed is not None:
            folders.append(fixed / "checkpoints")
        if any(any(f.glob("last*.ckpt")) for f in folders):
            return  # Lightning's own name, with a file behind it
    runs = _runs_folder(args) if args is not None else Path("lightning_logs")
    found = sorted(runs.glob("*/checkpoints/last.ckpt"), key=lambda p: p.stat().st_mtime_ns)
    give = (
        f"give the file, e.g. --ckpt_path {found[-1]} (the newest run's)"
        if found
        else "give the checkpoint file (<run>/checkpoints/last.ckpt or best-*.ckpt)"
    )
    where = ("the best checkpoint of a fit run in this same process, which a command line "
             "never has" if ckpt == "best" else
             "last.ckpt in this command's own run folder, a new version that holds none")  # fmt: skip
    raise ValueError(
        f"--ckpt_path {ckpt}: Lightning reads this name as {where} (it would "
        + ("train from scratch" if subcommand == "fit" else f"{_JUDGES.get(subcommand, subcommand)} the initial weights")
        + f"); {give}"
    )  # fmt: skip


def _checkpoint_dirpaths(cfg) -> list[str]:
    """The ``dirpath`` of each ``ModelCheckpoint`` the trainer's callbacks configure."""
    callbacks = cfg["trainer"].get("callbacks") or []
    out = []
    for cb in callbacks if isinstance(callbacks, list) else [callbacks]:
        init = cb.get("init_args") if hasattr(cb, "get") else getattr(cb, "init_args", None)
        dirpath = init.get("dirpath") if hasattr(init, "get") else None
        if dirpath:
            out.append(str(dirpath))
    return out


def _log_apart_from_a_fit_run(cfg) -> None:
    """``validate``, ``test`` and ``predict`` log as a run of their own (README): a logger
    version that names a fit's run folder (one holding its checkpoints: a resumed run's
    ``config.yaml`` pins its version, and ``test --config <run>/config.yaml`` had logged
    into that run, a trial) is dropped for the logger's next free ``version_<n>``."""
    logger = cfg["trainer"].get("logger")
    args = _logger_args(logger)
    folder = _fixed_run_folder(cfg, logger, args) if logger is not False else None
    if folder is not None and any(folder.glob("checkpoints/*.ckpt")):
        args["version"] = None


def _refuse_a_used_run_folder(folder: Path | None) -> None:
    """A new ``fit`` (no ``--ckpt_path``) into a folder that holds a run already is refused:
    it replaced that run's ``last.ckpt``, ``config.yaml``, export and card without a word
    (a training trial: ``--trainer.logger false --trainer.default_root_dir run`` twice; or
    an explicit ``--trainer.logger.init_args.version``, which also mixed two runs' curves in
    one TensorBoard folder). A folder whose run saved nothing yet (died before its first
    checkpoint: a ``config.yaml`` and logs alone) is taken: there is nothing to lose."""
    if folder is None:
        return
    saved = sorted(folder.glob("checkpoints/*.ckpt"), key=lambda p: p.stat().st_mtime_ns)
    held = [f"checkpoints/{p.name}" for p in saved] + [
        p.name for p in sorted(folder.glob("*.ckpt"))
    ]
    if held:
        # only a training run's Lightning checkpoint resumes (the repository's own folder,
        # default_root_dir ., holds exported estimators in checkpoints/: one of them, of
        # another family, had been offered, and was refused in turn)
        resumable = [p for p in saved if _kind_of(p)[0] == "lightning"]
        last = folder / "checkpoints" / "last.ckpt"
        resume = (f"resume it with --ckpt_path {last if last in resumable else resumable[-1]}"
                  if resumable else "none of them is a training run's checkpoint to resume "
                  "from")  # fmt: skip
        raise ValueError(
            f"the run folder {folder} holds a run already ({', '.join(held)}): a new fit would "
            f"replace its checkpoints, export and card; {resume}, or give another folder or "
            "version"
        )


def _check_resumed_settings(ckpt, model, datamodule) -> None:
    """A run resumed from its Lightning checkpoint goes on with the settings it was started
    with: ``ValueError`` naming each model or data setting this command gives otherwise
    (checked before the run's ``config.yaml`` is rewritten). A run resumed without its
    threat distribution trained its last epochs on the scenario's own attack, chose its best
    checkpoint between two validation sets, and its card said it had never seen the
    threats; one resumed with another ``--seed_everything`` recorded seeds that reproduce
    neither half."""
    if not ckpt or not Path(ckpt).is_file():
        return  # none, or a name Lightning resolves ("last"): it names a missing one itself
    # (mapped, not read: the settings are all it needs of a file holding the weights)
    saved = torch.load(ckpt, map_location="cpu", weights_only=True, mmap=True)
    changed = []
    for what, module, key in (("model", model, "hyper_parameters"),
                              ("data", datamodule, "datamodule_hyper_parameters")):  # fmt: skip
        before = saved.get(key)
        if module is None or not isinstance(before, dict):
            continue
        now = dict(module.hparams)
        changed += [_changed_text(f"--{what}.init_args.{name}", before.get(name), now.get(name))
                    for name in sorted(set(before) | set(now))
                    if not name.startswith("_")
                    and _in_order(before.get(name)) != _in_order(now.get(name))]  # fmt: skip
    from difffilter.models.yaml_scenario import SCENARIO_FILE_DIGEST, scenario_file_digest

    scenario = dict(getattr(model, "hparams", None) or {}).get("scenario")
    was = saved.get(SCENARIO_FILE_DIGEST)
    if was is not None and scenario is not None and scenario_file_digest(scenario) != was:
        # (a training trial: R edited between the epochs, the card naming the path alone)
        changed.append(f"the scenario file {scenario} (its contents changed since the run began)")
    if changed:
        raise _settings_refused(
            ckpt, "this command changes settings the run was trained with", changed,
            "resume with the run's own settings (its config.yaml: --config <run>/config.yaml "
            "--ckpt_path …)",
        )  # fmt: skip


def _changed_text(option: str, before, now) -> str:
    """``option: before → now``, whole where both are short, else at the first place they
    differ (a threat distribution: a trial's refusal printed two whole distributions of 600
    characters, which differed in one entry's order of fields)."""
    if (
        len(repr(before)) <= 60
        and len(repr(now)) <= 60
        and not (isinstance(before, dict) and isinstance(now, dict))
    ):
        return f"{option}: {before!r} → {now!r}"
    where, was, is_now = _first_difference(before, now)
    if isinstance(was, dict) and isinstance(is_now, dict) and list(was) != list(is_now):
        return (f"{option}{where}: the same keys in another order ({', '.join(map(str, was))} "
                f"→ {', '.join(map(str, is_now))})")  # fmt: skip
    return f"{option}{where}: {was!r} → {is_now!r}"


def _first_difference(before, now, where: str = "") -> tuple[str, object, object]:
    """``(path, before's part, now's part)`` of the first place ``before`` and ``now``
    differ (:func:`_in_order`'s way: mappings in their order), descending into mappings
    with the same keys in the same order and lists of the same length."""
    if isinstance(before, dict) and isinstance(now, dict) and list(before) == list(now):
        for key in before:
            if _in_order(before[key]) != _in_order(now[key]):
                return _first_difference(before[key], now[key], f"{where}.{key}")
    listed = (list, tuple)
    if isinstance(before, listed) and isinstance(now, listed) and len(before) == len(now):
        for i, (a, b) in enumerate(zip(before, now)):
            if _in_order(a) != _in_order(b):
                return _first_difference(a, b, f"{where}[{i}]")
    return where, before, now


def _in_order(value):
    """A setting with its mappings as lists of ``(key, value)`` pairs, so that settings
    compare in their order: a threat distribution draws a threat by its entry's place and
    an entry's random fields in their order, so the same entries in another order draw
    other runs (a trial's resume with its YAML's entries reversed had passed the check as
    equal dicts, trained on other data, and chosen its best checkpoint between two
    validation sets)."""
    if isinstance(value, dict):
        return [(k, _in_order(v)) for k, v in value.items()]
    if isinstance(value, (list, tuple)):
        return [_in_order(v) for v in value]
    return value


def _settings_refused(ckpt, what: str, changed: list[str], remedy: str) -> ValueError:
    """The error of a ``--ckpt_path`` given other settings than its run's: ``what``, each of
    ``changed``, the ``remedy`` and the other way out (a new run from these weights)."""
    return ValueError(
        f"--ckpt_path {ckpt}: {what} (" + "; ".join(changed) + f"): {remedy}, or start a new "
        "run from these weights (--model.init_args.init_from)"
    )


def _seeds_from_seed_everything(config, subcommand: str | None) -> None:
    """``--seed_everything s`` reaches the draws: the task's ``model_seed`` (the network's
    initial weights, the training's own draws) becomes ``s`` and the data's
    ``train_seed`` ``1 + 10 s`` (:func:`~difffilter.train.common.train_seed_of`, as a
    sweep seeds them), where the config leaves them unset. Every draw comes from those
    seeds, not from the global generators Lightning seeds, so without this two fits of
    different ``seed_everything`` trained the same network. Validation and test seeds
    stay the config's: every seed is judged on the same data."""
    cfg = config[subcommand] if subcommand else config
    seed = cfg.get("seed_everything")
    if isinstance(seed, bool) or not isinstance(seed, int):
        return  # seed_everything: false (Lightning seeds nothing): the defaults, 0 and 1
    for part, key, value in (("model", "model_seed", seed),
                             ("data", "train_seed", train_seed_of(seed))):  # fmt: skip
        args = _init_args(cfg, part)
        if args is not None and key in args and args[key] is None:
            args[key] = value


def _settings_given(cfg) -> dict:
    """The model settings of a command: its config's ``init_args`` as plain values, those
    given and those left at the class's default alike (the same command, or the run's
    ``config.yaml``, describes the checkpoint's run; a default is a setting too: a command
    that spelled a default where the run had another resumed with the run's), but for the
    unset ``None`` ones, which a run resolves later (``model_seed`` from
    ``--seed_everything``) or takes from the checkpoint."""
    return {k: v for k, v in _plain(_init_args(cfg, "model") or {}).items() if v is not None}


def _plain(value):
    """A config value as plain Python (jsonargparse's namespaces as dicts, tuples as lists),
    so that a command's settings compare with a checkpoint's."""
    if hasattr(value, "as_dict"):
        value = value.as_dict()
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _init_args(cfg, part: str):
    """The settings of the config's ``model`` or ``data`` (its ``init_args`` in subclass
    mode), or ``None``."""
    node = cfg.get(part)
    return node.get("init_args") if node is not None and "class_path" in node else node


#: The precisions the filters run in: the model's and data's ``dtype`` decide, not autocast.
_PRECISIONS = (None, 32, 64, "32", "64", "32-true", "64-true")


def _check_config(config, subcommand: str | None) -> None:
    """What Lightning refused only deep in its run, as one line: the model and the data
    of different scenarios or dtypes ("Error while merging hparams: the keys ['scenario']"),
    and mixed precision (a BFloat16 error inside the EKF over the weights)."""
    cfg = config[subcommand] if subcommand else config
    model, data = _init_args(cfg, "model"), _init_args(cfg, "data")
    if model is not None and data is not None:
        for key in ("scenario", "dtype"):
            if key in model and key in data and model[key] != data[key]:
                # (Lightning reads a --ckpt_path's own settings into the model's)
                whose = " (the model's from --ckpt_path)" if cfg.get("ckpt_path") else ""
                raise ValueError(
                    f"the model's {key} ({model[key]!r}) and the data's ({data[key]!r}) differ"
                    f"{whose}: give both --model.init_args.{key} and --data.init_args.{key}"
                )
    precision = (cfg.get("trainer") or {}).get("precision")
    if precision not in _PRECISIONS:
        raise ValueError(
            f"--trainer.precision {precision}: the filters and the EKF over the weights run in "
            "the dtype of the config (--model.init_args.dtype and --data.init_args.dtype, "
            "float32 or float64), not in mixed precision; leave --trainer.precision unset"
        )


def _quiet_lightning() -> None:
    """Leave out what Lightning prints on every command that is not about the run (a user
    trial called it noise): an advertisement for a cloud logger, and torch's deprecation
    of a check inside Lightning's own code (``_pytree``)."""
    import logging
    import warnings

    warnings.filterwarnings("ignore", r"`isinstance\(treespec, LeafSpec\)` is deprecated")
    log = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    if _not_a_tip not in log.filters:
        log.addFilter(_not_a_tip)


def _not_a_tip(record) -> bool:
    return not str(record.msg).startswith("💡 Tip:")


def _reason(message: str) -> str:
    """jsonargparse's error on one line, a nested class's own reason pulled out of the
    "Does not validate against any of the Union subtypes" preamble."""
    flat = " ".join(str(message).split())
    if "Union subtypes" not in flat:
        return flat
    end = r"(?: - Expected a <class 'NoneType'>| Given value|$)"
    nested = re.search(rf"Problem with given class_path '([^']+)': (.*?){end}", flat)
    listed = re.search(rf"Errors: - (.*?){end}", flat)
    if not (nested or listed):
        return flat
    key = re.match(r'Parser key "([^"]+)"', flat)
    where = [key.group(1)] if key else []
    if nested:
        where.append(f"({nested.group(1).rsplit('.', 1)[-1]})")
    reason = nested.group(2) if nested else listed.group(1)
    return f"{' '.join(where)}: {reason}" if where else reason


def _check_config_files(argv) -> None:
    """Each ``--config`` (``-c``) file of the command line ``argv`` with no key twice in a mapping,
    named by its path (:func:`~difffilter.models.yaml_scenario.check_unique_keys`); one
    that is missing or no valid YAML is left to jsonargparse's own error."""
    import yaml

    for path in map(Path, _values_of(argv, "--config", "-c")):
        if path.is_file():
            try:
                check_config_keys(path)
            except yaml.YAMLError:
                pass


def _refuse_duplicate_keys() -> None:
    """Have jsonargparse's YAML loader refuse a key given twice in one mapping of a config
    or a value (:func:`~difffilter.models.yaml_scenario.check_unique_keys`; PyYAML keeps
    the last one without a word: a trial's config with two threats named ``r`` trained
    on one). The loader it wraps reads what it read before; text that is no valid YAML is
    left to it (a plain string value). Where this jsonargparse does not give its loader
    (``get_loader`` from 4.28; the module's table before), values are not checked; the
    ``--config`` files still are (:func:`_check_config_files`)."""
    import yaml
    from jsonargparse import set_loader

    from difffilter.models.yaml_scenario import check_unique_keys

    try:
        from jsonargparse import get_loader

        load = get_loader("yaml")
    except ImportError:  # (4.27, the lowest version declared: a review)
        try:
            from jsonargparse._loaders_dumpers import loaders

            load = loaders["yaml"]
        except (ImportError, KeyError):
            return
    if not callable(load) or getattr(load, "_refuses_duplicates", False):
        return
    loader = jsonargparse_yaml_loader()

    def load_unique(text):
        if isinstance(text, str) and ":" in text:
            try:  # (each --config file is checked first, by its name: _check_config_files)
                check_unique_keys(text, "a YAML value or config", loader)
            except yaml.YAMLError:
                pass  # not YAML: as the loader reads it
        return load(text)

    load_unique._refuses_duplicates = True
    set_loader("yaml", load_unique, exceptions=(yaml.YAMLError,))


def _trainer_hint(card, ours) -> str:
    """Where an exported network was trained otherwise than the config trains (``trainer``
    ``"ekf"`` against ``"grad"``), the config of its training where the family ships one (a
    docs trial met only "(detection_head False against True)")."""
    if card.trainer == ours.trainer:
        return ""
    name = f"{card.scenario_family}_{card.trainer}.yaml"
    shipped = (Path(__file__).resolve().parent / "configs" / name).is_file()
    return f" (it was trained by {card.trainer!r}, the config trains by {ours.trainer!r}" + (
        f": its config is train/configs/{name})" if shipped else ")"
    )


def _config_hint(argv: list[str], command: str) -> str:
    """A hint where a command ran without ``--config``: the model and data come from a
    training config (a docs trial: ``difffilter-train fit`` alone said only "the following
    arguments are required: fit.data, fit.model")."""
    if _values_of(argv, "--config", "-c") or not command:
        return ""
    return (
        f"; no --config given: start from a training config, e.g. difffilter-train"
        f"{command} --config train/configs/four_tank.yaml (one per family in "
        "train/configs/; the README's section Training the neural FDI estimator)"
    )


def run(args: list[str] | None, argv: list[str], description: str) -> int:
    """LightningCLI on ``args`` (``None``: ``sys.argv``; ``argv`` the same as a list):
    exit code 0, or 2 after a one-line error; a ``KeyboardInterrupt`` after Ctrl-C, whether
    Lightning let it through or caught it (:func:`~difffilter.train.cli.main` exits 130).

    Training simulates closed loops step by step: a long chain of tiny tensor operations,
    for which intra-op threads only add synchronisation (and stall badly when another
    process holds a core): :func:`~difffilter.train.cli.main` sets one thread unless
    ``DIFFFILTER_THREADS`` says otherwise (:func:`~difffilter.runtime.command_threads`).
    """
    tune_cpu_allocator()
    _quiet_lightning()
    _refuse_duplicate_keys()
    import signal

    from jsonargparse import ArgumentError
    from lightning.fabric.utilities.exceptions import MisconfigurationException

    # a bad command line raises (one line below) instead of printing the whole usage first
    raising = {"exit_on_error": False}
    commands = DifffilterCLI.subcommands()
    # each command's own --help names the shortcut train/cli.py expands (Lightning's lacks it)
    shortcut = ("--scenario NAME (a registered name, package.module:object or a .yaml file) "
                "sets --model.init_args.scenario and --data.init_args.scenario at once; "
                "--no-progress sets --trainer.enable_progress_bar=false.")  # fmt: skip
    parser_kwargs = {**raising, "description": description,
                     **{name: {**raising, "description": shortcut} for name in commands}}  # fmt: skip
    sigint = signal.getsignal(signal.SIGINT)
    try:
        _check_config_files(argv)
        # Lightning reads a --ckpt_path's settings while it parses, before any hook
        for given in _ckpt_paths_in(argv):
            _check_ckpt_path({"ckpt_path": given}, None)
        cli = DifffilterCLI(
            pl.LightningModule,
            pl.LightningDataModule,
            subclass_mode_model=True,
            subclass_mode_data=True,
            args=args,
            save_config_callback=_SaveConfigOfItsStage,
            save_config_kwargs={"overwrite": True},
            auto_configure_optimizers=False,
            parser_kwargs=parser_kwargs,
        )
    except ArgumentError as exc:
        command = f" {argv[0]}" if argv and argv[0] in commands else ""
        print(f"difffilter-train: error: {_reason(str(exc))} (difffilter-train{command} --help "
              f"lists the options){_config_hint(argv, command)}", file=sys.stderr)  # fmt: skip
        return 2
    except (ValueError, FileNotFoundError, MisconfigurationException) as exc:
        # a user error (a setting out of range, a missing file): one line, no traceback
        print(f"difffilter-train: error: {_reason(str(exc))}", file=sys.stderr)
        return 2
    except PermissionError as exc:  # a run folder it may not make (a CLI trial's traceback)
        print(f"difffilter-train: error: cannot write {exc.filename} ({exc.strerror}): run "
              "from a writable folder or give one with --trainer.logger.init_args.save_dir "
              "(default: lightning_logs/ under the current folder)", file=sys.stderr)  # fmt: skip
        return 2
    except SystemExit as exc:
        # Ctrl-C: Lightning from 2.3 catches it, runs the callbacks' on_exception (last.ckpt
        # kept at the last whole epoch, how to resume said), ignores SIGINT from then on and
        # exits 1, the code of a failure: handed on as the interrupt it was (cli.main: 130;
        # SIGTERM, raised as Terminated by cli.main's handler: 143)
        from lightning.pytorch.utilities.exceptions import SIGTERMException

        from difffilter.interrupts import Terminated

        if isinstance(exc, SIGTERMException):  # Lightning's own SIGTERM stop: it exits 0
            raise Terminated from None
        if not isinstance(exc.__context__, KeyboardInterrupt):
            raise
        _restore_sigint(sigint)
        raise type(exc.__context__) from None
    # Lightning 2.2 returned from fit as if it had ended
    if getattr(getattr(cli, "trainer", None), "interrupted", False):
        from difffilter.interrupts import Terminated, sigterm_received

        _restore_sigint(sigint)
        raise Terminated if sigterm_received() else KeyboardInterrupt
    return 0


def _restore_sigint(handler) -> None:
    """SIGINT back to ``handler`` (Lightning left it ignored after an interrupt: a process
    that goes on, a sweep or a test, no longer stopped at Ctrl-C)."""
    import signal

    try:
        signal.signal(signal.SIGINT, handler if handler is not None else signal.SIG_DFL)
    except ValueError:  # not the main thread: it cannot be set there
        pass
