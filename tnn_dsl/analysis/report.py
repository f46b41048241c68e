"""The sensitivity pass's results: one row per parameter or component flow, the recommendations, and the
report (table, JSON, plot)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core import to_jsonable
from ..core.htmlview import html_list, html_table, safe_repr_html, view
from .common import _fmt
from .identifiability import Identifiability

__all__ = ["SensitivityReport", "ParameterSensitivity", "Recommendation"]


@dataclass
class ParameterSensitivity:
    """The sensitivity of every sensor to one parameter or component heat flow.

    ``alphas`` (A,) the scale factors; ``outputs`` (A, n_out) the steady sensor readings (K) at each;
    ``slope`` (n_out,) the least-squares slope of the readings against α (K per unit α, signed; thesis eq.
    4.5 without the absolute value); ``sensitivity`` = mean over sensors of ``|slope|`` (the ranking
    measure); ``autodiff`` (n_out,) the exact ``θ ∂y*/∂θ`` at α = 1 (eq. 3.4, K per unit α); ``linearity``
    the smallest R² of the line over the sensors; ``dynamic_rms``/``dynamic_max`` the RMS/max of
    ``|∂y(t)/∂α|`` along the data (K per unit α; ``None`` without data)."""

    name: str
    kind: str
    group: str
    role: str | None
    owner: str | None
    nominal: float | None
    unit: str | None
    alphas: np.ndarray
    outputs: np.ndarray
    slope: np.ndarray
    sensitivity: float
    autodiff: np.ndarray
    linearity: float
    dynamic_rms: float | None = None
    dynamic_max: float | None = None
    note: str | None = None

    @property
    def autodiff_sensitivity(self) -> float:
        return float(np.mean(np.abs(self.autodiff)))

    def to_dict(self) -> dict:
        return to_jsonable(dict(self.__dict__, autodiff_sensitivity=self.autodiff_sensitivity), inf_as_text=True)


@dataclass
class Recommendation:
    """``verdict``: ``"learn"`` (sensitive and identifiable), ``"fix"`` (insensitive, or confounded with a
    kept parameter, or not identifiable from this data) or ``"candidate"`` (sensitive; no data was given to
    check identifiability)."""

    name: str
    verdict: str
    reason: str

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class SensitivityReport:
    """Everything :func:`sensitivity` computed. ``parameters`` is ranked (most sensitive first; the ranking
    uses the steady sensitivity, ties — capacities at 0 — broken by the dynamic one)."""

    network: str
    backend: str
    delta: float
    alphas: np.ndarray
    inputs: dict[str, float]
    output_names: list[str]
    state_names: list[str]
    steady_state: dict[str, float]
    parameters: list[ParameterSensitivity]
    skipped: dict[str, str]
    identifiability: Identifiability | None
    data: list[str]
    recommendations: list[Recommendation]
    notes: list[str]
    min_effect: float

    @property
    def ranking(self) -> list[str]:
        return [p.name for p in self.parameters]

    def __getitem__(self, name: str) -> ParameterSensitivity:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(name)

    def to_dict(self) -> dict:
        return to_jsonable({
            "network": self.network, "backend": self.backend, "delta": self.delta, "alphas": self.alphas,
            "inputs": self.inputs, "outputs": self.output_names, "steady_state": self.steady_state,
            "ranking": self.ranking, "parameters": [p.to_dict() for p in self.parameters],
            "skipped": self.skipped,
            "identifiability": None if self.identifiability is None else self.identifiability.to_dict(),
            "data": self.data, "recommendations": [r.to_dict() for r in self.recommendations],
            "notes": self.notes, "min_effect": self.min_effect,
        }, inf_as_text=True)

    def ranking_rows(self, top: int | None = None) -> list[dict[str, Any]]:
        """The ranking table's rows (what :meth:`table` and the notebook view show): ``rank``, ``name``,
        ``group``, ``sensitivity`` and ``autodiff`` (K per unit α), ``linearity`` (R²), ``dynamic_rms`` (K per
        unit α, NaN without data)."""
        return [{"rank": k, "name": p.name, "group": p.group, "sensitivity": p.sensitivity,
                 "autodiff": p.autodiff_sensitivity, "linearity": p.linearity,
                 "dynamic_rms": p.dynamic_rms if p.dynamic_rms is not None else math.nan}
                for k, p in enumerate(self.parameters[: top or None], 1)]

    def skipped_by_reason(self) -> dict[str, list[str]]:
        """The parameters that were not scanned, grouped by the reason."""
        by_reason: dict[str, list[str]] = {}
        for k, v in self.skipped.items():
            by_reason.setdefault(v, []).append(k)
        return by_reason

    def ordered_recommendations(self) -> list[Recommendation]:
        """The recommendations in the order the table shows them: learn, candidate, fix."""
        return [r for verdict in ("learn", "candidate", "fix") for r in self.recommendations if r.verdict == verdict]

    def _title(self) -> str:
        return (f"Steady-state sensitivity of {', '.join(self.output_names)} (network {self.network}, "
                f"{self.backend}; α ∈ [{1 - self.delta:g}, {1 + self.delta:g}], thesis §4.3)")

    def table(self, top: int | None = None) -> str:
        out = [self._title(), "inputs: " + ", ".join(f"{k} = {v:.6g}" for k, v in self.inputs.items())]
        dyn = any(p.dynamic_rms is not None for p in self.parameters)
        head = (f"{'#':>3}  {'parameter':<24} {'group':<10} {'|dy/dα| K':>11} {'autodiff K':>11} "
                f"{'R²':>6}" + (f" {'dyn. RMS K':>11}" if dyn else ""))
        out += [head, "-" * len(head)]
        for r in self.ranking_rows(top):
            line = (f"{r['rank']:>3}  {r['name']:<24} {r['group']:<10} {_fmt(r['sensitivity'], 4):>11} "
                    f"{_fmt(r['autodiff'], 4):>11} {_fmt(r['linearity'], 3):>6}")
            if dyn:
                line += f" {_fmt(r['dynamic_rms'], 4):>11}"
            out.append(line)
        for reason, names in self.skipped_by_reason().items():
            out.append(f"not scanned: {', '.join(names)} ({reason})")
        if self.identifiability is not None:
            out += ["", self.identifiability.table()]
        if self.recommendations:
            out += ["", "Recommendation (thesis §4.4: combine with physical insight — keep well-known physics fixed)"]
            for r in self.ordered_recommendations():
                out.append(f"  {r.verdict.upper():<9} {r.name:<24} {r.reason}")
        for n in self.notes:
            out.append(f"note: {n}")
        return "\n".join(out)

    def _repr_html_(self) -> str:
        """The notebook view: :meth:`table` as tables (``<pre>`` of the table should that fail)."""
        return safe_repr_html(self._html, self.table, f"SensitivityReport({self.network!r})")

    def _html(self) -> str:
        dyn = any(p.dynamic_rms is not None for p in self.parameters)
        head = ["#", "parameter", "group", "|dy/dα| K", "autodiff K", "R²"] + (["dyn. RMS K"] if dyn else [])
        rows = [[r["rank"], r["name"], r["group"], r["sensitivity"], r["autodiff"], r["linearity"]]
                + ([r["dynamic_rms"]] if dyn else []) for r in self.ranking_rows()]
        parts = [html_list(["inputs: " + ", ".join(f"{k} = {v:.6g}" for k, v in self.inputs.items())]),
                 html_table(head, rows, numeric=[True, False, False] + [True] * (len(head) - 3))]
        notes = [f"not scanned: {', '.join(names)} ({reason})" for reason, names in self.skipped_by_reason().items()]
        if self.identifiability is not None:
            parts.append(self.identifiability.html())
        recs = self.ordered_recommendations()
        if recs:
            parts.append("<b>Recommendation</b> (thesis §4.4: combine with physical insight — keep well-known "
                         "physics fixed)"
                         + html_table(["verdict", "parameter", "reason"], [[r.verdict.upper(), r.name, r.reason]
                                                                          for r in recs]))
        parts.append(html_list(notes + [f"note: {n}" for n in self.notes]))
        return view(self._title(), *parts)

    def plot(self, path: str, top: int | None = 25) -> str:
        """Write the ranked bar chart (thesis Figure 5.3; :func:`tnn_dsl.plots.sensitivity_bars`) to ``path``."""
        from .. import plots
        from ..core import save_figure

        save_figure(plots.sensitivity_bars(self, top), path, dpi=120)
        return path
