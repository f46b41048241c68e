"""Giving freed memory back to the operating system (glibc's ``malloc``), between the phases of long jobs whose
large buffers come and go: the model doctor's rounds.

glibc keeps freed blocks on its heap for reuse; once small live objects sit between them (results, caches), the
heap cannot shrink from its top and the process's resident size stays at its highest. ``malloc_trim(0)`` hands
every free page of the heap back (``MADV_DONTNEED``) without moving anything; it costs one walk of the free lists
(milliseconds) and changes nothing about how later memory is allocated. Called between the doctor's phases, it
lowers the floor each phase's own arrays stand on: ``python benchmarks/trace_diagnose_memory.py`` against the same
with ``--no-release`` (README, "Speed"). A no-op off glibc.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import sys
from functools import lru_cache


@lru_cache(maxsize=1)
def _glibc():
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version.restype = ctypes.c_char_p
        libc.gnu_get_libc_version()
        libc.malloc_trim.argtypes = [ctypes.c_size_t]
        libc.malloc_trim.restype = ctypes.c_int
    except (OSError, AttributeError):
        return None  # musl or another libc
    return libc


def release_free_memory(collect: bool = False) -> bool:
    """Return the free pages of the C heap to the operating system (glibc's ``malloc_trim(0)``). Returns whether
    any memory was released (False off glibc). ``collect``: first free the unreachable reference cycles
    (``gc.collect()``, tens of milliseconds): a compiled model and the compiled functions it keeps, which refer
    back to it, are such a cycle once nothing else holds the model, and Python's collector may leave it for
    many phases."""
    if collect:
        gc.collect()
    libc = _glibc()
    return bool(libc.malloc_trim(0)) if libc is not None else False
