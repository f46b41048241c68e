"""Model directories: what ``tnnc train`` writes and ``tnnc evaluate``/``inspect`` read. No pickle.

A model directory ``MODEL/`` holds

* ``network.thn``        the network's source as written (the main file; included files under ``include/``),
* ``network.json``       the validated IR (``Network.to_json``), what :func:`load_model` reads,
* ``params.safetensors`` every array the compiled model reads, float64, SI units (kelvin, K/W, J/K, W ...),
* ``meta.json``          versions, backend, data-file hashes, normalisation statistics, metrics, the
                         training curve and the training configuration.

Directories are written to a temporary sibling and renamed into place, so a failed or interrupted write
never destroys an existing model. A model trained with one backend loads and predicts identically on the
other: parameters are stored as float64 numpy arrays and converted by ``Model.from_numpy``.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from ._errors import Diagnostic, ModelFileError
from ._ir import Network, Span

FORMAT = "tnn_dsl-model"
FORMAT_VERSION = 1
REQUIRED_FILES = ("network.json", "params.safetensors", "meta.json")


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def versions(backend: str | None = None) -> dict[str, str]:
    """Versions of the packages a model depends on (recorded in ``meta.json``)."""
    from . import __version__

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


def _jsonable(obj: Any) -> Any:
    """Make numpy scalars/arrays and paths JSON-serialisable; non-finite floats become ``None``."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if np.isfinite(v) else None
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _err(message: str, path: str | os.PathLike | None = None, hint: str | None = None, line: int = 1, col: int = 1):
    span = None
    if path is not None:
        span = Span(file=str(path), line=line, col=col, end_line=line, end_col=col)
    return ModelFileError(Diagnostic(message, span=span, hint=hint))


# ---------------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------------


def save_model(
    path: str | os.PathLike,
    network: Network,
    params: dict[str, np.ndarray],
    meta: dict[str, Any],
) -> Path:
    """Write a model directory atomically (temporary sibling directory, then rename).

    ``params``: name -> numpy array (SI). ``meta`` is stored as ``meta.json`` after adding the format
    header. An existing directory at ``path`` is replaced only once the new one is complete."""
    from safetensors.numpy import save_file

    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    if path.exists() and not path.is_dir():
        raise _err(f"cannot write the model to {path}: a file of that name exists", None,
                   hint="choose another -o MODEL directory name")
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=parent))
    try:
        # sources: the main file as network.thn, any included files under include/
        sources = [Path(s) for s in network.source_files if s and os.path.isfile(s)]
        if sources:
            shutil.copyfile(sources[0], tmp / "network.thn")
            if len(sources) > 1:
                (tmp / "include").mkdir()
                for s in sources[1:]:
                    shutil.copyfile(s, tmp / "include" / s.name)
        (tmp / "network.json").write_text(network.to_json(), encoding="utf-8")
        # np.array(order="C") keeps 0-d arrays 0-d (np.ascontiguousarray would make them 1-d)
        arrays = {k: np.array(v, dtype=np.float64, order="C") for k, v in params.items()}
        save_file(arrays, str(tmp / "params.safetensors"), metadata={"format": FORMAT, "version": str(FORMAT_VERSION)})
        full_meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        full_meta.update(meta)
        (tmp / "meta.json").write_text(json.dumps(_jsonable(full_meta), indent=2, allow_nan=False) + "\n", encoding="utf-8")
        # swap into place: the old model survives until the new one is complete
        old = None
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.old-", dir=parent))
            old.rmdir()
            os.replace(path, old)
        try:
            os.replace(tmp, path)
        except BaseException:
            if old is not None:
                os.replace(old, path)
            raise
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


# ---------------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------------


def load_model(path: str | os.PathLike) -> "TrainedModel":
    """Read a model directory written by :func:`save_model` / ``tnnc train``.

    Raises :class:`ModelFileError` (``MODEL/file:line:col: error: ...`` + hint) for a missing directory,
    a missing or corrupted file, or parameters that do not match the stored network."""
    from safetensors.numpy import load_file

    path = Path(path)
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
    except UnicodeDecodeError as e:
        raise _err(f"meta.json is not UTF-8 text: {e.reason}", meta_path, hint="the model directory is corrupted; re-train")
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
    except Exception as e:  # noqa: BLE001 - pydantic/json errors: all mean a corrupted file
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise _err(f"network.json cannot be read: {first}", net_path, hint="the model directory is corrupted; re-train")
    # params.safetensors
    p_path = path / "params.safetensors"
    try:
        params = {k: np.asarray(v, dtype=np.float64) for k, v in load_file(str(p_path)).items()}
    except Exception as e:  # noqa: BLE001 - safetensors raises several types for a damaged file
        raise _err(f"{p_path}: params.safetensors cannot be read: {e}", None,
                   hint="the model directory is corrupted; re-train or restore params.safetensors")
    bad = [k for k, v in params.items() if not np.all(np.isfinite(v))]
    if bad:
        raise _err(f"{p_path}: params.safetensors holds non-finite values in {', '.join(bad[:5])}", None,
                   hint="the model directory is corrupted; re-train")
    return TrainedModel(network, params, meta, path=path)


class TrainedModel:
    """A network with fitted parameters (what a model directory holds).

    * ``network``: the :class:`Network` IR; ``params``: name -> numpy array (SI), every array the
      compiled model reads; ``meta``: the ``meta.json`` dictionary; ``path``: where it was loaded from.
    * :meth:`predict` simulates experiments (free run, thesis eq. 4.7); :meth:`evaluate` computes per-sensor
      MAE, max error (thesis eq. 4.9) and bias in kelvin.
    """

    def __init__(self, network: Network, params: dict[str, np.ndarray], meta: dict[str, Any] | None = None,
                 path: str | os.PathLike | None = None):
        self.network = network
        self.params = {k: np.asarray(v, dtype=np.float64) for k, v in params.items()}
        self.meta = dict(meta or {})
        self.path = Path(path) if path is not None else None
        self._models: dict[tuple[str, str], Any] = {}

    def __repr__(self) -> str:
        where = f" from {self.path}" if self.path else ""
        return f"TrainedModel({self.network.name!r}, backend={self.backend!r}, {len(self.params)} arrays{where})"

    @property
    def backend(self) -> str:
        """The backend the model was trained with (any backend can load it)."""
        return str(self.meta.get("backend", "jax"))

    def compiled(self, backend: str | None = None, dtype: str = "float64"):
        """The compiled :class:`Model` for ``backend`` (default: the training backend); cached."""
        from ._compile import compile as compile_network

        backend = backend or self.backend
        key = (backend, dtype)
        if key not in self._models:
            model = compile_network(self.network, backend=backend, dtype=dtype)
            self._check_params(model)
            self._models[key] = model
        return self._models[key]

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

    def predict(self, data, backend: str | None = None, init: str = "auto",
                integrator: str | None = None) -> list[dict[str, Any]]:
        """Free-run simulation of each experiment in ``data`` (paths or ``Experiment``s).

        ``init``: ``"steady"`` (the steady state of the first inputs, thesis §4.5), ``"measured"``
        (sensor nodes from the first measurements, the rest from the steady state) or ``"auto"``
        (``measured`` for data that starts mid-file, i.e. ``t[0] > 0``, else ``steady``).
        Returns one dict per experiment: ``name``, ``t`` (N,) s, ``y`` (N, n_sensors) K predicted,
        ``measured`` (N, n_sensors) K (NaN where missing), ``states`` (N, n_states) K, ``sensors``,
        ``state_names``."""
        from ._train import as_experiments, simulate

        backend = backend or self.backend
        model = self.compiled(backend)
        params = self.backend_params(backend)
        integ = integrator or self.meta.get("config", {}).get("integrator", "rk4")
        substeps = self.meta.get("config", {}).get("substeps")
        out = []
        for exp in as_experiments(self.network, data):
            states, y = simulate(model, params, exp, init=init, integrator=integ, substeps=substeps)
            out.append({
                "name": exp.name, "t": np.asarray(exp.t), "y": y, "measured": np.asarray(exp.outputs, dtype=float),
                "states": states, "sensors": list(model.output_names), "state_names": list(model.state_names),
                "inputs": np.asarray(exp.inputs, dtype=float), "input_names": list(model.input_names),
            })
        return out

    def evaluate(self, data, backend: str | None = None, init: str = "auto") -> dict[str, Any]:
        """Per-sensor and overall MAE, max absolute error (thesis eq. 4.9), bias (mean of predicted −
        measured) and RMSE, in kelvin, over the non-missing samples of every experiment."""
        from ._train import error_metrics

        preds = self.predict(data, backend=backend, init=init)
        return error_metrics(preds, [s.name for s in self.network.sensors])

    def save(self, path: str | os.PathLike) -> Path:
        """Write this model to a directory (atomic)."""
        p = save_model(path, self.network, self.params, self.meta)
        self.path = Path(p)
        return self.path

    def nominal_params(self) -> dict[str, float]:
        """The nominal (as written) value of every constant parameter, SI."""
        return {p.name: float(p.value) for p in self.network.params if p.is_constant}


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


__all__ = ["save_model", "load_model", "TrainedModel", "file_sha256", "versions", "data_records"]
