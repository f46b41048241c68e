"""The time of a data file: which column it is, its unit (from the name, a suffix or a companion column), timestamps,
and the sample step; resampling inputs (zero-order hold, interval means) and outputs (linear) onto the model's step."""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from ..core import DataError, Diagnostic
from .tables import MAX_REPORTED, _find_column, _numeric, _plain_numbers, _row_list, _Table

__all__ = ["TIME_NAMES"]

TIME_NAMES = ("t", "time", "time_s", "timestamp", "datetime", "date_time", "timedate", "date")
"""Time-column names tried in this order (case-insensitive) when ``time_col`` is not given."""


_TIME_UNITS = {
    "s": 1.0, "sec": 1.0, "secs": 1.0, "second": 1.0, "seconds": 1.0,
    "ms": 1e-3,
    "min": 60.0, "mins": 60.0, "minute": 60.0, "minutes": 60.0,
    "h": 3600.0, "hr": 3600.0, "hrs": 3600.0, "hour": 3600.0, "hours": 3600.0,
    "d": 86400.0, "day": 86400.0, "days": 86400.0,
}


def _suffix_unit(name: str) -> float | None:
    n = name.strip().lower()
    for open_, close in (("[", "]"), ("(", ")")):
        if n.endswith(close) and open_ in n:
            u = n[n.rindex(open_) + 1 : -1].strip()
            if u in _TIME_UNITS:
                return _TIME_UNITS[u]
    for sep in ("_", " ", "-"):
        if sep in n:
            u = n.rsplit(sep, 1)[1]
            if u in _TIME_UNITS:
                return _TIME_UNITS[u]
    return None


_NOT_READ = object()


def _as_timestamps(vals: np.ndarray, plain: Any = _NOT_READ) -> tuple[np.ndarray, np.ndarray] | None:
    """(seconds since epoch as float64 with NaN for unparsable, ok mask) or None if it is not a time-stamp
    column (fewer than half the cells parse). ``plain``: the cells already read as plain numbers
    (:meth:`_Table.plain`, None when they are not), if the caller has them."""
    if vals.dtype.kind != "M":
        if vals.dtype.kind in "fiub" or len(vals) == 0:
            return None
        if plain is _NOT_READ:
            plain = _plain_numbers(np.array(["" if v is None else str(v) for v in vals], dtype=object))
        if plain is not None and (~np.isnan(plain)).mean() > 0.5:
            return None  # a column of plain numbers (decided without importing pandas)
    import pandas as pd

    if vals.dtype.kind == "M":
        s = pd.Series(vals)
        if getattr(s.dt, "tz", None) is not None:
            s = s.dt.tz_convert("UTC").dt.tz_localize(None)
        ns = s.to_numpy(dtype="datetime64[ns]").astype(np.int64).astype(np.float64)
        ok = ~pd.isna(s).to_numpy()
        return np.where(ok, ns / 1e9, np.nan), ok
    text = pd.Series(["" if v is None else str(v) for v in vals])
    # a column of plain numbers is not a time-stamp column
    if pd.to_numeric(text, errors="coerce").notna().mean() > 0.5:
        return None
    try:
        ts = pd.to_datetime(text, errors="coerce", utc=True, format="ISO8601")
    except (ValueError, TypeError):
        ts = pd.to_datetime(text, errors="coerce", utc=True, format="mixed")
    ok = ts.notna().to_numpy()
    if ok.mean() < 0.5:
        return None
    sec = np.full(len(vals), np.nan)
    sec[ok] = ts[ok].dt.tz_localize(None).to_numpy(dtype="datetime64[ns]").astype(np.int64) / 1e9
    return sec, ok


def _time(tab: _Table, time_col: str | None, time_unit: str | None, dt: float | None,
          used: set[int], problems: list[Diagnostic], notes: list[str]):
    """→ (t seconds from the first row (n_rows,), column index or None, start text or None)."""
    n = tab.n_rows
    j: int | None = None
    if time_col is not None:
        j = _find_column(tab, time_col)
        if j is None:
            problems.append(Diagnostic(
                f"{tab.prefix()}time column {time_col!r} not found; the file's columns are: {tab.listing()}",
                tab.span(None, None), hint="name the time column with --time-col (or time_col=)"))
            return None, None, None
    else:
        lowered = [c.strip().lower() for c in tab.columns]
        for cand in TIME_NAMES:
            for jj, c in enumerate(lowered):
                if jj not in used and c == cand:
                    j = jj
                    break
            if j is not None:
                break
        if j is None:  # a time column with a unit suffix: t_h, time_min, time [h]
            for jj, c in enumerate(lowered):
                if (jj not in used and _suffix_unit(c) is not None
                        and re.split(r"[\s_\-\[(]", c)[0] in ("t", "time", "elapsed")):
                    j = jj
                    break
        if j is None:  # a time-stamp column of any name (pandas writes its index unnamed)
            for jj in range(len(tab.columns)):
                if jj not in used and _as_timestamps(tab.cells[jj], tab.plain(jj)) is not None:
                    j = jj
                    break
        if j is None:
            if dt is not None:
                notes.append(f"no time column: rows taken as equally spaced by dt = {dt:g} s")
                return np.arange(n, dtype=np.float64) * dt, None, None
            problems.append(Diagnostic(
                f"{tab.prefix()}no time column found (looked for {', '.join(TIME_NAMES)}); "
                f"the file's columns are: {tab.listing()}",
                tab.span(None, None), hint="name it with --time-col NAME, or give --dt S for equally spaced rows"))
            return None, None, None

    vals = tab.cells[j]
    stamps = _as_timestamps(vals, tab.plain(j))
    start = None
    if stamps is not None:
        sec, ok = stamps
        if not ok.all():
            bad = np.flatnonzero(~ok)
            for row in bad[:MAX_REPORTED]:
                problems.append(Diagnostic(
                    f"{tab.prefix()}cannot read time stamp {str(vals[row])!r} in time column {tab.shown(j)!r} "
                    f"at {tab.where(int(row))}", tab.span(int(row), j),
                    hint="time stamps are ISO 8601 (2021-11-22 09:15:00, optionally with +01:00)"))
            return None, j, None
        start = str(vals[0])
        t = sec - sec[0]
        if time_unit is not None:
            notes.append(f"time_unit={time_unit!r} ignored: column {tab.shown(j)!r} holds time stamps")
    else:
        raw = _numeric(tab, j, problems, "time")
        if not np.isfinite(raw).all():
            rows = np.flatnonzero(~np.isfinite(raw))
            if not problems:
                problems.append(Diagnostic(
                    f"{tab.prefix()}time column {tab.shown(j)!r} has no (finite) value on {_row_list(tab, rows)}",
                    tab.span(int(rows[0]), j), hint="every row needs a time"))
            return None, j, None
        if time_unit is not None:
            if time_unit not in _TIME_UNITS:
                raise DataError(Diagnostic(f"unknown time unit {time_unit!r}",
                                           hint="use one of s, ms, min, h, d"))
            factor = _TIME_UNITS[time_unit]
        else:
            factor = _suffix_unit(tab.columns[j]) or 1.0
            inferred = _unit_from_companion(tab, j, raw, used)
            if inferred is not None and _suffix_unit(tab.columns[j]) is None and inferred[0] != 1.0:
                factor = inferred[0]
                notes.append(f"time column {tab.shown(j)!r} read in {inferred[1]}: its values match the time stamps "
                             f"in column {tab.shown(inferred[2])!r} (pass time_unit= / --time-unit to override)")
        t = (raw - raw[0]) * factor
    return t, j, start


def _unit_from_companion(tab: _Table, j: int, raw: np.ndarray, used: set[int]):
    """If another column holds time stamps, find the unit (s, min, h, d) of numeric time ``raw`` that
    matches them; → (factor, unit name, companion column) or None."""
    if len(raw) < 2 or raw[-1] == raw[0]:
        return None
    for jj in range(len(tab.columns)):
        if jj == j or jj in used:
            continue
        stamps = _as_timestamps(tab.cells[jj], tab.plain(jj))
        if stamps is None or not stamps[1].all():
            continue
        span_s = stamps[0][-1] - stamps[0][0]
        span_raw = raw[-1] - raw[0]
        for unit, factor in (("seconds", 1.0), ("minutes", 60.0), ("hours", 3600.0), ("days", 86400.0)):
            if abs(span_raw * factor - span_s) <= 1e-3 * abs(span_s) + 1.0:
                return factor, unit, jj
    return None


def _nice_step(dt: float) -> float:
    return float(f"{dt:.3g}")


def _interp_linear(t_src: np.ndarray, y: np.ndarray, t_new: np.ndarray) -> np.ndarray:
    """Linear interpolation of y (n,) at t_new; NaN if either neighbour is NaN (exact hits use one)."""
    i = np.clip(np.searchsorted(t_src, t_new, side="right") - 1, 0, len(t_src) - 1)
    i1 = np.minimum(i + 1, len(t_src) - 1)
    span = t_src[i1] - t_src[i]
    w = np.where(span > 0, (t_new - t_src[i]) / np.where(span > 0, span, 1.0), 0.0)
    w = np.clip(w, 0.0, 1.0)
    y0, y1 = y[i], y[i1]
    out = np.where(w == 0.0, y0, np.where(w == 1.0, y1, (1.0 - w) * y0 + w * y1))
    return out


def _interval_mean_zoh(t_src: np.ndarray, u: np.ndarray, t_new: np.ndarray, dt: float) -> np.ndarray:
    """Mean over [t, t + dt) of the zero-order-held signal u(τ) = u_i for τ ∈ [t_i, t_{i+1})
    (the last value held beyond the end)."""
    cum = np.concatenate([[0.0], np.cumsum(u[:-1] * np.diff(t_src))])

    def integral(x):
        i = np.clip(np.searchsorted(t_src, x, side="right") - 1, 0, len(t_src) - 1)
        return cum[i] + u[i] * (x - t_src[i])

    return (integral(t_new + dt) - integral(t_new)) / dt


def _show_time(tab: _Table, j: int | None, row: int) -> str:
    if j is None:
        return f"row {row}"
    return repr(str(tab.cells[j][row]))
