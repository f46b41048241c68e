"""Model directories: what ``tnnc train`` writes and ``tnnc evaluate``/``inspect`` read. No pickle.

A model directory ``MODEL/`` holds

* ``network.thn``        the network's source as written (the main file; included files under ``include/``),
* ``network.json``       the validated IR (``Network.to_json``), what :func:`load_model` reads,
* ``params.safetensors`` every array the compiled model reads, float64, SI units (kelvin, K/W, J/K, W ...),
* ``meta.json``          versions, backend, data-file hashes, normalisation statistics, metrics, the
                         training curve and the training configuration.

Directories are written to a temporary sibling, flushed to disk and swapped into place in one step, so
a failed, interrupted or concurrent write never leaves the path without a complete model
(:func:`save_model`); a directory that is not a model is never replaced. A model trained with one backend
loads and predicts identically on the other: parameters are stored as float64 numpy arrays and converted
by ``Model.from_numpy``.
"""

from __future__ import annotations

import errno
import json
import math
import os
import platform
import re
import secrets
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable

import numpy as np

from ..core import (
    Diagnostic,
    ModelFileError,
    OutputKind,
    TnnError,
    __version__,
    check_output,
    exchange_paths,
    file_sha256,
    fsync_dir,
    fsync_file,
    temp_sibling,
    to_jsonable,
)
from ..core.htmlview import html_list, html_table, safe_repr_html, view
from ..ir import Network, Span
from .simulation import FreeRun, as_experiments, error_metrics, free_runs

if TYPE_CHECKING:
    from ..compiler import Model

FORMAT = "tnn_dsl-model"
ROLE_UNIT = {"resistance": "K/W", "conductance": "W/K", "capacitance": "J/K", "time_constant": "s",
             "heat_flow": "W", "offset": "K", "temperature": "K"}
"""The SI unit a fitted value is shown in, by parameter role (``tnnc inspect``; other roles: the
parameter's own unit)."""
FORMAT_VERSION = 1
REQUIRED_FILES = ("network.json", "params.safetensors", "meta.json")


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


def versions(backend: str | None = None) -> dict[str, str]:
    """Versions of the packages a model depends on (recorded in ``meta.json``)."""

    out = {"tnn_dsl": __version__, "python": platform.python_version(), "numpy": np.__version__}
    for mod in ("jax", "torch", "scipy", "safetensors"):
        if backend is not None and mod in ("jax", "torch") and mod != backend:
            continue
        try:
            m = __import__(mod)
            out[mod] = getattr(m, "__version__", "?")
        except Exception:  # noqa: BLE001 - versions are informational only
            pass
    return out


def _err(message: str, path: str | os.PathLike | None = None, hint: str | None = None, line: int = 1, col: int = 1):
    span = None
    if path is not None:
        span = Span(file=str(path), line=line, col=col, end_line=line, end_col=col)
    return ModelFileError(Diagnostic(message, span=span, hint=hint))


# ---------------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------------


MODEL_FILES = frozenset({"network.thn", "network.json", "params.safetensors", "meta.json", "include"})
"""Every name a model directory may hold; a directory holding only these is a (perhaps damaged) model."""


def is_model_dir(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a directory this tool wrote as a model: its ``meta.json`` says
    ``"format": "tnn_dsl-model"``, or it holds nothing but a model's files (a damaged model:
    :func:`holds_only_model_files`)."""
    p = Path(path)
    if not p.is_dir():
        return False
    try:
        names = {c.name for c in p.iterdir()}
    except OSError:
        return False
    if names and holds_only_model_files(p):
        return True
    try:
        meta = json.loads((p / "meta.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and meta.get("format") == FORMAT


MODEL_DIR = OutputKind("model directory", is_dir=True, ours=is_model_dir, example="model/")
"""The output kind of ``tnnc train -o MODEL`` (for :func:`tnn_dsl.core.files.check_output`)."""


def save_model(
    path: str | os.PathLike,
    network: Network,
    params: dict[str, np.ndarray],
    meta: dict[str, Any],
    *,
    force: bool = False,
    source_text: str | None = None,
) -> Path:
    """Write a model directory; the path always holds a complete model, the old one or the new one.

    ``params``: name -> numpy array (SI). ``meta`` is stored as ``meta.json`` after adding the format
    header and a ``write_id`` (also in the safetensors header, so a reader can tell a mixed read).
    ``source_text``: the network's ``.thn`` text, written as ``network.thn``, for a network that no file on disk
    holds as it is (the doctor's extension, printed from the IR); by default the network's source files are copied.

    The new model is written to a temporary sibling directory, every file flushed to disk, then swapped
    with an existing model in one atomic step (Linux ``renameat2``, macOS ``renamex_np``; elsewhere two
    renames) and the old model removed. Concurrent writers never leave the path empty. ``path`` must be
    absent, empty or a model directory (:func:`is_model_dir`); with ``force=True`` an other directory is
    written into file by file and its other files are kept — and so is a model directory that holds files of the
    user's (notes, plots): only directories holding nothing but model files are ever swapped out and deleted
    (:func:`holds_only_model_files`). Temporary siblings of writers that were
    killed are removed by the next write."""
    from safetensors.numpy import save_file

    path = Path(path)
    try:
        check_output(path, MODEL_DIR, force=force)
    except TnnError as err:
        raise ModelFileError(err.diagnostics) from None
    parent = path.parent if str(path.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
        _remove_stale_temps(path)
        tmp = temp_sibling(path)
        tmp.mkdir()
    except OSError as err:
        raise _err(f"cannot write the model to {path}: {err.strerror or err}", None,
                   hint="choose a writable place for -o MODEL") from None
    write_id = secrets.token_hex(8)
    try:
        # sources: the main file as network.thn, any included files under include/
        sources = [] if source_text is not None else [Path(s) for s in network.source_files if s and os.path.isfile(s)]
        written = []
        if source_text is not None:
            (tmp / "network.thn").write_text(source_text, encoding="utf-8")
            written.append(tmp / "network.thn")
        elif sources:
            shutil.copyfile(sources[0], tmp / "network.thn")
            written.append(tmp / "network.thn")
            if len(sources) > 1:
                (tmp / "include").mkdir()
                for s in sources[1:]:
                    shutil.copyfile(s, tmp / "include" / s.name)
                    written.append(tmp / "include" / s.name)
        (tmp / "network.json").write_text(network.to_json(), encoding="utf-8")
        # np.array(order="C") keeps 0-d arrays 0-d (np.ascontiguousarray would make them 1-d)
        arrays = {k: np.array(v, dtype=np.float64, order="C") for k, v in params.items()}
        save_file(arrays, str(tmp / "params.safetensors"),
                  metadata={"format": FORMAT, "version": str(FORMAT_VERSION), "write_id": write_id})
        full_meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "write_id": write_id,
                     "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        full_meta.update(meta)
        full_meta["write_id"] = write_id
        (tmp / "meta.json").write_text(json.dumps(to_jsonable(full_meta), indent=2, allow_nan=False) + "\n",
                                       encoding="utf-8")
        for f in [*written, tmp / "network.json", tmp / "params.safetensors", tmp / "meta.json"]:
            fsync_file(f)
        if (tmp / "include").is_dir():
            fsync_dir(tmp / "include")
        fsync_dir(tmp)
        if path.is_dir() and not holds_only_model_files(path):
            _write_into(tmp, path)  # a directory with files of the user's (a model's or not): keep them
        else:
            _install(tmp, path)
    except OSError as err:
        raise _err(f"cannot write the model to {path}: {err.strerror or err}", None,
                   hint="check the free disk space and that the place is writable") from None
    finally:
        # tmp is ours (an exclusive mkdir of a fresh name) or holds the model it replaced (held to
        # holds_only_model_files before the swap): never a user's file
        if tmp.exists() and _names_only_model_files(tmp):
            shutil.rmtree(tmp, ignore_errors=True)
    fsync_dir(parent)
    return path


def _install(tmp: Path, path: Path) -> None:
    """Put the complete directory ``tmp`` at ``path`` (absent, empty or a model) in one step; what was at
    ``path`` ends up at ``tmp`` (the caller removes it)."""
    for _ in range(100):
        if not path.exists():
            try:
                os.rename(tmp, path)
                return
            except OSError as err:  # another writer got there first: swap with its model instead
                if err.errno not in (errno.EEXIST, errno.ENOTEMPTY, errno.EISDIR):
                    raise
                continue
        try:
            if exchange_paths(tmp, path):
                return
        except FileNotFoundError:
            continue  # another writer moved it aside (two-rename fallback): try again
        # no atomic swap here: the old model goes aside, the new one in, the old one away
        old = temp_sibling(path, "old")
        try:
            os.rename(path, old)
        except FileNotFoundError:
            continue
        try:
            os.rename(tmp, path)
        except OSError:
            if not path.exists():
                os.rename(old, path)
            elif holds_only_model_files(old):
                shutil.rmtree(old, ignore_errors=True)
            continue
        os.rename(old, tmp)  # the caller removes tmp
        return
    raise OSError(errno.EBUSY, "other writers kept replacing the model", str(path))


def _write_into(tmp: Path, path: Path) -> None:
    """Move the model files of ``tmp`` into the existing directory ``path`` one by one (each an atomic
    replace of that name only); nothing else in ``path`` is touched."""
    # meta.json last: a reader checks its write_id against the parameters'
    for src in sorted(tmp.rglob("*"), key=lambda q: (q.name == "meta.json", str(q))):
        dest = path / src.relative_to(tmp)
        if src.is_dir():
            dest.mkdir(exist_ok=True)
        elif src.name not in OWN_FILES and src.name != "meta.json" and (dest.exists() or dest.is_symlink()):
            continue  # a source copy (network.thn, include/…) where a file of that name is the user's: keep theirs
        else:
            os.replace(src, dest)
    fsync_dir(path)


def _remove_stale_temps(path: Path) -> None:
    """Remove ``.NAME.tmp-PID-…`` / ``.NAME.old-PID-…`` siblings of ``path`` left by a writer that was
    killed (its process no longer exists) and holding nothing but model files (and a library's ``.tmp*``
    file)."""
    parent = path.parent if str(path.parent) else Path(".")
    pattern = re.compile(rf"^\.{re.escape(path.name)}\.(tmp|old)-(\d+)-[0-9a-f]{{8}}$")
    try:
        entries = list(parent.iterdir())
    except OSError:
        return
    for e in entries:
        m = pattern.match(e.name)
        if not m or not e.is_dir() or e.is_symlink() or _process_alive(int(m.group(2))):
            continue
        if _names_only_model_files(e):  # the name (ours, its writer dead) proves whose it is
            shutil.rmtree(e, ignore_errors=True)


def _names_only_model_files(d: Path) -> bool:
    """Whether every entry of ``d`` has a model file's name (or is the ``.tmp*`` file safetensors writes): enough
    for a directory whose *name* proves it is ours (a ``.NAME.tmp-PID-…`` sibling this program created with an
    exclusive ``mkdir``), not for one at a user's path."""
    try:
        return all(c.name in MODEL_FILES or c.name.startswith(".tmp") for c in d.iterdir())
    except OSError:
        return False


OWN_FILES = ("network.json", "params.safetensors")
"""File names only this program writes into a model directory (``network.thn`` and ``include/`` are names a
user's own sources may have too)."""


def holds_only_model_files(d: Path) -> bool:
    """Whether directory ``d`` is a model this program wrote, damaged or not, and nothing else: empty, or only model
    file names including one only this program writes (``network.json``, ``params.safetensors``, or a ``meta.json``
    of format ``tnn_dsl-model``), with an ``include/`` of plain files only. The only directories at a user's path
    this program ever replaces or deletes; a directory holding just ``network.thn`` and ``include/`` (someone's
    sources) is not one. One it cannot read is not either."""
    if not _names_only_model_files(d):
        return False
    try:
        names = {c.name for c in d.iterdir()}
        inc = d / "include"
        if "include" in names and (inc.is_symlink() or not inc.is_dir()
                                   or any(f.is_symlink() or not f.is_file() for f in inc.iterdir())):
            return False
    except OSError:
        return False
    if not names or any(n in names for n in OWN_FILES):
        return True
    try:
        meta = json.loads((d / "meta.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and meta.get("format") == FORMAT


def _process_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, owned by someone else
        return True
    return True


# ---------------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------------


def load_model(path: str | os.PathLike) -> "TrainedModel":
    """Read a model directory written by :func:`save_model` / ``tnnc train``.

    Raises :class:`ModelFileError` (``MODEL/file:line:col: error: ...`` + hint) for a missing directory,
    a missing or corrupted file, or parameters that do not match the stored network. A read that
    overlaps a concurrent write (files of two versions) is retried."""
    for attempt in range(20):
        try:
            return _load_model_once(Path(path))
        except _MixedRead:
            time.sleep(0.005 * (attempt + 1))
    return _load_model_once(Path(path), final=True)


class _MixedRead(Exception):
    """The files read belong to two writes (a concurrent save swapped the directory in between)."""


def _vanished(path: Path, final: bool) -> Exception:
    """A file of the model directory disappeared while it was read: another writer is swapping the directory in.
    The last try says so (a :class:`ModelFileError`); earlier tries read again (:class:`_MixedRead`)."""
    if final:
        return _err(f"{path}: {path.name} vanished while it was read", None,
                    hint="another process is rewriting this model; try again")
    return _MixedRead()


def _load_model_once(path: Path, final: bool = False) -> "TrainedModel":
    from safetensors import safe_open
    from safetensors.numpy import load_file

    if not path.exists():
        raise _err(f"model directory {path} does not exist", None,
                   hint="train a model first: tnnc train NET.thn DATA.csv -o MODEL")
    if not path.is_dir():
        raise _err(f"{path} is not a model directory (it is a file)", None,
                   hint="pass the directory written by `tnnc train -o MODEL`")
    missing = [f for f in REQUIRED_FILES if not (path / f).is_file()]
    if missing:
        present = sorted(p.name for p in path.iterdir())
        raise _err(
            f"model directory {path} is incomplete: missing {', '.join(missing)}",
            None,
            hint=f"the directory holds: {', '.join(present) or 'nothing'}; re-run `tnnc train ... -o {path}`",
        )
    # meta.json
    meta_path = path / "meta.json"
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise _vanished(meta_path, final) from None
    except UnicodeDecodeError as e:
        raise _err(f"meta.json is not UTF-8 text: {e.reason}", meta_path,
                   hint="the model directory is corrupted; re-train")
    except json.JSONDecodeError as e:
        raise _err(f"meta.json is not valid JSON: {e.msg}", meta_path, line=e.lineno, col=e.colno,
                   hint="the model directory is corrupted; re-train or restore meta.json")
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise _err("meta.json is not a tnn_dsl model description (no \"format\": \"tnn_dsl-model\")", meta_path,
                   hint="pass the directory written by `tnnc train -o MODEL`")
    if int(meta.get("format_version", 0)) > FORMAT_VERSION:
        raise _err(f"model format version {meta.get('format_version')} is newer than this tnn_dsl understands "
                   f"({FORMAT_VERSION})", meta_path, hint="upgrade tnn_dsl")
    # network.json
    net_path = path / "network.json"
    try:
        network = Network.from_json(net_path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise _vanished(net_path, final) from None
    except Exception as e:  # noqa: BLE001 - pydantic/json errors: all mean a corrupted file
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise _err(f"network.json cannot be read: {first}", net_path, hint="the model directory is corrupted; re-train")
    # params.safetensors
    p_path = path / "params.safetensors"
    try:
        with safe_open(str(p_path), framework="numpy") as fh:
            header = fh.metadata() or {}
        params = {k: np.asarray(v, dtype=np.float64) for k, v in load_file(str(p_path)).items()}
    except FileNotFoundError:
        raise _vanished(p_path, final) from None
    except Exception as e:  # noqa: BLE001 - safetensors raises several types for a damaged file
        raise _err(f"{p_path}: params.safetensors cannot be read: {e}", None,
                   hint="the model directory is corrupted; re-train or restore params.safetensors")
    if meta.get("write_id") != header.get("write_id") and not final:
        raise _MixedRead
    bad = [k for k, v in params.items() if not np.all(np.isfinite(v))]
    if bad:
        raise _err(f"{p_path}: params.safetensors holds non-finite values in {', '.join(bad[:5])}", None,
                   hint="the model directory is corrupted; re-train")
    network = _validated_network(network, net_path)
    problems = stored_param_problems(network, params)
    if problems:
        raise ModelFileError([Diagnostic(f"{p_path}: {msg}", hint="the model directory was edited by hand or is "
                                         "corrupted; re-train, or restore the file") for msg in problems[:8]])
    return TrainedModel(network, params, meta, path=path)


def _validated_network(network: Network, net_path: Path) -> Network:
    """The stored network through the validation pass (the one a ``.thn`` file goes through): a hand-edited
    ``network.json`` (a negative capacity, a dangling node) is a ``file: error:`` message, not a model."""
    from ..lang import validate

    try:
        return validate(network)
    except TnnError as err:
        raise ModelFileError([Diagnostic(f"{net_path}: the stored network is not valid: {d.message}",
                                         hint="the model directory was edited by hand or is corrupted; re-train")
                              for d in err.diagnostics[:8]]) from None


def stored_param_problems(network: Network, params: dict[str, np.ndarray]) -> list[str]:
    """What is wrong with ``params`` (SI arrays by name) as the values of ``network``: missing arrays, shapes
    other than the compiled model's, and constants that are not physical (a negative capacity, a temperature
    below absolute zero; :func:`tnn_dsl.lang.value_problem`), normalisation scales that are not positive."""
    from ..compiler.learned import array_shapes
    from ..lang import value_problem

    out: list[str] = []
    for p in network.params:
        if not p.is_constant:
            continue
        if p.name not in params:
            out.append(f"`{p.name}` is missing")
            continue
        a = np.asarray(params[p.name])
        if a.size != 1:
            out.append(f"`{p.name}` has shape {a.shape}, expected one number")
            continue
        why = value_problem(p, float(a.reshape(-1)[0]))
        if why:
            out.append(f"`{p.name}`: {why}")
    for fn in network.learned:
        for k, (shape, _kind) in array_shapes(fn, len(fn.inputs), len(fn.targets)).items():
            name = f"{fn.name}.{k}"
            if name not in params:
                out.append(f"`{name}` is missing")
            elif tuple(np.shape(params[name])) != tuple(shape):
                out.append(f"`{name}` has shape {tuple(np.shape(params[name]))}, expected {tuple(shape)}")
            elif k in ("x_scale", "y_scale") and not np.all(np.asarray(params[name]) > 0):
                out.append(f"`{name}` must be positive (it divides the function's input or scales its output)")
    return out


class TrainedModel:
    """A network with fitted parameters (what a model directory holds).

    * ``network``: the :class:`Network` IR; ``params``: name -> numpy array (SI), every array the
      compiled model reads; ``meta``: the ``meta.json`` dictionary; ``path``: where it was loaded from.
    * :meth:`predict` simulates experiments (free run, thesis eq. 4.7); :meth:`evaluate` computes per-sensor
      MAE, max error (thesis eq. 4.9) and bias in kelvin.
    """

    def __init__(self, network: Network, params: dict[str, np.ndarray], meta: dict[str, Any] | None = None,
                 path: str | os.PathLike | None = None) -> None:
        self.network = network
        self.params = {k: np.asarray(v, dtype=np.float64) for k, v in params.items()}
        self.meta = dict(meta or {})
        self.path = Path(path) if path is not None else None
        self._models: dict[tuple[str, str], Any] = {}
        self._compiled_here: set[tuple[str, str]] = set()

    def __repr__(self) -> str:
        where = f" from {self.path}" if self.path else ""
        return f"TrainedModel({self.network.name!r}, backend={self.backend!r}, {len(self.params)} arrays{where})"

    @property
    def backend(self) -> str:
        """The backend the model was trained with (any backend can load it)."""
        return str(self.meta.get("backend", "jax"))

    def compiled(self, backend: str | None = None, dtype: str = "float64") -> Model:
        """The compiled :class:`Model` for ``backend`` (default: the training backend); cached."""
        from ..compiler import compile as compile_network

        backend = backend or self.backend
        key = (backend, dtype)
        if key not in self._models:
            model = compile_network(self.network, backend=backend, dtype=dtype)
            self._check_params(model)
            self._models[key] = model
            self._compiled_here.add(key)  # (the trainer hands over its own model, its compile choice made)
        return self._models[key]

    def release_compiled(self) -> None:
        """Let the compiled models (and their programs) go; :meth:`compiled` builds them again when next used. For a
        model kept for its values while other work needs the memory (the doctor's MLP check, issue 18)."""
        self._models.clear()
        self._compiled_here.clear()

    def _check_params(self, model) -> None:
        specs = model.param_specs
        missing = [k for k in specs if k not in self.params and not k.startswith("scale:")]
        wrong = [k for k, s in specs.items() if k in self.params and tuple(self.params[k].shape) != tuple(s.shape)]
        if missing or wrong:
            where = f"{self.path / 'params.safetensors'}: " if self.path else ""
            msg = []
            if missing:
                msg.append(f"missing arrays {', '.join(missing[:8])}")
            if wrong:
                msg.append("wrong shapes for " + ", ".join(
                    f"{k} {tuple(self.params[k].shape)} (expected {tuple(specs[k].shape)})" for k in wrong[:8]))
            raise _err(where + "the stored parameters do not match the network: " + "; ".join(msg), None,
                       hint="the model directory is corrupted or was edited by hand; re-train")

    def backend_params(self, backend: str | None = None, dtype: str = "float64") -> dict:
        """The parameters as backend arrays for :meth:`compiled` (missing ``scale:`` entries take the
        model's defaults)."""
        model = self.compiled(backend, dtype)
        base = model.to_numpy(model.init_params(seed=0))
        base.update({k: v for k, v in self.params.items() if k in base})
        return model.from_numpy(base)

    def predict(self, data: Any, backend: str | None = None, init: str = "estimate",
                integrator: str | None = None, burn_in_s: float | None = None,
                check: bool = True, log: Callable[[str], None] | None = None,
                errors: str = "raise") -> list[Any]:
        """Free-run simulation of each experiment in ``data`` (paths or ``Experiment``s); on torch, files alike in
        sample interval and length run as one batched rollout (:func:`~tnn_dsl.fit.simulation.free_runs`).

        ``init``: the initial-state rule (:mod:`tnn_dsl.fit.initial`): ``"estimate"`` (fitted to a burn-in at
        the start of each file, ``burn_in_s`` seconds or a tenth of the file; a training file continues from its
        stored fitted state), ``"filter"``, ``"steady"`` or ``"measured"``. Returns one dict per experiment:
        ``name``, ``t`` (N,) s, ``y`` (N, n_sensors) K predicted, ``measured`` (N, n_sensors) K (NaN where
        missing), ``states`` (N, n_states) K, ``burn_in`` (samples not scored), ``init`` (the rule applied),
        ``notes``, ``sensors``, ``state_names``. A run that leaves the physical range (non-finite, below 0 K,
        or far outside the data's temperatures) raises :class:`TnnError` naming the node and the time, unless
        ``check`` is false (:func:`~tnn_dsl.fit.simulation.check_rollout`); with ``errors="return"`` a file's error
        (there, or in finding its initial state) takes its place in the list and the other files run.

        On torch, a loaded model's rollouts are compiled (``torch.compile``) when the experiments hold
        :data:`~tnn_dsl.fit.config.FREE_RUN_COMPILE_MIN_SAMPLES` samples or more and ``TNN_TORCH_COMPILE`` is not
        set (``log``, if given, is told); the model the trainer left in memory keeps the trainer's choice."""

        from .config import free_runs_compile_pay

        backend = backend or self.backend
        model = self.compiled(backend)
        params = self.backend_params(backend)
        integ = integrator or self.meta.get("config", {}).get("integrator", "rk4")
        substeps = self.meta.get("config", {}).get("substeps")
        known = self.free_run_context()
        exps = as_experiments(self.network, data)
        n_samples = sum(len(e.t) for e in exps)
        if (model.backend == "torch" and not model.torch_compile and (backend, "float64") in self._compiled_here
                and free_runs_compile_pay(n_samples) and model.compile_torch_rollouts() and log is not None):
            log(f"torch: compiling the model's rollouts for {n_samples} samples (once; TNN_TORCH_COMPILE=0 runs "
                "eager)")
        runs = free_runs(model, params, exps, init, integrator=integ, substeps=substeps, burn_in_s=burn_in_s,
                         check=check, errors=errors, **known)
        out: list[Any] = []
        for exp, run in zip(exps, runs):
            if not isinstance(run, FreeRun):  # errors="return": the file's TnnError in its place
                out.append(run)
                continue
            out.append({
                "name": exp.name, "t": np.asarray(exp.t), "y": run.y, "measured": np.asarray(exp.outputs, dtype=float),
                "states": run.states, "sensors": list(model.output_names), "state_names": list(model.state_names),
                "inputs": np.asarray(exp.inputs, dtype=float), "input_names": list(model.input_names),
                "burn_in": run.burn_in, "init": run.init.rule, "notes": list(run.init.notes),
                "experiment_params": dict(run.init.params),
            })
        return out

    def free_run_context(self) -> dict[str, Any]:
        """What this model knows for a free run (keyword arguments of :func:`~tnn_dsl.fit.simulation.free_run`):
        the fitted initial states of its training files (``stored``), the mean of each per-experiment parameter
        (``per_experiment``) and each training file's values (``stored_params``)."""
        stored_params = {str(r.get("fingerprint")): dict(r.get("values") or {})
                         for r in self.meta.get("per_experiment") or []}
        means = {p.name: float(np.asarray(self.params[p.name]).reshape(-1)[0]) for p in self.network.params
                 if getattr(p, "per_experiment", False) and p.name in self.params}
        return {"stored": self.stored_initial_states(), "per_experiment": means, "stored_params": stored_params}

    def stored_initial_states(self) -> dict[str, list[float]]:
        """``{fingerprint: T0 (n_states,) K}``: the initial states fitted for the training files (state order of
        the compiled model); a file with the same step and samples continues from its own."""
        names = [n.name for n in self.network.nodes] + [f"{s.name}.lag" for s in self.network.sensors if s.lag]
        out = {}
        for rec in self.meta.get("initial_states") or []:
            T0 = rec.get("T0") or {}
            if isinstance(T0, dict) and all(n in T0 for n in names):
                out[str(rec.get("fingerprint"))] = [float(T0[n]) for n in names]
        return out

    def evaluate(self, data: Any, backend: str | None = None, init: str = "estimate",
                 burn_in_s: float | None = None, log: Callable[[str], None] | None = None) -> dict[str, Any]:
        """Per-sensor and overall MAE, max absolute error (thesis eq. 4.9), bias (mean of predicted −
        measured) and RMSE, in kelvin, over the non-missing samples of every experiment after its burn-in."""

        preds = self.predict(data, backend=backend, init=init, burn_in_s=burn_in_s, log=log)
        return error_metrics(preds, [s.name for s in self.network.sensors])

    def evaluate_each(self, data: Any, backend: str | None = None, init: str = "estimate",
                      burn_in_s: float | None = None) -> list[Any]:
        """:meth:`evaluate` of each experiment in ``data`` on its own (one ``error_metrics`` dict a file), or the
        file's :class:`TnnError` in its place (a run that left the physical range, an initial state that could not
        be found); the runs go in batches as in :meth:`predict`."""
        sensors = [s.name for s in self.network.sensors]
        return [p if isinstance(p, TnnError) else error_metrics([p], sensors)
                for p in self.predict(data, backend=backend, init=init, burn_in_s=burn_in_s, errors="return")]

    def save(self, path: str | os.PathLike, *, force: bool = False, source_text: str | None = None) -> Path:
        """Write this model to a directory (atomic; see :func:`save_model` for ``force`` and ``source_text``)."""
        p = save_model(path, self.network, self.params, self.meta, force=force, source_text=source_text)
        self.path = Path(p)
        return self.path

    def nominal_params(self) -> dict[str, float]:
        """The nominal (as written) value of every constant parameter, SI."""
        return {p.name: float(p.value) for p in self.network.params if p.is_constant}

    def parameter_table(self, all_params: bool = False) -> list[dict[str, Any]]:
        """Fitted against nominal, one row per free constant (every constant with ``all_params``):
        ``{name, role, nominal, fitted, change_pct, free, bounds}`` in SI (temperatures in K) and the same values
        in the unit the file wrote them in: ``unit``, ``nominal_shown``, ``fitted_shown`` (``tnnc inspect``
        prints these: ``Ta 23 degC → 25.2 degC``, ``a1 0.01 W/%``)."""
        rows = []
        for p in self.network.params:
            if not p.is_constant or p.name not in self.params:
                continue
            if not (p.free or all_params):
                continue
            fitted = float(np.asarray(self.params[p.name]).reshape(-1)[0])
            nominal = float(p.value)
            change = (fitted - nominal) / abs(nominal) * 100.0 if nominal != 0 else math.nan
            unit, scale, offset = display_unit(p, self.network.temperature_unit)
            rows.append({"name": p.name, "role": p.role, "unit": unit, "nominal": nominal, "fitted": fitted,
                         "nominal_shown": (nominal - offset) / scale, "fitted_shown": (fitted - offset) / scale,
                         "change_pct": change, "free": bool(p.free), "bounds": [p.lower, p.upper],
                         "absolute_temperature": bool(offset)})
        return rows

    def metric_rows(self) -> list[dict[str, Any]]:
        """``{part, mae, max_error}`` (K) for the ``train`` and ``validation`` metrics in ``meta``."""
        m = self.meta.get("metrics", {})
        return [{"part": part, "mae": m[part].get("mae"), "max_error": m[part].get("max_error")}
                for part in ("train", "validation") if isinstance(m.get(part), dict)]

    def _header(self) -> str:
        meta = self.meta
        return (f"network {self.network.name}, trained with {meta.get('backend', '?')} "
                f"(rollout {meta.get('rollout', '?')}, stopped: {meta.get('stopped', '?')})")

    def summary(self) -> str:
        """The text summary (the first part of ``tnnc inspect``): training, metrics, fitted vs nominal."""
        lines = [self._header()]
        for r in self.metric_rows():
            lines.append(f"  {r['part']:<10} MAE {r['mae'] or math.nan:.4g} K  max {r['max_error'] or math.nan:.4g} K")
        rows = self.parameter_table()
        if rows:
            lines.append(f"\n{'parameter':<22} {'nominal':>26} {'fitted':>26} {'change':>9}")
            lines += [format_row(r) for r in rows]
        if self.meta.get("estimation"):
            from ..estimation import estimation_summary

            lines += ["", estimation_summary(self.meta["estimation"])]
        lines += [f"warning: {w}" for w in self.meta.get("warnings", []) or []]
        return "\n".join(lines)

    def _repr_html_(self) -> str:
        """The notebook view: :meth:`summary` as tables (``<pre>`` of the summary should that fail)."""
        return safe_repr_html(self._html, self.summary, repr(self))

    def _html(self) -> str:
        parts = [html_list([self._header()] + ([f"loaded from {self.path}"] if self.path else []))]
        metrics = self.metric_rows()
        if metrics:
            parts.append(html_table(["data", "MAE K", "max error K"],
                                    [[r["part"], r["mae"], r["max_error"]] for r in metrics],
                                    numeric=[False, True, True]))
        rows = self.parameter_table()
        if rows:
            parts.append(html_table(
                ["parameter", "nominal", "fitted", "change"],
                [[r["name"], format_value(r["nominal_shown"], r["unit"]), format_value(r["fitted_shown"], r["unit"]),
                  change_text(r)] for r in rows],
                numeric=[False, True, True, True]))
        if self.meta.get("estimation"):
            from ..estimation import Estimates

            parts.append(Estimates.from_dict(self.meta["estimation"])._html())
        parts.append(html_list(f"warning: {w}" for w in self.meta.get("warnings", []) or []))
        return view(f"TrainedModel: {self.network.name} ({self.backend})", *parts)


def display_unit(p, temperature_unit: str = "K") -> tuple[str, float, float]:
    """``(unit, scale, offset)`` to show constant ``p`` in the unit its file wrote (SI = scale·x + offset):
    an absolute temperature in the file's temperature unit, other values in their written unit (``W/%``,
    ``kJ/K``), values written without a unit in their role's SI unit."""
    from ..lang import UnitError, unit_scale
    from ..lang.units import is_temperature_unit

    unit = p.unit
    absolute = p.role == "temperature" or (is_temperature_unit(unit) and p.role not in ("offset",))
    if absolute and p.dim.get("K") == 1.0 and len(p.dim) == 1:
        unit = temperature_unit if unit is None or is_temperature_unit(unit) else unit
    if not unit:
        return ROLE_UNIT.get(p.role, "SI"), 1.0, 0.0
    try:
        scale, offset = unit_scale(unit)
    except UnitError:
        return ROLE_UNIT.get(p.role, "SI"), 1.0, 0.0
    if not absolute:
        offset = 0.0  # a temperature difference written in degC is kelvin-sized
    return unit, scale, offset


def format_value(v: float, unit: str) -> str:
    """A value in ``unit`` as ``tnnc inspect`` shows it (``23 degC``, ``0.01 W/%``)."""
    return f"{v:.6g} {unit}" if unit not in ("SI", "1", "") else f"{v:.6g}"


def change_text(r: dict[str, Any]) -> str:
    """The change column of a parameter row: kelvin for an absolute temperature, percent otherwise."""
    if r.get("absolute_temperature"):
        return f"{r['fitted'] - r['nominal']:+.3g} K"
    return f"{r['change_pct']:+.1f} %" if math.isfinite(r["change_pct"]) else ""


def format_row(r: dict[str, Any]) -> str:
    """One line of the parameter table: name, nominal and fitted in the file's unit, change."""
    return (f"{r['name'][:22]:<22} {format_value(r['nominal_shown'], r['unit']):>26} "
            f"{format_value(r['fitted_shown'], r['unit']):>26} {change_text(r):>9}")


def data_records(paths: Iterable[str | os.PathLike | None]) -> list[dict[str, Any]]:
    """``[{path, sha256, bytes}]`` for the data files a model was trained on (for ``meta.json``)."""
    recs = []
    for p in paths:
        if p is None:
            continue
        p = Path(p)
        if p.is_file():
            recs.append({"path": str(p), "sha256": file_sha256(p), "bytes": p.stat().st_size})
    return recs


__all__ = ["save_model", "load_model", "is_model_dir", "MODEL_DIR", "TrainedModel", "file_sha256", "versions",
           "data_records"]
