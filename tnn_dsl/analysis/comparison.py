"""Comparing two networks fitted to the same data: nesting, the likelihood-ratio test, AIC/BIC and prediction errors
(``tnnc compare``; Bacher & Madsen 2011's forward selection Ti → TiTh → TiTeTh).

* :func:`nesting` decides from the IR alone whether network B is network A plus elements (:class:`Nesting`).
* :func:`compare_models` fits both (:func:`tnn_dsl.fit.train`, by default ``objective="ml"``) and gives a
  :class:`Comparison`: the likelihood-ratio statistic ``LR = 2(log L_B − log L_A)``, its degrees of freedom
  ``k_B − k_A`` (every estimated quantity counts: parameters, noise levels, initial states), ``p = P(χ²_df > LR)``,
  AIC and BIC of both, the free-run MAE and the one-step-ahead RMS (held-out data where given) and a verdict.

**The nesting rule.** B *extends* A when A is what B becomes in a limit of B's parameters, element by element:

* every input, node and boundary of A is in B under the same name (an input with the same column); the sensors are
  the same (name, node, column) — a sensor B adds changes the data the likelihood is over, so the two are then not
  comparable; B may add a lag or an offset to a sensor (τ → 0, offset → 0);
* every link of A is in B connecting the same two nodes (under its own name, else under another name, which is
  noted), or is *split in series* in B: a path between its two ends through nodes that only B has (TiTe's
  ``ti -- te -- amb`` for Ti's ``Ria``: with ``Ce → 0`` the path is one resistance ``Rie + Rea``);
* every source of A is in B (by name, else by the same value) on the same node, or has *moved* to a node that only
  B has and that B connects to the old node through nodes only B has (TiTh's heater node ``th``: with ``Ch → 0``
  and ``Rih → 0`` the heat goes straight into ``ti``);
* radiation, Peltier and fluid elements of A are in B unchanged; learned functions must be the same in both (else
  nesting cannot be decided: ``nested = None``);
* every parameter of A (other than a split link's resistance) is in B: a free one free, a fixed one fixed at the
  same value or free in B (that frees it), a derived one with the same expression;
* B adds something (an element, or a parameter freed); whatever B adds reduces to nothing in a limit (a link's
  ``R → ∞``, a source's gain → 0, a new node's capacitance → 0).

These limits lie on the edge of (often outside) B's declared ranges, so the χ² distribution of the likelihood
ratio is the usual approximation that Bacher & Madsen use, not an exact result. Under ``objective="ml"`` the
log-likelihood is the Kalman filter's (one-step-ahead), comparable between nested models on the same data. Under
``objective="output-error"`` it is the Gaussian likelihood of the free-run residuals, which are far from white:
the test is then only indicative, and the summary says so.
"""

from __future__ import annotations

import math
import os
from collections import deque
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any, Callable

import numpy as np

from ..core import Diagnostic, TnnError
from ..core.htmlview import html_list, html_table, pre, safe_repr_html, view
from ..ir import Network

__all__ = ["Nesting", "ModelFit", "Comparison", "nesting", "compare_models", "fit_and_score", "OBJECTIVES", "ALPHA"]

OBJECTIVES = ("ml", "output-error")
ALPHA = 0.05
"""The significance level of the verdict."""
_P_FLOOR = 1e-300


# ---------------------------------------------------------------------------------------------
# Nesting from the IR
# ---------------------------------------------------------------------------------------------


@dataclass
class Nesting:
    """Is network B network A plus elements? ``nested``: ``True``, ``False`` or ``None`` (cannot tell);
    ``added``: what B adds (``"node th"``, ``"link Rih (th–ti)"``, ``"parameter C_th"``); ``reductions``: how B
    reduces to A where it is not plain addition (a split link, a moved source, a renamed link); ``reasons``: why B
    does not extend A (or why that cannot be decided)."""

    nested: bool | None
    added: list[str] = field(default_factory=list)
    reductions: list[str] = field(default_factory=list)
    reasons: list[str] = field(default_factory=list)
    a: str = "A"
    b: str = "B"

    def to_dict(self) -> dict[str, Any]:
        return {"nested": self.nested, "a": self.a, "b": self.b, "added": list(self.added),
                "reductions": list(self.reductions), "reasons": list(self.reasons)}

    def summary(self) -> str:
        """One paragraph: the decision and what it rests on."""
        if self.nested:
            head = f"{self.b} extends {self.a}"
        elif self.nested is None:
            head = f"cannot tell whether {self.b} extends {self.a}"
        else:
            head = f"{self.b} does not extend {self.a}"
        lines = [head]
        if self.added:
            lines.append("  adds: " + ", ".join(self.added))
        lines += [f"  reduces: {r}" for r in self.reductions]
        lines += [f"  because: {r}" for r in self.reasons]
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.summary()


def _plain(obj: Any) -> Any:
    """A pydantic object as plain data without source positions (for comparing declarations across files)."""
    if hasattr(obj, "model_dump"):
        obj = obj.model_dump()
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items() if k != "span"}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj


def _path(start: str, goal: str, through: set[str], links: list[Any]) -> list[Any] | None:
    """The links of a shortest path ``start → goal`` in ``links`` whose interior nodes are all in ``through``."""
    adj: dict[str, list[tuple[str, Any]]] = {}
    for lk in links:
        adj.setdefault(lk.a, []).append((lk.b, lk))
        adj.setdefault(lk.b, []).append((lk.a, lk))
    prev: dict[str, tuple[str, Any] | None] = {start: None}
    queue = deque([start])
    while queue:
        n = queue.popleft()
        if n == goal:
            out = []
            while prev[n] is not None:
                n, lk = prev[n][0], prev[n][1]
                out.append(lk)
            return out[::-1]
        if n != start and n not in through:
            continue
        for m, lk in adj.get(n, ()):
            if m not in prev and (m == goal or m in through):
                prev[m] = (n, lk)
                queue.append(m)
    return None


def _ends(lk: Any) -> str:
    return f"{lk.a}–{lk.b}"


def nesting(a: Network, b: Network) -> Nesting:
    """Whether network ``b`` is network ``a`` plus elements (the rule in the module docstring)."""
    na, nb = a.name, b.name
    reasons: list[str] = []
    unsure: list[str] = []
    added: list[str] = []
    how: list[str] = []

    # learned functions: the same in both, else undecided
    la, lb = {f.name: f for f in a.learned}, {f.name: f for f in b.learned}
    for name, f in la.items():
        if name not in lb:
            reasons.append(f"learned function {name} of {na} is missing in {nb}")
        elif _plain(f) != _plain(lb[name]):
            unsure.append(f"learned function {name} differs between {na} and {nb}")
    for name in lb:
        if name not in la:
            unsure.append(f"{nb} adds learned function {name}: whether it reduces to {na} cannot be read from the "
                          "networks")

    # inputs
    ib = {i.name: i for i in b.inputs}
    for i in a.inputs:
        j = ib.get(i.name)
        if j is None:
            reasons.append(f"input {i.name} of {na} is missing in {nb}")
        elif j.column != i.column or j.dim != i.dim or j.is_temperature != i.is_temperature:
            reasons.append(f"input {i.name} reads column {i.column!r} in {na} but {j.column!r} in {nb}")
    added += [f"input {i.name}" for i in b.inputs if i.name not in {x.name for x in a.inputs}]

    # sensors: the same data
    sb = {s.name: s for s in b.sensors}
    for s in a.sensors:
        t = sb.get(s.name)
        if t is None:
            reasons.append(f"sensor {s.name} of {na} is missing in {nb}: the likelihoods are over different data")
            continue
        if t.node != s.node or t.column != s.column:
            reasons.append(f"sensor {s.name} reads node {s.node} (column {s.column!r}) in {na} but node {t.node} "
                           f"(column {t.column!r}) in {nb}")
        for what in ("lag", "offset"):
            if getattr(s, what) and not getattr(t, what):
                reasons.append(f"sensor {s.name} has a {what} in {na} but not in {nb}")
            elif getattr(t, what) and not getattr(s, what):
                added.append(f"sensor {what} of {s.name}")
    for s in b.sensors:
        if s.name not in {x.name for x in a.sensors}:
            reasons.append(f"{nb} adds sensor {s.name}: the likelihoods are over different data")

    # nodes and boundaries
    a_nodes, b_nodes = set(a.node_names), set(b.node_names)
    for n in a.node_names:
        if n not in b_nodes:
            what = "a boundary" if n in b.boundary_names else "missing"
            reasons.append(f"node {n} of {na} is {what} in {nb}")
    for n in a.boundary_names:
        if n not in b.boundary_names:
            what = "a node" if n in b_nodes else "missing"
            reasons.append(f"boundary {n} of {na} is {what} in {nb}")
    new_nodes = b_nodes - a_nodes - set(a.boundary_names)
    added += [f"node {n}" for n in b.node_names if n in new_nodes]
    added += [f"boundary {n}" for n in b.boundary_names if n not in a.boundary_names and n not in a_nodes]

    # links: same ends by name, else by ends, else split in series through B's new nodes
    param_map: dict[str, str | None] = {}  # A's link parameter -> B's (None: split, not compared)
    free_b = list(b.links)
    pending = []
    for lk in a.links:
        same = [m for m in free_b if m.name == lk.name and {m.a, m.b} == {lk.a, lk.b}]
        if same:
            free_b.remove(same[0])
            param_map[lk.value] = same[0].value
            if same[0].form != lk.form:
                how.append(f"link {lk.name} is given as {lk.form} in {na} and as {same[0].form} in {nb} (R = 1/G)")
        else:
            pending.append(lk)
    for lk in list(pending):
        other = [m for m in free_b if {m.a, m.b} == {lk.a, lk.b}]
        if other:
            free_b.remove(other[0])
            pending.remove(lk)
            param_map[lk.value] = other[0].value
            how.append(f"link {lk.name} of {na} ({_ends(lk)}) is link {other[0].name} in {nb}")
    for lk in pending:
        path = _path(lk.a, lk.b, new_nodes, free_b)
        if path:
            for m in path:
                free_b.remove(m)
            mids = [n for m in path for n in (m.a, m.b) if n in new_nodes]
            mids = list(dict.fromkeys(mids))
            param_map[lk.value] = None
            how.append(f"link {lk.name} of {na} ({_ends(lk)}) is split in series in {nb} through {', '.join(mids)} "
                       f"({' + '.join(m.name for m in path)}): with the capacitance of {', '.join(mids)} → 0 it is "
                       "one resistance, the sum")
        else:
            moved = [m for m in b.links if m.name == lk.name]
            where = f" ({nb}'s {lk.name} joins {_ends(moved[0])})" if moved else ""
            reasons.append(f"link {lk.name} of {na} ({_ends(lk)}) is missing in {nb}{where}")
    added += [f"link {m.name} ({_ends(m)})" for m in free_b]

    # other elements: unchanged
    for kind, la_, lb_ in (("radiation", a.radiations, b.radiations), ("peltier", a.peltiers, b.peltiers),
                           ("fluid", a.fluids, b.fluids)):
        by = {e.name: e for e in lb_}
        for e in la_:
            if e.name not in by:
                reasons.append(f"{kind} {e.name} of {na} is missing in {nb}")
            elif _plain(e) != _plain(by[e.name]):
                reasons.append(f"{kind} {e.name} differs between {na} and {nb}")
        names_a = {e.name for e in la_}
        added += [f"{kind} {e.name}" for e in lb_ if e.name not in names_a]

    # sources: by name, else by value; the same node, or moved to a new node joined to the old one
    src_b = list(b.sources)
    for s in a.sources:
        cand = [t for t in src_b if t.name == s.name]
        if not cand and s.value in {p.name for p in a.params}:
            expr = _plain(a.param(s.value).expr)
            cand = [t for t in src_b if t.value in b.param_names and _plain(b.param(t.value).expr) == expr]
        if not cand:
            reasons.append(f"source {s.name} of {na} (into {s.node}) is missing in {nb}")
            continue
        t = cand[0]
        src_b.remove(t)
        param_map.setdefault(s.value, t.value)
        if t.name != s.name:
            how.append(f"source {s.name} of {na} is source {t.name} in {nb}")
        if t.node == s.node:
            continue
        path = _path(t.node, s.node, new_nodes, b.links) if t.node in new_nodes else None
        if path:
            via = " + ".join(m.name for m in path)
            how.append(f"source {s.name} heats {s.node} in {na} but {t.node} in {nb}, a node only {nb} has, joined to "
                       f"{s.node} through {via}: with {via} → 0 and the capacitance of {t.node} → 0 the heat goes "
                       f"into {s.node}")
        else:
            reasons.append(f"source {s.name} heats {s.node} in {na} but {t.node} in {nb}"
                           + (f", not joined to {s.node} through nodes only {nb} has" if t.node in new_nodes
                              else ""))
    added += [f"source {t.name} (into {t.node})" for t in src_b]

    # parameters
    pb = {p.name: p for p in b.params}
    used_b: set[str] = set()
    for p in a.params:
        target = param_map.get(p.name, p.name)
        if target is None:  # a split link's resistance
            continue
        q = pb.get(target)
        if q is None:
            reasons.append(f"parameter {p.name} of {na} is missing in {nb}")
            continue
        used_b.add(target)
        label = p.name if target == p.name else f"{p.name} ({nb}'s {target})"
        if p.per_experiment != q.per_experiment:
            reasons.append(f"parameter {label} is per experiment in only one of {na} and {nb}")
        elif p.is_constant and q.is_constant:
            if p.free and not q.free:
                reasons.append(f"parameter {label} is free in {na} but fixed in {nb}")
            elif not p.free and q.free:
                added.append(f"parameter {label} freed")
            elif not p.free and not math.isclose(p.value, q.value, rel_tol=1e-12, abs_tol=0.0):
                reasons.append(f"parameter {label} is fixed at {p.value:.6g} in {na} but {q.value:.6g} in {nb} (SI)")
        elif p.is_constant != q.is_constant:
            if p.is_constant and not p.free:
                unsure.append(f"parameter {label} is a constant in {na} but an expression in {nb}")
            else:
                reasons.append(f"parameter {label} is {'a constant' if p.is_constant else 'an expression'} in {na} "
                               f"but {'a constant' if q.is_constant else 'an expression'} in {nb}")
        elif _plain(p.expr) != _plain(q.expr):
            reasons.append(f"parameter {label} is defined differently in {na} and {nb}")
    a_names = set(a.param_names)
    added += [f"parameter {q.name}" for q in b.params
              if q.free and q.name not in used_b and q.name not in a_names]

    if reasons:
        return Nesting(False, added, how, reasons + unsure, a.name, b.name)
    if unsure:
        return Nesting(None, added, how, unsure, a.name, b.name)
    if not added:
        return Nesting(False, added, how, [f"{nb} adds nothing to {na}: they are the same model"], a.name, b.name)
    return Nesting(True, added, how, [], a.name, b.name)


# ---------------------------------------------------------------------------------------------
# Fitting both and comparing
# ---------------------------------------------------------------------------------------------


@dataclass
class ModelFit:
    """One of the two models after its fit: the likelihood (``loglik``, ``k`` quantities estimated, ``n_obs``
    readings, AIC, BIC; ``None`` where the fit gave no likelihood), the free-run MAE (K) and the one-step-ahead RMS
    (K) on ``scored_on`` (``validation`` or ``training``), per sensor too, and the trained model (``trained``, not in
    :meth:`to_dict`)."""

    label: str
    network: str
    file: str | None
    loglik: float | None
    k: int | None
    n_obs: int | None
    aic: float | None
    bic: float | None
    converged: bool | None
    free_run_mae: float
    free_run_mae_sensors: dict[str, float]
    one_step_rms: float | None
    one_step_rms_sensors: dict[str, float]
    scored_on: str
    train_seconds: float
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    estimation_notes: list[str] = field(default_factory=list)
    """The fit's own notes (convergence, estimates without a standard error); in :meth:`to_dict`, not the table."""
    trained: Any = None
    one_step_loglik_rows: Any = None
    """``(n_scored,)`` the Gaussian log-likelihood of each scored sample's innovations (summed over its sensors; NaN
    where nothing was read), in the order of the scored files and rows; not in :meth:`to_dict`."""

    def to_dict(self) -> dict[str, Any]:
        return _clean({"label": self.label, "network": self.network, "file": self.file, "loglik": self.loglik,
                       "k": self.k, "n_obs": self.n_obs, "aic": self.aic, "bic": self.bic,
                       "converged": self.converged, "free_run_mae": self.free_run_mae,
                       "free_run_mae_sensors": self.free_run_mae_sensors, "one_step_rms": self.one_step_rms,
                       "one_step_rms_sensors": self.one_step_rms_sensors, "scored_on": self.scored_on,
                       "train_seconds": self.train_seconds, "notes": list(self.notes),
                       "warnings": list(self.warnings), "estimation_notes": list(self.estimation_notes)})


def _clean(v: Any) -> Any:
    """JSON-ready: NaN and ±inf as ``None``, numpy scalars as Python numbers."""
    if isinstance(v, dict):
        return {str(k): _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


def _fmt_p(p: float | None) -> str:
    if p is None or not math.isfinite(p):
        return "p —"
    if p < _P_FLOOR:
        return f"p < {_P_FLOOR:.0e}"
    return f"p = {p:.3g}"


@dataclass
class Comparison:
    """Two networks fitted to the same data (:func:`compare_models`).

    ``lr`` is ``2(log L_larger − log L_smaller)`` with ``df = k_larger − k_smaller`` and ``p = P(χ²_df > lr)``;
    ``larger`` says which model is the extension (``"B"``, or ``"A"`` when A extends B); ``lr_test`` is
    ``"nested"``, ``"undecided"`` (nesting could not be read from the networks: the test assumes B extends A) or
    ``"withheld"`` (not nested, or no likelihood: ``lr``, ``df`` and ``p`` are ``None``). ``verdict`` is one line;
    ``notes`` say what the numbers rest on."""

    a: ModelFit
    b: ModelFit
    nesting: Nesting
    objective: str
    backend: str
    held_out: bool
    lr: float | None
    df: int | None
    p: float | None
    larger: str | None
    lr_test: str
    verdict: str
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN as ``None``)."""
        return _clean({"objective": self.objective, "backend": self.backend, "held_out": self.held_out,
                       "a": self.a.to_dict(), "b": self.b.to_dict(), "nesting": self.nesting.to_dict(),
                       "lr": self.lr, "df": self.df, "p": self.p, "larger": self.larger, "lr_test": self.lr_test,
                       "alpha": ALPHA, "verdict": self.verdict, "notes": list(self.notes)})

    def _rows(self) -> list[tuple[str, Any, Any]]:
        on = "validation" if self.held_out else "training, no held-out data"
        return [
            ("log L", self.a.loglik, self.b.loglik),
            ("k (estimated)", self.a.k, self.b.k),
            ("n (readings)", self.a.n_obs, self.b.n_obs),
            ("AIC", self.a.aic, self.b.aic),
            ("BIC", self.a.bic, self.b.bic),
            (f"free-run MAE, K ({on})", self.a.free_run_mae, self.b.free_run_mae),
            (f"one-step RMS, K ({'validation' if self.held_out else 'training'})", self.a.one_step_rms,
             self.b.one_step_rms),
            ("fit converged", self.a.converged, self.b.converged),
            ("fit time, s", self.a.train_seconds, self.b.train_seconds),
        ]

    def summary(self) -> str:
        """The text table: both fits, the test, the verdict and the notes."""
        def f(v: Any) -> str:
            if v is None:
                return "—"
            if isinstance(v, bool):
                return "yes" if v else "NO"
            if isinstance(v, int):
                return str(v)
            if not math.isfinite(v):
                return "—"
            return f"{v:.2f}" if abs(v) >= 100 else f"{v:.4g}"

        what = "maximum likelihood (Kalman filter)" if self.objective == "ml" else "output error (free run)"
        lines = [f"A: {self.a.network}" + (f"  ({self.a.file})" if self.a.file else ""),
                 f"B: {self.b.network}" + (f"  ({self.b.file})" if self.b.file else ""),
                 f"objective: {what}; backend {self.backend}", "", "nesting: " + self.nesting.summary(), ""]
        rows = self._rows()
        w = max(len(r[0]) for r in rows)
        wa = max(14, len(self.a.network))
        wb = max(14, len(self.b.network))
        lines.append(f"{'':<{w}}  {'A ' + self.a.network:>{wa + 2}}  {'B ' + self.b.network:>{wb + 2}}")
        for name, va, vb in rows:
            lines.append(f"{name:<{w}}  {f(va):>{wa + 2}}  {f(vb):>{wb + 2}}")
        lines.append("")
        if self.lr is not None:
            big, small = ("B", "A") if self.larger == "B" else ("A", "B")
            lines.append(f"likelihood ratio: LR = 2(log L_{big} − log L_{small}) = {self.lr:.2f} on {self.df} df, "
                         f"{_fmt_p(self.p)}")
        else:
            lines.append("likelihood ratio: withheld")
        lines.append(f"verdict: {self.verdict}")
        lines += [f"note: {n}" for n in self.notes]
        for m in (self.a, self.b):
            lines += [f"note ({m.label}): {n}" for n in m.notes]
            lines += [f"warning ({m.label}): {n}" for n in m.warnings]
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.summary()

    def _repr_html_(self) -> str:
        return safe_repr_html(self._html, self.summary, f"Comparison({self.a.network!r}, {self.b.network!r})")

    def _html(self) -> str:
        rows = [[name, va, vb] for name, va, vb in self._rows()]
        table = html_table(["", f"A: {self.a.network}", f"B: {self.b.network}"], rows,
                           numeric=[False, True, True], digits=7)
        test = (f"LR = {self.lr:.2f} on {self.df} df, {_fmt_p(self.p)}" if self.lr is not None
                else "likelihood ratio: withheld")
        return view(f"comparison: {self.a.network} vs {self.b.network}", pre(self.nesting.summary()), table,
                    pre(test + "\nverdict: " + self.verdict),
                    html_list(self.notes + [f"{m.label}: {n}" for m in (self.a, self.b) for n in m.notes + m.warnings]))


def _experiments(net: Network, data: Any, read: dict[str, Any]) -> list[Any]:
    """Paths read for ``net`` (with ``read``'s time options) and/or Experiments whose columns are ``net``'s."""
    from ..data.reading import as_experiments

    return as_experiments(net, data, same_columns=True, **read)


def _noise_levels(tm: Any, est: dict[str, Any] | None, model: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """``(log σ_w per state, log σ_v per sensor)`` from an ``ml`` fit's rows, or ``None``."""
    if not est:
        return None
    by = {r["name"]: r["estimate"] for r in est.get("rows") or []}
    try:
        sw = [by[f"sigma_w[{s}]"] for s in model.state_names]
        sv = [by[f"sigma_v[{s}]"] for s in model.output_names]
    except KeyError:
        return None
    tiny = 1e-300  # a level estimated at exactly 0 (underflow): its log stays finite
    return np.log(np.maximum(np.asarray(sw, dtype=float), tiny)), np.log(np.maximum(np.asarray(sv, dtype=float), tiny))


def _start(pred: dict[str, Any]) -> tuple[int, np.ndarray]:
    """Where a free run starts: the first sample with a state, and that state."""
    S = np.asarray(pred["states"], dtype=float)
    ok = np.flatnonzero(np.all(np.isfinite(S), axis=1))
    k0 = int(ok[0]) if ok.size else 0
    return k0, S[k0]


def _one_step(tm: Any, objective: str, backend: str, train_exps: list, scored: list,
              notes: list[str]) -> tuple[float | None, dict[str, float], np.ndarray | None]:
    """The one-step-ahead RMS (K) of the Kalman filter over ``scored`` (each from its free run's initial state,
    after its burn-in), with the ``ml`` fit's noise levels or, for an output-error fit, noise levels fitted to the
    training data with the parameters held: ``(RMS, per sensor, per-sample log-likelihood (n,) or None)``."""
    from ..estimation import fit_ml, innovations

    model = tm.compiled(backend)
    params = tm.backend_params(backend)
    cfg = tm.meta.get("config") or {}
    integ, sub = cfg.get("integrator", "rk4"), cfg.get("substeps")
    levels = _noise_levels(tm, tm.meta.get("estimation"), model) if objective == "ml" else None
    if levels is None:
        recs, x0s = [], []
        for e, pred in zip(train_exps, tm.predict(train_exps, backend=backend)):
            k0, T0 = _start(pred)
            recs.append(SimpleNamespace(name=e.name, inputs=np.asarray(e.inputs, float)[k0:],
                                        outputs=np.asarray(e.outputs, float)[k0:], dt=float(e.dt)))
            x0s.append(T0)
        try:
            est = fit_ml(model, recs, backend=backend, free=[], params=params, x0=x0s, integrator=integ,
                         substeps=sub)
        except (TnnError, FloatingPointError, np.linalg.LinAlgError, ValueError) as err:
            notes.append(f"no one-step RMS: the noise levels could not be fitted ({err})")
            return None, {}, None
        levels = _noise_levels(tm, {"rows": est.rows}, model)
        if levels is None:
            notes.append("no one-step RMS: the noise-level fit gave no σ_w/σ_v")
            return None, {}, None
        if objective != "ml":
            notes.append("one-step RMS: Kalman filter with noise levels fitted to the training data, the parameters "
                         "held at the output-error fit")
    errs: list[np.ndarray] = []
    lls: list[np.ndarray] = []
    for e, pred in zip(scored, tm.predict(scored, backend=backend)):
        k0, T0 = _start(pred)
        inn = innovations(model, params, np.asarray(e.inputs, float)[k0:], np.asarray(e.outputs, float)[k0:],
                          float(e.dt), log_sigma_w=levels[0], log_sigma_v=levels[1], x0=T0, integrator=integ,
                          substeps=sub)
        skip = max(0, int(pred.get("burn_in", 0)) - k0)
        errs.append(inn.innovations[skip:])
        lls.append(np.concatenate([np.full(k0 + skip, np.nan), inn.loglik_rows[skip:]]))
    E = np.concatenate(errs) if errs else np.zeros((0, len(model.output_names)))
    per = {}
    for j, s in enumerate(model.output_names):
        v = E[:, j][np.isfinite(E[:, j])]
        per[s] = float(np.sqrt(np.mean(v**2))) if v.size else math.nan
    allv = E[np.isfinite(E)]
    return (float(np.sqrt(np.mean(allv**2))) if allv.size else math.nan), per, (np.concatenate(lls) if lls else None)


def fit_and_score(label: str, net: Network, exps: list, vals: list, objective: str,
                  options: dict[str, Any], log: Callable[[str], None] | None, *, val_in_training: bool = True
                  ) -> ModelFit:
    """Train ``net`` on ``exps`` (:func:`tnn_dsl.fit.train` with ``objective`` and ``options``; ``vals`` its
    validation data unless ``val_in_training`` is false: then nothing of ``vals`` is seen before scoring) and score
    it on ``vals`` (else on ``exps``): a :class:`ModelFit`."""
    import time

    from ..fit import train

    t0 = time.perf_counter()
    tm = train(net, exps, (vals or None) if val_in_training else None, objective=objective, log=log, **options)
    seconds = time.perf_counter() - t0
    backend = tm.backend
    est = tm.meta.get("estimation")
    scored = vals or exps
    metrics = tm.evaluate(scored, backend=backend)
    notes: list[str] = []
    rms, rms_s, ll_rows = _one_step(tm, objective, backend, exps, scored, notes)
    warnings = list(tm.meta.get("warnings") or [])
    if est is None:
        warnings.append("no likelihood: the fit gave no estimates")
    get = (est or {}).get
    return ModelFit(label=label, network=net.name, file=(net.source_files[0] if net.source_files else None),
                    loglik=get("loglik"), k=get("n_params"), n_obs=get("n_obs"), aic=get("aic"), bic=get("bic"),
                    converged=get("converged"), free_run_mae=float(metrics.get("mae", math.nan)),
                    free_run_mae_sensors={s: float(v.get("mae", math.nan))
                                          for s, v in (metrics.get("sensors") or {}).items()},
                    one_step_rms=rms, one_step_rms_sensors=rms_s, scored_on="validation" if vals else "training",
                    train_seconds=seconds, notes=notes, warnings=warnings,
                    estimation_notes=list((est or {}).get("notes") or []), trained=tm, one_step_loglik_rows=ll_rows)


def _net(x: Network | str | os.PathLike) -> Network:
    if isinstance(x, Network):
        return x
    from ..lang import load

    return load(x)


def compare_models(a: Network | str | os.PathLike, b: Network | str | os.PathLike, data: Any, *, val: Any = None,
                   objective: str = "ml", time_col: str | None = None, dt: float | None = None,
                   time_unit: str | None = None, log: Callable[[str], None] | None = None,
                   **train_options: Any) -> Comparison:
    """Fit networks ``a`` and ``b`` to the same ``data`` and compare them (module docstring).

    Parameters
    ----------
    a, b : networks or ``.thn`` paths; the test asks whether ``b`` extends ``a`` (or ``a`` extends ``b``)
    data : training data: paths (read for each network with ``time_col``, ``dt``, ``time_unit``) or
        ``Experiment``s read for networks with these inputs and sensors
    val : held-out data (likewise); the free-run MAE and the one-step RMS are scored on it, else on the training
        data (and the summary says there was no held-out data)
    objective : ``"ml"`` (default: the Kalman-filter likelihood) or ``"output-error"`` (the free run's; the test is
        then only indicative)
    log : ``f(message)`` for progress, notes and warnings (default silent)
    train_options : further options of :func:`tnn_dsl.fit.train` (``backend``, ``epochs``, ``seed`` ...), the same
        for both fits; ``val_fraction`` (without ``val``) holds out the end of each file for both

    Returns a :class:`Comparison`.
    """
    from scipy.stats import chi2

    if objective not in OBJECTIVES:
        raise TnnError(Diagnostic(f"unknown objective {objective!r}", hint=f"use one of: {', '.join(OBJECTIVES)}"))
    net_a, net_b = _net(a), _net(b)
    read = {"time_col": time_col, "dt": dt, "time_unit": time_unit}
    options = dict(train_options)
    frac = float(options.pop("val_fraction", 0.0) or 0.0)
    fits = []
    for label, net in (("A", net_a), ("B", net_b)):
        exps, vals = _experiments(net, data, read), _experiments(net, val, read)
        if not exps:
            raise TnnError(Diagnostic("no training data given", hint="pass at least one CSV or Parquet file"))
        if frac > 0 and not vals:
            from ..data import split_by_time

            parts = [split_by_time(e, 1.0 - frac) for e in exps]
            exps, vals = [p for p, _ in parts], [q for _, q in parts]
        if log is not None:
            log(f"fitting {label}: {net.name} ({objective}) ...")
        fits.append(fit_and_score(label, net, exps, vals, objective, options, log))
    fa, fb = fits
    nest = nesting(net_a, net_b)
    notes: list[str] = []
    larger: str | None = None
    lr_test = "withheld"
    if nest.nested:
        larger, lr_test = "B", "nested"
    else:
        rev = nesting(net_b, net_a)
        if rev.nested:
            larger, lr_test, nest = "A", "nested", rev
            notes.append("A extends B (the networks were given the other way round): the test runs from B to A")
        elif nest.nested is None:
            larger, lr_test = "B", "undecided"
            notes.append("whether B extends A cannot be read from the networks: the likelihood-ratio test below "
                         "assumes it does")
    structural = larger is not None
    have = fa.loglik is not None and fb.loglik is not None and fa.k is not None and fb.k is not None
    if larger and not have:
        notes.append("the likelihood-ratio test is withheld: "
                     + " and ".join(f"{m.label} has no likelihood" for m in (fa, fb) if m.loglik is None))
        larger, lr_test = None, "withheld"
    if larger and fa.n_obs != fb.n_obs:
        notes.append(f"the likelihood-ratio test is withheld: the fits count {fa.n_obs} and {fb.n_obs} readings")
        larger, lr_test = None, "withheld"
    lr = df = p = None
    big, small = (fb, fa) if larger == "B" else (fa, fb)
    if larger:
        lr = 2.0 * (float(big.loglik) - float(small.loglik))
        df = int(big.k) - int(small.k)
        if df <= 0:
            notes.append(f"the likelihood-ratio test is withheld: the larger model estimates {df:+d} quantities "
                         "more than the smaller one")
            lr = df = None
            larger, lr_test = None, "withheld"
        else:
            p = float(chi2.sf(lr, df)) if lr > 0 else 1.0
            if lr < 0:
                notes.append(f"the larger model {big.label} has the lower likelihood: its fit stopped short of the "
                             f"optimum (it contains {small.label}'s); refit it from other starting values")
    verdict = _verdict(fa, fb, structural, lr, df, p, larger, lr_test)
    if objective == "output-error":
        notes.append("objective output-error: log L is the Gaussian likelihood of the free-run residuals, which are "
                     "not white; the likelihood-ratio test and AIC/BIC are only indicative (use --objective ml)")
    elif lr_test == "nested":
        notes.append("the reduced model is a limit at the edge of the larger one's parameter ranges (a capacitance "
                     "or resistance → 0, a resistance → ∞): the χ² reference is the usual approximation")
    for m in (fa, fb):
        if m.converged is False:
            notes.append(f"the fit of {m.label} ({m.network}) did not converge: its log L may be too low")
    held_out = fa.scored_on == "validation"
    if not held_out:
        notes.append("no held-out data: the free-run MAE and one-step RMS are on the training data")
    backend = fa.trained.backend if fa.trained is not None else str(options.get("backend") or "jax")
    return Comparison(a=fa, b=fb, nesting=nest, objective=objective, backend=backend, held_out=held_out, lr=lr,
                      df=df, p=p, larger=larger, lr_test=lr_test, verdict=verdict, notes=notes)


def _verdict(fa: ModelFit, fb: ModelFit, structural: bool, lr: float | None, df: int | None, p: float | None,
             larger: str | None, lr_test: str) -> str:
    ics = []
    for what in ("aic", "bic"):
        va, vb = getattr(fa, what), getattr(fb, what)
        if va is not None and vb is not None:
            best = fa if va < vb else fb
            ics.append(f"{what.upper()} prefers {best.label} ({best.network}) by {abs(va - vb):.1f}")
    tail = ("; " + ", ".join(ics)) if ics else ""
    if lr is None or p is None or df is None or larger is None:
        if not structural:
            head = "not nested: the LR test does not apply; AIC/BIC only"
        else:
            head = "no likelihood-ratio test; AIC/BIC only"
        return head + tail if ics else head + " (no likelihoods)"
    big, small = (fb, fa) if larger == "B" else (fa, fb)
    stat = f"LR {lr:.1f} on {df} df, {_fmt_p(p)}"
    if p < ALPHA:
        head = f"{big.label} ({big.network}) is better: {stat}"
    else:
        head = (f"{big.label} ({big.network}) is not significantly better than {small.label} ({small.network}) "
                f"at {ALPHA * 100:g} %: {stat}")
    if lr_test == "undecided":
        head += " (if B extends A)"
    return head + tail
