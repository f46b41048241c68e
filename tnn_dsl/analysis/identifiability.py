"""Identifiability from trajectory sensitivities: the Fisher information of relative parameters, standard
errors, correlated pairs explained in the network's terms, weak directions."""

from __future__ import annotations

import html
import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from ..core import Diagnostic, TnnError, to_jsonable
from ..core.htmlview import html_list, html_table
from ..ir import Network
from .common import _pct

__all__ = ["fisher_analysis", "Identifiability", "CorrelatedPair", "WeakDirection", "CORR_LIMIT", "RESOLUTION"]

CORR_LIMIT = 0.95
"""Estimate correlations above this (in absolute value) are flagged as not separately identifiable."""


RESOLUTION = 1e-9
"""K per unit α: steady sensitivities below this are the steady-state solver's round-off (its Newton
tolerance is 1e-10 K) and are reported as exactly 0 — e.g. capacities, which do not enter the steady state."""


class _Record:
    """A plain result record: its fields as JSON-ready values (``inf`` as text)."""

    def to_dict(self) -> dict:
        return to_jsonable(self.__dict__, inf_as_text=True)


@dataclass
class WeakDirection(_Record):
    """A combination of relative parameter changes the data hardly see: an eigenvector of the Fisher
    information with standard error ``std_error`` (relative, 1/sqrt(eigenvalue)). ``weights`` are the
    relative changes (largest |w| = 1), only those with |w| ≥ 0.05."""

    weights: dict[str, float]
    eigenvalue: float
    std_error: float
    description: str


@dataclass
class CorrelatedPair(_Record):
    """Two parameters whose estimates correlate with ``|correlation| > 0.95``.

    ``direct``: the pair by itself cannot be separated — their sensitivities are almost proportional
    (``|cos| ≥ 0.95``) or the network's structure says why (series through an unmeasured node, parallel
    paths, ``ṁ``/``cp`` of one fluid, one Peltier element); then ``combination`` names what the data do
    determine and ``combination_std_error`` is its relative standard error with the other parameter of the
    pair held fixed. Otherwise (``direct`` false) the correlation comes through the other free parameters
    (typically a weak direction involving a third one) and each may still be well determined."""

    a: str
    b: str
    correlation: float
    cos: float
    direct: bool
    explanation: str
    combination: str
    combination_std_error: float


@dataclass
class Identifiability:
    """Fisher-information analysis of the parameters ``params`` in relative units (``α``).

    ``fisher`` (P, P) per (unit α)²; ``std_errors`` (P,) relative (fraction of the nominal value, ``inf``
    when not identifiable at all); ``abs_std_errors`` (P,) SI (NaN where the nominal is not a constant);
    ``correlation`` (P, P) of the estimates; ``eigenvalues`` ascending with ``eigenvectors`` as columns;
    ``sigma`` the noise level (K) and ``n_samples`` the number of sensor readings used; ``alone_std_errors``
    (P,) the relative standard error of each parameter when it is the only one estimated (``σ/‖s_i‖``, the
    best case)."""

    params: list[str]
    sigma: float
    n_samples: int
    fisher: np.ndarray
    std_errors: np.ndarray
    abs_std_errors: np.ndarray
    correlation: np.ndarray
    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    weak: list[WeakDirection]
    pairs: list[CorrelatedPair]
    max_se: float
    alone_std_errors: np.ndarray | None = None

    @property
    def condition(self) -> float:
        lo, hi = float(self.eigenvalues[0]), float(self.eigenvalues[-1])
        return hi / lo if lo > 0 else math.inf

    def identifiable(self, name: str) -> bool:
        i = self.params.index(name)
        paired = any(name in (p.a, p.b) for p in self.pairs if p.direct)
        return bool(self.std_errors[i] <= self.max_se and not paired)

    def to_dict(self) -> dict:
        return to_jsonable({
            "params": self.params, "sigma": self.sigma, "n_samples": self.n_samples,
            "std_errors": dict(zip(self.params, self.std_errors)),
            "abs_std_errors": dict(zip(self.params, self.abs_std_errors)),
            "alone_std_errors": dict(zip(self.params, self.alone_std_errors if self.alone_std_errors is not None
                                         else [math.nan] * len(self.params))),
            "identifiable": {p: self.identifiable(p) for p in self.params},
            "correlation": self.correlation, "fisher": self.fisher, "eigenvalues": self.eigenvalues,
            "eigenvectors": self.eigenvectors, "condition": self.condition, "max_se": self.max_se,
            "weak_directions": [w.to_dict() for w in self.weak], "correlated_pairs": [p.to_dict() for p in self.pairs],
        }, inf_as_text=True)

    def rows(self) -> list[dict[str, Any]]:
        """The verdict per parameter, best determined first (what :meth:`table` and the notebook view show):
        ``name``, ``std_error`` and ``alone_std_error`` (relative), ``identifiable``, ``verdict`` (text)."""
        alone = self.alone_std_errors if self.alone_std_errors is not None else np.full(len(self.params), np.nan)
        return [{"name": self.params[i], "std_error": float(self.std_errors[i]), "alone_std_error": float(alone[i]),
                 "identifiable": self.identifiable(self.params[i]),
                 "verdict": "ok" if self.identifiable(self.params[i]) else "NOT separately identifiable"}
                for i in np.lexsort((alone, self.std_errors))]

    def _title(self) -> str:
        return (f"Identifiability (Fisher information, σ = {self.sigma:g} K, {self.n_samples} readings; "
                f"standard errors relative to the nominal value, all {len(self.params)} estimated together / alone)")

    def html(self, max_lines: int = 8) -> str:
        """:meth:`table` as an HTML fragment (escaped): the verdicts as a table, then the correlated pairs and
        weak directions as a list."""
        rows = [[r["name"], "±" + _pct(r["std_error"]), "±" + _pct(r["alone_std_error"]), r["verdict"]]
                for r in self.rows()]
        tab = html_table(["parameter", "std. error (together)", "alone", "verdict"], rows,
                         numeric=[False, True, True, False])
        lines = self.table(max_lines).splitlines()[1 + len(rows):]
        return f"<b>{html.escape(self._title())}</b>" + tab + html_list(s.strip() for s in lines)

    def table(self, max_lines: int = 8) -> str:
        lines = [self._title()]
        for r in self.rows():
            lines.append(f"  {r['name']:<24} ±{_pct(r['std_error']):>10}  alone ±{_pct(r['alone_std_error']):>10}   "
                         f"{r['verdict']}")
        direct = [pr for pr in self.pairs if pr.direct]
        for pr in direct[:max_lines]:
            lines.append(f"  corr({pr.a}, {pr.b}) = {pr.correlation:+.3f}: {pr.explanation}")
            if math.isfinite(pr.combination_std_error):
                lines.append(f"      the data determine {pr.combination} to ±{_pct(pr.combination_std_error)}")
        if len(direct) > max_lines:
            lines.append(f"  … and {len(direct) - max_lines} more pairs that cannot be separated (see --json)")
        indirect = [pr for pr in self.pairs if not pr.direct]
        if indirect:
            shown = ", ".join(f"({pr.a}, {pr.b}) {pr.correlation:+.3f}" for pr in indirect[:max_lines])
            more = f" … and {len(indirect) - max_lines} more" if len(indirect) > max_lines else ""
            lines.append("  correlated only through the other free parameters (each may still be well determined): "
                         + shown + more)
        for w in self.weak[:max_lines]:
            lines.append(f"  weak direction (±{_pct(w.std_error)}): {w.description}")
        if len(self.weak) > max_lines:
            lines.append(f"  … and {len(self.weak) - max_lines} more weak directions (see --json)")
        return "\n".join(lines)


def _structure(net: Network | None) -> dict[str, Any]:
    """Maps from parameter names to the elements that use them (for plain-words explanations)."""
    info: dict[str, Any] = {"link": {}, "cap": {}, "fluid": {}, "peltier": {}, "sensor_nodes": set(),
                            "graph": None, "source_nodes": set(), "heat_load_nodes": set(), "nominal": {}}
    if net is None:
        return info
    for link in net.links:
        info["link"][link.value] = link
    for n in net.nodes:
        info["cap"][n.capacitance] = n
    for f in net.fluids:
        for slot in ("mdot", "cp", "ua", "inlet"):
            info["fluid"][getattr(f, slot)] = (f, slot)
    for pe in net.peltiers:
        for slot in ("current", "seebeck", "resistance", "r_internal"):
            v = getattr(pe, slot)
            if v:
                info["peltier"][v] = (pe, slot)
    info["sensor_nodes"] = {s.node for s in net.sensors}
    info["source_nodes"] = {s.node for s in net.sources}
    info["heat_load_nodes"] = {t.name for fn in net.learned for t in fn.targets if t.kind == "heat_load"}
    try:
        info["graph"] = net.graph()
    except Exception:  # noqa: BLE001 - explanations are optional
        info["graph"] = None
    info["nominal"] = {p.name: p.value for p in net.params}
    return info


def _resistance_value(link, nominal: Mapping[str, float | None]) -> float | None:
    v = nominal.get(link.value)
    if v is None or v == 0:
        return None
    return v if link.form == "R" else 1.0 / v


def _explain_pair(a: str, b: str, info: dict[str, Any], cos: float) -> tuple[str, str, bool]:
    """A plain-words reason why ``a`` and ``b`` cannot be separated, what the data do determine, and
    whether the reason is structural (the network says the pair acts as one)."""
    links, caps, fluids, pelts = info["link"], info["cap"], info["fluid"], info["peltier"]
    g = info.get("graph")
    if a in links and b in links:
        la, lb = links[a], links[b]
        ends_a, ends_b = {la.a, la.b}, {lb.a, lb.b}
        if ends_a == ends_b:
            return (f"{a} and {b} connect the same two nodes ({la.a}, {la.b}) in parallel: the data see only "
                    f"their combined conductance", f"the parallel combination of {a} and {b}", True)
        shared = ends_a & ends_b
        for m in shared:
            is_node = g is not None and g.nodes.get(m, {}).get("kind") == "node"
            if not is_node:
                continue
            only_two = g.degree(m) == 2 and m not in info["source_nodes"] and m not in info["heat_load_nodes"]
            if m not in info["sensor_nodes"] and only_two:
                what = "sum" if la.form == lb.form == "R" else "series resistance"
                cap = next((c for c, n in caps.items() if n.name == m), None)
                tail = f" (node {m}'s own capacity {cap} is too small to show in the data)" if cap else ""
                return (f"{a} and {b} act only through their {what}: they are in series through node {m} "
                        f"and no sensor sits between them{tail}", f"{a} + {b}" if what == "sum"
                        else f"the series resistance of {a} and {b}", True)
    if a in fluids and b in fluids and fluids[a][0].name == fluids[b][0].name:
        f = fluids[a][0]
        if {fluids[a][1], fluids[b][1]} == {"mdot", "cp"}:
            return (f"{a} and {b} enter fluid {f.name} only through the heat-capacity rate ṁ·cp",
                    f"the product {f.name}.mdot·{f.name}.cp", True)
        return (f"{a} and {b} both set the heat flow of fluid {f.name}; the data see one combination",
                f"fluid {f.name}'s heat flow", True)
    if a in pelts and b in pelts and pelts[a][0].name == pelts[b][0].name:
        pe = pelts[a][0]
        return (f"{a} and {b} both belong to Peltier element {pe.name} and act on the sensors through its heat "
                f"flows alike; the data see one combination",
                f"the heat flow of {pe.name}", True)
    for c, r in ((a, b), (b, a)):
        if c in caps and r in links:
            node = caps[c].name
            if node in (links[r].a, links[r].b):
                if abs(cos) >= CORR_LIMIT:
                    return (f"{c} and {r} set together the time constant of node {node} (τ ≈ R·C)",
                            f"the time constant {r}·{c}", False)
    if cos >= 0.9:
        return (f"the effects of {a} and {b} on the sensors are almost proportional (cos = {cos:+.3f}): "
                f"a change of one looks like a change of the other", f"one combination of {a} and {b}", False)
    if cos <= -0.9:
        return (f"the effects of {a} and {b} on the sensors are almost opposite (cos = {cos:+.3f}): "
                f"raising both together leaves the sensors almost unchanged", f"one combination of {a} and {b}", False)
    return (f"correlated only through the other free parameters: their own effects on the sensors differ "
            f"(cos = {cos:+.3f})", f"one combination of {a} and {b}", False)


def _cov_from_fisher(F: np.ndarray,
                     struct_rtol: float = 1e-13) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eigen-decomposition of ``F`` and the covariance ``F⁻¹`` with directions below ``struct_rtol·λ_max``
    clamped there (they carry no information); returns (eigenvalues ascending, eigenvectors, cov,
    structural-null mask per parameter)."""
    lam, V = np.linalg.eigh(0.5 * (F + F.T))
    lmax = max(float(lam[-1]), 0.0) if lam.size else 0.0
    floor = struct_rtol * lmax if lmax > 0 else 1e-300
    null = lam <= floor
    lam_c = np.where(null, floor, lam)
    cov = (V / lam_c) @ V.T
    loads_null = (np.abs(V[:, null]) > 1e-6).any(axis=1) if null.any() else np.zeros(F.shape[0], bool)
    return lam, V, cov, loads_null


def _rel_std_errors(S: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Relative standard errors and estimate correlations for sensitivity columns ``S`` (M, P)."""
    F = S.T @ S / sigma**2
    lam, V, cov, loads_null = _cov_from_fisher(F)
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    se = np.where(loads_null | (np.linalg.norm(S, axis=0) == 0), math.inf, se)
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = cov / np.outer(d, d)
    np.fill_diagonal(corr, 1.0)
    return se, np.clip(corr, -1.0, 1.0)


def fisher_analysis(S: np.ndarray, names: Sequence[str], sigma: float = 0.1, *,
                    nominal: Mapping[str, float | None] | None = None,
                    net: Network | None = None, max_se: float = 0.1) -> Identifiability:
    """Identifiability from trajectory sensitivities.

    ``S`` (M, P): K per unit relative change ``α`` of each of the ``P`` parameters ``names``, one row per
    measured sensor reading (stack samples × sensors); ``sigma`` the sensor noise (K, > 0). ``nominal``
    (name → SI value) gives absolute standard errors; ``net`` the structure for plain-words explanations;
    ``max_se`` the largest relative standard error still called identifiable.
    """
    S = np.asarray(S, dtype=float)
    if S.ndim != 2 or S.shape[1] != len(names):
        raise ValueError(f"S must be (M, {len(names)}), got {S.shape}")
    if not sigma > 0:
        raise TnnError(Diagnostic(f"the noise level sigma must be positive, not {sigma}", hint="e.g. --sigma 0.1"))
    names = list(names)
    S = S[np.all(np.isfinite(S), axis=1)]
    F = S.T @ S / sigma**2
    lam, V, cov, loads_null = _cov_from_fisher(F)
    se, corr = _rel_std_errors(S, sigma)
    nominal = dict(nominal or {})
    abs_se = np.array([se[i] * abs(nominal[n]) if nominal.get(n) is not None else math.nan
                       for i, n in enumerate(names)])
    info = _structure(net)
    norms = np.linalg.norm(S, axis=0)
    # --- weak directions
    weak: list[WeakDirection] = []
    lmax = float(lam[-1]) if lam.size else 0.0
    for k in range(len(lam)):
        sek = 1.0 / math.sqrt(lam[k]) if lam[k] > 1e-13 * max(lmax, 1e-300) else math.inf
        if sek <= max_se:
            continue
        v = V[:, k] / np.max(np.abs(V[:, k]))
        big = [i for i in np.argsort(-np.abs(v)) if abs(v[i]) >= 0.05]
        weights = {names[i]: float(v[i]) for i in big}
        if len(big) > 1 and all(abs(v[i] - v[big[0]]) < 0.02 for i in big):
            desc = (f"raising {', '.join(names[i] for i in big)} together by the same percentage changes the "
                    f"sensor readings by less than the noise (only their ratios matter)")
        elif len(big) == 1:
            desc = (f"{names[big[0]]} has {'no' if norms[big[0]] == 0 else 'almost no'} effect on the sensors "
                    f"in this data")
        else:
            parts = []
            sign0 = np.sign(v[big[0]])
            for i in big[:4]:
                verb = "raising" if not parts else ("and raising" if np.sign(v[i]) == sign0 else "and lowering")
                parts.append(f"{verb} {names[i]} by {abs(v[i]):.2g} %")
            more = f" (and {len(big) - 4} smaller parts)" if len(big) > 4 else ""
            desc = " ".join(parts) + more + " changes the sensor readings by less than the noise"
        weak.append(WeakDirection(weights=weights, eigenvalue=float(lam[k]), std_error=sek, description=desc))
    # --- correlated pairs
    ident_weak = weak
    pairs: list[CorrelatedPair] = []
    P = len(names)
    for i in range(P):
        for j in range(i + 1, P):
            if abs(corr[i, j]) <= CORR_LIMIT or norms[i] == 0 or norms[j] == 0:
                continue
            cos = float(S[:, i] @ S[:, j] / (norms[i] * norms[j]))
            text, comb, structural = _explain_pair(names[i], names[j], info, cos)
            direct = structural or abs(cos) >= CORR_LIMIT
            if not direct:
                wk = max(ident_weak, key=lambda w: abs(w.weights.get(names[i], 0) * w.weights.get(names[j], 0)),
                         default=None)
                if wk is not None and wk.weights.get(names[i]) and wk.weights.get(names[j]):
                    text += f"; both move along the weak direction ({wk.description.split(' changes')[0]})"
                text += f"; each alone is determined to ±{_pct(float(se[i]))} and ±{_pct(float(se[j]))}"
            keep, drop = (i, j) if norms[i] >= norms[j] else (j, i)
            cols = [c for c in range(P) if c != drop]
            se_red, _ = _rel_std_errors(S[:, cols], sigma)
            se_keep = float(se_red[cols.index(keep)])
            # relative standard error of the combination (a sum: scaled by the share of the kept one)
            comb_se = se_keep
            if names[keep] in info["link"] and names[drop] in info["link"] and "series" in text:
                la, lb = info["link"][names[keep]], info["link"][names[drop]]
                ra, rb = _resistance_value(la, info["nominal"]), _resistance_value(lb, info["nominal"])
                if ra and rb:
                    comb_se = se_keep * ra / (ra + rb)  # d(r_a + r_b) = r_a·dα_a, relative to the sum
            pairs.append(CorrelatedPair(a=names[i], b=names[j], correlation=float(corr[i, j]), cos=cos, direct=direct,
                                        explanation=text, combination=comb,
                                        combination_std_error=comb_se if direct else math.nan))
    with np.errstate(divide="ignore"):
        alone = np.where(norms > 0, sigma / np.where(norms > 0, norms, 1.0), math.inf)
    return Identifiability(params=names, sigma=float(sigma), n_samples=int(S.shape[0]), fisher=F, std_errors=se,
                           abs_std_errors=abs_se, correlation=corr, eigenvalues=lam, eigenvectors=V, weak=weak,
                           pairs=pairs, max_se=max_se, alone_std_errors=alone)
