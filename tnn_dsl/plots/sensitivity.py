"""The sensitivity pass's ranked bar chart (thesis Figure 5.3)."""

from __future__ import annotations

from typing import Any

import numpy as np

from .figure import new_figure

__all__ = ["sensitivity_bars"]

GROUP_COLORS = {"peltier": "tab:red", "link": "tab:blue", "fluid": "tab:cyan", "capacity": "tab:gray",
                "source": "tab:orange", "radiation": "tab:purple", "sensor": "tab:olive", "parameter": "tab:green"}


def sensitivity_bars(report: Any, top: int | None = 25, ax: Any | None = None) -> Any:
    """A horizontal bar chart of a ``SensitivityReport``'s ranked steady-state sensitivities |Δy/Δα|, coloured
    by element group; the ``top`` largest (all: ``None``)."""
    from matplotlib.patches import Rectangle

    params = [p for p in report.parameters if p.sensitivity > 0][: top or None]
    fig, axs = new_figure(1, 1, figsize=(7.5, 0.32 * max(len(params), 3) + 1.4), axes=None if ax is None else [ax])
    a = axs[0, 0]
    ys = np.arange(len(params))[::-1]
    a.barh(ys, [p.sensitivity for p in params], color=[GROUP_COLORS.get(p.group, "tab:green") for p in params])
    a.set_yticks(ys, [p.name for p in params])
    a.set_xlabel(f"|Δy/Δα| (K per unit α), mean over {', '.join(report.output_names)}")
    a.set_title(f"Local steady-state sensitivity, α ∈ [{1 - report.delta:g}, {1 + report.delta:g}]")
    groups = [g for g in GROUP_COLORS if any(p.group == g for p in params)]
    if groups:
        a.legend([Rectangle((0, 0), 1, 1, color=GROUP_COLORS[g]) for g in groups], groups, loc="lower right",
                 fontsize=8)
    a.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    return fig
