"""Standard errors of an output-error (free-run) fit: Gauss–Newton information scaled by the residual variance.

An output-error fit minimises the squared difference between the measured sensors and a free run of the
deterministic network (the trainer, :mod:`tnn_dsl.fit`). Read as maximum likelihood under independent Gaussian
errors with one variance per sensor ``σ_j²`` (estimated), the concentrated log-likelihood is::

    log L = −½ Σ_j n_j (log(2π σ̂_j²) + 1),     σ̂_j² = SSR_j / n_j

and its observed information at the optimum is, to first order (Gauss–Newton; exact when the residuals are
zero-mean and independent of the curvature of the model)::

    I(z) = Σ_j Jᵀ_j J_j / s_j²,     s_j² = SSR_j / (n_j − k·n_j/n)

with ``J_j = ∂ŷ_j/∂z`` (JAX: forward-mode automatic differentiation of the whole free run; torch: central
differences of it, see :func:`_jacobian`) and ``s_j²`` the residual
variance corrected for the ``k`` fitted entries. ``z`` holds the free constants (``log`` of positive ones, as
the likelihood fit) and each record's initial state (fitted with them; offsets in K). Learned functions' weights
and per-experiment values are held at their fitted values: the standard errors are conditional on them (said in
the notes). The covariance, delta method, t, p and the "at bound" / "not identifiable" rules are those of
:mod:`.estimates`.

**What these errors assume.** Residuals of a free run are correlated in time (a model error persists), so
``n`` overstates the information and the errors are optimistic — typically by the square root of the
residuals' correlation time in samples. The likelihood fit (``objective="ml"``, :func:`.fit_ml`) models that
correlation as process noise; its standard errors are the ones to quote. Each summary says which it is.
"""

from __future__ import annotations

import math
import time
from typing import Any, Sequence

import numpy as np

from ..compiler import backend_of
from ..core import Diagnostic, TnnError
from .estimates import Estimates, covariance_from_information, estimate_row

__all__ = ["output_error_estimates", "OE_AT_BOUND"]

OE_AT_BOUND = 1e-3
"""A parameter within this fraction of a bound (relative to the bound, in its own value) counts as at the bound:
the trainer's bounded coordinates approach a bound only asymptotically."""


def output_error_estimates(model: Any, params: Any, records: Sequence[tuple[str, Any, Any, float, Any]], *,
                           free: Sequence[str] | None = None, integrator: str = "rk4", substeps: int | None = None,
                           notes: Sequence[str] = ()) -> Estimates:
    """The standard errors of an output-error fit (module docstring) at the fitted ``params``.

    Parameters
    ----------
    model : compiled JAX or torch :class:`~tnn_dsl.Model`
    params : its fitted parameter table (numpy or backend arrays)
    records : ``(name, inputs (N, n_in) SI, outputs (N, n_out) K with NaN where missing, dt s, T0 (n_states,) K)``
        per record: the part of each file that was scored, with the initial state its free run starts from
    free : the constants to report (default: every trainable physical parameter)
    integrator, substeps : the free run's discretisation (as the fit's)
    notes : lines added to the result's notes

    Returns an :class:`~tnn_dsl.estimation.estimates.Estimates` with ``objective="output-error"``.
    """
    if model.backend not in ("jax", "torch"):
        raise TnnError(Diagnostic(f"standard errors need automatic differentiation; backend {model.backend!r} has "
                                  "none", hint="compile with backend='jax' or backend='torch'"))
    t0 = time.perf_counter()
    B = backend_of(model)
    specs = model.param_specs
    pn = model.to_numpy(params)
    if free is None:
        free = [k for k, s in specs.items() if s.kind == "physical" and s.trainable]
    free = list(free)
    logged = []
    for name in free:
        s = specs[name]
        v = float(pn[name])
        logged.append(bool((s.positive or (s.lower is not None and s.lower >= 0)) and v > 0))
    nf, ns, no = len(free), len(model.state_names), len(model.output_names)
    zp = np.array([math.log(float(pn[n])) if lg else float(pn[n]) for n, lg in zip(free, logged)], dtype=np.float64)
    base = model.from_numpy(pn)

    # per record: ∂ŷ/∂[z_params, x0 offset] (forward mode) and the residuals
    Js, Rs, masks = [], [], []
    for name, U, Y, dt, T0 in records:
        U = np.asarray(U, dtype=np.float64)
        Y = np.asarray(Y, dtype=np.float64)
        T0 = np.asarray(T0, dtype=np.float64).reshape(ns)

        def yhat(v, U=U, T0=T0, dt=float(dt)):
            p = dict(base)
            for i, (nm, lg) in enumerate(zip(free, logged)):
                p[nm] = B.xp.exp(v[i]) if lg else v[i]
            _, y = model.rollout(p, B.asarray(T0) + v[nf:], B.asarray(U), dt, integrator=integrator,
                                 substeps=substeps)
            return y

        v0 = np.concatenate([zp, np.zeros(ns)])
        y0 = B.numpy(B.no_grad(lambda: yhat(B.asarray(v0)))())
        J = _jacobian(B, yhat, v0)                   # (N, n_out, nf + ns)
        Js.append(J)
        Rs.append(Y - y0)
        masks.append(np.isfinite(Y) & np.all(np.isfinite(J), axis=-1) & np.isfinite(y0))

    n_j = np.array([sum(int(m[:, j].sum()) for m in masks) for j in range(no)])
    ssr = np.array([sum(float(np.sum(np.where(m[:, j], r[:, j], 0.0) ** 2)) for r, m in zip(Rs, masks))
                    for j in range(no)])
    n = int(n_j.sum())
    nz = nf + ns * len(records)
    k = nz + int((n_j > 0).sum())  # the constants, the initial states and one variance per sensor
    if n <= k:
        raise TnnError(Diagnostic(f"{n} readings for {k} estimates: too few for standard errors",
                                  hint="fit on a longer record"))
    with np.errstate(divide="ignore", invalid="ignore"):
        s2 = ssr / np.maximum(n_j - k * n_j / n, 1.0)   # residual variance per sensor, dof-corrected
        sig2 = ssr / np.maximum(n_j, 1)                 # its maximum-likelihood value
    if np.any((n_j > 0) & ~(s2 > 0)):
        raise TnnError(Diagnostic("a sensor's residuals are all zero: the information is unbounded",
                                  hint="standard errors need noisy measurements"))
    info = np.zeros((nz, nz))
    grad = np.zeros(nz)
    for r_i, (J, R, m) in enumerate(zip(Js, Rs, masks)):
        cols = np.r_[np.arange(nf), nf + r_i * ns + np.arange(ns)]
        for j in range(no):
            if n_j[j] == 0:
                continue
            Jj = J[:, j, :][m[:, j]]
            rj = R[:, j][m[:, j]]
            info[np.ix_(cols, cols)] += Jj.T @ Jj / s2[j]
            grad[cols] -= Jj.T @ rj / sig2[j]          # ∂(−log L)/∂z of the concentrated likelihood
    loglik = float(-0.5 * sum(nj * (math.log(2.0 * math.pi * sg) + 1.0) for nj, sg in zip(n_j, sig2) if nj > 0))

    at_bound = np.zeros(nz, dtype=bool)
    for i, name in enumerate(free):
        v = float(pn[name])
        for b in (specs[name].lower, specs[name].upper):
            if b is not None and abs(v - b) <= OE_AT_BOUND * max(abs(b), 1e-12):
                at_bound[i] = True
    cov, singular = covariance_from_information(info, at_bound)
    se_z = np.sqrt(np.where(np.diag(cov) >= 0, np.diag(cov), np.nan))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / se_z[:, None] / se_z[None, :]

    z = np.concatenate([zp] + [np.zeros(ns)] * len(records))
    labels = [f"log {n}" if lg else n for n, lg in zip(free, logged)]
    rows = []
    for i, (name, lg) in enumerate(zip(free, logged)):
        par = model.network.param(name)
        rows.append(estimate_row(name, "parameter", float(pn[name]), lg, se_z[i], grad[i], z[i], bool(at_bound[i]),
                                 bool(singular[i]), par.dim, par.unit))
    states = []
    for r_i, (rec_name, *_rest, T0) in enumerate(records):
        T0 = np.asarray(T0, dtype=np.float64).reshape(ns)
        states.append(T0.tolist())
        suffix = "" if len(records) == 1 else f" @{rec_name}"
        for s_i, s in enumerate(model.state_names):
            i = nf + r_i * ns + s_i
            labels.append(f"x0[{s}]{suffix} - x0_ref")
            rows.append(estimate_row(f"x0[{s}]{suffix}", "x0", float(T0[s_i]), False, se_z[i], grad[i], 0.0, False,
                             singular[i], {"K": 1.0}, None))
    for j, s in enumerate(model.output_names):
        if n_j[j] > 0:
            sd, se = math.sqrt(sig2[j]), math.sqrt(sig2[j] / (2.0 * n_j[j]))  # se of a normal sample's σ
            rows.append(estimate_row(f"sigma_v[{s}]", "sigma_v", sd, False, se, 0.0, sd, False, False, {"K": 1.0},
                                     None))
    out_notes = ["output error: standard errors from the Gauss–Newton information scaled by the residual variance; "
                 "a free run's residuals are correlated in time, so they are optimistic (the likelihood fit, "
                 "--objective ml, models that correlation)"] + list(notes)
    for r in rows:
        if r["status"] != "ok":
            why = ("it is at a bound of its declared range" if r["status"] == "at bound"
                   else "the fit is flat (the information singular) along a direction it loads on")
            out_notes.append(f"{r['name']}: no standard error, {why}")
    fitted = {name: float(pn[name]) for name in free}
    return Estimates(loglik=loglik, n_params=k, n_obs=n, rows=rows, labels=tuple(labels), z=z, grad=grad,
                     hessian=info, cov_z=cov, corr=corr, hessian_method="gauss-newton", backend=B.name,
                     network=model.network.name, records=tuple(r[0] for r in records), converged=True,
                     message="output-error fit (the trainer's)", nit=0, seconds=time.perf_counter() - t0,
                     notes=out_notes, objective="output-error", fitted=fitted, initial_states=states)


_FD_STEP = 1e-5
"""Central-difference step in ``z`` on torch (log-parameters: a relative change of 1e-5; initial states: 1e-5 K):
truncation ~1e-10 and round-off ~1e-9 relative in ``J`` — far below what a standard error is quoted to."""


def _jacobian(B, yhat, v0: np.ndarray) -> np.ndarray:
    """``∂ŷ/∂v (N, n_out, n_v)``: JAX forward mode (``jacfwd``, exact); torch central differences of the free run
    (:data:`_FD_STEP`): forward mode through torch's dual tensors costs ~50 free runs per direction (a 600-step
    TCLab run: 1.4 s per direction against 0.027 s per run), central differences two."""
    if B.name == "jax":
        return np.asarray(B.jacobian(yhat, v0), dtype=np.float64)
    run = B.no_grad(lambda v: B.numpy(yhat(B.asarray(v))))
    cols = []
    for i in range(len(v0)):
        e = np.zeros(len(v0))
        e[i] = _FD_STEP
        cols.append((run(v0 + e) - run(v0 - e)) / (2.0 * _FD_STEP))
    return np.stack(cols, axis=-1)
