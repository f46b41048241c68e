"""Free runs of a compiled model over experiments, and their error metrics (thesis eq. 4.7, 4.9).

Used by the trainer (validation), trained models (``predict``/``evaluate``) and the command line."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..compiler import backend_of
from ..data import Experiment, as_experiments
from .initial import InitialState, initial_state, with_values

__all__ = ["simulate", "free_run", "FreeRun", "error_metrics", "as_experiments"]


@dataclass
class FreeRun:
    """A free run over one experiment: ``states (N, n_states)`` K and ``y (N, n_outputs)`` K (before
    ``init.at``: NaN states and, for ``filter``, the filtered outputs), and where it started (``init``: the rule,
    the burn-in excluded from scores, notes for the user)."""

    states: np.ndarray
    y: np.ndarray
    init: InitialState

    @property
    def burn_in(self) -> int:
        return self.init.burn_in


_SIM_CACHE: dict[tuple[int, str, str, Any], tuple[Any, Callable]] = {}


def _sim_fn(model, integrator: str, dt: float, substeps):
    """A (jitted for JAX) ``f(params, U (N, n_in), T0 (n_states,)) -> (states, y)``."""
    key = (id(model), integrator, repr(float(dt)), substeps)
    hit = _SIM_CACHE.get(key)
    if hit is not None and hit[0] is model:
        return hit[1]

    B = backend_of(model)

    def f(params, U, T0):
        return model.rollout(params, T0, U, dt, integrator=integrator, substeps=substeps)

    fn = B.jit(B.no_grad(f))

    if len(_SIM_CACHE) > 64:
        _SIM_CACHE.clear()
    _SIM_CACHE[key] = (model, fn)
    return fn


def free_run(model: Any, params: Mapping[str, Any], exp: Experiment, init: str = "estimate", *,
             integrator: str = "rk4", substeps: int | None = None, burn_in_s: float | None = None,
             stored: Mapping[str, Any] | None = None, per_experiment: Mapping[str, float] | None = None,
             stored_params: Mapping[str, Mapping[str, float]] | None = None) -> FreeRun:
    """Free run of ``model`` (backend ``params``) over experiment ``exp``, started by the initial-state rule
    ``init`` (``estimate``, ``filter``, ``steady``, ``measured``: :mod:`tnn_dsl.fit.initial`); ``burn_in_s``
    overrides the default burn-in; ``stored`` holds a trained model's fitted initial states of its training
    files, ``per_experiment`` the mean values of its per-experiment parameters and ``stored_params`` their
    values per training file (see :func:`~tnn_dsl.fit.initial.initial_state`)."""
    ops = backend_of(model)
    ini = initial_state(model.network, model, params, exp, init, burn_in_s=burn_in_s, integrator=integrator,
                        substeps=substeps, stored=stored, per_experiment=per_experiment, stored_params=stored_params)
    if ini.params:
        params = with_values(model, params, ini.params)
    fn = _sim_fn(model, integrator, float(exp.dt), substeps)
    U = np.asarray(exp.inputs, dtype=float)
    states, y = fn(params, ops.asarray(U[ini.at:]), ops.asarray(ini.T))
    states, y = ops.numpy(states), ops.numpy(y)
    if ini.at:
        states = np.concatenate([np.full((ini.at, states.shape[1]), np.nan), states])
        y = np.concatenate([ini.prefix_outputs, y])
    return FreeRun(states, y, ini)


def simulate(model: Any, params: Mapping[str, Any], exp: Experiment, init: str = "estimate",
             integrator: str = "rk4", substeps: int | None = None, *, burn_in_s: float | None = None,
             stored: Mapping[str, Any] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`free_run` as ``(states (N, n_states) K, y (N, n_out) K)``."""
    run = free_run(model, params, exp, init, integrator=integrator, substeps=substeps, burn_in_s=burn_in_s,
                   stored=stored)
    return run.states, run.y


def error_metrics(preds: list[dict[str, Any]], sensors: Sequence[str]) -> dict[str, Any]:
    """Errors of predictions (from ``TrainedModel.predict``) against the measurements, in K.

    Per experiment and per sensor: ``mae``, ``max_error`` (thesis eq. 4.9 per sensor), ``bias``
    (mean predicted − measured), ``rmse``, ``n`` (samples), over the samples after each prediction's ``burn_in``
    (the part its initial state was estimated on). Overall ``mae`` is the mean absolute error
    over all measured samples of all sensors (equal to eq. 4.9's MAE for one sensor)."""
    per_exp = []
    all_err: dict[str, list[np.ndarray]] = {s: [] for s in sensors}
    for p in preds:
        e = np.asarray(p["y"], dtype=float) - np.asarray(p["measured"], dtype=float)
        e = e[int(p.get("burn_in", 0)):]
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
