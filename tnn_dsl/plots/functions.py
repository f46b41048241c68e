"""Learned functions over the range their inputs saw in training."""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from .figure import new_figure

__all__ = ["learned_function"]


def learned_function(summary: dict, values: Callable[[np.ndarray], np.ndarray], n: int = 101,
                     axes: Sequence[Any] | None = None) -> Any:
    """Each target of one learned function against each of its inputs over the input's training range, the
    other inputs at mid-range.

    ``summary``: ``name``, ``kind``, ``targets``, ``inputs``, ``input_kinds`` (``"node"`` for temperatures),
    ``x_min``, ``x_max`` (SI, K for temperatures) — as ``tnnc inspect`` computes it; ``values(X (m, n_in)) ->
    (m, n_targets)`` evaluates the function's targets. ``axes``: one per input."""
    s = summary
    n_in = max(len(s["inputs"]), 1)
    fig, ax = new_figure(1, n_in, figsize=(4.0 * n_in, 3.4), axes=axes)
    lo, hi = np.asarray(s["x_min"], dtype=float), np.asarray(s["x_max"], dtype=float)
    mid = (lo + hi) / 2
    for i in range(n_in):
        a = ax[0, i]
        if not s["inputs"]:
            a.bar(s["targets"], values(np.zeros((1, 0)))[0])
            continue
        X = np.tile(mid, (n, 1))
        span = hi[i] - lo[i]
        grid = np.linspace(lo[i], hi[i], n) if span > 0 else np.linspace(lo[i] - 0.5, hi[i] + 0.5, n)
        X[:, i] = grid
        vals = values(X)
        node = s["input_kinds"][i] == "node"
        gx, xlab = (grid - 273.15, f"T({s['inputs'][i]}) °C") if node else (grid, s["inputs"][i])
        for j, t in enumerate(s["targets"]):
            a.plot(gx, vals[:, j], label=t)
        a.set_xlabel(xlab)
        a.grid(alpha=0.3)
        if i == 0:
            a.legend(fontsize=8)
    fig.suptitle(f"{s['name']}: {', '.join(s['targets'])} as {s['kind']} (others at mid-range)")
    fig.tight_layout()
    return fig
