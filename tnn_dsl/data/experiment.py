"""One experiment as the stages see it (:class:`Experiment`: time, inputs in SI, outputs in K with NaN for
missing, names, columns, notes, warnings), and splitting one in time."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from ..core import DataError, Diagnostic

__all__ = ["Experiment", "split_by_time", "warning_lines"]


@dataclass(frozen=True, eq=False)
class Experiment:
    """One measured run, on a uniform grid, in SI.

    Attributes
    ----------
    name : str
        The file's stem (``"train"`` for ``data/train.csv``); split parts get ``[:70%]`` / ``[70%:]``, the
        segments of a file split at its gaps ``[1/2]`` / ``[2/2]``.
    path : str
        The file read.
    t : ndarray (N,)
        Time in s; ``t[k] = t[0] + k·dt``; ``t[0] = 0`` for a whole file (a part keeps its time in the file).
    dt : float
        The step, s.
    inputs : ndarray (N, n_inputs)
        In ``Network.inputs`` order, SI (temperature inputs in K). Zero-order hold over ``[t_k, t_k + dt)``.
    outputs : ndarray (N, n_outputs)
        In ``Network.sensors`` order, K; NaN where not measured.
    input_names, output_names : tuple[str, ...]
        Input and sensor names (not column names).
    notes : tuple[str, ...]
        What was done to the data on the way in (resampling, inferred units, missing sensor columns, gaps).
    input_columns, output_columns : tuple[str | None, ...]
        The file's column for each input / sensor (``None`` for a sensor column the file lacks).
    time_column : str | None
        The time column used (``None`` when the rows were taken as equally spaced by ``dt``).
    start : str | None
        The file's first time stamp as written (ISO), or ``None`` for a numeric time column.
    warnings : tuple[Diagnostic, ...]
        Data that looks wrong but was read (a sensor column with no value, temperatures that look like another
        unit): ``Diagnostic`` s of severity ``"warning"`` with the header cell's position; print them with
        ``d.format()``, even in quiet mode.
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
    warnings: tuple[Diagnostic, ...] = ()

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
            f"outputs={list(self.output_names)}, notes={len(self.notes)}"
            + (f", warnings={len(self.warnings)})" if self.warnings else ")")
        )


def warning_lines(experiments: Sequence[Experiment]) -> list[str]:
    """The experiments' warnings, formatted (``file:line:col: warning: ...``, the source line, a caret, the hint),
    each once (the segments of one file share theirs), in order: what a command prints even when quiet."""
    out: list[str] = []
    for e in experiments:
        for w in getattr(e, "warnings", ()):
            text = w.format()
            if text not in out:
                out.append(text)
    return out


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
