"""Naming a cause in physical units: fitted coefficients read back as laws ("R_hp1 ≈ 0.96·(1 + 0.9·(u1 − 0.48)) K/W"),
the element a candidate edits, and what is left in the residual."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ..analysis import residuals as R
from ..ir import Network
from .base import Candidate, Extended, element_value, var_label
from .engine import _Engine


def _fmt(x: float, digits: int = 3) -> str:
    if x == 0 or not math.isfinite(x):
        return "0" if x == 0 else str(x)
    return f"{x:.{digits}g}"


def _base_value(p, params) -> float | None:
    """The value a dependence law multiplies: a free parameter's fitted value (SI), else the written one."""
    v = params.get(p.name) if p.free else None
    return float(np.asarray(v).reshape(-1)[0]) if v is not None and np.asarray(v).size == 1 else p.value


def _is_poly(ext: Extended, fn: str | None) -> bool:
    return any(f.name == fn and f.kind == "poly" for f in ext.network.learned)


def _linear_coeffs(c: Candidate, params, ext: Extended):
    """For a linear learned-function candidate: (offset z0, [(var label, slope per unit, mean, scale)])
    with the raw output ``z = z0 + Σ slope·(x − mean)`` for the candidate's target (output ``j``)."""
    fn = c.fn
    vars_ = ext.fn_vars.get(fn, [])
    j = int(c.element.get("output", 0))
    n = max(len(vars_), 1)
    W = np.asarray(params.get(f"{fn}.W", np.zeros((n, j + 1))))
    if _is_poly(ext, fn) and W.size:  # the first-degree monomials' rows of a poly holding curved candidates too
        from ..compiler.learned import monomial_index

        rows = {tuple(int(a) for a in m): r for r, m in enumerate(monomial_index(len(vars_), 2))}
        W = W.reshape(len(rows), -1)[[rows[(0, i + 1)] for i in range(len(vars_))]]
    W = W.reshape(n, -1) if W.size else np.zeros((n, j + 1))
    b = np.asarray(params.get(f"{fn}.b", params.get(f"{fn}.c", np.zeros(j + 1)))).reshape(-1)
    mean = np.asarray(params.get(f"{fn}.x_mean", np.zeros(len(vars_)))).reshape(-1)
    scale = np.asarray(params.get(f"{fn}.x_scale", np.ones(len(vars_)))).reshape(-1)
    terms = []
    for i, (k, v) in enumerate(vars_):
        w = float(W[i, j])
        if w != 0.0:
            terms.append((var_label(k, v), w / scale[i], float(mean[i]), float(scale[i])))
    return (float(b[j]) if b.size > j else 0.0), terms


def _out_scale(params, c: Candidate) -> float:
    """The output scale of the candidate's own output ``j`` of its learned function (W, or the parameter's
    unit)."""
    ys = np.asarray(params.get(f"{c.fn}.y_scale", np.ones(1))).reshape(-1)
    j = int(c.element.get("output", 0))
    return float(ys[j] if j < ys.size else ys[0])


def _softplus(v: float) -> float:
    return math.log1p(math.exp(-abs(v))) + max(v, 0.0)  # no overflow


def _pos1(v: float) -> float:
    """``pos1`` of :mod:`tnn_dsl.compiler.learned` for one float: ``softplus(4v)/softplus(4)`` (a positive target is
    ``nominal·pos1(1 + z)``)."""
    return _softplus(4.0 * v) / _softplus(4.0)


def _d_pos1(v: float) -> float:
    """d pos1(v) / dv."""
    return 4.0 / (1.0 + math.exp(-4.0 * v)) / _softplus(4.0)


def _rel_slope(z0: float) -> float:
    """d ln(pos1(1 + z)) / dz at ``z0``: a positive target changes by this fraction of its value at the mid point per
    unit of ``z`` (the law's relative slope)."""
    level = _pos1(1.0 + z0)
    return _d_pos1(1.0 + z0) / level if level > 0 else 0.0


def _unit_of(net: Network, pname: str) -> str:
    try:
        p = net.param(pname)
    except KeyError:
        return ""
    # values are shown in SI: the SI unit of the role (a file's own unit, e.g. K/kW, would mislabel them)
    si = {"resistance": "K/W", "conductance": "W/K", "capacitance": "J/K", "heat_flow": "W", "time_constant": "s",
          "temperature": "K", "offset": "K"}
    if p.role in si:
        return si[p.role]
    from ..lang import format_dim

    try:
        return format_dim(p.dim) if p.dim else ""
    except Exception:  # noqa: BLE001 - display only
        return ""


def _var_unit(net: Network, label: str) -> tuple[str, float, float]:
    """(unit text, display offset, display scale) for a variable's value: temperatures shown in the
    file's unit (a centred value is the same in K and degC)."""
    if label.startswith("T("):
        return ("K", 0.0, 1.0)
    for i in net.inputs:
        if i.name == label:
            if i.is_temperature:
                return ("K", 0.0, 1.0)
            return (i.unit or "", 0.0, 1.0)
    return ("", 0.0, 1.0)


def _curved_terms(c: Candidate, params, ext: Extended) -> tuple[float, list[tuple[str, float]]]:
    """For a quadratic or product candidate (a ``poly`` function of degree 2): (offset z0, [(factor text, coefficient
    per unit of the factor)]) with ``z = z0 + Σ coefficient·factor``, the factors centred on the variables' means
    (``(I − 1.5)``, ``(I − 1.5)²``, ``(u1 − 0.5)·(T(hp) − 23 °C)``)."""
    from ..compiler.learned import monomial_index

    fn = c.fn
    vars_ = ext.fn_vars.get(fn, [])
    j = int(c.element.get("output", 0))
    mono = monomial_index(len(vars_), 2)
    W = np.asarray(params.get(f"{fn}.W", np.zeros((len(mono), j + 1)))).reshape(len(mono), -1)
    b = np.asarray(params.get(f"{fn}.b", np.zeros(j + 1))).reshape(-1)
    mean = np.asarray(params.get(f"{fn}.x_mean", np.zeros(len(vars_)))).reshape(-1)
    scale = np.asarray(params.get(f"{fn}.x_scale", np.ones(len(vars_)))).reshape(-1)

    def centred(i: int) -> str:
        lab = var_label(*vars_[i])
        m = float(mean[i]) - (273.15 if lab.startswith("T(") else 0.0)
        return f"({lab} − {_fmt(m, 3)}{' °C' if lab.startswith('T(') else ''})"

    terms = []
    for r, (a, bb) in enumerate(mono):
        w = float(W[r, j])
        if w == 0.0:
            continue
        if a == 0:
            terms.append((centred(bb - 1), w / scale[bb - 1]))
        elif a == bb:
            terms.append((f"{centred(a - 1)}²", w / scale[a - 1] ** 2))
        else:
            terms.append((f"{centred(a - 1)}·{centred(bb - 1)}", w / (scale[a - 1] * scale[bb - 1])))
    return (float(b[j]) if b.size > j else 0.0), terms


def _curved_words(c: Candidate, params, ext: Extended) -> str:
    """A dependence with a quadratic or product term read back as a law in physical units: every term of the target's
    degree-2 function (the accepted linear ones and the curved one), coefficients per unit of their factors."""
    net = ext.network
    z0, terms = _curved_terms(c, params, ext)
    y_scale = _out_scale(params, c)
    dep = ", ".join(c.depends_on)
    if c.kind in ("heat_load", "unused_column"):
        node = c.target[2:-1]
        inner = " ".join(f"{'+' if w >= 0 else '−'} {_fmt(abs(y_scale * w))}·{f}" for f, w in terms)
        return f"unmodelled heat load at {node} depending on {dep}: Q[{node}] ≈ {_fmt(y_scale * z0)} {inner} W"
    p = net.param(c.target)
    unit = _unit_of(net, c.target)
    where = _element_where(net, c.target)
    if p.role in ("resistance", "conductance", "capacitance", "time_constant") and p.value is not None:
        g = _rel_slope(z0)  # relative to the value at the mid point
        base_v = _base_value(p, params) * _pos1(1 + z0)
        inner = " ".join(f"{'+' if w >= 0 else '−'} {_fmt(abs(g * w))}·{f}" for f, w in terms)
        return f"{c.target}{where} depends on {dep}: {c.target} ≈ {_fmt(base_v)}·(1 {inner}) {unit}"
    inner = " ".join(f"{'+' if w >= 0 else '−'} {_fmt(abs(y_scale * w))}·{f}" for f, w in terms)
    return f"{c.target}{where} depends on {dep}: Δ{c.target} ≈ {_fmt(y_scale * z0)} {inner} {unit}"


def _words(c: Candidate, params, ext: Extended, eng: _Engine, model) -> str:
    net = ext.network
    if c.element.get("probe"):  # a line and its square accepted together: the square's words give the whole law
        return _words(replace(c.members[-1], depends_on=c.depends_on), params, ext, eng, model)
    if c.element.get("members"):  # a whole learned function's dependence: each target's law
        return (f"{c.target} (one learned function) depend together on {', '.join(c.depends_on)}: "
                + "; ".join(_words(m, params, ext, eng, model) for m in c.members))
    if c.element.get("shape") in ("quadratic", "product"):
        return _curved_words(c, params, ext)
    if c.kind in ("param_dependence", "wrong_constant"):
        p = net.param(c.target)
        nominal = _base_value(p, params)
        z0, terms = _linear_coeffs(c, params, ext)
        positive = p.role in ("resistance", "conductance", "capacitance", "time_constant")
        where = f" ({p.owner.split(' ', 1)[1] if p.owner and ' ' in p.owner else p.owner})" if p.owner else ""
        where = _element_where(net, c.target) or where
        unit = _unit_of(net, c.target)
        if positive and nominal is not None:
            g = _rel_slope(z0)  # relative to the value at the mid point
            rel = [(lab, g * s, m) for lab, s, m, _ in terms]
            base_v = nominal * _pos1(1 + z0)
            if not rel:
                return f"{c.target}{where} is wrong: ≈ {_fmt(base_v)} {unit} (was {_fmt(nominal)})"
            strengths = _strengths(terms, eng, c)
            dep = " and ".join(f"{lab} ({st})" for (lab, _, _), st in zip(rel, strengths))
            inner = " ".join(f"{'+' if r >= 0 else '−'} {_fmt(abs(r))}·"
                             f"({lab} − {_fmt(m if not lab.startswith('T(') else m - 273.15, 3)}"
                             f"{' °C' if lab.startswith('T(') else ''})"
                             for lab, r, m in rel)
            return (f"{c.target}{where} depends on {dep}: {c.target} ≈ {_fmt(base_v)}·(1 {inner}) {unit}")
        y_scale = _out_scale(params, c)
        off = y_scale * z0
        if not terms:
            return f"{c.target}{where} is wrong by {_fmt(off)} {unit}"
        inner = " ".join(f"{'+' if s >= 0 else '−'} {_fmt(abs(y_scale * s))}·({lab} − {_fmt(m, 3)})"
                         for lab, s, m, _ in terms)
        return (f"{c.target}{where} depends on {', '.join(t[0] for t in terms)}: "
                f"Δ{c.target} ≈ {_fmt(off)} {inner} {unit}")
    if c.kind in ("heat_load", "unused_column"):
        z0, terms = _linear_coeffs(c, params, ext)
        y_scale = _out_scale(params, c)
        node = c.target[2:-1]
        if not terms:
            return f"unmodelled constant heat load at {node}: Q ≈ {_fmt(y_scale * z0)} W"
        inner = " ".join(f"{'+' if s >= 0 else '−'} {_fmt(abs(y_scale * s))}·({lab} − {_fmt(m, 3)})"
                         for lab, s, m, _ in terms)
        what = "data column" if c.kind == "unused_column" else ""
        return (f"unmodelled heat load at {node} depending on {what + ' ' if what else ''}"
                f"{', '.join(t[0] for t in terms)}: Q[{node}] ≈ {_fmt(y_scale * z0)} {inner} W")
    if c.kind == "missing_link":
        g = element_value(params, c)
        return (f"missing conduction path {c.element['a']}–{c.element['b']}: G ≈ {_fmt(g)} W/K "
                f"(R ≈ {_fmt(1 / g) if g > 0 else '∞'} K/W)")
    if c.kind == "radiation":
        a = element_value(params, c)
        return f"missing radiation {c.element['a']}–{c.element['b']}: ε·A ≈ {_fmt(a)} m²"
    if c.kind == "sensor_offset":
        o = element_value(params, c)
        return f"sensor {c.target} reads {_fmt(o)} K {'high' if o > 0 else 'low'} (offset)"
    if c.kind == "sensor_lag":
        tau = element_value(params, c)
        return f"sensor {c.target} lags its node {c.element['node']}: first-order lag τ ≈ {_fmt(tau)} s"
    if c.kind == "thermal_mass":
        from .structural import mass_values

        el = c.element
        v = mass_values(net, c, params)
        return (f"missing thermal mass between {el['a']} and {el['b']}: a node {el['node']} of C ≈ {_fmt(v['C'])} J/K"
                f" splitting link {el['link']} ({el['a']}–{el['b']}, R ≈ {_fmt(v['R'])} K/W in total),"
                f" {100 * v['f']:.0f} % of it on the {el['a']} side;"
                f" its own time constant C·f(1−f)·R ≈ {_fmt(v['tau'])} s")
    if c.kind == "source_mass":
        from .structural import source_mass_values

        el = c.element
        v = source_mass_values(net, c, params)
        return (f"missing heat capacity behind source {el['source']}: it heats a node {el['node']} of C ≈"
                f" {_fmt(v['C'])} J/K joined to {el['at']} by R ≈ {_fmt(v['R'])} K/W (time constant C·R ≈"
                f" {_fmt(v['tau'])} s), not {el['at']} directly")
    return c.describe()


def _element_where(net: Network, pname: str) -> str:
    for l in net.links:
        if l.value == pname:
            return f" ({l.a}–{l.b})"
    for n in net.nodes:
        if n.capacitance == pname:
            return f" (capacity of {n.name})"
    return ""


def _strengths(terms, eng: _Engine, c: Candidate) -> list[str]:
    """'strongly' / 'weakly' by each term's share of the variation it causes (slope × spread)."""
    eff = [abs(s) * sc for _, s, _, sc in terms]
    top = max(eff) if eff else 0.0
    return ["strongly" if e >= 0.5 * top else "weakly" for e in eff]


def _var_text(net: Network, kind: str, name: str) -> str:
    if kind == "node":
        return f"T{name}" if name.isdigit() else name
    return name


def _what_is_left(res: R.ResidualSummary) -> str:
    parts = []
    for s, w in res.whiteness.items():
        sig = res.sigma[s]
        if w.get("white"):
            parts.append(f"{s}: white noise of σ ≈ {sig:.3g} K")
        else:
            dep = res.dependence.get(s, {})
            worst = max(dep.items(), key=lambda kv: abs(kv[1].get("corr", 0)), default=None)
            extra = (f"; largest correlation with {worst[0]} (r = {worst[1]['corr']:.2f})"
                     if worst and abs(worst[1].get("corr", 0)) > 0.2 else "")
            parts.append(f"{s}: structure it cannot explain (residual not white, Ljung–Box p = "
                         f"{w.get('ljung_box_p', 0):.2g}, MAE {res.errors[s]['mae']:.3g} K, "
                         f"noise σ ≈ {sig:.3g} K{extra})")
    if R.all_white(res.whiteness) and not all(w.get("white") for w in res.whiteness.values()):
        parts.append(f"taken together ({len(res.whiteness)} sensor(s), both whiteness tests at a family-wise 5 %) the "
                     "residuals are consistent with white noise")
    return "; ".join(parts)
