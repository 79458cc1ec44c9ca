"""Small helpers the training modules share: dtype names and seed mixing."""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["DTYPES", "dtype_of", "mix_seed"]

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def dtype_of(name: str) -> torch.dtype:
    """``"float32"``/``"float64"`` → the torch dtype; ``ValueError`` naming ``dtype`` otherwise."""
    if name not in DTYPES:
        raise ValueError(f"dtype must be one of {sorted(DTYPES)}; got {name!r}")
    return DTYPES[name]


def mix_seed(*parts: int) -> int:
    """A 63-bit seed mixed from integers (numpy SeedSequence: well spread, reproducible)."""
    state = np.random.SeedSequence([int(p) for p in parts]).generate_state(1, np.uint64)
    # shift a Python int: numpy < 2 has no right_shift for np.uint64 by a Python int
    return int(state[0]) >> 1
