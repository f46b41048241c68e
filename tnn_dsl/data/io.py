"""Measured data for a network: CSV / Parquet files → :class:`Experiment` (SI, kelvin, uniform step).

One experiment per file. The columns to read come from the IR: every ``Input.column`` and every
``Sensor.column``. The file's temperature unit is ``Network.temperature_unit``: temperature inputs and
all sensors are converted to kelvin; other inputs are scaled to SI by their declared unit (``[%]`` ×0.01,
``[kW]`` ×1000 ...).

Time
    The time column is ``time_col`` if given, else the first of ``t``, ``time``, ``time_s``, ``timestamp``,
    ``datetime``, ``date``, ... (case-insensitive), else an unnamed first column holding timestamps.
    Numbers are seconds unless the column name carries a unit suffix (``time_h``, ``t_min``, ``time [h]``)
    or ``time_unit`` says otherwise. A numeric time column that runs alongside a timestamp column in the
    same file (the Bacher–Madsen file's ``t`` next to ``TimeDate``) has its unit inferred from the
    timestamps, with a note. ISO timestamps are parsed (time zones respected). ``Experiment.t`` starts at 0.

Sampling
    The model step is ``dt`` if given, else the file's step (for irregular files the median step, rounded
    to 3 significant digits). If
    the file is sampled on that grid (to 1e-6 relative) its rows are used as they are. Otherwise the file is
    resampled to ``t_k = k·dt``: sensors and temperature inputs linearly, other inputs as the mean over
    ``[t_k, t_k + dt)`` of the zero-order-held signal (which is what the model's zero-order hold sees).
    ``Experiment.notes`` says so.

Missing values
    A NaN in a sensor column is kept (the trainer masks it). A NaN in an input column is a
    :class:`DataError` naming the rows.

Every problem is a :class:`DataError` whose diagnostics point at ``file:line:col`` (line = the CSV line,
the header is line 1); Parquet files have no lines, so their messages name the row instead.
"""

from __future__ import annotations

import csv
import difflib
import io
import math
import os
import re
from dataclasses import dataclass, replace
from typing import Iterable, Sequence

import numpy as np

from ..core import DataError, Diagnostic, atomic_path
from ..ir import Network, Span

__all__ = ["Experiment", "read_data", "split_by_time", "write_csv", "to_kelvin", "from_kelvin", "unit_factor"]

TIME_NAMES = ("t", "time", "time_s", "timestamp", "datetime", "date_time", "timedate", "date")
"""Time-column names tried in this order (case-insensitive) when ``time_col`` is not given."""

MISSING = frozenset({"", "nan", "na", "n/a", "null", "none", "-", "#n/a"})
"""Cell texts read as a missing value (case-insensitive)."""

_TIME_UNITS = {
    "s": 1.0, "sec": 1.0, "secs": 1.0, "second": 1.0, "seconds": 1.0,
    "ms": 1e-3,
    "min": 60.0, "mins": 60.0, "minute": 60.0, "minutes": 60.0,
    "h": 3600.0, "hr": 3600.0, "hrs": 3600.0, "hour": 3600.0, "hours": 3600.0,
    "d": 86400.0, "day": 86400.0, "days": 86400.0,
}

MAX_REPORTED = 5
"""At most this many diagnostics of one kind per column."""


# ---------------------------------------------------------------------------------------------
# The result
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Experiment:
    """One measured run, on a uniform grid, in SI.

    Attributes
    ----------
    name : str
        The file's stem (``"train"`` for ``data/train.csv``); split parts get ``[:70%]`` / ``[70%:]``.
    path : str
        The file read.
    t : ndarray (N,)
        Time in s; ``t[k] = t[0] + k·dt``; ``t[0] = 0`` for a whole file.
    dt : float
        The step, s.
    inputs : ndarray (N, n_inputs)
        In ``Network.inputs`` order, SI (temperature inputs in K). Zero-order hold over ``[t_k, t_k + dt)``.
    outputs : ndarray (N, n_outputs)
        In ``Network.sensors`` order, K; NaN where not measured.
    input_names, output_names : tuple[str, ...]
        Input and sensor names (not column names).
    notes : tuple[str, ...]
        What was done to the data on the way in (resampling, inferred units, missing sensor columns).
    input_columns, output_columns : tuple[str | None, ...]
        The file's column for each input / sensor (``None`` for a sensor column the file lacks).
    time_column : str | None
        The time column used (``None`` when the rows were taken as equally spaced by ``dt``).
    start : str | None
        The first time stamp as written in the file (ISO), or ``None`` for a numeric time column.
    """

    name: str
    path: str
    t: np.ndarray
    dt: float
    inputs: np.ndarray
    outputs: np.ndarray
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    notes: tuple[str, ...] = ()
    input_columns: tuple[str | None, ...] = ()
    output_columns: tuple[str | None, ...] = ()
    time_column: str | None = None
    start: str | None = None

    @property
    def n_steps(self) -> int:
        """N, the number of samples."""
        return int(self.t.shape[0])

    @property
    def duration(self) -> float:
        """``t[-1] − t[0]``, s."""
        return float(self.t[-1] - self.t[0]) if self.n_steps else 0.0

    def __repr__(self) -> str:  # arrays are long; say what matters
        return (
            f"Experiment({self.name!r}, N={self.n_steps}, dt={self.dt:g} s, inputs={list(self.input_names)}, "
            f"outputs={list(self.output_names)}, notes={len(self.notes)})"
        )


# ---------------------------------------------------------------------------------------------
# Units
# ---------------------------------------------------------------------------------------------


def to_kelvin(x, unit: str):
    """Temperatures (any array shape) from ``unit`` (``degC``, ``K``, ``degF``) to kelvin."""
    if unit == "degC":
        return x + 273.15
    if unit == "K":
        return x + 0.0
    if unit == "degF":
        return (x - 32.0) * (5.0 / 9.0) + 273.15
    raise ValueError(f"unknown temperature unit {unit!r}")


def from_kelvin(x, unit: str):
    """Temperatures (any array shape) from kelvin to ``unit`` (``degC``, ``K``, ``degF``)."""
    if unit == "degC":
        return x - 273.15
    if unit == "K":
        return x + 0.0
    if unit == "degF":
        return (x - 273.15) * (9.0 / 5.0) + 32.0
    raise ValueError(f"unknown temperature unit {unit!r}")


def unit_factor(unit: str | None) -> float:
    """The factor that takes a value in ``unit`` to SI (``"%"`` → 0.01, ``"kW"`` → 1000, ``None`` → 1).
    Raises ``ValueError`` for a unit that is not known (or is an absolute temperature scale)."""
    scale, offset = unit_scale_offset(unit)
    if offset != 0.0:
        raise ValueError(f"the unit {unit!r} is an absolute temperature; declare the input `: temperature`")
    return scale


def unit_scale_offset(unit: str | None) -> tuple[float, float]:
    """(scale, offset) with SI = scale·x + offset, from ``tnn_dsl.lang.units`` (pint underneath)."""
    if unit is None or unit.strip().strip("[]").strip() in ("", "1", "-"):
        return 1.0, 0.0
    from ..lang import UnitError, unit_scale

    try:
        return unit_scale(unit)
    except UnitError as err:
        raise ValueError(err.message) from None


# ---------------------------------------------------------------------------------------------
# Reading a file into a table of text/number columns with line numbers
# ---------------------------------------------------------------------------------------------


@dataclass
class _Table:
    path: str
    columns: list[str]  # as in the file (an empty header name is "")
    cells: dict[int, np.ndarray]  # column index -> values (object array of str for CSV; any for Parquet)
    lines: np.ndarray | None  # (n_rows,) CSV line of each row, None for Parquet
    raw: list[str] | None  # the file's lines (CSV only)
    sep: str = ","
    header_line: str = ""
    header_at: int = 1  # the CSV line of the header

    @property
    def n_rows(self) -> int:
        return 0 if not self.cells else len(next(iter(self.cells.values())))

    def shown(self, j: int) -> str:
        return self.columns[j] if self.columns[j] else f"(unnamed column {j + 1})"

    def listing(self) -> str:
        return ", ".join(repr(c) if c else f"(unnamed column {j + 1})" for j, c in enumerate(self.columns))

    # positions -----------------------------------------------------------------------------

    def span(self, row: int | None, j: int | None) -> Span | None:
        """Span of cell (row, column j); ``row=None`` is the header; ``j=None`` the whole line."""
        if self.lines is None:
            return None
        line = self.header_at if row is None else int(self.lines[row])
        text = self.raw[line - 1] if self.raw is not None and 1 <= line <= len(self.raw) else ""
        if j is None:
            return Span(file=self.path, line=line, col=1, end_line=line, end_col=max(2, len(text) + 1))
        start, end = _field_bounds(text, self.sep, j)
        return Span(file=self.path, line=line, col=start + 1, end_line=line, end_col=max(end + 1, start + 2))

    def where(self, row: int | None) -> str:
        """``line 12`` for CSV, ``row 11`` for Parquet (used inside messages)."""
        if row is None:
            return "the header"
        if self.lines is None:
            return f"row {row + 1}"
        return f"line {int(self.lines[row])}"

    def prefix(self) -> str:
        """For Parquet (no spans) the message itself names the file."""
        return f"{self.path}: " if self.lines is None else ""


def _field_bounds(line: str, sep: str, j: int) -> tuple[int, int]:
    """0-based [start, end) character range of field ``j`` of a CSV line (quote-aware)."""
    k, start, quoted = 0, 0, False
    for i, ch in enumerate(line):
        if ch == '"':
            quoted = not quoted
        elif ch == sep and not quoted:
            if k == j:
                return start, i
            k += 1
            start = i + 1
    if k == j:
        return start, len(line)
    return len(line), len(line)


def _detect_sep(header: str) -> str:
    counts = {s: 0 for s in (",", ";", "\t")}
    quoted = False
    for ch in header:
        if ch == '"':
            quoted = not quoted
        elif not quoted and ch in counts:
            counts[ch] += 1
    best = max(counts, key=lambda s: counts[s])
    return best if counts[best] > 0 else ","


def _read_csv(path: str) -> _Table:
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as err:
        raise DataError(Diagnostic(f"cannot read data file {path!r}: {err.strerror or err}",
                                   hint="check the path; data files are CSV or Parquet")) from None
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = data.decode("latin-1")
    if "\x00" in text[:4096]:
        raise DataError(Diagnostic(f"{path}: not a text file (binary content); expected CSV or Parquet",
                                   hint="Parquet files must end in .parquet or .pq"))
    raw = text.splitlines()
    first = next((i for i, ln in enumerate(raw) if ln.strip()), None)
    if first is None:
        raise DataError(Diagnostic("the data file is empty", Span(file=path, line=1, col=1, end_line=1, end_col=2),
                                   hint="a data file needs a header line and at least two rows"))
    header_line = raw[first]
    sep = _detect_sep(header_line)
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=sep)
    header: list[str] | None = None
    rows: list[list[str]] = []
    lines: list[int] = []
    problems: list[Diagnostic] = []
    prev_line = 0
    for rec in reader:
        line = prev_line + 1  # first line of this record
        prev_line = reader.line_num
        if not rec or all(not c.strip() for c in rec):
            continue  # blank line
        if header is None:
            header = [c.strip() for c in rec]
            header_at = line
            continue
        if len(rec) != len(header):
            if len(problems) < MAX_REPORTED:
                sp_text = raw[line - 1] if line <= len(raw) else ""
                problems.append(Diagnostic(
                    f"expected {len(header)} fields (as in the header), found {len(rec)}",
                    Span(file=path, line=line, col=1, end_line=line, end_col=max(2, len(sp_text) + 1)),
                    hint=f"the separator is {sep!r}; a stray separator or a missing field shifts the columns",
                ))
            continue
        rows.append(rec)
        lines.append(line)
    if problems:
        raise DataError(problems)
    if header is None:  # only separators and blanks
        raise DataError(Diagnostic("the data file has no header line (only blank fields)",
                                   Span(file=path, line=1, col=1, end_line=1, end_col=2),
                                   hint="a data file needs a header line naming its columns and at least two rows"))
    cells = {j: np.array([r[j].strip() for r in rows], dtype=object) for j in range(len(header))}
    if not rows:
        cells = {j: np.array([], dtype=object) for j in range(len(header))}
    return _Table(path=path, columns=header, cells=cells, lines=np.array(lines, dtype=np.int64), raw=raw, sep=sep,
                  header_line=header_line, header_at=header_at)


def _read_parquet(path: str) -> _Table:
    try:
        import pandas as pd

        df = pd.read_parquet(path)
    except ImportError as err:
        raise DataError(Diagnostic(f"cannot read Parquet file {path!r}: {err}",
                                   hint="install pyarrow (`pip install tnn_dsl[parquet]`) or convert to CSV")) from None
    except Exception as err:  # noqa: BLE001 - any reader failure is a bad file
        raise DataError(Diagnostic(f"cannot read Parquet file {path!r}: {type(err).__name__}: {err}",
                                   hint="is it a Parquet file? CSV files must not end in .parquet")) from None
    if df.index.name is not None or not isinstance(df.index, pd.RangeIndex):
        df = df.reset_index()
    cols = [str(c) if c is not None else "" for c in df.columns]
    cells = {j: df.iloc[:, j].to_numpy() for j in range(len(cols))}
    return _Table(path=path, columns=cols, cells=cells, lines=None, raw=None)


def read_table(path: str) -> _Table:
    path = os.fspath(path)
    if not os.path.exists(path):
        raise DataError(Diagnostic(f"data file {path!r} not found", hint="check the path"))
    if os.path.isdir(path):
        raise DataError(Diagnostic(f"{path!r} is a directory, not a data file", hint="give CSV or Parquet files"))
    if path.lower().endswith((".parquet", ".pq")):
        return _read_parquet(path)
    return _read_csv(path)


# ---------------------------------------------------------------------------------------------
# Columns → numbers
# ---------------------------------------------------------------------------------------------


def _numeric(tab: _Table, j: int, problems: list[Diagnostic], what: str) -> np.ndarray:
    """Column j as float64 with NaN for missing cells; text cells become diagnostics."""
    vals = tab.cells[j]
    if vals.dtype.kind in "fiub":
        return vals.astype(np.float64)
    if vals.dtype.kind == "M":
        problems.append(Diagnostic(f"{tab.prefix()}column {tab.shown(j)!r} ({what}) holds time stamps, not numbers",
                                   tab.span(None, j), hint="map the column to a number series"))
        return np.full(len(vals), np.nan)
    import pandas as pd

    text = np.array(["" if v is None else str(v) for v in vals], dtype=object)
    out = np.array(pd.to_numeric(pd.Series(text), errors="coerce"), dtype=np.float64)
    bad = np.isnan(out)
    if bad.any():
        lowered = np.array([s.strip().lower() for s in text[bad]], dtype=object)
        missing = np.isin(lowered, list(MISSING))
        idx = np.flatnonzero(bad)[~missing]
        if idx.size and tab.sep == ";":  # decimal comma (European CSV)
            fixed = pd.to_numeric(pd.Series([text[i].replace(",", ".", 1) if text[i].count(",") == 1 else text[i]
                                             for i in idx]), errors="coerce").to_numpy(dtype=np.float64)
            ok = ~np.isnan(fixed)
            out[idx[ok]] = fixed[ok]
            idx = idx[~ok]
        if idx.size:
            for n, row in enumerate(idx[:MAX_REPORTED]):
                more = f" ({idx.size} such rows in this column)" if n == 0 and idx.size > 1 else ""
                problems.append(Diagnostic(
                    f"{tab.prefix()}text {text[row]!r} in numeric column {tab.shown(j)!r} ({what}) at "
                    f"{tab.where(row)}{more}",
                    tab.span(int(row), j),
                    hint="numbers use '.' as decimal point; leave a cell empty (or NaN) for a missing sensor value",
                ))
    return out


def _row_list(tab: _Table, rows: np.ndarray, limit: int = 8) -> str:
    rows = np.asarray(rows)
    if tab.lines is not None:
        nums = [int(tab.lines[r]) for r in rows]
        word = "lines"
    else:
        nums = [int(r) + 1 for r in rows]
        word = "rows"
    # compress consecutive runs: 12-15, 40
    parts: list[str] = []
    i = 0
    while i < len(nums) and len(parts) < limit:
        j = i
        while j + 1 < len(nums) and nums[j + 1] == nums[j] + 1:
            j += 1
        parts.append(str(nums[i]) if i == j else f"{nums[i]}-{nums[j]}")
        i = j + 1
    tail = f", ... ({len(nums)} in all)" if i < len(nums) else ""
    return f"{word} {', '.join(parts)}{tail}"


def _find_column(tab: _Table, name: str) -> int | None:
    for j, c in enumerate(tab.columns):
        if c == name:
            return j
    for j, c in enumerate(tab.columns):  # forgiving: case and surrounding spaces
        if c.strip().lower() == name.strip().lower():
            return j
    return None


def _missing_column(tab: _Table, column: str, who: str, decl: Span | None) -> Diagnostic:
    close = difflib.get_close_matches(column, [c for c in tab.columns if c], n=1, cutoff=0.6)
    hint = f"did you mean {close[0]!r}? " if close else ""
    hint += f"set `column \"...\"` on the {who.split()[0]} in the network, or rename the column in the file"
    related = (("declared here", decl),) if decl is not None else ()
    return Diagnostic(
        f"{tab.prefix()}column {column!r} ({who}) not found; the file's columns are: {tab.listing()}",
        tab.span(None, None), hint=hint, related=related,
    )


# ---------------------------------------------------------------------------------------------
# Time
# ---------------------------------------------------------------------------------------------


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


def _as_timestamps(vals: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(seconds since epoch as float64 with NaN for unparsable, ok mask) or None if it is not a time-stamp
    column (fewer than half the cells parse)."""
    import pandas as pd

    if vals.dtype.kind == "M":
        s = pd.Series(vals)
        if getattr(s.dt, "tz", None) is not None:
            s = s.dt.tz_convert("UTC").dt.tz_localize(None)
        ns = s.to_numpy(dtype="datetime64[ns]").astype(np.int64).astype(np.float64)
        ok = ~pd.isna(s).to_numpy()
        return np.where(ok, ns / 1e9, np.nan), ok
    if vals.dtype.kind in "fiub" or len(vals) == 0:
        return None
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
                if jj not in used and _suffix_unit(c) is not None and re.split(r"[\s_\-\[(]", c)[0] in ("t", "time", "elapsed"):
                    j = jj
                    break
        if j is None:  # a time-stamp column of any name (pandas writes its index unnamed)
            for jj in range(len(tab.columns)):
                if jj not in used and _as_timestamps(tab.cells[jj]) is not None:
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
    stamps = _as_timestamps(vals)
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
        stamps = _as_timestamps(tab.cells[jj])
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


# ---------------------------------------------------------------------------------------------
# Resampling
# ---------------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------------
# read_data
# ---------------------------------------------------------------------------------------------


def read_data(
    net: Network,
    paths: str | os.PathLike | Sequence[str | os.PathLike],
    time_col: str | None = None,
    dt: float | None = None,
    *,
    time_unit: str | None = None,
    require_outputs: bool = True,
) -> list[Experiment]:
    """Read data files for ``net``: one :class:`Experiment` per file.

    Parameters
    ----------
    net : Network
        Says which columns to read (``Input.column``, ``Sensor.column``) and the temperature unit.
    paths : path or list of paths
        CSV (``,``, ``;`` or tab separated, detected) or Parquet (``.parquet``/``.pq``).
    time_col : str, optional
        The time column; default: detected (see the module docstring).
    dt : float, optional
        The model step in s; default: the file's median step. Files not on that grid are resampled.
    time_unit : {"s", "ms", "min", "h", "d"}, optional
        Unit of a numeric time column (the Bacher–Madsen file's ``t`` is in hours); default: from the
        column name's suffix, else seconds.
    require_outputs : bool
        If false, a missing sensor column gives an all-NaN output and a note instead of an error
        (``tnnc simulate`` needs only the inputs).

    Raises
    ------
    DataError
        With one diagnostic per problem found (``file:line:col``), all files checked before raising.
    """
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    paths = [os.fspath(p) for p in paths]
    if not paths:
        raise DataError(Diagnostic("no data files given", hint="pass at least one CSV or Parquet file"))
    if dt is not None and not (math.isfinite(dt) and dt > 0):
        raise DataError(Diagnostic(f"the step dt must be a positive number of seconds, got {dt!r}"))
    experiments: list[Experiment] = []
    problems: list[Diagnostic] = []
    for p in paths:
        try:
            experiments.append(_read_one(net, p, time_col, dt, time_unit, require_outputs))
        except DataError as err:
            problems.extend(err.diagnostics)
    if problems:
        raise DataError(problems)
    return experiments


def _read_one(net: Network, path: str, time_col, dt, time_unit, require_outputs) -> Experiment:
    tab = read_table(path)
    notes: list[str] = []
    problems: list[Diagnostic] = []
    n = tab.n_rows
    if n == 0:
        raise DataError(Diagnostic(f"{tab.prefix()}the data file has a header but no data rows",
                                   tab.span(None, None), hint="a data file needs at least two rows"))
    if n == 1:
        raise DataError(Diagnostic(f"{tab.prefix()}the data file has only one data row; at least two are needed",
                                   tab.span(0, None), hint="a simulation needs a time step: give two or more rows"))
    tunit = net.temperature_unit

    # columns of inputs and sensors
    in_cols: list[int | None] = []
    for inp in net.inputs:
        j = _find_column(tab, inp.column)
        if j is None:
            problems.append(_missing_column(tab, inp.column, f"input {inp.name}", inp.span))
        in_cols.append(j)
    out_cols: list[int | None] = []
    for s in net.sensors:
        j = _find_column(tab, s.column)
        if j is None:
            if require_outputs:
                problems.append(_missing_column(tab, s.column, f"sensor {s.name}", s.span))
            else:
                notes.append(f"sensor {s.name}: column {s.column!r} not in the file (no measurement)")
        out_cols.append(j)
    used = {j for j in in_cols + out_cols if j is not None}
    if problems:
        raise DataError(problems)

    t, tj, start = _time(tab, time_col, time_unit, dt, used, problems, notes)
    if tj is not None and tj in used:
        who = [f"input {i.name}" for i, j in zip(net.inputs, in_cols) if j == tj]
        who += [f"sensor {s.name}" for s, j in zip(net.sensors, out_cols) if j == tj]
        problems.append(Diagnostic(f"{tab.prefix()}column {tab.shown(tj)!r} is both the time and {', '.join(who)}",
                                   tab.span(None, tj), hint="name another time column with --time-col"))

    # values
    U = np.empty((n, len(net.inputs)))
    for k, (inp, j) in enumerate(zip(net.inputs, in_cols)):
        col = _numeric(tab, j, problems, f"input {inp.name}")
        if inp.is_temperature:
            col = to_kelvin(col, tunit)
        else:
            try:
                scale, offset = unit_scale_offset(inp.unit)
                col = col * scale + offset
            except ValueError as err:
                problems.append(Diagnostic(str(err), inp.span, hint="use a unit pint knows (%, W, kW, A, W/m^2 ...)"))
        U[:, k] = col
    Y = np.full((n, len(net.sensors)), np.nan)
    for k, (s, j) in enumerate(zip(net.sensors, out_cols)):
        if j is not None:
            Y[:, k] = to_kelvin(_numeric(tab, j, problems, f"sensor {s.name}"), tunit)
    if problems:
        raise DataError(problems)

    # NaN / infinite inputs: an error naming the rows
    for k, (inp, j) in enumerate(zip(net.inputs, in_cols)):
        bad = np.flatnonzero(~np.isfinite(U[:, k]))
        if bad.size:
            problems.append(Diagnostic(
                f"{tab.prefix()}input {inp.name} (column {tab.shown(j)!r}) has no value (empty, NaN or infinite) on "
                f"{_row_list(tab, bad)}",
                tab.span(int(bad[0]), j),
                hint="inputs must be known at every step: fill or drop those rows (sensor columns may have gaps)"))
    for k, (s, j) in enumerate(zip(net.sensors, out_cols)):
        bad = np.flatnonzero(np.isinf(Y[:, k]))
        if bad.size:
            problems.append(Diagnostic(
                f"{tab.prefix()}sensor {s.name} (column {tab.shown(j)!r}) is infinite on {_row_list(tab, bad)}",
                tab.span(int(bad[0]), j), hint="leave the cell empty for a missing value"))
    if t is not None:
        d = np.diff(t)
        back = np.flatnonzero(d < 0)
        dup = np.flatnonzero(d == 0)
        for r in back[:MAX_REPORTED]:
            problems.append(Diagnostic(
                f"{tab.prefix()}time goes backwards at {tab.where(int(r + 1))}: "
                f"{_show_time(tab, tj, r + 1)} after {_show_time(tab, tj, r)}",
                tab.span(int(r + 1), tj), hint="sort the rows by time, or split the file into separate runs"))
        for r in dup[:MAX_REPORTED]:
            problems.append(Diagnostic(
                f"{tab.prefix()}duplicate time {_show_time(tab, tj, r + 1)} at {tab.where(int(r + 1))} "
                f"(also at {tab.where(int(r))})",
                tab.span(int(r + 1), tj), hint="remove the repeated rows (or average them)"))
        if not np.all(np.isfinite(t)):
            problems.append(Diagnostic(f"{tab.prefix()}the time column has non-finite values", tab.span(None, tj)))
    if problems:
        raise DataError(problems)
    assert t is not None

    # the grid
    steps = np.diff(t)
    file_dt = float(np.median(steps))
    mean_step = float(t[-1] - t[0]) / (n - 1)
    if dt is not None:
        step = float(dt)
    elif np.all(np.abs(steps - mean_step) <= 1e-6 * mean_step):
        step = float(f"{mean_step:.9g}")  # a regular file: its own step (float noise removed)
    else:
        step = _nice_step(file_dt)  # an irregular one: its median step, rounded
    grid_n = int(math.floor(t[-1] / step * (1 + 1e-9) + 1e-9)) + 1
    on_grid = abs(t[-1] - (n - 1) * step) <= 1e-6 * step * max(n, 1) and \
        bool(np.all(np.abs(steps - step) <= 1e-6 * step))
    if on_grid:
        tt = np.arange(n, dtype=np.float64) * step
        Ug, Yg = U, Y
    else:
        if grid_n < 2:
            raise DataError(Diagnostic(
                f"{tab.prefix()}the file spans {t[-1]:g} s, less than one step of {step:g} s",
                tab.span(None, tj), hint="use a smaller --dt"))
        tt = np.arange(grid_n, dtype=np.float64) * step
        Ug = np.empty((grid_n, U.shape[1]))
        for k, inp in enumerate(net.inputs):
            if inp.is_temperature:
                Ug[:, k] = _interp_linear(t, U[:, k], tt)
            else:
                Ug[:, k] = _interval_mean_zoh(t, U[:, k], tt, step)
        Yg = np.empty((grid_n, Y.shape[1]))
        for k in range(Y.shape[1]):
            Yg[:, k] = _interp_linear(t, Y[:, k], tt)
        irregular = float(np.max(np.abs(steps - file_dt))) > 1e-6 * file_dt
        why = (f"irregular sampling (steps {steps.min():g} to {steps.max():g} s)" if irregular
               else f"the file's step {file_dt:g} s differs from dt")
        gap = float(steps.max())
        notes.append(
            f"resampled {n} rows to {grid_n} steps of {step:g} s because of {why}: sensors and temperature inputs "
            f"linearly, other inputs as the interval mean of their zero-order hold"
            + (f"; largest gap {gap:g} s ({gap / step:.0f} steps) interpolated" if gap > 10 * step else ""))

    name = os.path.splitext(os.path.basename(path))[0]
    return Experiment(
        name=name, path=path, t=tt, dt=step, inputs=np.ascontiguousarray(Ug, dtype=np.float64),
        outputs=np.ascontiguousarray(Yg, dtype=np.float64),
        input_names=tuple(net.input_names), output_names=tuple(s.name for s in net.sensors),
        notes=tuple(notes),
        input_columns=tuple(tab.columns[j] if j is not None else None for j in in_cols),
        output_columns=tuple(tab.columns[j] if j is not None else None for j in out_cols),
        time_column=tab.columns[tj] if tj is not None else None, start=start,
    )


def _show_time(tab: _Table, j: int | None, row: int) -> str:
    if j is None:
        return f"row {row}"
    return repr(str(tab.cells[j][row]))


# ---------------------------------------------------------------------------------------------
# Splitting and writing
# ---------------------------------------------------------------------------------------------



def as_experiments(net: Network, data) -> list[Experiment]:
    """Paths (one or many) and/or :class:`Experiment` objects → a list of ``Experiment`` for ``net``
    (paths are read with :func:`read_data`; ``None`` gives ``[]``). The one place the trainer, the
    sensitivity pass and saved models turn "data" arguments into experiments."""
    if data is None:
        return []
    if isinstance(data, (str, os.PathLike)) or hasattr(data, "inputs"):
        data = [data]
    exps, paths = [], []
    for d in data:
        if hasattr(d, "inputs") and hasattr(d, "outputs"):
            exps.append(d)
        else:
            paths.append(os.fspath(d))
    if paths:
        exps.extend(read_data(net, paths))
    return exps

def split_by_time(exp: Experiment, fraction: float) -> tuple[Experiment, Experiment]:
    """Split ``exp`` at ``fraction`` of its samples: (first part, rest). The parts keep their times
    (the second starts at ``t[k]``, not 0) and are named ``<name>[:70%]`` and ``<name>[70%:]``."""
    if not (0.0 < fraction < 1.0):
        raise ValueError(f"fraction must be in (0, 1), got {fraction!r}")
    k = int(round(exp.n_steps * fraction))
    if k < 2 or exp.n_steps - k < 2:
        raise DataError(Diagnostic(
            f"cannot split {exp.name!r} ({exp.n_steps} samples) at {fraction:.0%}: each part needs two samples"))
    pct = f"{fraction * 100:g}%"
    note = f"split at t = {exp.t[k]:g} s ({pct} of {exp.n_steps} samples)"
    a = replace(exp, name=f"{exp.name}[:{pct}]", t=exp.t[:k].copy(), inputs=exp.inputs[:k].copy(),
                outputs=exp.outputs[:k].copy(), notes=exp.notes + (note,))
    b = replace(exp, name=f"{exp.name}[{pct}:]", t=exp.t[k:].copy(), inputs=exp.inputs[k:].copy(),
                outputs=exp.outputs[k:].copy(), notes=exp.notes + (note,))
    return a, b


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
