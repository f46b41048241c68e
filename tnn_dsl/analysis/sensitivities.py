"""Sensitivity, identifiability and excitation (thesis §3.2, §4.2–4.4, §5.6.1–5.6.2; issue 5).

Five things, one module, both backends:

1. **Steady-state local sensitivity, exactly as thesis §4.3.** For a constant input vector ``u`` the steady
   state ``T*`` solves ``0 = f(T, u, θ)`` (eq. 4.1). Each candidate ``θ_i`` is scaled by ``α`` on a grid in
   ``[1 − δ, 1 + δ]`` (eq. 4.2; default ``δ = 0.2``, 5 values), the steady state is recomputed (eq. 4.3),
   the sensors read it (eq. 4.4), and the sensitivity is the slope of a least-squares line of the sensor
   output against ``α`` (eq. 4.5), per sensor (signed, K per unit ``α``) and summarised as the mean of
   ``|slope|`` over the sensors. The perturbation uses the compiled model's ``"scale:<name>"`` multipliers,
   so *any* parameter (constant, derived, learned) and any component heat flow (``pe.Q_hot``,
   ``pe.Q_cold``, ``f1.Q``) is scaled the same way. Capacities (and sensor lags) do not enter the steady
   state, so their steady sensitivity is exactly zero; they are judged by the dynamic sensitivity.
   Absolute temperatures and sensor offsets are not scanned (a multiplicative change of 295 K is not a
   meaningful perturbation; an offset of 0 cannot be scaled).

2. **The exact derivative (eq. 3.4)** at ``α = 1``: ``∂y*/∂α_i = θ_i ∂y*/∂θ_i = C (−(∂f/∂T)⁻¹ ∂f/∂α_i) +
   ∂h/∂α_i`` with the Jacobians of the model's ``rhs`` and ``outputs`` by automatic differentiation, in the
   same unit as the slope (K per unit ``α``), so the two are directly comparable; the slope equals it for a
   parameter that acts linearly and differs by the curvature over ``±δ`` otherwise.

3. **Dynamic sensitivity (eq. 3.2) along a data file**: ``S(t) = ∂y(t)/∂α`` by forward-mode automatic
   differentiation through ``model.rollout`` (JAX ``jacfwd``; PyTorch ``torch.func.jacfwd``), from the
   steady state of the first input sample (whose own sensitivity, eq. 3.4, is the initial condition
   ``S(0)``; ``init="fixed"`` uses ``S(0) = 0`` as eq. 3.2 states).

4. **Identifiability (thesis §3.2.2 and its future work on Fisher information).** With independent
   Gaussian sensor noise of standard deviation ``σ`` (K), the Fisher information of the relative parameters
   ``α`` is ``F = Σ_k S_kᵀ S_k / σ²`` over every measured sample ``k`` (NaN readings are skipped). From it:
   relative standard errors ``sqrt(diag F⁻¹)`` (``inf`` when a parameter loads on a direction with no
   information at all), the correlation matrix of the estimates, the eigen-directions of ``F`` with a
   standard error above ``max_se`` described in words ("raising R_a by 1 % and lowering R_b by 0.7 % leaves
   the sensors unchanged"), and every pair with ``|corr| > 0.95`` with a structural explanation when the
   network gives one (two resistances in series through an unmeasured node, parallel paths, ``ṁ`` and
   ``cp`` of one fluid, a capacity and its resistance). ``F`` is in relative units: multiply a relative
   standard error by the nominal value for the absolute one.

5. **Excitation (thesis §4.2, §5.6.1).** The block-Hankel matrix of the input sequence with window ``K``,
   its singular values, numerical rank, condition number ``κ = σ_max/σ_min`` (lower is better; ``inf`` when
   rank-deficient) and the entropy effective rank; see :func:`excitation` for the exact definition.

Finally a **recommendation**: a forward selection in order of sensitivity that keeps a parameter as
learnable only while the kept set stays identifiable from the data (every relative standard error below
``max_se`` and no estimate correlation above 0.95); the others stay fixed, each with the reason. Without data
the recommendation is sensitivity-only (thesis §4.4) and says so.

The public entry points are :func:`sensitivity` and :func:`excitation`; both return dataclasses with
``to_dict()`` (JSON-ready) and ``table()`` (terminal text).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from ..compiler import Backend, backend_of
from ..core import DataError, Diagnostic, TnnError
from ..ir import Network, Num

__all__ = [
    "sensitivity", "excitation", "SensitivityReport", "ParameterSensitivity", "Identifiability",
    "CorrelatedPair", "WeakDirection", "Recommendation", "ExcitationReport", "ExcitationResult",
    "hankel_matrix", "hankel_metrics", "fisher_analysis",
]

CORR_LIMIT = 0.95
"""Estimate correlations above this (in absolute value) are flagged as not separately identifiable."""

RESOLUTION = 1e-9
"""K per unit α: steady sensitivities below this are the steady-state solver's round-off (its Newton
tolerance is 1e-10 K) and are reported as exactly 0 — e.g. capacities, which do not enter the steady state."""

_SKIP_ROLES = {
    "temperature": "an absolute temperature: a multiplicative change of it is not a meaningful perturbation",
    "offset": "a sensor offset (additive, nominal 0): scaling it has no effect",
}

# =============================================================================================
# Small helpers
# =============================================================================================


def _jsonable(obj: Any) -> Any:
    """numpy → plain Python for ``json.dump``: NaN → ``None``, ±inf → ``"inf"``/``"-inf"``."""
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        if math.isnan(f):
            return None
        if math.isinf(f):
            return "inf" if f > 0 else "-inf"
        return f
    if hasattr(obj, "to_dict"):
        return obj.to_dict()
    return obj


def _fmt(x: float, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    if math.isinf(x):
        return "inf"
    return f"{x:.{digits}g}"


def _pct(x: float) -> str:
    if x is None or math.isnan(x):
        return "-"
    if math.isinf(x) or x > 1e4:
        return "inf" if math.isinf(x) else ">1e6 %"
    return f"{100 * x:.3g} %"


# =============================================================================================
# Excitation: the input Hankel matrix (thesis §4.2)
# =============================================================================================


def hankel_matrix(u: np.ndarray, window: int) -> np.ndarray:
    """Block-Hankel matrix of an input sequence.

    ``u`` (N, m) (or (N,)) → ``H`` (window·m, L) with ``L = N − window + 1``; column ``t`` stacks the samples
    ``u[t], u[t+1], …, u[t+window−1]`` (each an m-vector), divided by ``sqrt(L)`` so that the singular
    values are root-mean-square amplitudes and files of different length compare.
    """
    u = np.asarray(u, dtype=float)
    if u.ndim == 1:
        u = u[:, None]
    n, m = u.shape
    if window < 1:
        raise ValueError("window must be at least 1")
    if n < window:
        raise ValueError(f"{n} samples are fewer than the window {window}")
    w = np.lib.stride_tricks.sliding_window_view(u, window, axis=0)  # (L, m, K)
    L = w.shape[0]
    return w.transpose(0, 2, 1).reshape(L, window * m).T / math.sqrt(L)


def hankel_metrics(u: np.ndarray, window: int, rtol: float = 1e-10) -> dict[str, Any]:
    """Singular values and excitation metrics of ``hankel_matrix(u, window)``.

    Returns ``singular_values`` (descending, (window·m,)), ``rank`` (number above ``rtol·σ_max``),
    ``full_rank`` (rank = window·m), ``condition`` ``σ_max/σ_min`` (``inf`` when not of full rank, which
    includes an all-zero matrix), ``log10_condition`` and ``effective_rank`` ``exp(−Σ p_i log p_i)`` with
    ``p_i = σ_i/Σσ`` (Roy & Vetterli 2007; 1 … window·m, higher = more evenly spread singular values, 0 for
    an all-zero matrix).
    """
    H = hankel_matrix(u, window)
    s = np.linalg.svd(H, compute_uv=False) if H.size else np.zeros(0)
    smax = float(s[0]) if s.size else 0.0
    rank = int(np.sum(s > rtol * smax)) if smax > 0 else 0
    full = rank == H.shape[0]
    cond = float(smax / s[-1]) if full and smax > 0 else math.inf
    if smax > 0:
        p = s[s > 0] / s.sum()
        eff = float(np.exp(-np.sum(p * np.log(p))))
    else:
        eff = 0.0
    return {
        "singular_values": s, "rank": rank, "full_rank": bool(full), "condition": cond,
        "log10_condition": math.log10(cond) if math.isfinite(cond) else math.inf, "effective_rank": eff,
    }


@dataclass
class ExcitationResult:
    """The excitation of one data set. ``singular_values`` are those of the scaled, centred input block
    Hankel matrix (see :func:`excitation`), descending; ``condition = σ_max/σ_min`` (lower = better
    excited, ``inf`` if rank-deficient); ``rank`` numerical rank out of ``window·len(channels)``."""

    name: str
    path: str | None
    n_samples: int
    window: int
    channels: list[str]
    singular_values: np.ndarray
    rank: int
    full_rank: bool
    condition: float
    log10_condition: float
    effective_rank: float
    notes: list[str] = field(default_factory=list)

    @property
    def size(self) -> int:
        return self.window * len(self.channels)

    def to_dict(self) -> dict:
        return _jsonable({
            "name": self.name, "path": self.path, "n_samples": self.n_samples, "window": self.window,
            "channels": self.channels, "singular_values": self.singular_values, "rank": self.rank,
            "size": self.size, "full_rank": self.full_rank, "condition": self.condition,
            "log10_condition": self.log10_condition, "effective_rank": self.effective_rank,
            "notes": self.notes,
        })


EXCITATION_DEFINITION = (
    "Each input channel is centred on its own mean in each file and divided by a common scale (the largest "
    "standard deviation of that channel over all compared files), so one physical amplitude counts the same "
    "in every file; channels constant in every file are left out. The block-Hankel matrix H (window·m rows, "
    "N − window + 1 columns; column t stacks u[t..t+window−1]) is divided by sqrt(columns); the metric is its "
    "condition number σ_max/σ_min (inf when H is rank-deficient, e.g. constant or collinear inputs). Files are "
    "ranked by numerical rank (higher first), then condition number (lower first), then effective rank "
    "exp(entropy of σ/Σσ) (higher first)."
)


@dataclass
class ExcitationReport:
    """Excitation of several data sets, ranked best first (see ``definition``)."""

    results: list[ExcitationResult]
    window: int
    channels: list[str]
    excluded: list[str]
    scales: dict[str, float]
    definition: str = EXCITATION_DEFINITION

    @property
    def ranking(self) -> list[str]:
        return [r.name for r in self.results]

    def to_dict(self) -> dict:
        return _jsonable({
            "window": self.window, "channels": self.channels, "excluded_constant_channels": self.excluded,
            "scales": self.scales, "definition": self.definition, "ranking": self.ranking,
            "results": [r.to_dict() for r in self.results],
        })

    def table(self) -> str:
        lines = [f"Input excitation (Hankel window {self.window}; channels: {', '.join(self.channels) or 'none'})"]
        if self.excluded:
            lines.append(f"left out (constant in every file): {', '.join(self.excluded)}")
        head = f"{'rank':>4}  {'data':<40} {'samples':>8} {'H rank':>10} {'condition':>11} {'log10':>7} {'eff. rank':>9}"
        lines += [head, "-" * len(head)]
        for i, r in enumerate(self.results, 1):
            name = r.name if len(r.name) <= 40 else "…" + r.name[-39:]
            lines.append(
                f"{i:>4}  {name:<40} {r.n_samples:>8} {f'{r.rank}/{r.size}':>10} {_fmt(r.condition, 4):>11} "
                f"{_fmt(r.log10_condition, 3):>7} {r.effective_rank:>9.2f}")
            for n in r.notes:
                lines.append(f"      note: {n}")
        lines.append("lower condition number = richer excitation (thesis §4.2); inf = rank-deficient "
                     "(constant or collinear inputs, e.g. steady-state data).")
        return "\n".join(lines)


def _time_like(name: str) -> bool:
    return name.strip().lower() in {"t", "time", "time_s", "t_s", "seconds", "timestamp", "datetime", "date",
                                    "timedate", "", "unnamed: 0", "index"}


def _read_table_inputs(path: str, columns: Sequence[str] | None) -> tuple[list[str], np.ndarray, list[str]]:
    """Numeric columns of a CSV/Parquet file without a network: ``columns`` if given, else every numeric
    column that does not look like a time or index column."""
    import pandas as pd

    notes: list[str] = []
    if not os.path.isfile(path):
        raise DataError(Diagnostic(f"no such data file: {path}", hint="check the path"))
    try:
        if path.lower().endswith((".parquet", ".pq")):
            df = pd.read_parquet(path)
        else:
            df = pd.read_csv(path, sep=None, engine="python")
    except Exception as err:  # noqa: BLE001 - any reader problem is a data problem
        raise DataError(Diagnostic(f"{path}: cannot read the data file: {err}",
                                   hint="give a CSV (comma or semicolon separated) or a Parquet file")) from None
    if columns:
        missing = [c for c in columns if c not in df.columns]
        if missing:
            from ..ir import Span
            raise DataError(Diagnostic(
                f"no column {', '.join(repr(c) for c in missing)} in the data file",
                span=Span(file=path, line=1, col=1, end_line=1, end_col=1),
                hint=f"the columns are: {', '.join(map(str, df.columns))}"))
        names = list(columns)
    else:
        names = [str(c) for c in df.columns
                 if pd.api.types.is_numeric_dtype(df[c]) and not _time_like(str(c))]
        notes.append("no network given: every numeric column is treated as an input "
                     "(use --net NET or --columns to choose)")
    try:
        arr = df[names].to_numpy(dtype=float)
    except (ValueError, TypeError) as err:
        raise DataError(Diagnostic(f"{path}: a chosen column is not numeric: {err}",
                                   hint="choose numeric input columns with --columns")) from None
    bad = ~np.isfinite(arr)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        from ..ir import Span
        raise DataError(Diagnostic(f"missing or non-finite value in input column {names[col]!r}",
                                   span=Span(file=path, line=int(row) + 2, col=1, end_line=int(row) + 2, end_col=1),
                                   hint="fill or drop the gap before computing the excitation"))
    return names, arr, notes


def _excitation_sets(data, net, columns) -> list[tuple[str, str | None, list[str], np.ndarray, list[str]]]:
    """Normalise the ``data`` argument of :func:`excitation` to (name, path, channels, u (N, m), notes)."""
    if isinstance(data, (str, os.PathLike, np.ndarray, Mapping)) or hasattr(data, "inputs"):
        data = [data]
    sets = []
    for k, item in enumerate(data):
        if hasattr(item, "inputs") and hasattr(item, "input_names"):  # an Experiment
            sets.append((str(item.name), getattr(item, "path", None), list(item.input_names),
                         np.asarray(item.inputs, dtype=float), []))
        elif isinstance(item, np.ndarray):
            u = item[:, None] if item.ndim == 1 else item
            sets.append((f"array {k + 1}", None, [f"u{j}" for j in range(u.shape[1])], np.asarray(u, float), []))
        elif isinstance(item, Mapping):
            names = list(item)
            sets.append((f"set {k + 1}", None, names, np.column_stack([np.asarray(item[n], float) for n in names]), []))
        else:
            path = os.fspath(item)
            if net is not None:
                from ..data import read_data

                net_obj = _as_network(net)
                for e in read_data(net_obj, [path]):
                    u = np.asarray(e.inputs, dtype=float)
                    names = list(e.input_names)
                    if columns:
                        idx = [names.index(c) for c in columns if c in names]
                        u, names = u[:, idx], [names[i] for i in idx]
                    sets.append((str(e.name), path, names, u, []))
            else:
                names, u, notes = _read_table_inputs(path, columns)
                sets.append((os.path.basename(path), path, names, u, notes))
    if not sets:
        raise DataError(Diagnostic("no data to compute the excitation of", hint="give one or more data files"))
    return sets


def excitation(data, *, net=None, window: int = 20, columns: Sequence[str] | None = None,
               stride: int = 1, rtol: float = 1e-10) -> ExcitationReport:
    """Compare the input excitation of data sets by their block-Hankel singular values (thesis §4.2, §5.6.1).

    ``data``: a path, an ``Experiment``, an (N, m) array, a ``{name: (N,) array}`` mapping, or a list of these.
    With ``net`` (a ``Network`` or a ``.thn`` path) files are read with ``read_data`` and the network's inputs
    (SI) are the channels; without it, the numeric non-time columns (or ``columns``) are. ``stride`` keeps
    every ``stride``-th sample first (so the window spans ``window·stride`` samples).

    Exactly what is computed: every channel ``j`` of file ``f`` is centred on its mean in ``f`` and divided by
    the common scale ``s_j = max_f std(u_fj)``; channels with ``s_j = 0`` (constant in every file) are left
    out. :func:`hankel_metrics` then gives, per file, the singular values of the block-Hankel matrix
    (``window·m × (N − window + 1)``, divided by ``sqrt(N − window + 1)``), its numerical rank, the condition
    number ``σ_max/σ_min`` (``inf`` if rank-deficient: a constant input gives an all-zero matrix, inputs
    stepped together give collinear rows) and the effective rank. Files are ranked by rank (descending),
    condition number (ascending) and effective rank (descending). Returns an :class:`ExcitationReport`.
    """
    if window < 1:
        raise TnnError(Diagnostic(f"window must be a positive integer, not {window}", hint="try --window 20"))
    if stride < 1:
        raise TnnError(Diagnostic(f"stride must be a positive integer, not {stride}"))
    sets = _excitation_sets(data, net, columns)
    channels = sets[0][2]
    for name, path, ch, _, _ in sets[1:]:
        if ch != channels:
            raise DataError(Diagnostic(
                f"{name}: input channels {ch} differ from {channels} of {sets[0][0]}",
                hint="compare files with the same input columns (use --columns or --net)"))
    us = [u[::stride] for (_, _, _, u, _) in sets]
    centred = [u - u.mean(axis=0, keepdims=True) for u in us]
    scale = np.max(np.stack([c.std(axis=0) for c in centred]), axis=0) if us else np.zeros(0)
    tiny = 1e-12 * np.maximum(np.max(np.stack([np.abs(u).max(axis=0) for u in us]), axis=0), 1e-300)
    keep = np.flatnonzero(scale > tiny)
    excluded = [channels[j] for j in range(len(channels)) if j not in set(keep.tolist())]
    kept = [channels[j] for j in keep]
    results = []
    for (name, path, _, u, notes), c in zip(sets, centred):
        notes = list(notes)
        n = c.shape[0]
        if len(kept) == 0:
            m = {"singular_values": np.zeros(0), "rank": 0, "full_rank": False, "condition": math.inf,
                 "log10_condition": math.inf, "effective_rank": 0.0}
            notes.append("no input varies in any file: nothing excites the system")
        elif n < window:
            raise DataError(Diagnostic(f"{name}: {n} samples are fewer than the Hankel window {window}",
                                       hint="use a smaller --window"))
        else:
            z = c[:, keep] / scale[keep]
            m = hankel_metrics(z, window, rtol)
            flat = [kept[i] for i in range(len(kept)) if np.ptp(u[:, keep[i]]) == 0]
            if flat:
                notes.append(f"constant in this file: {', '.join(flat)}")
        results.append(ExcitationResult(name=name, path=None if path is None else str(path), n_samples=n,
                                        window=window, channels=kept, notes=notes, **m))
    results.sort(key=lambda r: (-r.rank, r.condition, -r.effective_rank))
    return ExcitationReport(results=results, window=window, channels=kept, excluded=excluded,
                            scales={kept[i]: float(scale[keep[i]]) for i in range(len(kept))})


# =============================================================================================
# Identifiability: Fisher information of relative parameters
# =============================================================================================


@dataclass
class WeakDirection:
    """A combination of relative parameter changes the data hardly see: an eigenvector of the Fisher
    information with standard error ``std_error`` (relative, 1/sqrt(eigenvalue)). ``weights`` are the
    relative changes (largest |w| = 1), only those with |w| ≥ 0.05."""

    weights: dict[str, float]
    eigenvalue: float
    std_error: float
    description: str

    def to_dict(self) -> dict:
        return _jsonable(self.__dict__)


@dataclass
class CorrelatedPair:
    """Two parameters whose estimates correlate with ``|correlation| > 0.95``.

    ``direct``: the pair by itself cannot be separated — their sensitivities are almost proportional
    (``|cos| ≥ 0.95``) or the network's structure says why (series through an unmeasured node, parallel
    paths, ``ṁ``/``cp`` of one fluid, one Peltier element); then ``combination`` names what the data do
    determine and ``combination_std_error`` is its relative standard error with the other parameter of the
    pair held fixed. Otherwise (``direct`` false) the correlation comes through the other free parameters
    (typically a weak direction involving a third one) and each may still be well determined."""

    a: str
    b: str
    correlation: float
    cos: float
    direct: bool
    explanation: str
    combination: str
    combination_std_error: float

    def to_dict(self) -> dict:
        return _jsonable(self.__dict__)


@dataclass
class Identifiability:
    """Fisher-information analysis of the parameters ``params`` in relative units (``α``).

    ``fisher`` (P, P) per (unit α)²; ``std_errors`` (P,) relative (fraction of the nominal value, ``inf``
    when not identifiable at all); ``abs_std_errors`` (P,) SI (NaN where the nominal is not a constant);
    ``correlation`` (P, P) of the estimates; ``eigenvalues`` ascending with ``eigenvectors`` as columns;
    ``sigma`` the noise level (K) and ``n_samples`` the number of sensor readings used; ``alone_std_errors``
    (P,) the relative standard error of each parameter when it is the only one estimated (``σ/‖s_i‖``, the
    best case)."""

    params: list[str]
    sigma: float
    n_samples: int
    fisher: np.ndarray
    std_errors: np.ndarray
    abs_std_errors: np.ndarray
    correlation: np.ndarray
    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    weak: list[WeakDirection]
    pairs: list[CorrelatedPair]
    max_se: float
    alone_std_errors: np.ndarray | None = None

    @property
    def condition(self) -> float:
        lo, hi = float(self.eigenvalues[0]), float(self.eigenvalues[-1])
        return hi / lo if lo > 0 else math.inf

    def identifiable(self, name: str) -> bool:
        i = self.params.index(name)
        paired = any(name in (p.a, p.b) for p in self.pairs if p.direct)
        return bool(self.std_errors[i] <= self.max_se and not paired)

    def to_dict(self) -> dict:
        return _jsonable({
            "params": self.params, "sigma": self.sigma, "n_samples": self.n_samples,
            "std_errors": dict(zip(self.params, self.std_errors)),
            "abs_std_errors": dict(zip(self.params, self.abs_std_errors)),
            "alone_std_errors": dict(zip(self.params, self.alone_std_errors if self.alone_std_errors is not None
                                         else [math.nan] * len(self.params))),
            "identifiable": {p: self.identifiable(p) for p in self.params},
            "correlation": self.correlation, "fisher": self.fisher, "eigenvalues": self.eigenvalues,
            "eigenvectors": self.eigenvectors, "condition": self.condition, "max_se": self.max_se,
            "weak_directions": [w.to_dict() for w in self.weak], "correlated_pairs": [p.to_dict() for p in self.pairs],
        })

    def table(self, max_lines: int = 8) -> str:
        lines = [f"Identifiability (Fisher information, σ = {self.sigma:g} K, {self.n_samples} readings; "
                 f"standard errors relative to the nominal value, all {len(self.params)} estimated together / alone)"]
        alone = self.alone_std_errors if self.alone_std_errors is not None else np.full(len(self.params), np.nan)
        order = np.lexsort((alone, self.std_errors))
        for i in order:
            p = self.params[i]
            mark = "ok" if self.identifiable(p) else "NOT separately identifiable"
            lines.append(f"  {p:<24} ±{_pct(self.std_errors[i]):>10}  alone ±{_pct(alone[i]):>10}   {mark}")
        direct = [pr for pr in self.pairs if pr.direct]
        for pr in direct[:max_lines]:
            lines.append(f"  corr({pr.a}, {pr.b}) = {pr.correlation:+.3f}: {pr.explanation}")
            if math.isfinite(pr.combination_std_error):
                lines.append(f"      the data determine {pr.combination} to ±{_pct(pr.combination_std_error)}")
        if len(direct) > max_lines:
            lines.append(f"  … and {len(direct) - max_lines} more pairs that cannot be separated (see --json)")
        indirect = [pr for pr in self.pairs if not pr.direct]
        if indirect:
            shown = ", ".join(f"({pr.a}, {pr.b}) {pr.correlation:+.3f}" for pr in indirect[:max_lines])
            more = f" … and {len(indirect) - max_lines} more" if len(indirect) > max_lines else ""
            lines.append("  correlated only through the other free parameters (each may still be well determined): "
                         + shown + more)
        for w in self.weak[:max_lines]:
            lines.append(f"  weak direction (±{_pct(w.std_error)}): {w.description}")
        if len(self.weak) > max_lines:
            lines.append(f"  … and {len(self.weak) - max_lines} more weak directions (see --json)")
        return "\n".join(lines)


def _structure(net: Network | None) -> dict[str, Any]:
    """Maps from parameter names to the elements that use them (for plain-words explanations)."""
    info: dict[str, Any] = {"link": {}, "cap": {}, "fluid": {}, "peltier": {}, "sensor_nodes": set(),
                            "graph": None, "source_nodes": set(), "heat_load_nodes": set(), "nominal": {}}
    if net is None:
        return info
    for link in net.links:
        info["link"][link.value] = link
    for n in net.nodes:
        info["cap"][n.capacitance] = n
    for f in net.fluids:
        for slot in ("mdot", "cp", "ua", "inlet"):
            info["fluid"][getattr(f, slot)] = (f, slot)
    for pe in net.peltiers:
        for slot in ("current", "seebeck", "resistance", "r_internal"):
            v = getattr(pe, slot)
            if v:
                info["peltier"][v] = (pe, slot)
    info["sensor_nodes"] = {s.node for s in net.sensors}
    info["source_nodes"] = {s.node for s in net.sources}
    info["heat_load_nodes"] = {t.name for fn in net.learned for t in fn.targets if t.kind == "heat_load"}
    try:
        info["graph"] = net.graph()
    except Exception:  # noqa: BLE001 - explanations are optional
        info["graph"] = None
    info["nominal"] = {p.name: p.value for p in net.params}
    return info


def _resistance_value(link, nominal: Mapping[str, float | None]) -> float | None:
    v = nominal.get(link.value)
    if v is None or v == 0:
        return None
    return v if link.form == "R" else 1.0 / v


def _explain_pair(a: str, b: str, info: dict[str, Any], cos: float) -> tuple[str, str, bool]:
    """A plain-words reason why ``a`` and ``b`` cannot be separated, what the data do determine, and
    whether the reason is structural (the network says the pair acts as one)."""
    links, caps, fluids, pelts = info["link"], info["cap"], info["fluid"], info["peltier"]
    g = info.get("graph")
    if a in links and b in links:
        la, lb = links[a], links[b]
        ends_a, ends_b = {la.a, la.b}, {lb.a, lb.b}
        if ends_a == ends_b:
            return (f"{a} and {b} connect the same two nodes ({la.a}, {la.b}) in parallel: the data see only "
                    f"their combined conductance", f"the parallel combination of {a} and {b}", True)
        shared = ends_a & ends_b
        for m in shared:
            is_node = g is not None and g.nodes.get(m, {}).get("kind") == "node"
            if not is_node:
                continue
            only_two = g.degree(m) == 2 and m not in info["source_nodes"] and m not in info["heat_load_nodes"]
            if m not in info["sensor_nodes"] and only_two:
                what = "sum" if la.form == lb.form == "R" else "series resistance"
                cap = next((c for c, n in caps.items() if n.name == m), None)
                tail = f" (node {m}'s own capacity {cap} is too small to show in the data)" if cap else ""
                return (f"{a} and {b} act only through their {what}: they are in series through node {m} "
                        f"and no sensor sits between them{tail}", f"{a} + {b}" if what == "sum"
                        else f"the series resistance of {a} and {b}", True)
    if a in fluids and b in fluids and fluids[a][0].name == fluids[b][0].name:
        f = fluids[a][0]
        if {fluids[a][1], fluids[b][1]} == {"mdot", "cp"}:
            return (f"{a} and {b} enter fluid {f.name} only through the heat-capacity rate ṁ·cp",
                    f"the product {f.name}.mdot·{f.name}.cp", True)
        return (f"{a} and {b} both set the heat flow of fluid {f.name}; the data see one combination",
                f"fluid {f.name}'s heat flow", True)
    if a in pelts and b in pelts and pelts[a][0].name == pelts[b][0].name:
        pe = pelts[a][0]
        return (f"{a} and {b} both belong to Peltier element {pe.name} and act on the sensors through its heat "
                f"flows alike; the data see one combination",
                f"the heat flow of {pe.name}", True)
    for c, r in ((a, b), (b, a)):
        if c in caps and r in links:
            node = caps[c].name
            if node in (links[r].a, links[r].b):
                if abs(cos) >= CORR_LIMIT:
                    return (f"{c} and {r} set together the time constant of node {node} (τ ≈ R·C)",
                            f"the time constant {r}·{c}", False)
    if cos >= 0.9:
        return (f"the effects of {a} and {b} on the sensors are almost proportional (cos = {cos:+.3f}): "
                f"a change of one looks like a change of the other", f"one combination of {a} and {b}", False)
    if cos <= -0.9:
        return (f"the effects of {a} and {b} on the sensors are almost opposite (cos = {cos:+.3f}): "
                f"raising both together leaves the sensors almost unchanged", f"one combination of {a} and {b}", False)
    return (f"correlated only through the other free parameters: their own effects on the sensors differ "
            f"(cos = {cos:+.3f})", f"one combination of {a} and {b}", False)


def _cov_from_fisher(F: np.ndarray, struct_rtol: float = 1e-13) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eigen-decomposition of ``F`` and the covariance ``F⁻¹`` with directions below ``struct_rtol·λ_max``
    clamped there (they carry no information); returns (eigenvalues ascending, eigenvectors, cov,
    structural-null mask per parameter)."""
    lam, V = np.linalg.eigh(0.5 * (F + F.T))
    lmax = max(float(lam[-1]), 0.0) if lam.size else 0.0
    floor = struct_rtol * lmax if lmax > 0 else 1e-300
    null = lam <= floor
    lam_c = np.where(null, floor, lam)
    cov = (V / lam_c) @ V.T
    loads_null = (np.abs(V[:, null]) > 1e-6).any(axis=1) if null.any() else np.zeros(F.shape[0], bool)
    return lam, V, cov, loads_null


def _rel_std_errors(S: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Relative standard errors and estimate correlations for sensitivity columns ``S`` (M, P)."""
    F = S.T @ S / sigma**2
    lam, V, cov, loads_null = _cov_from_fisher(F)
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    se = np.where(loads_null | (np.linalg.norm(S, axis=0) == 0), math.inf, se)
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = cov / np.outer(d, d)
    np.fill_diagonal(corr, 1.0)
    return se, np.clip(corr, -1.0, 1.0)


def fisher_analysis(S: np.ndarray, names: Sequence[str], sigma: float = 0.1, *, nominal: Mapping[str, float | None] | None = None,
                    net: Network | None = None, max_se: float = 0.1) -> Identifiability:
    """Identifiability from trajectory sensitivities.

    ``S`` (M, P): K per unit relative change ``α`` of each of the ``P`` parameters ``names``, one row per
    measured sensor reading (stack samples × sensors); ``sigma`` the sensor noise (K, > 0). ``nominal``
    (name → SI value) gives absolute standard errors; ``net`` the structure for plain-words explanations;
    ``max_se`` the largest relative standard error still called identifiable.
    """
    S = np.asarray(S, dtype=float)
    if S.ndim != 2 or S.shape[1] != len(names):
        raise ValueError(f"S must be (M, {len(names)}), got {S.shape}")
    if not sigma > 0:
        raise TnnError(Diagnostic(f"the noise level sigma must be positive, not {sigma}", hint="e.g. --sigma 0.1"))
    names = list(names)
    S = S[np.all(np.isfinite(S), axis=1)]
    F = S.T @ S / sigma**2
    lam, V, cov, loads_null = _cov_from_fisher(F)
    se, corr = _rel_std_errors(S, sigma)
    nominal = dict(nominal or {})
    abs_se = np.array([se[i] * abs(nominal[n]) if nominal.get(n) is not None else math.nan
                       for i, n in enumerate(names)])
    info = _structure(net)
    norms = np.linalg.norm(S, axis=0)
    # --- weak directions
    weak: list[WeakDirection] = []
    lmax = float(lam[-1]) if lam.size else 0.0
    for k in range(len(lam)):
        sek = 1.0 / math.sqrt(lam[k]) if lam[k] > 1e-13 * max(lmax, 1e-300) else math.inf
        if sek <= max_se:
            continue
        v = V[:, k] / np.max(np.abs(V[:, k]))
        big = [i for i in np.argsort(-np.abs(v)) if abs(v[i]) >= 0.05]
        weights = {names[i]: float(v[i]) for i in big}
        if len(big) > 1 and all(abs(v[i] - v[big[0]]) < 0.02 for i in big):
            desc = (f"raising {', '.join(names[i] for i in big)} together by the same percentage changes the "
                    f"sensor readings by less than the noise (only their ratios matter)")
        elif len(big) == 1:
            desc = (f"{names[big[0]]} has {'no' if norms[big[0]] == 0 else 'almost no'} effect on the sensors "
                    f"in this data")
        else:
            parts = []
            sign0 = np.sign(v[big[0]])
            for i in big[:4]:
                verb = "raising" if not parts else ("and raising" if np.sign(v[i]) == sign0 else "and lowering")
                parts.append(f"{verb} {names[i]} by {abs(v[i]):.2g} %")
            more = f" (and {len(big) - 4} smaller parts)" if len(big) > 4 else ""
            desc = " ".join(parts) + more + " changes the sensor readings by less than the noise"
        weak.append(WeakDirection(weights=weights, eigenvalue=float(lam[k]), std_error=sek, description=desc))
    # --- correlated pairs
    ident_weak = weak
    pairs: list[CorrelatedPair] = []
    P = len(names)
    for i in range(P):
        for j in range(i + 1, P):
            if abs(corr[i, j]) <= CORR_LIMIT or norms[i] == 0 or norms[j] == 0:
                continue
            cos = float(S[:, i] @ S[:, j] / (norms[i] * norms[j]))
            text, comb, structural = _explain_pair(names[i], names[j], info, cos)
            direct = structural or abs(cos) >= CORR_LIMIT
            if not direct:
                wk = max(ident_weak, key=lambda w: abs(w.weights.get(names[i], 0) * w.weights.get(names[j], 0)),
                         default=None)
                if wk is not None and wk.weights.get(names[i]) and wk.weights.get(names[j]):
                    text += f"; both move along the weak direction ({wk.description.split(' changes')[0]})"
                text += f"; each alone is determined to ±{_pct(float(se[i]))} and ±{_pct(float(se[j]))}"
            keep, drop = (i, j) if norms[i] >= norms[j] else (j, i)
            cols = [c for c in range(P) if c != drop]
            se_red, _ = _rel_std_errors(S[:, cols], sigma)
            se_keep = float(se_red[cols.index(keep)])
            # relative standard error of the combination (a sum: scaled by the share of the kept one)
            comb_se = se_keep
            if names[keep] in info["link"] and names[drop] in info["link"] and "series" in text:
                la, lb = info["link"][names[keep]], info["link"][names[drop]]
                ra, rb = _resistance_value(la, info["nominal"]), _resistance_value(lb, info["nominal"])
                if ra and rb:
                    comb_se = se_keep * ra / (ra + rb)  # d(r_a + r_b) = r_a·dα_a, relative to the sum
            pairs.append(CorrelatedPair(a=names[i], b=names[j], correlation=float(corr[i, j]), cos=cos, direct=direct,
                                        explanation=text, combination=comb,
                                        combination_std_error=comb_se if direct else math.nan))
    with np.errstate(divide="ignore"):
        alone = np.where(norms > 0, sigma / np.where(norms > 0, norms, 1.0), math.inf)
    return Identifiability(params=names, sigma=float(sigma), n_samples=int(S.shape[0]), fisher=F, std_errors=se,
                           abs_std_errors=abs_se, correlation=corr, eigenvalues=lam, eigenvectors=V, weak=weak,
                           pairs=pairs, max_se=max_se, alone_std_errors=alone)


# =============================================================================================
# Backend adapter (the only backend-specific code in this module)
# =============================================================================================


# =============================================================================================
# Sensitivity
# =============================================================================================


@dataclass
class ParameterSensitivity:
    """The sensitivity of every sensor to one parameter or component heat flow.

    ``alphas`` (A,) the scale factors; ``outputs`` (A, n_out) the steady sensor readings (K) at each;
    ``slope`` (n_out,) the least-squares slope of the readings against α (K per unit α, signed; thesis eq.
    4.5 without the absolute value); ``sensitivity`` = mean over sensors of ``|slope|`` (the ranking
    measure); ``autodiff`` (n_out,) the exact ``θ ∂y*/∂θ`` at α = 1 (eq. 3.4, K per unit α); ``linearity``
    the smallest R² of the line over the sensors; ``dynamic_rms``/``dynamic_max`` the RMS/max of
    ``|∂y(t)/∂α|`` along the data (K per unit α; ``None`` without data)."""

    name: str
    kind: str
    group: str
    role: str | None
    owner: str | None
    nominal: float | None
    unit: str | None
    alphas: np.ndarray
    outputs: np.ndarray
    slope: np.ndarray
    sensitivity: float
    autodiff: np.ndarray
    linearity: float
    dynamic_rms: float | None = None
    dynamic_max: float | None = None
    note: str | None = None

    @property
    def autodiff_sensitivity(self) -> float:
        return float(np.mean(np.abs(self.autodiff)))

    def to_dict(self) -> dict:
        return _jsonable(dict(self.__dict__, autodiff_sensitivity=self.autodiff_sensitivity))


@dataclass
class Recommendation:
    """``verdict``: ``"learn"`` (sensitive and identifiable), ``"fix"`` (insensitive, or confounded with a
    kept parameter, or not identifiable from this data) or ``"candidate"`` (sensitive; no data was given to
    check identifiability)."""

    name: str
    verdict: str
    reason: str

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class SensitivityReport:
    """Everything :func:`sensitivity` computed. ``parameters`` is ranked (most sensitive first; the ranking
    uses the steady sensitivity, ties — capacities at 0 — broken by the dynamic one)."""

    network: str
    backend: str
    delta: float
    alphas: np.ndarray
    inputs: dict[str, float]
    output_names: list[str]
    state_names: list[str]
    steady_state: dict[str, float]
    parameters: list[ParameterSensitivity]
    skipped: dict[str, str]
    identifiability: Identifiability | None
    data: list[str]
    recommendations: list[Recommendation]
    notes: list[str]
    min_effect: float

    @property
    def ranking(self) -> list[str]:
        return [p.name for p in self.parameters]

    def __getitem__(self, name: str) -> ParameterSensitivity:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(name)

    def to_dict(self) -> dict:
        return _jsonable({
            "network": self.network, "backend": self.backend, "delta": self.delta, "alphas": self.alphas,
            "inputs": self.inputs, "outputs": self.output_names, "steady_state": self.steady_state,
            "ranking": self.ranking, "parameters": [p.to_dict() for p in self.parameters],
            "skipped": self.skipped,
            "identifiability": None if self.identifiability is None else self.identifiability.to_dict(),
            "data": self.data, "recommendations": [r.to_dict() for r in self.recommendations],
            "notes": self.notes, "min_effect": self.min_effect,
        })

    def table(self, top: int | None = None) -> str:
        out = [f"Steady-state sensitivity of {', '.join(self.output_names)} (network {self.network}, "
               f"{self.backend}; α ∈ [{1 - self.delta:g}, {1 + self.delta:g}], thesis §4.3)",
               "inputs: " + ", ".join(f"{k} = {v:.6g}" for k, v in self.inputs.items())]
        dyn = any(p.dynamic_rms is not None for p in self.parameters)
        head = (f"{'#':>3}  {'parameter':<24} {'group':<10} {'|dy/dα| K':>11} {'autodiff K':>11} "
                f"{'R²':>6}" + (f" {'dyn. RMS K':>11}" if dyn else ""))
        out += [head, "-" * len(head)]
        for k, p in enumerate(self.parameters[: top or None], 1):
            line = (f"{k:>3}  {p.name:<24} {p.group:<10} {_fmt(p.sensitivity, 4):>11} "
                    f"{_fmt(p.autodiff_sensitivity, 4):>11} {_fmt(p.linearity, 3):>6}")
            if dyn:
                line += f" {_fmt(p.dynamic_rms if p.dynamic_rms is not None else math.nan, 4):>11}"
            out.append(line)
        by_reason: dict[str, list[str]] = {}
        for k, v in self.skipped.items():
            by_reason.setdefault(v, []).append(k)
        for reason, names in by_reason.items():
            out.append(f"not scanned: {', '.join(names)} ({reason})")
        if self.identifiability is not None:
            out += ["", self.identifiability.table()]
        if self.recommendations:
            out += ["", "Recommendation (thesis §4.4: combine with physical insight — keep well-known physics fixed)"]
            for verdict in ("learn", "candidate", "fix"):
                for r in self.recommendations:
                    if r.verdict == verdict:
                        out.append(f"  {r.verdict.upper():<9} {r.name:<24} {r.reason}")
        for n in self.notes:
            out.append(f"note: {n}")
        return "\n".join(out)

    def plot(self, path: str, top: int | None = 25) -> str:
        """A horizontal bar chart of the ranked sensitivities (like the thesis's Figure 5.3); PNG to ``path``."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        params = [p for p in self.parameters if p.sensitivity > 0][: top or None]
        colors = {"peltier": "tab:red", "link": "tab:blue", "fluid": "tab:cyan", "capacity": "tab:gray",
                  "source": "tab:orange", "radiation": "tab:purple", "sensor": "tab:olive", "parameter": "tab:green"}
        fig, ax = plt.subplots(figsize=(7.5, 0.32 * max(len(params), 3) + 1.4))
        ys = np.arange(len(params))[::-1]
        ax.barh(ys, [p.sensitivity for p in params], color=[colors.get(p.group, "tab:green") for p in params])
        ax.set_yticks(ys, [p.name for p in params])
        ax.set_xlabel(f"|Δy/Δα| (K per unit α), mean over {', '.join(self.output_names)}")
        ax.set_title(f"Local steady-state sensitivity, α ∈ [{1 - self.delta:g}, {1 + self.delta:g}]")
        handles = [plt.Rectangle((0, 0), 1, 1, color=c) for g, c in colors.items() if any(p.group == g for p in params)]
        labels = [g for g in colors if any(p.group == g for p in params)]
        if handles:
            ax.legend(handles, labels, loc="lower right", fontsize=8)
        ax.grid(axis="x", alpha=0.3)
        fig.tight_layout()
        from ..core import save_figure

        save_figure(fig, path, dpi=120)
        plt.close(fig)
        return path


def _as_network(net) -> Network:
    if isinstance(net, Network):
        return net
    if hasattr(net, "network") and hasattr(net, "rhs"):
        return net.network
    from ..lang import load

    return load(os.fspath(net))


def _is_absolute_temperature(p) -> bool:
    """A boundary/inlet temperature, or a parameter written in degC/degF, or a kelvin value above 150 K."""
    if p.role == "temperature":
        return True
    unit = (p.unit or "").replace("°", "deg").strip()
    if unit in ("degC", "degF", "celsius", "fahrenheit"):
        return True
    return p.dim == {"K": 1.0} and p.value is not None and p.value > 150.0


def _targets(net: Network) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """The scale targets: every parameter (except absolute temperatures and offsets) and every component
    heat flow, each as ``{name, kind, group, role, owner, nominal, unit}``."""
    info = _structure(net)
    learned = net.learned_targets()
    sensor_params = {s.lag for s in net.sensors if s.lag} | {s.offset for s in net.sensors if s.offset}
    source_params = {s.value for s in net.sources}
    rad_params = {getattr(r, k) for r in net.radiations for k in ("area", "emissivity", "view_factor")}
    targets, skipped = [], {}
    for p in net.params:
        role = "temperature" if _is_absolute_temperature(p) else p.role
        if role in _SKIP_ROLES:
            skipped[p.name] = _SKIP_ROLES[role] + (" (it is in the identifiability analysis)" if p.free else "")
            continue
        if p.name in info["link"]:
            group = "link"
        elif p.name in info["cap"]:
            group = "capacity"
        elif p.name in info["peltier"]:
            group = "peltier"
        elif p.name in info["fluid"]:
            group = "fluid"
        elif p.name in source_params:
            group = "source"
        elif p.name in rad_params:
            group = "radiation"
        elif p.name in sensor_params:
            group = "sensor"
        else:
            group = "parameter"
        kind = "learned" if p.name in learned else ("constant" if isinstance(p.expr, Num) else "derived")
        note = None
        if group == "capacity":
            note = "a capacity does not enter the steady state (zero steady sensitivity); see the dynamic sensitivity"
        elif group == "sensor" and p.role == "time_constant":
            note = "a sensor lag does not enter the steady state; see the dynamic sensitivity"
        elif p.value == 0:
            note = "nominal value 0: scaling it has no effect"
        targets.append({"name": p.name, "kind": kind, "group": group, "role": p.role, "owner": p.owner,
                        "nominal": p.value, "unit": p.unit, "note": note})
    for pe in net.peltiers:
        for flow in ("Q_hot", "Q_cold"):
            targets.append({"name": f"{pe.name}.{flow}", "kind": "flow", "group": "peltier", "role": None,
                            "owner": f"peltier {pe.name}", "nominal": None, "unit": "W", "note": None})
    for f in net.fluids:
        targets.append({"name": f"{f.name}.Q", "kind": "flow", "group": "fluid", "role": None,
                        "owner": f"fluid {f.name}", "nominal": None, "unit": "W", "note": None})
    return targets, skipped


def _default_fisher_params(net: Network, targets: list[dict[str, Any]]) -> list[str]:
    """Constant parameters (plus every ``free`` one, temperatures included) with a nonzero nominal value;
    derived parameters (functions of inputs) and component flows are not parameters one estimates."""
    by = {t["name"]: t for t in targets}
    out = []
    for p in net.params:
        if not isinstance(p.expr, Num) or p.value == 0:
            continue
        if p.name in by and by[p.name]["kind"] in ("constant", "learned"):
            out.append(p.name)
        elif p.free and (p.role == "offset" or _is_absolute_temperature(p)):
            out.append(p.name)
    learned = net.learned_targets()
    for name in learned:
        if name in by and name not in out:
            out.append(name)
    return out


def _input_vector(net: Network, inputs: Mapping[str, float] | None, experiments) -> tuple[np.ndarray, list[str]]:
    names = net.input_names
    notes = []
    given = dict(inputs or {})
    unknown = [k for k in given if k not in names]
    if unknown:
        raise TnnError(Diagnostic(f"unknown input {', '.join(map(repr, unknown))}",
                                  hint=f"the network's inputs are: {', '.join(names) or '(none)'}"))
    u = np.full(len(names), np.nan)
    for i, n in enumerate(names):
        if n in given:
            u[i] = float(given[n])
    missing = [n for i, n in enumerate(names) if not np.isfinite(u[i])]
    if missing and experiments:
        allu = np.concatenate([np.asarray(e.inputs, float) for e in experiments], axis=0)
        mean = np.nanmean(allu, axis=0)
        for i, n in enumerate(names):
            if not np.isfinite(u[i]):
                u[i] = mean[i]
        notes.append(f"steady-state inputs not given ({', '.join(missing)}) are the data means")
        missing = []
    if missing:
        raise TnnError(Diagnostic(
            f"the steady state needs a constant value for every input; missing: {', '.join(missing)}",
            hint="give them as --inputs " + " ".join(f"{n}=VALUE" for n in missing) + " (or give a data file)"))
    return u, notes


def sensitivity(net, data=None, *, inputs: Mapping[str, float] | None = None, backend: str = "jax",
                dtype: str = "float64", params: Mapping[str, Any] | None = None, delta: float = 0.2,
                n_alpha: int = 5, targets: Sequence[str] | None = None, fisher_params: Sequence[str] | None = None,
                sigma: float = 0.1, max_se: float = 0.1, min_effect: float | None = None, min_rel: float = 0.05,
                integrator: str = "rk4", init: str = "steady", seed: int = 0) -> SensitivityReport:
    """Sensitivity, identifiability and a learnable-parameter recommendation (see the module docstring).

    ``net``: a ``Network``, a ``.thn`` path or a compiled ``Model`` (then ``backend``/``dtype`` are its own).
    ``data``: optional data path(s) or ``Experiment``(s): adds the dynamic sensitivity, the Fisher
    identifiability analysis and a data-based recommendation. ``inputs``: constant input values for the steady
    state, **SI** (kelvin for temperature inputs); inputs not given take the data mean. ``params``: parameter
    arrays (numpy or backend) overriding ``model.init_params(seed)`` (e.g. a trained model's). ``delta``: the
    α range ``[1 − δ, 1 + δ]`` with ``n_alpha`` values. ``targets``: names to scan (default: every parameter
    but absolute temperatures and offsets, and every component heat flow). ``fisher_params``: the
    parameters of the identifiability analysis (default: constants with a nonzero value, free temperatures,
    learned targets). ``sigma``: sensor noise (K). ``max_se``: the largest relative standard error still
    identifiable. ``min_effect``: the smallest sensor change (K) over ``±δ`` (steady, or RMS along the data)
    that makes a parameter sensitive (default: ``min_rel`` = 5 % of the largest such change among the
    parameters of the identifiability analysis; whether a sensitive parameter is worth learning against the
    noise is then the Fisher analysis's question). ``init``: ``"steady"`` (trajectory from the steady state of the first
    input sample, ``S(0)`` by eq. 3.4) or ``"fixed"`` (``S(0) = 0``).
    """
    if not 0 < delta < 1:
        raise TnnError(Diagnostic(f"delta must be in (0, 1), not {delta}", hint="the thesis uses --delta 0.2"))
    if n_alpha < 2:
        raise TnnError(Diagnostic(f"n_alpha must be at least 2, not {n_alpha}"))
    if not sigma > 0:
        raise TnnError(Diagnostic(f"the noise level sigma must be positive, not {sigma}", hint="e.g. --sigma 0.1"))
    if init not in ("steady", "fixed"):
        raise ValueError("init must be 'steady' or 'fixed'")

    if hasattr(net, "rhs") and hasattr(net, "network"):
        model = net
        network = model.network
    else:
        from ..compiler import compile as _compile

        network = _as_network(net)
        model = _compile(network, backend=backend, dtype=dtype)
    if not network.sensors:
        raise TnnError(Diagnostic(f"network {network.name} has no sensor: there is no output to be sensitive",
                                  hint="add `sensor NAME = NODE`"))
    from ..data import as_experiments

    experiments = as_experiments(network, data)

    base = dict(model.init_params(seed=seed))
    if params:
        for k, v in params.items():
            base[k] = v
    ops = backend_of(model)
    base = {k: (ops.asarray(v) if isinstance(v, (np.ndarray, float, int, np.floating)) else v) for k, v in base.items()}

    all_targets, skipped = _targets(network)
    if targets is not None:
        by = {t["name"]: t for t in all_targets}
        unknown = [t for t in targets if t not in by]
        if unknown:
            raise TnnError(Diagnostic(f"cannot scan {', '.join(map(repr, unknown))}: not a parameter or component flow",
                                      hint="scannable: " + ", ".join(by)))
        all_targets = [by[t] for t in targets]
    names = [t["name"] for t in all_targets]
    fisher_names = list(fisher_params) if fisher_params is not None else _default_fisher_params(network, all_targets)
    pnames = set(network.param_names) | set(names)
    unknown = [n for n in fisher_names if n not in pnames]
    if unknown:
        raise TnnError(Diagnostic(f"unknown parameter {', '.join(map(repr, unknown))} for the identifiability analysis",
                                  hint="parameters: " + ", ".join(network.param_names)))
    scale_names = names + [n for n in fisher_names if n not in names]
    P = len(scale_names)

    def with_scales(s):
        p = dict(base)
        for i, n in enumerate(scale_names):
            p[f"scale:{n}"] = s[i]
        return p

    u_np, notes = _input_vector(network, inputs, experiments)
    u = ops.asarray(u_np)

    def steady(s):
        p = with_scales(s)
        T = model.steady_state(p, u)
        return T, model.outputs(p, T, u)

    steady_j = ops.jit(steady, fallback=True)
    ones = np.ones(P)
    T_star_b, y_star_b = steady_j(ops.asarray(ones))
    T_star = ops.numpy(T_star_b)
    if not np.all(np.isfinite(T_star)):
        raise TnnError(Diagnostic("the steady state for these inputs is not finite",
                                  hint="check the inputs (a Peltier current too large for its heat sink?)"))

    # --- eq. 3.4: exact derivative at α = 1 ------------------------------------------------
    J_T, J_s, H_T, H_s = _local_jacobians(model, ops, with_scales, T_star, u, P)
    try:
        dT_ds = -np.linalg.solve(J_T, J_s)
    except np.linalg.LinAlgError:
        raise TnnError(Diagnostic(
            "∂f/∂T is singular at the steady state: some node has no heat path to a boundary",
            hint="connect every node to a boundary (or a fluid) through links")) from None
    dy_ds = H_T @ dT_ds + H_s  # (n_out, P)
    residual = float(np.max(np.abs(ops.numpy(model.rhs(with_scales(ops.asarray(ones)), T_star_b, u)))))
    if residual > 1e-6:
        notes.append(f"the steady state leaves |dT/dt| up to {residual:.2g} K/s: not fully converged")

    # --- eq. 4.2–4.5: the α scan -------------------------------------------------------------
    alphas = np.linspace(1 - delta, 1 + delta, n_alpha)
    results: list[ParameterSensitivity] = []
    n_out = len(model.output_names)
    for i, t in enumerate(all_targets):
        ys = np.empty((n_alpha, n_out))
        for a_k, a in enumerate(alphas):
            s = ones.copy()
            s[i] = a
            _, y = steady_j(ops.asarray(s))
            ys[a_k] = ops.numpy(y)
        note = t["note"]
        if not np.all(np.isfinite(ys)):
            note = (note + "; " if note else "") + "no finite steady state for part of the α range"
        A = np.column_stack([alphas, np.ones_like(alphas)])
        coef, *_ = np.linalg.lstsq(A, np.nan_to_num(ys), rcond=None)
        slope = coef[0]
        fit = A @ coef
        ss_res = np.sum((ys - fit) ** 2, axis=0)
        ss_tot = np.sum((ys - ys.mean(axis=0)) ** 2, axis=0)
        r2 = np.where(ss_tot > 1e-24, 1 - ss_res / np.where(ss_tot > 0, ss_tot, 1), 1.0)
        slope = np.where(np.abs(slope) < RESOLUTION, 0.0, slope)
        exact = np.where(np.abs(dy_ds[:, i]) < RESOLUTION, 0.0, dy_ds[:, i])
        results.append(ParameterSensitivity(
            name=t["name"], kind=t["kind"], group=t["group"], role=t["role"], owner=t["owner"],
            nominal=t["nominal"], unit=t["unit"], alphas=alphas, outputs=ys, slope=slope,
            sensitivity=float(np.mean(np.abs(slope))), autodiff=exact, linearity=float(np.min(r2)), note=note))

    # --- eq. 3.2: dynamic sensitivity along the data ----------------------------------------
    ident = None
    rows: list[np.ndarray] = []
    dyn_sq = np.zeros(P)
    dyn_max = np.zeros(P)
    dyn_n = 0
    for e in experiments:
        Sx = _trajectory_sensitivity(model, ops, with_scales, scale_names, e, integrator, init)
        mask = np.isfinite(np.asarray(e.outputs, dtype=float)) if getattr(e, "outputs", None) is not None \
            else np.ones(Sx.shape[:2], bool)
        dyn_sq += np.sum(Sx**2, axis=(0, 1))
        dyn_max = np.maximum(dyn_max, np.max(np.abs(Sx), axis=(0, 1)))
        dyn_n += Sx.shape[0] * Sx.shape[1]
        rows.append(Sx[mask])
    if experiments:
        rms = np.sqrt(dyn_sq / max(dyn_n, 1))
        for i, r in enumerate(results):
            r.dynamic_rms, r.dynamic_max = float(rms[i]), float(dyn_max[i])
        S_all = np.concatenate(rows, axis=0)
        if S_all.shape[0] == 0:
            notes.append("the data hold no sensor readings: no identifiability analysis")
        else:
            cols = [scale_names.index(n) for n in fisher_names]
            nominal = {p.name: p.value for p in network.params}
            ident = fisher_analysis(S_all[:, cols], fisher_names, sigma, nominal=nominal, net=network, max_se=max_se)
            ident_S = S_all[:, cols]
    results.sort(key=lambda r: (-r.sensitivity, -(r.dynamic_rms or 0.0), r.name))

    effects = [delta * max(r.sensitivity, r.dynamic_rms or 0.0) for r in results if r.name in fisher_names]
    if min_effect is None:
        min_effect = min_rel * max(effects, default=0.0)
        notes.append(f"sensitive = a ±{100 * delta:g} % change moves the sensors by at least {_fmt(min_effect, 3)} K "
                     f"({100 * min_rel:g} % of the largest such change)")
    min_effect = float(min_effect)
    recs = _recommend(results, fisher_names, ident, ident_S if ident is not None else None, sigma, max_se,
                      delta, min_effect, network, bool(experiments))
    return SensitivityReport(
        network=network.name, backend=model.backend, delta=float(delta), alphas=alphas,
        inputs={n: float(v) for n, v in zip(network.input_names, u_np)}, output_names=list(model.output_names),
        state_names=list(model.state_names), steady_state=dict(zip(model.state_names, map(float, T_star))),
        parameters=results, skipped=skipped, identifiability=ident, data=[str(e.name) for e in experiments],
        recommendations=recs, notes=notes, min_effect=min_effect)


def _local_jacobians(model, ops: Backend, with_scales, T_np: np.ndarray, u, P: int):
    """``∂f/∂T (n_s, n_s)``, ``∂f/∂α (n_s, P)``, ``∂h/∂T (n_o, n_s)``, ``∂h/∂α (n_o, P)`` at ``T``, ``u`` and
    ``α = 1`` (``f`` = ``model.rhs``, ``h`` = ``model.outputs``), by one forward-mode Jacobian."""
    n_s = T_np.shape[-1]

    def g(z):
        p = with_scales(z[n_s:])
        T = z[:n_s]
        return model.xp.concat([model.rhs(p, T, u), model.outputs(p, T, u)])

    J = ops.jacobian(g, np.concatenate([T_np, np.ones(P)]))
    return J[:n_s, :n_s], J[:n_s, n_s:], J[n_s:, :n_s], J[n_s:, n_s:]


def _trajectory_sensitivity(model, ops: Backend, with_scales, scale_names, exp, integrator: str, init: str) -> np.ndarray:
    """``S`` (N, n_out, P): ``∂y(t_k)/∂α`` along one experiment (eq. 3.2 by forward-mode AD through the rollout)."""
    P = len(scale_names)
    n_s = len(model.state_names)
    u_np = np.asarray(exp.inputs, dtype=float)
    U = ops.asarray(u_np)
    u0 = ops.asarray(u_np[0])
    ones = np.ones(P)
    p1 = with_scales(ops.asarray(ones))
    T0 = model.steady_state(p1, u0)
    T0_np = ops.numpy(T0)
    if init == "steady":
        J_T, J_s, _, _ = _local_jacobians(model, ops, with_scales, T0_np, u0, P)
        dT0 = -np.linalg.solve(J_T, J_s)
    else:
        dT0 = np.zeros((n_s, P))
    dt = float(exp.dt)

    def traj(z):
        s, T = z[:P], z[P:]
        _, y = model.rollout(with_scales(s), T, U, dt, integrator=integrator)
        return y

    J = ops.jacobian(traj, np.concatenate([ones, T0_np]))  # (N, n_out, P + n_s)
    return J[..., :P] + J[..., P:] @ dT0


def _recommend(results: list[ParameterSensitivity], fisher_names: list[str], ident: Identifiability | None,
               S: np.ndarray | None, sigma: float, max_se: float, delta: float, min_effect: float,
               net: Network, have_data: bool) -> list[Recommendation]:
    """Forward selection in order of sensitivity (see the module docstring)."""
    by = {r.name: r for r in results}
    order = [r.name for r in results if r.name in fisher_names]
    order += [n for n in fisher_names if n not in order]
    recs: list[Recommendation] = []

    def effect(n: str) -> float:
        r = by.get(n)
        if r is None:
            return math.nan
        e = delta * r.sensitivity
        if r.dynamic_rms is not None:
            e = max(e, delta * r.dynamic_rms)
        return e

    info = _structure(net)
    selected: list[str] = []
    for n in order:
        e = effect(n)
        if math.isfinite(e) and (e < min_effect or e == 0):
            what = "steady or dynamic " if have_data else "steady "
            recs.append(Recommendation(n, "fix", f"insensitive: ±{100 * delta:g} % changes the {what}sensor "
                                                 f"readings by {_fmt(e, 2)} K < {_fmt(min_effect, 3)} K"))
            continue
        if ident is None or S is None:
            kind = "capacity" if by.get(n) is not None and by[n].group == "capacity" else None
            reason = (f"sensitive: ±{100 * delta:g} % moves the sensors by {_fmt(e, 3)} K"
                      if math.isfinite(e) else "not scanned")
            if kind:
                reason = "a capacity: no steady-state effect; give data to judge its dynamic effect"
            recs.append(Recommendation(n, "candidate", reason + "; give a data file to check identifiability"))
            continue
        trial = selected + [n]
        cols = [fisher_names.index(x) for x in trial]
        se, corr = _rel_std_errors(S[:, cols], sigma)
        j = len(trial) - 1
        worst = int(np.argmax(np.abs(corr[j, :j]))) if j > 0 else -1
        c = float(corr[j, worst]) if worst >= 0 else 0.0
        if np.all(se <= max_se) and abs(c) <= CORR_LIMIT:
            selected.append(n)
            head = (f"sensitive (±{100 * delta:g} % → {_fmt(e, 3)} K) and " if math.isfinite(e)
                    else "an absolute temperature (not scanned), ")
            recs.append(Recommendation(n, "learn", head + f"identifiable (±{_pct(float(se[j]))} with the others kept)"))
            continue
        if abs(c) > CORR_LIMIT:
            other = trial[worst]
            a, b = fisher_names.index(n), fisher_names.index(other)
            na, nb = np.linalg.norm(S[:, a]), np.linalg.norm(S[:, b])
            cos = float(S[:, a] @ S[:, b] / (na * nb)) if na > 0 and nb > 0 else 0.0
            text, _, _ = _explain_pair(n, other, info, cos)
            recs.append(Recommendation(n, "fix", f"confounded with {other} (corr {c:+.3f}): {text}; learn only "
                                                 f"one of them: {other} (more sensitive), or {n} instead if physical "
                                                 f"insight says {n} is the uncertain one"))
        else:
            bad = [trial[k] for k in range(len(trial)) if se[k] > max_se]
            recs.append(Recommendation(n, "fix", f"not identifiable from this data together with the kept "
                                                 f"parameters (standard error ±{_pct(float(se[j]))}"
                                                 + (f"; it would spoil {', '.join(b for b in bad if b != n)}"
                                                    if any(b != n for b in bad) else "") + ")"))
    return recs
