"""Writing a CSV of time series (atomic; temperatures in the network's unit)."""

from __future__ import annotations

import csv
import os
from typing import Iterable

import numpy as np

from ..core import atomic_path
from .units import from_kelvin

__all__ = ["write_csv"]


def write_csv(
    path: str | os.PathLike,
    t: np.ndarray,
    columns: dict[str, np.ndarray],
    temperature_unit: str,
    *,
    kelvin: Iterable[str] | None = None,
    time_col: str = "time_s",
    digits: int = 10,
) -> None:
    """Write a CSV with a time column and ``columns`` (each (N,)), temperatures in the file's units.

    Columns named in ``kelvin`` (default: all of them) hold kelvin and are written in
    ``temperature_unit`` (``degC``/``K``/``degF``); the others are written as they are. NaN is written
    as an empty cell. The file is written to a temporary name, flushed and renamed (never half-written)."""
    path = os.fspath(path)
    t = np.asarray(t, dtype=np.float64)
    kel = set(columns) if kelvin is None else set(kelvin)
    cols = {}
    for name, v in columns.items():
        v = np.asarray(v, dtype=np.float64)
        if v.shape != t.shape:
            raise ValueError(f"column {name!r} has shape {v.shape}, time has {t.shape}")
        cols[name] = from_kelvin(v, temperature_unit) if name in kel else v
    fmt = f"{{:.{digits}g}}"
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow([time_col, *cols])
        arrays = [cols[c] for c in cols]
        for k in range(t.shape[0]):
            w.writerow([fmt.format(t[k]), *("" if not np.isfinite(a[k]) else fmt.format(a[k]) for a in arrays)])
