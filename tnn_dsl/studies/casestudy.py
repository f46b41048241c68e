"""The case-study generator (``shared/spec/case-study.md``): a Peltier cooler with a hidden heat pipe.

The "measured" data every test, example and benchmark compares against. The true system is the network
``networks/peltier_heatpipe/truth.thn`` (the nominal network plus the hidden heat pipe: ``R_hp1``,
``R_hp2``, ``R_hpa`` as derived parameters depending on ``u1`` and node temperatures), integrated by the
compiled model with RK4 at 0.1 s in float64 and sampled every 1 s.

Inputs (one CSV column each, in the network's units):

* ``I`` (A) in ``[0, 3·(1+p)]`` and ``u1`` (1) in ``[−p, 1+p]`` (``p`` = widening, 0 in distribution):
  pseudo-random steps, hold times uniform over the integers 120 … 600 s, levels uniform within the
  bounds; each signal has its own random stream (``numpy.random.SeedSequence(seed).spawn``), so the
  signals are independent, and the same seed at another widening gives the same switching times with
  levels stretched to the wider bounds (common random numbers: the out-of-distribution curve compares
  like with like).
* ``Ta`` = 22 °C, ``Tf1`` = ``Tf2`` = 25 °C, constant.

Outputs: ``T_out`` (°C; plus Gaussian noise of σ ``noise`` K if asked, from a third stream of the same
seed) and the true state of every node as ``T_<node>`` (°C, noise-free). The run starts at the steady
state of the first inputs.

Files: ``train.csv`` (4 h, seed 1), ``val.csv`` (2 h, seed 2), ``ood_<P>_<k>.csv`` (2 h, P = 10, 20, 30,
40 percent widening, k = 0 … n_ood−1 with seed ``seed_ood + k``), and ``manifest.json`` (settings, file
hashes). A directory whose manifest has the same settings and intact files is not regenerated.
"""

from __future__ import annotations

import json
import os
from importlib import resources
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..compiler import backend_of
from ..core import Diagnostic, OutputKind, TnnError, __version__, check_output, file_sha256, write_text_atomic

__all__ = [
    "generate_case_study", "step_sequence", "case_study_inputs", "truth_network_path", "network_path",
    "I_BOUNDS", "U1_BOUNDS", "HOLD_S", "SAMPLE_DT", "TRUTH_DT", "TRAIN_S", "VAL_S", "OOD_S",
]

GENERATOR_VERSION = 2
"""Bumped whenever the generated numbers change for the same settings (invalidates caches)."""

I_BOUNDS = (0.0, 3.0)  # A
U1_BOUNDS = (0.0, 1.0)  # 1
HOLD_S = (120, 600)  # s, hold time of each level, integer seconds
T_AMBIENT_C = 22.0
T_FLUID_C = 25.0
SAMPLE_DT = 1.0  # s
TRUTH_DT = 0.1  # s (RK4 sub-step)
TRAIN_S = 4 * 3600
VAL_S = 2 * 3600
OOD_S = 2 * 3600
TRUTH_NETWORK = "peltier_heatpipe/truth.thn"
LEVEL_DECIMALS = 6


# ---------------------------------------------------------------------------------------------
# Where the shipped networks are
# ---------------------------------------------------------------------------------------------


def network_path(relative: str) -> Path:
    """Path of a shipped network file, ``relative`` to ``networks/`` (e.g. ``"tclab/tclab.thn"``):
    inside the installed wheel (``tnn_dsl/networks``), else in the source checkout."""
    try:
        p = resources.files("tnn_dsl").joinpath("networks", *relative.split("/"))
        if p.is_file():
            return Path(str(p))
    except (ModuleNotFoundError, FileNotFoundError, NotADirectoryError):
        pass
    repo = Path(__file__).resolve().parents[2] / "networks" / relative
    if repo.is_file():
        return repo
    raise TnnError(Diagnostic(f"shipped network {relative!r} not found (looked in tnn_dsl/networks and {repo.parent})",
                              hint="reinstall tnn_dsl; the networks are part of the package"))


def truth_network_path() -> Path:
    """``networks/peltier_heatpipe/truth.thn``: the case study's true system."""
    return network_path(TRUTH_NETWORK)


# ---------------------------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------------------------


def step_sequence(rng: np.random.Generator, n: int, low: float, high: float,
                  hold: tuple[int, int] = HOLD_S, dt: float = SAMPLE_DT) -> np.ndarray:
    """A pseudo-random step signal of ``n`` samples (step ``dt`` s): each level is held for an integer
    number of seconds drawn uniformly from ``hold`` (inclusive), the level drawn uniformly from
    ``[low, high]`` and rounded to ``LEVEL_DECIMALS`` decimals (so the CSV holds exactly the values the
    truth was driven with). Draw order per segment: hold, then level. → (n,) float64."""
    out = np.empty(n, dtype=np.float64)
    k = 0
    while k < n:
        h = int(rng.integers(hold[0], hold[1] + 1))
        level = min(max(round(float(rng.uniform(low, high)), LEVEL_DECIMALS), low), high)
        m = max(1, int(round(h / dt)))
        out[k : k + m] = level
        k += m
    return out


def widened_bounds(widen: float) -> dict[str, tuple[float, float]]:
    """Input bounds widened by the fraction ``widen``: I ∈ [0, 3·(1+p)] A, u1 ∈ [−p, 1+p]."""
    p = float(widen)
    return {"I": (I_BOUNDS[0], I_BOUNDS[1] * (1.0 + p)), "u1": (U1_BOUNDS[0] - p, U1_BOUNDS[1] + p)}


def case_study_inputs(seed: int, duration_s: float, widen: float = 0.0, dt: float = SAMPLE_DT) -> dict[str, np.ndarray]:
    """The five input signals of one data set, in the file's units: ``I`` (A), ``u1`` (1), ``Ta``,
    ``Tf1``, ``Tf2`` (°C); each (N,) with ``N = duration_s/dt + 1`` samples (t = 0 … duration)."""
    n = int(round(duration_s / dt)) + 1
    s_i, s_u, _noise = np.random.SeedSequence(int(seed)).spawn(3)
    b = widened_bounds(widen)
    return {
        "I": step_sequence(np.random.default_rng(s_i), n, *b["I"], dt=dt),
        "u1": step_sequence(np.random.default_rng(s_u), n, *b["u1"], dt=dt),
        "Ta": np.full(n, T_AMBIENT_C),
        "Tf1": np.full(n, T_FLUID_C),
        "Tf2": np.full(n, T_FLUID_C),
    }


def _noise(seed: int, n: int, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return np.zeros(n)
    s_noise = np.random.SeedSequence(int(seed)).spawn(3)[2]
    return float(sigma) * np.random.default_rng(s_noise).standard_normal(n)


# ---------------------------------------------------------------------------------------------
# The truth
# ---------------------------------------------------------------------------------------------


class _Truth:
    """The compiled true network; ``simulate`` runs batches of data sets."""

    def __init__(self, backend: str = "jax", path: Path | None = None):
        import tnn_dsl

        from ..data import to_kelvin

        self.path = Path(path) if path is not None else truth_network_path()
        self.net = tnn_dsl.load(str(self.path))
        from ..compiler import compile as compile_network

        self.model = compile_network(self.net, backend=backend, dtype="float64")
        self.params = self.model.init_params(seed=0)
        self.tunit = self.net.temperature_unit
        self._to_k = to_kelvin
        names = {i.name for i in self.net.inputs}
        need = {"I", "u1", "Ta", "Tf1", "Tf2"}
        if not need <= names:
            raise TnnError(Diagnostic(f"{self.path}: the truth network must have inputs {sorted(need)}; it has "
                                      f"{sorted(names)}"))

    def input_matrix(self, sig: dict[str, np.ndarray]) -> np.ndarray:
        """(N, n_inputs) SI in the model's input order (temperatures to K)."""
        cols = []
        for inp in self.net.inputs:
            v = np.asarray(sig[inp.name], dtype=np.float64)
            cols.append(self._to_k(v, "degC") if inp.is_temperature else v)
        return np.stack(cols, axis=-1)

    def simulate(self, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """U (B, N, n_inputs) SI → (states (B, N, n_states) K, outputs (B, N, n_outputs) K): start at the
        steady state of the first inputs, RK4 with ``SAMPLE_DT/TRUTH_DT`` sub-steps per sample."""
        m = self.model
        B = backend_of(m)
        Ub = B.asarray(np.asarray(U, dtype=np.float64))
        u0 = Ub[:, 0, :]
        T0 = m.steady_state(self.params, u0)
        resid = np.abs(B.numpy(m.rhs(self.params, T0, u0))).max()
        if not np.isfinite(resid) or resid > 1e-8:
            raise TnnError(Diagnostic(
                f"the steady state of {self.path} for the first inputs did not converge "
                f"(max |dT/dt| = {resid:.3g} K/s)",
                hint="check the truth network's derived parameters for values outside their physical range"))
        substeps = int(round(SAMPLE_DT / TRUTH_DT))
        states, outputs = m.rollout(self.params, T0, Ub, SAMPLE_DT, integrator="rk4", substeps=substeps)
        return B.numpy(states), B.numpy(outputs)


_TRUTHS: dict[tuple, _Truth] = {}


def _truth(backend: str, path: Path) -> _Truth:
    """The compiled truth, kept for the process (compiling and tracing cost seconds; the file's
    modification time and size are part of the key, so an edited truth.thn is recompiled)."""
    st = path.stat()
    key = (backend, str(path.resolve()), st.st_mtime_ns, st.st_size)
    if key not in _TRUTHS:
        _TRUTHS[key] = _Truth(backend=backend, path=path)
    return _TRUTHS[key]


# ---------------------------------------------------------------------------------------------
# Writing the data sets
# ---------------------------------------------------------------------------------------------


def _write_set(truth: _Truth, path: Path, sig: dict[str, np.ndarray], states: np.ndarray, outputs: np.ndarray,
               noise: np.ndarray) -> None:
    from ..data import write_csv

    n = states.shape[0]
    t = np.arange(n, dtype=np.float64) * SAMPLE_DT
    cols: dict[str, np.ndarray] = {}
    plain: set[str] = set()
    for inp in truth.net.inputs:
        v = sig[inp.name]
        if inp.is_temperature:  # written back in the network's unit (°C in, unit out)
            v = truth._to_k(v, "degC")
        else:
            plain.add(inp.column)
        cols[inp.column] = v
    for k, s in enumerate(truth.net.sensors):
        cols[s.column] = outputs[:, k] + (noise if k == 0 else 0.0)
    for k, name in enumerate(truth.model.state_names):
        if name in truth.net.node_names:
            cols[f"T_{name}"] = states[:, k]
    kelvin = [c for c in cols if c not in plain]
    write_csv(path, t, cols, truth.tunit, kelvin=kelvin, time_col="time_s", digits=10)


def _settings(noise, widen, n_ood, seed_train, seed_val, seed_ood, truth_path: Path) -> dict:
    return {
        "generator_version": GENERATOR_VERSION,
        "noise_K": float(noise),
        "widen": [float(w) for w in widen],
        "n_ood": int(n_ood),
        "seed_train": int(seed_train),
        "seed_val": int(seed_val),
        "seed_ood": int(seed_ood),
        "train_s": TRAIN_S,
        "val_s": VAL_S,
        "ood_s": OOD_S,
        "sample_dt_s": SAMPLE_DT,
        "truth_dt_s": TRUTH_DT,
        "hold_s": list(HOLD_S),
        "truth_sha256": file_sha256(truth_path),
    }


def _ood_name(p: float, k: int) -> str:
    return f"ood_{round(p * 100):d}_{k}.csv"


_WHAT = "tnn_dsl case study (shared/spec/case-study.md): Peltier cooler with hidden heat pipe"


_INCOMPLETE = ".tnn_dsl-incomplete"
"""Marker file present while a generation is under way (and after one that failed): the directory is ours."""


def _is_our_manifest(path: Path) -> bool:
    """Whether ``path`` is a manifest this generator wrote (its ``what`` names the case study)."""
    try:
        return json.loads(path.read_text(encoding="utf-8")).get("what") == _WHAT
    except (OSError, ValueError, AttributeError):
        return False


def _is_data_dir(p: Path) -> bool:
    """A directory this generator wrote: its ``manifest.json`` says so, or the marker of an interrupted
    or failed generation is there."""
    try:
        if (p / _INCOMPLETE).read_text(encoding="utf-8").strip() == _WHAT:
            return True
    except (OSError, UnicodeDecodeError):
        pass
    return _is_our_manifest(p / "manifest.json")


DATA_DIR = OutputKind("case-study data directory", is_dir=True, ours=_is_data_dir, example="out/cs")


def generate_case_study(
    out_dir: str | os.PathLike,
    noise: float = 0.0,
    widen: Sequence[float] = (0.1, 0.2, 0.3, 0.4),
    n_ood: int = 10,
    seed_train: int = 1,
    seed_val: int = 2,
    seed_ood: int = 100,
    backend: str = "jax",
    *,
    force: bool = False,
    durations: tuple[float, float, float] | None = None,
    truth_path: str | os.PathLike | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """Write the case-study data sets to ``out_dir`` (see the module docstring); → a summary dict::

        {"dir": str, "train": path, "val": path, "ood": {"10": [paths], ...}, "manifest": path,
         "cached": bool, "settings": {...}}

    ``noise`` is the σ (K) of Gaussian noise on ``T_out``; ``widen`` the out-of-distribution widenings as
    fractions (0.1 = 10 %); ``durations`` overrides (train, val, ood) in s (tests use short ones);
    ``force`` regenerates even if the cache is valid, and writes into an existing directory that is not a
    case-study data directory (its other files are kept; see :mod:`tnn_dsl.core.files`); ``progress(msg)`` is
    called with one-line status.
    """
    out = Path(out_dir)
    widen = _checked_arguments(noise, widen, n_ood)
    tpath = Path(truth_path) if truth_path is not None else truth_network_path()
    settings = _settings(noise, widen, n_ood, seed_train, seed_val, seed_ood, tpath)
    if durations is not None:
        settings.update(train_s=float(durations[0]), val_s=float(durations[1]), ood_s=float(durations[2]))
    summary = _summary(out, settings, widen, n_ood)
    say = progress or (lambda msg: None)

    check_output(out, DATA_DIR, force=force)
    if not force and _cache_valid(out, settings):
        say(f"case-study data in {out} is up to date (manifest.json)")
        return {**summary, "cached": True}

    out.mkdir(parents=True, exist_ok=True)
    # a half-regenerated directory must never look valid, but stays recognisable as ours; a file of that name
    # that this generator did not write is never replaced (nor removed at the end)
    marker = out / _INCOMPLETE
    if marker.exists() and not (marker.is_file() and marker.read_text(encoding="utf-8", errors="replace")
                                == _WHAT + "\n"):
        raise TnnError(Diagnostic(f"{marker} exists and was not written by this generator",
                                  hint="move it away or choose another -o directory"))
    write_text_atomic(marker, _WHAT + "\n")
    if _is_our_manifest(out / "manifest.json"):  # only our own: a user's file of that name is left until replaced
        (out / "manifest.json").unlink()
    truth = _truth(backend, tpath)
    written: dict[str, str] = {}
    say(f"simulating the true system: training set ({settings['train_s'] / 3600:g} h, seed {seed_train})")
    _simulate_sets(truth, out, [("train.csv", seed_train, settings["train_s"], 0.0)], noise, written)
    jobs = [("val.csv", seed_val, settings["val_s"], 0.0)]
    ood_jobs = [(_ood_name(p, k), seed_ood + k, settings["ood_s"], p) for p in widen for k in range(n_ood)]
    say(f"simulating validation (seed {seed_val}) and {len(ood_jobs)} out-of-distribution sets")
    if settings["val_s"] == settings["ood_s"]:  # sets of equal length run as one batched rollout
        _simulate_sets(truth, out, jobs + ood_jobs, noise, written)
    else:
        _simulate_sets(truth, out, jobs, noise, written)
        if ood_jobs:
            _simulate_sets(truth, out, ood_jobs, noise, written)
    _write_manifest(out, settings, backend, tpath, written)
    say(f"wrote {len(written)} files to {out}")
    return {**summary, "cached": False}


def _checked_arguments(noise: float, widen: Sequence[float], n_ood: int) -> list[float]:
    """The widenings as floats; :class:`TnnError` for a widening, noise or count out of range."""
    widen = [float(w) for w in widen]
    for w in widen:
        if not (0.0 <= w <= 10.0):
            raise TnnError(Diagnostic(f"widening {w!r} out of range", hint="widen is a fraction: 0.1 for 10 %"))
    if noise < 0 or not np.isfinite(noise):
        raise TnnError(Diagnostic(f"noise σ must be ≥ 0 K, got {noise!r}"))
    if n_ood < 0:
        raise TnnError(Diagnostic(f"n_ood must be ≥ 0, got {n_ood!r}"))
    return widen


def _summary(out: Path, settings: dict, widen: list[float], n_ood: int) -> dict:
    """What :func:`generate_case_study` returns (without ``cached``): the directory and every file's path."""
    ood_files = {f"{round(p * 100):d}": [_ood_name(p, k) for k in range(n_ood)] for p in widen}
    return {"dir": str(out), "train": str(out / "train.csv"), "val": str(out / "val.csv"),
            "ood": {p: [str(out / f) for f in fs] for p, fs in ood_files.items()},
            "manifest": str(out / "manifest.json"), "settings": settings}


def _simulate_sets(truth: _Truth, out: Path, jobs: list[tuple[str, int, float, float]], noise: float,
                   written: dict[str, str]) -> None:
    """Simulate the data sets ``jobs`` (file name, seed, duration s, widening) as one batched rollout, check
    that the truth stayed physical, write them and record their SHA-256 in ``written``."""
    sigs = [case_study_inputs(seed, dur, w) for (_, seed, dur, w) in jobs]
    states, outputs = truth.simulate(np.stack([truth.input_matrix(s) for s in sigs]))
    for b, (fname, seed, _dur, w) in enumerate(jobs):
        _check_physical(truth, fname, seed, w, states[b])
    for b, (fname, seed, _dur, _w) in enumerate(jobs):
        _write_set(truth, out / fname, sigs[b], states[b], outputs[b], _noise(seed, states.shape[1], noise))
        written[fname] = file_sha256(out / fname)


def _write_manifest(out: Path, settings: dict, backend: str, truth_path: Path, written: dict[str, str]) -> None:
    """``manifest.json`` (the settings and every file's hash: what makes the directory a valid cache); then
    the directory is complete."""
    manifest = {
        "what": _WHAT,
        "settings": settings,
        "backend": backend,
        "tnn_dsl_version": __version__,
        "truth_network": str(truth_path),
        "files": written,
        "columns": "time_s (s); inputs in the network's units (I A, u1 1, Ta Tf1 Tf2 °C); T_out (°C, with noise "
                   "if noise_K > 0); T_<node> true node temperatures (°C, noise-free)",
    }
    write_text_atomic(out / "manifest.json", json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    (out / _INCOMPLETE).unlink()


PHYSICAL_RANGE_K = (173.15, 473.15)
"""Every true node temperature must stay within −100 … 200 °C; outside it the truth is unphysical."""


def _check_physical(truth: _Truth, fname: str, seed: int, widen: float, states: np.ndarray) -> None:
    """Refuse to write data from a truth that ran away (e.g. a derived resistance that turned negative
    for widened inputs): → TnnError naming the set, the node and the time."""
    lo, hi = PHYSICAL_RANGE_K
    bad = ~np.isfinite(states) | (states < lo) | (states > hi)
    if not bad.any():
        return
    k, i = np.argwhere(bad)[0]
    name = truth.model.state_names[i]
    val = states[k, i]
    shown = "not finite" if not np.isfinite(val) else f"{val - 273.15:.4g} °C"
    raise TnnError(Diagnostic(
        f"the true system is unphysical in {fname} (seed {seed}, inputs widened by {widen:.0%}): "
        f"T({name}) is {shown} at t = {k * SAMPLE_DT:g} s; no data written for it",
        hint=f"a derived parameter of {truth.path} probably leaves its physical range for these inputs (a "
             f"resistance such as 0.2·(1 + 1.5·(u1 − 0.5) − …) is negative for u1 < −1/6); bound it, e.g. "
             f"`max(0.1, …)`, or use smaller widenings"))


def _cache_valid(out: Path, settings: dict) -> bool:
    m = out / "manifest.json"
    if not m.is_file():
        return False
    try:
        manifest = json.loads(m.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    if manifest.get("settings") != settings:
        return False
    files = manifest.get("files") or {}
    if not files:
        return False
    for name, digest in files.items():
        p = out / name
        if not p.is_file() or file_sha256(p) != digest:
            return False
    return True
