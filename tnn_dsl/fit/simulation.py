"""Free runs of a compiled model over experiments, and their error metrics (thesis eq. 4.7, 4.9).

Used by the trainer (validation), trained models (``predict``/``evaluate``) and the command line."""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..compiler import backend_of
from ..core import Diagnostic, TnnError
from ..data import Experiment, as_experiments
from ..ir import Network

__all__ = ["simulate", "error_metrics", "as_experiments", "initial_state", "simulate_experiment"]


def _resolve_init(init: str, exp) -> str:
    if init == "auto":
        return "measured" if float(np.asarray(exp.t)[0]) > 0 else "steady"
    return init


def _measured_state(model, network: Network, params_np: dict[str, np.ndarray] | None):
    """``[(state index, output index, offset K)]``: states a measurement sets directly."""
    names = list(model.state_names)
    out = []
    seen = set()
    for j, s in enumerate(network.sensors):
        off = 0.0
        if s.offset and params_np is not None and s.offset in params_np:
            off = float(np.asarray(params_np[s.offset]).reshape(()))
        targets = [s.node] + ([f"{s.name}.lag"] if s.lag else [])
        for t in targets:
            if t in names and t not in seen:
                seen.add(t)
                out.append((names.index(t), j, off))
    return out


def _measured_init_arrays(mapping, n_states: int, y0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``mask (..., n_states) bool`` and ``values (..., n_states)`` from first measurements ``y0 (..., n_out)``."""
    y0 = np.asarray(y0, dtype=float)
    mask = np.zeros(y0.shape[:-1] + (n_states,), dtype=bool)
    vals = np.zeros(y0.shape[:-1] + (n_states,), dtype=float)
    for i, j, off in mapping:
        ok = np.isfinite(y0[..., j])
        mask[..., i] = ok
        vals[..., i] = np.where(ok, y0[..., j] - off, 0.0)
    return mask, vals


_SIM_CACHE: dict[tuple[int, str, str, Any], tuple[Any, Callable]] = {}


def _sim_fn(model, integrator: str, dt: float, substeps):
    """A (jitted for JAX) ``f(params, U (N, n_in), mask (n_states,), vals (n_states,)) -> (states, y)``."""
    key = (id(model), integrator, repr(float(dt)), substeps)
    hit = _SIM_CACHE.get(key)
    if hit is not None and hit[0] is model:
        return hit[1]

    B = backend_of(model)

    def f(params, U, mask, vals):
        T0 = model.xp.where(mask, vals, model.steady_state(params, U[0]))
        return model.rollout(params, T0, U, dt, integrator=integrator, substeps=substeps)

    fn = B.jit(B.no_grad(f))

    if len(_SIM_CACHE) > 64:
        _SIM_CACHE.clear()
    _SIM_CACHE[key] = (model, fn)
    return fn


def simulate(model: Any, params: Mapping[str, Any], exp: Experiment, init: str = "steady",
             integrator: str = "rk4", substeps: int | None = None,
             params_np: dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Free run of ``model`` over experiment ``exp`` with backend ``params``.

    ``init``: ``steady`` (steady state of the first inputs), ``measured`` (sensor nodes from the first
    measurement, the rest steady) or ``auto``. Returns ``states (N, n_states)`` K, ``y (N, n_out)`` K."""
    ops = backend_of(model)
    init = _resolve_init(init, exp)
    n_states = len(model.state_names)
    if init == "measured":
        pn = params_np if params_np is not None else model.to_numpy(params)
        mask, vals = _measured_init_arrays(_measured_state(model, model.network, pn), n_states,
                                           np.asarray(exp.outputs)[0])
    else:
        mask, vals = np.zeros(n_states, dtype=bool), np.zeros(n_states)
    fn = _sim_fn(model, integrator, float(exp.dt), substeps)
    states, y = fn(params, ops.asarray(np.asarray(exp.inputs, dtype=float)), ops.asarray(mask), ops.asarray(vals))
    return ops.numpy(states), ops.numpy(y)


def error_metrics(preds: list[dict[str, Any]], sensors: Sequence[str]) -> dict[str, Any]:
    """Errors of predictions (from ``TrainedModel.predict``) against the measurements, in K.

    Per experiment and per sensor: ``mae``, ``max_error`` (thesis eq. 4.9 per sensor), ``bias``
    (mean predicted − measured), ``rmse``, ``n`` (samples). Overall ``mae`` is the mean absolute error
    over all measured samples of all sensors (equal to eq. 4.9's MAE for one sensor)."""
    per_exp = []
    all_err: dict[str, list[np.ndarray]] = {s: [] for s in sensors}
    for p in preds:
        e = np.asarray(p["y"], dtype=float) - np.asarray(p["measured"], dtype=float)
        rec = {"name": p["name"], "n_samples": int(e.shape[0]), "sensors": {}}
        for j, s in enumerate(sensors):
            ej = e[:, j][np.isfinite(e[:, j])]
            all_err[s].append(ej)
            rec["sensors"][s] = _stats(ej)
        allv = e[np.isfinite(e)]
        rec.update({k: v for k, v in _stats(allv).items()})
        per_exp.append(rec)
    out: dict[str, Any] = {"experiments": per_exp, "sensors": {}}
    for s in sensors:
        out["sensors"][s] = _stats(np.concatenate(all_err[s]) if all_err[s] else np.zeros(0))
    allv = np.concatenate([np.concatenate(v) for v in all_err.values() if v]) if sensors else np.zeros(0)
    out.update(_stats(allv))
    return out


def _stats(e: np.ndarray) -> dict[str, float]:
    if e.size == 0:
        return {"mae": math.nan, "max_error": math.nan, "bias": math.nan, "rmse": math.nan, "n": 0}
    return {"mae": float(np.mean(np.abs(e))), "max_error": float(np.max(np.abs(e))), "bias": float(np.mean(e)),
            "rmse": float(np.sqrt(np.mean(e * e))), "n": int(e.size)}


def initial_state(net: Network, model: Any, params: Mapping[str, Any], u0: np.ndarray, y0: np.ndarray | None,
                  how: str) -> tuple[np.ndarray, list[str]]:
    """The initial state (n_states,) K and notes. ``how="steady"``: steady state of ``u0`` (n_inputs,) SI;
    ``"measured"``: that, with each sensed node (and its lag state) shifted so that the sensor reads
    ``y0`` (n_outputs,) K; nodes read by several sensors take the mean shift; NaN readings are skipped."""
    B = backend_of(model)
    ub = B.asarray(np.asarray(u0, dtype=np.float64))
    T0 = B.numpy(model.steady_state(params, ub))
    notes: list[str] = []
    if not np.all(np.isfinite(T0)):
        raise TnnError(Diagnostic("the steady state of the first inputs could not be computed (not finite)",
                                  hint="check the network's parameters; a node with no path to a boundary has no "
                                       "steady state"))
    if y0 is None:
        return T0, notes
    y_model = B.numpy(model.outputs(params, B.asarray(T0), ub))
    gap = y0 - y_model
    if how == "steady":
        worst = np.nanmax(np.abs(gap)) if np.isfinite(gap).any() else 0.0
        if worst > 1.0:
            k = int(np.nanargmax(np.abs(gap)))
            notes.append(f"note: started at the steady state of the first inputs, {model.output_names[k]} is "
                         f"{abs(gap[k]):.2f} K {'below' if gap[k] > 0 else 'above'} its first measurement; "
                         f"if the run does not start at rest use --init measured")
        return T0, notes
    idx = {n: i for i, n in enumerate(model.state_names)}
    shifts: dict[int, list[float]] = {}
    for k, s in enumerate(net.sensors):
        if not np.isfinite(gap[k]):
            continue
        for name in (s.node, f"{s.name}.lag"):
            if name in idx:
                shifts.setdefault(idx[name], []).append(float(gap[k]))
    T = T0.copy()
    for i, g in shifts.items():
        T[i] += float(np.mean(g))
    moved = sorted({model.state_names[i] for i in shifts})
    notes.append(f"note: initial state: steady state of the first inputs, with {', '.join(moved) or 'no state'} "
                 f"moved to the first measurements")
    return T, notes


def simulate_experiment(net: Network, model: Any, params: Mapping[str, Any], exp: Experiment,
                        integrator: str = "rk4", substeps: int | None = None,
                        init: str = "steady") -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Free run of one :class:`Experiment` → (states (N, n_states) K, outputs (N, n_outputs) K, notes)."""
    y0 = exp.outputs[0] if np.isfinite(exp.outputs[0]).any() else None
    T0, notes = initial_state(net, model, params, exp.inputs[0], y0, init)
    B = backend_of(model)
    states, outputs = model.rollout(params, B.asarray(T0), B.asarray(np.asarray(exp.inputs, dtype=np.float64)),
                                    float(exp.dt), integrator=integrator, substeps=substeps)
    return B.numpy(states), B.numpy(outputs), notes
