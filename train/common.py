"""Small helpers the training modules share: dtype names, seed mixing and where an
exported checkpoint may be written."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

__all__ = ["DTYPES", "check_checkpoint_out", "dtype_of", "load_source", "mix_seed", "train_seed_of"]

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def dtype_of(name: str) -> torch.dtype:
    """``"float32"``/``"float64"`` → the torch dtype; ``ValueError`` naming ``dtype`` otherwise."""
    if name not in DTYPES:
        raise ValueError(f"dtype must be one of {sorted(DTYPES)}; got {name!r}")
    return DTYPES[name]


def check_checkpoint_out(out: Path, *, force: bool, replacing: Path | None = None) -> None:
    """``ValueError`` (naming ``--out``) unless an exported checkpoint may be written to
    ``out``: a ``.ckpt`` file (its card is ``out`` with suffix ``.json``, so any other name
    could make the card land on a file of another name, a shipped card among them) of which
    neither the file nor the card exists, unless ``force``. ``replacing``: the source being
    rewritten in place, allowed with ``force`` only (its own card is rewritten with it)."""
    if out.is_dir():  # (a folder named x.ckpt failed on an internal temporary file's name)
        raise ValueError(f"--out: {out} is a folder; give the name of a .ckpt file")
    if out.suffix != ".ckpt":
        raise ValueError(
            f"--out must name a .ckpt file (its card is the .json beside it); got {out}"
        )
    if replacing is not None and out.resolve() == replacing.resolve():
        if not force:
            raise ValueError(f"--out: {out} is the source itself; pass --force to rewrite it")
        return
    for path in (out, out.with_suffix(".json")):
        if path.exists() and not force:
            raise ValueError(f"--out: {path} exists; pass --force to replace it")
    # where it goes can be written: said now, before any work (a calibration scores first)
    make_writable_folder(out.parent)


def make_writable_folder(folder: Path, option: str = "--out") -> None:
    """Make ``folder`` and prove it writable, or a ``ValueError`` naming ``option`` (a folder
    that could not be made had failed with a PermissionError traceback)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ValueError(f"{option}: cannot make the folder {folder} ({error.strerror})") from None
    if not os.access(folder, os.W_OK):
        raise ValueError(f"{option}: the folder {folder} is not writable")


def mix_seed(*parts: int) -> int:
    """A 63-bit seed mixed from integers (numpy SeedSequence: well spread, reproducible)."""
    state = np.random.SeedSequence([int(p) for p in parts]).generate_state(1, np.uint64)
    # shift a Python int: numpy < 2 has no right_shift for np.uint64 by a Python int
    return int(state[0]) >> 1


def train_seed_of(seed: int) -> int:
    """The training batches' ``train_seed`` of run seed ``seed`` (``seed_everything``, a
    sweep's seed): ``1 + 10 s``, never a default validation (2) or test (0) seed; seed 0
    gives the default 1."""
    return 1 + 10 * int(seed)


def load_source(src):
    """``(estimator, card)`` of the checkpoint a command reads (``export``, ``calibrate``),
    its weights in their own dtype; its errors name it as the commands do, ``src``, and
    come before any about ``--out``."""
    return load_estimator_as(src, "src")


def load_estimator_as(path, setting: str, dtype=None):
    """``(estimator, card)`` of the checkpoint at ``path`` (``dtype``: the weights', ``None``
    their own), its errors naming ``setting``, where the path came from (the loader's own
    name a setting ``ckpt`` that the commands and configs do not have)."""
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    try:
        return load_estimator_checkpoint(path, dtype=dtype)
    except (ValueError, FileNotFoundError) as exc:
        raise type(exc)(f"{setting}: {str(exc).removeprefix('ckpt: ')}") from None


def check_config_keys(config: Path) -> None:
    """``ValueError`` naming ``config`` where a mapping of that YAML file holds a key twice,
    keys told apart as the training command line's loader tells them
    (:func:`jsonargparse_yaml_loader`,
    :func:`~difffilter.models.yaml_scenario.check_unique_keys`); the parser's
    ``yaml.YAMLError`` where it is no valid YAML."""
    from difffilter.models.yaml_scenario import check_unique_keys

    check_unique_keys(
        Path(config).read_text(encoding="utf-8"), str(config), jsonargparse_yaml_loader()
    )


def jsonargparse_yaml_loader():
    """The PyYAML loader class jsonargparse reads configs with (it reads ``1e3`` as a number
    and no dates, unlike SafeLoader): keys are told apart as it tells them
    (:func:`~difffilter.models.yaml_scenario.check_unique_keys`). Private in jsonargparse:
    ``get_yaml_default_loader()`` from 4.36, the module's ``DefaultLoader`` before (4.27,
    the lowest version we declare); SafeLoader where neither is found (a review: the first
    alone fell back to SafeLoader on 4.27–4.35, and a changed one would have crashed every
    fit)."""
    import yaml

    try:
        from jsonargparse import _loaders_dumpers as loaders
    except ImportError:
        return yaml.SafeLoader
    try:
        loader = loaders.get_yaml_default_loader()
    except Exception:  # absent (before 4.36) or changed: the older name, else SafeLoader
        loader = getattr(loaders, "DefaultLoader", None)
    is_loader = isinstance(loader, type) and issubclass(loader, yaml.resolver.BaseResolver)
    return loader if is_loader else yaml.SafeLoader
