"""Sensitivity, identifiability and excitation (thesis §3.2, §4.2–4.4, §5.6.1–5.6.2; issue 5).

Five things, one module, both backends:

1. **Steady-state local sensitivity, exactly as thesis §4.3.** For a constant input vector ``u`` the steady
   state ``T*`` solves ``0 = f(T, u, θ)`` (eq. 4.1). Each candidate ``θ_i`` is scaled by ``α`` on a grid in
   ``[1 − δ, 1 + δ]`` (eq. 4.2; default ``δ = 0.2``, 5 values), the steady state is recomputed (eq. 4.3),
   the sensors read it (eq. 4.4), and the sensitivity is the slope of a least-squares line of the sensor
   output against ``α`` (eq. 4.5), per sensor (signed, K per unit ``α``) and summarised as the mean of
   ``|slope|`` over the sensors. The perturbation uses the compiled model's ``"scale:<name>"`` multipliers,
   so *any* parameter (constant, derived, learned) and any component heat flow (``pe.Q_hot``,
   ``pe.Q_cold``, ``f1.Q``) is scaled the same way. Capacities (and sensor lags) do not enter the steady
   state, so their steady sensitivity is exactly zero; they are judged by the dynamic sensitivity.
   Absolute temperatures and sensor offsets are not scanned (a multiplicative change of 295 K is not a
   meaningful perturbation; an offset of 0 cannot be scaled).

2. **The exact derivative (eq. 3.4)** at ``α = 1``: ``∂y*/∂α_i = θ_i ∂y*/∂θ_i = C (−(∂f/∂T)⁻¹ ∂f/∂α_i) +
   ∂h/∂α_i`` with the Jacobians of the model's ``rhs`` and ``outputs`` by automatic differentiation, in the
   same unit as the slope (K per unit ``α``), so the two are directly comparable; the slope equals it for a
   parameter that acts linearly and differs by the curvature over ``±δ`` otherwise.

3. **Dynamic sensitivity (eq. 3.2) along a data file**: ``S(t) = ∂y(t)/∂α`` by forward-mode automatic
   differentiation through ``model.rollout`` (JAX ``jacfwd``; PyTorch ``torch.func.jacfwd``), from the
   steady state of the first input sample (whose own sensitivity, eq. 3.4, is the initial condition
   ``S(0)``; ``init="fixed"`` uses ``S(0) = 0`` as eq. 3.2 states).

4. **Identifiability (thesis §3.2.2 and its future work on Fisher information).** With independent
   Gaussian sensor noise of standard deviation ``σ`` (K), the Fisher information of the relative parameters
   ``α`` is ``F = Σ_k S_kᵀ S_k / σ²`` over every measured sample ``k`` (NaN readings are skipped). From it:
   relative standard errors ``sqrt(diag F⁻¹)`` (``inf`` when a parameter loads on a direction with no
   information at all), the correlation matrix of the estimates, the eigen-directions of ``F`` with a
   standard error above ``max_se`` described in words ("raising R_a by 1 % and lowering R_b by 0.7 % leaves
   the sensors unchanged"), and every pair with ``|corr| > 0.95`` with a structural explanation when the
   network gives one (two resistances in series through an unmeasured node, parallel paths, ``ṁ`` and
   ``cp`` of one fluid, a capacity and its resistance). ``F`` is in relative units: multiply a relative
   standard error by the nominal value for the absolute one.

5. **Excitation (thesis §4.2, §5.6.1).** The block-Hankel matrix of the input sequence with window ``K``,
   its singular values, numerical rank, condition number ``κ = σ_max/σ_min`` (lower is better; ``inf`` when
   rank-deficient) and the entropy effective rank; see :func:`excitation` for the exact definition.

Finally a **recommendation**: a forward selection in order of sensitivity that keeps a parameter as
learnable only while the kept set stays identifiable from the data (every relative standard error below
``max_se`` and no estimate correlation above 0.95); the others stay fixed, each with the reason. Without data
the recommendation is sensitivity-only (thesis §4.4) and says so.

The public entry points are :func:`sensitivity` and :func:`excitation`; both return dataclasses with
``to_dict()`` (JSON-ready) and ``table()`` (terminal text).
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

from ..compiler import Backend, backend_of
from ..core import Diagnostic, TnnError
from ..ir import Network, Num
from .common import _as_network, _fmt, _pct
from .identifiability import (
    CORR_LIMIT,
    RESOLUTION,
    Identifiability,
    _explain_pair,
    _rel_std_errors,
    _structure,
    fisher_analysis,
)
from .report import ParameterSensitivity, Recommendation, SensitivityReport

__all__ = ["sensitivity"]


_SKIP_ROLES = {
    "temperature": "an absolute temperature: a multiplicative change of it is not a meaningful perturbation",
    "offset": "a sensor offset (additive, nominal 0): scaling it has no effect",
}

# =============================================================================================
# Sensitivity
# =============================================================================================


def _is_absolute_temperature(p) -> bool:
    """A boundary/inlet temperature, or a parameter written in degC/degF, or a kelvin value above 150 K."""
    if p.role == "temperature":
        return True
    unit = (p.unit or "").replace("°", "deg").strip()
    if unit in ("degC", "degF", "celsius", "fahrenheit"):
        return True
    return p.dim == {"K": 1.0} and p.value is not None and p.value > 150.0


def _targets(net: Network) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """The scale targets: every parameter (except absolute temperatures and offsets) and every component
    heat flow, each as ``{name, kind, group, role, owner, nominal, unit}``."""
    info = _structure(net)
    learned = net.learned_targets()
    sensor_params = {s.lag for s in net.sensors if s.lag} | {s.offset for s in net.sensors if s.offset}
    source_params = {s.value for s in net.sources}
    rad_params = {getattr(r, k) for r in net.radiations for k in ("area", "emissivity", "view_factor")}
    targets, skipped = [], {}
    for p in net.params:
        role = "temperature" if _is_absolute_temperature(p) else p.role
        if role in _SKIP_ROLES:
            skipped[p.name] = _SKIP_ROLES[role] + (" (it is in the identifiability analysis)" if p.free else "")
            continue
        if p.name in info["link"]:
            group = "link"
        elif p.name in info["cap"]:
            group = "capacity"
        elif p.name in info["peltier"]:
            group = "peltier"
        elif p.name in info["fluid"]:
            group = "fluid"
        elif p.name in source_params:
            group = "source"
        elif p.name in rad_params:
            group = "radiation"
        elif p.name in sensor_params:
            group = "sensor"
        else:
            group = "parameter"
        kind = "learned" if p.name in learned else ("constant" if isinstance(p.expr, Num) else "derived")
        note = None
        if group == "capacity":
            note = "a capacity does not enter the steady state (zero steady sensitivity); see the dynamic sensitivity"
        elif group == "sensor" and p.role == "time_constant":
            note = "a sensor lag does not enter the steady state; see the dynamic sensitivity"
        elif p.value == 0:
            note = "nominal value 0: scaling it has no effect"
        targets.append({"name": p.name, "kind": kind, "group": group, "role": p.role, "owner": p.owner,
                        "nominal": p.value, "unit": p.unit, "note": note})
    for pe in net.peltiers:
        for flow in ("Q_hot", "Q_cold"):
            targets.append({"name": f"{pe.name}.{flow}", "kind": "flow", "group": "peltier", "role": None,
                            "owner": f"peltier {pe.name}", "nominal": None, "unit": "W", "note": None})
    for f in net.fluids:
        targets.append({"name": f"{f.name}.Q", "kind": "flow", "group": "fluid", "role": None,
                        "owner": f"fluid {f.name}", "nominal": None, "unit": "W", "note": None})
    return targets, skipped


def _default_fisher_params(net: Network, targets: list[dict[str, Any]]) -> list[str]:
    """Constant parameters (plus every ``free`` one, temperatures included) with a nonzero nominal value;
    derived parameters (functions of inputs) and component flows are not parameters one estimates."""
    by = {t["name"]: t for t in targets}
    out = []
    for p in net.params:
        if not isinstance(p.expr, Num) or p.value == 0:
            continue
        if p.name in by and by[p.name]["kind"] in ("constant", "learned"):
            out.append(p.name)
        elif p.free and (p.role == "offset" or _is_absolute_temperature(p)):
            out.append(p.name)
    learned = net.learned_targets()
    for name in learned:
        if name in by and name not in out:
            out.append(name)
    return out


def _input_vector(net: Network, inputs: Mapping[str, float] | None, experiments) -> tuple[np.ndarray, list[str]]:
    names = net.input_names
    notes = []
    given = dict(inputs or {})
    unknown = [k for k in given if k not in names]
    if unknown:
        raise TnnError(Diagnostic(f"unknown input {', '.join(map(repr, unknown))}",
                                  hint=f"the network's inputs are: {', '.join(names) or '(none)'}"))
    u = np.full(len(names), np.nan)
    for i, n in enumerate(names):
        if n in given:
            u[i] = float(given[n])
    missing = [n for i, n in enumerate(names) if not np.isfinite(u[i])]
    if missing and experiments:
        allu = np.concatenate([np.asarray(e.inputs, float) for e in experiments], axis=0)
        mean = np.nanmean(allu, axis=0)
        for i, n in enumerate(names):
            if not np.isfinite(u[i]):
                u[i] = mean[i]
        notes.append(f"steady-state inputs not given ({', '.join(missing)}) are the data means")
        missing = []
    if missing:
        raise TnnError(Diagnostic(
            f"the steady state needs a constant value for every input; missing: {', '.join(missing)}",
            hint="give them as --inputs " + " ".join(f"{n}=VALUE" for n in missing) + " (or give a data file)"))
    return u, notes


def sensitivity(net: Any, data: Any = None, *, inputs: Mapping[str, float] | None = None, backend: str = "jax",
                dtype: str = "float64", params: Mapping[str, Any] | None = None, delta: float = 0.2,
                n_alpha: int = 5, targets: Sequence[str] | None = None, fisher_params: Sequence[str] | None = None,
                sigma: float = 0.1, max_se: float = 0.1, min_effect: float | None = None, min_rel: float = 0.05,
                integrator: str = "rk4", init: str = "steady", seed: int = 0) -> SensitivityReport:
    """Sensitivity, identifiability and a learnable-parameter recommendation (see the module docstring).

    ``net``: a ``Network``, a ``.thn`` path or a compiled ``Model`` (then ``backend``/``dtype`` are its own).
    ``data``: optional data path(s) or ``Experiment``(s): adds the dynamic sensitivity, the Fisher
    identifiability analysis and a data-based recommendation. ``inputs``: constant input values for the steady
    state, **SI** (kelvin for temperature inputs); inputs not given take the data mean. ``params``: parameter
    arrays (numpy or backend) overriding ``model.init_params(seed)`` (e.g. a trained model's). ``delta``: the
    α range ``[1 − δ, 1 + δ]`` with ``n_alpha`` values. ``targets``: names to scan (default: every parameter
    but absolute temperatures and offsets, and every component heat flow). ``fisher_params``: the
    parameters of the identifiability analysis (default: constants with a nonzero value, free temperatures,
    learned targets). ``sigma``: sensor noise (K). ``max_se``: the largest relative standard error still
    identifiable. ``min_effect``: the smallest sensor change (K) over ``±δ`` (steady, or RMS along the data)
    that makes a parameter sensitive (default: ``min_rel`` = 5 % of the largest such change among the
    parameters of the identifiability analysis; whether a sensitive parameter is worth learning against the
    noise is then the Fisher analysis's question). ``init``: ``"steady"`` (trajectory from the steady state of the first
    input sample, ``S(0)`` by eq. 3.4) or ``"fixed"`` (``S(0) = 0``).
    """
    _check_options(delta, n_alpha, sigma, init)
    model, network = _model_of(net, backend, dtype)
    from ..data import as_experiments

    experiments = as_experiments(network, data)
    ops = backend_of(model)
    base = dict(model.init_params(seed=seed))
    base.update(params or {})
    base = {k: (ops.asarray(v) if isinstance(v, (np.ndarray, float, int, np.floating)) else v) for k, v in base.items()}
    all_targets, skipped, fisher_names = _scan_targets(network, targets, fisher_params)
    names = [t["name"] for t in all_targets]
    scale_names = names + [n for n in fisher_names if n not in names]
    P = len(scale_names)

    def with_scales(s):
        p = dict(base)
        for i, n in enumerate(scale_names):
            p[f"scale:{n}"] = s[i]
        return p

    u_np, notes = _input_vector(network, inputs, experiments)
    u = ops.asarray(u_np)

    def steady(s):
        p = with_scales(s)
        T = model.steady_state(p, u)
        return T, model.outputs(p, T, u)

    steady_j = ops.jit(steady, fallback=True)
    ones = np.ones(P)
    T_star_b, _ = steady_j(ops.asarray(ones))
    T_star = ops.numpy(T_star_b)
    if not np.all(np.isfinite(T_star)):
        raise TnnError(Diagnostic("the steady state for these inputs is not finite",
                                  hint="check the inputs (a Peltier current too large for its heat sink?)"))
    dy_ds = _exact_derivative(model, ops, with_scales, T_star, T_star_b, u, P, notes)
    alphas = np.linspace(1 - delta, 1 + delta, n_alpha)
    results = _alpha_scan(all_targets, alphas, steady_j, ops, dy_ds, len(model.output_names))
    ident, ident_S = None, None
    if experiments:
        ident, ident_S = _along_the_data(experiments, results, model, ops, with_scales, scale_names, fisher_names,
                                         network, integrator, init, sigma, max_se, notes)
    results.sort(key=lambda r: (-r.sensitivity, -(r.dynamic_rms or 0.0), r.name))

    effects = [delta * max(r.sensitivity, r.dynamic_rms or 0.0) for r in results if r.name in fisher_names]
    if min_effect is None:
        min_effect = min_rel * max(effects, default=0.0)
        notes.append(f"sensitive = a ±{100 * delta:g} % change moves the sensors by at least {_fmt(min_effect, 3)} K "
                     f"({100 * min_rel:g} % of the largest such change)")
    min_effect = float(min_effect)
    recs = _recommend(results, fisher_names, ident, ident_S, sigma, max_se, delta, min_effect, network,
                      bool(experiments))
    return SensitivityReport(
        network=network.name, backend=model.backend, delta=float(delta), alphas=alphas,
        inputs={n: float(v) for n, v in zip(network.input_names, u_np)}, output_names=list(model.output_names),
        state_names=list(model.state_names), steady_state=dict(zip(model.state_names, map(float, T_star))),
        parameters=results, skipped=skipped, identifiability=ident, data=[str(e.name) for e in experiments],
        recommendations=recs, notes=notes, min_effect=min_effect)


def _check_options(delta: float, n_alpha: int, sigma: float, init: str) -> None:
    if not 0 < delta < 1:
        raise TnnError(Diagnostic(f"delta must be in (0, 1), not {delta}", hint="the thesis uses --delta 0.2"))
    if n_alpha < 2:
        raise TnnError(Diagnostic(f"n_alpha must be at least 2, not {n_alpha}"))
    if not sigma > 0:
        raise TnnError(Diagnostic(f"the noise level sigma must be positive, not {sigma}", hint="e.g. --sigma 0.1"))
    if init not in ("steady", "fixed"):
        raise ValueError("init must be 'steady' or 'fixed'")


def _model_of(net, backend: str, dtype: str):
    """``(compiled model, network)`` from a compiled model, a ``Network`` or a ``.thn`` path."""
    if hasattr(net, "rhs") and hasattr(net, "network"):
        model = net
        network = model.network
    else:
        from ..compiler import compile as _compile

        network = _as_network(net)
        model = _compile(network, backend=backend, dtype=dtype)
    if not network.sensors:
        raise TnnError(Diagnostic(f"network {network.name} has no sensor: there is no output to be sensitive",
                                  hint="add `sensor NAME = NODE`"))
    return model, network


def _scan_targets(network: Network, targets, fisher_params) -> tuple[list[dict], list, list[str]]:
    """The targets of the α scan (all, or the ``targets`` named), the skipped ones, and the parameters of the
    identifiability analysis."""
    all_targets, skipped = _targets(network)
    if targets is not None:
        by = {t["name"]: t for t in all_targets}
        unknown = [t for t in targets if t not in by]
        if unknown:
            raise TnnError(Diagnostic(f"cannot scan {', '.join(map(repr, unknown))}: not a parameter or component flow",
                                      hint="scannable: " + ", ".join(by)))
        all_targets = [by[t] for t in targets]
    fisher_names = list(fisher_params) if fisher_params is not None else _default_fisher_params(network, all_targets)
    pnames = set(network.param_names) | {t["name"] for t in all_targets}
    unknown = [n for n in fisher_names if n not in pnames]
    if unknown:
        raise TnnError(Diagnostic(f"unknown parameter {', '.join(map(repr, unknown))} for the identifiability analysis",
                                  hint="parameters: " + ", ".join(network.param_names)))
    return all_targets, skipped, fisher_names


def _exact_derivative(model, ops: Backend, with_scales, T_star: np.ndarray, T_star_b, u, P: int,
                      notes: list[str]) -> np.ndarray:
    """Eq. 3.4: ``dy/dα (n_out, P)`` at α = 1 by the implicit-function theorem at the steady state."""
    J_T, J_s, H_T, H_s = _local_jacobians(model, ops, with_scales, T_star, u, P)
    try:
        dT_ds = -np.linalg.solve(J_T, J_s)
    except np.linalg.LinAlgError:
        raise TnnError(Diagnostic(
            "∂f/∂T is singular at the steady state: some node has no heat path to a boundary",
            hint="connect every node to a boundary (or a fluid) through links")) from None
    residual = float(np.max(np.abs(ops.numpy(model.rhs(with_scales(ops.asarray(np.ones(P))), T_star_b, u)))))
    if residual > 1e-6:
        notes.append(f"the steady state leaves |dT/dt| up to {residual:.2g} K/s: not fully converged")
    return H_T @ dT_ds + H_s


def _alpha_scan(all_targets: list[dict], alphas: np.ndarray, steady_j, ops: Backend, dy_ds: np.ndarray,
                n_out: int) -> list[ParameterSensitivity]:
    """Eq. 4.2–4.5: each target scaled by every α with the others at 1; the slope of a line through the
    steady outputs, its linearity, and the exact derivative beside it."""
    P = dy_ds.shape[1]
    results: list[ParameterSensitivity] = []
    for i, t in enumerate(all_targets):
        ys = np.empty((len(alphas), n_out))
        for a_k, a in enumerate(alphas):
            s = np.ones(P)
            s[i] = a
            _, y = steady_j(ops.asarray(s))
            ys[a_k] = ops.numpy(y)
        note = t["note"]
        if not np.all(np.isfinite(ys)):
            note = (note + "; " if note else "") + "no finite steady state for part of the α range"
        A = np.column_stack([alphas, np.ones_like(alphas)])
        coef, *_ = np.linalg.lstsq(A, np.nan_to_num(ys), rcond=None)
        slope = coef[0]
        fit = A @ coef
        ss_res = np.sum((ys - fit) ** 2, axis=0)
        ss_tot = np.sum((ys - ys.mean(axis=0)) ** 2, axis=0)
        r2 = np.where(ss_tot > 1e-24, 1 - ss_res / np.where(ss_tot > 0, ss_tot, 1), 1.0)
        slope = np.where(np.abs(slope) < RESOLUTION, 0.0, slope)
        exact = np.where(np.abs(dy_ds[:, i]) < RESOLUTION, 0.0, dy_ds[:, i])
        results.append(ParameterSensitivity(
            name=t["name"], kind=t["kind"], group=t["group"], role=t["role"], owner=t["owner"],
            nominal=t["nominal"], unit=t["unit"], alphas=alphas, outputs=ys, slope=slope,
            sensitivity=float(np.mean(np.abs(slope))), autodiff=exact, linearity=float(np.min(r2)), note=note))
    return results


def _along_the_data(experiments, results, model, ops: Backend, with_scales, scale_names, fisher_names,
                    network: Network, integrator: str, init: str, sigma: float, max_se: float, notes: list[str]):
    """Eq. 3.2 along each experiment: every result's RMS and max dynamic sensitivity, and the Fisher
    identifiability of ``fisher_names`` from the sensitivities at the measured samples → ``(ident, S)``."""
    P = len(scale_names)
    rows: list[np.ndarray] = []
    dyn_sq = np.zeros(P)
    dyn_max = np.zeros(P)
    dyn_n = 0
    for e in experiments:
        Sx = _trajectory_sensitivity(model, ops, with_scales, scale_names, e, integrator, init)
        mask = np.isfinite(np.asarray(e.outputs, dtype=float)) if getattr(e, "outputs", None) is not None \
            else np.ones(Sx.shape[:2], bool)
        dyn_sq += np.sum(Sx**2, axis=(0, 1))
        dyn_max = np.maximum(dyn_max, np.max(np.abs(Sx), axis=(0, 1)))
        dyn_n += Sx.shape[0] * Sx.shape[1]
        rows.append(Sx[mask])
    rms = np.sqrt(dyn_sq / max(dyn_n, 1))
    for i, r in enumerate(results):
        r.dynamic_rms, r.dynamic_max = float(rms[i]), float(dyn_max[i])
    S_all = np.concatenate(rows, axis=0)
    if S_all.shape[0] == 0:
        notes.append("the data hold no sensor readings: no identifiability analysis")
        return None, None
    cols = [scale_names.index(n) for n in fisher_names]
    nominal = {p.name: p.value for p in network.params}
    ident = fisher_analysis(S_all[:, cols], fisher_names, sigma, nominal=nominal, net=network, max_se=max_se)
    return ident, S_all[:, cols]


def _local_jacobians(model, ops: Backend, with_scales, T_np: np.ndarray, u, P: int):
    """``∂f/∂T (n_s, n_s)``, ``∂f/∂α (n_s, P)``, ``∂h/∂T (n_o, n_s)``, ``∂h/∂α (n_o, P)`` at ``T``, ``u`` and
    ``α = 1`` (``f`` = ``model.rhs``, ``h`` = ``model.outputs``), by one forward-mode Jacobian."""
    n_s = T_np.shape[-1]

    def g(z):
        p = with_scales(z[n_s:])
        T = z[:n_s]
        return model.xp.concat([model.rhs(p, T, u), model.outputs(p, T, u)])

    J = ops.jacobian(g, np.concatenate([T_np, np.ones(P)]))
    return J[:n_s, :n_s], J[:n_s, n_s:], J[n_s:, :n_s], J[n_s:, n_s:]


def _trajectory_sensitivity(model, ops: Backend, with_scales, scale_names, exp, integrator: str,
                            init: str) -> np.ndarray:
    """``S`` (N, n_out, P): ``∂y(t_k)/∂α`` along one experiment (eq. 3.2 by forward-mode AD through the rollout)."""
    P = len(scale_names)
    n_s = len(model.state_names)
    u_np = np.asarray(exp.inputs, dtype=float)
    U = ops.asarray(u_np)
    u0 = ops.asarray(u_np[0])
    ones = np.ones(P)
    p1 = with_scales(ops.asarray(ones))
    T0 = model.steady_state(p1, u0)
    T0_np = ops.numpy(T0)
    if init == "steady":
        J_T, J_s, _, _ = _local_jacobians(model, ops, with_scales, T0_np, u0, P)
        dT0 = -np.linalg.solve(J_T, J_s)
    else:
        dT0 = np.zeros((n_s, P))
    dt = float(exp.dt)

    def traj(z):
        s, T = z[:P], z[P:]
        _, y = model.rollout(with_scales(s), T, U, dt, integrator=integrator)
        return y

    J = ops.jacobian(traj, np.concatenate([ones, T0_np]))  # (N, n_out, P + n_s)
    return J[..., :P] + J[..., P:] @ dT0


def _recommend(results: list[ParameterSensitivity], fisher_names: list[str], ident: Identifiability | None,
               S: np.ndarray | None, sigma: float, max_se: float, delta: float, min_effect: float,
               net: Network, have_data: bool) -> list[Recommendation]:
    """Forward selection in order of sensitivity (see the module docstring)."""
    by = {r.name: r for r in results}
    order = [r.name for r in results if r.name in fisher_names]
    order += [n for n in fisher_names if n not in order]
    recs: list[Recommendation] = []

    def effect(n: str) -> float:
        r = by.get(n)
        if r is None:
            return math.nan
        e = delta * r.sensitivity
        if r.dynamic_rms is not None:
            e = max(e, delta * r.dynamic_rms)
        return e

    info = _structure(net)
    selected: list[str] = []
    for n in order:
        e = effect(n)
        if math.isfinite(e) and (e < min_effect or e == 0):
            what = "steady or dynamic " if have_data else "steady "
            recs.append(Recommendation(n, "fix", f"insensitive: ±{100 * delta:g} % changes the {what}sensor "
                                                 f"readings by {_fmt(e, 2)} K < {_fmt(min_effect, 3)} K"))
            continue
        if ident is None or S is None:
            kind = "capacity" if by.get(n) is not None and by[n].group == "capacity" else None
            reason = (f"sensitive: ±{100 * delta:g} % moves the sensors by {_fmt(e, 3)} K"
                      if math.isfinite(e) else "not scanned")
            if kind:
                reason = "a capacity: no steady-state effect; give data to judge its dynamic effect"
            recs.append(Recommendation(n, "candidate", reason + "; give a data file to check identifiability"))
            continue
        trial = selected + [n]
        cols = [fisher_names.index(x) for x in trial]
        se, corr = _rel_std_errors(S[:, cols], sigma)
        j = len(trial) - 1
        worst = int(np.argmax(np.abs(corr[j, :j]))) if j > 0 else -1
        c = float(corr[j, worst]) if worst >= 0 else 0.0
        if np.all(se <= max_se) and abs(c) <= CORR_LIMIT:
            selected.append(n)
            head = (f"sensitive (±{100 * delta:g} % → {_fmt(e, 3)} K) and " if math.isfinite(e)
                    else "an absolute temperature (not scanned), ")
            recs.append(Recommendation(n, "learn", head + f"identifiable (±{_pct(float(se[j]))} with the others kept)"))
            continue
        if abs(c) > CORR_LIMIT:
            other = trial[worst]
            a, b = fisher_names.index(n), fisher_names.index(other)
            na, nb = np.linalg.norm(S[:, a]), np.linalg.norm(S[:, b])
            cos = float(S[:, a] @ S[:, b] / (na * nb)) if na > 0 and nb > 0 else 0.0
            text, _, _ = _explain_pair(n, other, info, cos)
            recs.append(Recommendation(n, "fix", f"confounded with {other} (corr {c:+.3f}): {text}; learn only "
                                                 f"one of them: {other} (more sensitive), or {n} instead if physical "
                                                 f"insight says {n} is the uncertain one"))
        else:
            bad = [trial[k] for k in range(len(trial)) if se[k] > max_se]
            recs.append(Recommendation(n, "fix", f"not identifiable from this data together with the kept "
                                                 f"parameters (standard error ±{_pct(float(se[j]))}"
                                                 + (f"; it would spoil {', '.join(b for b in bad if b != n)}"
                                                    if any(b != n for b in bad) else "") + ")"))
    return recs
