"""Running a fleet: every unit's work (:func:`tnn_dsl.fleet.units.run_unit`) as a Ray task, each result written
atomically under ``OUT/units/<unit>/`` as it arrives, then the fleet report.

* **Ray**: a local Ray started on demand (``ray.init(num_cpus=workers)``) and stopped at the end, or an existing
  cluster (``address="auto"`` or ``"HOST:PORT"``, left running). ``workers=0`` runs the units one by one in this
  process, without Ray (the reference the Ray path is tested against).
* **Resume**: a unit whose ``result.json`` holds the same key (template text, the unit's entry, the options, the
  SHA-256 of its data files: :func:`~tnn_dsl.fleet.units.unit_key`) is not run again; a unit that ended in an
  internal error is.
* **Isolation**: a unit whose data cannot be read, or whose fit fails, gets a ``failed`` row saying why; the rest
  go on. A worker that dies is retried once by Ray (``max_retries=1``), then the unit is reported as ``error``.
* **Ctrl-C**: the pending tasks are cancelled; every unit whose result had arrived is on disk (each is written as
  it arrives); the next run continues from there.
* Only the driver reads the data files and writes ``OUT`` (the workers receive arrays and return bytes), so a
  cluster needs no shared file system: only ``tnn_dsl`` installed on its nodes.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..core import Diagnostic, OutputKind, TnnError, check_output, file_sha256, fsync_dir, write_text_atomic
from ..core.files import exchange_paths
from .manifest import Fleet, read_fleet
from .units import FleetOptions, run_batch, run_unit, unit_key, unit_network

__all__ = ["run_fleet", "FleetRun", "FLEET_DIR", "RESULT_FILE", "load_results", "auto_batch", "BATCH_MAX"]

RESULT_FILE = "result.json"
REPLACED = "replaced"
"""Under ``OUT``: a unit's earlier results, moved here when a re-run replaces them (its data, entry, options or
the template changed): a re-run never deletes a trained model."""
FLEET_FILE = "fleet.json"


def _is_fleet_dir(p: Path) -> bool:
    return (p / FLEET_FILE).is_file() and (p / "units").is_dir() or not any(p.iterdir())


FLEET_DIR = OutputKind("fleet output directory", is_dir=True, ours=_is_fleet_dir, example="fleet_out/")


@dataclass
class FleetRun:
    """What :func:`run_fleet` did: ``rows`` (one result row per unit, in the fleet's order, without the model
    bytes), ``ran``/``skipped`` (unit names run now / found finished), ``interrupted`` (Ctrl-C), ``out`` (the
    directory), ``seconds``, ``report`` (the fleet report, :func:`tnn_dsl.fleet.report.fleet_report`)."""

    rows: list[dict[str, Any]]
    ran: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    interrupted: bool = False
    out: str = ""
    seconds: float = 0.0
    report: dict[str, Any] = field(default_factory=dict)


def _unit_dir(out: Path, name: str) -> Path:
    return out / "units" / name


def load_results(out: str | os.PathLike) -> dict[str, dict[str, Any]]:
    """``{unit: row}`` of the finished units under ``out`` (their ``result.json``); unreadable ones are left out
    (they are run again)."""
    res = {}
    base = Path(out) / "units"
    if not base.is_dir():
        return res
    for d in sorted(base.iterdir()):
        f = d / RESULT_FILE
        if d.is_dir() and not d.name.startswith(".") and f.is_file():
            try:
                row = json.loads(f.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                continue
            if isinstance(row, dict) and row.get("unit") == d.name:
                res[d.name] = row
    return res


def _write_unit(out: Path, row: dict[str, Any], key: str) -> dict[str, Any]:
    """Write one unit's result in one step: everything into a hidden sibling directory, then renamed (or swapped
    with the unit's previous result, which is then removed) into ``OUT/units/<unit>/``."""
    name = row["unit"]
    final = _unit_dir(out, name)
    tmp = out / "units" / f".{name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)  # our own leftover from a killed run (hidden name with our pid)
    tmp.mkdir(parents=True)
    written = []  # what the unit's directory holds beside its result, for the report to point at
    for sub in ("model", "extended_model"):  # the unit's trained model; the doctor's extended one (diagnose)
        files = row.pop(sub, None) or {}
        if files:
            (tmp / sub).mkdir()
            for fname, data in files.items():
                (tmp / sub / Path(fname).name).write_bytes(data)
            written.append(sub)
    if row.get("extended"):
        (tmp / "extended.thn").write_text(row["extended"], encoding="utf-8")
        written.append("extended.thn")
    doc = {**row, "files": sorted(written), "key": key}
    (tmp / RESULT_FILE).write_text(json.dumps(doc, indent=1, default=_jsonable), encoding="utf-8")
    fsync_dir(tmp)
    if final.exists():  # the unit's previous result (its key changed): kept under OUT/replaced/, never deleted
        if not exchange_paths(tmp, final):
            old = out / "units" / f".{name}.old-{os.getpid()}"
            os.rename(final, old)
            os.rename(tmp, final)
            tmp = old
        keep = out / REPLACED / f"{name}.{time.strftime('%Y%m%dT%H%M%S')}.{os.getpid()}"
        keep.parent.mkdir(exist_ok=True)
        os.rename(tmp, keep)
    else:
        os.rename(tmp, final)
    fsync_dir(out / "units")
    return doc


def _remove_partial_writes(out: Path) -> None:
    """A killed run may leave a unit half written in a hidden ``.<unit>.tmp-<pid>``: never a finished result (that
    is only ever ``units/<unit>/``, and a replaced one ``replaced/<unit>.<time>.<pid>``); removed. A hidden
    ``.<unit>.old-<pid>`` (a replaced result caught between two renames) is moved to ``replaced/``."""
    import re

    pat = re.compile(r"^\..+\.tmp-\d+$")
    old = re.compile(r"^\.(.+)\.old-(\d+)$")
    for p in (out / "units").iterdir():
        if p.is_dir() and not p.is_symlink() and pat.match(p.name):
            shutil.rmtree(p)
        elif p.is_dir() and not p.is_symlink() and (m := old.match(p.name)):
            (out / REPLACED).mkdir(exist_ok=True)
            os.rename(p, out / REPLACED / f"{m.group(1)}.recovered.{m.group(2)}")


def _jsonable(x: Any) -> Any:
    from ..core.jsonable import to_jsonable

    return to_jsonable(x)


def _read_unit(net, unit) -> tuple[list, list]:
    from ..data import read_data

    unet = unit_network(net, unit.to_dict())
    train = read_data(unet, list(unit.train))
    val = read_data(unet, list(unit.val)) if unit.val else []
    return train, val


KILL_WORKER_ENV = "TNN_FLEET_KILL_WORKER"
"""Fault injection for the tests of a dying worker (comma-separated entries): ``UNIT`` makes the process running
that unit exit at once, every time; ``UNIT:FILE`` only while ``FILE`` does not exist (it is created first: the
worker dies once and its retry lives)."""


def _task(template_text: str, template_file: str, members: list[tuple[dict[str, Any], list, list]],
          options: FleetOptions) -> list[dict[str, Any]]:
    """One task in a worker (or in this process): the template parsed, each unit's overrides applied, the work
    done — one unit, or a batch of units of one structure fitted in one compiled program
    (:func:`~tnn_dsl.fleet.units.run_batch`). Returns the units' rows."""
    from ..lang import loads

    _maybe_die([u["name"] for u, _t, _v in members])
    torch_threads()
    rows: list[dict[str, Any] | None] = [None] * len(members)
    ok: list[tuple[int, Any, tuple]] = []
    try:
        template = loads(template_text, template_file)
    except TnnError as e:
        return [{"unit": u["name"], "status": "failed", "reason": str(e).strip(), "params": {}, "findings": []}
                for u, _t, _v in members]
    for i, (u, t, v) in enumerate(members):
        try:
            ok.append((i, unit_network(template, u), (u, t, v)))
        except TnnError as e:
            rows[i] = {"unit": u["name"], "status": "failed", "reason": str(e).strip(), "params": {}, "findings": []}
    if ok:
        # the engine batches units with the same overrides only: one network for the batch
        done = run_batch(ok[0][1], [m for _i, _n, m in ok], options, networks=[n for _i, n, _m in ok]) \
            if len(ok) > 1 else [run_unit(ok[0][1], *ok[0][2], options)]
        for (i, _n, _m), row in zip(ok, done):
            rows[i] = row
    return [r for r in rows if r is not None]


def _maybe_die(names: list[str]) -> None:
    for entry in filter(None, os.environ.get(KILL_WORKER_ENV, "").split(",")):
        unit, _, marker = entry.partition(":")
        if unit not in names:
            continue
        if marker:
            if os.path.exists(marker):
                continue
            with open(marker, "w", encoding="utf-8") as f:
                f.write("died once\n")
        os._exit(70)


BATCH_MAX = 16
"""The largest batch of units fitted in one compiled program (``--batch auto``): the joint program's compile time
and each L-BFGS step grow with the units in it (BENCHMARKS.md, fleet)."""


def auto_batch(n_units: int, workers: int, options: FleetOptions) -> int:
    """``--batch auto``: units per task. ``train``: the units spread evenly over the workers (``workers=0``: one
    process), at most :data:`BATCH_MAX` per batch, one by one where a worker would get fewer than two;
    ``diagnose``: one (the doctor runs unit by unit)."""
    if options.mode != "train":
        return 1
    per_worker = -(-n_units // max(int(workers), 1))
    return 1 if per_worker < 2 else min(BATCH_MAX, per_worker)


def _batches(jobs: list[tuple[dict[str, Any], list, list]], size: int) -> list[list[tuple[dict[str, Any], list, list]]]:
    """The units in tasks of at most ``size``: units with the same known values (``params:`` overrides, so the same
    free constants) and one training file each, in the fleet's order; every other unit alone."""
    if size <= 1:
        return [[j] for j in jobs]
    groups: dict[str, list] = {}
    alone = []
    for j in jobs:
        u, train, _val = j
        if len(train) != 1:
            alone.append([j])
            continue
        groups.setdefault(json.dumps(u.get("params") or {}, sort_keys=True), []).append(j)
    out = []
    for members in groups.values():
        n = -(-len(members) // size)  # as many tasks as needed, evenly filled
        k = -(-len(members) // n)
        out += [members[i:i + k] for i in range(0, len(members), k)]
    return out + alone


def torch_threads() -> None:
    """One intra-op thread per worker (the workers share the cores)."""
    try:
        import torch

        torch.set_num_threads(1)
    except Exception:  # noqa: BLE001 - torch absent or already set: nothing to do
        pass


COMPILE_CACHE = ".jax_cache"
"""Under ``OUT``: JAX's persistent compilation cache shared by the units (one structure, one data length: the
programs of the second unit on are read, not compiled), unless the environment names one already."""


def _cache_env(out: Path) -> dict[str, str]:
    """The JAX cache settings of the units' processes: the directory ``JAX_COMPILATION_CACHE_DIR`` names where the
    user set one (a cache kept across runs: a second fleet run, or a fleet after a single unit's ``tnnc train``,
    reads the programs instead of compiling them), else ``OUT/.jax_cache``; every program kept either way (JAX's
    default keeps only those that took over a second to compile, and a unit's take less)."""
    from ..compiler.backends.jax_ops import CACHE_THRESHOLDS

    where = os.environ.get("JAX_COMPILATION_CACHE_DIR", "").strip()
    return {"JAX_COMPILATION_CACHE_DIR": str(Path(where).expanduser().resolve() if where
                                             else (out / COMPILE_CACHE).resolve()),
            **{env: f"{value:g}" for env, (_, value) in CACHE_THRESHOLDS.items()}}


WORKER_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
"""XLA's flags for a local Ray's workers: one thread each (the workers share the cores)."""


def worker_env(cache_env: dict[str, str]) -> dict[str, str]:
    """The environment variables a local Ray's workers start with: one thread per numerical library, no helper
    processes compiling beside a training (``TNN_COMPILE_AHEAD=0``, :mod:`tnn_dsl.fit.compile_ahead`: the workers
    already take the cores), JAX's cache (``cache_env``, :func:`_cache_env`), and ``XLA_FLAGS`` holding the user's
    own flags (this process's, which a worker would otherwise not see: Ray's ``env_vars`` replace a variable)
    followed by :data:`WORKER_XLA_FLAGS`."""
    xla = " ".join(f for f in (os.environ.get("XLA_FLAGS", "").strip(), WORKER_XLA_FLAGS) if f)
    return {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "TNN_COMPILE_AHEAD": "0",
            "XLA_FLAGS": xla, **cache_env}


def _use_cache_here(env: dict[str, str]) -> None:
    """JAX's persistent compilation cache for the units run in this process."""
    import jax

    from ..compiler.backends.jax_ops import CACHE_THRESHOLDS

    jax.config.update("jax_compilation_cache_dir", env["JAX_COMPILATION_CACHE_DIR"])
    for option, value in CACHE_THRESHOLDS.values():
        jax.config.update(option, value)


def run_fleet(network: str | os.PathLike, fleet: str | os.PathLike | Fleet, out: str | os.PathLike, *,
              options: FleetOptions | None = None, workers: int = 2, address: str | None = None,
              force: bool = False, progress: Callable[[str], None] | None = None,
              compile_cache: bool = True, batch: int | None = None) -> FleetRun:
    """Fit (``options.mode="train"``) or diagnose (``"diagnose"``) every unit of ``fleet`` with the network template
    ``network`` (a ``.thn`` path), writing each unit's result under ``out/units/<unit>/`` and the fleet report
    (``out/report.json``, ``out/report.html``). ``workers``: Ray CPUs of a local Ray (0: this process, no Ray);
    ``address``: an existing Ray cluster (``"auto"`` or ``"HOST:PORT"``). ``force``: allow ``out`` to hold a
    fleet run with other options or another network (its units are then redone as their keys differ).
    ``compile_cache``: share JAX's persistent compilation cache between the units (``OUT/.jax_cache``, or the
    directory ``JAX_COMPILATION_CACHE_DIR`` names where set; with ``workers=0`` it stays set in this process's JAX
    configuration afterwards). ``batch``: units per task, fitted
    in one compiled program (:func:`~tnn_dsl.fleet.units.run_batch`; 1: one unit per task; ``None``:
    :func:`auto_batch`).
    Returns a :class:`FleetRun`; Ctrl-C returns one with ``interrupted`` set after the finished units are written."""
    from ..lang import load

    t0 = time.perf_counter()
    say = progress or (lambda s: None)
    options = options or FleetOptions()
    fl = fleet if isinstance(fleet, Fleet) else read_fleet(fleet)
    template_path = Path(network)
    inputs = [str(template_path), fl.source] + [f for u in fl.units for f in (*u.train, *u.val)]
    outp = check_output(out, FLEET_DIR, inputs=inputs, force=force, option="-o")
    net = load(template_path)
    template_text = template_path.read_text(encoding="utf-8")
    _check_same_run(outp, net.name, template_text, options, force)
    (outp / "units").mkdir(parents=True, exist_ok=True)
    _remove_partial_writes(outp)
    header = {"tool": "tnnc fleet", "network": net.name, "template": str(template_path),
              "template_sha256": _sha(template_text), "fleet": fl.source, "options": options.to_dict(),
              "units": [u.name for u in fl.units], "status": "running", "started": time.time()}
    write_text_atomic(outp / FLEET_FILE, json.dumps(header, indent=1))

    done = load_results(outp)
    rows: dict[str, dict[str, Any]] = {}
    jobs: list[tuple[Any, ...]] = []
    keys: dict[str, str] = {}
    run = FleetRun(rows=[], out=str(outp))
    for u in fl.units:
        try:
            digest = "+".join(file_sha256(f) for f in (*u.train, *u.val))
        except OSError as e:
            digest = f"unreadable: {e}"
        key = keys[u.name] = unit_key(template_text, u.to_dict(), options, digest)
        prev = done.get(u.name)
        if prev is not None and prev.get("key") == key and prev.get("status") in ("ok", "failed"):
            rows[u.name] = prev
            run.skipped.append(u.name)
            continue
        try:
            train, val = _read_unit(net, u)
        except TnnError as e:  # the unit's data is at fault: its row says why, the rest go on
            rows[u.name] = _write_unit(outp, {"unit": u.name, "status": "failed", "reason": str(e).strip(),
                                              "params": {}, "findings": [], "val_mae": None, "gain": None}, key)
            run.ran.append(u.name)
            say(f"{u.name}: failed: {str(e).strip().splitlines()[0]}")
            continue
        jobs.append((u.to_dict(), train, val))
    if run.skipped:
        say(f"{len(run.skipped)} of {len(fl.units)} units already finished in {outp}: not run again")
    size = auto_batch(len(jobs), workers if address is None else max(workers, 1), options) if batch is None \
        else max(int(batch), 1)
    tasks = [(template_text, str(template_path), members, options) for members in _batches(jobs, size)]
    if size > 1 and jobs:
        say(f"{len(jobs)} units in {len(tasks)} tasks (up to {size} units fitted together per task)")

    def arrived(row: dict[str, Any]) -> None:
        rows[row["unit"]] = _write_unit(outp, row, keys[row["unit"]])
        run.ran.append(row["unit"])
        n = len(rows)
        extra = f" ({row.get('reason', '').splitlines()[0]})" if row.get("status") != "ok" and row.get("reason") else ""
        say(f"[{n}/{len(fl.units)}] {row['unit']}: {row.get('status')}{extra}")

    env = _cache_env(outp) if compile_cache else {}
    try:
        if tasks:
            if workers <= 0 and address is None:
                if env:
                    _use_cache_here(env)
                for task in tasks:
                    for row in _task(*task):
                        arrived(row)
            else:
                _run_on_ray(tasks, workers, address, arrived, say, env)
    except KeyboardInterrupt:
        run.interrupted = True
        say(f"interrupted: {len(rows)} of {len(fl.units)} units finished and written; run the same command again "
            "to continue")
    from .report import fleet_report, write_report

    run.rows = [rows[u.name] for u in fl.units if u.name in rows]
    run.report = fleet_report(run.rows, net, options.mode)
    write_report(run.report, outp)
    header.update(status="interrupted" if run.interrupted else "finished", finished=time.time(),
                  ran=len(run.ran), skipped=len(run.skipped))
    write_text_atomic(outp / FLEET_FILE, json.dumps(header, indent=1))
    run.seconds = time.perf_counter() - t0
    return run


def _sha(text: str) -> str:
    import hashlib

    return hashlib.sha256(text.encode()).hexdigest()


def _check_same_run(out: Path, network: str, template_text: str, options: FleetOptions, force: bool) -> None:
    f = out / FLEET_FILE
    if not f.is_file() or force:
        return
    try:
        prev = json.loads(f.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return
    if prev.get("template_sha256") != _sha(template_text) or prev.get("options") != options.to_dict():
        what = "another network" if prev.get("template_sha256") != _sha(template_text) else "other options"
        raise TnnError(Diagnostic(
            f"-o {out}: holds a fleet run of {what} (network {prev.get('network')!r}, options {prev.get('options')})",
            hint="write to a new directory; or add --force to redo every unit there with this network and these "
                 "options (each unit's previous result is moved to OUT/replaced/ as its new one arrives)"))


def _run_on_ray(tasks: list, workers: int, address: str | None, arrived: Callable[[dict], None],
                say: Callable[[str], None], cache_env: dict[str, str]) -> None:
    try:
        import ray
    except ImportError:
        raise TnnError(Diagnostic("fleets run on Ray, which is not installed",
                                  hint="pip install 'tnn_dsl[fleet]' (or ray); or run in this process with "
                                       "--workers 0")) from None
    started = False
    if not ray.is_initialized():
        env = {"env_vars": worker_env(cache_env if address is None else {})}  # a cluster's nodes: no shared cache path
        kw: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False, "runtime_env": env,
                              "logging_level": "ERROR"}
        t = time.perf_counter()
        if address is not None:
            ray.init(address=address, **kw)
            say(f"connected to the Ray cluster at {address} in {time.perf_counter() - t:.1f} s")
        else:
            ray.init(num_cpus=max(int(workers), 1), **kw)
            say(f"local Ray with {max(int(workers), 1)} CPUs started in {time.perf_counter() - t:.1f} s")
        started = True
    task = ray.remote(num_cpus=1, max_retries=1, retry_exceptions=False)(_task)
    refs = {task.remote(*t): [u["name"] for u, _tr, _v in t[2]] for t in tasks}
    pending = list(refs)
    try:
        while pending:
            ready, pending = ray.wait(pending, num_returns=1, timeout=0.5)  # Ctrl-C is seen between waits
            for r in ready:
                try:
                    rows = ray.get(r)
                except ray.exceptions.RayError as e:  # the worker died (twice: Ray retried once) or was lost
                    why = str(e).strip().splitlines()[0] if str(e).strip() else ""
                    rows = [{"unit": name, "status": "error", "params": {}, "findings": [],
                             "reason": f"the worker running this unit died and its retry too: {type(e).__name__}: "
                                       f"{why}"} for name in refs[r]]
                for row in rows:
                    arrived(row)
    except KeyboardInterrupt:
        # a local Ray is stopped below (its workers with it); on a cluster the pending tasks are cancelled without
        # force (Ray 2.60 aborts the driver when a forced cancel races a task that is just completing)
        if not started:
            for r in pending:
                try:
                    ray.cancel(r, force=False)
                except Exception:  # noqa: BLE001 - a task that finished meanwhile: nothing to cancel
                    pass
        raise
    finally:
        if started:
            _shutdown_ray(ray)


def _shutdown_ray(ray: Any) -> None:
    """``ray.shutdown()`` with Ctrl-C held until it is done: a shutdown cut short leaves Ray half stopped, and the
    process then ends with status 1 at exit, its output lost. A Ctrl-C that came meanwhile is raised after."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        ray.shutdown()
        return
    got: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: got.append(signum))
    try:
        ray.shutdown()
    finally:
        signal.signal(signal.SIGINT, previous)
    if got:
        raise KeyboardInterrupt
