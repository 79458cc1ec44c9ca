"""``difffilter-train``: the Lightning command line of difffilter's trainable estimators.

Usage::

    difffilter-train fit --config train/configs/lfc.yaml
    difffilter-train fit --config train/configs/four_tank.yaml
    difffilter-train fit --config train/configs/lfc.yaml --trainer.fast_dev_run=1
    difffilter-train fit --config train/configs/lfc.yaml --ckpt_path <run>/checkpoints/last.ckpt
    difffilter-train export <run>/lfc_nn_grad.ckpt --out checkpoints/lfc_nn_grad.ckpt --force
    difffilter-train test --config train/configs/lfc.yaml --ckpt_path checkpoints/lfc_nn_grad.ckpt \
        --model.gating=false --model.features=null  # the shipped network's

The YAML files in ``train/configs/`` hold every setting (model, data, trainer, callbacks):
one per scenario family, each naming its LightningModule and data module (``class_path``,
subclass mode): :class:`~difffilter.train.task.FilterEstimatorTask` with
:class:`~difffilter.train.task.ScenarioDataModule` for any registered scenario, open or
closed loop (LFC);
``--print_config`` shows the resolved configuration. TensorBoard logs go under the
logger's ``save_dir`` (``tensorboard --logdir lightning_logs``). ``fit`` writes only
inside its run folder; ``export`` (:mod:`difffilter.train.export`) ships a result.
"""

from __future__ import annotations

import os
import sys
import textwrap

__all__ = ["main"]  # DifffilterCLI: difffilter.train.lightning_cli (also read here)

HELP = (
    "Train, validate, test and predict with difffilter's neural FDI estimator (LightningCLI; "
    "one YAML per scenario family in train/configs/). Ship a trained estimator with "
    "'difffilter-train export SRC --out FILE' (export --help); set its alarm threshold for a "
    "false-alarm rate with 'difffilter-train calibrate SRC --far 0.01 --out FILE' "
    "(calibrate --help); train one config on several seeds and report the spread with "
    "'difffilter-train sweep --config FILE --seeds 0 1 2 --out DIR' (sweep --help)."
)


USAGE = """usage: difffilter-train COMMAND [options]

{help}

commands:
  fit        train (--config train/configs/<family>.yaml; --ckpt_path <run>/checkpoints/last.ckpt resumes;
             --scenario NAME or module:object trains on another scenario, yours included)
  validate   validate a Lightning checkpoint or an exported estimator (--ckpt_path)
  test       test one on the scenario's test runs (those of difffilter-eval --seed <test_seed>)
  predict    write its estimates, probabilities and alarms to <run>/predictions/
  export     ship a trained estimator to a file of your choice, with its card
  calibrate  set an exported estimator's alarm threshold for a false-alarm rate
  sweep      train one config on several seeds; the spread and the median seed

difffilter-train COMMAND --help lists the options of each command.
"""

_EXTRA = {"export": ".export", "calibrate": ".calibrate", "sweep": ".sweep"}
#: The Lightning commands (:func:`~difffilter.train.lightning_cli.run`).
_LIGHTNING = ("fit", "validate", "test", "predict")


def __getattr__(name: str):
    if name == "DifffilterCLI":  # Lightning is imported only when a command needs it
        from .lightning_cli import DifffilterCLI

        return DifffilterCLI
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def main(args: list[str] | None = None) -> int:
    """Entry point of the ``difffilter-train`` console script (``args`` for tests): the
    top-level ``--help`` at once, ``export``, ``calibrate`` and ``sweep`` by their own
    modules, the Lightning commands by :func:`~difffilter.train.lightning_cli.run`. An
    interrupt (Ctrl-C) ends it with one line and exit code 130, SIGTERM with one line and
    143, as ``difffilter-eval`` (Lightning's exit code 1 had read as a failure, and its
    code 0 after SIGTERM as a finished run); a fit's ``last.ckpt`` is written as before
    (:mod:`~difffilter.train.last_checkpoint`)."""
    from difffilter.interrupts import (
        console_output_tolerant,
        reader_left,
        sigterm_as_interrupt,
        stop_words,
    )

    argv = sys.argv[1:] if args is None else list(args)
    console_output_tolerant()
    try:
        with sigterm_as_interrupt():
            return _main(args, argv)
    except BrokenPipeError:  # `… | head`: the reader of its output left (an I/O trial:
        # a traceback and exit 1 after `--help | head -1`)
        reader_left()
        if not argv or {"-h", "--help"} & set(argv):
            return 0  # the help, read as far as wanted
        command = argv[0] if not argv[0].startswith("-") else "the command"
        print(f"difffilter-train: the reader of its output left (a closed pipe): {command} "
              "stopped where it was; rerun it without the pipe, or into a file", file=sys.stderr)  # fmt: skip
        return 141  # (128 + SIGPIPE: a shell's code for a writer stopped by a closed pipe)
    except KeyboardInterrupt as exc:
        hints = sys.modules.get("difffilter.train.last_checkpoint")
        if hints is not None and os.environ.get(hints.RESUME_HINT):
            raise  # a sweep's seed: the sweep says how to go on (and exits 130)
        command = argv[0] if argv and not argv[0].startswith("-") else "the command"
        if command == "fit":
            what = ("the training did not finish and exported nothing; rerun the same command "
                    "with --ckpt_path <its run folder>/checkpoints/last.ckpt to resume from the "
                    "last whole epoch (named above where one ended)")  # fmt: skip
        else:
            what = f"{command} did not finish; rerun the same command"
        said, code = stop_words(exc)
        print(f"difffilter-train: {said}: {what}", file=sys.stderr)
        return code


def _main(args: list[str] | None, argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE.format(help=textwrap.fill(" ".join(HELP.split()), 90)))
        return 0 if argv else 2
    from difffilter.runtime import command_threads

    try:  # every command on one intra-op thread unless DIFFFILTER_THREADS says otherwise
        command_threads()
    except ValueError as exc:
        print(f"difffilter-train: error: {exc}", file=sys.stderr)
        return 2
    if argv[0] in _EXTRA:
        from importlib import import_module

        return import_module(_EXTRA[argv[0]], __package__).main(argv[1:])
    if not argv[0].startswith("-") and argv[0] not in _LIGHTNING:  # (Lightning's list lacks ours)
        print(f"difffilter-train: error: unknown command {argv[0]!r}; choose from "
              f"{', '.join((*_LIGHTNING, *_EXTRA))}", file=sys.stderr)  # fmt: skip
        return 2
    try:
        argv = _scenario_option(argv)
    except ValueError as exc:
        print(f"difffilter-train: error: {exc}", file=sys.stderr)
        return 2
    from .lightning_cli import run

    if args is None:  # the console script: LightningCLI reads sys.argv itself
        sys.argv = [sys.argv[0], *argv]
        return run(None, argv, HELP)
    # called with its arguments (a sweep's seeds): sys.argv is another command's, which
    # LightningCLI warned about at every seed
    saved, sys.argv = sys.argv, sys.argv[:1]
    try:
        return run(argv, argv, HELP)
    finally:
        sys.argv = saved


def _scenario_option(argv: list[str]) -> list[str]:
    """``--scenario NAME`` (or ``--scenario=NAME``; a registered name or
    ``package.module:object``) sets the model's and the data's scenario at once;
    ``--no-progress`` turns the trainer's progress bar off, as in ``sweep`` and
    ``calibrate`` (``--trainer.enable_progress_bar=false``)."""
    out, i = [], 0
    while i < len(argv):
        arg = argv[i]
        if arg == "--no-progress":
            out.append("--trainer.enable_progress_bar=false")
            i += 1
            continue
        if arg == "--scenario" or arg.startswith("--scenario="):
            value = (
                arg.partition("=")[2] if "=" in arg else (argv[i + 1] if i + 1 < len(argv) else "")
            )
            i += 1 if "=" in arg else 2
            if not value:
                raise ValueError("--scenario needs a scenario name or package.module:object")
            out += [f"--model.init_args.scenario={value}", f"--data.init_args.scenario={value}"]
            continue
        out.append(arg)
        i += 1
    return out


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
