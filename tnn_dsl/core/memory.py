"""Giving freed memory back to the operating system (glibc's ``malloc``), between the phases of long jobs whose
large buffers come and go: the model doctor's rounds.

glibc keeps freed blocks on its heap for reuse; once small live objects sit between them (results, caches), the
heap cannot shrink from its top and the process's resident size stays at its highest. ``malloc_trim(0)`` hands
every free page of the heap back (``MADV_DONTNEED``) without moving anything; it costs one walk of the free lists
(milliseconds) and changes nothing about how later memory is allocated. Called between the doctor's phases, it
lowers the floor each phase's own arrays stand on: ``python benchmarks/trace_diagnose_memory.py`` against the same
with ``--no-release`` (docs/measurement-log.md, "Speed"). A no-op off glibc.

:func:`large_blocks_mapped` goes further for the length of a ``with`` block (the doctor's rounds): every block of at
least a megabyte gets its own mapping, handed back the moment it is freed, so the large buffers a long job makes and
frees (a compiled simulation's temporaries, a Jacobian) never sit in the heap between its small live objects.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import sys
from contextlib import contextmanager
from functools import lru_cache
from typing import Iterator


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


M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
"""glibc's ``mallopt`` parameter numbers (``malloc.h``)."""

LARGE_BLOCK_BYTES = 1 << 20
""":func:`large_blocks_mapped`' threshold, bytes (1 MiB)."""

GLIBC_MMAP_THRESHOLD_MAX = 32 << 20
"""The highest mapping threshold glibc's own rule reaches on a 64-bit machine (``DEFAULT_MMAP_THRESHOLD_MAX``),
bytes: set on leaving :func:`large_blocks_mapped`, with a trim threshold of twice that as that rule sets."""


def _mallopt(param: int, value: int) -> bool:
    libc = _glibc()
    if libc is None:
        return False
    libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    libc.mallopt.restype = ctypes.c_int
    return bool(libc.mallopt(param, int(value)))


@contextmanager
def large_blocks_mapped(threshold: int = LARGE_BLOCK_BYTES) -> Iterator[bool]:
    """Inside the block, every C-heap request of at least ``threshold`` bytes gets a mapping of its own, unmapped
    when it is freed (glibc's ``mallopt(M_MMAP_THRESHOLD)``); yields whether the setting was taken (False off glibc).

    glibc's own rule raises the threshold each time a mapped block is freed (up to 32 MiB), so after the first few
    calls a compiled simulation's temporaries and the Jacobians (1–40 MB each on the case study's 4 h) come from the
    heap, and the small objects allocated meanwhile pin the pages they leave: the resident size then carries the
    fragments of every phase. ``tnn_dsl.diagnose`` runs its rounds in this block (issue 18, ``python
    benchmarks/bench_diagnose.py --threads 1,2``, 2026-11-29, BENCHMARKS.md: with the score test's network released
    between rounds too, peak 678 → 574 MB with one candidate fit at a time, 727 → 605 MB with two, as fast; runs of
    one code had differed by up to 46 MB, now by a few). The setting is the process's: glibc cannot go back to its rule
    once it is set, so on leaving the threshold is fixed where that rule ends, 32 MiB (the trim threshold at twice
    that), for the trainings after it whose buffers are reused step after step."""
    taken = _mallopt(M_MMAP_THRESHOLD, threshold)
    try:
        yield taken
    finally:
        if taken:
            _mallopt(M_MMAP_THRESHOLD, GLIBC_MMAP_THRESHOLD_MAX)
            _mallopt(M_TRIM_THRESHOLD, 2 * GLIBC_MMAP_THRESHOLD_MAX)
