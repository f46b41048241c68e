"""Excitation (thesis §4.2): how well a data set's inputs excite the system, from the singular values of the
input block-Hankel matrix; one report ranks data files."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from ..core import DataError, Diagnostic, TnnError, to_jsonable
from .common import _as_network, _fmt

__all__ = ["excitation", "ExcitationReport", "ExcitationResult", "hankel_matrix", "hankel_metrics",
           "EXCITATION_DEFINITION"]


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
        return to_jsonable({
            "name": self.name, "path": self.path, "n_samples": self.n_samples, "window": self.window,
            "channels": self.channels, "singular_values": self.singular_values, "rank": self.rank,
            "size": self.size, "full_rank": self.full_rank, "condition": self.condition,
            "log10_condition": self.log10_condition, "effective_rank": self.effective_rank,
            "notes": self.notes,
        }, inf_as_text=True)


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
        return to_jsonable({
            "window": self.window, "channels": self.channels, "excluded_constant_channels": self.excluded,
            "scales": self.scales, "definition": self.definition, "ranking": self.ranking,
            "results": [r.to_dict() for r in self.results],
        }, inf_as_text=True)

    def table(self) -> str:
        lines = [f"Input excitation (Hankel window {self.window}; channels: {', '.join(self.channels) or 'none'})"]
        if self.excluded:
            lines.append(f"left out (constant in every file): {', '.join(self.excluded)}")
        head = (f"{'rank':>4}  {'data':<40} {'samples':>8} {'H rank':>10} {'condition':>11} {'log10':>7} "
                f"{'eff. rank':>9}")
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


def excitation(data: Any, *, net: Any = None, window: int = 20, columns: Sequence[str] | None = None,
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
