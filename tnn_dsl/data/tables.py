"""Reading a CSV or Parquet file into a table of text and number columns with line numbers (for messages that
point at the row), and turning columns into numbers."""

from __future__ import annotations

import csv
import difflib
import io
import os
from dataclasses import dataclass, field

import numpy as np

from ..core import DataError, Diagnostic
from ..ir import Span

__all__ = ["read_table", "MISSING"]

MISSING = frozenset({"", "nan", "na", "n/a", "null", "none", "-", "#n/a"})
_PLAIN_CHARS = frozenset("0123456789.eE+- \t")


def _plain_numbers(text: np.ndarray) -> np.ndarray | None:
    """Text cells ``text`` (object array of str) that are all plain decimal numbers or blank, as float64 (NaN where
    blank); None when any cell is something else (a missing-value marker, a word, a decimal comma, ``inf``): pandas'
    parser then decides, with its diagnostics. Reading a clean numeric CSV thus never imports pandas (60–90 MB
    resident for the rest of the process, issue 18). Within these characters Python's ``float`` and
    ``pandas.to_numeric`` accept the same strings and round them the same (correctly)."""
    chars = set("".join(text))
    if not chars <= _PLAIN_CHARS:
        return None
    cells = [c.strip() for c in text] if chars & {" ", "\t"} else text
    nan = float("nan")
    try:  # Python's float per cell: twice as fast as numpy's conversion of the text array (2026-11-29)
        return np.fromiter((float(c) if c else nan for c in cells), dtype=np.float64, count=len(cells))
    except ValueError:  # "1e", "+-", "1.2.3": pandas' parser reports them
        return None
"""Cell texts read as a missing value (case-insensitive)."""


MAX_REPORTED = 5
"""At most this many diagnostics of one kind per column."""


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
    _plain: dict[int, np.ndarray | None] = field(default_factory=dict, repr=False)

    @property
    def n_rows(self) -> int:
        return 0 if not self.cells else len(next(iter(self.cells.values())))

    def texts(self, j: int) -> np.ndarray:
        """Column ``j``'s cells as text (object array of str; ``""`` for None). A CSV column is that already."""
        if self.lines is not None:
            return self.cells[j]
        return np.array(["" if v is None else str(v) for v in self.cells[j]], dtype=object)

    def plain(self, j: int) -> np.ndarray | None:
        """Column ``j`` of text cells read as plain decimal numbers (:func:`_plain_numbers`: float64, NaN where
        blank), or None when a cell is something else or the column holds no text (numbers or time stamps from
        Parquet, or no rows). Read once per column: the search for a time column, the time column and the inputs'
        and sensors' values look at the same columns (three reads of each before, 2026-11-29)."""
        if j not in self._plain:
            vals = self.cells[j]
            self._plain[j] = (None if vals.dtype.kind in "fiubM" or len(vals) == 0
                              else _plain_numbers(self.texts(j)))
        return self._plain[j]

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
        if not rec or not "".join(rec).strip():
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
    if any(ch.isspace() for ch in set("".join(map("".join, rows)))):  # cells to strip (what str.strip strips)
        cells = {j: np.array([r[j].strip() for r in rows], dtype=object) for j in range(len(header))}
    else:  # machine-written files: nothing to strip, the columns are the rows transposed
        cells = {j: np.array(col, dtype=object) for j, col in enumerate(zip(*rows))}
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


def _numeric(tab: _Table, j: int, problems: list[Diagnostic], what: str) -> np.ndarray:
    """Column j as float64 with NaN for missing cells; text cells become diagnostics."""
    vals = tab.cells[j]
    if vals.dtype.kind in "fiub":
        return vals.astype(np.float64)
    if vals.dtype.kind == "M":
        problems.append(Diagnostic(f"{tab.prefix()}column {tab.shown(j)!r} ({what}) holds time stamps, not numbers",
                                   tab.span(None, j), hint="map the column to a number series"))
        return np.full(len(vals), np.nan)
    plain = tab.plain(j)
    if plain is not None:
        return plain.copy()
    text = tab.texts(j)
    import pandas as pd

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
