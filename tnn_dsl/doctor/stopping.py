"""Ctrl-C during a diagnosis stops it the way a spent budget does: no new piece of work starts, a fit in progress
ends after its current iteration, and the diagnosis returns what it has — the findings accepted so far, the extended
model with their values, the report — marked as stopped (``Diagnosis.budget["interrupted"]``). A second Ctrl-C
aborts at once (``KeyboardInterrupt``), as before.

A diagnosis of the case study runs for minutes; before this a Ctrl-C threw away every accepted round. It is opt-in
(``diagnose(..., stop_on_ctrl_c=True)``; ``tnnc diagnose`` turns it on): a program that runs diagnoses one after
another in its own loop — a fleet in one process — stops its loop on Ctrl-C, and a first Ctrl-C that only ended the
current diagnosis would leave that loop running.

The request is one flag for the process (Ctrl-C is the process's): :func:`stop_requested` is what the session's budget
check, the engine's fits and the MLP check's trainings look at; :func:`request_stop` sets it without a signal (a test,
or a program's own stop button)."""

from __future__ import annotations

import contextlib
import signal
import threading
from typing import Callable, Iterator

__all__ = ["ctrl_c_stops", "request_stop", "stop_requested"]

_STOP = threading.Event()


def stop_requested() -> bool:
    """Whether the diagnosis running now was asked to stop (Ctrl-C, or :func:`request_stop`)."""
    return _STOP.is_set()


def request_stop() -> None:
    """Ask the diagnosis running now to stop, as a first Ctrl-C does (cleared when the next one starts)."""
    _STOP.set()


@contextlib.contextmanager
def ctrl_c_stops(say: Callable[[str], None], enabled: bool = True) -> Iterator[None]:
    """For the duration of the block: the first SIGINT asks the diagnosis to stop (and says so through ``say``), a
    second one raises ``KeyboardInterrupt``. Left as it is outside the main thread (where Python delivers no signal),
    where SIGINT is ignored (a job started in the background), or when not ``enabled``; the stop request is cleared
    on entry and on exit either way."""
    _STOP.clear()
    previous = signal.getsignal(signal.SIGINT) if threading.current_thread() is threading.main_thread() else None
    install = enabled and previous is not None and previous is not signal.SIG_IGN

    def on_sigint(signum, frame) -> None:
        if _STOP.is_set():
            raise KeyboardInterrupt
        _STOP.set()
        say("Ctrl-C: stopping after the current step and keeping what was found so far (Ctrl-C again to abort)")

    if install:
        signal.signal(signal.SIGINT, on_sigint)
    try:
        yield
    finally:
        if install:
            signal.signal(signal.SIGINT, previous)
        _STOP.clear()
