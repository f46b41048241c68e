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

Each such mapping is fresh memory, though: the kernel hands it out a 4 KiB page at a time, one page fault each, and
the case study's diagnosis took 4.5–4.7 million of them (14.5–15.3 s of system time). :func:`huge_pages_environment`
is the environment in which glibc asks for transparent huge pages on those mappings (a fault per 2 MiB); ``tnnc``
starts its doctor's commands again in it (``tnn_dsl.cli.entry``).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
import sys
from contextlib import contextmanager
from functools import lru_cache
from typing import Iterator, Mapping


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


def freeze_live_objects() -> None:
    """Collect the garbage, then move every object alive now to the collector's permanent generation
    (``gc.freeze``): its full collections from then on walk only what was made later. For a process of ours once its
    libraries are imported (``tnnc diagnose``: JAX's, SciPy's and our modules, about 150 000 objects that every full
    collection of the diagnosis walked again; the case study's ten full collections took 0.90 s, 0.38 s after this,
    issue 18). Not for a library call: the caller's objects would never be collected while frozen."""
    gc.collect()
    gc.freeze()


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


HUGE_PAGES_ENV = "TNN_HUGE_PAGES"
"""Environment switch: ``0`` keeps glibc's mapped blocks on ordinary pages (:func:`huge_pages_environment` returns
None)."""

GLIBC_HUGETLB = "glibc.malloc.hugetlb"
"""glibc's tunable (2.35 and later; read once, when a program starts): ``1`` makes ``malloc`` advise transparent huge
pages (``madvise(MADV_HUGEPAGE)``) on the memory it maps."""

THP_MODE_FILE = "/sys/kernel/mm/transparent_hugepage/enabled"
"""Where Linux tells its transparent-huge-page mode: ``always [madvise] never`` (the one in brackets is set)."""


def _thp_mode() -> str | None:
    """The kernel's transparent-huge-page mode (``always``, ``madvise``, ``never``), or None where it does not say."""
    try:
        with open(THP_MODE_FILE) as f:
            text = f.read()
    except OSError:
        return None
    start, end = text.find("["), text.find("]")
    return text[start + 1: end] if 0 <= start < end else None


def _glibc_version() -> tuple[int, int] | None:
    libc = _glibc()
    if libc is None:
        return None
    try:
        major, minor = libc.gnu_get_libc_version().decode().split(".")[:2]
        return int(major), int(minor)
    except (ValueError, UnicodeDecodeError):
        return None


def huge_pages_environment(env: Mapping[str, str] | None = None, *, thp_mode: str | None = None,
                           glibc_version: tuple[int, int] | None = None) -> dict[str, str] | None:
    """``env`` (default ``os.environ``) with ``GLIBC_TUNABLES`` extended by ``glibc.malloc.hugetlb=1``: a program
    started in it gets transparent huge pages on the blocks its ``malloc`` maps, a page fault per 2 MiB instead of
    per 4 KiB. Returns None where that would change nothing or is not wanted: off glibc or before glibc 2.35, the
    kernel's mode other than ``madvise`` (``always`` gives the huge pages anyway, ``never`` not at all), the tunable
    already set (whatever its value: the user's, or a program started again), or ``TNN_HUGE_PAGES=0``. ``thp_mode``
    and ``glibc_version`` stand in for the machine's (tests).

    Why: inside :func:`large_blocks_mapped` every simulation's temporaries and every Jacobian (1–100 MB on the case
    study) is a fresh mapping, each of its pages faulted in and zeroed on first touch. ``tnnc diagnose`` of the case
    study, three pairs alternating (2026-12-07 13:12–13:19 UTC, AMD EPYC, 2 cores, 0.82–0.89 s per 10⁷ Python
    additions; ``perf stat -e page-faults``): 4.50–4.73 million page faults and 14.5–15.3 s of system time without,
    1.49–1.79 million and 7.6–9.0 s with; wall 75.4–78.4 s against 67.6–70.2 s; peak resident 555–557 against
    555–561 MB (glibc advises its heap's growth too); the same diagnosis (its JSON but for the timings)."""
    env = dict(os.environ if env is None else env)
    if env.get(HUGE_PAGES_ENV, "").strip() == "0":
        return None
    tunables = env.get("GLIBC_TUNABLES", "")
    if GLIBC_HUGETLB in tunables:
        return None
    version = _glibc_version() if glibc_version is None else glibc_version
    if version is None or version < (2, 35):
        return None
    if (_thp_mode() if thp_mode is None else thp_mode) != "madvise":
        return None
    env["GLIBC_TUNABLES"] = f"{tunables}:{GLIBC_HUGETLB}=1" if tunables else f"{GLIBC_HUGETLB}=1"
    return env
