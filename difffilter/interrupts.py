"""How the command-line entry points stop: SIGTERM (a batch scheduler's stop, ``kill``)
ends a command as Ctrl-C does, with its own words and exit code (130 after Ctrl-C, 143
after SIGTERM). Imports nothing heavy: ``--help`` runs before torch is imported."""

from __future__ import annotations

import os
import signal
import sys
import threading
from contextlib import contextmanager

__all__ = [
    "Terminated",
    "sigterm_as_interrupt",
    "sigterm_received",
    "signals_deferred",
    "stop_words",
]


class Terminated(KeyboardInterrupt):
    """SIGTERM (a batch scheduler's stop, ``kill``) raised where a command is, by
    :func:`sigterm_as_interrupt`: the command then ends as after Ctrl-C (its ``with``
    blocks closed, a training's ``last.ckpt`` kept, one line said), with exit code 143."""


def _raise_terminated(signum, frame):
    _RECEIVED[0] = True
    raise Terminated


#: Whether SIGTERM arrived in the current :func:`sigterm_as_interrupt` block (for a caller
#: that swallowed the exception: Lightning 2.2 returns from an interrupted fit).
_RECEIVED = [False]


def sigterm_received() -> bool:
    """Whether SIGTERM arrived inside the current (or last) :func:`sigterm_as_interrupt`
    block."""
    return _RECEIVED[0]


@contextmanager
def sigterm_as_interrupt():
    """Run the block with SIGTERM raising :class:`Terminated` (a ``KeyboardInterrupt``) in
    the main thread; the previous handler afterwards. Outside the main thread, where no
    handler can be set, the block runs as it is. (Python's default had ended the commands
    at once and silently: ``difffilter-eval`` with 143 and nothing said, a training with
    Lightning's exit code 0, as if it had finished.)"""
    previous, _RECEIVED[0] = None, False
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


@contextmanager
def signals_deferred():
    """Run the block (a few renames that must happen together) with Ctrl-C and SIGTERM
    held: one that arrives inside is raised as it would have been (``KeyboardInterrupt``,
    :class:`Terminated`) once the block is done. Outside the main thread the block runs as
    it is. (``calibrate --out SRC --force`` stopped between writing a checkpoint and its
    card had left a pair that no longer matched, and the rerun it advised was refused: an
    interrupts trial.)"""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []

    def hold(signum, frame):
        held.append(signum)

    previous = {sig: signal.signal(sig, hold) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:  # (also where the block raised: a held SIGTERM had been dropped, a review)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        _deliver(held)


def _deliver(held: list[int]) -> None:
    """Each held signal delivered again, to the handler it would have met: ignored where the
    process ignores it, a caller's own handler called (raising KeyboardInterrupt or
    Terminated regardless had overridden both: a review); every one, ``Terminated`` first
    among what the handlers raise."""
    error = None
    for sig in dict.fromkeys(held):  # (every one: a SIGINT's KeyboardInterrupt had dropped a
        try:  # SIGTERM held after it, exit 130 for 143: a review)
            signal.raise_signal(sig)
        except BaseException as raised:
            if error is None or isinstance(raised, Terminated):
                error = raised
    if error is not None:
        raise error


def stop_words(interrupt: KeyboardInterrupt) -> tuple[str, int]:
    """``(what happened, exit code)`` of a command stopped by ``interrupt``:
    ``("terminated (SIGTERM)", 143)`` or ``("interrupted", 130)`` (Ctrl-C)."""
    if isinstance(interrupt, Terminated):
        return "terminated (SIGTERM)", 143
    return "interrupted", 130


def console_output_tolerant() -> None:
    """Standard output that writes what its encoding lacks as escapes: under a locale of
    another encoding (Python's UTF-8 mode off: ``PYTHONUTF8=0``, a Windows code page) the
    reports' ✓, ≥ and × had stopped a finished evaluation at its last print (an I/O
    trial). The files are written in UTF-8 whatever the locale."""
    reconfigure = getattr(sys.stdout, "reconfigure", None)
    encoding = (getattr(sys.stdout, "encoding", None) or "").lower().replace("-", "")
    if reconfigure is not None and encoding != "utf8":
        reconfigure(errors="backslashreplace")


def reader_left() -> None:
    """After ``BrokenPipeError`` (``… | head``: the reader of standard output left), what is
    still written to it goes nowhere: the interpreter's last flush would raise again."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
