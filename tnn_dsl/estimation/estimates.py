"""Estimates with their uncertainty (:class:`Estimates`), shared by the maximum-likelihood fit (:mod:`.ml_fit`) and
the output-error standard errors (:mod:`.output_error`): the covariance from an information matrix in the fitted
coordinates, the delta method to the parameters' own units, t, p, and the CTSM-R-like table.

**Rules** (the project's: every estimate comes with its uncertainty or the statement that it is not identifiable).
A parameter within 1e-6 (relative) of a bound gets no standard error (``status = "at bound"``; the covariance of the
others is then that of the information matrix without its row and column). A parameter that loads on a direction
in which the information is singular (an eigenvalue ``≤ 1e-9 ×`` the largest of the unit-diagonal scaled matrix, or
negative) gets ``status = "not identifiable"``. So does a parameter fitted in log space whose standard error there
exceeds 5 (a 95 % interval wider than a factor ``e^±10``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..core.htmlview import html_table, pre, safe_repr_html, view
from ..data import unit_factor

__all__ = ["Estimates", "estimation_summary", "estimate_row", "covariance_from_information", "null_directions",
           "display_factor",
           "normal_p", "si_unit", "file_temperatures", "SINGULAR", "LOG_SE_MAX", "AT_BOUND"]

SINGULAR = 1e-9
AT_BOUND = 1e-6
LOG_SE_MAX = 5.0
"""A log-coordinate standard error above this (a 95 % interval wider than a factor ``e^±10``) is no estimate:
the likelihood is flat along the parameter (σ_v → 0 on Bacher & Madsen's Ti) — ``not identifiable``."""


# ---------------------------------------------------------------------------------------------
# Units for display (the file's unit of a parameter)
# ---------------------------------------------------------------------------------------------


def display_factor(unit: str | None) -> float | None:
    """SI per one ``unit`` (``"kWh/K"`` → 3.6e6, ``"K/kW"`` → 1e-3) by the project's unit parser
    (:func:`tnn_dsl.data.unit_factor`, pint underneath); ``None`` for an absolute temperature or a unit it does not
    know (the estimate is then shown in SI only)."""
    if unit is None:
        return None
    try:
        v = unit_factor(unit)
    except ValueError:
        return None
    return v if math.isfinite(v) and v > 0 else None


# ---------------------------------------------------------------------------------------------
# The result
# ---------------------------------------------------------------------------------------------


@dataclass
class Estimates:
    """Estimates with their uncertainty: a maximum-likelihood fit (:func:`~tnn_dsl.estimation.fit_ml`,
    ``objective="ml"``) or the standard errors of an output-error fit
    (:func:`~tnn_dsl.estimation.output_error_estimates`, ``objective="output-error"``).

    ``rows``: one dict per estimated quantity — ``name``, ``kind`` (``parameter``/``sigma_w``/``sigma_v``/``x0``/
    ``p0_std``), ``estimate`` and ``se`` (SI; σ_w in K/√s, σ_v, x0 and p0 in K), ``unit_si`` and ``display``
    (``format_quantity``), ``unit`` / ``estimate_unit`` / ``se_unit`` (the file's unit where one was written and
    understood, else ``None``), ``t``, ``p`` (two-sided, normal), ``dF`` (``∂(−log L)/∂z`` at the optimum),
    ``coordinate`` (``log`` or ``linear``), ``z``, ``se_z``, ``status`` (``ok``/``at bound``/``not identifiable``).
    ``labels``, ``z``, ``grad``, ``hessian``, ``cov_z`` and ``corr`` are in the fitted coordinates.
    """

    loglik: float
    n_params: int
    n_obs: int
    rows: list[dict[str, Any]]
    labels: tuple[str, ...]
    z: np.ndarray
    grad: np.ndarray
    hessian: np.ndarray
    cov_z: np.ndarray
    corr: np.ndarray
    hessian_method: str
    backend: str
    network: str
    records: tuple[str, ...]
    converged: bool
    message: str
    nit: int
    seconds: float
    notes: list[str] = field(default_factory=list)
    objective: str = "ml"
    """``ml`` (the EKF likelihood) or ``output-error`` (Gaussian white residuals of the free run)."""
    fitted: dict[str, Any] = field(default_factory=dict)
    """The estimated arrays by parameter-table name (SI floats; a learned array as a nested list)."""
    initial_states: list[list[float]] = field(default_factory=list)
    """Each record's estimated initial state (K, one list per record, the model's state order)."""

    @property
    def aic(self) -> float:
        return 2.0 * self.n_params - 2.0 * self.loglik

    @property
    def bic(self) -> float:
        return self.n_params * math.log(self.n_obs) - 2.0 * self.loglik

    @property
    def estimates(self) -> dict[str, float]:
        """``{name: estimate}`` (SI)."""
        return {r["name"]: r["estimate"] for r in self.rows}

    @property
    def std_errors(self) -> dict[str, float]:
        """``{name: se}`` (SI; NaN where at a bound or not identifiable)."""
        return {r["name"]: r["se"] for r in self.rows}

    def row(self, name: str) -> dict[str, Any]:
        for r in self.rows:
            if r["name"] == name:
                return r
        raise KeyError(f"no estimate {name!r}; estimates are: {', '.join(r['name'] for r in self.rows)}")

    def summary(self) -> str:
        """CTSM-R's coefficient table (Estimate, Std. Error, t value, Pr(>|t|), dF/dPar), then log L, AIC, BIC."""
        w = max(12, *(len(r["name"]) for r in self.rows))
        head = f"{'':<{w}} {'Estimate':>12} {'Std. Error':>12} {'t value':>9} {'Pr(>|t|)':>10} {'dF/dPar':>11}  unit"
        what = "maximum-likelihood fit" if self.objective == "ml" else "output-error fit"
        lines = [f"{what} of {self.network} ({self.backend}, {len(self.records)} record(s), "
                 f"{self.n_obs} readings; Hessian: {self.hessian_method})", "Coefficients:", head]
        for r in self.rows:
            if r["status"] == "ok":
                se, t, p = f"{r['se']:12.4e}", f"{r['t']:9.3f}", f"{r['p']:10.3g}"
            else:
                se, t, p = f"{r['status']:>12}", f"{'':9}", f"{'':10}"
            unit = r["unit_si"]
            extra = ""
            if r.get("unit") and r.get("estimate_unit") is not None:
                extra = f"   = {r['estimate_unit']:.5g}" + (f" ± {r['se_unit']:.3g}" if r["status"] == "ok" else "") \
                    + f" {r['unit']}"
            lines.append(f"{r['name']:<{w}} {r['estimate']:12.4e} {se} {t} {p} {r['dF']:11.3e}  {unit}{extra}")
        lines.append(f"log L = {self.loglik:.3f}   k = {self.n_params}   n = {self.n_obs}   AIC = {self.aic:.2f}   "
                     f"BIC = {self.bic:.2f}")
        if self.objective == "ml":
            lines.append(f"optimiser: {'converged' if self.converged else 'NOT converged'} ({self.message}), "
                         f"{self.nit} iterations, {self.seconds:.1f} s")
        else:
            lines.append(f"standard errors of the trainer's fit at its optimum ({self.seconds:.1f} s)")
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.summary()

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (floats and lists; NaN as ``None``)."""
        def clean(v):
            if isinstance(v, (float, np.floating)):
                return float(v) if math.isfinite(v) else None
            if isinstance(v, np.ndarray):
                return [clean(x) for x in v.tolist()] if v.ndim == 1 else [clean(np.asarray(x)) for x in v]
            if isinstance(v, (list, tuple)):
                return [clean(x) for x in v]
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            if isinstance(v, (np.integer,)):
                return int(v)
            return v
        return clean({"objective": self.objective, "network": self.network, "backend": self.backend,
                      "records": list(self.records),
                      "loglik": self.loglik, "n_params": self.n_params, "n_obs": self.n_obs, "aic": self.aic,
                      "bic": self.bic, "rows": self.rows, "labels": list(self.labels), "z": self.z,
                      "grad": self.grad, "cov_z": self.cov_z, "corr": self.corr,
                      "hessian_method": self.hessian_method, "converged": self.converged, "message": self.message,
                      "nit": self.nit, "seconds": self.seconds, "notes": list(self.notes),
                      "fitted": self.fitted, "initial_states": self.initial_states})

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Estimates":
        """The inverse of :meth:`to_dict` (as stored in ``meta.json``; ``None`` read back as NaN; the Hessian, not
        stored, is empty)."""
        def num(v: Any) -> float:
            return math.nan if v is None else float(v)

        def arr(v: Any) -> np.ndarray:
            return np.asarray([[num(x) for x in row] for row in v] if v and isinstance(v[0], list)
                              else [num(x) for x in (v or [])], dtype=np.float64)

        numeric = ("estimate", "se", "t", "p", "dF", "z", "se_z")
        rows = [{k: (num(v) if k in numeric else v) for k, v in r.items()} for r in d.get("rows") or []]
        return cls(loglik=num(d.get("loglik")), n_params=int(d.get("n_params") or 0), n_obs=int(d.get("n_obs") or 0),
                   rows=rows, labels=tuple(d.get("labels") or ()), z=arr(d.get("z")), grad=arr(d.get("grad")),
                   hessian=np.zeros((0, 0)), cov_z=arr(d.get("cov_z")), corr=arr(d.get("corr")),
                   hessian_method=str(d.get("hessian_method", "?")), backend=str(d.get("backend", "?")),
                   network=str(d.get("network", "?")), records=tuple(d.get("records") or ()),
                   converged=bool(d.get("converged", False)), message=str(d.get("message", "")),
                   nit=int(d.get("nit") or 0), seconds=num(d.get("seconds")), notes=list(d.get("notes") or []),
                   objective=str(d.get("objective", "ml")), fitted=dict(d.get("fitted") or {}),
                   initial_states=list(d.get("initial_states") or []))

    def _repr_html_(self) -> str:
        return safe_repr_html(self._html, self.summary, f"Estimates({self.network!r}, {self.objective!r})")

    def _html(self) -> str:
        rows = [[r["name"], r["display"], r["se"] if r["status"] == "ok" else r["status"],
                 r["t"] if r["status"] == "ok" else None, r["p"] if r["status"] == "ok" else None, r["dF"]]
                for r in self.rows]
        table = html_table(["parameter", "estimate", "std. error (SI)", "t value", "Pr(>|t|)", "dF/dPar"], rows,
                           numeric=[False, False, True, True, True, True])
        fit = html_table(["log L", "k", "n", "AIC", "BIC"],
                         [[self.loglik, self.n_params, self.n_obs, self.aic, self.bic]], numeric=[True] * 5, digits=7)
        what = "maximum-likelihood" if self.objective == "ml" else "output-error"
        return view(f"{what} fit: {self.network}", fit, table,
                    pre("\n".join(f"note: {n}" for n in self.notes)) if self.notes else "")


def _scaled_spectrum(H: np.ndarray, fixed: np.ndarray):
    """``(keep, d, lam, V, bad)``: the free entries of ``H``, its diagonal scale, the eigen-decomposition of ``H``
    scaled to unit diagonal (singularity independent of the coordinates) and which eigenvalues are singular."""
    keep = np.flatnonzero(~fixed)
    Hk = H[np.ix_(keep, keep)]
    d = np.sqrt(np.abs(np.diag(Hk)))
    d = np.where(d > 0, d, 1.0)
    S = Hk / d[:, None] / d[None, :]
    lam, V = np.linalg.eigh(S)
    bad = lam <= SINGULAR * max(lam.max(), 0.0) if lam.max() > 0 else np.ones_like(lam, dtype=bool)
    return keep, d, lam, V, bad


def covariance_from_information(H: np.ndarray, fixed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The covariance ``H⁻¹`` of the fitted coordinates from the information matrix ``H (n, n)`` (the Hessian of
    ``−log L``, or ``JᵀJ`` of weighted residuals) with the entries ``fixed (n,)`` held (at a bound): returns
    ``(cov (n, n) with NaN rows/columns for the fixed and the not identifiable, singular mask (n,))``."""
    n = len(H)
    cov = np.full((n, n), np.nan)
    singular = np.zeros(n, dtype=bool)
    if not (~fixed).any():
        return cov, singular
    keep, d, lam, V, bad = _scaled_spectrum(H, fixed)
    if bad.any():
        load = np.sqrt(np.sum(V[:, bad] ** 2, axis=1))
        singular[keep[load > 0.1]] = True
    good = ~bad
    Sinv = (V[:, good] / lam[good]) @ V[:, good].T
    Ck = Sinv / d[:, None] / d[None, :]
    cov[np.ix_(keep, keep)] = Ck
    cov[singular, :] = np.nan
    cov[:, singular] = np.nan
    return cov, singular


def null_directions(H: np.ndarray, fixed: np.ndarray) -> list[np.ndarray]:
    """The directions ``(n,)`` (unit length in coordinates scaled to unit information, 0 at the fixed entries) along
    which the information ``H`` is singular: moving the fitted values together along one leaves the fit unchanged
    (the entries loading more than 0.1 are those :func:`covariance_from_information` marks singular)."""
    if not (~fixed).any():
        return []
    keep, _, _, V, bad = _scaled_spectrum(H, fixed)
    out = []
    for v in V[:, bad].T:
        full = np.zeros(len(H))
        full[keep] = v
        out.append(full)
    return out


def normal_p(t: float) -> float:
    """Two-sided p-value of a standard-normal ``t``."""
    return math.erfc(abs(t) / math.sqrt(2.0)) if math.isfinite(t) else math.nan


def si_unit(dim) -> str:
    """The SI unit of a dimension as ``format_quantity`` writes it (``"1"`` for none)."""
    from ..ir.emit import format_quantity

    s = format_quantity(1.0, dim)
    return s[2:] if s.startswith("1 ") else "1"


def estimation_summary(d: dict[str, Any]) -> str:
    """The coefficient table of an :class:`Estimates` stored as a dict (``meta.json``'s ``"estimation"``)."""
    return Estimates.from_dict(d).summary()


def file_temperatures(est: Estimates, network: Any) -> Estimates:
    """``est`` with every absolute temperature (initial states, parameters of role ``temperature``) also given in
    the file's temperature unit (``network.temperature_unit``: ``degC``/``degF``/``K``) as ``estimate_unit`` /
    ``se_unit`` / ``unit`` — a standard error in °C equals the one in K, in °F it is 9/5 of it."""
    unit = getattr(network, "temperature_unit", "K")
    roles = {p.name: p.role for p in getattr(network, "params", [])}
    for r in est.rows:
        if not (r["kind"] == "x0" or (r["kind"] == "parameter" and roles.get(r["name"]) == "temperature")):
            continue
        v, se = r["estimate"], r["se"]
        if unit == "degC":
            r["estimate_unit"], r["se_unit"] = v - 273.15, se
        elif unit == "degF":
            r["estimate_unit"], r["se_unit"] = (v - 273.15) * 9.0 / 5.0 + 32.0, se * 9.0 / 5.0
        else:
            r["estimate_unit"], r["se_unit"] = v, se
        r["unit"] = unit
    return est


def estimate_row(name: str, kind: str, estimate: float, log: bool, se_z: float, dF: float, z: float,
                 at_bound: bool, singular: bool, dim: dict[str, float], unit: str | None) -> dict[str, Any]:
    """One row of the coefficient table (:class:`Estimates`): the rules of this module applied to an estimate
    (SI) fitted in coordinate ``z`` (``log`` or linear) with standard error ``se_z`` there; ``unit`` the file's
    unit of a parameter (shown beside SI where :func:`display_factor` knows it); σ_w rows (``kind="sigma_w"``) in
    K/√s."""
    from ..ir.emit import format_quantity

    status = "at bound" if at_bound else ("not identifiable" if singular else "ok")
    sz = float(se_z) if status == "ok" else math.nan
    se = abs(estimate) * sz if log else sz
    t = estimate / se if status == "ok" and se > 0 else math.nan
    if log and status == "ok" and sz > LOG_SE_MAX:
        status, sz, se, t = "not identifiable", math.nan, math.nan, math.nan
    fac = display_factor(unit) if unit else None
    sigma_w = kind == "sigma_w"
    return {"name": name, "kind": kind, "estimate": estimate, "se": se,
            "unit_si": "K/√s" if sigma_w else si_unit(dim),
            "display": f"{estimate:.6g} K/√s" if sigma_w else format_quantity(estimate, dim),
            "unit": unit if fac else None, "estimate_unit": estimate / fac if fac else None,
            "se_unit": se / fac if fac else None, "t": t, "p": normal_p(t), "dF": float(dF),
            "coordinate": "log" if log else "linear", "z": float(z), "se_z": sz, "status": status}
