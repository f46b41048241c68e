"""Candidate fits side by side (issue 18): how many threads, and running jobs on them with their progress lines
kept together."""

from __future__ import annotations

import os
from typing import Callable, TypeVar

from ..core import Diagnostic, TnnError
from ..core.memory import release_free_memory

THREADS_ENV = "TNN_DOCTOR_THREADS"
"""Environment variable: the number of candidate fits run side by side (default: the CPUs this process may use, at
most ``MAX_THREADS``)."""
MAX_THREADS = 4

_A = TypeVar("_A")
_B = TypeVar("_B")


def fit_threads(threads: int | None = None) -> int:
    """How many candidate fits run side by side: ``threads`` if given, else ``$TNN_DOCTOR_THREADS``, else the CPUs
    this process may use (at most ``MAX_THREADS``: a round fits five candidates and continues three)."""
    if threads is None:
        env = os.environ.get(THREADS_ENV, "").strip()
        if env:
            try:
                threads = int(env)
            except ValueError:
                raise TnnError(Diagnostic(f"{THREADS_ENV}={env!r} is not a whole number",
                                          hint=f"set {THREADS_ENV} to 1 (one fit at a time) or more")) from None
        else:
            try:
                threads = min(MAX_THREADS, len(os.sched_getaffinity(0)))
            except AttributeError:  # not Linux
                threads = min(MAX_THREADS, os.cpu_count() or 1)
    if threads < 1:
        raise TnnError(Diagnostic(f"threads must be at least 1 (got {threads})", hint="use 1 for one fit at a time"))
    return int(threads)


def side_by_side(jobs: list[Callable[[Callable[[str], None]], object]], threads: int,
                 say: Callable[[str], None], first: list[int] | None = None) -> list:
    """Run ``jobs`` (each called with its own progress function) on up to ``threads`` threads; results in job order,
    and each job's progress lines said together, in job order, as the jobs finish. ``first``: the order the jobs
    are started in (a permutation of their indices; default job order) — the longest first, where the caller can
    tell, so that no thread is left alone with a long job at the end (the results and lines are the same).
    Candidate fits are independent (each on its own engine clone or network) and spend their time inside compiled
    simulations, where JAX releases the interpreter (torch runs one job at a time: the session sets ``threads`` =
    1). The case study's whole diagnosis on 2 cores: 356 s with one thread, 279 s with two, on a slow host
    (``benchmarks/bench_diagnose.py --threads 1,2``, 2026-11-29; BENCHMARKS.md)."""
    jobs = [_then_release(job) for job in jobs]
    if threads <= 1 or len(jobs) <= 1:
        return [job(say) for job in jobs]
    from concurrent.futures import ThreadPoolExecutor

    order = list(range(len(jobs))) if first is None else list(first)
    if sorted(order) != list(range(len(jobs))):
        raise ValueError(f"first must be a permutation of 0..{len(jobs) - 1}, got {first}")
    bufs: list[list[str]] = [[] for _ in jobs]
    out = []
    with ThreadPoolExecutor(max_workers=min(threads, len(jobs)), thread_name_prefix="tnn-doctor") as pool:
        started = {i: pool.submit(jobs[i], bufs[i].append) for i in order}
        futures = [started[i] for i in range(len(jobs))]
        for fut, buf in zip(futures, bufs):
            res = fut.result()
            for line in buf:
                say(line)
            out.append(res)
    return out


def two_at_once(beside: Callable[[], _A], here: Callable[[], _B], threads: int) -> tuple[_A, _B]:
    """``(beside(), here())``: with ``threads`` ≥ 2 ``beside`` runs on a second thread while ``here`` runs on this one
    (both waited for; an error in ``here`` is raised after ``beside`` ends, then one in ``beside``), else one after the
    other. For two independent pieces of work of one stretch that would leave a core idle (issue 18: a network's
    Jacobian program compiled beside its simulations', the MLP check's linear free run beside the MLP's training)."""
    if threads <= 1:
        a = beside()
        return a, here()
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="tnn-beside") as pool:
        job = pool.submit(beside)
        b = here()
        return job.result(), b


def _then_release(job: Callable[[Callable[[str], None]], object]) -> Callable[[Callable[[str], None]], object]:
    """``job``, then the C heap's free pages back to the system (a fit's arrays, freed on a heap that other
    results fragment, would otherwise keep the resident size at every fit's peak: ``core.memory``)."""
    def run(say: Callable[[str], None]) -> object:
        try:
            return job(say)
        finally:
            release_free_memory()

    return run
