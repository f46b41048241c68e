"""Measured data for a network: CSV / Parquet files → :class:`Experiment` (SI, kelvin, uniform step).

One experiment per file (or per segment of a file with long gaps, see Gaps). The columns to read come
from the IR: every ``Input.column`` and every ``Sensor.column``. The file's temperature unit is
``Network.temperature_unit``: temperature inputs and all sensors are converted to kelvin; other inputs are
scaled to SI by their declared unit (``[%]`` ×0.01, ``[kW]`` ×1000 ...).

Time
    The time column is ``time_col`` if given, else the first of ``t``, ``time``, ``time_s``, ``timestamp``,
    ``datetime``, ``date``, ... (case-insensitive), else an unnamed first column holding timestamps.
    Numbers are seconds unless the column name carries a unit suffix (``time_h``, ``t_min``, ``time [h]``)
    or ``time_unit`` says otherwise. A numeric time column that runs alongside a timestamp column in the
    same file (the Bacher–Madsen file's ``t`` next to ``TimeDate``) has its unit inferred from the
    timestamps, with a note. ISO timestamps are parsed (time zones respected). ``Experiment.t`` starts at 0
    (a gap segment's at its time in the file).

Sampling
    The model step is ``dt`` if given, else the file's step (for irregular files the median step of the
    rows within segments, rounded to 3 significant digits). If a segment is sampled on that grid (to 1e-6
    relative) its rows are used as they are. Otherwise it is resampled to ``t_k = t_0 + k·dt``: temperature
    inputs linearly, other inputs as the mean over ``[t_k, t_k + dt)`` of the zero-order-held signal (which
    is what the model's zero-order hold sees), sensors linearly between neighbouring rows, but only where
    the two rows are at most ``HOLE_STEPS`` (1.5) periods apart: a grid point inside a longer hole of
    missing rows has no sensor reading (NaN, masked by the trainer and the metrics) rather than an invented
    one. ``Experiment.notes`` says so (and how many such short gaps the inputs were carried across).

Gaps (never interpolated across)
    The *period* is ``max(median row spacing, dt)``. Rows in which every input and every sensor present in
    the file is missing (a logger that kept writing time stamps) count as missing rows. A jump between two
    rows with data longer than ``GAP_STEPS`` (5) periods splits the file into segments, each its own
    :class:`Experiment` named ``<stem>[1/3]``, ``<stem>[2/3]`` ... with the file's ``path``, its own part of
    the file's time (``t[0]`` is the segment's start, not 0) and a note naming the gaps and its lines. A
    segment with fewer than two rows (or spanning less than one step) is dropped, with a note. With
    ``split_gaps=False`` (``tnnc simulate``: one continuous run) a long gap is an error instead.

Missing values
    A NaN in a sensor column is kept (the trainer masks it). A NaN in an input column is a
    :class:`DataError` naming the rows, unless every input and sensor of that row is missing (see Gaps).

Warnings (``Experiment.warnings``: :class:`Diagnostic` s of severity ``"warning"``, ``file:line:col``)
    Kept apart from ``notes`` (what was done to the data) so that the commands can print them even with
    ``-q``. A sensor column with no value in any row when other sensors have data (no sensor with any data,
    when outputs are required, is an error). A temperature column whose values, read in the network's unit,
    look like another unit: in a ``degC``/``degF`` file every value within 200…450 (kelvin); in a ``K``
    file any value below 150 K (°C). A temperature below absolute zero (a -999 "missing" code, or the
    wrong unit). A column the network reads (input, sensor or time) that appears twice in the header is an
    error, at the second occurrence.

Every problem is a :class:`DataError` whose diagnostics point at ``file:line:col`` (line = the CSV line,
the header is line 1); Parquet files have no lines, so their messages name the row instead.
"""

from __future__ import annotations

import math
import os
from typing import Any, Sequence

import numpy as np

from ..core import DataError, Diagnostic
from ..ir import Network
from .experiment import Experiment
from .tables import MAX_REPORTED, _find_column, _missing_column, _numeric, _row_list, read_table
from .timebase import _interp_linear, _interval_mean_zoh, _nice_step, _show_time, _time
from .units import from_kelvin, to_kelvin, unit_scale_offset

__all__ = ["read_data", "as_experiments", "columns_read", "GAP_STEPS", "HOLE_STEPS"]

GAP_STEPS = 5.0
"""A jump between rows with data longer than this many periods splits a file into segments (module docstring)."""

HOLE_STEPS = 1.5
"""Sensors are interpolated only between rows at most this many periods apart; inside longer holes they are NaN."""

_KELVIN_LIKE = (200.0, 450.0)
"""A ``degC``/``degF`` temperature column with every value in this range looks like kelvin."""

_KELVIN_MIN = 150.0
"""A ``K`` temperature column with a value below this looks like °C (or °F)."""


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
    split_gaps: bool = True,
) -> list[Experiment]:
    """Read data files for ``net``: one :class:`Experiment` per file, or per segment of a file with gaps.

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
    split_gaps : bool
        If true (default), a gap longer than ``GAP_STEPS`` periods splits a file into segments (experiments
        ``<stem>[1/2]``, ``<stem>[2/2]``); if false it is an error (callers that need one continuous run).

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
            experiments.extend(_read_one(net, p, time_col, dt, time_unit, require_outputs, split_gaps))
        except DataError as err:
            problems.extend(err.diagnostics)
    if problems:
        raise DataError(problems)
    return experiments


def columns_read(net: Network) -> tuple:
    """What :func:`read_data` takes from ``net`` to read a file, as a hashable key: the temperature unit, each
    input's name, column, unit and whether it is a temperature, each sensor's name and column (in order). Two
    networks with equal keys read any file into the same experiments, so a caller that runs several networks on
    the same files can read each file once (the case study's five models share their 40 out-of-distribution
    files: ``tnn_dsl.studies.thesis``)."""
    return (net.temperature_unit,
            tuple((i.name, i.column, i.unit, bool(i.is_temperature)) for i in net.inputs),
            tuple((s.name, s.column) for s in net.sensors))


def _read_one(net: Network, path: str, time_col, dt, time_unit, require_outputs, split_gaps) -> list[Experiment]:
    """One file as :class:`Experiment` s (one per segment): its columns, values in SI, checks, time, gaps and
    the model's grid."""
    tab = read_table(path)
    _check_row_count(tab)
    notes: list[str] = []
    in_cols, out_cols = _columns(net, tab, require_outputs, notes)
    used = {j for j in in_cols + out_cols if j is not None}
    problems: list[Diagnostic] = []
    t, tj, start = _time(tab, time_col, time_unit, dt, used, problems, notes)
    if tj is not None and tj in used:
        who = [f"input {i.name}" for i, j in zip(net.inputs, in_cols) if j == tj]
        who += [f"sensor {s.name}" for s, j in zip(net.sensors, out_cols) if j == tj]
        problems.append(Diagnostic(f"{tab.prefix()}column {tab.shown(tj)!r} is both the time and {', '.join(who)}",
                                   tab.span(None, tj), hint="name another time column with --time-col"))
    problems.extend(_duplicate_columns(net, tab, in_cols, out_cols, tj, time_col))
    U, Y = _values(net, tab, in_cols, out_cols, problems)
    if problems:
        raise DataError(problems)
    empty = _empty_rows(U, Y, out_cols)
    _check_values(net, tab, in_cols, out_cols, U, Y, empty, problems)
    warnings: list[Diagnostic] = []
    _check_temperatures(net, tab, in_cols, out_cols, U, Y, warnings)
    _check_sensor_columns(net, tab, out_cols, Y, require_outputs, problems, warnings, notes)
    if t is not None:
        _check_time(tab, t, tj, problems)
    if problems:
        raise DataError(problems)
    assert t is not None
    rows = np.flatnonzero(~empty)
    if rows.size < 2:
        raise DataError(Diagnostic(
            f"{tab.prefix()}only {rows.size} row(s) of {tab.n_rows} have any input or sensor value; at least two "
            f"are needed", tab.span(int(rows[0]) if rows.size else None, None),
            hint="every other row has no value in any input or sensor column"))
    if empty.any():
        notes.append(f"{int(empty.sum())} row(s) with no input and no sensor value "
                     f"({_row_list(tab, np.flatnonzero(empty))}) taken as missing rows")
    tk, Uk, Yk = t[rows], U[rows], Y[rows]
    bounds, step, file_dt, gaps, limit = _segments(tk, dt)
    if gaps.size and not split_gaps:
        raise DataError([_gap_diagnostic(tab, tj, rows, tk, g, limit, step) for g in gaps[:MAX_REPORTED]])
    name = os.path.splitext(os.path.basename(path))[0]
    kept: list[tuple[int, int, np.ndarray, np.ndarray, np.ndarray, list[str]]] = []
    dropped: list[str] = []
    for a, b in bounds:
        span_s = float(tk[b - 1] - tk[a])
        if b - a < 2 or span_s < step * (1 - 1e-9):
            if len(bounds) == 1:  # the whole file: the former errors
                raise DataError(Diagnostic(
                    f"{tab.prefix()}the file spans {span_s:g} s, less than one step of {step:g} s",
                    tab.span(None, tj), hint="use a smaller --dt"))
            dropped.append(f"{_lines(tab, rows[a], rows[b - 1])} ({b - a} row(s), {span_s:g} s)")
            continue
        seg_notes: list[str] = []
        tt, Ug, Yg = _on_model_grid(net, tk[a:b], Uk[a:b], Yk[a:b], step, file_dt, seg_notes)
        kept.append((a, b, tt, Ug, Yg, seg_notes))
    if not kept:
        raise DataError(Diagnostic(
            f"{tab.prefix()}every part of the file between gaps longer than {GAP_STEPS:g} periods ({limit:g} s) "
            f"is shorter than two steps", tab.span(None, tj),
            hint="the rows are too far apart for the step: give a larger --dt, or fill the gaps in the file"))
    split_note = ""
    if gaps.size:
        shown = ", ".join(f"{tk[g + 1] - tk[g]:g} s after {tab.where(int(rows[g]))}" for g in gaps[:MAX_REPORTED])
        more = f", ... ({gaps.size} in all)" if gaps.size > MAX_REPORTED else ""
        split_note = (f"split into {len(kept)} segment(s) at {gaps.size} gap(s) with no data longer than "
                      f"{GAP_STEPS:g} periods ({limit:g} s), never interpolated across: {shown}{more}")
        if dropped:
            split_note += f"; dropped segment(s) shorter than two steps: {'; '.join(dropped)}"
    out: list[Experiment] = []
    for i, (a, b, tt, Ug, Yg, seg_notes) in enumerate(kept):
        mine = list(notes)
        if split_note:
            mine.append(f"{split_note}; this is segment {i + 1} of {len(kept)}: {_lines(tab, rows[a], rows[b - 1])}, "
                        f"t = {tt[0]:g} … {tt[-1]:g} s")
        mine.extend(seg_notes)
        out.append(Experiment(
            name=f"{name}[{i + 1}/{len(kept)}]" if len(kept) > 1 else name, path=path, t=tt, dt=step,
            inputs=np.ascontiguousarray(Ug, dtype=np.float64), outputs=np.ascontiguousarray(Yg, dtype=np.float64),
            input_names=tuple(net.input_names), output_names=tuple(s.name for s in net.sensors),
            notes=tuple(mine), warnings=tuple(warnings),
            input_columns=tuple(tab.columns[j] if j is not None else None for j in in_cols),
            output_columns=tuple(tab.columns[j] if j is not None else None for j in out_cols),
            time_column=tab.columns[tj] if tj is not None else None, start=start,
        ))
    return out


def _lines(tab, first: int, last: int) -> str:
    """``lines 2–3601`` (CSV) / ``rows 1–3600`` (Parquet)."""
    a, b = tab.where(int(first)), tab.where(int(last))
    return a if first == last else f"{a.split()[0]}s {a.split()[1]}–{b.split()[1]}"


def _check_row_count(tab) -> None:
    if tab.n_rows == 0:
        raise DataError(Diagnostic(f"{tab.prefix()}the data file has a header but no data rows",
                                   tab.span(None, None), hint="a data file needs at least two rows"))
    if tab.n_rows == 1:
        raise DataError(Diagnostic(f"{tab.prefix()}the data file has only one data row; at least two are needed",
                                   tab.span(0, None), hint="a simulation needs a time step: give two or more rows"))


def _columns(net: Network, tab, require_outputs: bool, notes: list[str]) -> tuple[list, list]:
    """The column index of every input and sensor (``None``: absent); a missing input (or, with
    ``require_outputs``, sensor) column is an error."""
    problems: list[Diagnostic] = []
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
    if problems:
        raise DataError(problems)
    return in_cols, out_cols


def _values(net: Network, tab, in_cols, out_cols, problems: list[Diagnostic]) -> tuple[np.ndarray, np.ndarray]:
    """Inputs ``(n, n_inputs)`` in SI (temperatures in K) and sensors ``(n, n_sensors)`` in K (NaN: none)."""
    n, tunit = tab.n_rows, net.temperature_unit
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
    return U, Y


def _empty_rows(U: np.ndarray, Y: np.ndarray, out_cols) -> np.ndarray:
    """Rows (n,) in which every input and every sensor the file has is missing: missing rows (see Gaps).
    A file without any sensor column has none (a missing input there is an error, as always)."""
    present = [k for k, j in enumerate(out_cols) if j is not None]
    if not present:
        return np.zeros(U.shape[0], dtype=bool)
    return np.all(np.isnan(U), axis=1) & np.all(np.isnan(Y[:, present]), axis=1)


def _check_values(net: Network, tab, in_cols, out_cols, U, Y, empty, problems: list[Diagnostic]) -> None:
    """NaN or infinite inputs (outside rows with no value at all), infinite sensor readings: errors naming
    the rows."""
    for k, (inp, j) in enumerate(zip(net.inputs, in_cols)):
        bad = np.flatnonzero(~np.isfinite(U[:, k]) & ~empty)
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


def _duplicate_columns(net: Network, tab, in_cols, out_cols, tj, time_col) -> list[Diagnostic]:
    """A column the network reads (input, sensor, time) whose name the header holds twice: an error at the
    second occurrence (the reader would silently take the first). Names are compared exactly, or ignoring
    case and spaces when the column was found that way."""
    wanted = [(j, inp.column, f"input {inp.name}") for inp, j in zip(net.inputs, in_cols)]
    wanted += [(j, s.column, f"sensor {s.name}") for s, j in zip(net.sensors, out_cols)]
    wanted.append((tj, time_col, "the time"))
    out: list[Diagnostic] = []
    seen: set[int] = set()
    for j, name, who in wanted:
        if j is None or j in seen:
            continue
        seen.add(j)
        if name is not None and tab.columns[j] == name:
            same = [k for k, c in enumerate(tab.columns) if c == name]
        else:
            key = tab.columns[j].strip().lower()
            same = [k for k, c in enumerate(tab.columns) if c.strip().lower() == key]
        if len(same) < 2:
            continue
        times = "twice" if len(same) == 2 else f"{len(same)} times"
        where = ", ".join(str(k + 1) for k in same[:-1]) + f" and {same[-1] + 1}"
        out.append(Diagnostic(
            f"{tab.prefix()}column {tab.shown(same[1])!r} appears {times} (columns {where}); it is {who}, and "
            f"which one is meant is ambiguous", tab.span(None, same[1]),
            hint="rename the columns so that each name is unique (or point `column \"...\"` in the network at "
                 "the one meant)"))
    return out


def _check_temperatures(net: Network, tab, in_cols, out_cols, U, Y, warnings: list[Diagnostic]) -> None:
    """Temperature columns (temperature inputs, sensors) read in the network's unit: values below absolute
    zero, or a range that looks like another unit, are warnings (module docstring)."""
    unit = net.temperature_unit
    cols = [(U[:, k], j, f"input {inp.name}") for k, (inp, j) in enumerate(zip(net.inputs, in_cols))
            if inp.is_temperature]
    cols += [(Y[:, k], j, f"sensor {s.name}") for k, (s, j) in enumerate(zip(net.sensors, out_cols)) if j is not None]
    switch = "if the file is in {0}, write `units temperature = {0}` in the network"
    for kelvin, j, who in cols:
        ok = np.isfinite(kelvin)
        if not ok.any():
            continue
        below = np.flatnonzero(ok & (kelvin < -1e-9))
        if below.size:
            r = int(below[0])
            warnings.append(Diagnostic(
                f"{tab.prefix()}{who} (column {tab.shown(j)!r}) reads {from_kelvin(kelvin[r], unit):.6g} {unit} at "
                f"{tab.where(r)}, below absolute zero" + (f" ({below.size} such rows)" if below.size > 1 else ""),
                tab.span(r, j), severity="warning",
                hint=f"the network reads temperatures in {unit}; leave the cell empty for a missing value"
                     + ("" if unit != "K" else "; " + switch.format("degC"))))
            continue
        raw = from_kelvin(kelvin[ok], unit)
        lo, hi = float(raw.min()), float(raw.max())
        seen = f"{lo:.4g} … {hi:.4g} {unit}"
        if unit in ("degC", "degF") and _KELVIN_LIKE[0] <= lo and hi <= _KELVIN_LIKE[1]:
            warnings.append(Diagnostic(
                f"{tab.prefix()}{who} (column {tab.shown(j)!r}) reads {seen}, which looks like kelvin, not {unit}",
                tab.span(None, j), severity="warning", hint=switch.format("K")))
        elif unit == "K" and lo < _KELVIN_MIN:
            warnings.append(Diagnostic(
                f"{tab.prefix()}{who} (column {tab.shown(j)!r}) reads {seen}; below {_KELVIN_MIN:g} K is implausible: "
                f"the values look like degC (or degF), not kelvin",
                tab.span(None, j), severity="warning", hint=switch.format("degC") + " (or degF)"))


def _check_sensor_columns(net: Network, tab, out_cols, Y, require_outputs: bool, problems: list[Diagnostic],
                          warnings: list[Diagnostic], notes: list[str]) -> None:
    """Sensor columns with no value in any row: a warning each when another sensor has data (a note when
    outputs are not required); an error when none has (and outputs are required)."""
    empty = [(s, j) for k, (s, j) in enumerate(zip(net.sensors, out_cols))
             if j is not None and not np.isfinite(Y[:, k]).any()]
    if not empty:
        return
    if require_outputs and len(empty) == len(net.sensors):
        names = ", ".join(f"{tab.shown(j)!r} (sensor {s.name})" for s, j in empty)
        problems.append(Diagnostic(
            f"{tab.prefix()}no sensor column has a value in any row: {names}", tab.span(None, empty[0][1]),
            hint="training and evaluation need measurements: check the file, or point the sensors' "
                 "`column \"...\"` at the measured columns"))
        return
    for s, j in empty:
        msg = f"sensor {s.name} (column {tab.shown(j)!r}) has no value in any row: it is not measured in this file"
        if require_outputs:
            warnings.append(Diagnostic(f"{tab.prefix()}{msg}", tab.span(None, j), severity="warning",
                                       hint="check the file, or the sensor's `column \"...\"` in the network"))
        else:
            notes.append(msg)


def _check_time(tab, t: np.ndarray, tj, problems: list[Diagnostic]) -> None:
    """Time that goes backwards, repeats or is not finite."""
    d = np.diff(t)
    for r in np.flatnonzero(d < 0)[:MAX_REPORTED]:
        problems.append(Diagnostic(
            f"{tab.prefix()}time goes backwards at {tab.where(int(r + 1))}: "
            f"{_show_time(tab, tj, r + 1)} after {_show_time(tab, tj, r)}",
            tab.span(int(r + 1), tj), hint="sort the rows by time, or split the file into separate runs"))
    for r in np.flatnonzero(d == 0)[:MAX_REPORTED]:
        problems.append(Diagnostic(
            f"{tab.prefix()}duplicate time {_show_time(tab, tj, r + 1)} at {tab.where(int(r + 1))} "
            f"(also at {tab.where(int(r))})",
            tab.span(int(r + 1), tj), hint="remove the repeated rows (or average them)"))
    if not np.all(np.isfinite(t)):
        problems.append(Diagnostic(f"{tab.prefix()}the time column has non-finite values", tab.span(None, tj)))


def _segments(t: np.ndarray, dt):
    """Rows with data at times ``t`` → ``(bounds [(a, b)], step, file_dt, gaps, limit)``: the segments between
    jumps longer than ``GAP_STEPS`` periods (``gaps``: the indices ``g`` of jumps ``t[g] → t[g+1]``), the model
    step, the median row spacing and the gap threshold in s."""
    d = np.diff(t)
    file_dt = float(np.median(d))
    limit = GAP_STEPS * max(file_dt, float(dt) if dt is not None else 0.0)
    gaps = np.flatnonzero(d > limit)
    cuts = [0, *(int(g) + 1 for g in gaps), len(t)]
    bounds = list(zip(cuts[:-1], cuts[1:]))
    inner = np.delete(d, gaps)
    if dt is not None:
        step = float(dt)
    elif inner.size and np.all(np.abs(inner - inner.mean()) <= 1e-6 * inner.mean()):
        step = float(f"{inner.mean():.9g}")  # a regular file: its own step (float noise removed)
    else:
        step = _nice_step(float(np.median(inner)) if inner.size else file_dt)  # an irregular one: its median step
    return bounds, step, file_dt, gaps, limit


def _gap_diagnostic(tab, tj, rows: np.ndarray, t: np.ndarray, g: int, limit: float, step: float) -> Diagnostic:
    """The error for a gap when the caller needs one continuous run."""
    r0, r1 = int(rows[g]), int(rows[g + 1])
    gap = float(t[g + 1] - t[g])
    return Diagnostic(
        f"{tab.prefix()}gap of {gap:g} s ({gap / step:.0f} steps of {step:g} s) with no data between "
        f"{tab.where(r0)} and {tab.where(r1)}; longer than {GAP_STEPS:g} periods ({limit:g} s), so not interpolated",
        tab.span(r1, tj), hint="this command needs one continuous run: split the file at the gap (or fill it)")


def _on_model_grid(net: Network, t: np.ndarray, U: np.ndarray, Y: np.ndarray, step: float, file_dt: float,
                   notes: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One segment (rows at file times ``t``, no long gap) → ``(t_k = t_0 + k·step, inputs, sensors)``: the rows
    as they are when they lie on the step's grid, else resampled (temperature inputs linearly, other inputs as
    interval means of their zero-order hold, sensors linearly but NaN inside holes longer than ``HOLE_STEPS``
    periods), with a note saying so."""
    n = len(t)
    t0 = float(t[0])
    r = t - t0
    steps = np.diff(r)
    on_grid = abs(r[-1] - (n - 1) * step) <= 1e-6 * step * max(n, 1) and \
        bool(np.all(np.abs(steps - step) <= 1e-6 * step))
    if on_grid:
        return t0 + np.arange(n, dtype=np.float64) * step, U, Y
    grid_n = int(math.floor(r[-1] / step * (1 + 1e-9) + 1e-9)) + 1
    tt = np.arange(grid_n, dtype=np.float64) * step
    Ug = np.empty((grid_n, U.shape[1]))
    for k, inp in enumerate(net.inputs):
        if inp.is_temperature:
            Ug[:, k] = _interp_linear(r, U[:, k], tt)
        else:
            Ug[:, k] = _interval_mean_zoh(r, U[:, k], tt, step)
    Yg = np.empty((grid_n, Y.shape[1]))
    for k in range(Y.shape[1]):
        Yg[:, k] = _interp_linear(r, Y[:, k], tt)
    hole = HOLE_STEPS * max(file_dt, step)
    holes = np.flatnonzero(steps > hole)
    masked = 0
    if holes.size:
        i = np.clip(np.searchsorted(r, tt, side="right") - 1, 0, n - 2)
        inside = (steps[i] > hole) & (tt > r[i] + 1e-6 * step) & (tt < r[i + 1] - 1e-6 * step)
        Yg[inside] = np.nan
        masked = int(inside.sum())
    seg_dt = float(np.median(steps))
    irregular = float(np.max(np.abs(steps - seg_dt))) > 1e-6 * seg_dt
    why = (f"irregular sampling (steps {steps.min():g} to {steps.max():g} s)" if irregular
           else f"the file's step {seg_dt:g} s differs from dt")
    note = (f"resampled {n} rows to {grid_n} steps of {step:g} s because of {why}: sensors and temperature inputs "
            f"linearly, other inputs as the interval mean of their zero-order hold")
    if holes.size:
        note += (f"; {holes.size} short gap(s) of missing rows (longest {steps[holes].max():g} s, at most "
                 f"{GAP_STEPS:g} periods): inputs carried across them, sensors not interpolated "
                 f"({masked} step(s) left unmeasured)")
    notes.append(note)
    return t0 + tt, Ug, Yg


# ---------------------------------------------------------------------------------------------
# Splitting and writing
# ---------------------------------------------------------------------------------------------


def as_experiments(net: Network, data: Any, *, same_columns: bool = False, time_col: str | None = None,
                   dt: float | None = None, time_unit: str | None = None) -> list[Experiment]:
    """Paths (one or many) and/or :class:`Experiment` objects → a list of ``Experiment`` for ``net``
    (paths are read with :func:`read_data` and the time options; ``None`` gives ``[]``). The one place the
    trainer, the sensitivity pass, saved models and model comparison turn "data" arguments into experiments.
    ``same_columns``: an ``Experiment`` read for other inputs or sensors than ``net``'s is an error (comparing two
    networks, each must read its own columns)."""
    if data is None:
        return []
    if isinstance(data, (str, os.PathLike)) or hasattr(data, "inputs"):
        data = [data]
    exps, paths = [], []
    for d in data:
        if hasattr(d, "inputs") and hasattr(d, "outputs"):
            if same_columns and (tuple(getattr(d, "input_names", ())) != tuple(net.input_names)
                                 or tuple(getattr(d, "output_names", ())) != tuple(s.name for s in net.sensors)):
                raise DataError(Diagnostic(
                    f"experiment {getattr(d, 'name', '?')!r} was read for other inputs or sensors than network "
                    f"{net.name!r} has", hint="pass the data files' paths: each network reads its own columns"))
            exps.append(d)
        else:
            paths.append(os.fspath(d))
    if paths:
        exps.extend(read_data(net, paths, time_col, dt, time_unit=time_unit))
    return exps
