"""Process-level CPU tuning for long batched runs (opt-in; the library never calls it).

:func:`one_thread` runs a block with one intra-op thread; :func:`command_threads` sets a
command's intra-op threads from ``DIFFFILTER_THREADS`` (default one);
:func:`tune_cpu_allocator` keeps large freed blocks in glibc's heap.

Why: PyTorch's CPU tensors of a few MB (a particle cloud ``[B, N, d]`` with ``B·N`` ≈
1e5) are allocated with glibc ``malloc``, which serves blocks above its mmap threshold
with fresh ``mmap`` pages and returns them on ``free``. Every temporary of a filter step
then costs page faults, which made a bootstrap PF step about 1.5× slower on our 2-core
machine. PyTorch's CPU performance guide recommends a caching allocator (jemalloc,
tcmalloc) for the same reason; :func:`tune_cpu_allocator` gets most of that effect by
raising glibc's mmap and trim thresholds, so freed blocks stay in the heap and are
reused. Command-line entry points (``difffilter-eval``, ``difffilter-train``,
``make bench``) call it at start-up.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
from contextlib import contextmanager

import torch

from ._checks import check_integer

__all__ = ["command_threads", "one_thread", "tune_cpu_allocator"]

#: The environment variable that sets a command's intra-op threads (:func:`command_threads`).
THREADS_VARIABLE = "DIFFFILTER_THREADS"


# mallopt parameter numbers from glibc's <malloc.h>
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3
_INT_MAX = (1 << 31) - 1


def tune_cpu_allocator(mmap_threshold: int = 1 << 30, top_pad: int = 64 << 20) -> bool:
    """Keep large freed blocks in the heap (glibc only). Returns whether it applied.

    Sets ``M_MMAP_THRESHOLD`` (blocks below it come from the heap, not ``mmap``) and
    ``M_TRIM_THRESHOLD`` (the heap is not shrunk below it) to ``mmap_threshold`` and
    ``M_TOP_PAD`` to ``top_pad``. A no-op returning ``False`` on other C libraries or
    platforms. Affects the whole process and should be called before large allocations.
    Both are byte counts in ``[0, 2³¹ − 1]`` (mallopt takes a C ``int``: ``2**32`` had
    wrapped to 0, every block mmapped, and returned ``True``); ``ValueError`` else.
    """
    for value, name in ((mmap_threshold, "mmap_threshold"), (top_pad, "top_pad")):
        if check_integer(value, name) > _INT_MAX:
            raise ValueError(f"{name} must be an integer <= 2**31 - 1 (a C int); got {value!r}")
    if not sys.platform.startswith("linux"):
        return False
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold)) == 1
    ok &= mallopt(_M_TRIM_THRESHOLD, int(mmap_threshold)) == 1
    ok &= mallopt(_M_TOP_PAD, int(top_pad)) == 1
    return bool(ok)


def command_threads(default: int = 1) -> int:
    """Set torch's intra-op threads for a command-line run to ``DIFFFILTER_THREADS`` (else
    ``default``) and return the number; ``ValueError`` naming the variable for anything but
    a positive integer.

    Why one by default: a command that simulates closed loops or small filters runs long
    chains of tiny tensor operations, for which a second thread only adds synchronisation,
    and stalls badly when another process holds a core (``difffilter-train calibrate`` of
    the LFC network beside another run on two cores: 629 s with two threads in each
    process, 16 s with one in each).
    """
    raw = os.environ.get(THREADS_VARIABLE, str(default))
    try:
        threads = int(raw)
    except ValueError:
        threads = 0
    if threads < 1:
        raise ValueError(f"{THREADS_VARIABLE} must be a positive integer; got {raw!r}")
    torch.set_num_threads(threads)
    return threads


@contextmanager
def one_thread(enabled: bool = True):
    """Run the block with one intra-op thread (restored afterwards; ``enabled=False``: as is).

    The tensors of a study are small (``B·N·dx`` ≈ 1e4–1e5): on a 2-core machine a second
    thread costs more in synchronisation than it gains (measured 5× slower under load).
    A scenario whose estimators carry large matrices (``Scenario.single_thread = False``:
    the LFC EKF over a network's weights, ``[B, P, P]`` covariances) keeps torch's threads.
    """
    threads = torch.get_num_threads()
    if enabled:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
