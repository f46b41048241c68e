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

import math
import os
from typing import Any, Sequence

import numpy as np

from ..core import DataError, Diagnostic
from ..ir import Network
from .experiment import Experiment
from .tables import MAX_REPORTED, _find_column, _missing_column, _numeric, _row_list, read_table
from .timebase import _interp_linear, _interval_mean_zoh, _nice_step, _show_time, _time
from .units import to_kelvin, unit_scale_offset

__all__ = ["read_data", "as_experiments"]


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
    """One file as an :class:`Experiment`: its columns, values in SI, checks, time and the model's grid."""
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
    U, Y = _values(net, tab, in_cols, out_cols, problems)
    if problems:
        raise DataError(problems)
    _check_values(net, tab, in_cols, out_cols, U, Y, problems)
    if t is not None:
        _check_time(tab, t, tj, problems)
    if problems:
        raise DataError(problems)
    assert t is not None
    tt, Ug, Yg, step = _on_model_grid(net, tab, t, tj, U, Y, dt, notes)
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


def _check_values(net: Network, tab, in_cols, out_cols, U, Y, problems: list[Diagnostic]) -> None:
    """NaN or infinite inputs, infinite sensor readings: errors naming the rows."""
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


def _on_model_grid(net: Network, tab, t: np.ndarray, tj, U: np.ndarray, Y: np.ndarray, dt, notes: list[str]):
    """``(t_k = k·step, inputs, sensors, step)``: the rows as they are when the file is on the step's grid,
    else resampled (sensors and temperature inputs linearly, other inputs as interval means of their
    zero-order hold), with a note saying so."""
    n = tab.n_rows
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
        return np.arange(n, dtype=np.float64) * step, U, Y, step
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
    return tt, Ug, Yg, step


# ---------------------------------------------------------------------------------------------
# Splitting and writing
# ---------------------------------------------------------------------------------------------


def as_experiments(net: Network, data: Any) -> list[Experiment]:
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
