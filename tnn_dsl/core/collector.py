"""Python's cyclic garbage collector, paused while a large network is read or compiled.

Reading a 10 000-node plate creates about a million small objects (tokens, tree nodes, spans, IR records) that
all stay alive; the collector's full passes walk every one of them again and again while they are being made:
about half of the parse time and of the compile time measured on that plate (``python benchmarks/bench_scaling.py``,
BENCHMARKS.md). These phases make no reference cycles worth collecting, and what they allocate is bounded by the
file-size limit, so the collector is paused for their duration and restored after — the process-wide switch is
turned back on only by the last of several threads inside a paused phase, and only if it was on before.
"""

from __future__ import annotations

import gc
import threading
from collections.abc import Iterator
from contextlib import contextmanager

_lock = threading.Lock()
_depth = 0
_was_enabled = False


@contextmanager
def collector_paused() -> Iterator[None]:
    """Run the body with ``gc`` disabled (nesting and threads allowed); the collector's previous state is restored
    when the outermost body ends, whether it returns or raises."""
    global _depth, _was_enabled
    with _lock:
        if _depth == 0:
            _was_enabled = gc.isenabled()
            gc.disable()
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0 and _was_enabled:
                gc.enable()
