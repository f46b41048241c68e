"""Compile the next trainings' torch programs ahead, in a process of their own, while this one trains.

A job that trains several networks one after the other on torch (``tnnc demo``: the thesis's M1–M5) pays each
network's compilation before its first epoch: 11–25 s per model of the case study on the Intel host (2026-12-02),
four fifths of it inductor and the C++ compiler (dynamo's tracing the rest; ``benchmarks/profile_demo_compile.py``),
while the training itself runs on one core (``torch.set_num_threads(1)``) and the machine's second core idles. torch
keeps compiled scans in its on-disk caches (:data:`tnn_dsl.compiler.model.TORCH_CACHE_SCANS`, keyed by the graph,
not by the process), so a helper process that trains the *later* networks for one epoch on the same data and options
compiles the very graphs the main process will ask for, and the main process then loads them instead of compiling
(``tests/test_compile_ahead.py``). ``tnnc demo --backend torch`` (BENCHMARKS.md, "The demos with torch's compiled
scans cached and compiled ahead"): M2–M5 compiled for 4.7, 4.4, 3.7 and 5.8 s against 12.1, 17.6, 17.1 and 24.8 s
with the helper off.

The helper only warms caches: it writes no model (``out=None``), prints nothing, runs at a lower priority
(``nice`` 10), and a failure in it changes nothing but the time the main process spends compiling. What the main
process computes does not depend on it: a cached program is the program the main process would have compiled
(the cache key holds the graph's code, constants and shapes). It stops after its last job, when its parent goes
away, or when :meth:`CompileAhead.close` (the context manager's exit) terminates it.

    with CompileAhead([Job(net_path, train_paths, val_paths, options), ...]):
        for each network: train(...)

``TNN_COMPILE_AHEAD=0`` turns it off wherever it would start (:func:`wanted`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import asdict, dataclass, field
from typing import Any, Sequence

__all__ = ["CompileAhead", "Job", "wanted"]

ENV = "TNN_COMPILE_AHEAD"
"""Environment switch: ``0`` never compiles ahead; ``1`` does where the caller would (:func:`wanted`)."""

NICE = 10
"""The helper's niceness increment: it yields the CPU to the main process where they contend."""

MIN_AVAILABLE_BYTES = 2 * 2**30
"""The memory the machine must have available (``MemAvailable`` of ``/proc/meminfo``, where there is one) for the
helper to start: its peak resident size was 614 MB in ``tnnc demo --backend torch`` (a training of the case study
on torch, 2026-12-02), beside the main process's 882 MB."""


@dataclass
class Job:
    """One training to compile ahead: the network (a ``.thn`` path; its includes resolve as for the main
    process), the training and validation data (paths), and the options of :func:`tnn_dsl.fit.train` that shape
    the compiled graphs (integrator, windows, batch, dtype, …; the schedule is replaced: one epoch, no L-BFGS,
    ``torch_compile=True``)."""

    network: str
    train: list[str]
    val: list[str] | None = None
    options: dict[str, Any] = field(default_factory=dict)
    init_from: int | None = None
    """The index of an earlier job whose model this network's ``init_from`` clauses read (the thesis's M5
    freezes M4's Peltier network): the helper writes that job's one-epoch model to a directory of its own and
    points the clauses there. Frozen weights enter the compiled graphs as inputs, so their values do not matter to
    the cache; their shapes do."""


def wanted(backend: str, n_jobs: int) -> bool:
    """Whether compiling ahead can pay here: torch, at least one job, a second core for the helper, memory to spare
    (:data:`MIN_AVAILABLE_BYTES`, where the system tells), and ``TNN_COMPILE_AHEAD`` not ``0``."""
    if os.environ.get(ENV, "").strip() == "0":
        return False
    if not (backend == "torch" and n_jobs > 0 and (os.cpu_count() or 1) >= 2):
        return False
    available = _available_bytes()
    return available is None or available >= MIN_AVAILABLE_BYTES


def _available_bytes() -> int | None:
    """``MemAvailable`` of ``/proc/meminfo`` in bytes, or None where there is none."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


class CompileAhead:
    """The helper process for ``jobs`` (started at construction; a context manager that stops it on exit)."""

    def __init__(self, jobs: Sequence[Job]):
        self.proc: subprocess.Popen | None = None
        if not jobs:
            return
        env = {**os.environ, "TORCHINDUCTOR_COMPILE_THREADS": "1", ENV: "0"}
        try:
            self.proc = subprocess.Popen([sys.executable, "-m", __name__], stdin=subprocess.PIPE,
                                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
                                         text=True)
            assert self.proc.stdin is not None
            self.proc.stdin.write(json.dumps({"parent": os.getpid(), "jobs": [asdict(j) for j in jobs]}))
            self.proc.stdin.close()
        except OSError:  # no helper: the main process compiles as it always did
            self.proc = None

    def close(self) -> None:
        """Stop the helper if it still runs (it holds no files of the user's; killing it loses only warm-up)."""
        proc, self.proc = self.proc, None
        if proc is None or proc.poll() is not None:
            return
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()

    def __enter__(self) -> "CompileAhead":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _run(spec: dict) -> None:
    """The helper's body: each job trained for one epoch with its graphs compiled, nothing written; stops early
    when the parent process is gone."""
    import tempfile
    from pathlib import Path

    from ..lang import load
    from . import train

    parent = int(spec.get("parent", 0))
    jobs = spec["jobs"]
    read_later = {j["init_from"] for j in jobs if j.get("init_from") is not None}
    written: dict[int, str] = {}
    with tempfile.TemporaryDirectory(prefix="tnn_compile_ahead_") as tmp:
        for i, job in enumerate(jobs):
            if parent and os.getppid() != parent:
                return
            options = {k: v for k, v in job.get("options", {}).items()
                       if k not in ("epochs", "lbfgs_iters", "time_limit", "torch_compile", "backend")}
            out = str(Path(tmp) / f"job{i}") if i in read_later else None
            try:
                net = load(job["network"])
                k = job.get("init_from")
                if k is not None:
                    if k not in written:
                        continue
                    net = net.model_copy(update={"learned": [
                        fn.model_copy(update={"init_from": written[k]}) if fn.init_from else fn for fn in net.learned]})
                train(net, job["train"], val=job.get("val"), out=out, backend="torch", epochs=1, lbfgs_iters=0,
                      time_limit=None, torch_compile=True, **options)
            except Exception:  # noqa: BLE001 - a warm-up only: the main process compiles what this did not
                continue
            if out is not None:
                written[i] = out


def main() -> int:
    import signal

    # terminated (CompileAhead.close): unwind, so that the temporary directory of the models it wrote goes too
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    try:
        os.nice(NICE)
    except OSError:  # pragma: no cover - not permitted here: run at the same priority
        pass
    _run(json.loads(sys.stdin.read()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
