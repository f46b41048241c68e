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

A single training compiles two graphs one after the other on torch: the forward scan, then, at its first backward
pass, the adjoint's reverse scan (:mod:`tnn_dsl.compiler.torch_adjoint`; 10–14 s each for the case study's M2 on the
AMD host). :class:`CompileBeside` compiles the second while the training compiles the first: a helper process trains
the same network on the same data for one epoch with its forward scans uncompiled, so that it reaches the reverse
scan's compilation within seconds, says so on its standard output, compiles it into torch's on-disk cache and exits.
The training waits for it at its first backward pass (:data:`BESIDE_WAIT_S` at most) and loads the program instead
of compiling it: the same program, so the same numbers to the bit, whether or not the helper ran or finished
(``tests/test_compile_ahead.py``). Where the helper has not begun compiling when the training needs the graph (a warm
cache, a busy machine), the training compiles it itself and stops the helper. :func:`train` starts it where
:func:`beside_wanted` says it can pay.

``TNN_COMPILE_AHEAD=0`` turns both off wherever they would start (:func:`wanted`)."""

from __future__ import annotations

import base64
import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, field, fields
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

if TYPE_CHECKING:
    from ..data import Experiment
    from ..ir import Network

__all__ = ["BESIDE_WAIT_S", "CompileAhead", "CompileBeside", "Job", "beside_wanted", "wanted"]

ENV = "TNN_COMPILE_AHEAD"
"""Environment switch: ``0`` never compiles ahead; ``1`` does where the caller would (:func:`wanted`)."""

NICE = 10
"""The helper's niceness increment: it yields the CPU to the main process where they contend."""

BESIDE_WAIT_S = 60.0
"""The longest a training waits at its first backward pass for :class:`CompileBeside`'s helper once the helper has
begun compiling the reverse scan (s). The compilation took 10–14 s on the AMD host (the case study's M2,
2026-12-08); a helper still compiling after this is taken as stuck, stopped, and the training compiles the graph
itself."""

BEGUN = "compiling the reverse scan"
"""The line :class:`CompileBeside`'s helper prints when it begins compiling."""

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


def beside_wanted(backend: str, torch_compile: bool | None) -> bool:
    """Whether :class:`CompileBeside` can pay for a training: its rollouts compiled on torch (``torch_compile``
    true), :func:`wanted`'s conditions, no :class:`CompileAhead` open in this process (a study whose later
    trainings are compiled ahead: their graphs are in the cache, and a third process would slow the second), and the
    training run on the main thread (the hook it sets is the process's: a training on another thread — the model
    doctor's MLP check beside its other work — may share the process with another)."""
    main_thread = threading.current_thread() is threading.main_thread()
    return bool(torch_compile) and CompileAhead.open_count == 0 and main_thread and wanted(backend, 1)


class CompileAhead:
    """The helper process for ``jobs`` (started at construction; a context manager that stops it on exit)."""

    open_count = 0
    """How many are open (started and not yet closed) in this process."""

    def __init__(self, jobs: Sequence[Job]):
        self.proc: subprocess.Popen | None = None
        self._open = False
        if not jobs:
            return
        CompileAhead.open_count += 1
        self._open = True
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
        if self._open:
            self._open = False
            CompileAhead.open_count -= 1
        proc, self.proc = self.proc, None
        _stop(proc)

    def __enter__(self) -> "CompileAhead":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _stop(proc: subprocess.Popen | None) -> None:
    """Terminate a helper if it still runs (it holds no files of the user's; killing it loses only warm-up)."""
    if proc is None or proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class CompileBeside:
    """The helper that compiles a training's reverse scan while the training compiles its forward scan (the module's
    docstring). Started at construction with the training's network (its IR as JSON), data (the arrays, through the
    helper's standard input: no file is written) and options; a context manager that makes the training wait for it
    at its first backward pass (:data:`tnn_dsl.compiler.torch_adjoint.SHARED`) and stops it on exit.

        with CompileBeside(net, exps, vals, cfg.to_dict()):
            ... train ...

    ``wait()`` (the hook): returns at once when no helper runs or it has not begun compiling (it is stopped then:
    the training compiles the graph itself); else when the helper has exited (its program in the cache), or after
    :data:`BESIDE_WAIT_S`. ``waited_s`` sums the seconds spent waiting; ``outcome`` says what happened (None before
    the training asked)."""

    def __init__(self, network: "Network", train: Sequence["Experiment"], val: Sequence["Experiment"] | None,
                 options: dict[str, Any]):
        self.proc: subprocess.Popen | None = None
        self.waited_s = 0.0
        self.outcome: str | None = None
        self._begun = threading.Event()
        self._hooked = False
        # (no parent pid as CompileAhead's jobs have: a helper whose training has gone fails writing its line)
        spec = {"beside": {"network": network.to_json(indent=None), "train": [encode_experiment(e) for e in train],
                           "val": [encode_experiment(e) for e in val or ()], "options": _beside_options(options)}}
        env = {**os.environ, "TORCHINDUCTOR_COMPILE_THREADS": "1", ENV: "0"}
        try:
            self.proc = subprocess.Popen(_beside_argv(), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                         stderr=subprocess.DEVNULL, env=env, text=True)
            assert self.proc.stdin is not None and self.proc.stdout is not None
            threading.Thread(target=self._read, args=(self.proc.stdout,), daemon=True).start()
            self.proc.stdin.write(json.dumps(spec))
            self.proc.stdin.close()
        except OSError:  # no helper: the training compiles as it always did
            _stop(self.proc)
            self.proc = None

    def _read(self, out) -> None:
        for line in out:
            if line.strip() == BEGUN:
                self._begun.set()

    def wait(self) -> None:
        """Block until the helper's reverse scan is in the cache, where it is on its way (the class docstring)."""
        proc = self.proc
        if proc is None:
            return
        if proc.poll() is None and not self._begun.is_set():
            self.close()  # behind the training: compiling beside it now would only take the second core
            self.outcome = ("the helper had not begun compiling the reverse scan when the training needed it: "
                            "compiled here")
            return
        t = time.monotonic()
        try:
            rc: int | None = proc.wait(timeout=BESIDE_WAIT_S)
        except subprocess.TimeoutExpired:
            rc = None
        self.waited_s += time.monotonic() - t
        self.close()
        waited = f"after waiting {self.waited_s:.1f} s"
        self.outcome = (f"the reverse scan compiled by the helper, {waited}" if rc == 0 and self._begun.is_set()
                        else f"the helper ended with status {rc} {waited}: compiled here" if rc is not None
                        else f"the helper still compiling {waited}: stopped, compiled here")

    def close(self) -> None:
        """Stop the helper if it still runs."""
        proc, self.proc = self.proc, None
        _stop(proc)

    def __enter__(self) -> "CompileBeside":
        from ..compiler.torch_adjoint import SHARED

        if self.proc is not None and SHARED.before_backward is None:
            SHARED.before_backward, self._hooked = self.wait, True
        return self

    def __exit__(self, *exc) -> None:
        from ..compiler.torch_adjoint import SHARED

        if self._hooked:
            SHARED.before_backward, self._hooked = None, False
        self.close()


def _beside_argv() -> list[str]:
    """The command of :class:`CompileBeside`'s helper (this module run as a script; it reads its spec on stdin)."""
    return [sys.executable, "-m", __name__]


def _beside_options(options: dict[str, Any]) -> dict[str, Any]:
    """The training's options for the helper: one epoch of Adam, no L-BFGS, no time limit, compiled torch."""
    return {**options, "epochs": 1, "lbfgs_iters": 0, "time_limit": None, "torch_compile": True, "backend": "torch"}


def encode_experiment(e: "Experiment") -> dict[str, Any]:
    """An :class:`~tnn_dsl.data.Experiment` as JSON-ready values (arrays as dtype, shape and base64 bytes; its
    warnings left out: the helper reads no file); :func:`decode_experiment` undoes it."""
    out: dict[str, Any] = {}
    for f in fields(e):
        v = getattr(e, f.name)
        if f.name == "warnings":
            continue
        if isinstance(v, np.ndarray):
            a = np.ascontiguousarray(v)
            out[f.name] = {"dtype": a.dtype.str, "shape": list(a.shape), "data": base64.b64encode(a.tobytes()).decode()}
        elif isinstance(v, tuple):
            out[f.name] = list(v)
        else:
            out[f.name] = v
    return out


def decode_experiment(d: dict[str, Any]) -> "Experiment":
    """The :class:`~tnn_dsl.data.Experiment` of :func:`encode_experiment` (the same arrays, bit for bit)."""
    from ..data import Experiment

    kw: dict[str, Any] = {}
    for f in fields(Experiment):
        if f.name not in d:
            continue
        v = d[f.name]
        if isinstance(v, dict):
            dtype = np.dtype(v["dtype"])
            if dtype.hasobject:
                raise ValueError(f"{f.name}: object arrays are not sent to the helper")
            v = np.frombuffer(base64.b64decode(v["data"]), dtype=dtype).reshape(v["shape"]).copy()
        elif isinstance(v, list):
            v = tuple(v)
        kw[f.name] = v
    return Experiment(**kw)


def _run_beside(spec: dict) -> None:
    """The body of :class:`CompileBeside`'s helper: the training's one-epoch copy, with its forward scans
    uncompiled, that prints :data:`BEGUN` before compiling its first reverse scan and exits as soon as that is
    compiled (the program is in torch's on-disk cache)."""
    from ..compiler.torch_adjoint import SHARED
    from ..ir import Network
    from . import train

    def begun() -> None:
        print(BEGUN, flush=True)

    def done() -> None:
        os._exit(0)  # the cache is written; nothing else of this process is of use

    SHARED.before_backward, SHARED.after_backward, SHARED.eager_forward = begun, done, True
    net = Network.from_json(spec["network"])
    exps = [decode_experiment(d) for d in spec["train"]]
    vals = [decode_experiment(d) for d in spec["val"]] or None
    train(net, exps, val=vals, config=spec["options"])


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
    spec = json.loads(sys.stdin.read())
    if "beside" in spec:
        try:
            _run_beside(spec["beside"])
        except Exception:  # noqa: BLE001 - a warm-up only: the training compiles what this did not
            return 1
        return 0
    _run(spec)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
