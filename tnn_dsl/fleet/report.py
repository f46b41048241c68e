"""The fleet report: per unit what its fit and diagnosis found, across the fleet the distribution of each fitted
parameter, the units that lie outside it, and the units grouped by finding.

Outliers: for each parameter, over the units whose fit gave it a standard error, the median and the robust
spread ``s = 1.4826·MAD``; a unit's robust z-score is ``z = (x − median)/s`` (Iglewicz & Hoaglin's modified
z-score). A unit is an outlier on a parameter when ``|z| ≥ OUTLIER_Z`` **and** its distance from the median is more
than ``OUTLIER_SE`` of its own standard errors (a poorly determined value is not called an outlier). Each outlier
gets a reading from the parameter's role in the network ("U2 is 38 % below the fleet median: less heat leaves
h2 to amb — a fouled heat sink, blocked airflow or a loose contact?").

A unit is **flagged** when the doctor accepted a finding for it or it is an outlier on some parameter.
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..core import write_text_atomic
from ..ir import Network

__all__ = ["fleet_report", "write_report", "report_text", "report_html", "OUTLIER_Z", "OUTLIER_SE", "robust_z"]

OUTLIER_Z = 3.5
"""|modified z-score| from which a unit lies outside the fleet's distribution of a parameter."""

OUTLIER_SE = 3.0
"""... and only if its distance from the fleet median exceeds this many of its own standard errors."""

MIN_UNITS = 10
"""Fewer units with a parameter than this: no distribution, no outliers (with a handful of units the MAD can be
small by chance: five healthy boards with ±10 % spread called one 20 % below the median an outlier, z = −5.5)."""

MIN_UNITS_ERROR = 5
"""Fewer units with a held-out error than this: no error outliers (healthy units' errors sit at the noise level,
so a unit the template does not describe stands out among few)."""


def robust_z(values: np.ndarray) -> tuple[float, float, np.ndarray]:
    """``(median, s, z)``: the median, ``s = 1.4826·MAD`` and the modified z-scores of ``values`` (``z`` is 0 where
    ``s`` is 0 and the value is the median, ±inf where it is not)."""
    v = np.asarray(values, dtype=float)
    med = float(np.median(v))
    s = 1.4826 * float(np.median(np.abs(v - med)))
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(s > 0, (v - med) / (s if s > 0 else 1.0), np.where(v == med, 0.0, np.sign(v - med) * np.inf))
    return med, s, z


def _roles(net: Network) -> dict[str, tuple[str, str]]:
    """``{parameter: (role, where)}``: what each parameter is in the network, in words for the readings."""
    out: dict[str, tuple[str, str]] = {}
    for nd in net.nodes:
        out[nd.capacitance] = ("capacitance", nd.name)
    for ln in net.links:
        out[ln.value] = ("resistance" if ln.form == "R" else "conductance", f"{ln.a} to {ln.b}")
    for p in net.params:
        if p.name not in out:
            out[p.name] = (p.role, p.label or p.name)
    return out


def _reading(name: str, role: str, where: str, rel: float) -> str:
    pct = f"{abs(rel) * 100:.0f} % {'below' if rel < 0 else 'above'} the fleet median"
    low = rel < 0
    if role == "resistance":
        role, low = "conductance", not low  # a higher resistance: less heat flows
    if role == "conductance":
        why = (f"less heat flows from {where} — a fouled heat sink, blocked airflow or a loose thermal contact?" if low
               else f"more heat flows from {where} — stronger airflow, missing insulation or a thermal short?")
    elif role == "capacitance":
        why = (f"less thermal mass at {where} — a missing or detached part?" if low
               else f"more thermal mass at {where} — extra material or a second body attached?")
    elif role == "temperature":
        why = "a colder place or a different installation?" if low else "a warmer place or a different installation?"
    else:
        why = "a weaker actuator, driver or supply?" if low else "a stronger actuator, driver or supply?"
    return f"{name} is {pct}: {why}"


ERROR_RATIO = 2.0
"""A unit's held-out error is an outlier when its robust z-score (of the logarithm, over the fleet) is at least
``OUTLIER_Z`` and it is more than this many times the fleet median."""


def _error_outliers(ok: list[dict[str, Any]], mode: str) -> list[dict[str, Any]]:
    """The units whose held-out MAE lies far above the fleet's (the template does not describe them)."""
    have = [(r["unit"], float(r["val_mae"])) for r in ok if r.get("val_mae") is not None and r["val_mae"] > 0]
    if len(have) < MIN_UNITS_ERROR:
        return []
    x = np.array([v for _, v in have])
    med_log, _, z = robust_z(np.log(x))
    med = float(np.exp(med_log))
    out = []
    for (unit, v), zi in zip(have, z):
        if zi >= OUTLIER_Z and v > ERROR_RATIO * med:
            out.append({"unit": unit, "parameter": "val_mae", "z": float(zi), "value": v, "median": med, "se": None,
                        "unit_si": "K",
                        "reading": f"unit {unit}: held-out MAE {v:.3g} K is {v / med:.3g}× the fleet median "
                                   f"({med:.3g} K): the network does not describe this unit"
                                   + (" (the doctor names what is missing: tnnc fleet diagnose)" if mode == "train"
                                      else "")})
    return out


def _undecided(row: dict[str, Any]) -> str | None:
    """Why a fitted unit's diagnosis is not decided (its per-unit budget ran out with nothing accepted: no
    deficiency found, but the search did not finish), else ``None``: such a unit is not a clean one."""
    d = row.get("diagnosis") or {}
    if row.get("status") != "ok" or d.get("decided") is not False:
        return None
    b = d.get("budget") or {}
    return f"diagnosis not decided: its budget ({_g(b.get('seconds'))} s) ran out {b.get('ran_out', '')}".rstrip()


def _finding_label(f: dict[str, Any]) -> str:
    kind = str(f.get("kind", "")).replace("_", " ")
    deps = [d for d in (f.get("depends_on") or []) if d]
    return f"{kind} on {f.get('target')}" + (f" depending on {', '.join(deps)}" if deps else "")


def fleet_report(rows: list[dict[str, Any]], net: Network, mode: str = "train") -> dict[str, Any]:
    """The report (``mode``: the fleet run's, ``train`` or ``diagnose``) as a JSON-able dict: ``units`` (per
    unit: ``unit``, ``status``, ``reason``, ``val_mae``,
    ``gain``, ``findings`` (accepted ones, as ``tnnc diagnose --json``), ``params``, ``flagged``, ``why``,
    ``undecided``: why its diagnosis is not decided, or ``None``; ``files``: what its directory holds beside its
    result, relative to the run's directory — ``model``, and where the doctor accepted a finding ``extended.thn`` and
    ``extended_model``),
    ``distributions`` (per parameter: ``n``, ``median``, ``s``, ``q10``, ``q90``, unit), ``outliers`` (``unit``,
    ``parameter``, ``z``, ``value``, ``median``, ``se``, ``reading``), ``groups`` (``finding`` -> units) and
    ``counts``."""
    roles = _roles(net)
    ok = [r for r in rows if r.get("status") == "ok"]
    dists: dict[str, dict[str, Any]] = {}
    outliers: list[dict[str, Any]] = []
    names = sorted({k for r in ok for k in (r.get("params") or {})})
    for pname in names:
        have = [(r["unit"], r["params"][pname]) for r in ok if pname in (r.get("params") or {})
                and r["params"][pname].get("estimate") is not None and r["params"][pname].get("status") == "ok"
                and r["params"][pname].get("se") is not None]
        if len(have) < MIN_UNITS:
            continue
        x = np.array([p["estimate"] for _, p in have], dtype=float)
        med, s, z = robust_z(x)
        first = have[0][1]
        dists[pname] = {"n": len(have), "median": med, "s": s, "q10": float(np.quantile(x, 0.1)),
                        "q90": float(np.quantile(x, 0.9)), "unit_si": first.get("unit_si"),
                        "values": {u: float(v) for (u, _), v in zip(have, x)}}
        role, where = roles.get(pname, ("generic", pname))
        for (unit, p), zi, xi in zip(have, z, x):
            if abs(zi) >= OUTLIER_Z and abs(xi - med) > OUTLIER_SE * float(p["se"]):
                rel = (xi - med) / med if med != 0 else math.copysign(math.inf, xi - med)
                outliers.append({"unit": unit, "parameter": pname, "z": float(zi), "value": float(xi),
                                 "median": med, "se": float(p["se"]), "unit_si": p.get("unit_si"),
                                 "reading": f"unit {unit}: " + _reading(pname, role, where, rel)})
    fit_outliers = _error_outliers(ok, mode)
    outliers += fit_outliers
    outliers.sort(key=lambda o: -abs(o["z"]))
    by_unit: dict[str, list[dict]] = {}
    for o in outliers:
        by_unit.setdefault(o["unit"], []).append(o)
    groups: dict[str, list[str]] = {}
    units = []
    for r in rows:
        acc = [f for f in r.get("findings") or [] if f.get("accepted")]
        for f in acc[:1]:
            groups.setdefault(_finding_label(f), []).append(r["unit"])
        why = [_finding_label(f) for f in acc] + [o["reading"].split(": ", 1)[1] for o in by_unit.get(r["unit"], [])]
        undecided = _undecided(r)
        units.append({"unit": r["unit"], "status": r.get("status"), "reason": r.get("reason") or "",
                      "val_mae": r.get("val_mae"), "train_mae": r.get("train_mae"), "gain": r.get("gain"),
                      "findings": acc, "params": r.get("params") or {},
                      "flagged": r.get("status") == "ok" and bool(why), "why": why + ([undecided] if undecided else []),
                      "undecided": undecided, "seconds": r.get("seconds"),
                      "files": [f"units/{r['unit']}/{f}" for f in r.get("files") or []]})
    counts = {"units": len(rows), "ok": len(ok), "failed": sum(r.get("status") == "failed" for r in rows),
              "error": sum(r.get("status") == "error" for r in rows), "flagged": sum(u["flagged"] for u in units),
              "undecided": sum(bool(u["undecided"]) for u in units)}
    return {"network": net.name, "mode": mode, "counts": counts, "units": units, "distributions": dists,
            "outliers": outliers, "groups": dict(sorted(groups.items(), key=lambda kv: (-len(kv[1]), kv[0])))}


def _g(x: Any, d: int = 4) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x:.{d}g}" if isinstance(x, (float, int)) and not isinstance(x, bool) else str(x)


def report_text(rep: dict[str, Any], max_units: int = 40) -> str:
    """The terminal table: counts, one line per unit (flagged ones first, at most ``max_units``), the groups of
    units by finding and the outliers with their readings."""
    c = rep["counts"]
    lines = [f"fleet of {c['units']} units on network {rep['network']}: {c['ok']} fitted, {c['failed']} failed, "
             f"{c['error']} internal errors; {c['flagged']} flagged"
             + (f"; {c['undecided']} not decided (their diagnosis budget ran out: give --budget more or none)"
                if c.get("undecided") else "")]
    units = sorted(rep["units"], key=lambda u: (not u["flagged"], u["status"] != "ok", u["unit"]))
    w = max([len(u["unit"]) for u in units] + [4])
    lines.append("")
    lines.append(f"{'unit':<{w}}  {'status':<7} {'val MAE K':>9} {'gain':>6}  why")
    for u in units[:max_units]:
        why = "; ".join(u["why"]) if u["status"] == "ok" else (u["reason"].splitlines() or [""])[0]
        lines.append(f"{u['unit']:<{w}}  {u['status']:<7} {_g(u['val_mae'], 3):>9} {_g(u['gain'], 3):>6}  {why}")
    if len(units) > max_units:
        lines.append(f"... {len(units) - max_units} more units in report.json")
    extended = [u for u in units if any(f.endswith("/extended_model") for f in u.get("files") or [])]
    if extended:
        lines.append("")
        lines.append(f"extended models (the doctor's extension at its values; `tnnc evaluate DIR FILE` runs one): "
                     f"OUT/units/UNIT/extended_model for {len(extended)} unit{'s' if len(extended) != 1 else ''}"
                     f" ({', '.join(u['unit'] for u in extended[:8])}{', ...' if len(extended) > 8 else ''})")
    if rep["groups"]:
        lines.append("")
        lines.append("units by finding:")
        for label, us in rep["groups"].items():
            shown = ", ".join(us[:8]) + (f", ... ({len(us) - 8} more)" if len(us) > 8 else "")
            lines.append(f"  {len(us)} unit{'s' if len(us) != 1 else ''}: {label} ({shown})")
    if rep["outliers"]:
        lines.append("")
        lines.append(f"outliers (|robust z| ≥ {OUTLIER_Z:g} and beyond {OUTLIER_SE:g} standard errors):")
        for o in rep["outliers"][:max_units]:
            lines.append(f"  {o['reading']} (z = {o['z']:+.1f})")
    return "\n".join(lines)


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _distribution_plot(rep: dict[str, Any]) -> str | None:
    """One strip per parameter (values relative to the fleet median), outliers in red; ``None`` without any."""
    dists = rep["distributions"]
    if not dists:
        return None
    from matplotlib.figure import Figure  # no pyplot state (the library never switches the backend)

    out = {(o["unit"], o["parameter"]) for o in rep["outliers"]}
    names = list(dists)
    fig = Figure(figsize=(8, 0.45 * len(names) + 1.2))
    ax = fig.subplots()
    rng = np.random.default_rng(0)
    for i, n in enumerate(names):
        d = dists[n]
        us = list(d["values"])
        x = np.array([d["values"][u] for u in us]) / d["median"] - 1.0 if d["median"] else np.zeros(len(us))
        y = i + rng.uniform(-0.15, 0.15, len(us))
        red = np.array([(u, n) in out for u in us])
        ax.scatter(100 * x[~red], y[~red], s=10, color="#4c72b0", alpha=0.6)
        if red.any():
            ax.scatter(100 * x[red], y[red], s=28, color="#c44e52", marker="D")
    ax.set_yticks(range(len(names)), names)
    ax.axvline(0.0, color="0.5", lw=0.8)
    ax.set_xlabel("relative to the fleet median (%)")
    ax.set_title("fitted parameters across the fleet (red: outliers)")
    fig.tight_layout()
    return _png(fig)


_MARK = "<meta name='generator' content='tnnc fleet'>"


def report_html(rep: dict[str, Any]) -> str:
    """The report as one self-contained HTML page (plots embedded, no scripts)."""
    e = html.escape
    c = rep["counts"]
    parts = ["<!DOCTYPE html><html><head><meta charset='utf-8'>", _MARK,
             f"<title>fleet report: {e(rep['network'])}</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:1em auto;padding:0 1em}"
             "table{border-collapse:collapse;font-size:90%}td,th{padding:0.2em 0.6em;border-bottom:1px solid #ddd;"
             "text-align:left;vertical-align:top}.flag{background:#fff3f0}.num{text-align:right}"
             "td:first-child{white-space:nowrap}</style>",
             "</head><body>", f"<h1>Fleet report: {e(rep['network'])}</h1>",
             f"<p>{c['units']} units: {c['ok']} fitted, {c['failed']} failed, {c['error']} internal errors; "
             f"<b>{c['flagged']} flagged</b>"
             + (f"; {c['undecided']} not decided (their diagnosis budget ran out)" if c.get("undecided") else "")
             + ".</p>"]
    uri = _distribution_plot(rep)
    if uri:
        parts.append(f"<h2>Parameters across the fleet</h2><img src='{uri}' alt='fitted parameters across the "
                     "fleet' style='max-width:100%'>")
    if rep["groups"]:
        parts.append("<h2>Units by finding</h2><ul>")
        for label, us in rep["groups"].items():
            parts.append(f"<li><b>{len(us)}</b> unit{'s' if len(us) != 1 else ''}: {e(label)} "
                         f"({e(', '.join(us))})</li>")
        parts.append("</ul>")
    if rep["outliers"]:
        parts.append("<h2>Outliers</h2><table><tr><th>unit</th><th>parameter</th><th>z</th><th>reading</th></tr>")
        for o in rep["outliers"]:
            parts.append(f"<tr><td>{e(o['unit'])}</td><td>{e(o['parameter'])}</td><td class='num'>{o['z']:+.1f}</td>"
                         f"<td>{e(o['reading'])}</td></tr>")
        parts.append("</table>")
    parts.append("<h2>Units</h2><table><tr><th>unit</th><th>status</th><th>held-out MAE (K)</th><th>gain</th>"
                 "<th>why flagged / reason</th><th>files (under the run's directory)</th></tr>")
    for u in sorted(rep["units"], key=lambda u: (not u["flagged"], u["unit"])):
        why = "; ".join(u["why"]) if u["status"] == "ok" else u["reason"]
        parts.append(f"<tr class='{'flag' if u['flagged'] else ''}'><td>{e(u['unit'])}</td><td>{e(u['status'])}</td>"
                     f"<td class='num'>{e(_g(u['val_mae'], 3))}</td><td class='num'>{e(_g(u['gain'], 3))}</td>"
                     f"<td>{e(why)}</td><td>{e(', '.join(u.get('files') or []))}</td></tr>")
    parts.append("</table></body></html>")
    return "\n".join(parts)


def write_report(rep: dict[str, Any], out: str | Path) -> None:
    """``out/report.json`` and ``out/report.html`` (each written atomically)."""
    from ..core.jsonable import to_jsonable

    out = Path(out)
    write_text_atomic(out / "report.json", json.dumps(to_jsonable(rep), indent=1))
    write_text_atomic(out / "report.html", report_html(rep))
