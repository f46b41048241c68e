"""Helpers shared by the plots: a figure with a grid of axes (or the caller's axes), time axes, unit labels."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

__all__ = ["new_figure", "time_axis", "UNIT_LABEL"]

UNIT_LABEL = {"degC": "°C", "K": "K", "degF": "°F"}
"""How a network's temperature unit is shown on an axis."""


def new_figure(nrows: int = 1, ncols: int = 1, figsize: tuple[float, float] = (8.0, 4.0),
               axes: Sequence[Any] | None = None, **subplot_kw: Any) -> tuple[Any, np.ndarray]:
    """``(figure, axes (nrows, ncols))``: a new :class:`~matplotlib.figure.Figure` with a grid of axes, or the
    figure of the caller's ``axes`` (a sequence of at least ``nrows·ncols`` axes, used in order)."""
    if axes is not None:
        flat = list(np.ravel(np.asarray(axes, dtype=object)))
        if len(flat) < nrows * ncols:
            raise ValueError(f"this plot needs {nrows * ncols} axes, got {len(flat)}")
        return flat[0].figure, np.asarray(flat[: nrows * ncols], dtype=object).reshape(nrows, ncols)
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    ax = fig.subplots(nrows, ncols, squeeze=False, **subplot_kw)
    return fig, ax


def time_axis(t: np.ndarray) -> tuple[np.ndarray, str]:
    """Time ``t`` (s) in the unit its duration reads best in: ``(values, "s" | "min" | "h")``."""
    t = np.asarray(t, dtype=float)
    span = float(t[-1] - t[0]) if t.size else 0.0
    scale, unit = (3600.0, "h") if span > 3 * 3600 else ((60.0, "min") if span > 600 else (1.0, "s"))
    return t / scale, unit
