"""How well the data determine the extended model's values: standard errors of the final fit and what the sensors
cannot tell apart.

After the forward selection the extended model is fitted to convergence (:meth:`_Session.polish`); this module takes
that fit's Gauss–Newton information on the training rows, ``H = Jᵀ W J`` with ``J`` the forward-mode Jacobian of the
free run and ``W`` each sensor's inverse residual variance, and reads from ``H⁻¹`` (:func:`covariance_from_information`)

* every free constant's value with its standard error (SI, its own unit), the information of each sensor's
  ``N`` correlated residuals counted as that of ``N_eff`` independent ones (:func:`effective_n`, AR(1));
* for every learned target of the extension (the user's ``learn`` clauses and the doctor's): its level at the mid
  point of its inputs and its slope per unit of each input, with standard errors (the delta method through
  :func:`tnn_dsl.compiler.learned.target_value`);
* the statements a thermal engineer needs before reading those numbers: pairs of values whose estimates are
  correlated beyond ``CORR_MAX`` (these sensors determine only a combination: two resistances in series seen from
  one end), values that are not identifiable at all (a singular direction), and values whose standard error is at
  least half of the value.

The initial states of the training files are fitted with the rest (nuisance columns: they enter ``H`` but are not
reported). Free-run residuals are correlated in time; the ``N_eff/N`` weighting covers first-order autocorrelation,
and the errors stay optimistic where the residual holds structure the model cannot explain; the report says so.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..analysis.residuals import effective_n
from ..estimation.estimates import covariance_from_information, null_directions
from ..ir import POSITIVE_ROLES
from .engine import X0_PREFIX, _Engine
from .words import _d_pos1, _pos1, _unit_of

__all__ = ["CORR_MAX", "final_uncertainty"]

CORR_MAX = 0.95
"""Two estimates correlated beyond this (in absolute value) are reported as not separately identifiable."""

def _fmt(x: float) -> str:
    return f"{x:.3g}" if math.isfinite(x) else "n/a"


class _Labeller:
    """Each engine column (a free constant, a learned function's bias or weight) → the physical value it moves:
    a label, its value and ``d value / d θ`` (so ``se_value = |d value / d θ|·se_θ``), and its unit."""

    def __init__(self, eng: _Engine, fn_vars: dict[str, list]):
        self.eng, self.net, self.p = eng, eng.net, eng.params
        self.fns = {fn.name: fn for fn in self.net.learned}
        self.fn_vars = fn_vars

    def _target(self, fn, j: int) -> tuple[str, float, float, bool, str]:
        """(target name, its nominal value, y_scale, positive, unit) of output ``j`` of ``fn``."""
        t = fn.targets[j]
        if t.kind == "heat_load":
            return f"Q[{t.name}]", 0.0, self._ys(fn, j), False, "W"
        par = self.net.param(t.name)
        unit = _unit_of(self.net, par.name)
        v = self.p.get(par.name) if par.free else None
        nominal = float(np.asarray(v).reshape(-1)[0]) if v is not None and np.asarray(v).size == 1 else par.value
        positive = par.role in POSITIVE_ROLES and nominal is not None and nominal > 0
        return t.name, float(nominal or 0.0), self._ys(fn, j), positive, unit

    def _ys(self, fn, j: int) -> float:
        ys = np.asarray(self.p.get(f"{fn.name}.y_scale", np.ones(1))).reshape(-1)
        return float(ys[j] if j < ys.size else ys[0])

    def label(self, col) -> dict | None:
        key, idx = col.key, col.index
        fname, _, leaf = key.partition(".")
        fn = self.fns.get(fname)
        if fn is not None and leaf in ("b", "c", "W") and fn.kind in ("linear", "const"):
            n_out = len(fn.targets)
            j = idx % n_out if leaf == "W" else idx
            name, nominal, ys, positive, unit = self._target(fn, j)
            z0 = float(np.asarray(self.p.get(f"{fname}.b", self.p.get(f"{fname}.c", np.zeros(n_out)))).reshape(-1)[j])
            dz = nominal * _d_pos1(1.0 + z0) if positive else ys  # d value / d z at the mid point
            level = nominal * _pos1(1.0 + z0) if positive else (nominal + ys * z0)
            if leaf in ("b", "c"):
                mids = self._mids(fn)
                at = f" at {mids}" if mids else ""
                return {"name": f"{name}{at}", "value": level, "d": dz, "unit": unit}
            r = idx // n_out
            vars_ = self.fn_vars.get(fname) or [(i.kind, i.name) for i in fn.inputs]
            if r >= len(vars_):
                return None
            kind, var = vars_[r]
            scale = float(np.asarray(self.p.get(f"{fname}.x_scale", np.ones(len(vars_)))).reshape(-1)[r]) or 1.0
            w = float(np.asarray(self.p[f"{fname}.W"]).reshape(-1)[idx])
            lab = f"T({var})" if kind == "node" else var
            per = "K" if kind == "node" else self._input_unit(var)
            return {"name": f"d{name}/d{lab}", "value": dz * w / scale, "d": dz / scale,
                    "unit": f"{unit}/{per}" if per else unit}
        if key in self.p and not key.startswith(X0_PREFIX) and fn is None:
            if key not in self.net.param_names:
                return None
            v = float(np.asarray(self.p[key]).reshape(-1)[idx])
            return {"name": key + (f"[{idx}]" if idx else ""), "value": v, "d": v if col.log else 1.0,
                    "unit": _unit_of(self.net, key)}
        return None

    def _mids(self, fn) -> str:
        vars_ = self.fn_vars.get(fn.name) or [(i.kind, i.name) for i in fn.inputs]
        if not vars_:
            return ""
        mean = np.asarray(self.p.get(f"{fn.name}.x_mean", np.zeros(len(vars_)))).reshape(-1)
        parts = []
        for (kind, var), m in zip(vars_, mean):
            parts.append(f"T({var}) = {m - 273.15:.3g} °C" if kind == "node" else f"{var} = {m:.3g}")
        return ", ".join(parts)

    def _input_unit(self, name: str) -> str:
        for i in self.net.inputs:
            if i.name == name:
                return "K" if i.is_temperature else ("" if (i.unit or "1") == "1" else i.unit)
        return ""


def final_uncertainty(eng: _Engine, active: list[int], fn_vars: dict[str, list]) -> dict[str, Any]:
    """Standard errors and identifiability of the fit held by ``eng`` over its columns ``active``.

    Returns ``{"estimates": [{name, value, se, unit, rel_se, status}], "statements": [str], "method": str}``:
    values in SI; ``status`` ``ok``, ``not identifiable`` or ``poorly determined`` (relative SE ≥ 0.5);
    ``statements`` the sentences for the summary (pairs correlated beyond :data:`CORR_MAX`, the not identifiable,
    the poorly determined)."""
    method = ("Gauss–Newton information of the free run on the training rows, each sensor weighted by its residual "
              "variance and by N_eff/N, its residual's autocorrelation (AR(1)); still optimistic where the residual "
              "holds structure no parameter here explains")
    lab = _Labeller(eng, fn_vars)
    rows = [(i, lab.label(eng.cols[j])) for i, j in enumerate(active)]
    rows = [(i, r) for i, r in rows if r is not None]
    if not rows:
        return {"estimates": [], "statements": [], "method": method}
    J = eng.jacobian(active)
    res = eng.residual().ravel()[eng.train_idx]
    n_out = eng.y.shape[1]
    sensor = eng.train_idx % n_out
    w = np.zeros_like(res)
    n_eff = {}
    for s in range(n_out):
        m = sensor == s
        if m.any():
            # AR(1) inflation: N_eff of the N correlated residuals carry the information of N_eff independent ones
            n_eff[s] = (effective_n(res[m]), int(m.sum()))
            w[m] = n_eff[s][0] / n_eff[s][1] / max(float(np.mean(res[m] ** 2)), 1e-300)
    method += "; N_eff of N: " + ", ".join(f"{eng.model.output_names[s]} {a:.0f} of {b}" for s, (a, b) in n_eff.items())
    ok = np.isfinite(J).all(axis=1) & np.isfinite(res)
    H = J[ok].T @ (J[ok] * w[ok, None])
    cov, singular = covariance_from_information(H, np.zeros(len(active), dtype=bool))
    out, statements, poorly = [], [], []
    for i, r in rows:
        se = abs(r["d"]) * math.sqrt(cov[i, i]) if not singular[i] and math.isfinite(cov[i, i]) else math.nan
        rel = se / abs(r["value"]) if r["value"] and math.isfinite(se) else math.nan
        status = ("not identifiable" if singular[i] else "poorly determined" if math.isfinite(rel) and rel >= 0.5
                  else "ok")
        out.append({"name": r["name"], "value": r["value"], "se": se, "unit": r["unit"], "rel_se": rel,
                    "status": status})
        if status == "poorly determined":
            poorly.append(f"{r['name']} = {_fmt(r['value'])} ± {_fmt(se)} {r['unit']}".rstrip())
    names = {i: r["name"] for i, r in rows}
    for v in null_directions(H, np.zeros(len(active), dtype=bool)):
        moved = [names[i] for i in np.flatnonzero(np.abs(v) > 0.1) if i in names]
        if len(moved) == 1:
            statements.append(f"{moved[0]} is not identifiable from these sensors")
        elif moved:
            statements.append(f"{', '.join(moved)} are not identifiable one by one: moving them together (one "
                              "direction) leaves every sensor's reading unchanged, so only a combination is determined")
    sd = np.sqrt(np.abs(np.diag(cov)))
    for a in range(len(rows)):
        for b in range(a + 1, len(rows)):
            i, j = rows[a][0], rows[b][0]
            if singular[i] or singular[j] or not (sd[i] > 0 and sd[j] > 0):
                continue
            c = cov[i, j] / (sd[i] * sd[j])
            if math.isfinite(c) and abs(c) >= CORR_MAX:
                statements.append(f"{rows[a][1]['name']} and {rows[b][1]['name']} are correlated {c:+.3f}: these "
                                  f"sensors determine only a combination of them, not each one")
    if poorly:
        statements.append("poorly determined (standard error at least half the value): " + "; ".join(poorly))
    return {"estimates": out, "statements": statements, "method": method}
