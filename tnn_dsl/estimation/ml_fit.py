"""Maximum-likelihood grey-box identification with standard errors (CTSM-R's ``$summary`` for a ``.thn``).

:func:`fit_ml` maximises the continuous–discrete EKF likelihood (:mod:`tnn_dsl.estimation.likelihood`) over
one or more records: the sum of the records' negative log-likelihoods, the physical parameters and the noise
levels (``σ_w`` per state, ``σ_v`` per sensor) shared, each record with its own initial state. The optimiser is
scipy's L-BFGS-B on :class:`~tnn_dsl.estimation.likelihood.LikelihoodProblem`'s flat vector ``z`` (positive
parameters and σ's in log space, the declared ranges as bounds), started from the written values, ``σ_v = 0.1 K``
and ``σ_w = 1e-3 K/√s`` (LikelihoodProblem's default; 0.017 K per 5-min sample: starting from 0.01 K per sample
instead, TiTh stops in a local optimum at log L = 3841 with the solar gain at zero), then restarted once from
where it stopped (a fresh quasi-Newton memory; the better end is kept) — unless the likelihood turned non-finite in
its last line search (the filter diverged): the run then ends at the best finite point it evaluated, reported not
converged, without a restart. If a free parameter then sits at a bound
of its declared range, one more start (``release=True``): the fitted point with each such parameter moved back
to its starting value (the middle of its range where the start is at the bound), the better optimum kept — a
local optimum with a parameter pinned at a bound is the usual sign of a wrong basin (TiTh from the written values
can end at 3841 with ``Aw = 0``; moved back it reaches 3904.7). No random multi-start: log-uniform draws within
the declared ranges, or within a factor 4–10 of the written values, mostly end in worse optima or in regions where
the filter diverges (measured on TiTeTh, 2026-11-24), and none reached CTSM-R's 5437 there.

**Uncertainty.** The observed information is the Hessian of ``−log L`` at the optimum in the fitted
coordinates ``z``. By default (``hessian="auto"``, both backends) central differences of the compiled analytic
gradient at steps ``1e-4`` and ``5e-5`` combined by one Richardson step (``4n`` gradients, ``O(h⁴)``
truncation; within 1e-6 relative of the exact one in the tests; a fraction of a second, where compiling
``jax.hessian`` of the filter took 4–11 s
of a 7–22 s fit); ``hessian="exact"``: ``jax.hessian`` of the jitted likelihood (JAX); ``hessian="fd"``: plain
central differences (step ``1e-4``: ``O(h²)`` truncation and ``~1e-12/h`` round-off, ~1e-7 relative; the tests
check the three against each other on JAX). Its inverse is
the covariance of ``z``; standard errors in the parameters' own units follow by the delta method
(``se(e^z) = e^z·se(z)``), ``t = estimate/se``, two-sided normal p-values, and ``dF/dPar`` is the gradient at
the optimum (in ``z``, as CTSM prints it). A parameter within 1e-6 (relative) of a bound gets no standard error
(``status = "at bound"``; the covariance of the others is then that of the Hessian without its row and column,
the bound held), and a parameter that loads on a direction in which the Hessian is singular (an eigenvalue
``≤ 1e-9 ×`` the largest, or negative) gets ``status = "not identifiable"`` instead of a number — the project's
rule: every estimate comes with its uncertainty or the statement that it is not identifiable. So does a
parameter fitted in log space whose standard error there exceeds 5 (its 95 % interval spans more than a factor
``e^±10``; e.g. ``σ_v → 0`` on Bacher & Madsen's Ti, where CTSM-R prints an estimate ~0 with a vast error).

:class:`MLResult` holds ``loglik``, ``aic = 2k − 2 log L``, ``bic = k ln n − 2 log L`` (``n`` the readings
present), the table (:meth:`MLResult.summary`, :meth:`MLResult.to_dict`, a notebook view).
"""

from __future__ import annotations

import copy
import math
import time
from typing import Any, Callable, Sequence

import numpy as np

from ..compiler import backend_of
from ..compiler import compile as compile_network
from ..core import Diagnostic, TnnError
from .estimates import AT_BOUND, Estimates, display_factor, estimate_row
from .estimates import covariance_from_information as _covariance
from .likelihood import LikelihoodProblem

__all__ = ["fit_ml", "MLResult", "HESSIAN_METHODS", "display_factor"]

MLResult = Estimates
"""The result of :func:`fit_ml` (an :class:`~tnn_dsl.estimation.estimates.Estimates` with ``objective="ml"``)."""

HESSIAN_METHODS = ("auto", "exact", "fd")
_FD_STEP = 1e-4
_PG_TOL = 1e-2
"""L-BFGS-B's ``ABNORMAL`` end (no decrease found: −log L is flat to round-off) counts as converged when no
projected gradient component exceeds this (in −log L per unit of ``z``)."""
_SIGMA_V0 = 0.1
_SIGMA_W0 = 1e-3


# ---------------------------------------------------------------------------------------------
# The fit
# ---------------------------------------------------------------------------------------------


def _records(experiments) -> list[tuple[str, np.ndarray, np.ndarray, float]]:
    if hasattr(experiments, "inputs") or (isinstance(experiments, tuple) and len(experiments) == 3
                                          and not hasattr(experiments[0], "inputs")):
        experiments = [experiments]
    out = []
    for i, e in enumerate(experiments):
        if hasattr(e, "inputs"):
            out.append((str(getattr(e, "name", f"record {i}")), np.asarray(e.inputs, float),
                        np.asarray(e.outputs, float), float(e.dt)))
        else:
            U, Y, dt = e
            out.append((f"record {i}", np.asarray(U, float), np.asarray(Y, float), float(dt)))
    if not out:
        raise TnnError("fit_ml needs at least one record")
    return out


_JIT: dict = {}
"""Compiled ``value_and_grad`` and Hessian per (model, layout, record shapes): refits of same-shaped records
(a Monte-Carlo study, a cross-validation) trace and compile once."""


class _Joint:
    """The sum of per-record problems over one vector: shared ``[params, log σ_w, log σ_v]``, then each
    record's own ``[x0 offsets (, log p0)]``. The records' data (inputs, readings, x0 reference) are arguments
    of the compiled functions, not constants in them, so that same-shaped records share one compilation."""

    def __init__(self, problems: list[LikelihoodProblem], names: list[str]):
        self.problems = problems
        p = problems[0]
        self.B = p.B
        ns, no = len(p.model.state_names), len(p.model.output_names)
        self.n_shared = len(p.free) + p.n_learned + ns + no
        self.n_own = len(p.z0) - self.n_shared
        z = [p.z0[:self.n_shared]] + [q.z0[self.n_shared:] for q in problems]
        self.z0 = np.concatenate(z)
        labels = list(p.labels[:self.n_shared])
        for q, nm in zip(problems, names):
            suffix = "" if len(problems) == 1 else f" @{nm}"
            labels += [lab + suffix for lab in q.labels[self.n_shared:]]
        self.labels = tuple(labels)
        self.data = tuple((q.U, q.Y, q._x0_ref_b) for q in problems)
        key = (id(p.model), tuple(p.free), tuple(p.logged), tuple(p.learned), p.fit_x0, p.fit_p0,
               tuple((q.static, tuple(q.U.shape), tuple(q.Y.shape)) for q in problems))
        hit = _JIT.get(key)
        if hit is None or hit["model"] is not p.model:
            if len(_JIT) > 16:
                _JIT.clear()
            templates = [copy.copy(q) for q in problems]
            hit = {"model": p.model, "templates": templates, "vg": None, "hess": None,
                   "nll": lambda zz, data: self._total(templates, zz, data)}
            _JIT[key] = hit
        self._fns = hit

    def _total(self, templates, z, data):
        m = self.B.xp
        total = 0.0
        for r, (q, (U, Y, xr)) in enumerate(zip(templates, data)):
            a = self.n_shared + r * self.n_own
            qq = copy.copy(q)  # the record's data as (traced) arguments
            qq.U, qq.Y, qq._x0_ref_b = U, Y, xr
            total = total + qq.nll(m.concatenate([z[:self.n_shared], z[a:a + self.n_own]]))
        return total

    def nll(self, z):
        return self._fns["nll"](z, self.data)

    def value_and_grad(self, z):
        if self._fns["vg"] is None:
            self._fns["vg"] = self.B.value_and_grad(self._fns["nll"])
        return self._fns["vg"](np.asarray(z, dtype=np.float64), self.data)

    def hessian(self, z):
        """``∂²(−log L)/∂z²`` by ``jax.hessian`` (JAX only)."""
        B = self.B
        if B.name != "jax":
            raise TnnError(Diagnostic("hessian='exact' needs the JAX backend", hint="use hessian='fd' on torch"))
        if self._fns["hess"] is None:
            # one call per fit: XLA's lean options (``Backend.jit``; the one-node record of tests/test_ml_fit.py:
            # its compilation about 2.3 instead of 2.9 s, the fit's exact minus its finite-difference time, issue 18)
            self._fns["hess"] = B.jit(B.jax.hessian(self._fns["nll"]), lean=True)
        H = np.asarray(self._fns["hess"](B.xp.asarray(z), self.data), dtype=np.float64)
        return 0.5 * (H + H.T)

    def bounds(self):
        b = self.problems[0].bounds()
        return b[:self.n_shared] + [(None, None)] * (len(self.z0) - self.n_shared)


def _hessian_fd(joint: _Joint, z: np.ndarray, h: float = _FD_STEP, richardson: bool = False) -> np.ndarray:
    """Central differences of the gradient, column by column (``2n`` gradients); ``richardson``: at ``h`` and
    ``h/2`` combined as ``(4 D(h/2) − D(h))/3`` (``4n`` gradients, ``O(h⁴)`` truncation)."""
    n = len(z)

    def central(step):
        H = np.empty((n, n))
        for i in range(n):
            e = np.zeros(n)
            e[i] = step
            H[:, i] = (joint.value_and_grad(z + e)[1] - joint.value_and_grad(z - e)[1]) / (2.0 * step)
        return H

    H = (4.0 * central(0.5 * h) - central(h)) / 3.0 if richardson else central(h)
    return 0.5 * (H + H.T)


def _at_bounds(z: np.ndarray, z0: np.ndarray, bounds, zero_floor: list[bool]) -> list[int]:
    """The free parameters within 1e-8 (in ``z``) of a bound of their declared range; one fitted in log space
    with a declared lower bound of 0 (``zero_floor``; no bound in ``z``) counts as at it once it has fallen
    below 1e-6 of its starting value."""
    out = []
    for i, (lo, hi) in enumerate(bounds[:len(zero_floor)]):
        if (lo is not None and z[i] <= lo + 1e-8) or (hi is not None and z[i] >= hi - 1e-8) \
                or (zero_floor[i] and z[i] < z0[i] - math.log(1e6)):
            out.append(i)
    return out


def _projected_gradient(z, g, bounds) -> float:
    """``max |g|`` without the components that push against an active bound."""
    g = g.copy()
    for i, (lo, hi) in enumerate(bounds):
        if lo is not None and z[i] <= lo + 1e-10 and g[i] > 0:
            g[i] = 0.0
        if hi is not None and z[i] >= hi - 1e-10 and g[i] < 0:
            g[i] = 0.0
    return float(np.max(np.abs(g))) if g.size else 0.0


def fit_ml(net_or_model: Any, experiments: Any, *, backend: str = "jax", free: Sequence[str] | None = None,
           params: Any = None, x0: Any = None, integrator: str = "rk4", substeps: int | None = None,
           qd: str = "vanloan", sigma_w: Any = None, sigma_v: Any = _SIGMA_V0, fit_p0: bool = False,
           hessian: str = "auto", maxiter: int = 1000, restart: bool = True, release: bool = True) -> MLResult:
    """Maximum-likelihood estimates of a network's free parameters and noise levels, with standard errors.

    Parameters
    ----------
    net_or_model : a :class:`~tnn_dsl.ir.Network` (compiled here with ``backend``) or a compiled JAX/torch model
    experiments : one record or a list: :class:`~tnn_dsl.data.Experiment` objects (``inputs``, ``outputs``,
        ``dt``, ``name``) or ``(inputs (N, n_in), outputs (N, n_out), dt)`` tuples (SI)
    free : the parameters to estimate (default every free constant); the others are held at their values.
        A learned function's weight array named here is estimated too (no standard error per weight: the
        summary says how many weights each array holds; the constants' errors account for them)
    params : the starting values (the model's parameter table, numpy or backend arrays; e.g. an output-error
        fit's); default the values written in the network (``model.init_params()``)
    x0 : the initial state's reference per record (a list of ``(n_states,)``, or one for all); default each
        record's steady state with the sensors' nodes at their first readings; the offsets are always estimated
    sigma_w : starting σ_w, K/√s (scalar or per state); default 1e-3 K/√s
    sigma_v : starting σ_v, K (scalar or per sensor); default 0.1 K
    fit_p0 : also estimate each record's initial-state standard deviation (default: CTSM's ``P0 = Q_d``)
    hessian : ``"exact"`` (``jax.hessian``, JAX only; its compilation costs 3–10 s), ``"fd"`` (central
        differences of the gradient, step ``1e-4``), ``"auto"`` (the default: central differences at ``1e-4``
        and ``5e-5`` with one Richardson step, ``4n`` gradients, on either backend)
    restart : run L-BFGS-B a second time from where the first stopped, keep the better end (not after a run that
        stopped on a non-finite likelihood: that run's result is its best finite point, not converged)
    release : if a free parameter ends at a bound of its declared range, start once more from the fitted point
        with each such parameter moved back to its starting value (to the middle of its range where the start
        is itself at the bound), and keep the better optimum

    Returns
    -------
    :class:`MLResult`
    """
    from scipy.optimize import OptimizeResult, minimize

    if hessian not in HESSIAN_METHODS:
        raise TnnError(f"unknown hessian method {hessian!r}; use one of: {', '.join(HESSIAN_METHODS)}")
    model = net_or_model
    if not hasattr(model, "param_specs"):
        model = compile_network(net_or_model, backend)
    B = backend_of(model)
    recs = _records(experiments)
    ns, no = len(model.state_names), len(model.output_names)
    if sigma_w is None:
        sigma_w = _SIGMA_W0
    lsw = np.log(np.broadcast_to(np.asarray(sigma_w, float), (ns,)))
    lsv = np.log(np.broadcast_to(np.asarray(sigma_v, float), (no,)))
    if x0 is None or np.ndim(x0) == 1:
        x0s = [x0] * len(recs)
    else:
        x0s = list(x0)
        if len(x0s) != len(recs):
            raise TnnError(f"x0 gives {len(x0s)} initial states for {len(recs)} records")
    params = model.init_params() if params is None else model.from_numpy(model.to_numpy(params))
    problems = [LikelihoodProblem(model, params, U, Y, dt, free=free, log_sigma_w=lsw, log_sigma_v=lsv, x0=x,
                                  fit_p0=fit_p0, integrator=integrator, substeps=substeps, qd=qd)
                for (_, U, Y, dt), x in zip(recs, x0s)]
    joint = _Joint(problems, [r[0] for r in recs])
    bounds = joint.bounds()
    z0 = np.array([min(max(v, lo if lo is not None else -np.inf), hi if hi is not None else np.inf)
                   for v, (lo, hi) in zip(joint.z0, bounds)])

    t0 = time.perf_counter()
    opts = {"maxiter": maxiter, "ftol": 1e-14, "gtol": 1e-8, "maxcor": 20}

    def run(start):
        best = _BestFinite(joint.value_and_grad)
        r = minimize(best, start, jac=True, method="L-BFGS-B", bounds=bounds, options=opts)
        if not np.isfinite(r.fun):
            # the filter diverged in the last line search: the run ends at the best finite point it evaluated, not
            # converged. No restart from there: on a candidate of the doctor (BM Ti with a heat capacity behind the
            # solar gain, diverging as its new link's resistance fell) the restart crawled 1000 iterations from log L
            # 1638.3 to 1664.7 (torch: a noise level to exp(−9884)), where the other start reaches 2301.4
            if best.z is not None:
                r = OptimizeResult(x=best.z, fun=best.f, nit=r.nit, success=False,
                                   message=f"the likelihood became non-finite after {r.nit} iterations (the filter "
                                           "diverged); stopped at the best finite point evaluated")
            return r
        if restart:
            r2 = minimize(joint.value_and_grad, r.x, jac=True, method="L-BFGS-B", bounds=bounds, options=opts)
            r2.nit += r.nit
            if r2.fun <= r.fun:  # a non-finite end compares False: the first run's kept
                return r2
            r.nit = r2.nit
        return r

    res = run(z0)
    nit = int(res.nit)
    pr = problems[0]
    zero_floor = [log and model.param_specs[name].lower == 0 for name, log in zip(pr.free, pr.logged)]
    stuck = _at_bounds(np.asarray(res.x), z0, bounds, zero_floor) if release else []
    if stuck:  # one more start: the fitted point with the parameters at a bound moved back to their start values
        z1 = np.asarray(res.x, dtype=np.float64).copy()
        for i in stuck:
            lo, hi = bounds[i]
            inside = (lo is None or z0[i] > lo + 1e-8) and (hi is None or z0[i] < hi - 1e-8)
            z1[i] = z0[i] if inside else (0.5 * (lo + hi) if lo is not None and hi is not None else z1[i])
        r3 = run(z1)
        nit += int(r3.nit)
        if r3.fun < res.fun or not np.isfinite(res.fun):
            res = r3
    z = np.asarray(res.x, dtype=np.float64)
    f, g = joint.value_and_grad(z)
    method = "fd" if hessian == "auto" else hessian
    H = joint.hessian(z) if method == "exact" else _hessian_fd(joint, z, richardson=hessian == "auto")
    seconds = time.perf_counter() - t0

    # parameters at a bound (relative 1e-6 in their own value)
    p0 = problems[0]
    nf = len(p0.free)
    at_bound = np.zeros(len(z), dtype=bool)
    for i, (lo, hi) in enumerate(bounds[:nf]):
        v = math.exp(z[i]) if p0.logged[i] else z[i]
        for b in (lo, hi):
            if b is not None:
                bv = math.exp(b) if p0.logged[i] else b
                if abs(v - bv) <= AT_BOUND * max(abs(bv), 1e-300):
                    at_bound[i] = True
    cov, singular = _covariance(H, at_bound)
    se_z = np.sqrt(np.where(np.diag(cov) >= 0, np.diag(cov), np.nan))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / se_z[:, None] / se_z[None, :]

    rows = _rows(model, joint, z, g, se_z, at_bound, singular)
    notes = []
    pg = _projected_gradient(z, np.asarray(g, float), bounds)
    converged = bool(res.success) or ("ABNORMAL" in str(res.message) and pg <= _PG_TOL)
    if not res.success:
        notes.append(f"L-BFGS-B: {res.message} (largest projected gradient {pg:.2g}"
                     + (", taken as converged: the line search is at round-off)" if converged else ")"))
    for r in rows:
        if r["status"] != "ok":
            why = ("it is at a bound of its declared range" if r["status"] == "at bound"
                   else "the likelihood is flat (the Hessian singular) along a direction it loads on")
            notes.append(f"{r['name']}: no standard error, {why}")
    for name, shape in p0.learned:
        notes.append(f"{name}: {int(np.prod(shape))} weights of a learned function estimated with the rest (no "
                     "standard error per weight; the constants' standard errors account for them)")
    n_obs = int(sum(np.isfinite(Y).sum() for _, _, Y, _ in recs))
    fitted, initial_states = _fitted_values(joint, z)
    return MLResult(loglik=-float(f), n_params=len(z), n_obs=n_obs, rows=rows, labels=joint.labels, z=z,
                    grad=np.asarray(g, float), hessian=H, cov_z=cov, corr=corr, hessian_method=method,
                    backend=B.name, network=model.network.name, records=tuple(r[0] for r in recs),
                    converged=converged, message=str(res.message), nit=nit, seconds=seconds, notes=notes,
                    objective="ml", fitted=fitted, initial_states=initial_states)


class _BestFinite:
    """``value_and_grad`` passed through, keeping the point of the lowest finite value evaluated (``z``, ``f``)."""

    def __init__(self, value_and_grad: Callable[[np.ndarray], tuple[float, np.ndarray]]):
        self.value_and_grad = value_and_grad
        self.z: np.ndarray | None = None
        self.f = math.inf

    def __call__(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        f, g = self.value_and_grad(z)
        if np.isfinite(f) and f < self.f and np.all(np.isfinite(g)):
            self.z, self.f = np.array(z, dtype=np.float64), float(f)
        return f, g


def _fitted_values(joint: _Joint, z: np.ndarray) -> tuple[dict[str, Any], list[list[float]]]:
    """``({table name: SI float or nested list}, [initial state per record (K)])`` at ``z``."""
    p0 = joint.problems[0]
    fitted: dict[str, Any] = {}
    for i, (name, log) in enumerate(zip(p0.free, p0.logged)):
        fitted[name] = float(math.exp(z[i]) if log else z[i])
    i = len(p0.free)
    for name, shape in p0.learned:
        size = int(np.prod(shape))
        fitted[name] = np.asarray(z[i:i + size], dtype=np.float64).reshape(shape).tolist()
        i += size
    states = []
    for r, q in enumerate(joint.problems):
        a = joint.n_shared + r * joint.n_own
        off = z[a:a + len(q.x0_ref)] if q.fit_x0 else np.zeros(len(q.x0_ref))
        states.append((q.x0_ref + off).tolist())
    return fitted, states


def _rows(model, joint: _Joint, z, g, se_z, at_bound, singular) -> list[dict[str, Any]]:
    p0 = joint.problems[0]
    net = model.network
    nf = len(p0.free)
    rows = []
    for i, lab in enumerate(joint.labels):
        if nf <= i < nf + p0.n_learned:
            continue  # a learned function's weight: summarised per array in the notes
        log = lab.startswith("log ")
        base = lab[4:] if log else lab
        if i < nf:
            name, kind = p0.free[i], "parameter"
            par = net.param(name)
            dim, unit = par.dim, par.unit
            est = math.exp(z[i]) if log else float(z[i])
        else:
            head = base.split(" - ")[0]
            suffix = base[base.index(" @"):] if " @" in base else ""
            name = head.split(" @")[0] + suffix
            kind = name.split("[")[0]
            dim = {"K": 1.0, "s": -0.5} if kind == "sigma_w" else {"K": 1.0}
            unit = None
            if kind == "x0":
                r = (i - joint.n_shared) // joint.n_own
                k = (i - joint.n_shared) % joint.n_own
                est = float(joint.problems[r].x0_ref[k] + z[i])
            else:
                est = math.exp(z[i])
        rows.append(estimate_row(name, kind, est, log, se_z[i], g[i], z[i], bool(at_bound[i]), bool(singular[i]),
                                 dim, unit))
    return rows
