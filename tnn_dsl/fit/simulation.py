"""Free runs of a compiled model over experiments, and their error metrics (thesis eq. 4.7, 4.9).

Used by the trainer (validation), trained models (``predict``/``evaluate``) and the command line."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..compiler import backend_of
from ..data import Experiment, as_experiments
from .initial import InitialState, initial_states, with_values
from .ranges import (  # noqa: F401 - re-exported: the ranges' home before they moved to .ranges
    IMPLAUSIBLE_SPANS,
    IMPLAUSIBLE_SPANS_BELOW,
    START_PENALTY,
    START_SPANS_BELOW,
    plausible_range,
    start_range,
)

__all__ = ["simulate", "free_run", "free_runs", "FreeRun", "error_metrics", "as_experiments", "check_rollout",
           "plausible_range"]


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
             stored_params: Mapping[str, Mapping[str, float]] | None = None, check: bool = False) -> FreeRun:
    """Free run of ``model`` (backend ``params``) over experiment ``exp``, started by the initial-state rule
    ``init`` (``estimate``, ``filter``, ``steady``, ``measured``: :mod:`tnn_dsl.fit.initial`); ``burn_in_s``
    overrides the default burn-in; ``stored`` holds a trained model's fitted initial states of its training
    files, ``per_experiment`` the mean values of its per-experiment parameters and ``stored_params`` their
    values per training file (see :func:`~tnn_dsl.fit.initial.initial_state`). With ``check`` a run that
    leaves the physical range raises :class:`~tnn_dsl.core.TnnError` naming the node and the time
    (:func:`check_rollout`); the trainer's own runs are unchecked (it has its divergence guard)."""
    (run,) = free_runs(model, params, [exp], init, integrator=integrator, substeps=substeps, burn_in_s=burn_in_s,
                       stored=stored, per_experiment=per_experiment, stored_params=stored_params, check=check)
    return run


def free_runs(model: Any, params: Mapping[str, Any], exps: Sequence[Experiment], init: str = "estimate", *,
              integrator: str = "rk4", substeps: int | None = None, burn_in_s: float | None = None,
              stored: Mapping[str, Any] | None = None, per_experiment: Mapping[str, float] | None = None,
              stored_params: Mapping[str, Mapping[str, float]] | None = None, check: bool = False,
              errors: str = "raise") -> list[Any]:
    """:func:`free_run` of every experiment in ``exps``, in order. Each file's initial state is found on its own;
    on torch the runs of files with the same sample interval and the same number of samples from their start, and
    no per-experiment values of their own, then go as one batched rollout (``(B, N, n_inputs)``; at most
    :data:`~tnn_dsl.fit.config.FREE_RUN_BATCH_VALUES` state values a batch): torch pays its per-step overhead
    once a batch (its compiled scan's batch axis is dynamic; eager torch dispatches every operation once a step
    whatever the batch). On JAX each file runs on its own: a 2 h file's run at 1 s takes about 10 ms there
    (``benchmarks/profile_burn_in_fits.py``: ten files 0.33 s, 0.23 s of it their initial states) and a new batch
    shape compiled a program of its own, 0.33–0.37 s (``benchmarks/bench_free_runs.py``, the ten files in one call
    first and again; 2026-12-02). The runs are the single runs to round-off: each row of a batch is its own file's
    arithmetic.

    ``errors``: ``"raise"`` raises the first file's :class:`~tnn_dsl.core.TnnError` (its initial state, or with
    ``check`` its run leaving the physical range), in file order; ``"return"`` puts the error in that file's
    place and runs the others."""
    from ..core import TnnError
    from .config import FREE_RUN_BATCH_VALUES

    if errors not in ("raise", "return"):
        raise ValueError(f"errors must be 'raise' or 'return', got {errors!r}")
    ops = backend_of(model)
    out: list[Any] = [None] * len(exps)
    starts: list[tuple[int, InitialState]] = []
    # each file's initial state (torch: the burn-in fits of files alike in step and burn-in length together)
    for i, ini in enumerate(initial_states(model.network, model, params, exps, init, burn_in_s=burn_in_s,
                                           integrator=integrator, substeps=substeps, stored=stored,
                                           per_experiment=per_experiment, stored_params=stored_params)):
        if isinstance(ini, TnnError):
            out[i] = ini  # raised below when it is the first file's error (errors="raise")
        else:
            starts.append((i, ini))
    # batches: files alike in step and length from their start, sharing the model's values
    groups: dict[Any, list[tuple[int, InitialState]]] = {}
    batches = ops.name == "torch"  # JAX: a 2 h file's run takes ~10 ms, a new batch shape ~0.35 s to compile
    for i, ini in starts:
        exp = exps[i]
        key = (repr(float(exp.dt)), len(exp.t) - ini.at) if batches and not ini.params else ("alone", i)
        groups.setdefault(key, []).append((i, ini))
    n_states = len(model.state_names)
    pack = getattr(model, "pack_params", None)  # a large network: one jit argument, not one per constant
    packed = pack(params) if pack else params
    for key, members in groups.items():
        n = max(1, key[1] if key[0] != "alone" else 1)
        per_batch = max(1, FREE_RUN_BATCH_VALUES // max(1, n * n_states))
        for k in range(0, len(members), per_batch):
            chunk = members[k:k + per_batch]
            for (i, ini), (states, y) in zip(chunk, _batched_rollout(model, packed, params, exps, chunk, integrator,
                                                                    substeps, ops, pack)):
                exp = exps[i]
                if ini.at:
                    states = np.concatenate([np.full((ini.at, states.shape[1]), np.nan), states])
                    y = np.concatenate([ini.prefix_outputs, y])
                run = FreeRun(states, y, ini)
                if check:
                    try:
                        check_rollout(model, exp, states, y, start=ini.at)
                    except TnnError as err:
                        run = err
                out[i] = run
    if errors == "raise":
        for r in out:
            if isinstance(r, TnnError):
                raise r
    return out


def _batched_rollout(model, packed, params, exps, chunk, integrator, substeps, ops, pack):
    """The rollouts of ``chunk`` (``[(index, InitialState)]``, files alike in step and length from their start):
    one call with a batch axis for two or more, the single-sequence call for one (or a file with values of its
    own) → ``[(states (N, n_states), y (N, n_outputs))]`` as numpy."""
    i0, ini0 = chunk[0]
    fn = _sim_fn(model, integrator, float(exps[i0].dt), substeps)
    if len(chunk) == 1:
        if ini0.params:
            p = with_values(model, params, ini0.params)
            p = pack(p) if pack else p
        else:
            p = packed
        U = np.asarray(exps[i0].inputs, dtype=float)[ini0.at:]
        states, y = fn(p, ops.asarray(U), ops.asarray(ini0.T))
        return [(ops.numpy(states), ops.numpy(y))]
    U = np.stack([np.asarray(exps[i].inputs, dtype=float)[ini.at:] for i, ini in chunk])
    T0 = np.stack([np.asarray(ini.T, dtype=float) for _, ini in chunk])
    states, y = fn(packed, ops.asarray(U), ops.asarray(T0))
    states, y = ops.numpy(states), ops.numpy(y)
    return [(states[b], y[b]) for b in range(len(chunk))]


def check_rollout(model: Any, exp: Experiment, states: np.ndarray, y: np.ndarray, start: int = 0) -> None:
    """Raise :class:`~tnn_dsl.core.TnnError` if a free run over ``exp`` (simulated from row ``start`` on) produced
    a non-finite temperature or one outside :func:`plausible_range`: the message names the first node (or
    sensor) and the time it happened."""
    from ..core import Diagnostic, TnnError

    lo, hi = plausible_range(model, exp)
    t = np.asarray(exp.t, dtype=float)
    names = [(f"node `{n}`" if n in model.network.node_names else f"state `{n}`") for n in model.state_names]
    names += [f"sensor `{n}`" for n in model.output_names]
    X = np.concatenate([np.asarray(states, dtype=float), np.asarray(y, dtype=float)], axis=1)[start:]
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(X) | (X <= 0.0) | (X < lo) | (X > hi)
    if not bad.any():
        return
    k, j = np.unravel_index(int(np.argmax(bad.ravel())), bad.shape)
    k = int(k) + start
    X = np.concatenate([np.asarray(states, dtype=float), np.asarray(y, dtype=float)], axis=1)
    v = X[k, j]
    when = f"t = {t[k]:g} s (sample {k + 1} of {len(t)}, file {exp.path or exp.name})"
    if not np.isfinite(v):
        what = f"{names[j]} became {'NaN' if np.isnan(v) else 'infinite'} at {when}"
    elif v <= 0:
        what = f"{names[j]} fell to or below absolute zero ({v:.4g} K) at {when}"
    else:
        what = (f"{names[j]} reached {v:.4g} K at {when}, far outside the data's temperatures "
                f"(plausible: {lo:.4g} … {hi:.4g} K)")
    raise TnnError(Diagnostic(
        f"the simulation left the physical range: {what}",
        hint="a value is far from physical (a tiny capacity beside a large conductance, a huge heat source, a "
             "learned function far outside its training range) or the step is too long for the integrator: check "
             "the parameters (tnnc inspect / tnnc check), try --integrator expeuler or more --substeps"))


def simulate(model: Any, params: Mapping[str, Any], exp: Experiment, init: str = "estimate",
             integrator: str = "rk4", substeps: int | None = None, *, burn_in_s: float | None = None,
             stored: Mapping[str, Any] | None = None, check: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """:func:`free_run` as ``(states (N, n_states) K, y (N, n_out) K)``; a run that leaves the physical range
    raises unless ``check`` is false (:func:`check_rollout`)."""
    run = free_run(model, params, exp, init, integrator=integrator, substeps=substeps, burn_in_s=burn_in_s,
                   stored=stored, check=check)
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
